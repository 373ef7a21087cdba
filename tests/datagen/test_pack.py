"""``python -m datagen.pack``: every field of every record against the BOP reader, shards read
with grain, the object table and banks, a published-style BOP dataset packed beside generated
scenes (ids remapped by mesh identity), and clear errors.

References: the BOP reader (``threept_jax.data.bop``) reading the source scenes, the mask PNGs,
``grids`` rotations, and the source model files byte for byte.
"""

import json
import pathlib

import grain
import numpy as np
import pytest
import trimesh

from datagen import generate, pack
from datagen.scene import write_ply
from threept_jax.data import banks, bop, records
from threept_jax.geometry.grids import prior_view_rotations, super_fibonacci_rotations
from threept_jax.testing.bop_synthetic import SyntheticInstance, write_synthetic_dataset

BANK = ["--bank-backend", "mitsuba", "--num-templates", "8", "--bank-size", "32", "--quiet"]


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    out = tmp_path_factory.mktemp("gen")
    generate.main(["--meshes", "procedural:5", "--procedural-max-faces", "800", "--out",
                   str(out), "--num-scenes", "2", "--views", "2", "--resolution", "64", "48",
                   "--spp", "2", "--instances", "6", "--image-format", "jpg", "--quiet",
                   "--seed", "11"])
    return out


@pytest.fixture(scope="module")
def published(tmp_path_factory):
    """A small BOP dataset laid out like a published PBR training set (no extrinsics)."""
    root = tmp_path_factory.mktemp("pub") / "mini"
    (root / "models").mkdir(parents=True)
    models = {}
    for oid, ext in [(1, (40.0, 30.0, 20.0)), (2, (25.0, 25.0, 60.0))]:
        b = trimesh.creation.box(extents=ext)
        ply = root / "models" / f"obj_{oid:06d}.ply"
        write_ply(ply, b.vertices, b.faces)
        models[oid] = bop.compute_model_info(np.asarray(b.vertices), obj_id=oid, path=ply)
    rng = np.random.default_rng(0)
    scenes = {}
    for sid in (0, 1):
        ims = {}
        for im in range(3):
            insts = []
            for oid in (1, 2, 2):
                T = np.eye(4)
                T[:3, :3] = np.linalg.qr(rng.normal(size=(3, 3)))[0] * [1, 1, 1]
                if np.linalg.det(T[:3, :3]) < 0:
                    T[:3, 0] *= -1
                T[:3, 3] = [rng.uniform(-60, 60), rng.uniform(-40, 40), rng.uniform(400, 600)]
                insts.append(SyntheticInstance(oid, T, rng.uniform(0.0, 1.0)))
            ims[im] = insts
        scenes[sid] = ims
    K = np.array([[300.0, 0, 79.5], [0, 310.0, 59.5], [0, 0, 1]])
    write_synthetic_dataset(root, models, scenes, K, 160, 120, split="train_pbr")
    return root


def _records(folder):
    paths = sorted(str(p) for p in pathlib.Path(folder).glob("shard-*.array_record"))
    source = grain.sources.ArrayRecordDataSource(paths)
    return [records.decode_example(source[i]) for i in range(len(source))], paths


def _check_roundtrip(examples, split_dir, id_map, label):
    split = bop.BopSplit(split_dir)
    want = [(sid, im) for sid in split.scene_ids for im in split.scene(sid).image_ids]
    assert [(int(e["scene_id"]), int(e["im_id"])) for e in examples] == want
    for ex, (sid, im) in zip(examples, want):
        scene = split.scene(sid)
        cam = scene.cameras[im]
        gts, infos = scene.gt[im], scene.gt_info[im]
        assert ex["source"] == label
        np.testing.assert_array_equal(ex["rgb"], scene.image(im))
        np.testing.assert_allclose(ex["K"], cam.K, rtol=1e-6)
        T_cw = np.eye(4) if cam.T_cam_world is None else cam.T_cam_world
        np.testing.assert_allclose(ex["T_cam_world"], T_cw, atol=1e-3)
        assert ex["obj_id"].tolist() == [id_map[g.obj_id] for g in gts]
        np.testing.assert_allclose(ex["T_cam_obj"], [g.T_cam_obj for g in gts], atol=1e-3)
        for k, info in enumerate(infos):
            for key, box in (("bbox_obj", info.bbox_obj), ("bbox_visib", info.bbox_visib)):
                x, y, w, h = box
                expect = [-1, -1, -1, -1] if w < 0 else [x, y, x + w, y + h]
                assert ex[key][k].tolist() == expect
            assert ex["visib_fract"][k] == pytest.approx(info.visib_fract, abs=1e-6)
            visib = scene.mask_visib(im, k)
            mine = ex["instances"] == k + 1
            if info.px_count_visib:
                np.testing.assert_array_equal(mine, visib & ~np.any(
                    [scene.mask_visib(im, j) for j in range(k)] or [np.zeros_like(visib)], 0))
            else:
                assert not mine.any()


def test_generated_scenes_roundtrip(generated, tmp_path):
    out = tmp_path / "rec"
    index = pack.main(["--scenes", str(generated / "train_pbr"), "--out", str(out),
                       "--num-shards", "3", *BANK])
    examples, paths = _records(out / "train")
    assert [pathlib.Path(p).name for p in paths] == [
        f"shard-{k:05d}-of-00003.array_record" for k in range(3)]
    assert len(examples) == index["num_records"] == 4
    assert sorted(index["shards"].values()) == [1, 1, 2]
    manifest = json.loads((generated / "train_pbr" / "manifest.json").read_text())
    table = json.loads((out / "objects.json").read_text())
    id_map = {int(k): int(v) for k, v in index["sources"][0]["obj_ids"].items()}
    # One generated dataset: ids kept, names from the generator.
    assert all(k == v for k, v in id_map.items())
    for oid, name in manifest["objects"].items():
        assert table[oid]["name"] == name
    _check_roundtrip(examples, generated / "train_pbr", id_map, f"{generated.name}/train_pbr")
    assert any(np.abs(e["T_cam_world"] - np.eye(4)).max() > 1 for e in examples)

    entries = banks.load_object_table(out)
    assert sorted(entries) == sorted(id_map.values())
    for oid, entry in entries.items():
        row = table[str(oid)]
        src = generated / "models" / f"obj_{row['source_obj_id']:06d}.ply"
        assert (out / row["mesh"]).read_bytes() == src.read_bytes()
        bank = banks.load_bank(entry.bank_path)
        assert bank.obj_id == oid and bank.image_hw == (32, 32) and bank.num_templates == 8
        np.testing.assert_allclose(bank.prior_rotations, prior_view_rotations(), atol=1e-6)
        np.testing.assert_allclose(bank.template_rotations, super_fibonacci_rotations(8),
                                   atol=1e-6)
        assert bank.diameter == pytest.approx(entry.diameter)
        assert (bank.prior_rgb.reshape(12, -1).max(1) > 0).all()
        assert (bank.template_rgb.reshape(8, -1).max(1) > 0).all()
        models = bop.load_models(generated / "models")
        assert len(bank.symmetries) >= 1 + len(models[row["source_obj_id"]].symmetries.discrete)


def test_packing_is_deterministic(generated, tmp_path):
    """Same inputs and arguments, same shard bytes, with one or two encoding processes."""
    args = ["--scenes", str(generated / "train_pbr"), "--num-shards", "2", "--no-banks",
            "--quiet", "--image-format", "jpg"]
    pack.main(args + ["--out", str(tmp_path / "a")])
    pack.main(args + ["--out", str(tmp_path / "b"), "--workers", "2"])
    for k in range(2):
        name = f"shard-{k:05d}-of-00002.array_record"
        assert (tmp_path / "a" / "train" / name).read_bytes() == (
            tmp_path / "b" / "train" / name).read_bytes()


def test_published_dataset_packs_beside_generated_scenes(generated, published, tmp_path):
    out = tmp_path / "mixed"
    pack.main(["--scenes", str(generated / "train_pbr"), "--out", str(out), "--split-label",
               "train", *BANK])
    index = pack.main(["--scenes", str(published / "train_pbr"), "--out", str(out), "--name",
                       "val", "--split-label", "val", "--num-shards", "2", *BANK])
    table = banks.load_object_table(out)
    gen_ids = set(json.loads((out / "train" / "index.json").read_text())["sources"][0][
        "obj_ids"].values())
    id_map = {int(k): int(v) for k, v in index["sources"][0]["obj_ids"].items()}
    # Ids 1 and 2 are taken by generated meshes: the published objects get new ones.
    assert set(id_map) == {1, 2} and not set(id_map.values()) & gen_ids
    for src_id, oid in id_map.items():
        assert table[oid].name == f"mini/obj_{src_id:06d}" and table[oid].split == "val"
        assert table[oid].diameter == pytest.approx(np.linalg.norm(
            [[40, 30, 20], [25, 25, 60]][src_id - 1]))
    assert all(table[o].split == "train" for o in gen_ids)
    examples, _ = _records(out / "val")
    _check_roundtrip(examples, published / "train_pbr", id_map, "mini/train_pbr")
    # Packing the same published set again maps to the same ids (mesh identity), and the
    # rendered banks are kept.
    before = {p.name: p.stat().st_mtime_ns for p in (out / "banks").iterdir()}
    again = pack.main(["--scenes", str(published / "train_pbr"), "--out", str(out), "--name",
                       "val2", *BANK])
    assert again["sources"][0]["obj_ids"] == index["sources"][0]["obj_ids"]
    assert {p.name: p.stat().st_mtime_ns for p in (out / "banks").iterdir()} == before


def _refused(capsys, argv) -> str:
    """``pack.main(argv)`` exits with status 2 and ``error: ...``; returns stderr."""
    with pytest.raises(SystemExit) as e:
        pack.main(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.startswith("error: "), (e.value.code, err)
    return err


def test_pack_errors_name_the_fix(generated, published, tmp_path, capsys):
    assert "dataset root" in _refused(
        capsys, ["--scenes", str(generated), "--out", str(tmp_path / "a"), *BANK])
    assert "--models" in _refused(
        capsys, ["--scenes", str(published / "train_pbr"), "--out", str(tmp_path / "b"),
                 "--models", str(tmp_path), *BANK])
    broken = tmp_path / "broken" / "train_pbr"
    import shutil

    shutil.copytree(published / "train_pbr", broken)
    shutil.copytree(published / "models", broken.parent / "models")
    shutil.rmtree(broken / "000000" / "mask_visib")
    assert "calc_gt_masks" in _refused(
        capsys, ["--scenes", str(broken), "--out", str(tmp_path / "c"), "--no-banks", "--quiet"])
