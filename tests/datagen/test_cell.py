"""Robot-cell scenes (``datagen --layout cell``): the cell's camera and tray from its hand-derived
definition, every part of generated scenes inside the recorded depth range, one cell per dataset
(both splits), carried into the records, no lamp hiding the view, a rig of two cameras (its
geometry, its dataset's groups and depth range), and the errors.

References: the pinhole relation size = f d / z derived by hand; ground-truth poses read back
from the written BOP files with ``threept_jax.data.bop``; ``cv2.projectPoints`` for where the
tray centre lands; a float64 ray cast through every pixel for what a lamp hides.
"""

import dataclasses
import json
import math
import shutil

import cv2
import numpy as np
import pytest

from datagen import cell as C
from datagen import generate, pack
from datagen import scene as S
from threept_jax.data import bop

ARGS = ["--meshes", "procedural:5", "--procedural-max-faces", "1000", "--resolution", "160",
        "120", "--spp", "1", "--max-depth", "2", "--instances", "6", "--image-format", "png",
        "--quiet", "--seed", "5", "--layout", "cell"]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("cell")
    generate.main(ARGS + ["--out", str(out), "--num-scenes", "3", "--images-per-scene", "2"])
    generate.main(ARGS + ["--out", str(out), "--num-scenes", "1", "--split", "val"])
    return out


def test_design_matches_its_definition():
    rng = np.random.default_rng(0)
    diameters = [60.0, 80.0, 100.0, 150.0]
    cell = C.design_cell(rng, diameters, (640, 480))
    K = np.asarray(cell.K)
    # The median part (90 mm) projects to MEDIAN_PART_SHARE of 640 px at the working distance.
    px = K[0, 0] * 90.0 / cell.working_distance
    assert C.MEDIAN_PART_SHARE[0] * 640 <= px <= C.MEDIAN_PART_SHARE[1] * 640
    # The tray fills TRAY_FILL of the image width at the floor: x = f X / z.
    assert K[0, 0] * cell.tray_inner[0] / cell.working_distance == pytest.approx(
        C.TRAY_FILL * 640, rel=1e-9)
    assert cell.max_height == pytest.approx(cell.tray_height + 75.0)
    zmin, zmax = cell.depth_range()
    lo, hi = cell.distance_range
    assert zmin < lo - cell.max_height and zmax > hi
    # Very mixed sizes: the camera backs off so the largest part stays in front of it.
    mixed = C.design_cell(rng, [10.0, 12.0, 400.0], (640, 480))
    assert mixed.depth_range()[0] >= 0.4 * mixed.working_distance
    with pytest.raises(ValueError, match="positive diameters"):
        C.design_cell(rng, [], (640, 480))


def test_captures_look_down_at_the_tray():
    rng = np.random.default_rng(1)
    cell = C.design_cell(rng, [50.0, 70.0], (320, 240))
    for _ in range(20):
        (K,), (T,) = C.capture(rng, cell)
        R, t = T[:3, :3], T[:3, 3]
        # The optical axis (camera +z in the world) points down, within the tilt bound.
        down = -R[2, 2]
        assert down >= math.cos(math.radians(C.TILT_DEG)) - 1e-9
        depth = (R @ np.zeros(3) + t)[2]  # the tray centre's depth
        lo, hi = cell.distance_range
        s = 0.5 * math.hypot(*cell.tray_inner) * 2 * C.AIM_JITTER
        assert lo - s <= depth <= hi + s
        uv, _ = cv2.projectPoints(np.zeros((1, 3)), cv2.Rodrigues(R)[0], t, K, None)
        u, v = uv[0, 0]
        assert abs(u - 160) < 0.15 * 320 and abs(v - 120) < 0.15 * 240


def _rays_hit_lamp(corners, K, T_cam_world, hw, depth, near=1.0, step=2, grow=1.0):
    """Brute force: whether a camera ray through any pixel (every ``step`` px, borders
    included) meets the rectangle ``corners`` [4, 3] (world), scaled by ``grow`` about its
    centre, between ``near`` and ``depth``."""
    corners = corners.mean(0) + grow * (corners - corners.mean(0))
    c = corners @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    ex, ey = c[1] - c[0], c[3] - c[0]
    n = np.cross(ex, ey)
    h, w = hw
    u, v = np.meshgrid(np.r_[np.arange(0, w, step), w], np.r_[np.arange(0, h, step), h])
    d = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], -1) @ np.linalg.inv(K).T  # z = 1
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (c[0] @ n) / (d @ n)
    p = d * t[:, None] - c[0]
    a, b = p @ ex / (ex @ ex), p @ ey / (ey @ ey)
    hit = (t >= near) & (t <= depth) & (a >= 0) & (a <= 1) & (b >= 0) & (b <= 1)
    return bool(hit.any())


def test_lamps_never_hide_the_view():
    """A rectangular lamp hides a camera's view exactly where rays through its pixels meet it
    before the scene (a float64 ray cast), and the generator moves such a lamp away until none
    does: one drawn between a cell's camera and the tray made its image black."""
    rng = np.random.default_rng(3)
    cell = C.design_cell(rng, [50.0, 70.0, 120.0], (160, 120))
    hw, centre = (120, 160), np.zeros(3)
    seen = borderline = 0
    for _ in range(300):
        (K,), (T,) = C.capture(rng, cell)
        depth = float((T[:3, :3] @ centre + T[:3, 3])[2])
        el, az = math.radians(rng.uniform(40, 90)), rng.uniform(0, 2 * math.pi)
        dist = cell.working_distance * rng.uniform(0.5, 1.6)
        pos = dist * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az),
                               math.sin(el)])
        size = rng.uniform(20.0, 300.0, 2)
        corners = S.lamp_corners(pos, centre, size)
        # The rectangle the renderer draws: centred on pos, facing the centre.
        np.testing.assert_allclose(corners.mean(0), pos, atol=1e-9)
        normal = np.cross(corners[1] - corners[0], corners[3] - corners[0])
        assert normal @ (centre - pos) > 0
        hidden = S.hides_view(corners, K, T, hw, depth)
        # A lamp whose edge grazes the image or the scene's depth within 1 % of its size is
        # too close to call on a pixel grid (and on another machine's last float bits).
        inner, outer = (_rays_hit_lamp(corners, K, T, hw, depth, grow=g) for g in (0.99, 1.01))
        if inner == outer:
            assert hidden == inner
        else:
            borderline += 1
        seen += hidden
        away = S.lamp_out_of_view(pos, centre, size, [K], [T], hw)
        assert away is not None and (away == 1.0) == (not hidden)
        moved = S.lamp_corners(centre + away * (pos - centre), centre, size)
        assert not _rays_hit_lamp(moved, K, T, hw, depth, grow=0.99)
    assert 10 < seen < 290 and borderline < 10  # both kinds of lamps were drawn


def test_scenes_stay_in_the_recorded_depth_range(dataset):
    cell = bop.load_cell(dataset)
    zmin, zmax = cell["depth_range_mm"]
    assert cell["resolution"] == [160, 120]
    ds = bop.BopDataset(dataset)
    depths, n = [], 0
    for split in ("train_pbr", "val_pbr"):
        sp = ds.split(split)
        for sid in sp.scene_ids:
            sc = sp.scene(sid)
            for im in sc.image_ids:
                np.testing.assert_allclose(sc.cameras[im].K.ravel(), cell["cam_K"], rtol=0,
                                           atol=1e-6)  # one camera for the whole dataset
                for g in sc.gt[im]:
                    depths.append(g.T_cam_obj[2, 3])
                n += 1
    assert n == 7 and len(depths) >= 7
    assert zmin <= min(depths) and max(depths) <= zmax, (min(depths), max(depths), zmin, zmax)
    manifest = json.loads((dataset / "train_pbr" / "manifest.json").read_text())
    assert manifest["layouts"] == {"cell": 3}
    assert manifest["config"]["cell"]["working_distance"] == pytest.approx(
        cell["working_distance_mm"])


def test_a_dataset_from_before_rigs_resumes(dataset, tmp_path):
    """A manifest written before cells had rigs (its cell without ``views``) is the one-camera
    cell: the same arguments resume it rather than being refused as other arguments."""
    out = tmp_path / "old"
    shutil.copytree(dataset, out)
    path = out / "train_pbr" / "manifest.json"
    manifest = json.loads(path.read_text())
    del manifest["config"]["cell"]["views"]
    path.write_text(json.dumps(manifest))
    images = sorted((out / "train_pbr").rglob("*.png"))
    generate.main(ARGS + ["--out", str(out), "--num-scenes", "3", "--images-per-scene", "2"])
    assert sorted((out / "train_pbr").rglob("*.png")) == images
    assert json.loads(path.read_text())["config"]["cell"]["views"] == 1


def test_pack_carries_the_cell_and_refuses_another(dataset, tmp_path):
    records = tmp_path / "records"
    pack.main(["--scenes", str(dataset / "train_pbr"), "--out", str(records), "--no-banks",
               "--quiet"])
    assert bop.load_cell(records) == bop.load_cell(dataset)
    other = tmp_path / "other"
    generate.main([a if a != "5" else "6" for a in ARGS] + ["--out", str(other),
                                                            "--num-scenes", "1"])
    assert bop.load_cell(other) != bop.load_cell(dataset)
    with pytest.raises(SystemExit):
        pack.main(["--scenes", str(other / "train_pbr"), "--out", str(records), "--name", "b",
                   "--no-banks", "--quiet"])


def test_a_rig_sees_one_aim_point_from_cameras_apart():
    """Two cameras: each axis RIG_TILT_DEG +- RIG_JITTER_DEG off the vertical, on opposite
    sides (azimuths 180 +- 2 jitter degrees apart), both through one aim point on the floor
    (the rays intersected with z = 0 in float64), the baseline what that geometry gives."""
    rng = np.random.default_rng(4)
    diameters = [60.0, 80.0, 100.0, 110.0]
    one = C.design_cell(np.random.default_rng(9), diameters, (320, 240))
    cell = C.design_cell(np.random.default_rng(9), diameters, (320, 240), views=2)
    assert dataclasses.replace(cell, views=1) == one  # the same cell, another rig
    lo, hi = cell.distance_range
    tilt = math.radians(C.RIG_TILT_DEG + C.RIG_JITTER_DEG)
    s = 0.5 * math.hypot(*cell.tray_inner) * (1 + 2 * C.AIM_JITTER)
    assert cell.depth_range() == pytest.approx((lo - cell.max_height - s * math.sin(tilt),
                                                hi + s * math.sin(tilt)), rel=1e-12)
    assert cell.depth_range()[1] > one.depth_range()[1]  # a steeper view of the tray
    for _ in range(20):
        Ks, Ts = C.capture(rng, cell)
        assert Ks.shape == (2, 3, 3) and Ts.shape == (2, 4, 4)
        centres, aims, azimuths = [], [], []
        for T in Ts:
            R, t = T[:3, :3], T[:3, 3]
            centre, axis = -R.T @ t, R[2]  # the optical centre and axis in the world
            off = math.degrees(math.acos(-axis[2]))
            assert C.RIG_TILT_DEG - C.RIG_JITTER_DEG - 1e-9 <= off
            assert off <= C.RIG_TILT_DEG + C.RIG_JITTER_DEG + 1e-9
            aims.append(centre - centre[2] / axis[2] * axis)
            centres.append(centre)
            azimuths.append(math.atan2(centre[1] - aims[-1][1], centre[0] - aims[-1][0]))
            assert lo - 1e-6 <= np.linalg.norm(centre - aims[-1]) <= hi + 1e-6
        np.testing.assert_allclose(aims[0], aims[1], atol=1e-6)
        assert np.all(np.abs(aims[0][:2]) <= C.AIM_JITTER * np.asarray(cell.tray_inner))
        apart = abs((math.degrees(azimuths[0] - azimuths[1]) + 180) % 360 - 180)
        assert 180 - 2 * C.RIG_JITTER_DEG - 1e-6 <= apart
        baseline = np.linalg.norm(centres[0] - centres[1])
        lo_tilt = math.radians(C.RIG_TILT_DEG - C.RIG_JITTER_DEG)
        assert baseline >= 2 * lo * math.sin(lo_tilt) * math.cos(math.radians(C.RIG_JITTER_DEG))


def test_a_rig_dataset_groups_its_views(tmp_path):
    out = tmp_path / "rig"
    generate.main(ARGS + ["--out", str(out), "--num-scenes", "1", "--images-per-scene", "2",
                          "--views", "2", "--split", "val"])
    cell = bop.load_cell(out)
    assert cell["views"] == 2
    groups = bop.load_multiview_targets(out / "test_targets_multiview_bop25.json")
    assert [(g.scene_id, [im for _, im in g.views]) for g in groups] == [(0, [0, 1]), (0, [2, 3])]
    scene = bop.BopDataset(out).split("val_pbr").scene(0)
    zmin, zmax = cell["depth_range_mm"]
    for im in range(4):
        assert all(zmin <= g.T_cam_obj[2, 3] <= zmax for g in scene.gt[im])
    # The two views of a capture see the same parts from cameras far apart.
    centres = [-(T[:3, :3].T @ T[:3, 3]) for T in (scene.cameras[i].T_cam_world for i in (0, 1))]
    assert np.linalg.norm(centres[0] - centres[1]) > 0.3 * cell["working_distance_mm"]
    assert {g.obj_id for g in scene.gt[0]} == {g.obj_id for g in scene.gt[1]}


def test_bad_cell_options_and_files(tmp_path):
    cell = C.design_cell(np.random.default_rng(0), [50.0], (64, 48))
    with pytest.raises(ValueError, match="views=1"):
        S.SceneConfig(resolution=(64, 48), layout="cell", cell=cell, views=3)
    with pytest.raises(ValueError, match="needs its cell"):
        S.SceneConfig(resolution=(64, 48), layout="cell")
    with pytest.raises(ValueError, match="at least one camera"):
        C.design_cell(np.random.default_rng(0), [50.0], (64, 48), views=0)
    (tmp_path / bop.CELL_FILE).write_text(json.dumps({"depth_range_mm": [500, 100]}))
    with pytest.raises(ValueError, match="cell.json.*zmin <= zmax"):
        bop.load_cell(tmp_path)
    assert bop.load_cell(tmp_path / "missing") is None
