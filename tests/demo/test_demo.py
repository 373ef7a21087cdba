"""``python -m demo``: what it passes to ``train.adapt`` and what it reports (the stages faked;
the real stages are tests/train/test_adapt.py's)."""

import json

import pytest

import demo.__main__ as demo
from train import adapt


def _figures(pose_ap: float, refined: bool) -> dict:
    figs = {"box_ap": 0.3, "box_ap50": 0.5, "box_f1": 0.4, "box_f1_threshold": 0.2,
            "pose_ap": pose_ap, "pose_ap_mm": pose_ap / 2, "pose_ap_mssd": pose_ap,
            "pose_ap_mspd": pose_ap, "segm_ap": 0.25}
    if refined:
        figs.update({f"{k}_initial": 0.1 for k in adapt.POSE_FIGURES})
    return figs


def test_demo_refines_both_settings_and_reports_before_and_after(tmp_path, monkeypatch,
                                                                 capsys):
    calls = {}

    import infer.shape_detect

    def shared():  # inside infer.shape_detect.shared_searches
        return infer.shape_detect._SHARED is not None

    def fake_main(argv):
        calls["adapt"] = argv
        calls["shared"] = [shared()]
        w = tmp_path / "out" / "adapted"
        w.mkdir(parents=True)
        return {"test": _figures(0.3, refined=True), "refiner": str(w / "refiner"),
                "overlays": str(w / "test" / "overlays")}

    def fake_test(workdir, data, out, cache, overlays, instances, refiner=None,
                  templates_score=None):
        calls[out.name] = (workdir, data, refiner, templates_score)
        calls["shared"].append(shared())
        calls.setdefault("cache", {})[out.name] = cache
        # A worse "after" than "before" is reported as it is.
        return {"test": _figures(0.05, refined=refiner is not None), "overlay_threshold": 0.2,
                "overlays": str(out / "test" / "overlays")}

    import infer.shipped

    models = {"detector": tmp_path / "models" / "d", "refiner": tmp_path / "models" / "r"}
    monkeypatch.setattr(infer.shipped, "shipped", models.get)
    monkeypatch.setattr(adapt, "main", fake_main)
    monkeypatch.setattr(adapt, "generate", lambda *a, **k: None)
    monkeypatch.setattr(adapt, "test", fake_test)

    def fake_calibrate(data, split, cache):
        calls["calibrate"] = data
        return {"parts": {"1": [0.0] * 9}}

    from train import cell_score

    monkeypatch.setattr(cell_score, "calibrate_cell", fake_calibrate)
    monkeypatch.setattr(demo, "write_captures", lambda data: calls.setdefault("captures", data))

    def fake_infer_bop(workdir, dataset, out, cache, max_detections, **options):
        calls["two_views"] = (workdir, dataset, cache, options)
        calls["shared"].append(shared())
        return "result"

    monkeypatch.setattr(adapt, "infer_bop", fake_infer_bop)
    monkeypatch.setattr(adapt, "figures", lambda result: _figures(0.05, refined=True))
    report = demo.main(["--out", str(tmp_path / "out")])

    argv = calls["adapt"]
    # The adapted, no-training, calibrated and two-view settings (the same images and parts)
    # share the templates detector's searches; the zero-shot setting (other parts) does not.
    assert calls["shared"] == [True, True, True, True, False] and not shared()
    assert float(argv[argv.index("--refiner-minutes") + 1]) == 0  # no 3PT-R by default
    assert argv[argv.index("--detector") + 1] == "cell"  # the dense cell detector
    assert argv[argv.index("--from") + 1] == "scratch"  # (3PT-D's, with --detector 3pt)
    # The zero-shot parts meet the shipped models, as a user who installs threept_jax does.
    assert calls["zero_shot"][:3:2] == (models["detector"], models["refiner"])
    # No training: the templates detector (no workdir) on the adapted setting's own scenes,
    # refined by the contour refiner; calibrated: the same, with the score fitted on the
    # adapted setting's training scenes (never its test scenes), written where train.adapt
    # writes its own (the faked adapt wrote none).
    data = tmp_path / "out" / "adapted" / "data"
    assert calls["no_training"] == (None, data, "contour", None)
    score_file = tmp_path / "out" / "adapted" / "templates_score.json"
    assert calls["calibrate"] == data / "train"
    assert calls["calibrated"] == (None, data, "contour", score_file)
    # Both read the parts' contour models the adapted setting's test wrote.
    cache = tmp_path / "out" / "adapted" / "cache"
    assert calls["cache"]["no_training"] == calls["cache"]["calibrated"] == cache
    assert json.loads(score_file.read_text()) == {"parts": {"1": [0.0] * 9}}
    # Two views: the templates detector (no workdir) on the same test scenes, grouped two
    # images a capture, refined by the contour refiner, the no-training setting's threshold.
    assert calls["captures"] == data / "test"
    workdir, dataset, cache_2v, options = calls["two_views"]
    assert (workdir, dataset, cache_2v) == (None, data / "test", cache)
    assert options["targets"] == "multiview" and options["refiner"] == "contour"
    assert options["overlay_threshold"] == 0.2  # no_training's val best-F1 threshold (faked)
    saved = json.loads((tmp_path / "out" / "report.json").read_text())
    for setting in ("adapted", "no_training", "calibrated", "two_views", "zero_shot"):
        assert saved[setting]["test"]["pose_ap_initial"] == pytest.approx(0.1)
        assert saved[setting]["test"]["pose_ap_mm_initial"] == pytest.approx(0.1)
    assert report["zero_shot"]["test"]["pose_ap"] == pytest.approx(0.05)
    out = capsys.readouterr().out.split("done in")[1]
    assert out.count("before refinement: 6D AP 0.100, AP-mm 0.100, segm AP 0.100") == 5
    assert "after refinement:  6D AP 0.300, AP-mm 0.150, segm AP 0.250" in out
    assert "after refinement:  6D AP 0.050, AP-mm 0.025, segm AP 0.250" in out


def test_without_a_trained_refiner_the_contour_refiner_refines(tmp_path, monkeypatch, capsys):
    """No 3PT-R ships and the adapted one is not used (it made held-out poses worse): both
    settings are refined by the training-free contour refiner, and the summary says why."""
    import infer.shipped

    monkeypatch.setattr(infer.shipped, "shipped", {"detector": tmp_path / "d"}.get)
    monkeypatch.setattr(adapt, "main", lambda argv: {
        "test": _figures(0.3, refined=True), "refiner": "contour", "overlays": "o",
        "refiner_trained": str(tmp_path / "adapted" / "refiner")})
    monkeypatch.setattr(adapt, "generate", lambda *a, **k: None)
    seen = []

    def fake_test(*a, refiner=None, **k):
        seen.append(refiner)
        return {"test": _figures(0.05, refined=refiner is not None), "overlays": "o",
                "overlay_threshold": 0.2}

    def fake_infer_bop(*a, refiner=None, **k):
        seen.append(refiner)

    monkeypatch.setattr(adapt, "test", fake_test)
    monkeypatch.setattr(adapt, "infer_bop", fake_infer_bop)
    monkeypatch.setattr(adapt, "figures", lambda result: _figures(0.05, refined=True))
    monkeypatch.setattr(demo, "write_captures", lambda data: None)
    from train import cell_score

    monkeypatch.setattr(cell_score, "calibrate_cell", lambda *a: {"parts": {}})
    demo.main(["--out", str(tmp_path)])
    assert seen == ["contour"] * 4  # no training, calibrated, two views, then zero-shot
    out = capsys.readouterr().out.split("done in")[1]
    assert out.count("before refinement: 6D AP 0.100") == 5
    assert "the trained refiner is not used (it does not make held-out poses better): the " \
           "contour refiner refines instead" in out


def test_write_captures_groups_each_scenes_images(tmp_path):
    """Every image of a scene in one group, read back as ``--targets multiview`` reads it."""
    from threept_jax.data import bop

    K = [500.0, 0, 320, 0, 500, 240, 0, 0, 1]
    for scene, images in ((4, (0, 1)), (7, (0, 1, 2))):
        folder = tmp_path / "val_pbr" / f"{scene:06d}"
        folder.mkdir(parents=True)
        (folder / "scene_camera.json").write_text(json.dumps({str(i): {
            "cam_K": K, "cam_R_w2c": [1, 0, 0, 0, 1, 0, 0, 0, 1], "cam_t_w2c": [0, 0, 0],
            "depth_scale": 1.0} for i in images}))
    demo.write_captures(tmp_path)
    assert json.loads((tmp_path / bop.MULTIVIEW_TARGETS_FILE).read_text()) == [
        {"scene_id": 4, "im_ids": [0, 1]}, {"scene_id": 7, "im_ids": [0, 1, 2]}]
    assert [t.views for t in bop.load_multiview_targets(tmp_path / bop.MULTIVIEW_TARGETS_FILE)
            ] == [((None, 0), (None, 1)), ((None, 0), (None, 1), (None, 2))]
