"""BOP reading and writing: shared models, a generated mini dataset round trip, result files,
validation errors. References: raw JSON, Python float parsing, trimesh, OpenCV, pycocotools."""

import json

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from threept_jax.data import bop
from threept_jax.data.ply import load_ply_mesh, load_ply_vertices
from threept_jax.geometry.validate import validate_intrinsics
from threept_jax.testing.bop_synthetic import SyntheticInstance, write_synthetic_dataset

DATASETS = ["icbin", "itodd", "tless", "tudl", "ycbv"]
K = np.array([[600.0, 0.0, 320.0], [0.0, 610.0, 240.0], [0.0, 0.0, 1.0]])


def _pose(x, y, z, seed):
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    T[:3, 3] = [x, y, z]
    return T


@pytest.mark.parametrize("name", DATASETS)
def test_shared_models_load_with_symmetries(bop_models_dir, name):
    folder = bop_models_dir / name / "models"
    models = bop.load_models(folder)
    raw = json.loads((folder / "models_info.json").read_text())
    assert sorted(models) == sorted(int(k) for k in raw)
    for k, info in raw.items():
        m = models[int(k)]
        assert m.diameter == info["diameter"]
        np.testing.assert_array_equal(m.bbox_min, [info["min_x"], info["min_y"], info["min_z"]])
        disc = info.get("symmetries_discrete", [])
        assert len(m.symmetries.discrete) == len(disc)
        for got, want in zip(m.symmetries.discrete, disc):
            np.testing.assert_array_equal(got.reshape(-1), want)
        cont = info.get("symmetries_continuous", [])
        assert len(m.symmetries.continuous) == len(cont)
        for got, want in zip(m.symmetries.continuous, cont):
            np.testing.assert_array_equal(got.axis, want["axis"])
            np.testing.assert_array_equal(got.offset, want["offset"])
        ply = folder / f"obj_{int(k):06d}.ply"
        assert (m.path is not None) == ply.is_file()


def test_ply_vertices_match_python_parsing_and_trimesh(bop_models_dir):
    import trimesh

    path = bop_models_dir / "itodd" / "models" / "obj_000019.ply"
    lines = path.read_text().splitlines()
    start = lines.index("end_header") + 1
    n = int(next(ln.split()[-1] for ln in lines if ln.startswith("element vertex")))
    want = np.array([[float(v) for v in ln.split()[:3]] for ln in lines[start : start + n]])
    verts, faces = load_ply_mesh(path)
    np.testing.assert_array_equal(verts, want)
    tm = trimesh.load(path, process=False)
    np.testing.assert_array_equal(faces, tm.faces)
    np.testing.assert_allclose(verts, tm.vertices, atol=1e-4)


def test_binary_ply_matches_ascii(tmp_path, bop_models_dir):
    import trimesh

    src = bop_models_dir / "itodd" / "models" / "obj_000003.ply"
    verts, faces = load_ply_mesh(src)
    out = tmp_path / "bin.ply"
    out.write_bytes(
        trimesh.exchange.ply.export_ply(
            trimesh.Trimesh(verts, faces, process=False), encoding="binary"
        )
    )
    np.testing.assert_allclose(load_ply_vertices(out), verts, rtol=1e-6)
    np.testing.assert_array_equal(load_ply_mesh(out)[1], faces)


@pytest.fixture(scope="module")
def mini(tmp_path_factory, bop_models_dir):
    itodd = bop.load_models(bop_models_dir / "itodd" / "models")
    models = {3: itodd[3], 19: itodd[19]}
    scenes = {
        1: {
            0: [
                SyntheticInstance(3, _pose(-80, 0, 800, 1)),
                SyntheticInstance(19, _pose(60, 0, 700, 2)),
                SyntheticInstance(3, _pose(0, 90, 900, 3), 0.25),
            ],
            7: [SyntheticInstance(19, _pose(0, 0, 600, 4))],
        },
        3: {2: [SyntheticInstance(3, _pose(10, -20, 650, 5))]},
    }
    root = write_synthetic_dataset(tmp_path_factory.mktemp("bop") / "mini", models, scenes, K)
    return root, scenes, models


def test_round_trip_of_generated_dataset(mini):
    root, scenes, models = mini
    ds = bop.BopDataset(root)
    assert sorted(ds.models()) == [3, 19]
    split = ds.split("test")
    assert split.scene_ids == [1, 3]
    for sid, ims in scenes.items():
        sc = split.scene(sid)
        assert sc.image_ids == sorted(ims)
        for iid, insts in ims.items():
            np.testing.assert_array_equal(sc.cameras[iid].K, K)
            assert sc.cameras[iid].depth_scale == 1.0
            assert [g.obj_id for g in sc.gt[iid]] == [i.obj_id for i in insts]
            for g, inst in zip(sc.gt[iid], insts):
                np.testing.assert_array_equal(g.T_cam_obj, inst.T_cam_obj)
            rgb = sc.image(iid)
            assert rgb.shape == (480, 640, 3) and rgb.dtype == np.uint8
            assert sc.image_size(iid) == (640, 480)
            for j, info in enumerate(sc.gt_info[iid]):
                full, vis = sc.mask(iid, j), sc.mask_visib(iid, j)
                x, y, w, h = cv2.boundingRect(full.astype(np.uint8))
                assert info.bbox_obj == (x, y, w - 1, h - 1)  # BOP: x_max - x_min, no +1
                x, y, w, h = cv2.boundingRect(vis.astype(np.uint8))
                assert info.bbox_visib == (x, y, w - 1, h - 1)
                assert info.px_count_all == cv2.countNonZero(full.astype(np.uint8))
                assert info.px_count_visib == cv2.countNonZero(vis.astype(np.uint8))
                assert info.visib_fract == info.px_count_visib / info.px_count_all
    assert abs(split.scene(1).gt_info[0][2].visib_fract - 0.25) < 0.05
    t24 = ds.targets("bop24")
    assert [(t.scene_id, t.im_id) for t in t24] == [(1, 0), (1, 7), (3, 2)]
    t19 = ds.targets("bop19")
    assert {(t.scene_id, t.im_id, t.obj_id, t.inst_count) for t in t19} == {
        (1, 0, 3, 2),
        (1, 0, 19, 1),
        (1, 7, 19, 1),
        (3, 2, 3, 1),
    }


def test_scene_json_has_bop_formatting(mini):
    root = mini[0]
    text = (root / "test" / "000001" / "scene_gt.json").read_text()
    lines = text.splitlines()
    assert lines[0] == "{" and lines[-1] == "}"
    assert lines[1].startswith('  "0": [{"cam_R_m2c": [') and lines[2].startswith('  "7": ')
    raw = json.loads(text)
    assert isinstance(raw["0"][0]["obj_id"], int) and len(raw["0"][0]["cam_R_m2c"]) == 9
    cam = json.loads((root / "test" / "000001" / "scene_camera.json").read_text())
    assert cam["0"]["cam_K"] == K.reshape(-1).tolist()
    assert not list((root / "test" / "000001").glob("*.tmp"))


def test_opening_is_lazy(mini, monkeypatch):
    def boom(*a, **k):
        raise AssertionError("an image was read")

    monkeypatch.setattr(bop.reader, "_read_image", boom)
    ds = bop.BopDataset(mini[0])
    sc = ds.split("test").scene(1)
    assert len(sc.gt[0]) == 3 and sc.gt_info[0][0].visib_fract == 1.0
    with pytest.raises(AssertionError):
        sc.image(0)


def test_scene_writer_depth_and_world_pose(tmp_path):
    T_cw = np.eye(4)
    T_cw[:3, :3] = Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_matrix()
    T_cw[:3, 3] = [1, 2, 3]
    cam = bop.Camera(K, 0.1, T_cw)
    depth = np.zeros((4, 5))
    depth[1:3, 1:4] = 812.3
    masks = np.zeros((1, 4, 5), bool)
    masks[0, 1:3, 1:4] = True
    vis = masks.copy()
    vis[0, 2] = False
    with bop.BopSceneWriter(tmp_path / "000000", image_ext="jpg") as w:
        infos = w.add_image(
            4,
            cam,
            np.zeros((4, 5, 3), np.uint8),
            [bop.GtInstance(2, np.eye(4))],
            masks,
            vis,
            depth_mm=depth,
        )
    assert infos[0].px_count_all == 6 and infos[0].px_count_visib == 3
    assert infos[0].px_count_valid == 6 and infos[0].visib_fract == 0.5
    sc = bop.BopScene(tmp_path / "000000")
    np.testing.assert_array_equal(sc.cameras[4].T_cam_world, T_cw)
    raw = cv2.imread(str(tmp_path / "000000" / "depth" / "000004.png"), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16 and raw[1, 1] == 8123
    np.testing.assert_allclose(sc.depth(4)[1, 1], 812.3, atol=1e-3)
    assert (tmp_path / "000000" / "rgb" / "000004.jpg").is_file()
    assert (tmp_path / "000000" / "mask_visib" / "000004_000000.png").is_file()


def test_scene_writer_full_canvas_counts_truncated_pixels(tmp_path):
    masks = np.zeros((1, 4, 4), bool)
    masks[0, :, :2] = True
    full = np.zeros((1, 4, 8), bool)
    full[0, :, 2:6] = True  # image column 0 sits at canvas column 4: 2 columns are cut off
    w = bop.BopSceneWriter(tmp_path / "000000")
    info = w.add_image(
        0,
        bop.Camera(K),
        None,
        [bop.GtInstance(1, np.eye(4))],
        masks,
        masks,
        masks_full=full,
        full_offset=(4, 0),
    )[0]
    assert info.px_count_all == 16 and info.px_count_visib == 8 and info.visib_fract == 0.5
    assert info.bbox_obj == (-2, 0, 3, 3)


def test_pose_csv_round_trip(tmp_path):
    R = Rotation.random(3, random_state=0).as_matrix()
    ests = [
        bop.PoseEstimate(1, 2, 5, 0.75, R[0], [1.5, -2.0, 800.25], 0.3),
        bop.PoseEstimate(1, 2, 6, 0.5, R[1], [0, 0, 500], 0.3),
        bop.PoseEstimate(2, 0, 5, 1e-3, R[2], [3, 4, 5], -1),
    ]
    path = tmp_path / "m_tless-test.csv"
    bop.write_pose_results(path, ests)
    lines = path.read_text().splitlines()
    assert lines[0] == "scene_id,im_id,obj_id,score,R,t,time"
    cols = lines[1].split(",")
    assert cols[:4] == ["1", "2", "5", "0.75"] and len(cols[4].split()) == 9
    back = bop.read_pose_results(path)
    for a, b in zip(ests, back):
        assert (a.scene_id, a.im_id, a.obj_id, a.score, a.time) == (
            b.scene_id,
            b.im_id,
            b.obj_id,
            b.score,
            b.time,
        )
        np.testing.assert_array_equal(a.R, b.R)
        np.testing.assert_array_equal(a.t, b.t)


def test_pose_csv_rejects_bad_rows(tmp_path):
    good = "1,2,3,0.5," + " ".join(map(str, np.eye(3).reshape(-1))) + ",1 2 3,0.1\n"
    p = tmp_path / "r.csv"
    p.write_text("scene_id,im_id,obj_id,score,R,t,time\n" + good + "1,2,3,0.5,1 0 0,0.1\n")
    with pytest.raises(ValueError, match=r"r.csv:3: expected 7 comma-separated columns"):
        bop.read_pose_results(p)
    p.write_text(good.replace("1.0 0.0 0.0", "2.0 0.0 0.0", 1))
    with pytest.raises(ValueError, match="not orthonormal"):
        bop.read_pose_results(p)
    R = np.eye(3)
    with pytest.raises(ValueError, match="one time per image"):
        bop.write_pose_results(
            p,
            [
                bop.PoseEstimate(1, 1, 1, 1, R, [0, 0, 1], 0.1),
                bop.PoseEstimate(1, 1, 2, 1, R, [0, 0, 1], 0.5),
            ],
        )


def test_detection_json_round_trip_and_rle(tmp_path):
    from pycocotools import mask as mask_utils

    rng = np.random.default_rng(0)
    m = rng.random((37, 53)) > 0.6
    rle = bop.mask_to_rle(m)
    assert isinstance(rle["counts"], str) and rle["size"] == [37, 53]
    np.testing.assert_array_equal(
        mask_utils.decode({"counts": rle["counts"].encode(), "size": rle["size"]}).astype(bool), m
    )
    # Uncompressed (BOP pycoco_utils.binary_mask_to_rle style) counts decode too.
    flat = m.ravel(order="F")
    change = np.flatnonzero(np.diff(np.concatenate([[0], flat.astype(int), [2]])) != 0)
    counts = np.diff(np.concatenate([[0], change])).tolist()
    np.testing.assert_array_equal(bop.rle_to_mask({"counts": counts, "size": [37, 53]}), m)
    dets = [
        bop.Detection2D(1, 4, 7, 0.9, (1.0, 2.0, 30.5, 40.0), rle, 0.25),
        bop.Detection2D(1, 5, 8, 0.1, (0, 0, 1, 1), None, 0.25),
    ]
    path = tmp_path / "d.json"
    bop.write_detection_results(path, dets)
    raw = json.loads(path.read_text())
    assert raw[0]["scene_id"] == 1 and raw[0]["image_id"] == 4 and raw[0]["category_id"] == 7
    assert raw[0]["bbox"] == [1.0, 2.0, 30.5, 40.0] and "segmentation" not in raw[1]
    back = bop.read_detection_results(path)
    np.testing.assert_array_equal(bop.rle_to_mask(back[0].segmentation), m)
    assert back[1].bbox == (0, 0, 1, 1) and back[1].segmentation is None
    raw[0]["image_id"] = 4.0
    path.write_text(json.dumps(raw))
    with pytest.raises(ValueError, match="image_id must be an integer"):
        bop.read_detection_results(path)


def test_validation_errors(tmp_path, mini):
    with pytest.raises(ValueError, match="not upper-triangular"):
        bop.Camera(K.T)
    with pytest.raises(ValueError, match="focal lengths must be positive"):
        bop.Camera(np.diag([-1.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match="9 values"):
        validate_intrinsics([1, 2, 3])
    with pytest.raises(FileNotFoundError, match="does not exist"):
        bop.BopDataset(tmp_path / "nope")
    with pytest.raises(FileNotFoundError, match="no models_info.json"):
        bop.load_models(tmp_path)
    info = json.loads((mini[0] / "models" / "models_info.json").read_text())
    info["3"]["diameter"] = 0.21
    (tmp_path / "models_info.json").write_text(json.dumps(info))
    with pytest.raises(ValueError, match="looks like metres"):
        bop.load_models(tmp_path)
    sc_dir = tmp_path / "test" / "000001"
    sc_dir.mkdir(parents=True)
    (sc_dir / "scene_camera_cam1.json").write_text("{}")
    with pytest.raises(FileNotFoundError, match="multi-sensor scene, pass sensor"):
        bop.BopDataset(tmp_path).split("test").scene(1)
    (sc_dir / "scene_camera.json").write_text(
        json.dumps({"0": {"cam_K": [1, 0, 0, 1, 1, 0, 0, 0, 1]}})
    )
    with pytest.raises(ValueError, match="not upper-triangular"):
        _ = bop.BopScene(sc_dir).cameras
    bad_gt = {
        "0": [{"obj_id": 1, "cam_R_m2c": [1, 0, 0, 0, 1, 0, 0, 0, -1], "cam_t_m2c": [0, 0, 1]}]
    }
    (sc_dir / "scene_gt.json").write_text(json.dumps(bad_gt))
    with pytest.raises(ValueError, match="scene_gt.json image 0 gt 0 cam_R_m2c"):
        _ = bop.BopScene(sc_dir).gt
    (sc_dir / "scene_gt_info.json").write_text('{"0": [')
    with pytest.raises(ValueError, match="not valid JSON"):
        _ = bop.BopScene(sc_dir).gt_info


def test_multisensor_files_and_multiview_targets(tmp_path):
    sc = tmp_path / "test" / "000000"
    with bop.BopSceneWriter(sc, sensor="cam2") as w:
        m = np.ones((1, 3, 3), bool)
        w.add_image(
            5, bop.Camera(K), np.zeros((3, 3), np.uint8), [bop.GtInstance(1, np.eye(4))], m, m
        )
    assert (sc / "scene_camera_cam2.json").is_file() and (sc / "gray_cam2" / "000005.png").is_file()
    split = bop.BopDataset(tmp_path).split("test", sensor="cam2")
    assert split.sensors() == ["cam2"]
    assert split.scene(0).image(5).shape == (3, 3)
    (tmp_path / "test_targets_multiview_bop25.json").write_text(
        json.dumps(
            [
                {"scene_id": 0, "im_id": [["cam1", 5], ["cam2", 5]]},
                {"scene_id": 1, "im_ids": [3, 4]},
            ]
        )
    )
    mv = bop.BopDataset(tmp_path).multiview_targets()
    assert mv[0] == bop.MultiviewTarget(0, (("cam1", 5), ("cam2", 5)))
    assert mv[1] == bop.MultiviewTarget(1, ((None, 3), (None, 4)))
    with pytest.raises(ValueError, match="multi-view targets file"):
        bop.load_targets(tmp_path / "test_targets_multiview_bop25.json")


def test_inconsistent_times_are_rejected():
    R = np.eye(3)
    ests = [
        bop.PoseEstimate(1, 1, 1, 1, R, [0, 0, 1], 0.1),
        bop.PoseEstimate(1, 1, 2, 1, R, [0, 0, 1], 0.1005),
        bop.PoseEstimate(1, 2, 2, 1, R, [0, 0, 1], 3.0),
    ]
    bop.check_consistent_times(ests)
    with pytest.raises(ValueError, match="scene 1 and image 1 is not the same"):
        bop.check_consistent_times(ests + [bop.PoseEstimate(1, 1, 3, 1, R, [0, 0, 1], 0.2)])


def _write_gt(sc_dir, rotations):
    sc_dir.mkdir(parents=True, exist_ok=True)
    gt = {"0": [{"obj_id": 1, "cam_R_m2c": np.asarray(R).reshape(-1).tolist(),
                 "cam_t_m2c": [0.0, 0.0, 500.0]} for R in rotations]}
    (sc_dir / "scene_gt.json").write_text(json.dumps(gt))
    return gt


def test_rounded_gt_rotations_are_accepted_as_stored_and_projected(tmp_path):
    # Official BOP GT (LM-O) stores rounded rotations, |R R^T - I| ~ 1e-2: the toolkit evaluates
    # them as stored, so gt_as_stored keeps the file's values; gt gives the nearest rotation.
    R = np.round(Rotation.random(3, random_state=11).as_matrix(), 2)
    R[0] = Rotation.random(random_state=12).as_matrix()  # an exact one is kept as it is
    dev = [np.abs(r @ r.T - np.eye(3)).max() for r in R]
    assert dev[0] < 1e-12 and 3e-3 < max(dev) < 0.1
    gt = _write_gt(tmp_path / "000001", R)
    scene = bop.BopScene(tmp_path / "000001")
    with pytest.warns(UserWarning, match=rf"scene_gt.json: 2 ground-truth rotations .*worst "
                                         rf"\|R R\^T - I\| = {max(dev):.2e}"):
        stored = scene.gt_as_stored[0]
    for g, e in zip(stored, gt["0"]):
        np.testing.assert_array_equal(g.R.reshape(-1), e["cam_R_m2c"])
    projected = scene.gt[0]
    for g, r in zip(projected, R):
        U, _, Vt = np.linalg.svd(r)  # nearest rotation (Frobenius), float64 NumPy
        ref = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
        np.testing.assert_allclose(g.R, ref, atol=1e-12)
        np.testing.assert_array_equal(g.t, [0.0, 0.0, 500.0])
    np.testing.assert_array_equal(projected[0].R, R[0])


@pytest.mark.parametrize(
    "R, msg",
    [
        (np.diag([1.0, 1.0, -1.0]), "not orthonormal"),  # a reflection
        (1.2 * np.eye(3), "not orthonormal"),  # deviation 0.44 > 0.1
        (np.array([[np.nan, 0, 0], [0, 1, 0], [0, 0, 1]]), "non-finite"),
    ],
)
def test_gt_that_is_not_a_rotation_is_refused(tmp_path, R, msg):
    _write_gt(tmp_path / "000001", [R])
    with pytest.raises(ValueError, match=f"scene_gt.json image 0 gt 0 cam_R_m2c.*{msg}"):
        _ = bop.BopScene(tmp_path / "000001").gt_as_stored


@pytest.mark.parametrize("stem, content, where", [
    ("scene_gt", {"0": [{"cam_R_m2c": [1, 0, 0, 0, 1, 0, 0, 0, 1], "cam_t_m2c": [0, 0, 9],
                         "obj_id": None}]}, "image 0"),
    ("scene_gt", {"0": {"obj_id": 1}}, "image 0"),
    ("scene_gt", {"0": [{"cam_R_m2c": [1, 0, 0, 0, 1, 0, 0, 0, [1]], "cam_t_m2c": [0, 0, 9],
                         "obj_id": 1}]}, "image 0"),
    ("scene_camera", {"0": {"cam_K": None}}, "image 0"),
    ("scene_gt_info", {"3": [{"bbox_obj": [0, 0, 1, 1]}]}, "image 3"),
])
def test_malformed_scene_entries_name_file_and_entry(tmp_path, stem, content, where):
    """A structurally wrong entry (null id, dict for a list, nested value, missing key) is a
    ValueError naming the file and the image, not a TypeError/KeyError from the parsing."""
    scene = tmp_path / "000001"
    scene.mkdir()
    (scene / f"{stem}.json").write_text(json.dumps(content))
    s = bop.BopScene(scene)
    attr = {"scene_gt": "gt", "scene_camera": "cameras", "scene_gt_info": "gt_info"}[stem]
    with pytest.raises(ValueError, match=rf"{stem}\.json {where}"):
        getattr(s, attr)


@pytest.mark.parametrize("content", [
    [{"scene_id": 1, "im_id": 2.5}], [{"scene_id": 1, "im_id": True}], [7], [None],
    [{"scene_id": "1", "im_id": 2}],
])
def test_malformed_targets_name_the_entry(tmp_path, content):
    """Ids must be integers: a fraction, a boolean or a string is refused, not truncated."""
    p = tmp_path / "test_targets_bop19.json"
    p.write_text(json.dumps(content))
    with pytest.raises(ValueError, match=r"test_targets_bop19\.json entry 0"):
        bop.load_targets(p)


def test_binary_json_is_a_value_error_naming_the_file(tmp_path):
    p = tmp_path / "models_info.json"
    p.write_bytes(b"\x80\xff{")
    with pytest.raises(ValueError, match="models_info.json is not UTF-8"):
        bop.load_models_info(p)
