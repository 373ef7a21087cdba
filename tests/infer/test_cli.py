"""The inference CLI's arguments: parsed into Cameras, bad ones named (``error: ...``, exit 2)
before any model is loaded; an image without detections says so on the console and overlay."""

import json

import cv2
import numpy as np
import pytest

from infer import cli
from infer.cli import build_parser, main
from infer.options import cameras_from_args
from infer.scene import Instances
from infer.visualize import caption_band_height
from tests.fixtures.cli import fails_naming


def _args(tmp_path, *extra):
    return build_parser().parse_args(["images", "--workdir", str(tmp_path), "--out",
                                      str(tmp_path / "out"), "--mesh", "1=a.ply",
                                      "--image", "a.png", *extra])


@pytest.fixture
def files(tmp_path):
    """A mesh file and two 64x48 images; load_models fails loudly if it is ever reached."""
    (tmp_path / "a.ply").write_text("ply\n")
    rng = np.random.default_rng(0)
    for name in ("a.png", "b.png"):
        cv2.imwrite(str(tmp_path / name), rng.integers(0, 256, (48, 64, 3), dtype=np.uint8))
    return tmp_path


def _images_argv(tmp_path, *extra):
    return ["images", "--workdir", str(tmp_path / "no_run"), "--out", str(tmp_path / "out"),
            "--mesh", f"1={tmp_path / 'a.ply'}", "--image", str(tmp_path / "a.png"), *extra]


def test_score_threshold_defaults_to_the_detectors_own(files, capsys, monkeypatch):
    """Without --score-threshold the command's detector sets it: 0.4 for the templates detector
    (a contour score), 0.1 for 3PT-D (``--workdir`` or ``--detector 3pt``); a given value
    stays."""
    seen = []

    def no_load(args, detector=True):
        seen.append(args.score_threshold)
        raise SystemExit(0)

    monkeypatch.setattr(cli, "load_models", no_load)
    plain = ["images", "--out", str(files / "out"), "--mesh", f"1={files / 'a.ply'}",
             "--image", str(files / "a.png"), "--K", "60,60,31.5,23.5"]
    for extra in ([], ["--detector", "3pt"], ["--workdir", str(files)],
                  ["--score-threshold", "0.25"]):
        with pytest.raises(SystemExit):
            main(plain + extra)
    assert seen == [0.4, 0.1, 0.1, 0.25]


def test_k_flags_and_camera_files_become_cameras(tmp_path):
    (cam,) = cameras_from_args(_args(tmp_path, "--K", "600,610,319.5,239.5"), 1)
    np.testing.assert_array_equal(cam.K, [[600, 0, 319.5], [0, 610, 239.5], [0, 0, 1]])
    assert cam.T_cam_world is None and cam.calibration_hw is None
    T = np.eye(4)
    T[:3, 3] = [10.0, -5.0, 700.0]
    path = tmp_path / "cams.json"
    path.write_text(json.dumps([{"K": cam.K.tolist(), "T_cam_world": T.tolist()}]))
    (rig,) = cameras_from_args(_args(tmp_path, "--cameras", str(path)), 1)
    np.testing.assert_array_equal(rig.T_cam_world, T)


def test_calibration_size_reaches_the_cameras_as_height_width(tmp_path):
    (cam,) = cameras_from_args(_args(tmp_path, "--K", "1000,1000,639.5,479.5", "--calibration-size",
                            "1280", "960"), 1)
    assert cam.calibration_hw == (960, 1280)
    path = tmp_path / "cams.json"
    path.write_text(json.dumps([{"K": cam.K.tolist(), "calibration_size": [1920, 1080]}]))
    (own,) = cameras_from_args(_args(tmp_path, "--cameras", str(path), "--calibration-size", "1280",
                            "960"), 1)
    assert own.calibration_hw == (1080, 1920)  # a camera's own entry wins


def test_run_scene_rescales_k_from_the_calibration_size():
    from infer.api import Camera, prepare_views

    image = np.zeros((480, 640, 3), np.uint8)
    cam = Camera(np.array([[1000.0, 0, 651.0], [0, 1000.0, 489.0], [0, 0, 1]]),
                 calibration_hw=(960, 1280))
    (K,), T = prepare_views([image], [cam])
    # Hand-derived: fx * 0.5, (c + 0.5) * 0.5 - 0.5.
    np.testing.assert_allclose(K, [[500, 0, 325.25], [0, 500, 244.25], [0, 0, 1]], atol=1e-12)
    assert T is None
    with pytest.raises(ValueError, match="camera 0 K.*outside the 640x480 image"):
        prepare_views([image], [Camera(cam.K)])


def test_bad_camera_arguments_name_the_problem(tmp_path):
    path = tmp_path / "cams.json"
    path.write_text(json.dumps([{"T_cam_world": np.eye(4).tolist()}]))
    with pytest.raises(ValueError, match='camera 0 has no "K"'):
        cameras_from_args(_args(tmp_path, "--cameras", str(path)), 1)
    with pytest.raises(ValueError, match="four numbers"):
        cameras_from_args(_args(tmp_path, "--K", "600,610,319.5"), 1)
    with pytest.raises(ValueError, match="one --K"):
        cameras_from_args(_args(tmp_path), 1)
    path.write_text("[{")
    with pytest.raises(ValueError, match="cams.json is not valid JSON"):
        cameras_from_args(_args(tmp_path, "--cameras", str(path)), 1)


def test_camera_with_a_bad_bottom_row_is_labelled_t_cam_world(tmp_path):
    from infer.api import Camera

    T = np.eye(4)
    T[3] = [0, 0, 1, 1]
    with pytest.raises(ValueError, match="T_cam_world") as e:
        Camera(np.array([[600.0, 0, 320], [0, 600, 240], [0, 0, 1]]), T_cam_world=T)
    assert "T_cam_obj" not in str(e.value)


@pytest.mark.parametrize("flag, value, match", [
    ("--num-scales", "0", "argument --num-scales: must be >= 1"),
    ("--score-threshold", "1.5", "argument --score-threshold: must be in [0, 1]"),
    ("--score-threshold", "nan", "argument --score-threshold: must be in [0, 1]"),
    ("--max-detections", "0", "argument --max-detections: must be >= 1"),
    ("--overlays", "-1", "argument --overlays: must be >= 0"),
    ("--step", "newest", "argument --step: must be best, latest or a step number"),
    ("--num-templates", "0", "argument --num-templates: must be >= 1"),
    ("--calibration-size", "0", "argument --calibration-size: must be >= 1"),
])
def test_bad_numeric_options_exit_2_naming_the_flag(files, capsys, flag, value, match):
    extra = [flag, value] + (["480"] if flag == "--calibration-size" else [])
    fails_naming(capsys, _images_argv(files, "--K", "60,60,31.5,23.5", *extra), match)


def test_bad_bop_options_exit_2_naming_the_flag(tmp_path, capsys):
    base = ["bop", "--workdir", str(tmp_path), "--out", str(tmp_path / "o"), "--dataset-dir",
            str(tmp_path)]
    fails_naming(capsys, base + ["--max-images", "0"], "argument --max-images: must be >= 1")
    fails_naming(capsys, base + ["--obj-ids", "-2"], "argument --obj-ids: must be >= 0")


def test_input_errors_exit_2_before_loading_models(files, capsys, monkeypatch):
    def no_load(args):
        raise AssertionError("models loaded before the inputs were checked")

    monkeypatch.setattr(cli, "load_models", no_load)
    argv = _images_argv(files, "--image", str(files / "b.png"), "--K", "60,60,31.5,23.5")
    fails_naming(capsys, argv, "error: 1 --K for 2 --image")
    cams = files / "cams.json"
    cams.write_text(json.dumps([{"T_cam_world": np.eye(4).tolist()}]))
    fails_naming(capsys, _images_argv(files, "--cameras", str(cams)), 'camera 0 has no "K"')
    T = np.eye(4)
    T[3] = [0, 0, 0, 2]
    K = [[60, 0, 31.5], [0, 60, 23.5], [0, 0, 1]]
    cams.write_text(json.dumps([{"K": K, "T_cam_world": T.tolist()}]))
    err = fails_naming(capsys, _images_argv(files, "--cameras", str(cams)),
                 "cams.json camera 0 T_cam_world")
    assert "T_cam_obj" not in err
    fails_naming(capsys, _images_argv(files, "--K", "60,60,31.5,23.5", "--mesh", "2=nowhere.ply"),
           "no mesh file nowhere.ply")
    # K of a 4x larger image: its principal point lies outside this one.
    fails_naming(capsys, _images_argv(files, "--K", "240,240,127.5,95.5"), "outside the 64x48 image")


def test_no_detections_are_reported_on_console_and_overlay(files, capsys, monkeypatch):
    class FakeModels:
        def onboard(self, meshes, units):
            return []

    monkeypatch.setattr(cli, "load_models", lambda args: FakeModels())
    monkeypatch.setattr(cli, "run_scene", lambda *a, **k: Instances([], best_score=0.0342))
    main(_images_argv(files, "--K", "60,60,31.5,23.5", "--score-threshold", "0.2"))
    assert "0 detections above threshold 0.2 (best score 0.034)" in capsys.readouterr().out
    image = cv2.imread(str(files / "a.png"))
    overlay = cv2.imread(str(files / "out" / "overlay_0_a.png"))
    # The 64 x 48 image is shown 10x enlarged (overlays are at least 640 px wide).
    image = cv2.resize(image, (640, 480), interpolation=cv2.INTER_LINEAR)
    assert overlay.shape == image.shape
    band = caption_band_height(image.shape[:2])
    assert np.any(overlay[:band] != image[:band])  # the caption
    np.testing.assert_array_equal(overlay[band:], image[band:])


def test_small_overlays_are_enlarged_with_their_boxes_and_contours():
    from infer.detect import Detection
    from infer.visualize import MIN_OVERLAY_WIDTH, draw_detections

    image = np.zeros((120, 160, 3), np.uint8)
    mask = np.zeros((120, 160), bool)
    mask[70:90, 100:130] = True
    det = Detection(3, np.array([10.0, 20.0, 50.0, 60.0]), 0.9, np.eye(4)[None], np.ones(1),
                    np.zeros(0))
    canvas = draw_detections(image, [det], [mask])
    assert canvas.shape == (480, 640, 3) and MIN_OVERLAY_WIDTH == 640
    lit = canvas.max(axis=2) > 0
    # The box's edges at 4x: x 40 and 200, y 80 and 240 (1 px lines).
    assert lit[150, 40] and lit[150, 200] and lit[80, 120] and lit[240, 120]
    assert not lit[150, 120]  # inside the box: untouched
    # The mask's contour at 4x: rows 280-359, columns 400-519.
    assert lit[320, 400] and lit[320, 519] and not lit[320, 460]
    assert not lit[320, 380] and not lit[320, 540]


def test_mesh_units_error_names_the_units_flag(files, capsys, monkeypatch):
    """A mesh in metres (a 0.1 m tetrahedron): the error names --units, not units='m'."""
    from threept_jax.render import load_mesh

    v = np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0, 0, 0.1]])
    lines = ["ply", "format ascii 1.0", "element vertex 4", "property float x",
             "property float y", "property float z", "element face 4",
             "property list uchar int vertex_indices", "end_header"]
    lines += [" ".join(map(str, row)) for row in v]
    lines += ["3 0 2 1", "3 0 1 3", "3 0 3 2", "3 1 2 3"]
    (files / "a.ply").write_text("\n".join(lines) + "\n")

    class MeshLoadingModels:  # the real mesh loader and its unit check; no network needed
        def onboard(self, meshes, units):
            return [load_mesh(path, units=units) for path in meshes.values()]

    monkeypatch.setattr(cli, "load_models", lambda args: MeshLoadingModels())
    err = fails_naming(capsys, _images_argv(files, "--K", "60,60,31.5,23.5"), "pass --units m")
    assert "units='m'" not in err and "a.ply" in err


def test_depth_range_reaches_the_detector_and_bad_ones_exit_2(files, capsys, monkeypatch):
    class FakeModels:
        def onboard(self, meshes, units):
            return []

    seen = {}

    def fake_run_scene(*args, **options):
        seen.update(options)
        return Instances([], best_score=0.0)

    monkeypatch.setattr(cli, "load_models", lambda args: FakeModels())
    monkeypatch.setattr(cli, "run_scene", fake_run_scene)
    main(_images_argv(files, "--K", "60,60,31.5,23.5", "--depth-range", "400", "900"))
    assert seen["depth_range"] == [400.0, 900.0] and "num_scales" not in seen
    argv = _images_argv(files, "--K", "60,60,31.5,23.5", "--depth-range")
    fails_naming(capsys, argv + ["0", "500"], "argument --depth-range: must be a finite number > 0")
    fails_naming(capsys, argv + ["900", "400"], "argument --depth-range: ZMIN must be <= ZMAX")


def test_depth_range_option_plans_one_scale_from_the_projected_diameters():
    """run_scene's ``depth_range`` option reaches the tiles: a 100 mm object at 500-800 mm
    through f = 600 px spans 75-120 px (diameter * f / z), one scale for the 512 px tile:
    sqrt(128 * 350 / (75 * 120)) = 2.2311 (hand-derived)."""
    from flax import nnx

    from infer.api import Models
    from infer.onboarding import OnboardedObject
    from threept_jax.models.configs import DetectorConfig
    from threept_jax.models.detector import Detector

    cfg = DetectorConfig(variant="tiny/16", image_size=512, render_size=32)
    obj = OnboardedObject(1, "o", None, 100.0, np.zeros((8, 3), np.float32),
                          np.zeros((cfg.num_prior_tokens, cfg.width), np.float32),
                          np.eye(4, cfg.embed_dim, dtype=np.float32),
                          np.tile(np.eye(3, dtype=np.float32), (4, 1, 1)),
                          np.eye(4, dtype=np.float32)[None], np.zeros(3, np.float32))
    models = Models(Detector(cfg, rngs=nnx.Rngs(0)), cfg, 0, onboarder=None)
    K = np.array([[600.0, 0, 319.5], [0, 600.0, 239.5], [0, 0, 1]])
    layout = models.scene_detector([obj], depth_range=(500.0, 800.0)).layout((480, 640), K)
    np.testing.assert_allclose(layout.scales, [2.2311], rtol=1e-4)
    unknown = models.scene_detector([obj]).layout((480, 640), K)
    assert len(unknown.scales) == 3
    with pytest.raises(ValueError, match="depth range"):
        models.scene_detector([obj], depth_range=(800.0, 500.0))
