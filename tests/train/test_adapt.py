"""``python -m train.adapt``: the whole adaptation command at toy size, run twice (resume)."""

import json
import pathlib

import cv2
import pytest

from infer import api
from infer.checkpoint import load_detector, load_refiner
from tests.fixtures.run_dirs import tiny_detector_run
from threept_jax.data.run_dir import RunDir
from train import adapt, stages


def test_bad_arguments_exit_2_naming_the_flag(tmp_path, capsys):
    for argv, match in (
        (["--minutes", "0"], "--minutes must be in"),
        (["--refiner-minutes", "-1"], "--refiner-minutes must be in"),
        (["--refiner-config", "huge"], "invalid choice: 'huge'"),
        (["--train-scenes", "0"], "--train-scenes must be >= 1"),
        (["--resolution", "32", "32"], "--resolution must be at least"),
        (["--from", str(tmp_path)], "is not a detector training run"),
    ):
        with pytest.raises(SystemExit) as e:
            adapt.main(["--meshes", "procedural:1", "--workdir", str(tmp_path / "w"), *argv])
        assert e.value.code == 2
        assert match in capsys.readouterr().err
    args = adapt.parse_args(["--meshes", "procedural:1", "--workdir", str(tmp_path), "--from",
                             "scratch"])
    assert args.refiner_minutes == 0 and args.refiner_config == "tiny"  # no refiner by default
    assert args.init_from is None


def test_from_defaults_to_the_shipped_detector(tmp_path, monkeypatch):
    import infer.shipped

    run = tiny_detector_run(tmp_path / "models" / "detector-x")
    monkeypatch.setattr(infer.shipped, "MODELS_DIR", tmp_path / "models")
    (tmp_path / "models" / "shipped.json").write_text('{"detector": "detector-x", "refiner": null}')
    args = adapt.parse_args(["--meshes", "procedural:1", "--workdir", str(tmp_path / "w")])
    assert args.init_from == run
    assert adapt.base_config(args, tmp_path / "records").init_from == str(run)


def test_corrupt_meshes_are_checked_before_any_work(tmp_path, capsys):
    """A truncated PLY: alone, the command refuses in one message naming the file and makes no
    workdir; beside a good mesh, it is skipped with one line that names it."""
    good = "/work/shared/meshes/bop/tless/models/obj_000018.ply"
    data = open(good, "rb").read()
    bad_dir, mixed_dir = tmp_path / "bad", tmp_path / "mixed"
    for d in (bad_dir, mixed_dir):
        d.mkdir()
        (d / "obj_000005.ply").write_bytes(data[:3000])  # header and part of the vertices
    (mixed_dir / "obj_000018.ply").write_bytes(data)
    work = tmp_path / "w"
    with pytest.raises(SystemExit, match=r"(?s)no usable mesh in --meshes.*obj_000005.ply"):
        adapt.main(["--meshes", str(bad_dir), "--workdir", str(work), "--from", "scratch"])
    assert not work.exists()
    args = adapt.parse_args(["--meshes", str(mixed_dir), "--workdir", str(work), "--from",
                             "scratch"])
    adapt.check_meshes(args)
    out = capsys.readouterr().out
    assert "skipping 1 of 2 meshes" in out and "obj_000005.ply" in out, out
    assert not work.exists()


def _summary(ap: float, initial: bool) -> dict:
    """An ``infer bop --evaluate`` summary (the interface of infer/bop_runner.py) whose every
    figure is ``ap`` plus a distinct offset, the initial files' ``ap + 0.5`` plus the same."""

    def files(base):
        pose = {"ap": base, "ap_mm": base + .01, "ap_mssd": base + .02, "ap_mspd": base + .03,
                "ar_mssd": 0.9, "per_object": {"1": 0.9}}
        det = {"bbox": {"ap": base + .04, "ap50": base + .05, "f1": base + .06,
                        "f1_threshold": base + .07},
               "segm": {"ap": base + .08, "ap50": 0.9}}
        return pose, det

    pose, det = files(ap)
    out = {"csv": "x.csv", "json": "x.json", "pose": pose, "detection": det}
    if initial:
        out["pose_initial"], out["detection_initial"] = files(ap + 0.5)
    return out


def test_figures_before_and_after_refinement():
    plain = adapt.figures(_summary(0.1, initial=False))
    assert plain == pytest.approx({
        "box_ap": .14, "box_ap50": .15, "box_f1": .16, "box_f1_threshold": .17,
        "pose_ap": .1, "pose_ap_mm": .11, "pose_ap_mssd": .12, "pose_ap_mspd": .13,
        "segm_ap": .18})
    assert adapt.summary_lines(plain) == [
        "object generation (no refiner): 6D AP 0.100, AP-mm 0.110, segm AP 0.180"]

    refined = adapt.figures(_summary(0.1, initial=True))
    # The boxes are the detector's (the initial file's); pose and masks after refinement come
    # from the final files, before refinement from the initial ones.
    assert refined == pytest.approx({
        "box_ap": .64, "box_ap50": .65, "box_f1": .66, "box_f1_threshold": .67,
        "pose_ap": .1, "pose_ap_mm": .11, "pose_ap_mssd": .12, "pose_ap_mspd": .13,
        "segm_ap": .18,
        "pose_ap_initial": .6, "pose_ap_mm_initial": .61, "pose_ap_mssd_initial": .62,
        "pose_ap_mspd_initial": .63, "segm_ap_initial": .68})
    # A worse "after" is printed as it is.
    assert adapt.summary_lines(refined) == [
        "before refinement: 6D AP 0.600, AP-mm 0.610, segm AP 0.680",
        "after refinement:  6D AP 0.100, AP-mm 0.110, segm AP 0.180"]


def test_test_stage_refines_the_test_scenes_only(tmp_path, monkeypatch):
    """The test stage calls the bop command's function with its options (no argument list)."""
    import infer.bop_runner

    calls = []

    def fake_run_bop(args):
        calls.append(args)
        return _summary(0.2, initial=str(args.refiner) != "none")

    monkeypatch.setattr(infer.bop_runner, "run_bop", fake_run_bop)
    report = adapt.test(tmp_path / "w", tmp_path / "data", tmp_path / "w", tmp_path / "cache",
                        overlays=2, instances=6, refiner=tmp_path / "w" / "refiner")
    (val, test) = calls
    # The val scenes choose the overlay threshold: boxes alone, no refiner (not a shipped one).
    assert str(val.refiner) == "none"
    assert test.refiner == tmp_path / "w" / "refiner"
    for args in (val, test):  # the detector's best checkpoint, every detection kept for AP
        assert args.workdir == tmp_path / "w" and args.step == "best" and args.evaluate
        assert args.score_threshold == 0.0 and args.split == "val_pbr"
    # Scenes of --instances 6 hold 3 to 9 instances (datagen's spread 0.5).
    assert val.max_detections == test.max_detections == 9
    assert test.overlay_threshold == pytest.approx(0.27)
    assert report["overlay_threshold"] == pytest.approx(0.27)  # the val run's box F1 threshold
    assert report["test"]["pose_ap_initial"] == pytest.approx(0.7)
    assert "pose_ap_initial" not in report["val"]


def test_bop_args_are_the_commands_defaults_with_the_options_given(tmp_path):
    """bop_args against the parser on the same flags; a misspelt option is refused."""
    from infer.cli import bop_args, build_parser

    got = bop_args(tmp_path / "d", tmp_path / "o", refiner=pathlib.Path("contour"),
                   score_threshold=0.25, obj_ids=[3, 1], max_detections=7)
    want = build_parser().parse_args(
        ["bop", "--dataset-dir", str(tmp_path / "d"), "--out", str(tmp_path / "o"),
         "--refiner", "contour", "--score-threshold", "0.25", "--obj-ids", "3", "1",
         "--max-detections", "7"])
    assert vars(got) == vars(want)
    # Without a threshold: the default detector's (templates: 0.4).
    assert bop_args(tmp_path / "d", tmp_path / "o").score_threshold == 0.4
    with pytest.raises(TypeError, match="max_detection"):
        bop_args(tmp_path / "d", tmp_path / "o", max_detection=3)


def small_refiner(args, records):
    """``--refiner-config tiny`` at the refiner tests' smallest settings (4 fake devices)."""
    c = REFINER_CONFIG(args, records)
    c.batch_size = 4
    c.data.update(num_hypotheses=3, max_symmetries=8)
    c.refine.update(num_matches=16, max_faces=256)
    c.optim.warmup_steps = 1
    c.eval.update(num_examples=4, batch_size=4, num_steps=1)
    c.checkpoint.async_save = False
    return c


REFINER_CONFIG = adapt.refiner_config
#: Step times in the test below: measuring them costs one more compilation of each model's step
#: (a minute on 2 cores); the measurement has its own test
#: (test_measure_step_seconds_times_the_configs_trainer).
STEP_SECONDS = {"detector": 0.2, "refiner": 0.5}


def test_measure_step_seconds_times_the_configs_trainer(monkeypatch):
    """The probe runs the trainer of ``config.trainer`` on a copy of the config without
    evaluations and times TIMED_STEPS steps after 3 untimed ones."""
    import train.trainers
    from train.configs.refiner import get_config

    seen = []

    class Probe:
        def __init__(self, config, workdir):
            seen.append((config.eval.every_steps, config.init_from))
            self.steps = 0

        def next_batch(self):
            return {}

        def train_step(self, batch):
            self.steps += 1
            return self.steps

        def close(self):
            seen.append(self.steps)

    monkeypatch.setattr(train.trainers, "RefinerTrainer", Probe)
    config = get_config("tiny")
    config.init_from = "/elsewhere"
    assert adapt.measure_step_seconds(config) > 0
    assert seen == [(0, ""), 3 + stages.TIMED_STEPS]
    assert config.eval.every_steps == 200 and config.init_from == "/elsewhere"  # a copy


def _mtimes(folder: pathlib.Path) -> dict:
    return {p: p.stat().st_mtime for p in folder.rglob("*") if p.is_file()}


def test_adapt_trains_tests_and_resumes_without_redoing_work(tmp_path, monkeypatch):
    """The 3PT-D adaptation with a trained refiner. Its test stage calls the bop command's
    function with the trained runs, recorded, not run: the inference of a 3PT-D run is
    tested by tests/infer/test_bop_runner.py and the shipped detector's guard, the test stage
    through the real command by the cell detector's test below."""
    import infer.bop_runner

    monkeypatch.setattr(adapt, "refiner_config", small_refiner)
    monkeypatch.setattr(adapt, "measure_step_seconds", lambda c: STEP_SECONDS[c.trainer])
    # One evaluation per run, at its end (the trainers' tests cover every evaluation; at
    # this module's unoptimised compilation a detector step takes about a second).
    monkeypatch.setattr(adapt, "NUM_EVALS", 1)
    bop_calls = []

    def run_bop(args):
        bop_calls.append(args)
        if args.overlays:
            (args.out / "overlays").mkdir(parents=True)
        return _summary(0.2, initial=str(args.refiner) != "none")

    monkeypatch.setattr(infer.bop_runner, "run_bop", run_bop)
    w = tmp_path / "w"
    argv = ["--meshes", "procedural:2", "--seed", "3", "--workdir", str(w), "--minutes", "0.03",
            "--config", "tiny", "--train-scenes", "4", "--test-scenes", "1", "--resolution",
            "96", "80", "--spp", "1", "--instances", "3", "--overlays", "1",
            "--refiner-minutes", "0.04", "--detector", "3pt", "--from", "scratch"]
    report = adapt.main(argv)

    # Three disjoint scene sets of the same parts: val and test are shards of one held-out set.
    scenes = {name: sorted(p.name for p in (w / "data" / name / f"{folder}_pbr").iterdir()
                           if p.is_dir())
              for name, folder in (("train", "train"), ("val", "val"), ("test", "val"))}
    assert scenes["val"] and scenes["test"] and not set(scenes["val"]) & set(scenes["test"])
    # The budgets: the steps that fit 85% of each model's minutes at its measured step time.
    budget = json.loads((w / "adapt.json").read_text())
    for name, minutes in (("detector", 0.03), ("refiner", 0.04)):
        entry = budget[name]
        assert entry["steps"] == max(adapt.NUM_EVALS, int(minutes * 60 * (1 - adapt.EVAL_SHARE)
                                                          / entry["step_seconds"]))
        assert entry["minutes"] == minutes and entry["config"] == "tiny"
    assert budget["detector"]["steps"] == 7  # int(0.03 * 51 / 0.2)
    assert budget["refiner"] == {"steps": 4, "step_seconds": STEP_SECONDS["refiner"],
                                 "minutes": 0.04, "config": "tiny"}  # int(0.04 * 51 / 0.5)
    run = RunDir(w)
    assert run.checkpoint_steps()[-1] == budget["detector"]["steps"]
    model, cfg, step = load_detector(w)  # an ordinary run directory
    assert cfg.variant == "tiny/16" and step in run.checkpoint_steps()
    assert cfg.stem == adapt.SCRATCH_STEM == "conv"  # from scratch: early convolutions
    # The refiner: an ordinary 3PT-R run on the same records, trained to its planned steps.
    refiner_run = RunDir(w / "refiner", model="refiner")
    assert (w / "refiner" / "refiner.json").exists()
    assert refiner_run.checkpoint_steps()[-1] == budget["refiner"]["steps"]
    assert refiner_run.read_config()["data_dir"] == str((w / "records").resolve())
    assert load_refiner(w / "refiner")[1].variant == "tiny/16"

    # Refined either way (the trained refiner, or the contour refiner when it does not help):
    # figures before and after refinement.
    refined = adapt.refiner_helps(report["refiner_heldout"])
    assert set(report["test"]) == {"box_ap", "box_ap50", "box_f1", "box_f1_threshold",
                                   *adapt.POSE_FIGURES,
                                   *(f"{k}_initial" for k in adapt.POSE_FIGURES)}
    assert set(report["val"]) == {"box_ap", "box_ap50", "box_f1", "box_f1_threshold",
                                  *adapt.POSE_FIGURES}
    assert report["overlay_threshold"] == report["val"]["box_f1_threshold"]
    saved = json.loads((w / "report.json").read_text())
    assert saved["steps"] == budget["detector"]["steps"]
    assert saved["refiner_steps"] == budget["refiner"]["steps"]
    # The refiner's held-out figures (train.eval_refiner on its val records) beside the AP; the
    # test uses the refiner only when they say it does not make poses worse.
    held = saved["refiner_heldout"]
    helps = held["ar_mssd_after"] > held["ar_mssd_before"]
    assert saved["refiner"] == (str(w / "refiner") if helps else "contour") and helps == refined
    assert saved["refiner_trained"] == str(w / "refiner")
    assert held["num_instances"] > 0 and held["step"] in refiner_run.checkpoint_steps()
    assert 0.0 <= held["ar_mssd_before"] <= 1.0 and 0.0 <= held["score_acc"] <= 1.0
    assert 0.0 <= held["match_within_2px_same_place"] <= 1.0  # the baseline beside the matching
    assert held["rot_deg_before"] > 0.0
    # The trained runs were tested: the detector's best checkpoint, refined by the refiner
    # chosen.
    (val, test), = [bop_calls]
    assert val.workdir == test.workdir == w and val.step == test.step == "best"
    assert str(val.refiner) == "none" and str(test.refiner) == saved["refiner"]
    assert test.dataset_dir == w / "data" / "test" and test.overlays == 1

    # Again: every stage is found done; neither training runs another step, and the test,
    # which tested these checkpoints with these options, is not run again.
    mtime = (w / "adapt.json").stat().st_mtime
    checkpoints = _mtimes(w / "refiner")
    again = adapt.main(argv)
    assert (w / "adapt.json").stat().st_mtime == mtime
    assert run.checkpoint_steps()[-1] == budget["detector"]["steps"]
    assert _mtimes(w / "refiner") == checkpoints and len(bop_calls) == 2
    assert again["test"] == report["test"] and again["val"] == report["val"]
    assert saved["test_inputs"] == {"scenes": {k: scenes[k] for k in ("val", "test")},
                                    "detector_step": run.best_step(), "refiner":
                                    saved["refiner"], "refiner_step": held["step"]
                                    if helps else None, "overlays": 1, "instances": 3,
                                    "templates_score": None}  # 3PT-D: no templates


def test_a_report_is_reused_only_for_the_checkpoints_and_options_it_tested(tmp_path):
    inputs = {"scenes": {"val": ["000000"], "test": ["000001"]}, "detector_step": 7,
              "refiner": "contour", "refiner_step": None, "overlays": 1, "instances": 3}
    path = tmp_path / "report.json"
    assert adapt.tested(path, inputs) is None  # no report yet
    figures = {"test": {"box_ap50": 0.5}, "val": {"box_ap50": 0.4}, "overlay_threshold": 0.2,
               "refiner": "contour", "overlays": str(tmp_path / "test" / "overlays")}
    path.write_text(json.dumps({**figures, "steps": 7, "test_inputs": inputs}))
    assert adapt.tested(path, inputs) is None  # its overlays are gone
    (tmp_path / "test" / "overlays").mkdir(parents=True)
    assert adapt.tested(path, inputs) == figures
    for key, other in (("scenes", {"val": ["000000"], "test": ["000001", "000003"]}),
                       ("detector_step", 5), ("refiner", "/r"), ("refiner_step", 3),
                       ("overlays", 0), ("instances", 8)):
        assert adapt.tested(path, {**inputs, key: other}) is None, key


def test_only_a_refiner_that_raises_held_out_recall_is_used():
    """refiner_helps: the MSSD recall after the refiner's steps against before, by hand; one
    that changes nothing (its steps all refused) gives way to the contour refiner."""
    assert not adapt.refiner_helps({"ar_mssd_before": 0.49, "ar_mssd_after": 0.49})
    assert adapt.refiner_helps({"ar_mssd_before": 0.30, "ar_mssd_after": 0.52})
    assert not adapt.refiner_helps({"ar_mssd_before": 0.49, "ar_mssd_after": 0.305})


def test_held_out_figures_of_a_run_saved_without_them_are_evaluated(tmp_path, monkeypatch):
    """A best checkpoint without the evaluation training saves with it (a run stopped between
    evaluations; here an untrained run written by hand) is evaluated then, at that step; the
    figures come back without the ``eval/`` prefix."""
    import train.eval_refiner
    from tests.fixtures.run_dirs import tiny_refiner_run

    run = tiny_refiner_run(tmp_path / "refiner")
    calls = []

    def evaluate_run(workdir, step="best"):
        calls.append((workdir, step))
        return {"eval/ar_mssd_after": 0.5, "eval/ar_mssd_before": 0.4, "step": step}

    monkeypatch.setattr(train.eval_refiner, "evaluate_run", evaluate_run)
    assert adapt.refiner_heldout(run) == {"ar_mssd_after": 0.5, "ar_mssd_before": 0.4, "step": 0}
    assert calls == [(run, 0)]


def test_adapt_trains_the_cell_detector_by_default_and_tests_it(tmp_path, monkeypatch):
    """The default adaptation: the dense cell detector trained to its deadline on records
    without banks, its run tested through the inference path (posed by the templates' fit,
    refined by the contour refiner), and found done when run again. Toy sizes: the trainer's
    network and the shape search shrunk."""
    import functools

    from threept_jax.data import dense_run
    from threept_jax.pipeline.shape_search import ShapeSearchSettings
    from train import cell_detector

    monkeypatch.setattr(cell_detector, "train", functools.partial(
        cell_detector.train, batch_size=2, width=8, depths=(1, 1, 1, 1), neck_width=16,
        image_size=(64, 96)))
    import infer.shape_detect

    small = ShapeSearchSettings(num_views=40, num_inplane=12, max_proposals=50, candidates=32)
    monkeypatch.setattr(api, "ShapeSearchSettings", lambda: small)
    monkeypatch.setattr(infer.shape_detect, "ShapeSearchSettings", lambda: small)  # calibration
    w = tmp_path / "w"
    argv = ["--meshes", "procedural:2", "--seed", "3", "--workdir", str(w), "--minutes", "0.01",
            "--train-scenes", "3", "--test-scenes", "1", "--resolution", "96", "80", "--spp",
            "1", "--instances", "3", "--overlays", "1"]
    report = adapt.main(argv)
    assert not (w / "records" / "banks").exists()  # the cell detector reads no bank
    # The test queries both parts, whether its one scene shows both or not.
    from threept_jax.data import bop

    for name in ("train", "val", "test"):
        assert sorted(bop.load_models_info(w / "data" / name / "models" / "models_info.json")
                      ) == [1, 2], name
    net, class_ids, info = dense_run.load(w / "cell")
    assert class_ids == [1, 2] and info["steps"] >= 21  # the plan comes after 20 timed steps
    assert [p["step"] for p in info["curve"]][-1] == info["steps"] and "val" in info["curve"][0]
    assert report["detector"] == "cell" and report["steps"] == info["steps"]
    assert report["refiner"] == "contour"
    for value in (*report["test"].values(), *report["val"].values()):
        assert 0.0 <= value <= 1.0
    assert report["test_inputs"]["detector_step"] == info["steps"]
    overlays = sorted((w / "test" / "overlays").glob("*.png"))
    assert len(overlays) == 1 and cv2.imread(str(overlays[0])).shape[1] >= 640
    # The templates' score calibrated on the training scenes: this toy cell (3 images) has too
    # few right and wrong candidates of either part to fit one (train.templates_score's
    # minimum), so the file holds no part (the shared score) and why; the test used it.
    score = w / adapt.SCORE_FILE
    calibration = json.loads(score.read_text())
    assert calibration["parts"] == {} and "no part had" in calibration["error"]
    assert report["test_inputs"]["templates_score"] == str(score)
    # Again: the finished training, the calibration and the test are found done.
    results, run, fitted = _mtimes(w / "test"), _mtimes(w / "cell"), score.stat().st_mtime
    again = adapt.main(argv)
    assert _mtimes(w / "test") == results and _mtimes(w / "cell") == run
    assert score.stat().st_mtime == fitted and again["test"] == report["test"]


def test_every_split_lists_the_parts_of_all_of_them(tmp_path):
    """share_models: a part that only another split's scenes show is copied into each split
    that lacks it (its files byte for byte, its models_info entry); a split without models
    (not generated) is left alone; run again, nothing changes."""
    from threept_jax.data import bop

    def info(k):
        return {"diameter": 10.0 * k, "min_x": -k, "min_y": -k, "min_z": -k, "size_x": 2 * k,
                "size_y": 2 * k, "size_z": 2 * k}

    splits = {"train": (1, 2), "val": (1, 3), "test": (1,)}
    for name, ids in splits.items():
        models = tmp_path / name / "models"
        models.mkdir(parents=True)
        (models / "models_info.json").write_text(json.dumps({str(k): info(k) for k in ids}))
        for k in ids:
            (models / f"obj_{k:06d}.ply").write_bytes(f"{name} mesh {k}".encode())
    (tmp_path / "train" / "models" / "obj_000002.png").write_bytes(b"texture 2")
    adapt.share_models(tmp_path, ("train", "val", "test", "other"))
    for name in splits:
        models = tmp_path / name / "models"
        got = bop.load_models_info(models / "models_info.json")
        assert sorted(got) == [1, 2, 3], name
        assert {k: got[k].to_json()["diameter"] for k in got} == {1: 10.0, 2: 20.0, 3: 30.0}
        own = splits[name]
        assert (models / "obj_000001.ply").read_bytes() == f"{name} mesh 1".encode()
        if 2 not in own:  # from train, the first split that has it, with its texture
            assert (models / "obj_000002.ply").read_bytes() == b"train mesh 2"
            assert (models / "obj_000002.png").read_bytes() == b"texture 2"
        if 3 not in own:
            assert (models / "obj_000003.ply").read_bytes() == b"val mesh 3"
    assert not (tmp_path / "other").exists()
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    adapt.share_models(tmp_path, ("train", "val", "test"))
    assert {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()} == before


def test_calibration_keeps_the_shared_score_only_for_a_cell_too_small(tmp_path, monkeypatch):
    """adapt.calibrate: too few candidates -> a file without parts, with the reason; a folder
    that is not a dataset is an error, not a silent fallback, and writes no file."""
    from train import cell_score

    def too_few(*a):
        raise cell_score.TooFewCandidates("no part had 10 right and 10 wrong candidates")

    monkeypatch.setattr(cell_score, "calibrate_cell", too_few)
    path = adapt.calibrate(tmp_path / "train", tmp_path / "small.json", tmp_path / "cache")
    saved = json.loads(path.read_text())
    assert saved["parts"] == {} and saved["error"].startswith("no part had 10")
    monkeypatch.undo()
    with pytest.raises(SystemExit, match="is not a BOP dataset"):
        adapt.calibrate(tmp_path / "nothing", tmp_path / "bad.json", tmp_path / "cache")
    assert not (tmp_path / "bad.json").exists()
