"""``python -m infer track`` with UNTRAINED tiny networks saved as run directories: one jsonl line
per frame, the first frame refined from ``--init``, re-detection under ``--min-score``, a track
that found nothing looks again, a latency summary that keeps cold frames apart, and bad input
named before any model is loaded (``error: ...``, exit 2).

Every run refines 3 or 4 instances in 64 x 96 frames: one instance bin, so one compiled
refinement loop (shared by the module's runs) and one compiled detector serve the module.
"""

import json

import cv2
import jax
import numpy as np
import pytest
import trimesh

import infer
from infer import api, track_cli
from infer.cli import main
from infer.scene import Instances
from tests.fixtures.cli import fails_naming
from tests.fixtures.poses import pose_z
from tests.fixtures.run_dirs import plumbing_scene_refiner, tiny_detector_run, tiny_refiner_run

K = "90,90,47.5,31.5"  # fx,fy,cx,cy of the 64 x 96 frames
HW = (64, 96)


INIT = [(1, pose_z(0, 0, 600)), (2, pose_z(-30, 0, 700)), (1, pose_z(30, 10, 650, 30))]


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    """Run dirs of an untrained detector and refiner, two box meshes, 3 frames, an init file,
    and the models each (detector, refiner) pair loads to, memoised: the module's runs share
    one compiled refinement loop."""
    root = tmp_path_factory.mktemp("track")
    tiny_refiner_run(root / "refiner")
    tiny_detector_run(root / "detector")
    trimesh.creation.box((80, 40, 20)).export(root / "plate.ply")
    trimesh.creation.box((30, 30, 90)).export(root / "post.ply")
    frames = root / "frames"
    frames.mkdir()
    rng = np.random.default_rng(0)
    for i in range(3):
        cv2.imwrite(str(frames / f"f{i}.png"), rng.integers(0, 256, (*HW, 3), dtype=np.uint8))
    init = root / "init.json"
    init.write_text(json.dumps([{"obj_id": o, "T_world_obj": T.tolist()} for o, T in INIT]))
    cache_dir = jax.config.jax_compilation_cache_dir
    # The loop runs 1 iteration on 2 hypotheses (a third of the default loop's compile time):
    # what is tested here is tracking around it, not the loop.
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(api, "SceneRefiner", plumbing_scene_refiner())
        yield {"root": root, "frames": frames, "init": init, "memo": {}}
    jax.config.update("jax_compilation_cache_dir", cache_dir)  # the CLI set it to ours


@pytest.fixture
def loads(env, monkeypatch):
    """The CLI's model loading, memoised per (detector run, refiner run) across the module."""
    real, memo = track_cli.load_models, env["memo"]

    def load(args, detector=True):
        key = (args.workdir if detector else None, str(args.refiner))
        if key not in memo:
            memo[key] = real(args, detector)
            if memo.get("refiners") is None:
                memo["refiners"] = memo[key]._scene_refiners
            # The same refiner run in every entry: one compiled loop for the module.
            memo[key]._scene_refiners = memo["refiners"]
        return memo[key]

    monkeypatch.setattr(track_cli, "load_models", load)
    return memo


def _argv(env, *extra, detector=False):
    root = env["root"]
    argv = ["track", "--refiner", str(root / "refiner"), "--out", str(root / "out"),
            "--cache-dir", str(root / "cache"), "--num-templates", "48",
            "--mesh", f"1={root / 'plate.ply'}", "--mesh", f"2={root / 'post.ply'}", *extra]
    if detector:
        argv += ["--workdir", str(root / "detector"), "--num-scales", "1",
                 "--score-threshold", "0", "--max-detections", "4"]
    return argv


def _lines(env):
    return [json.loads(s) for s in (env["root"] / "out" / "track.jsonl").read_text().splitlines()]


def test_three_frames_from_init_refine_each_from_the_previous_pose(env, loads, capsys):
    fresh = not loads  # the module's first run compiles the refinement loop on frame 0
    summary = main(_argv(env, "--frames", str(env["frames"]), "--K", K, "--init",
                         str(env["init"]), "--overlays", "2"))
    lines = _lines(env)
    assert [r["index"] for r in lines] == [0, 1, 2]
    assert [r["redetected"] for r in lines] == [False, False, False]
    assert [r["compiled"] for r in lines] == [fresh, False, False]
    assert all(r["latency_s"] > 0 for r in lines)
    # Frame 0 starts from --init; each later frame from the previous frame's refined pose.
    first = lines[0]["instances"]
    assert [x["obj_id"] for x in first] == [o for o, _ in INIT]
    for x, (_, T) in zip(first, INIT):
        np.testing.assert_allclose(x["T_world_obj_initial"], T, atol=1e-3)
    for prev, cur in zip(lines, lines[1:]):
        for a, b in zip(prev["instances"], cur["instances"]):
            np.testing.assert_allclose(b["T_world_obj_initial"], a["T_world_obj"], atol=1e-3)
            assert np.isfinite(b["score"])
    overlays = sorted(p.name for p in (env["root"] / "out").glob("overlay_*.png"))
    assert overlays == ["overlay_00000_v0.png", "overlay_00001_v0.png"]
    assert cv2.imread(str(env["root"] / "out" / overlays[0])).shape[1] >= 640
    assert summary["frames"] == 3 and summary["redetections"] == 0
    assert summary["warm"]["frames"] == 2 and summary["first_frame_s"] == lines[0]["latency_s"]
    assert summary["compiled"]["frames"] == 0  # frame 0 is reported apart on its own
    out = capsys.readouterr().out
    assert "3 frames, 0 re-detections" in out and "warm frames (2)" in out


def test_a_min_score_above_any_score_redetects_every_frame(env, loads, tmp_path):
    video = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10, HW[::-1])
    for f in sorted(env["frames"].iterdir()):
        writer.write(cv2.imread(str(f)))
    writer.release()
    summary = main(_argv(env, "--video", str(video), "--K", K, "--init", str(env["init"]),
                         "--min-score", "1e9", "--overlays", "0", detector=True))
    lines = _lines(env)
    assert [r["redetected"] for r in lines] == [True, True, True]
    assert summary["redetections"] == 3 and summary["warm"]["frames"] == 0
    for r in lines:
        assert 3 <= len(r["instances"]) <= 4  # the other test's bin: no new compilation
        for x in r["instances"]:  # after a detection the start is object generation's pose,
            # not --init's (the untrained refiner's updates are refused: the safety test)
            assert not any(np.allclose(x["T_world_obj_initial"], T, atol=1e-3) for _, T in INIT)


def test_a_track_that_found_nothing_detects_again(monkeypatch):
    """Without init, the first detection finds nothing: the next frames detect again (they
    used to refine an empty set for ever)."""
    calls = []

    def run_scene(images, *args, **kwargs):
        calls.append(len(images))
        return Instances([], -np.inf)

    monkeypatch.setattr(api, "run_scene", run_scene)
    models = infer.Models(detector=object(), config=None, step=None, onboarder=None)
    frames = [np.zeros((*HW, 3), np.uint8)] * 3
    got = list(infer.track(frames, [np.eye(3)], [], models))
    assert [f.redetected for f in got] == [True, True, True] and calls == [1, 1, 1]
    assert all(f.poses == [] for f in got)


def test_summary_keeps_cold_frames_apart():
    flags = [(5.0, False, True), (0.1, False, False), (0.3, False, False), (2.0, True, False),
             (0.2, False, False), (1.5, False, True)]
    records = [{"latency_s": t, "redetected": r, "compiled": c} for t, r, c in flags]
    s = track_cli.summarize(records)
    assert s["frames"] == 6 and s["redetections"] == 1 and s["first_frame_s"] == 5.0
    # Warm: 0.1, 0.3, 0.2 -> median 0.2; p90 by linear interpolation 0.2 + 0.8 * 0.1.
    assert s["warm"] == {"frames": 3, "median_s": pytest.approx(0.2), "p90_s": pytest.approx(0.28)}
    assert s["redetected"]["frames"] == 1 and s["redetected"]["median_s"] == 2.0
    assert s["compiled"]["frames"] == 1 and s["compiled"]["median_s"] == 1.5


def test_frames_are_read_in_natural_order(tmp_path):
    for name in ("f10.png", "f2.png", "f1.png", "notes.txt"):
        (tmp_path / name).write_bytes(b"")
    (files,) = track_cli.frame_files([tmp_path])
    assert [f.name for f in files] == ["f1.png", "f2.png", "f10.png"]


@pytest.fixture
def no_models(monkeypatch):
    def fail(args):
        raise AssertionError("bad input must be refused before the models are loaded")

    monkeypatch.setattr(track_cli, "load_models", fail)


def test_bad_input_is_named_before_loading(env, no_models, tmp_path, capsys):
    frames, init = str(env["frames"]), str(env["init"])
    short = tmp_path / "short"
    short.mkdir()
    cv2.imwrite(str(short / "a.png"), np.zeros((*HW, 3), np.uint8))
    fails_naming(capsys, _argv(env, "--frames", frames, str(short), "--K", K, "--K", K, "--init", init),
           "different numbers of images")
    bad_video = tmp_path / "clip.mp4"
    bad_video.write_text("not a video")
    fails_naming(capsys, _argv(env, "--video", str(bad_video), "--K", K, "--init", init),
           "OpenCV cannot open it")
    stray = tmp_path / "init.json"
    stray.write_text(json.dumps([{"obj_id": 7, "T_world_obj": np.eye(4).tolist()}]))
    fails_naming(capsys, _argv(env, "--frames", frames, "--K", K, "--init", str(stray)),
           "entry 0: object 7 has no mesh; add --mesh 7=PATH")
    scaled = tmp_path / "scaled.json"
    scaled.write_text(json.dumps([{"obj_id": 1, "T_world_obj": np.diag([2, 2, 2, 1]).tolist()}]))
    fails_naming(capsys, _argv(env, "--frames", frames, "--K", K, "--init", str(scaled)),
           "is not a rigid transform")
    no_refiner = _argv(env, "--frames", frames, "--K", K, "--init", init)
    no_refiner[2] = "none"
    fails_naming(capsys, no_refiner, "track refines every frame: drop --refiner none")
    fails_naming(capsys, _argv(env, "--frames", frames, frames, "--K", K, "--K", K, "--init", init),
           "2 views need each camera's pose")
    fails_naming(capsys, _argv(env, "--frames", frames, "--init", init), "0 --K for 1 view(s)")
    fails_naming(capsys, _argv(env, "--frames", str(tmp_path / "none"), "--K", K, "--init", init),
           "no such folder")
    fails_naming(capsys, _argv(env, "--frames", frames, "--K", "900,900,500,31.5", "--init", init),
           "outside the 96x64 image")


def test_a_mesh_in_metres_names_the_units_flag(env, monkeypatch, tmp_path, capsys):
    trimesh.creation.box((0.08, 0.04, 0.02)).export(tmp_path / "metres.ply")
    monkeypatch.setattr(track_cli, "load_models",
                        lambda args, detector: infer.Models(None, None, None, None))  # refiner only
    argv = _argv(env, "--frames", str(env["frames"]), "--K", K, "--init", str(env["init"]))
    argv[argv.index(f"1={env['root'] / 'plate.ply'}")] = f"1={tmp_path / 'metres.ply'}"
    fails_naming(capsys, argv, "it looks like metres: pass --units m to convert it to mm")
