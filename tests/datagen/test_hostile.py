"""Hostile use of the datagen command lines: out-of-range options, splits of one ``--out`` that
disagree on the held-out meshes, two writers of one shard, and leftovers of killed runs.

References: hand-written bounds; Mitsuba's own renders for the path-length bound; held-out sets
recomputed here from SHA-256 of the mesh names; byte comparison with the output of a clean run.
"""

import hashlib
import json
import pathlib
import shutil
import signal
import subprocess
import sys

import numpy as np
import pytest
import trimesh
from fixtures.training import ROOT, SUBPROCESS_ENV

from datagen import banks, generate, pack
from datagen import scene as S

# Seed 2's 8 parts hash to 0.06 0.11 0.13 0.15 0.22 0.31 0.39 0.92 (test_leak_is_real).
SPLIT_ARGS = ["--meshes", "procedural:8", "--procedural-max-faces", "600", "--seed", "2",
              "--resolution", "32", "24", "--spp", "1", "--instances", "2", "--distinct", "1",
              "1", "--distractors", "0", "0", "--max-depth", "2", "--image-format", "png",
              "--quiet", "--num-scenes", "1"]


def _refused(capsys, argv, main=generate.main) -> str:
    """Run ``main(argv)``, expect ``error: ...`` on stderr and exit status 2; return stderr."""
    with pytest.raises(SystemExit) as e:
        main(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2, (e.value.code, err)
    assert err.startswith("error: "), err
    return err


def _tree(root: pathlib.Path) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes()
            for p in sorted(root.rglob("*")) if p.is_file()}


# --------------------------------------------------------------------------------------------
# Numeric options.

BAD_GENERATE = [
    (["--max-depth", "0"], "--max-depth"),
    (["--max-depth", "1"], "--max-depth"),
    (["--max-depth", "-2"], "--max-depth"),
    (["--num-scenes", "0"], "--num-scenes"),
    (["--images-per-scene", "0"], "--images-per-scene"),
    (["--views", "0"], "--views"),
    (["--resolution", "64", "15"], "--resolution"),
    (["--spp", "0"], "--spp"),
    (["--seed", "-1"], "--seed"),
    (["--num-shards", "0"], "--num-shards"),
    (["--shard", "2", "--num-shards", "2"], "--shard"),
    (["--shard", "-1"], "--shard"),
    (["--val-fraction", "1"], "--val-fraction"),
    (["--val-fraction", "-0.1"], "--val-fraction"),
    (["--val-fraction", "nan"], "--val-fraction"),
    (["--instances", "0"], "--instances"),
    (["--distinct", "3", "2"], "--distinct"),
    (["--distinct", "0", "2"], "--distinct"),
    (["--distractors", "2", "1"], "--distractors"),
    (["--distractors", "-1", "1"], "--distractors"),
    (["--closeup-probability", "1.5"], "--closeup-probability"),
    (["--closeup-probability", "-0.5"], "--closeup-probability"),
    (["--procedural-max-faces", "100"], "--procedural-max-faces"),
    (["--threads", "-1"], "--threads"),
]


@pytest.mark.parametrize("flags, flag", BAD_GENERATE, ids=[" ".join(f) for f, _ in BAD_GENERATE])
def test_generate_refuses_bad_numbers_before_any_work(flags, flag, tmp_path, capsys,
                                                      monkeypatch):
    def no_pool(*a, **k):
        raise AssertionError("the mesh pool was built before the options were checked")

    monkeypatch.setattr(generate, "build_pool", no_pool)
    out = tmp_path / "out"
    err = _refused(capsys, ["--meshes", "procedural:2", "--out", str(out), "--num-scenes", "1",
                            *flags])
    assert err.startswith(f"error: {flag} "), err
    assert "Traceback" not in err and not out.exists()


GOOD_GENERATE = [["--max-depth", "-1"], ["--max-depth", "2"], ["--val-fraction", "0"],
                 ["--closeup-probability", "0"], ["--closeup-probability", "1"],
                 ["--distinct", "1", "1"], ["--distractors", "0", "0"], ["--threads", "0"],
                 ["--shard", "1", "--num-shards", "2"], ["--resolution", "16", "16"],
                 ["--procedural-max-faces", "500"], ["--seed", "0"]]


@pytest.mark.parametrize("flags", GOOD_GENERATE, ids=[" ".join(f) for f in GOOD_GENERATE])
def test_generate_accepts_the_bounds(flags):
    args = generate.build_parser().parse_args(
        ["--meshes", "procedural:2", "--out", "x", "--num-scenes", "2", *flags])
    generate.check_args(args)


def test_max_depth_bound_is_where_mitsuba_lights_objects():
    """A lit grey box path traced at one below ``MIN_MAX_DEPTH`` is black inside its silhouette
    (only the light sources are drawn); at ``MIN_MAX_DEPTH`` it is lit."""
    from threept_jax.render.mesh import Mesh
    from threept_jax.render.mitsuba_backend import Material, MitsubaScene

    box = trimesh.creation.box(extents=(50.0, 50.0, 50.0))
    mesh = Mesh(np.asarray(box.vertices, np.float32), np.asarray(box.faces, np.int32), name="b")
    K = np.array([[40.0, 0, 15.5], [0, 40.0, 11.5], [0, 0, 1]])
    T_cw = np.eye(4)
    T_cw[2, 3] = 300.0
    medians = []
    for depth in (S.MIN_MAX_DEPTH - 1, S.MIN_MAX_DEPTH):
        scene = MitsubaScene(max_depth=depth)
        scene.add_object(mesh, np.eye(4), Material(color=(0.8, 0.8, 0.8)))
        scene.set_environment((0.5, 0.5, 0.5))
        scene.add_point_light((0.0, 0.0, -400.0), (1e5, 1e5, 1e5))
        out = scene.render(K, T_cw, (24, 32), spp=1, seed=0, outputs=("rgb", "instance"),
                           linear=True)
        inside = out["instance"] == 1
        assert inside.sum() > 30
        medians.append(float(np.median(out["rgb"][inside])))
    assert medians[0] == 0.0 and medians[1] > 0.1
    with pytest.raises(ValueError, match="max_depth"):
        S.SceneConfig(max_depth=S.MIN_MAX_DEPTH - 1)


BAD_PACK = [
    (["--num-shards", "0"], "--num-shards"),
    (["--workers", "0"], "--workers"),
    (["--bank-size", "4"], "--bank-size"),
    (["--num-templates", "0"], "--num-templates"),
    (["--bank-max-faces", "0"], "--bank-max-faces"),
]


@pytest.mark.parametrize("flags, flag", BAD_PACK, ids=[" ".join(f) for f, _ in BAD_PACK])
def test_pack_refuses_bad_numbers_before_any_work(flags, flag, tmp_path, capsys):
    out = tmp_path / "rec"
    err = _refused(capsys, ["--scenes", str(tmp_path / "missing"), "--out", str(out), "--quiet",
                            *flags], main=pack.main)
    assert err.startswith(f"error: {flag} "), err
    assert not out.exists()


# --------------------------------------------------------------------------------------------
# Splits of one --out.


@pytest.fixture(scope="module")
def splits(tmp_path_factory):
    """One --out with a train and a val split at --val-fraction 0.3."""
    out = tmp_path_factory.mktemp("splits")
    for split in ("train", "val"):
        generate.main(SPLIT_ARGS + ["--out", str(out), "--split", split, "--val-fraction", "0.3"])
    return out


def _hash(name: str) -> float:
    return int.from_bytes(hashlib.sha256(name.encode()).digest()[:8], "big") / 2**64


def test_leak_is_real():
    """With train at --val-fraction 0.3 and val at 0.5, some meshes would be in both splits."""
    pool = generate.build_pool(["procedural:8"], 2, procedural_max_faces=600)
    h = [_hash(r.name) for r in pool.records]
    assert [round(x, 2) for x in sorted(h)] == [0.06, 0.11, 0.13, 0.15, 0.22, 0.31, 0.39, 0.92]
    train_03 = {i for i, x in enumerate(h) if x >= 0.3}
    val_05 = {i for i, x in enumerate(h) if x < 0.5}
    assert len(train_03 & val_05) == 2


def _only(splits, split: str, dst: pathlib.Path) -> pathlib.Path:
    """A fresh --out holding only ``split``'s manifest and the models of ``splits``."""
    (dst / f"{split}_pbr").mkdir(parents=True)
    shutil.copy(splits / f"{split}_pbr" / "manifest.json", dst / f"{split}_pbr")
    shutil.copytree(splits / "models", dst / "models")
    return dst


@pytest.mark.parametrize("first, then", [("train", "val"), ("val", "train")])
def test_a_split_with_another_val_fraction_is_refused(splits, first, then, tmp_path, capsys):
    out = _only(splits, first, tmp_path / "out")
    manifest = out / f"{first}_pbr" / "manifest.json"
    err = _refused(capsys, SPLIT_ARGS + ["--out", str(out), "--split", then,
                                         "--val-fraction", "0.5"])
    assert "--val-fraction 0.5 differs from --val-fraction 0.3" in err
    assert str(manifest) in err and "rerun with --val-fraction 0.3" in err
    assert not (out / f"{then}_pbr").exists()


def test_a_split_with_another_seed_or_pool_is_refused(splits, tmp_path, capsys):
    out = _only(splits, "train", tmp_path / "out")
    base = SPLIT_ARGS + ["--out", str(out), "--split", "val", "--val-fraction", "0.3"]
    err = _refused(capsys, base + ["--seed", "5"])
    assert "--seed 5 differs from --seed 2" in err
    err = _refused(capsys, [*base[:1], "procedural:9", *base[2:]])
    assert "--meshes procedural:9 differs from --meshes procedural:8" in err
    err = _refused(capsys, base + ["--procedural-max-faces", "700"])
    assert "--procedural-max-faces 700 differs from --procedural-max-faces 600" in err


def test_a_sibling_holding_out_other_meshes_is_refused(splits, tmp_path, capsys):
    """The held-out set itself is compared: a sibling recording another one (same arguments,
    e.g. an older split rule) is refused."""
    held = sorted(r.name for r in generate.build_pool(["procedural:8"], 2, procedural_max_faces=600
                                                      ).records if _hash(r.name) < 0.3)
    m = json.loads((splits / "train_pbr" / "manifest.json").read_text())
    assert m["held_out"] == {"num_meshes": 5, "fingerprint": hashlib.sha256(
        "".join(f"{n}\n" for n in held).encode()).hexdigest()[:16]}
    out = _only(splits, "train", tmp_path / "out")
    m["held_out"]["fingerprint"] = "0" * 16
    (out / "train_pbr" / "manifest.json").write_text(json.dumps(m))
    err = _refused(capsys, SPLIT_ARGS + ["--out", str(out), "--split", "val",
                                         "--val-fraction", "0.3"])
    assert "holds out 5 meshes" in err and "new --out" in err


# --------------------------------------------------------------------------------------------
# Two writers of one shard; leftovers of killed runs.

HOLD = """
import sys
from datagen import generate
with generate.shard_lock(generate.pathlib.Path(sys.argv[1]), 0, 1):
    print("locked", flush=True)
    sys.stdin.read()
"""


def test_a_second_writer_of_a_shard_is_refused_and_leftovers_are_cleaned(splits, tmp_path):
    """Process A holds the shard; the command line in process B is refused with A's pid and
    touches nothing. A is killed (its lock dies with it), leaving temporary folders and files
    as killed runs do; the next run removes them and leaves the bytes of the clean run."""
    out = tmp_path / "out"
    shutil.copytree(splits, out)
    split = out / "train_pbr"
    clean = _tree(out)
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(split)], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True, env=SUBPROCESS_ENV, cwd=ROOT)
    try:
        assert holder.stdout.readline() == "locked\n"
        # Leftovers of killed runs: a partial scene beside its finished copy, a scene of
        # another range, a torn atomic write.
        shutil.copytree(split / "000000", split / "000000.tmp")
        (split / "000003.tmp").mkdir()
        (split / ".manifest.json.x1y2.tmp").write_text("{ torn")
        planted = _tree(out)
        argv = SPLIT_ARGS + ["--out", str(out), "--split", "train", "--val-fraction", "0.3"]
        second = subprocess.run([sys.executable, "-m", "datagen.generate", *argv],
                                capture_output=True, text=True, env=SUBPROCESS_ENV, cwd=ROOT)
        assert second.returncode == 2, second.stderr
        assert second.stderr.startswith(
            f"error: shard 0 of 1 in {split} is being written by process {holder.pid} ")
        assert "Traceback" not in second.stderr
        assert _tree(out) == planted
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    assert (split / generate.LOCK_FILE).read_text()  # the dead holder's signature stays
    generate.main(argv)
    assert _tree(out) == clean


def test_a_rerun_removes_what_killed_runs_left(splits, tmp_path):
    """Temporary folders and files of killed runs, beside finished scenes too, are deleted by
    the next run, which leaves the bytes of the clean run."""
    out = tmp_path / "out"
    shutil.copytree(splits, out)
    split = out / "val_pbr"
    clean = _tree(out)
    shutil.copytree(split / "000000", split / "000000.tmp")
    (split / "000000.tmp" / "scene_gt.json").write_text("{ torn")
    (split / "000004.tmp" / "rgb").mkdir(parents=True)
    (split / ".scene_gt.json.a1b2c3.tmp").write_text("{ torn")
    generate.main(SPLIT_ARGS + ["--out", str(out), "--split", "val", "--val-fraction", "0.3"])
    assert _tree(out) == clean
    assert sorted(p.name for p in split.iterdir()) == [generate.LOCK_FILE, "000000",
                                                        "manifest.json"]


@pytest.mark.parametrize("argv, flag", [(["--size", "4"], "--size"),
                                        (["--num-templates", "0"], "--num-templates"),
                                        (["--max-faces", "0"], "--max-faces")])
def test_banks_cli_refuses_bad_numbers(tmp_path, capsys, argv, flag):
    with pytest.raises(SystemExit) as e:
        banks.main(["--records", str(tmp_path), *argv])
    assert e.value.code == 2
    assert f"error: {flag} must be >=" in capsys.readouterr().err


def test_banks_cli_reports_a_missing_table_with_exit_2(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        banks.main(["--records", str(tmp_path), "--quiet"])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "Traceback" not in err
