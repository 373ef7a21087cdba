"""``python -m train.adapt``: the whole adaptation command at toy size, run twice (resume)."""

import json

import cv2
import pytest

from infer.checkpoint import load_detector
from threept_jax.data.run_dir import RunDir
from train import adapt


def test_bad_arguments_exit_2_naming_the_flag(tmp_path, capsys):
    for argv, match in (
        (["--minutes", "0"], "--minutes must be in"),
        (["--train-scenes", "0"], "--train-scenes must be >= 1"),
        (["--resolution", "32", "32"], "--resolution must be at least"),
        (["--from", str(tmp_path)], "is not a detector training run"),
    ):
        with pytest.raises(SystemExit) as e:
            adapt.main(["--meshes", "procedural:1", "--workdir", str(tmp_path / "w"), *argv])
        assert e.value.code == 2
        assert match in capsys.readouterr().err


def test_adapt_trains_tests_and_resumes_without_redoing_work(tmp_path):
    w = tmp_path / "w"
    argv = ["--meshes", "procedural:2", "--seed", "3", "--workdir", str(w), "--minutes", "0.15",
            "--config", "tiny", "--train-scenes", "2", "--test-scenes", "1", "--resolution",
            "96", "80", "--spp", "1", "--instances", "3", "--overlays", "1"]
    report = adapt.main(argv)

    # Three disjoint scene sets of the same parts: val and test are shards of one held-out set.
    scenes = {name: sorted(p.name for p in (w / "data" / name / f"{folder}_pbr").iterdir()
                           if p.is_dir())
              for name, folder in (("train", "train"), ("val", "val"), ("test", "val"))}
    assert scenes["val"] and scenes["test"] and not set(scenes["val"]) & set(scenes["test"])
    # The budget: the steps that fit 85% of the minutes at the measured step time.
    budget = json.loads((w / "adapt.json").read_text())
    assert budget["steps"] == max(adapt.NUM_EVALS, int(0.15 * 60 * (1 - adapt.EVAL_SHARE)
                                                       / budget["step_seconds"]))
    run = RunDir(w)
    assert run.checkpoint_steps()[-1] == budget["steps"]
    model, cfg, step = load_detector(w)  # an ordinary run directory
    assert cfg.variant == "tiny/16" and step in run.checkpoint_steps()

    assert set(report["test"]) == {"box_ap", "box_ap50", "box_f1", "box_f1_threshold",
                                   "pose_ap", "pose_ap_mssd", "pose_ap_mspd"}
    for value in (*report["test"].values(), *report["val"].values()):
        assert 0.0 <= value <= 1.0
    assert report["overlay_threshold"] == report["val"]["box_f1_threshold"]
    assert json.loads((w / "report.json").read_text())["steps"] == budget["steps"]
    overlays = sorted((w / "test" / "overlays").glob("*.png"))
    assert len(overlays) == 1 and cv2.imread(str(overlays[0])).shape[1] >= 640

    # Again: every stage is found done; training does not run another step.
    mtime = (w / "adapt.json").stat().st_mtime
    again = adapt.main(argv)
    assert (w / "adapt.json").stat().st_mtime == mtime
    assert run.checkpoint_steps()[-1] == budget["steps"]
    assert again["test"] == report["test"]
