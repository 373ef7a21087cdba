"""``python -m datagen.generate``: same arguments, same bytes; resume after a kill; bad meshes
skipped and counted; shards independent of the split; held-out meshes; the shared BOP meshes.

References: byte comparison of whole output trees against an uninterrupted run (no reference
values are stored), hashes recomputed here for the mesh split.
"""

import hashlib
import json
import pathlib
import subprocess
import sys
import warnings

import numpy as np
import pytest
import trimesh

from datagen import generate
from datagen import scene as S
from datagen.meshes import MeshSkippedWarning
from threept_jax.data.bop import BopDataset

ARGS = ["--meshes", "procedural:6", "--procedural-max-faces", "1000", "--resolution", "64",
        "48", "--spp", "2", "--instances", "5", "--image-format", "png", "--quiet",
        "--seed", "3", "--num-scenes", "3"]


def _tree(root: pathlib.Path) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes()
            for p in sorted(root.rglob("*")) if p.is_file()}


def _refused(capsys, argv) -> str:
    """``generate.main(argv)`` exits with status 2 and ``error: ...``; returns stderr."""
    with pytest.raises(SystemExit) as e:
        generate.main(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.startswith("error: "), (e.value.code, err)
    return err


def _assert_same_tree(a, b):
    ta, tb = _tree(a), _tree(b)
    assert sorted(ta) == sorted(tb)
    diff = [k for k in ta if ta[k] != tb[k]]
    assert not diff, diff


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    out = tmp_path_factory.mktemp("reference")
    generate.main(ARGS + ["--out", str(out)])
    return out


def test_output_layout_and_manifest(reference):
    assert sorted(p.name for p in (reference / "train_pbr").iterdir()) == [
        generate.LOCK_FILE, "000000", "000001", "000002", "manifest.json"]
    assert (reference / "train_pbr" / generate.LOCK_FILE).read_bytes() == b""  # released
    m = json.loads((reference / "train_pbr" / "manifest.json").read_text())
    assert m["status"] == "complete" and m["num_images"] == 3 and m["skipped_meshes"] == 0
    assert (m["seed"], m["shard"], m["num_shards"], m["split"]) == (3, 0, 1, "train")
    assert m["config"]["resolution"] == [64, 48] and m["config"]["spp"] == 2
    models = sorted(p.name for p in (reference / "models").glob("obj_*.ply"))
    info = json.loads((reference / "models" / "models_info.json").read_text())
    assert [f"obj_{int(k):06d}.ply" for k in sorted(info, key=int)] == models
    assert {int(k) for k in m["objects"]} <= {int(k) for k in info}


def _killed_after_images(monkeypatch, n: int, argv) -> None:
    """``generate.main(argv)`` killed (KeyboardInterrupt) right after writing its n-th image."""
    real = S.BopSceneWriter.add_image
    calls = {"n": 0}

    def dying(self, *a, **k):
        res = real(self, *a, **k)
        calls["n"] += 1
        if calls["n"] == n:
            raise KeyboardInterrupt("simulated kill")
        return res

    monkeypatch.setattr(S.BopSceneWriter, "add_image", dying)
    with pytest.raises(KeyboardInterrupt):
        generate.main(argv)
    monkeypatch.setattr(S.BopSceneWriter, "add_image", real)


def test_resume_after_a_kill_gives_the_same_bytes(reference, tmp_path, monkeypatch):
    """A run killed inside scene 1 (after writing one of its files) resumes to the bytes of an
    uninterrupted run; so does a scene left half written in its temporary folder."""
    out = tmp_path / "killed"
    # The first image of scene 1 is on disk, then the process dies.
    _killed_after_images(monkeypatch, 2, ARGS + ["--out", str(out)])
    split = out / "train_pbr"
    assert (split / "000000").is_dir() and (split / "000001.tmp").is_dir()
    assert not (split / "000001").exists()
    assert json.loads((split / "manifest.json").read_text())["status"] == "running"
    generate.main(ARGS + ["--out", str(out)])
    _assert_same_tree(reference, out)

    # A second kind of kill: the last scene's folder demoted to a half-written temporary one.
    (split / "000002").rename(split / "000002.tmp")
    for f in sorted((split / "000002.tmp" / "mask").iterdir())[::2]:
        f.unlink()
    (split / "000002.tmp" / "scene_gt.json").write_text("{ truncated")
    generate.main(ARGS + ["--out", str(out)])
    _assert_same_tree(reference, out)


def test_a_shard_is_independent_of_the_split(reference, tmp_path, capsys):
    out = tmp_path / "shard2"
    generate.main(ARGS + ["--out", str(out), "--shard", "2", "--num-shards", "3"])
    assert sorted(p.name for p in (out / "train_pbr").iterdir()) == [
        generate.LOCK_FILE, "000002", "manifest.json"]
    _assert_same_tree(reference / "train_pbr" / "000002", out / "train_pbr" / "000002")
    for ply in (out / "models").glob("obj_*.ply"):
        assert ply.read_bytes() == (reference / "models" / ply.name).read_bytes()
    assert list(generate.shard_scene_ids(10, 0, 3)) == [0, 1, 2]
    assert [list(generate.shard_scene_ids(10, k, 3)) for k in range(3)] == [
        [0, 1, 2], [3, 4, 5], [6, 7, 8, 9]]
    # Two shards in one folder, or other arguments: refused with the fix named.
    assert "own --out" in _refused(
        capsys, ARGS + ["--out", str(out), "--shard", "1", "--num-shards", "3"])
    assert "different arguments" in _refused(
        capsys, ARGS[:-1] + ["4", "--out", str(out), "--shard", "2", "--num-shards", "3"])


def test_command_line_with_one_thread_gives_the_same_bytes(reference, tmp_path):
    """``python -m datagen.generate`` in a fresh process with one Dr.Jit thread (the reference
    ran with all cores) writes the same scene."""
    out = tmp_path / "one_thread"
    subprocess.run([sys.executable, "-m", "datagen.generate", *ARGS, "--out", str(out),
                    "--shard", "0", "--num-shards", "3", "--threads", "1"], check=True,
                   cwd=pathlib.Path(__file__).resolve().parents[2])
    _assert_same_tree(reference / "train_pbr" / "000000", out / "train_pbr" / "000000")


def test_bad_meshes_are_skipped_and_counted(tmp_path):
    cad = tmp_path / "cad"
    cad.mkdir()
    trimesh.creation.box(extents=(30.0, 40.0, 50.0)).export(cad / "good.obj")
    (cad / "garbage.ply").write_bytes(np.random.default_rng(0).bytes(2000))
    # Loads fine but is flat: it cannot be simulated.
    trimesh.Trimesh([[0, 0, 0], [60, 0, 0], [0, 60, 0]], [[0, 1, 2]]).export(cad / "flat.obj")
    out = tmp_path / "out"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        generate.main(["--meshes", str(cad), "--out", str(out), "--num-scenes", "2",
                       "--resolution", "64", "48", "--spp", "1", "--instances", "3",
                       "--distinct", "3", "3", "--quiet"])
    assert any(issubclass(w.category, MeshSkippedWarning) for w in caught)
    m = json.loads((out / "train_pbr" / "manifest.json").read_text())
    assert m["status"] == "complete" and m["skipped_meshes"] == 2
    assert sorted(m["skipped_mesh_reasons"]) == ["cad/flat", "cad/garbage"]
    assert list(m["objects"].values()) == ["cad/good"]
    # Only usable meshes reach models/ (ids follow sorted paths: flat, garbage, good).
    assert list(m["objects"]) == ["3"]
    assert sorted(p.name for p in (out / "models").glob("obj_*")) == ["obj_000003.ply"]


def test_held_out_meshes():
    names = [f"procedural/gear_{k:04d}" for k in range(400)]
    val = [n for n in names if generate.mesh_split(n, 0.25) == "val"]
    # Independent recomputation of the documented rule.
    want = [n for n in names
            if int.from_bytes(hashlib.sha256(n.encode()).digest()[:8], "big") / 2**64 < 0.25]
    assert val == want and 70 < len(val) < 130
    pool = generate.build_pool(["procedural:12"], 0, procedural_max_faces=800)
    tr = generate.split_candidates(pool, "train", 0.3)
    va = generate.split_candidates(pool, "val", 0.3)
    assert sorted(tr + va) == list(range(12)) and not set(tr) & set(va)
    assert generate.split_candidates(pool, "val", 0.0) == list(range(12))


def test_train_and_val_splits_share_one_folder(tmp_path, capsys):
    """Held-out meshes: a val run beside a train run (same seed and meshes) uses only val meshes,
    and both splits' models end up in the shared models/ and models_info.json."""
    out = tmp_path / "splits"
    # Seed 2's 12 parts: 3 fall in train, 9 in val.
    base = ["--meshes", "procedural:12", "--procedural-max-faces", "800", "--resolution",
            "64", "48", "--spp", "1", "--instances", "4", "--quiet", "--val-fraction", "0.5"]
    generate.main(base + ["--seed", "2", "--out", str(out), "--split", "train",
                          "--num-scenes", "2"])
    generate.main(base + ["--seed", "2", "--out", str(out), "--split", "val",
                          "--num-scenes", "1"])
    pool = generate.build_pool(["procedural:12"], 2, procedural_max_faces=800)
    objs = {}
    for split in ("train", "val"):
        m = json.loads((out / f"{split}_pbr" / "manifest.json").read_text())
        objs[split] = set(m["objects"].values())
        assert all(generate.mesh_split(n, 0.5) == split for n in objs[split])
    assert objs["train"] and objs["val"] and not objs["train"] & objs["val"]
    info = json.loads((out / "models" / "models_info.json").read_text())
    names = {pool.records[int(k) - 1].name for k in info}
    assert objs["train"] | objs["val"] <= names
    # A split of another seed next to them is refused before any work.
    other = tmp_path / "other"
    (other / "train_pbr").mkdir(parents=True)
    (other / "train_pbr" / "manifest.json").write_bytes(
        (out / "train_pbr" / "manifest.json").read_bytes())
    err = _refused(capsys, base + ["--seed", "9", "--out", str(other), "--split", "val",
                                   "--num-scenes", "1"])
    assert "--seed 9 differs from --seed 2" in err


def test_cli_errors_name_the_fix(tmp_path, capsys):
    assert "procedural:N" in _refused(
        capsys, ["--meshes", "procedural:x", "--out", str(tmp_path), "--num-scenes", "1"])
    assert "neither a folder" in _refused(
        capsys, ["--meshes", str(tmp_path / "nope"), "--out", str(tmp_path), "--num-scenes", "1"])
    assert "--shard" in _refused(
        capsys, ["--meshes", "procedural:2", "--out", str(tmp_path), "--num-scenes", "1",
                 "--shard", "3", "--num-shards", "2"])


def test_shared_bop_meshes(bop_models_dir, tmp_path):
    """docs/datagen.md's example on the shared meshes: BOP models keep their ids' files (copied,
    textures renamed), symmetries and a two-view rig."""
    out = tmp_path / "bop"
    generate.main(["--meshes", str(bop_models_dir / "itodd" / "models"),
                   str(bop_models_dir / "tudl" / "models"), "--out", str(out),
                   "--num-scenes", "1", "--views", "2", "--resolution", "64", "48", "--spp", "1",
                   "--instances", "3", "--distinct", "2", "2", "--quiet", "--seed", "1"])
    ds = BopDataset(out)
    manifest = json.loads((out / "train_pbr" / "manifest.json").read_text())
    scene = ds.split("train_pbr").scene(0)
    assert scene.image_ids == [0, 1] and len(scene.gt[0]) >= 2
    models = ds.models()
    for oid, name in manifest["objects"].items():
        dataset, obj = name.split("/")
        src = bop_models_dir / dataset / "models" / f"{obj}.ply"
        assert models[int(oid)].path.read_bytes() == src.read_bytes()
        info = json.loads((src.parent / "models_info.json").read_text())[obj.split("_")[1].lstrip(
            "0")]
        assert models[int(oid)].diameter == pytest.approx(info["diameter"], rel=1e-3)
        assert len(models[int(oid)].symmetries.discrete) == len(
            info.get("symmetries_discrete", []))


MULTIVIEW = ["--meshes", "procedural:4", "--procedural-max-faces", "800", "--resolution", "64",
             "48", "--spp", "1", "--instances", "3", "--quiet", "--seed", "5", "--num-scenes",
             "2", "--views", "2", "--images-per-scene", "2"]


def test_multiview_targets_list_every_capture_after_a_resume(tmp_path, monkeypatch):
    """A two-view rig, two captures per scene, killed inside scene 1: the resumed run's
    targets file lists the captures of both scenes (it is written from the scenes on disk)."""
    out = tmp_path / "mv"
    # Scene 0's 4 images, then the first of scene 1.
    _killed_after_images(monkeypatch, 5, MULTIVIEW + ["--out", str(out)])
    generate.main(MULTIVIEW + ["--out", str(out)])
    ds = BopDataset(out)
    got = ds.multiview_targets()
    # Capture m of a scene holds image ids 2m, 2m + 1.
    assert [(t.scene_id, [i for _, i in t.views]) for t in got] == [
        (0, [0, 1]), (0, [2, 3]), (1, [0, 1]), (1, [2, 3])]
    for t in got:  # each group is one capture: views of one rig, posed in one world frame
        scene = ds.split("train_pbr").scene(t.scene_id)
        assert {i for _, i in t.views} <= set(scene.image_ids)
        assert all(scene.cameras[i].T_cam_world is not None for _, i in t.views)
    raw = json.loads((out / "test_targets_multiview_bop25.json").read_text())
    assert raw[0] == {"scene_id": 0, "im_ids": [0, 1]}


def test_multiview_targets_follow_the_val_split_when_both_are_multiview(tmp_path):
    """Hand-built roots: only multi-view splits count, and val wins over train."""
    def split(name, views, scenes, captures=1):
        d = tmp_path / f"{name}_pbr"
        d.mkdir()
        (d / "manifest.json").write_text(json.dumps({"config": {"views": views}}))
        for s in scenes:
            (d / f"{s:06d}").mkdir()
            (d / f"{s:06d}" / generate.INFO_FILE).write_text(
                json.dumps({"views": views, "captures": captures}))
        (d / "000009.tmp").mkdir()  # a partial scene: not listed

    split("train", 1, [0, 1])
    assert generate.multiview_targets(tmp_path) is None
    split("val", 3, [4, 2], captures=2)
    got = generate.multiview_targets(tmp_path)
    assert [(t.scene_id, [i for _, i in t.views]) for t in got] == [
        (2, [0, 1, 2]), (2, [3, 4, 5]), (4, [0, 1, 2]), (4, [3, 4, 5])]
