"""``python -m infer bop`` picks its objects before any slow work: only the run's targets are
onboarded, a target without a mesh is named (id and expected file); an image without
detections says so. Models are faked: these tests stop where the networks would start."""

import json
import time

import cv2
import numpy as np
import pytest
import trimesh

from infer import bop_runner
from infer.cli import main
from infer.scene import Instance, Instances
from threept_jax.data import bop
from threept_jax.geometry.symmetry import Symmetries


class _Onboarding(Exception):
    """Raised by the fake models where onboarding would start."""


@pytest.fixture
def dataset(tmp_path):
    """models_info lists objects 1, 2, 3; only 1 and 2 have meshes; the BOP19 targets of the
    one test image are objects 1 and 2."""
    root = tmp_path / "ds"
    models = root / "models"
    models.mkdir(parents=True)
    info = {str(k): {"diameter": 100.0, "min_x": -10, "min_y": -10, "min_z": -10,
                     "size_x": 20, "size_y": 20, "size_z": 20} for k in (1, 2, 3)}
    (models / "models_info.json").write_text(json.dumps(info))
    for k in (1, 2):
        trimesh.creation.box((20, 20, 20)).export(models / f"obj_{k:06d}.ply")
    scene = root / "test" / "000001"
    (scene / "rgb").mkdir(parents=True)
    K = [60.0, 0, 31.5, 0, 60.0, 23.5, 0, 0, 1]
    (scene / "scene_camera.json").write_text(json.dumps({"0": {"cam_K": K}}))
    cv2.imwrite(str(scene / "rgb" / "000000.png"), np.full((48, 64, 3), 90, np.uint8))
    (root / "test_targets_bop19.json").write_text(json.dumps(
        [{"scene_id": 1, "im_id": 0, "obj_id": k, "inst_count": 1} for k in (1, 2)]))
    (root / "test_targets_bop24.json").write_text(json.dumps([{"scene_id": 1, "im_id": 0}]))
    return root


def _argv(root, *extra):
    return ["bop", "--workdir", str(root / "no_run"), "--out", str(root / "out"),
            "--dataset-dir", str(root), *extra]


@pytest.fixture
def onboarded(monkeypatch):
    """The meshes handed to onboarding ({} until it is reached)."""
    seen = {}

    class FakeNets:
        def onboard(self, meshes):
            seen.update(meshes)
            raise _Onboarding

    monkeypatch.setattr(bop_runner, "load_models", lambda args, detector=True: FakeNets())
    return seen


def test_only_target_objects_are_onboarded(dataset, onboarded):
    with pytest.raises(_Onboarding):
        main(_argv(dataset, "--targets", "bop19"))
    assert onboarded == {k: dataset / "models" / f"obj_{k:06d}.ply" for k in (1, 2)}
    onboarded.clear()
    with pytest.raises(_Onboarding):
        main(_argv(dataset, "--targets", "bop24", "--obj-ids", "2"))
    assert list(onboarded) == [2]


def test_a_target_without_mesh_is_named_before_models_load(dataset, onboarded, capsys):
    # BOP24 targets name images only, so every object of models_info.json is queried.
    with pytest.raises(SystemExit) as e:
        main(_argv(dataset, "--targets", "bop24"))
    err = capsys.readouterr().err
    assert e.value.code == 2
    assert "target objects [3]" in err and str(dataset / "models" / "obj_000003.ply") in err
    assert onboarded == {}
    with pytest.raises(SystemExit):
        main(_argv(dataset, "--targets", "bop24", "--obj-ids", "4"))
    assert "--obj-ids [4] are not in" in capsys.readouterr().err


def test_missing_mesh_message_names_the_file():
    model = bop.ObjectModel(7, 100.0, np.zeros(3), np.ones(3), Symmetries(), None)
    with pytest.raises(FileNotFoundError, match=r"object 7: mesh file obj_000007\.ply is missing"):
        model.vertices()


def test_images_without_detections_are_reported(dataset, monkeypatch, capsys):
    class FakeNets:
        refiner = None

        def onboard(self, meshes):
            return []

    monkeypatch.setattr(bop_runner, "load_models", lambda args, detector=True: FakeNets())
    monkeypatch.setattr(bop_runner, "run_scene",
                        lambda *a, **k: Instances([], best_score=0.0517))
    main(_argv(dataset, "--targets", "bop19"))
    out = capsys.readouterr().out
    assert "scene 1 image 0: 0 detections above threshold 0.1 (best score 0.052)" in out
    assert "1 of 1 images had 0 detections above threshold 0.1" in out
    overlay = cv2.imread(str(dataset / "out" / "overlays" / "000001_000000.png"))
    assert np.any(overlay != 90)  # the caption; the input is a flat grey


def test_bop19_targets_query_each_image_with_its_own_objects(dataset, monkeypatch):
    """Image 0's targets are objects 1 and 2, image 1's object 2 alone: each image is queried
    with its own (the BOP 6D localisation task); ``--obj-ids`` queries every image with all."""
    scene = dataset / "test" / "000001"
    cv2.imwrite(str(scene / "rgb" / "000001.png"), np.full((48, 64, 3), 90, np.uint8))
    cams = json.loads((scene / "scene_camera.json").read_text())
    (scene / "scene_camera.json").write_text(json.dumps({**cams, "1": cams["0"]}))
    (dataset / "test_targets_bop19.json").write_text(json.dumps(
        [{"scene_id": 1, "im_id": 0, "obj_id": k, "inst_count": 1} for k in (1, 2)]
        + [{"scene_id": 1, "im_id": 1, "obj_id": 2, "inst_count": 1}]))

    class FakeNets:
        refiner = None

        def onboard(self, meshes):
            return [type("Onboarded", (), {"obj_id": k})() for k in meshes]

    queried = []

    def fake_run_scene(images, cams, objects, nets, **kw):
        queried.append([o.obj_id for o in objects])
        return Instances([], best_score=0.0)

    monkeypatch.setattr(bop_runner, "load_models", lambda args, detector=True: FakeNets())
    monkeypatch.setattr(bop_runner, "run_scene", fake_run_scene)
    main(_argv(dataset, "--targets", "bop19"))
    assert queried == [[1, 2], [2]]
    queried.clear()
    main(_argv(dataset, "--targets", "bop19", "--obj-ids", "1", "2"))
    assert queried == [[1, 2], [1, 2]]


# --------------------------------------------------------------------------- through run_scene
# One module-scoped dataset and one pair of untrained tiny runs (detector, refiner): every test
# below refines 3 instances of objects {1, 2} in one 64 x 96 view, so one compiled refinement
# loop (one instance bin) serves the module.

H, W = 64, 96
K = np.array([[80.0, 0, 47.5], [0, 80.0, 31.5], [0, 0, 1]])
SIZES = {1: (80.0, 40.0, 20.0), 2: (30.0, 30.0, 90.0)}


def _rigid(R, t):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _look_at(centre, target):
    """T_cam_world of a camera at ``centre`` (world, mm) looking at ``target`` (OpenCV axes)."""
    z = np.asarray(target, float) - centre
    z /= np.linalg.norm(z)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])  # rows: camera axes in the world
    return _rigid(R, -R @ centre)


#: World -> camera of images 0-3: two captures of two views each (multi-view groups (0, 1) and
#: (2, 3)); the even views sit at the world origin.
RIG = [np.eye(4), _look_at(np.array([300.0, 0, 100]), [0, 0, 600])] * 2


@pytest.fixture(scope="module")
def bop_setup(tmp_path_factory):
    """(dataset root, detector run, refiner run, the runs loaded by infer.load).

    The refinement loop runs 1 iteration on 2 hypotheses (a third of the default loop's
    compile time): what is tested here is the runner around it, not the loop."""
    import infer
    from infer import api
    from tests.fixtures.run_dirs import plumbing_scene_refiner, tiny_detector_run, tiny_refiner_run

    root = tmp_path_factory.mktemp("bop") / "ds"
    models = root / "models"
    models.mkdir(parents=True)
    info = {}
    for k, size in SIZES.items():
        trimesh.creation.box(size).export(models / f"obj_{k:06d}.ply")
        info[str(k)] = {"diameter": float(np.linalg.norm(size)),
                        **{f"min_{a}": -s / 2 for a, s in zip("xyz", size)},
                        **{f"size_{a}": s for a, s in zip("xyz", size)}}
    info["3"] = dict(info["1"])  # listed, no mesh
    (models / "models_info.json").write_text(json.dumps(info))
    rng = np.random.default_rng(0)
    T_world_gt = _rigid(np.eye(3), [0.0, 0.0, 600.0])
    with bop.BopSceneWriter(root / "test" / "000001") as writer:
        for im_id, T_cw in enumerate(RIG):
            mask = np.zeros((1, H, W), bool)
            mask[0, 20:44, 30:66] = True
            writer.add_image(im_id, bop.Camera(K, T_cam_world=T_cw),
                             rng.integers(0, 256, (H, W, 3), dtype=np.uint8),
                             [bop.GtInstance(1, T_cw @ T_world_gt)], mask, mask)
    (root / "test_targets_multiview_bop25.json").write_text(json.dumps(
        [{"scene_id": 1, "im_ids": [0, 1]}, {"scene_id": 1, "im_ids": [2, 3]}]))
    runs = tmp_path_factory.mktemp("runs")
    detector, refiner = tiny_detector_run(runs / "detector"), tiny_refiner_run(runs / "refiner")
    cache = tmp_path_factory.mktemp("cache")
    loaded = infer.load(detector, refiner=refiner, cache_dir=cache, num_templates=48)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(api, "SceneRefiner", plumbing_scene_refiner())
        yield root, detector, refiner, loaded


def _run_argv(setup, out, *extra):
    root, detector, refiner, _ = setup
    return ["bop", "--workdir", str(detector), "--refiner", str(refiner), "--dataset-dir",
            str(root), "--out", str(out), "--num-scales", "1", "--score-threshold", "0",
            "--max-detections", "3", "--num-templates", "48", "--overlays", "1", "--obj-ids",
            "1", "2", *extra]


def _by_image(rows):
    out = {}
    for r in rows:
        out.setdefault((r.scene_id, r.im_id), []).append(r)
    return out


def test_load_models_passes_the_refiner_run(monkeypatch, tmp_path):
    from infer import cli, options
    from infer.api import Models

    seen = {}

    def fake_load(*a, **k):
        seen.clear()
        seen.update(args=a, **k)
        return Models(None, None, None, None)

    monkeypatch.setattr(options, "load", fake_load)
    args = cli.build_parser().parse_args(
        ["bop", "--workdir", "d", "--refiner", "r", "--refiner-step", "7", "--dataset-dir", "x",
         "--out", "o", "--cache-dir", str(tmp_path)])
    options.load_models(args)
    assert tuple(map(str, seen["args"])) == ("d", "best") and str(seen["refiner"]) == "r"
    assert seen["refiner_step"] == 7 and seen["detector"] == "3pt"  # a run is 3PT-D
    # Without --workdir / --refiner: the templates detector (no network), and the contour
    # refiner while no 3PT-R ships; a shipped 3PT-R when one does; --refiner none: no refiner;
    # --detector 3pt: the shipped detector.
    import infer.shipped

    shipped = {"detector": tmp_path / "models" / "d", "refiner": None}
    monkeypatch.setattr(options, "shipped", shipped.get)
    monkeypatch.setattr(infer.shipped, "shipped", shipped.get)
    bare = ["bop", "--dataset-dir", "x", "--out", "o"]
    options.load_models(cli.build_parser().parse_args(bare))
    assert seen["args"] == (None, "best") and seen["detector"] == "templates"
    assert seen["refiner"] == "contour"
    options.load_models(cli.build_parser().parse_args(bare + ["--detector", "3pt"]))
    assert seen["args"] == (shipped["detector"], "best") and seen["detector"] == "3pt"
    shipped["refiner"] = tmp_path / "models" / "r"
    options.load_models(cli.build_parser().parse_args(bare))
    assert seen["refiner"] == shipped["refiner"]
    assert options.load_models(cli.build_parser().parse_args(
        bare + ["--refiner", "none"])).refiner is None
    assert seen["refiner"] is None


def test_single_view_run_writes_refined_and_initial_results(bop_setup, tmp_path, monkeypatch,
                                                            capsys):
    import infer

    root, _, _, models = bop_setup
    assert models.refiner is not None and models.refine_settings.num_matches == 16
    calls = []

    def spy(*args, **kwargs):
        start = time.perf_counter()
        found = infer.run_scene(*args, **kwargs)
        calls.append((args[0], found, time.perf_counter() - start))
        return found

    monkeypatch.setattr(bop_runner, "load_models", lambda args, detector=True: models)
    monkeypatch.setattr(bop_runner, "run_scene", spy)
    summary = main(_run_argv(bop_setup, tmp_path, "--targets", "all", "--max-images", "2",
                             "--evaluate"))
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["overlays", "threept-initial_ds-test.csv", "threept-initial_ds-test.json",
                     "threept_ds-test.csv", "threept_ds-test.json", "threept_ds-test_scores.json"]
    final = _by_image(bop.read_pose_results(tmp_path / "threept_ds-test.csv"))
    initial = _by_image(bop.read_pose_results(tmp_path / "threept-initial_ds-test.csv"))
    final2d = _by_image(bop.read_detection_results(tmp_path / "threept_ds-test.json"))
    initial2d = _by_image(bop.read_detection_results(tmp_path / "threept-initial_ds-test.json"))
    assert sorted(final) == sorted(initial) == [(1, 0), (1, 1)] and len(calls) == 2
    objects = models.onboard({k: root / "models" / f"obj_{k:06d}.ply" for k in SIZES})
    times = []
    moved = 0.0
    for (images, found, inner), key in zip(calls, [(1, 0), (1, 1)]):
        assert len(found) == 3  # --max-detections 3 at --score-threshold 0
        plain = infer.run_scene(images, [K], objects, models, refine=False, num_scales=1,
                                score_threshold=0.0, max_detections=3)
        rows, before = final[key], initial[key]
        for x, p, r, b, d, d0 in zip(found, plain, rows, before, final2d[key], initial2d[key]):
            # Final: the refined pose and the refiner's mask; initial: object generation's
            # pose and silhouette, as a run without the refiner gives them.
            assert r.obj_id == b.obj_id == x.obj_id == p.obj_id
            assert r.score == pytest.approx(x.score) and b.score == pytest.approx(p.score)
            np.testing.assert_allclose(r.T_cam_obj, x.T_world_obj, atol=1e-4)
            np.testing.assert_allclose(b.T_cam_obj, p.T_world_obj, atol=1e-4)
            moved = max(moved, np.abs(r.T_cam_obj - b.T_cam_obj).max())
            np.testing.assert_array_equal(bop.rle_to_mask(d.segmentation), x.masks[0])
            np.testing.assert_array_equal(bop.rle_to_mask(d0.segmentation), p.masks[0])
            # The refined box: amodal as the ground truth's, the part's 8 corners projected at
            # the refined pose (pixel edges), clipped to the image; not the visible mask's.
            assert d.bbox == pytest.approx(_amodal_xywh(x.obj_id, x.T_world_obj, K), abs=1e-3)
            box = np.clip(p.boxes[0], 0, [W, H, W, H])  # the initial box: the detection's
            assert d0.bbox == pytest.approx((*box[:2], *(box[2:] - box[:2])), abs=1e-4)
        # One time per image, on every row of both files: its run_scene call's wall time.
        assert len({r.time for r in rows + before + final2d[key] + initial2d[key]}) == 1
        assert rows[0].time >= inner
        times.append(rows[0].time)
    assert moved > 1e-3 and times[0] != times[1]
    for key in ("pose", "detection", "pose_initial", "detection_initial"):
        assert key in summary
    assert {"ap", "ap_mssd", "ap_mspd"} <= set(summary["pose"])
    assert {"bbox", "segm"} <= set(summary["detection_initial"])
    # Every score in the file, per object too; the console's table has the headline ones.
    written = json.loads((tmp_path / "threept_ds-test_scores.json").read_text())
    assert written == json.loads(json.dumps({k: summary[k] for k in (
        "pose", "detection", "pose_initial", "detection_initial")}))
    out = capsys.readouterr().out
    assert f"refined              {summary['pose']['ap']:.3f}" in out
    assert f"before refinement    {summary['pose_initial']['ap']:.3f}" in out


def test_score_lines_by_hand():
    """The console's table of a hand-made summary: one row per result file, the 2D columns
    a file without detections lacks as dashes."""
    from infer.bop_runner import score_lines

    pose = dict(ap=0.5, ap_mssd=0.25, ap_mspd=0.75, ap_mm=0.125, num_gt=7)
    box = dict(ap=0.3, ap50=0.6, f1=0.8, f1_threshold=0.45)
    lines = score_lines({"pose": pose, "detection": {"bbox": box},
                         "pose_initial": dict(pose, ap=0.375)})
    assert lines == [
        "BOP scores (7 ground-truth instances):",
        "                       6D AP    MSSD    MSPD   AP-mm  box AP    AP50 mask AP    AP50",
        "  refined              0.500   0.250   0.750   0.125   0.300   0.600       -       -",
        "  before refinement    0.375   0.250   0.750   0.125       -       -       -       -",
        "  box: best F1 0.800 at score 0.450"]
    assert score_lines({"pose": pose})[2].startswith("  results              0.500")


def _project(T_cam_world, p_world):
    p = T_cam_world[:3, :3] @ p_world + T_cam_world[:3, 3]
    u, v = (K @ p)[:2] / p[2]
    return p[2] > 0 and -0.5 <= u < W - 0.5 and -0.5 <= v < H - 0.5


def _amodal_xywh(obj_id, T_cam_obj, K):
    """COCO xywh of a SIZES box's 8 corners projected at T_cam_obj (float64; pixel centres at
    integers, so edges half a pixel out), clipped to the image."""
    half = np.array(SIZES[obj_id]) / 2
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * half
    T = np.asarray(T_cam_obj, np.float64)
    X = corners @ T[:3, :3].T + T[:3, 3]
    uv = X[:, :2] / X[:, 2:] * np.diag(K)[:2] + K[:2, 2] + 0.5
    x0, y0 = np.clip(uv.min(0), 0, [W, H])
    x1, y1 = np.clip(uv.max(0), 0, [W, H])
    return x0, y0, x1 - x0, y1 - y0


def test_multiview_run_writes_each_view_in_its_camera_frame(bop_setup, tmp_path, monkeypatch):
    """Groups (0, 1) and (2, 3) each make one run_scene call with the rig's cameras; a fixed
    scene stands in for detection: instance 1 (object 1 at the rig's focus) lies in both views,
    instance 2 (object 2, far left) in the even views only; its refined mask is empty there."""
    from scipy.spatial.transform import Rotation

    _, _, _, models = bop_setup
    T_a = _rigid(Rotation.from_euler("xyz", [20, -30, 50], degrees=True).as_matrix(),
                 [0.0, 0.0, 600.0])
    T_b = _rigid(Rotation.from_euler("xyz", [-10, 60, 5], degrees=True).as_matrix(),
                 [-150.0, 0.0, 300.0])
    assert _project(RIG[0], T_a[:3, 3]) and _project(RIG[1], T_a[:3, 3])
    assert _project(RIG[0], T_b[:3, 3]) and not _project(RIG[1], T_b[:3, 3])
    nudge = _rigid(np.eye(3), [4.0, -3.0, 10.0])  # object generation's pose, before refining
    full = np.zeros((H, W), bool)
    full[10:30, 40:70] = True
    calls = []

    def fake_run_scene(images, cameras, objects, nets, **options):
        calls.append(cameras)
        a = Instance(1, 0.9, T_a.astype(np.float32), T_a[None], np.ones(1),
                     {0: np.array([38.0, 8.0, 72.0, 33.0]), 1: np.array([-5.0, 2.0, 40, 30])},
                     {0: full.copy(), 1: full.copy()}, (nudge @ T_a).astype(np.float32), 1.5)
        b = Instance(2, 0.4, T_b.astype(np.float32), T_b[None], np.ones(1),
                     {0: np.array([1.0, 10.0, 30.0, 50.0])},
                     {0: np.zeros((H, W), bool), 1: full.copy()},
                     (nudge @ T_b).astype(np.float32), -2.0)
        return Instances([a, b], best_score=0.9)

    monkeypatch.setattr(bop_runner, "load_models", lambda args, detector=True: models)
    monkeypatch.setattr(bop_runner, "run_scene", fake_run_scene)
    summary = main(_run_argv(bop_setup, tmp_path, "--targets", "multiview", "--evaluate"))
    assert len(calls) == 2
    for cams, ids in zip(calls, [(0, 1), (2, 3)]):
        for cam, im_id in zip(cams, ids):
            np.testing.assert_allclose(cam.K, K)
            np.testing.assert_allclose(cam.T_cam_world, RIG[im_id], atol=1e-12)
    for stem, world in (("threept", {1: T_a, 2: T_b}),
                        ("threept-initial", {1: nudge @ T_a, 2: nudge @ T_b})):
        rows = _by_image(bop.read_pose_results(tmp_path / f"{stem}_ds-test.csv"))
        dets = _by_image(bop.read_detection_results(tmp_path / f"{stem}_ds-test.json"))
        assert sorted(rows) == [(1, 0), (1, 1), (1, 2), (1, 3)]
        for (_, im_id), got in rows.items():
            assert [r.obj_id for r in got] == ([1, 2] if im_id % 2 == 0 else [1])
            assert len({r.time for r in got + rows[(1, im_id ^ 1)]}) == 1  # the group's time
            for r in got:  # float64 reference: world -> this view's camera
                want = RIG[im_id] @ np.float32(world[r.obj_id]).astype(np.float64)
                np.testing.assert_allclose(r.T_cam_obj, want, atol=1e-9)
                assert r.score == pytest.approx({1: 0.9, 2: 0.4}[r.obj_id])
        if stem == "threept":
            # Refined boxes: the part projected at its pose in that view (amodal), whatever
            # its mask (b's is empty in view 0: its row and pose stay, for 6D).
            a0, b0 = dets[(1, 0)]
            assert a0.bbox == pytest.approx(_amodal_xywh(1, RIG[0] @ T_a, K), abs=1e-3)
            assert b0.bbox == pytest.approx(_amodal_xywh(2, RIG[0] @ T_b, K), abs=1e-3)
            assert not bop.rle_to_mask(b0.segmentation).any()
            (a1,) = dets[(1, 1)]
            assert a1.bbox == pytest.approx(_amodal_xywh(1, RIG[1] @ T_a, K), abs=1e-3)
    targets = tmp_path / "test_targets_multiview-views_ds-test.json"
    assert [(t.scene_id, t.im_id) for t in bop.load_targets(targets)] == [
        (1, 0), (1, 1), (1, 2), (1, 3)]
    assert {"pose", "detection", "pose_initial", "detection_initial"} <= set(summary)


def _csv_row(scene_id, im_id, obj_id, score, T, time_s):
    R = " ".join(repr(float(v)) for v in T[:3, :3].ravel())
    t = " ".join(repr(float(v)) for v in T[:3, 3])
    return f"{scene_id},{im_id},{obj_id},{score},{R},{t},{time_s}"


def test_refine_only_refines_every_row_keeping_scores_and_adding_time(bop_setup, tmp_path,
                                                                       monkeypatch):
    from scipy.spatial.transform import Rotation

    import infer

    root, _, refiner, models = bop_setup
    rot = Rotation.from_euler("xyz", [[10, 20, 30], [80, -5, 0], [0, 0, 120]],
                              degrees=True).as_matrix()
    given = {(0, 1, 0.8): _rigid(rot[0], [-20.0, 5.0, 600.0]),
             (0, 2, 0.6): _rigid(rot[1], [25.0, -10.0, 650.0]),
             (0, 1, 0.3): _rigid(rot[2], [0.0, 15.0, 550.0]),
             (1, 2, 0.7): _rigid(rot[2], [10.0, 0.0, 620.0]),
             (1, 1, 0.5): _rigid(rot[0], [-30.0, -5.0, 700.0]),
             (1, 2, 0.2): _rigid(rot[1], [20.0, 10.0, 580.0])}
    # Not sorted by score within an image: the output is, best first.
    order = [(0, 1, 0.3), (0, 1, 0.8), (0, 2, 0.6), (1, 2, 0.2), (1, 2, 0.7), (1, 1, 0.5)]
    times = {0: 0.25, 1: -1}
    path = tmp_path / "other_ds-test.csv"
    path.write_text("scene_id,im_id,obj_id,score,R,t,time\n" + "\n".join(
        _csv_row(1, k[0], k[1], k[2], given[k], times[k[0]]) for k in order) + "\n")
    calls = []

    def spy(images, cameras, objects, initial_poses, nets):
        start = time.perf_counter()
        out = infer.refine(images, cameras, objects, initial_poses, nets)
        calls.append((initial_poses, out, time.perf_counter() - start))
        return out

    monkeypatch.setattr(bop_runner, "load_models", lambda args, detector=True: models)
    monkeypatch.setattr(bop_runner, "refine", spy)
    out = tmp_path / "out"
    summary = main(["bop", "--refine-only", str(path), "--refiner", str(refiner),
                    "--dataset-dir", str(root), "--out", str(out), "--overlays", "1",
                    "--evaluate"])  # no targets file: the evaluator's ground-truth images
    assert {"pose", "detection", "pose_initial"} <= set(summary)  # pose_initial: the input's
    rows = _by_image(bop.read_pose_results(out / "other-3ptr_ds-test.csv"))
    dets = _by_image(bop.read_detection_results(out / "other-3ptr_ds-test.json"))
    assert sorted(rows) == [(1, 0), (1, 1)] and len(calls) == 2
    for (im_id, want_time), (initial_poses, refined, inner) in zip(times.items(), calls):
        got, got2d = rows[(1, im_id)], dets[(1, im_id)]
        keys = sorted((k for k in given if k[0] == im_id), key=lambda k: -k[2])
        assert [(r.obj_id, r.score) for r in got] == [(k[1], k[2]) for k in keys]
        for k, (obj_id, T0), r, d, x in zip(keys, initial_poses, got, got2d, refined):
            assert obj_id == k[1]  # every estimate refined, from its own pose
            np.testing.assert_allclose(T0, given[k], atol=1e-12)
            np.testing.assert_allclose(x.history[0], given[k], atol=1e-3)
            np.testing.assert_allclose(r.T_cam_obj, x.T_world_obj, atol=1e-9)
            assert len(x.history) == 3  # the loop ran: the start, 1 iteration, the pose kept
            np.testing.assert_array_equal(bop.rle_to_mask(d.segmentation), x.masks[0])
        assert sum(x.masks[0].astype(int) for x in refined).max() <= 1  # pixels to one each
        assert len({r.time for r in got + got2d}) == 1
        if want_time < 0:
            assert got[0].time == -1  # unknown stays unknown
        else:
            assert got[0].time >= want_time + inner


def test_refine_only_input_errors_exit_2_naming_the_file(dataset, monkeypatch, capsys):
    def no_load(args, detector=True):
        raise AssertionError("models loaded before the inputs were checked")

    monkeypatch.setattr(bop_runner, "load_models", no_load)
    csv = dataset / "m_ds-test.csv"
    base = ["bop", "--refiner", str(dataset / "ref"), "--dataset-dir", str(dataset), "--out",
            str(dataset / "out"), "--refine-only", str(csv)]

    def fails(argv, *parts):
        with pytest.raises(SystemExit) as e:
            main(argv)
        err = capsys.readouterr().err
        assert e.value.code == 2 and "Traceback" not in err, err
        for part in parts:
            assert part in err, err

    fails(base, "error:", str(csv), "does not exist")
    csv.write_text("1,0,1,0.5,not numbers\n")
    fails(base, "error:", f"{csv}:1")
    T = _rigid(np.eye(3), [0.0, 0.0, 500.0])
    csv.write_text(_csv_row(1, 0, 3, 0.5, T, 0.1) + "\n")
    fails(base, "error:", str(csv), "objects [3] without a mesh",
          str(dataset / "models" / "obj_000003.ply"))
    csv.write_text(_csv_row(1, 0, 1, 0.5, T, 0.1) + "\n" + _csv_row(1, 5, 2, 0.5, T, 0.1) + "\n")
    fails(base, "error:", str(csv), "scene 1 image 5")
    csv.write_text(_csv_row(2, 0, 1, 0.5, T, 0.1) + "\n")
    fails(base, "error:", str(csv), "scene 2 image 0")
    # The options: --refine-only needs a refiner (the default one unless --refiner none) and
    # no detector.
    fails([a if a != str(dataset / "ref") else "none" for a in base],
          "--refine-only refines with a refiner: drop --refiner none")
    fails(base + ["--workdir", str(dataset)], "drop --workdir")


def test_a_pose_score_ranks_the_6d_row_and_the_box_score_the_2d_row(tmp_path):
    """Results.add: the 6D row (the CSV) carries the pose score where one is given, the 2D
    row (the JSON) the detection score; without one both carry the detection score. Read
    back by the BOP readers."""
    results = bop_runner.Results()
    mask = np.zeros((4, 6), bool)
    mask[1:3, 2:5] = True
    results.add(1, 0, 7, 0.9, np.eye(4), mask, [2, 1, 5, 3], 0.5, pose_score=0.25)
    results.add(1, 0, 8, 0.6, np.eye(4), mask, [2, 1, 5, 3], 0.5)
    csv_path, json_path = results.write(tmp_path, "x_ds-test")
    poses, boxes = bop.read_pose_results(csv_path), bop.read_detection_results(json_path)
    assert [(p.obj_id, p.score) for p in poses] == [(7, 0.25), (8, 0.6)]
    assert [(d.obj_id, d.score) for d in boxes] == [(7, 0.9), (8, 0.6)]


def test_an_overlay_with_nothing_above_its_threshold_says_so(tmp_path, monkeypatch):
    """``_draw`` with every instance under the threshold: no box drawn, and the caption gives
    the threshold and the best score (the string by hand); the file is written."""
    import types

    import infer.visualize
    from infer.bop_runner import _draw

    seen = {}

    def draw(image, dets, masks, caption=None, before_masks=()):
        seen.update(dets=dets, caption=caption)
        return image

    monkeypatch.setattr(infer.visualize, "draw_detections", draw)
    instances = [types.SimpleNamespace(obj_id=1, score=0.2),
                 types.SimpleNamespace(obj_id=2, score=0.05)]
    rows = [(i, np.eye(4), np.array([0.0, 0.0, 4.0, 4.0]), np.zeros((8, 8), bool))
            for i in range(2)]
    _draw(tmp_path / "o" / "x.png", np.zeros((8, 8, 3), np.uint8), rows, instances, 0.5, None)
    assert seen == {"dets": [], "caption": "0 detections above threshold 0.5 (best score 0.200)"}
    assert (tmp_path / "o" / "x.png").is_file()
