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
        return {"test": _figures(0.05, refined=refiner is not None),
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
    report = demo.main(["--out", str(tmp_path / "out")])

    argv = calls["adapt"]
    # The adapted, no-training and calibrated settings (the same images and parts) share the
    # templates detector's searches; the zero-shot setting (other parts) does not.
    assert calls["shared"] == [True, True, True, False] and not shared()
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
    saved = json.loads((tmp_path / "out" / "report.json").read_text())
    for setting in ("adapted", "no_training", "calibrated", "zero_shot"):
        assert saved[setting]["test"]["pose_ap_initial"] == pytest.approx(0.1)
        assert saved[setting]["test"]["pose_ap_mm_initial"] == pytest.approx(0.1)
    assert report["zero_shot"]["test"]["pose_ap"] == pytest.approx(0.05)
    out = capsys.readouterr().out.split("done in")[1]
    assert out.count("before refinement: 6D AP 0.100, AP-mm 0.100, segm AP 0.100") == 4
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
        return {"test": _figures(0.05, refined=refiner is not None), "overlays": "o"}

    monkeypatch.setattr(adapt, "test", fake_test)
    from train import cell_score

    monkeypatch.setattr(cell_score, "calibrate_cell", lambda *a: {"parts": {}})
    demo.main(["--out", str(tmp_path)])
    assert seen == ["contour"] * 3  # no training, calibrated, then zero-shot
    out = capsys.readouterr().out.split("done in")[1]
    assert out.count("before refinement: 6D AP 0.100") == 4
    assert "the trained refiner is not used (it does not make held-out poses better): the " \
           "contour refiner refines instead" in out
