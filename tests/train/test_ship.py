"""``python -m train.ship``: a 3PT-R ships only when it refines held-out scenes better than the
default refiner, and then loads by default. The inference path is recorded, not run (its
figures are those of ``infer.bop_runner.run_bop``, tested in tests/infer/test_bop_runner.py);
the export, the card, ``models/shipped.json`` and the default loading are real."""

import json
import subprocess

import jax
import numpy as np
import pytest
from flax import nnx

import infer
from infer import shipped
from infer.checkpoint import load_refiner
from tests.fixtures.run_dirs import tiny_refiner_run
from threept_jax.pipeline.contour import ContourSettings
from train import ship


def _summary(ap: float) -> dict:
    """An ``infer bop --evaluate`` summary with refinement: 6D AP ``ap`` after, 0.05 before."""

    def files(base):
        pose = {"ap": base, "ap_mm": base + .01, "ap_mssd": base + .02, "ap_mspd": base + .03,
                "ar_mssd": 0.5, "per_object": {"1": base}}
        det = {"bbox": {"ap": .3, "ap50": .45, "f1": .4, "f1_threshold": .5},
               "segm": {"ap": base + .04, "ap50": .5}}
        return pose, det

    pose, det = files(ap)
    initial_pose, initial_det = files(0.05)
    return {"csv": "x.csv", "json": "x.json", "pose": pose, "detection": det,
            "pose_initial": initial_pose, "detection_initial": initial_det}


@pytest.fixture
def repo(tmp_path, monkeypatch):
    """A models/ folder whose shipped.json names no 3PT-R (the repository's today), a held-out
    dataset folder, and run_bop recorded: the refiner named in ``aps`` gets that 6D AP."""
    import infer.bop_runner

    models = tmp_path / "models"
    models.mkdir()
    (models / shipped.SHIPPED_FILE).write_text('{"detector": "detector-cpu", "refiner": null}')
    monkeypatch.setattr(shipped, "MODELS_DIR", models)
    (tmp_path / "held" / "val_pbr").mkdir(parents=True)
    aps, calls = {}, []

    def run_bop(args):
        calls.append(args)
        return _summary(aps[str(args.refiner)])

    monkeypatch.setattr(infer.bop_runner, "run_bop", run_bop)
    return models, aps, calls


def _argv(tmp_path, run, name):
    return ["--run", str(run), "--name", name, "--dataset-dir", str(tmp_path / "held"),
            "--out", str(tmp_path / "out" / name)]


def _params(model):
    return [np.asarray(x) for x in jax.tree.leaves(nnx.state(model, nnx.Param))]


def test_bad_arguments_exit_2_naming_the_flag(tmp_path, capsys):
    run = tiny_refiner_run(tmp_path / "run")
    (tmp_path / "held" / "val_pbr").mkdir(parents=True)
    good = ["--run", str(run), "--name", "x", "--dataset-dir", str(tmp_path / "held")]
    for argv, match in (
        ([*good[:1], str(tmp_path), *good[2:]], "is not a 3PT-R training run"),
        ([*good[:3], "Big Name", *good[4:]], "--name 'Big Name'"),
        ([*good[:5], str(tmp_path)], "has no val_pbr split"),
        ([*good, "--records", str(tmp_path)], "is not a records folder"),
        ([*good, "--max-detections", "0"], "--max-detections must be >= 1"),
    ):
        with pytest.raises(SystemExit) as e:
            ship.main(argv)
        assert e.value.code == 2
        assert match in capsys.readouterr().err


def test_a_better_refiner_ships_loads_by_default_and_a_worse_one_does_not_replace_it(
        tmp_path, repo, monkeypatch, capsys):
    models, aps, calls = repo
    import train.eval_refiner

    monkeypatch.setattr(train.eval_refiner, "evaluate_run", lambda run, data_dir: {
        "eval/match_within_2px": 0.31, "eval/match_within_2px_same_place": 0.11,
        "eval/rot_deg_before": 10.3, "eval/rot_deg_after_1": 8.1, "eval/rot_deg_after_3": 7.2,
        "eval/ar_mssd_before": 0.5,
        "eval/ar_mssd_after": 0.6, "step": 0})
    records = tmp_path / "records"
    records.mkdir()
    (records / "objects.json").write_text("{}")
    run = tiny_refiner_run(tmp_path / "run")
    aps.update({str(run): 0.41, "contour": 0.33})
    result = ship.main([*_argv(tmp_path, run, "gpu"), "--records", str(records)])

    # Both refined the same detections: the default detector, the held-out val_pbr images.
    assert [str(a.refiner) for a in calls] == [str(run), "contour"]
    for args in calls:
        assert args.dataset_dir == tmp_path / "held" and args.split == "val_pbr"
        assert args.detector == "templates" and args.evaluate and args.score_threshold == 0.0
    assert result["ships"] and result["candidate"]["pose_ap"] == pytest.approx(0.41)
    folder = models / "refiner-gpu"
    assert result["shipped_as"] == str(folder)
    assert json.loads((models / "shipped.json").read_text()) == {
        "detector": "detector-cpu", "refiner": "refiner-gpu"}
    check = subprocess.run(["sha256sum", "--check", "--strict", "SHA256SUMS"], cwd=folder,
                           capture_output=True, text=True)
    assert check.returncode == 0, check.stdout + check.stderr
    card = (folder / "MODEL_CARD.md").read_text()
    for text in ("| **0.410** |", "| **0.330** |", "python -m train.ship --run", "`tiny/16`",
                 "replaced `contour`", "matches within 2 px 0.310 against position alone 0.110",
                 "10.30 -> 7.20 degrees; MSSD recall 0.500 -> 0.600 (before -> after its 3 steps)"):
        assert text in card, (text, card)
    assert json.loads((tmp_path / "out" / "gpu" / "ship_check.json").read_text())["ships"]
    assert "shipped as" in capsys.readouterr().out

    # From now on it is the default refiner: loaded, with the run's parameters.
    assert shipped.default_refiner() == folder
    models_loaded = infer.load(cache_dir=None)
    assert not isinstance(models_loaded.refiner, ContourSettings)
    for a, b in zip(_params(models_loaded.refiner), _params(load_refiner(run)[0]), strict=True):
        np.testing.assert_array_equal(a, b)

    # A second run is checked against the shipped one, not the contour refiner; no better
    # (equal), it changes nothing under models/.
    before = {p: p.read_bytes() for p in models.rglob("*") if p.is_file()}
    other = tiny_refiner_run(tmp_path / "other", seed=1)
    aps[str(other)], aps[str(folder)] = 0.41, 0.41
    calls.clear()
    result = ship.main(_argv(tmp_path, other, "other"))
    assert [str(a.refiner) for a in calls] == [str(other), str(folder)]
    assert not result["ships"] and result["default_refiner"] == str(folder)
    assert {p: p.read_bytes() for p in models.rglob("*") if p.is_file()} == before
    assert "not shipped" in capsys.readouterr().out
    assert not json.loads((tmp_path / "out" / "other" / "ship_check.json").read_text())["ships"]
    # A name taken by a folder that is not the shipped refiner is refused before any work.
    (models / "refiner-stale").mkdir()
    with pytest.raises(SystemExit) as e:
        ship.main(_argv(tmp_path, other, "stale"))
    assert e.value.code == 2 and "exists and is not the shipped refiner" in capsys.readouterr().err


def test_shipped_json_missing_or_malformed_is_named_with_its_restore(tmp_path, monkeypatch):
    from threept_jax.data.run_dir import ModelFileError

    models = tmp_path / "models"
    models.mkdir()
    monkeypatch.setattr(shipped, "MODELS_DIR", models)
    with pytest.raises(ModelFileError, match=r"shipped.json not found.*git checkout -- "
                                             r"models/shipped.json"):
        shipped.shipped("refiner")
    for text in ("{", '{"detector": "detector-cpu"}', '{"detector": 3, "refiner": null}'):
        (models / "shipped.json").write_text(text)
        with pytest.raises(ModelFileError, match="shipped.json.*git checkout"):
            shipped.default_refiner()
    (models / "shipped.json").write_text('{"detector": null, "refiner": null}')
    with pytest.raises(ValueError, match="is not a refiner model folder"):
        shipped.set_shipped("refiner", "refiner-none")
    assert shipped.default_refiner() == shipped.CONTOUR
    # A non-editable install has no models/: the contour refiner refines.
    monkeypatch.setattr(shipped, "MODELS_DIR", tmp_path / "absent" / "models")
    assert shipped.default_refiner() == shipped.CONTOUR
    with pytest.raises(ModelFileError, match="pip install -e"):
        shipped.shipped("detector")
