"""The training-free detector (issue 37): its pieces against independent references, then the
whole on rasterised scenes with known ground truth.

References: a brute-force loop over pixels and windows (the LINE-2D response maps), a box's
silhouette derived by hand (the templates' extents), the poses the scenes were rendered at
(template fit, detection), and what a featureless image must give (nothing).
"""

import json
import math

import cv2
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

import infer
import infer.shape_detect as D
from infer.refine import RefineObject
from infer.shape_detect import ShapeSearchDetector
from threept_jax.pipeline import contour as C
from threept_jax.pipeline import shape_search as S
from threept_jax.render.mesh import Mesh, to_raster_mesh
from threept_jax.render.raster import render

HW = (240, 320)
K = np.array([[400.0, 0, 159.5], [0, 400.0, 119.5], [0, 0, 1]], np.float64)
SMALL = S.ShapeSearchSettings(num_views=100, num_inplane=24, max_proposals=200, candidates=64)


def _box_mesh(size=(60.0, 42.0, 30.0), color=(0.9, 0.2, 0.1)):
    box = trimesh.creation.box(size)
    v, f = np.asarray(box.vertices), np.asarray(box.faces)
    return Mesh(v, f, colors=np.tile(color, (len(v), 1)))


def _cylinder_mesh(color=(0.2, 0.3, 0.9)):
    cyl = trimesh.creation.cylinder(radius=12.0, height=90.0, sections=32)
    v, f = np.asarray(cyl.vertices), np.asarray(cyl.faces)
    return Mesh(v, f, colors=np.tile(color, (len(v), 1)))


def test_orientation_response_matches_a_brute_force_loop():
    rng = np.random.default_rng(0)
    img = np.full((20, 24, 3), 60, np.uint8)
    cv2.rectangle(img, (5, 4), (15, 12), (200, 90, 30), -1)
    cv2.circle(img, (18, 14), 4, (20, 220, 120), -1)
    img = np.clip(img + rng.integers(-8, 9, img.shape), 0, 255).astype(np.uint8)
    spread, thr = 1, 30.0
    ours = S.orientation_response(img, spread, thr)
    f = img.astype(np.float32)
    gx = [cv2.Sobel(f[..., c], cv2.CV_32F, 1, 0, ksize=3) for c in range(3)]
    gy = [cv2.Sobel(f[..., c], cv2.CV_32F, 0, 1, ksize=3) for c in range(3)]
    H, W = img.shape[:2]
    found = {}  # pixel -> bin of its strongest channel's gradient, when strong
    ambiguous = set()  # on a bin border or at the threshold: float32 and float64 may differ
    for y in range(H):
        for x in range(W):
            c = max(range(3), key=lambda c: gx[c][y, x] ** 2 + gy[c][y, x] ** 2)
            g = math.hypot(gx[c][y, x], gy[c][y, x])
            a = math.atan2(gy[c][y, x], gx[c][y, x]) % math.pi
            frac = a / math.pi * 8 + 0.5  # bins centred on multiples of 22.5 degrees
            if abs(g - thr) < 1e-3 or (g > thr and abs(frac - round(frac)) < 1e-4):
                ambiguous.add((y, x))
            if g > thr:
                found[(y, x)] = int(frac) % 8
    centre = [b * math.pi / 8 for b in range(8)]
    ref = np.zeros((8, H, W), np.float32)
    compared = np.ones((H, W), bool)
    for y in range(H):
        for x in range(W):
            for dy in range(-spread, spread + 1):
                for dx in range(-spread, spread + 1):
                    compared[y, x] &= (y + dy, x + dx) not in ambiguous
                    b = found.get((y + dy, x + dx))
                    if b is None:
                        continue
                    for k in range(8):
                        ref[k, y, x] = max(ref[k, y, x], abs(math.cos(centre[b] - centre[k])))
    assert found and compared.mean() > 0.8, "the test image must have clear edges"
    np.testing.assert_allclose(ours[:, compared], ref[:, compared], atol=1e-5)


def test_templates_of_a_box_seen_along_its_axis_have_its_extent():
    """The 60 x 42 x 30 mm box seen from +z: the outline is its 60 x 42 mm rectangle, turned
    in the image plane as the template's rotation says; every template's rotation is a
    rotation."""
    contours = C.mesh_contours(_box_mesh(), num_views=100, num_points=64)
    settings = S.ShapeSearchSettings(num_views=100, num_inplane=4)
    t = S.shape_templates(contours, settings)
    assert t["xy"].shape == (400, settings.num_points, 2)
    R = t["rotations"].astype(np.float64)
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape),
                               atol=1e-5)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-5)
    # The camera of the view nearest +z looks down -z: its optical axis (row 2) is -z.
    view = int(np.argmax(contours["directions"] @ np.array([0, 0, 1.0])))
    tilt = math.degrees(math.acos(contours["directions"][view, 2]))
    tol = 30 * math.sin(math.radians(tilt)) * 2 + 2.0
    for turn in range(4):
        j = view * 4 + turn
        assert R[j, 2, 2] < -0.98
        # The box's x axis appears turned by phi in the image: a 60 x 42 rectangle turned by
        # phi spans 60 |cos| + 42 |sin| by 60 |sin| + 42 |cos| (the view is nearly straight).
        phi = math.atan2(R[j, 1, 0], R[j, 0, 0])
        c, s_ = abs(math.cos(phi)), abs(math.sin(phi))
        xy = t["xy"][j][t["valid"][j]]
        np.testing.assert_allclose(xy.max(0) - xy.min(0), [60 * c + 42 * s_, 60 * s_ + 42 * c],
                                   atol=tol)
    # A quarter turn swaps the extents.
    e0 = np.ptp(t["xy"][view * 4][t["valid"][view * 4]], 0)
    e1 = np.ptp(t["xy"][view * 4 + 1][t["valid"][view * 4 + 1]], 0)
    np.testing.assert_allclose(e0, e1[::-1], atol=1.0)


def _render(meshes_poses, background, intrinsics=K):
    """uint8 image of meshes at T_cam_obj poses (nearest wins) over ``background`` [H, W, 3]."""
    img = background.astype(np.float32) / 255.0
    depth = np.full(HW, np.inf)
    for mesh, T in meshes_poses:
        out = render(to_raster_mesh(mesh), T.astype(np.float32), intrinsics.astype(np.float32), HW,
                     ("rgb", "mask", "depth"), ambient=0.6)
        m = np.asarray(out["mask"]) & (np.asarray(out["depth"]) < depth)
        img[m] = np.asarray(out["rgb"])[m]
        depth[m] = np.asarray(out["depth"])[m]
    return np.round(img * 255).astype(np.uint8)


def _background(seed=0):
    """A smooth random texture: blurred noise, grey-green."""
    rng = np.random.default_rng(seed)
    noise = cv2.GaussianBlur(rng.random(HW + (3,)).astype(np.float32), (0, 0), 6)
    noise = (noise - noise.min()) / np.ptp(noise)
    return np.round(255 * (0.3 + 0.3 * noise * np.array([0.6, 1.0, 0.7]))).astype(np.uint8)


def _pose(R, uv, z, center=None):
    center = np.zeros(3) if center is None else center
    return S.poses_from_fit(R[None], center[None], np.array([z]), np.array([uv], np.float64),
                            K)[0]


BOX_SYMMETRIES = [np.diag(d) for d in ((1, 1, 1), (1, -1, -1), (-1, 1, -1), (-1, -1, 1))]


def _angle(Ra, Rb, symmetries):
    return min(math.degrees(math.acos(np.clip((np.trace(Ra.T @ Rb @ S_) - 1) / 2, -1, 1)))
               for S_ in symmetries)


def test_proposals_are_the_same_whatever_called_rand_before():
    """Selective search ranks its regions with C's ``rand()``: the same image must give the
    same boxes, in the same order, however many times anything else drew from it between
    two calls (it did not: detections changed from run to run), and in threads run at once."""
    import ctypes
    import ctypes.util
    from concurrent.futures import ThreadPoolExecutor

    libc = ctypes.CDLL(ctypes.util.find_library("c"))
    image = _background(1)
    for k, (x, y) in enumerate([(40, 30), (150, 90), (230, 40)]):
        cv2.rectangle(image, (x, y), (x + 50, y + 70), (200, 60 * k, 30), -1)
    first = S.proposals(image, SMALL)
    for draws in (1, 17, 1000):
        for _ in range(draws):
            libc.rand()
        np.testing.assert_array_equal(S.proposals(image, SMALL), first)
    assert len(first) > 10
    # Four threads at once (OpenCV lets go of the GIL): the same boxes in every call.
    with ThreadPoolExecutor(4) as pool:
        for boxes in pool.map(lambda _: S.proposals(image, SMALL), range(8)):
            np.testing.assert_array_equal(boxes, first)


def test_settings_refuse_counts_that_cannot_work():
    """A count below one (or not an integer), or fewer candidates than half a box's templates,
    is refused naming the field and the fix; the defaults and the tests' small settings pass."""
    assert S.ShapeSearchSettings().per_box == 16 and SMALL.candidates == 64
    for bad in ({"per_box": 0}, {"per_proposal": -1}, {"candidates": 2.5}, {"lines": True}):
        name = next(iter(bad))
        with pytest.raises(ValueError, match=rf"ShapeSearchSettings\.{name} must be an integer"):
            S.ShapeSearchSettings(**bad)
    with pytest.raises(ValueError, match="raise candidates or lower per_box"):
        S.ShapeSearchSettings(candidates=7, per_box=16)
    S.ShapeSearchSettings(candidates=8, per_box=16)  # exactly half: one box a call


def test_each_part_gets_its_share_of_the_verified_candidates():
    """select_candidates against a loop: every part's best n // P, then the best of the rest,
    best score first; a part with fewer candidates than its share leaves the rest to others."""
    rng = np.random.default_rng(0)
    for parts_n, size, n in ((3, 40, 12), (4, 30, 10), (2, 5, 12), (1, 7, 3)):
        scores = rng.permutation(size).astype(np.float64)  # distinct: one right answer
        parts = rng.integers(0, parts_n, size)
        parts[:parts_n] = np.arange(parts_n)
        if parts_n == 4:
            parts[parts == 3] = 0
            parts[5] = 3  # part 3 has one candidate, under its share of 2
        each = n // len(np.unique(parts))
        want = []
        for p in np.unique(parts):
            mine = [i for i in range(size) if parts[i] == p]
            want += sorted(mine, key=lambda i: -scores[i])[:each]
        rest = sorted((i for i in range(size) if i not in want), key=lambda i: -scores[i])
        want = sorted(want + rest[:n - len(want)], key=lambda i: -scores[i])
        got = S.select_candidates(scores, parts, n)
        assert got.tolist() == want, (parts_n, size, n)
    assert S.select_candidates(np.zeros(0), np.zeros(0, int), 5).tolist() == []


@pytest.mark.parametrize("centre", [(150.0, 110.0), (14.0, 110.0), (150.0, 16.0), (14.0, 30.0)],
                         ids=["inside", "cut_left", "cut_top", "cut_corner"])
def test_fit_finds_the_template_depth_and_centre_of_a_rendered_box(centre):
    """The box rendered at a template's rotation, inside the image or cut by its left or top
    side (about a third of it outside: its proposal is the visible part's box, whose area
    alone would put it 20 % too far), or by both, the top only a little (the less cut extent
    sets the distance)."""
    mesh = _box_mesh()
    contours = C.mesh_contours(mesh, num_views=100, num_points=200)
    t = S.shape_templates(contours, SMALL)
    j = 1234  # a template; the box is rendered exactly at its rotation
    R = t["rotations"][j].astype(np.float64)
    T = _pose(R, centre, 420.0, contours["center"])
    img = _render([(mesh, T)], _background())
    mask = np.any(img != _background(), -1)
    ys, xs = np.nonzero(mask)
    box = np.array([[xs.min(), ys.min(), np.ptp(xs) + 1, np.ptp(ys) + 1]], np.float32)
    assert (xs.min() == 0 or ys.min() == 0) == (min(centre) < 50)  # cut where it should be
    response = S.orientation_response(img)
    score, idx, depth, uv = S.fit_templates(
        jnp.asarray(response), jnp.asarray(box), t["xy"], t["bins"], t["valid"],
        jnp.asarray(K, jnp.float32), jnp.array([300.0, 600.0]), box_fit=0.6, k=64)
    # The rendered rotation (or a symmetric one) is among the best templates, with the distance
    # and centre it was rendered at. (A box's outline is the same rectangle or hexagon from
    # many views: several templates fit a clean render perfectly, and verification decides;
    # more of them fit the part of it a cut box shows.) The best template is near the distance.
    assert abs(float(depth[0, 0]) - 420.0) < 0.1 * 420.0
    near = [i for i in range(64)
            if _angle(t["rotations"][int(idx[0, i])].astype(np.float64), R, BOX_SYMMETRIES) < 5]
    assert near, [int(i) for i in idx[0]]
    i = near[0]
    assert abs(float(depth[0, i]) - 420.0) < 0.05 * 420.0
    np.testing.assert_allclose(np.asarray(uv[0, i]), centre, atol=4.0)
    # A cut fit's mean response is scaled by the square root of its share inside (over 60 %).
    floor = 0.85 if min(centre) > 50 else 0.85 * math.sqrt(0.6)
    assert float(score[0, i]) > floor and float(score[0, 0]) >= float(score[0, i])
    # Outside the depth range nothing fits.
    score, *_ = S.fit_templates(
        jnp.asarray(response), jnp.asarray(box), t["xy"], t["bins"], t["valid"],
        jnp.asarray(K, jnp.float32), jnp.array([1000.0, 2000.0]), box_fit=0.6, k=16)
    assert np.all(np.asarray(score) == -1.0)


def _fit_by_loop(response, box, xy, bins, valid, depth_range, box_fit):
    """[R] the template fit's score of every template in one proposal (xywh), -1 where it does
    not fit: the rule of ``fit_templates``' docstring in float64 NumPy, one template at a
    time."""
    H, W = response.shape[1:]
    x0, y0, bw, bh = (float(v) for v in box)
    fx, fy = K[0, 0], K[1, 1]
    left, right, top, bottom = x0 <= 3, x0 + bw >= W - 3, y0 <= 3, y0 + bh >= H - 3
    ax, ay = (left != right) and not (top and bottom), (top != bottom) and not (left and right)
    out = np.full(len(xy), -1.0)
    for r in range(len(xy)):
        pts, b = xy[r][valid[r]].astype(np.float64), bins[r][valid[r]]
        if not len(pts):
            continue
        lo, size = pts.min(0), np.maximum(np.ptp(pts, 0), 1e-3)
        z_h, z_w = fy * size[1] / bh, fx * size[0] / bw
        Z = (min(z_h, z_w) if ax and ay else z_h if ax else z_w if ay
             else math.sqrt(fx * size[0] * fy * size[1] / (bw * bh)))
        pw, ph = fx * size[0] / Z, fy * size[1] / Z
        tx = (x0 + bw - pw if left else x0) if ax else x0 + (bw - pw) / 2
        ty = (y0 + bh - ph if top else y0) if ay else y0 + (bh - ph) / 2
        cw = np.clip(tx + pw, 0, W) - np.clip(tx, 0, W)
        ch = np.clip(ty + ph, 0, H) - np.clip(ty, 0, H)
        inter = (max(min(tx + pw, x0 + bw) - max(tx, x0), 0)
                 * max(min(ty + ph, y0 + bh) - max(ty, y0), 0))
        if (inter / (cw * ch + bw * bh - inter) < box_fit or cw * ch < 0.5 * pw * ph
                or not depth_range[0] <= Z <= depth_range[1]):
            continue
        u = np.round(tx + (pts[:, 0] - lo[0]) * fx / Z).astype(int)
        v = np.round(ty + (pts[:, 1] - lo[1]) * fy / Z).astype(int)
        inside = (u >= 0) & (u < W) & (v >= 0) & (v < H)
        got = response[b[inside], v[inside], u[inside]]
        out[r] = (got.sum() / max(inside.sum(), 0.5 * len(pts), 1)
                  * math.sqrt(inside.sum() / len(pts)))
    return out


def test_fit_scores_every_fitting_template_as_a_loop_over_them_does():
    """The fit scores only the (proposal, template) pairs that fit, gathered into a list: its
    best templates and their scores are those of a float64 loop over every template, for
    proposals inside the image, cut by its sides, of no part and out of the depth range."""
    mesh = _box_mesh()
    t = S.shape_templates(C.mesh_contours(mesh, num_views=100, num_points=200), SMALL)
    T = _pose(Rotation.from_euler("xyz", [25, -10, 40], degrees=True).as_matrix(),
              (150.0, 110.0), 420.0)
    response = S.orientation_response(_render([(mesh, T)], _background()))
    boxes = np.array([[112, 78, 80, 66], [0, 60, 40, 70], [280, 0, 40, 30], [0, 0, 60, 45],
                      [30, 150, 150, 60], [140, 100, 8, 8]], np.float32)
    depth_range = np.array([300.0, 600.0])
    k = 16
    score, idx, *_ = S.fit_templates(
        jnp.asarray(response), jnp.asarray(boxes), t["xy"], t["bins"], t["valid"],
        jnp.asarray(K, jnp.float32), jnp.asarray(depth_range, jnp.float32), box_fit=0.6, k=k)
    score, idx = np.asarray(score), np.asarray(idx)
    fitted = 0
    for b, box in enumerate(boxes):
        want = _fit_by_loop(response, box, t["xy"], t["bins"], t["valid"], depth_range, 0.6)
        fitted += int(np.sum(want > -1))
        best = np.sort(want)[::-1][:k]
        # float32 against float64: a point's pixel may round the other way (1/48 of a score).
        np.testing.assert_allclose(score[b], best, atol=0.045, err_msg=str(b))
        ok = score[b] > -1
        np.testing.assert_allclose(want[idx[b][ok]], score[b][ok], atol=0.045)
        assert np.all(want[idx[b][~ok]] == -1)
    assert 0 < fitted < len(boxes) * len(t["xy"])  # some pairs fit, not all
    assert np.all(score[5] == -1)  # an 8 px box is out of the depth range


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    """A cache folder whose contour models the scene's detector writes and others read."""
    return tmp_path_factory.mktemp("cache")


@pytest.fixture(scope="module")
def scene(cache):
    box, cyl = _box_mesh(), _cylinder_mesh()
    T_box = _pose(Rotation.from_euler("xyz", [20, -15, 30], degrees=True).as_matrix(),
                  (95.0, 120.0), 400.0)
    T_cyl = _pose(Rotation.from_euler("xyz", [80, 10, -35], degrees=True).as_matrix(),
                  (230.0, 115.0), 420.0)
    img = _render([(box, T_box), (cyl, T_cyl)], _background(1))
    objects = [RefineObject(1, box, np.eye(4)[None]), RefineObject(2, cyl, np.eye(4)[None])]
    # The search alone: the verifier (the default) has its own test.
    detector = ShapeSearchDetector(objects, depth_range=(330.0, 500.0), score_threshold=0.1,
                                   max_detections=10, settings=SMALL,
                                   cache_dir=cache / "contours", verifier=None)
    return img, {1: T_box, 2: T_cyl}, objects, detector


def _iou(a, b):
    iw = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    ih = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = iw * ih
    return inter / ((a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter)


def test_detector_finds_each_part_where_it_was_rendered(scene):
    img, truth, objects, detector = scene
    found = detector.detect(img, K)
    assert 2 <= len(found) <= 10
    assert [d.score for d in found] == sorted((d.score for d in found), reverse=True)
    meshes = {o.obj_id: o.mesh for o in objects}
    gt_boxes, best = {}, {}
    for obj_id, T in truth.items():
        X = meshes[obj_id].vertices @ T[:3, :3].T + T[:3, 3]
        uv = X[:, :2] / X[:, 2:] * K[[0, 1], [0, 1]] + K[:2, 2]
        gt_boxes[obj_id] = np.concatenate([uv.min(0), uv.max(0)])
        mine = [d for d in found if d.obj_id == obj_id and _iou(d.box, gt_boxes[obj_id]) >= 0.5]
        assert mine, f"object {obj_id} not found: {[(d.obj_id, d.box) for d in found]}"
        best[obj_id] = mine[0]
        # Its pose: the centre within a tenth of the distance (depth from size, one view).
        c = mine[0].pose[:3, :3] @ meshes[obj_id].center + mine[0].pose[:3, 3]
        c_gt = T[:3, :3] @ meshes[obj_id].center + T[:3, 3]
        assert np.linalg.norm(c - c_gt) < 0.1 * c_gt[2]
    # Each part's detection outscores every detection on the background.
    background = [d.score for d in found
                  if all(_iou(d.box, g) < 0.1 for g in gt_boxes.values())]
    assert min(d.score for d in best.values()) > max(background, default=0.0)


def test_a_part_cut_by_the_image_side_is_found_and_boxed_inside_it(scene):
    """The scene's box moved left until about a third of it is outside the image: found, at
    its distance, its box the part the image shows (the projected vertices' box clipped)."""
    _, truth, objects, detector = scene
    T = _pose(truth[1][:3, :3], (18.0, 120.0), 400.0)
    img = _render([(objects[0].mesh, T), (objects[1].mesh, truth[2])], _background(1))
    X = objects[0].mesh.vertices @ T[:3, :3].T + T[:3, 3]
    uv = X[:, :2] / X[:, 2:] * K[[0, 1], [0, 1]] + K[:2, 2]
    whole = np.concatenate([uv.min(0), uv.max(0)])
    assert whole[0] < -15  # the premise: cut
    seen = np.clip(whole, 0, [HW[1], HW[0], HW[1], HW[0]])
    found = [d for d in detector.detect(img, K) if d.obj_id == 1 and _iou(d.box, seen) >= 0.5]
    assert found, "the cut box was not found"
    d = found[0]
    assert d.box[0] >= 0 and d.box[2] <= HW[1] and _iou(d.box, seen) >= 0.7
    c, c_gt = d.pose[:3, 3], T[:3, 3]  # the box's centre is its origin
    assert np.linalg.norm(c - c_gt) < 0.1 * c_gt[2]


def _gt_boxes(objects, truth):
    meshes = {o.obj_id: o.mesh for o in objects}
    out = {}
    for obj_id, T in truth.items():
        X = meshes[obj_id].vertices @ T[:3, :3].T + T[:3, 3]
        uv = X[:, :2] / X[:, 2:] * K[[0, 1], [0, 1]] + K[:2, 2]
        out[obj_id] = np.concatenate([uv.min(0), uv.max(0)])
    return out


def test_a_cell_detectors_boxes_are_posed_by_the_templates_fit(scene, cache):
    """The cell detector's composition: its network's boxes (here the rendered parts' true
    boxes, a few px off, and a low-scored box on the background) are thresholded, named and
    posed by the part's templates fitted inside them; the pose's centre is where the part was
    rendered."""
    from flax import nnx

    from infer.cell_detect import CellDetector
    from threept_jax.models.dense import DenseConfig, DenseDetector

    img, truth, objects, detector = scene
    meshes = {o.obj_id: o.mesh for o in objects}
    gt = _gt_boxes(objects, truth)
    boxes = np.array([gt[1] + [-3, 2, 2, -2], gt[2] + [2, -3, -2, 3], [250, 180, 300, 230]])
    rows = np.array([0, 1, 0])
    poses, scores = detector.poses_in_boxes(img, K, boxes[:2], rows[:2])
    for obj_id, pose in zip((1, 2), poses):
        c = pose[:3, :3] @ meshes[obj_id].center + pose[:3, 3]
        c_gt = truth[obj_id][:3, :3] @ meshes[obj_id].center + truth[obj_id][:3, 3]
        assert np.linalg.norm(c - c_gt) < 0.1 * c_gt[2]
    assert np.isfinite(scores).all()
    # Abstract (no weights): the network's boxes are set by hand below.
    net = nnx.eval_shape(lambda: DenseDetector(DenseConfig(
        num_classes=3, width=8, depths=(1, 1, 1, 1), neck_width=16, image_size=(64, 96)),
        rngs=nnx.Rngs(0)))
    with pytest.raises(ValueError, match=r"trained on the parts \[2, 5, 9\]; \[1\]"):
        CellDetector(net, [2, 5, 9], objects)
    cell = CellDetector(net, [2, 1, 9], objects, depth_range=(330.0, 500.0), settings=SMALL,
                        cache_dir=cache / "contours", score_threshold=0.3,
                        templates_threshold=None)  # the network's boxes alone
    # The network's output classes: 0 -> part 2, 1 -> part 1, 2 -> part 9 (not queried).
    cell._boxes = lambda image: (np.concatenate([boxes, boxes[:1]]),
                                 np.array([0.9, 0.8, 0.2, 0.7]), np.array([1, 0, 1, 2]))
    found = cell.detect(img, K)
    assert sorted(d.obj_id for d in found) == [1, 2] and found.best_score == pytest.approx(0.9)
    # The network's score ranks the boxes, the outline's calibrated score the poses (and the
    # order: best pose first, :func:`infer.cell_detect.merge`).
    assert {d.obj_id: d.score for d in found} == pytest.approx({1: 0.9, 2: 0.8})
    assert [d.pose_score for d in found] == sorted((d.pose_score for d in found), reverse=True)
    for d in found:
        assert 0.0 < d.pose_score < 1.0 and d.pose_scores == pytest.approx([d.pose_score])
        c = d.pose[:3, :3] @ meshes[d.obj_id].center + d.pose[:3, 3]
        c_gt = truth[d.obj_id][:3, :3] @ meshes[d.obj_id].center + truth[d.obj_id][:3, 3]
        assert np.linalg.norm(c - c_gt) < 0.1 * c_gt[2]
    # The templates detector's own detections joined: the same two parts, each once, where
    # they were rendered (a part both found is kept with the better-scored pose).
    union = CellDetector(net, [2, 1, 9], objects, depth_range=(330.0, 500.0), settings=SMALL,
                         cache_dir=cache / "contours", score_threshold=0.3)
    union._boxes = cell._boxes
    merged = union.detect(img, K)
    assert sorted(d.obj_id for d in merged) == [1, 2]
    for d in merged:
        c = d.pose[:3, :3] @ meshes[d.obj_id].center + d.pose[:3, 3]
        c_gt = truth[d.obj_id][:3, :3] @ meshes[d.obj_id].center + truth[d.obj_id][:3, 3]
        assert np.linalg.norm(c - c_gt) < 0.1 * c_gt[2]
    # A box where no template of its part fits (far too large for the depth range): no pose,
    # no detection.
    cell._boxes = lambda image: (np.array([[0.0, 0.0, 320.0, 240.0]]), np.array([0.9]),
                                 np.array([1]))
    assert len(cell.detect(img, K)) == 0


def test_merge_keeps_the_best_pose_of_each_place():
    """cell_detect.merge by hand: part 1 found twice 20 mm apart at 500 mm depth (under 10 %
    of it) is one detection, the better pose score's; part 2 at that place, and part 1 100 mm
    away, are others; a detection without a pose score ranks by its score; ``most`` caps."""
    from infer.cell_detect import merge
    from infer.detect import Detection

    def det(obj_id, x, score, pose_score=None):
        T = np.eye(4)
        T[:3, 3] = [x, 0.0, 500.0]
        return Detection(obj_id, np.zeros(4), score, T[None], np.ones(1), np.zeros(0),
                         pose_score=pose_score)

    centers = {1: np.array([0.0, 0.0, 10.0]), 2: np.zeros(3)}
    a, b = det(1, 0.0, 0.9, 0.6), det(1, 20.0, 0.3, 0.8)
    c, d, e = det(2, 0.0, 0.5), det(1, 100.0, 0.2, 0.7), det(1, 45.0, 0.9, 0.1)
    assert merge([a, b, c, d, e], centers, 10) == [b, d, c]  # e: 25 mm from b
    assert merge([a, b, c, d, e], centers, 2) == [b, d]
    assert merge([], centers, 3) == []


def test_box_variants_by_hand():
    """A 100 x 40 box at (10, 20): scaled by 0.5 about its centre (60, 40), then moved by 10 %
    of the given box's width and height."""
    v = S.box_variants(np.array([[10.0, 20.0, 100.0, 40.0]]), (0.5, 1.0), 0.1)
    assert v.shape == (1, 10, 4)
    np.testing.assert_allclose(v[0, :5], [[35, 30, 50, 20], [45, 30, 50, 20], [25, 30, 50, 20],
                                          [35, 34, 50, 20], [35, 26, 50, 20]])
    np.testing.assert_allclose(v[0, 5], [10, 20, 100, 40])
    np.testing.assert_allclose(S.box_variants(np.array([[0.0, 0.0, 8.0, 8.0]]), (1.0,), 0.0),
                               [[[0, 0, 8, 8]]])


def test_featureless_images_give_no_detections(scene):
    _, _, _, detector = scene
    for value in (0, 128):
        assert len(detector.detect(np.full(HW + (3,), value, np.uint8), K)) == 0


def test_noisy_featureless_images_give_no_detections_at_the_default_threshold(scene, cache):
    """A dark or grey image with sensor noise, or uniform noise: no box at the default score
    threshold (at 0.1 such images gave 50-60), where the rendered parts are still found."""
    img, truth, objects, _ = scene
    detector = ShapeSearchDetector(objects, depth_range=(330.0, 500.0), max_detections=10,
                                   settings=SMALL, cache_dir=cache / "contours")
    assert detector.score_threshold == 0.4
    rng = np.random.default_rng(0)
    for noisy in (10 + rng.normal(0, 3, HW + (3,)), 128 + rng.normal(0, 8, HW + (3,)),
                  rng.uniform(0, 255, HW + (3,))):
        assert len(detector.detect(np.clip(noisy, 0, 255).astype(np.uint8), K)) == 0
    assert {d.obj_id for d in detector.detect(img, K)} == set(truth)


def test_bad_input_is_refused_with_the_reason(scene):
    img, _, objects, detector = scene
    with pytest.raises(ValueError, match="uint8 RGB"):
        detector.detect(img.astype(np.float32), K)
    with pytest.raises(ValueError, match="K"):
        detector.detect(img, np.eye(3) * np.nan)
    with pytest.raises(ValueError, match="depth_range"):
        ShapeSearchDetector(objects, depth_range=(500.0, 300.0))
    with pytest.raises(ValueError, match="no objects"):
        ShapeSearchDetector([])


def test_api_runs_the_templates_detector_on_one_view_and_on_a_rig(scene, cache):
    img, truth, objects, _ = scene
    models = infer.load(detector="templates", refiner="contour", cache_dir=cache)
    assert models.detector is None and models.shape_search is not None
    models.shape_search = SMALL
    found = infer.run_scene([img], [K], objects, models, refine=False, with_masks=False,
                            depth_range=(330.0, 500.0), max_detections=10)
    assert {1, 2} <= {x.obj_id for x in found}
    # A rig: the scene rendered again by a second camera 40 mm to the side (the world is the
    # first camera's frame). Each part is found in both views and fused
    # (infer.scene.fuse_posed_views), its centre within 6 % of its distance of the truth.
    second = np.eye(4)
    second[0, 3] = 40.0
    meshes = {o.obj_id: o.mesh for o in objects}
    img2 = _render([(meshes[o], second @ T) for o, T in truth.items()], _background(2))
    rig = infer.run_scene([img, img2], [infer.Camera(K, T_cam_world=np.eye(4)),
                                        infer.Camera(K, T_cam_world=second)], objects, models,
                          refine=False, with_masks=False, depth_range=(330.0, 500.0),
                          max_detections=10)
    for obj_id, T in truth.items():
        c_gt = T[:3, :3] @ meshes[obj_id].center + T[:3, 3]
        near = [x for x in rig if x.obj_id == obj_id and sorted(x.boxes) == [0, 1]
                and np.linalg.norm(x.T_world_obj[:3, :3] @ meshes[obj_id].center
                                   + x.T_world_obj[:3, 3] - c_gt) < 0.06 * c_gt[2]]
        assert near, [(x.obj_id, sorted(x.boxes), x.T_world_obj[:3, 3]) for x in rig]
    with pytest.raises(ValueError, match="num_scales"):
        infer.run_scene([img], [K], objects, models, refine=False, num_scales=2)
    with pytest.raises(ValueError, match="detector must be one of"):
        infer.load(detector="yolo")
    with pytest.raises(ValueError, match="3PT-D"):
        infer.load("runs/x", detector="templates")
    # The learned verifier checks the templates (and cell) detector's candidates by default
    # (it ran above), not 3PT-D's.
    assert models.scene_detector(objects, depth_range=(330.0, 500.0)).verifier is not None
    plain = infer.load(detector="templates", refiner=None, cache_dir=cache,
                       templates_verifier=False)
    plain.shape_search = SMALL
    assert plain.scene_detector(objects, depth_range=(330.0, 500.0)).verifier is None
    with pytest.raises(ValueError, match="templates_verifier checks"):
        infer.load(detector="3pt", templates_verifier=True)


def test_images_command_with_the_templates_detector(scene, cache, tmp_path, capsys,
                                                   monkeypatch):
    """``python -m infer images --detector templates``: no network, both parts in
    instances.json; with a detector run as well, a message saying to drop one."""
    import infer.api
    from infer.cli import main

    monkeypatch.setattr(infer.api, "ShapeSearchSettings", lambda: SMALL)  # compiled above

    img, truth, objects, _ = scene
    args = []
    for o in objects:
        path = tmp_path / f"obj_{o.obj_id}.ply"
        trimesh.Trimesh(o.mesh.vertices, o.mesh.faces, process=False).export(path)
        args += ["--mesh", f"{o.obj_id}={path}"]
    cv2.imwrite(str(tmp_path / "scene.png"), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
    args += ["--image", str(tmp_path / "scene.png"), "--K", "400,400,159.5,119.5",
             "--depth-range", "330", "500", "--cache-dir", str(cache)]
    main(["images", "--detector", "templates", "--max-detections", "10",
          "--out", str(tmp_path / "out"), *args])
    rows = json.loads((tmp_path / "out" / "instances.json").read_text())["instances"]
    assert {1, 2} <= {r["obj_id"] for r in rows}
    with pytest.raises(SystemExit) as e:
        main(["images", "--detector", "templates", "--workdir", str(tmp_path), "--out",
              str(tmp_path / "out2"), *args])
    assert e.value.code == 2
    assert "drop one of them" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        main(["images", "--detector", "3pt", "--templates-verifier", "--out",
              str(tmp_path / "out3"), *args])
    assert e.value.code == 2
    assert "--templates-verifier checks" in capsys.readouterr().err
    # On by default (None: the detector decides), off with --no-templates-verifier.
    from infer.cli import build_parser

    for flag, want in (([], None), (["--templates-verifier"], True),
                       (["--no-templates-verifier"], False)):
        parsed = build_parser().parse_args(["images", "--out", "o", *args, *flag])
        assert parsed.templates_verifier is want


def _perimeter_covariance(polygon):
    """[2, 2] covariance of points spread evenly along a closed polygon's perimeter [k, 2]: the
    line integral of x x^T over each side, L (p p^T / 3 + (p q^T + q p^T) / 6 + q q^T / 3)."""
    p, q = polygon, np.roll(polygon, -1, 0)
    L = np.linalg.norm(q - p, axis=1)
    mean = np.sum(L[:, None] * (p + q) / 2, 0) / L.sum()
    p, q = p - mean, q - mean
    second = sum(li * (np.outer(a, a) / 3 + (np.outer(a, b) + np.outer(b, a)) / 6
                       + np.outer(b, b) / 3) for li, a, b in zip(L, p, q))
    return second / L.sum()


def test_outline_features_of_a_plate_against_its_projected_corners():
    """A 50 x 50 x 2 mm plate seen face-on, edge-on and obliquely from three of its stored
    views, far away (nearly orthographic): thinness and elongation against the convex hull of
    its 8 projected corners (its silhouette), the size against its bounding sphere, the LINE-2D
    similarity near 1 on its own render and 0 on a grey image, the clutter in its box small on
    the render (its face is flat) and 0 on the grey image; the given scores pass through."""
    from scipy.spatial import ConvexHull

    from threept_jax.geometry.grids import viewpoint_rotation

    plate = _box_mesh((50.0, 50.0, 2.0))
    contours = C.mesh_contours(plate, num_views=100, num_points=200)
    model = C.stack_contours([contours])
    dirs = contours["directions"]
    views = [int(np.argmax(dirs[:, 2])), int(np.argmin(np.abs(dirs[:, 2]))), 37]
    Kf = np.array([[5000.0, 0, 159.5], [0, 5000.0, 119.5], [0, 0, 1]])
    corners = np.array(trimesh.creation.box((50.0, 50.0, 2.0)).vertices)
    poses = []
    for v in views:
        T = np.eye(4)
        T[:3, :3] = viewpoint_rotation(dirs[v])
        T[:3, 3] = [0.0, 0.0, 5000.0]
        poses.append(T)
    poses = np.stack(poses)
    n = len(views)
    given = np.linspace(0.2, 0.6, n)
    img = _render([(plate, poses[0])], np.full(HW + (3,), 90, np.uint8), Kf)
    out = {}
    for name, image in (("render", img), ("grey", np.full(HW + (3,), 128, np.uint8))):
        out[name] = np.asarray(S.outline_features(
            model, jnp.asarray(S.orientation_response(image)), jnp.asarray(Kf, jnp.float32),
            jnp.asarray(poses, jnp.float32), jnp.zeros(n, jnp.int32),
            jnp.asarray(given, jnp.float32), jnp.asarray(given + 0.1, jnp.float32),
            jnp.asarray(given + 0.2, jnp.float32)))
    f = out["render"]
    col = {k: i for i, k in enumerate(S.FEATURES)}
    np.testing.assert_allclose(f[:, col["contour"]], given, atol=1e-6)
    np.testing.assert_allclose(f[:, col["template"]], given + 0.1, atol=1e-6)
    np.testing.assert_allclose(f[:, col["lines"]], given + 0.2, atol=1e-6)
    radius = float(contours["radius"])
    np.testing.assert_allclose(f[:, col["size"]], np.log(2 * radius), rtol=1e-4)
    for i, T in enumerate(poses):
        X = corners @ T[:3, :3].T + T[:3, 3]
        uv = X[:, :2] / X[:, 2:] * 5000.0
        hull = uv[ConvexHull(uv).vertices]
        ev = np.linalg.eigvalsh(_perimeter_covariance(hull))
        np.testing.assert_allclose(f[i, col["thinness"]], np.sqrt(ev[0]) / radius, atol=0.03)
        np.testing.assert_allclose(f[i, col["elongation"]], np.sqrt(ev[0] / ev[1]), atol=0.03)
    assert f[0, col["elongation"]] > 0.9 and f[1, col["elongation"]] < 0.3  # face-on, edge-on
    # Only the face-on plate was rendered: its outline lies on the image's edges, inside its
    # box only its flat face (edges within the 1 px spread of its border).
    assert f[0, col["line2d"]] > 0.8
    assert 0.0 < f[0, col["clutter"]] < 0.3
    np.testing.assert_allclose(out["grey"][:, [col["line2d"], col["clutter"]]], 0.0)


def test_score_weights_are_recovered_from_a_known_logistic_model():
    """Candidates drawn from a logistic model with known weights: the fit returns them (within
    a few standard errors at 40000 draws) and ``calibrated_score`` is that model's
    probability, checked by hand on one row."""
    rng = np.random.default_rng(3)
    n = 40000
    f = np.column_stack([rng.uniform(0.05, 0.95, (n, 3)), rng.uniform(0.5, 1.0, n),
                         rng.uniform(0.0, 0.6, n), rng.uniform(0.1, 1.0, n),
                         rng.uniform(3.0, 6.0, n), rng.uniform(0.0, 0.8, n)])
    w = np.array([0.8, -0.4, 1.2, 2.0, 3.0, -1.0, 0.5, -2.0, -3.0])
    logit = lambda p: np.log(p / (1 - p))  # noqa: E731
    z = (w[0] * logit(f[:, 0]) + w[1] * logit(f[:, 1]) + w[2] * logit(f[:, 2])
         + f[:, 3:] @ w[3:8] + w[8])
    right = rng.random(n) < 1 / (1 + np.exp(-z))
    got = S.fit_score_weights(f, right, l2=0.0)
    np.testing.assert_allclose(got[:-1], w[:-1], atol=0.25)
    np.testing.assert_allclose(got[-1], w[-1], atol=0.6)  # inputs far from 0: a wider error
    np.testing.assert_allclose(S.calibrated_score(f[:100], got), 1 / (1 + np.exp(-z[:100])),
                               atol=0.05)
    row = np.array([[0.5, 0.5, 0.5, 1.0, 0.0, 1.0, 0.0, 0.5]])  # z = 2 - 1 - 1 - 3
    np.testing.assert_allclose(S.calibrated_score(row, w), [1 / (1 + np.exp(3.0))], rtol=1e-9)


def test_part_weights_are_recovered_per_part():
    """Two parts' candidates drawn from two known logistic models (a third part with three
    right candidates): ``fit_part_weights`` returns each part's model (within a few standard
    errors) and leaves the third out; ``calibrated_score`` with one row of weights per
    candidate is each row's own model, checked by hand."""
    rng = np.random.default_rng(5)
    n = 30000
    F = len(S.FEATURES)

    def draw(m):
        return np.column_stack([rng.uniform(0.05, 0.95, (m, 3)), rng.uniform(0.5, 1.0, m),
                                rng.uniform(0.0, 0.6, m), rng.uniform(0.1, 1.0, m),
                                rng.uniform(3.0, 6.0, m), rng.uniform(0.0, 0.8, m)])

    logit = lambda p: np.log(p / (1 - p))  # noqa: E731
    truth = {3: np.array([0.8, -0.4, 1.2, 2.0, 3.0, -1.0, 0.5, -2.0, -3.0]),
             8: np.array([-0.5, 1.0, 0.3, -1.5, -2.0, 2.5, -0.5, 1.5, 1.0])}
    feats, right, parts = [], [], []
    for p, w in truth.items():
        f = draw(n)
        z = logit(f[:, :3]) @ w[:3] + f[:, 3:] @ w[3:F] + w[F]
        feats.append(f)
        right.append(rng.random(n) < 1 / (1 + np.exp(-z)))
        parts.append(np.full(n, p))
    feats.append(draw(50))
    right.append(np.arange(50) < 3)  # part 9: too few right candidates to fit
    parts.append(np.full(50, 9))
    got = S.fit_part_weights(np.concatenate(feats), np.concatenate(right),
                             np.concatenate(parts), l2=0.0)
    assert sorted(got) == [3, 8]
    for p, w in truth.items():
        np.testing.assert_allclose(got[p][:-1], w[:-1], atol=0.3)
        np.testing.assert_allclose(got[p][-1], w[-1], atol=0.8)
    rows = np.array([[0.5, 0.5, 0.5, 1.0, 0.0, 1.0, 0.0, 0.5]] * 2)
    # Row 0 with part 3's weights: z = 2 - 1 - 1 - 3; row 1 with part 8's: -1.5 + 2.5 + 0.75 + 1.
    np.testing.assert_allclose(S.calibrated_score(rows, np.stack([truth[3], truth[8]])),
                               1 / (1 + np.exp([3.0, -2.75])), rtol=1e-9)


def test_a_cells_score_calibration_scores_its_parts(scene, cache, tmp_path):
    """A calibration file whose part 1 scores every candidate logit(0.77) (zero weights, that
    bias): every detection of part 1 scores 0.77, part 2 keeps the shared weights; the file
    goes through ``infer.load(templates_score=)``; a file of other features, a wrong length,
    a missing file or a 3PT-D load are refused with what to do."""
    img, _, objects, _ = scene
    F = len(S.FEATURES)
    constant = [0.0] * F + [float(np.log(0.77 / 0.23))]
    path = tmp_path / "cell_score.json"
    path.write_text(json.dumps({"features": [*S.FEATURES, "bias"],
                                "parts": {"1": constant, "7": constant}}))
    # The calibration's own scores (the verifier, on by default, has its own test).
    models = infer.load(detector="templates", refiner=None, cache_dir=cache,
                        templates_score=path, templates_verifier=False)
    assert models.templates_score == {1: tuple(constant), 7: tuple(constant)}
    models.shape_search = SMALL
    detector = models.scene_detector(objects, depth_range=(330.0, 500.0), score_threshold=0.0,
                                     max_detections=50)
    c = detector.candidates(img, K)
    shared = S.calibrated_score(c.features[c.obj == 1], S.SCORE_WEIGHTS)  # row 1: part 2
    found = detector.detect(img, K)
    assert {d.obj_id for d in found} == {1, 2}
    for d in found:
        if d.obj_id == 1:
            assert d.score == pytest.approx(0.77, abs=1e-9)
        else:
            assert np.min(np.abs(shared - d.score)) < 1e-9
    # The cell detector's templates score the same way with the file (its poses' scores and
    # its templates' detections): part 1's weights are the file's, part 2's the shared ones.
    from flax import nnx

    from threept_jax.data import dense_run
    from threept_jax.models.dense import DenseConfig, DenseDetector

    cfg = DenseConfig(num_classes=2, width=8, depths=(1, 1, 1, 1), neck_width=16,
                      image_size=(64, 96))
    _, params, stats = nnx.split(DenseDetector(cfg, rngs=nnx.Rngs(0)), nnx.Param, nnx.BatchStat)
    dense_run.save(tmp_path / "cell", cfg, [1, 2], params, stats, {"steps": 1})
    cell = infer.load(tmp_path / "cell", refiner=None, cache_dir=cache, templates_score=path)
    cell.shape_search = SMALL
    weights = cell.scene_detector(objects, depth_range=(330.0, 500.0)).shapes.score_weights
    np.testing.assert_array_equal(weights, [constant, S.SCORE_WEIGHTS])
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"features": ["contour", "bias"], "parts": {"1": [0.0, 1.0]}}))
    with pytest.raises(ValueError, match="fitted on the features"):
        infer.load(detector="templates", cache_dir=None, templates_score=bad)
    for parts, match in (({"1": [0.0]}, "part 1 must be"), ({"1": ["a"] * (F + 1)}, "part 1"),
                         ({"gear": constant}, "not an obj_id")):
        bad.write_text(json.dumps({"features": [*S.FEATURES, "bias"], "parts": parts}))
        with pytest.raises(ValueError, match=match):
            infer.load(detector="templates", cache_dir=None, templates_score=bad)
    with pytest.raises(FileNotFoundError, match="train.templates_score --cell"):
        infer.load(detector="templates", cache_dir=None, templates_score=tmp_path / "no.json")
    with pytest.raises(ValueError, match="calibrates the templates detector"):
        infer.load(detector="3pt", cache_dir=None, templates_score=path)
    with pytest.raises(ValueError, match="score weights of part 2"):
        ShapeSearchDetector(objects, score_weights={2: [1.0, 2.0]})


def test_an_image_is_searched_once_whatever_the_score(scene, cache, monkeypatch):
    """The verified candidates do not depend on the score weights: within
    ``shared_searches`` a second detector of the same parts, depth range and settings, with a
    cell's weights (part 1 scores every candidate 0.77), takes the first's candidates of an
    image without fitting a template (read-only, equal to a search outside it) and scores them
    with its own weights; another depth range, other parts, other intrinsics or a changed image
    search again, a nested context shares the outer one's, and outside it every call
    searches."""
    from infer.shape_detect import shared_searches

    img, _, objects, detector = scene
    fits = []
    fit = D.fit_templates
    monkeypatch.setattr(D, "fit_templates", lambda *a, **k: fits.append(1) or fit(*a, **k))
    alone = detector.candidates(img, K)
    assert len(fits) == 2 and alone.xyxy.flags.writeable  # one fit per part
    constant = [0.0] * len(S.FEATURES) + [float(np.log(0.77 / 0.23))]
    other = ShapeSearchDetector(objects, depth_range=(330.0, 500.0), score_threshold=0.1,
                                max_detections=10, settings=SMALL, cache_dir=cache / "contours",
                                score_weights={1: constant}, verifier=None)
    farther = ShapeSearchDetector(objects, depth_range=(330.0, 600.0), settings=SMALL,
                                  cache_dir=cache / "contours", verifier=None)
    changed = img.copy()
    changed[0, 0] ^= 1
    with shared_searches():
        first = detector.candidates(img, K)
        assert len(fits) == 4
        assert other.candidates(img, K.astype(np.float32)) is first and len(fits) == 4
        assert not any(a.flags.writeable for a in first)
        found = other.detect(img, K)
        assert len(fits) == 4 and 1 in {d.obj_id for d in found}
        assert all(d.score == pytest.approx(0.77, abs=1e-9) for d in found if d.obj_id == 1)
        farther.candidates(img, K)
        detector.candidates(changed, K)
        assert len(fits) == 8
        box_only = ShapeSearchDetector(objects[:1], depth_range=(330.0, 500.0), settings=SMALL,
                                       cache_dir=cache / "contours", verifier=None)
        box_only.candidates(img, K)  # other parts
        assert len(fits) == 9
        detector.candidates(img, K * [[1.01], [1.01], [1.0]])  # other intrinsics
        assert len(fits) == 11
        with shared_searches():  # nested: the outer searches stay shared
            assert detector.candidates(img, K) is first and len(fits) == 11
    for a, b in zip(first, alone):
        np.testing.assert_array_equal(a, b)
    other.candidates(img, K)
    assert len(fits) == 13


def test_a_right_candidate_is_its_part_at_iou_one_half():
    """Hand-derived: a 10 x 10 box against one shifted by 5 px (IoU 50 / 150 = 1/3) and by
    2 px in x (IoU 80 / 120 = 2/3), of the same part or another; no instances, no rows."""
    cand = np.array([[0, 0, 10, 10], [5, 0, 15, 10], [2, 0, 12, 10], [2, 0, 12, 10]], float)
    right = S.right_candidates(cand, np.array([1, 1, 1, 2]), np.array([[0, 0, 10, 10]]),
                               np.array([1]))
    assert right[:, 0].tolist() == [True, False, True, False]
    assert S.right_candidates(cand, np.ones(4, int), np.zeros((0, 4)),
                              np.zeros(0, int)).shape == (4, 0)


def test_verifier_boxes_by_hand():
    """Square, centred on the outline box, 1.3 times its longer side, at least 16 px."""
    got = S.verifier_boxes(np.array([[10.0, 20.0, 50.0, 40.0], [100.0, 100.0, 104.0, 102.0]]))
    np.testing.assert_allclose(got, [[4.0, 4.0, 56.0, 56.0], [94.0, 93.0, 110.0, 109.0]])


def test_verifier_inputs_against_opencv_and_a_full_image_render(scene):
    """The crop is the image warped by OpenCV to the crop box (bilinear, the crop's pixel
    convention), within a grey level; the render is the part rendered into the whole image at
    its pose, warped the same way (nearest): the silhouettes agree to IoU 0.9, edges lie on
    or inside them, and shading is zero outside."""
    img, truth, objects, detector = scene
    poses = np.stack([truth[1], truth[2]])
    meshes = D.raster_meshes(objects)
    xyxy = np.array([[50.0, 80.0, 140.0, 160.0], [190.0, 70.0, 270.0, 150.0]])
    crops, renders = S.verifier_inputs(img, K, poses, np.array([0, 1]), xyxy, meshes)
    assert crops.shape == renders.shape == (2, 64, 64, 3) and crops.dtype == np.uint8
    for i, box in enumerate(S.verifier_boxes(xyxy)):
        s = 64 / (box[2] - box[0])
        # Output pixel (i, j) samples the image at ((i + 0.5) / s + x0 - 0.5, ...).
        A = np.array([[s, 0, s * (0.5 - box[0]) - 0.5], [0, s, s * (0.5 - box[1]) - 0.5]])
        want = cv2.warpAffine(img.astype(np.float32), A, (64, 64), flags=cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_CONSTANT)
        assert np.abs(crops[i].astype(np.float32) - want).max() <= 1.0 + 1e-3
        full = np.asarray(render(meshes[i], poses[i].astype(np.float32), K.astype(np.float32), HW,
                                 ("mask",))["mask"]).astype(np.uint8)
        mask = cv2.warpAffine(full, A, (64, 64), flags=cv2.INTER_NEAREST) > 0
        got = renders[i, ..., 0] > 0
        assert (got & mask).sum() / (got | mask).sum() > 0.9
        assert set(np.unique(renders[i, ..., 0])) == {0, 255}
        assert renders[i, ..., 1][~got].max() == 0 and renders[i, ..., 1].max() == 255
        assert renders[i, ..., 2][~got].max() == 0 and renders[i, ..., 2][got].mean() > 50


def test_fitting_with_evidence_moves_only_the_bias():
    """A constant evidence c is a shift of the log-odds: the fit's weights are those without
    it and its bias is theirs minus c; per part too."""
    rng = np.random.default_rng(3)
    f = np.column_stack([rng.uniform(0.05, 0.95, (4000, 3)), rng.uniform(0.5, 1.0, 4000),
                         rng.uniform(0.0, 0.6, 4000), rng.uniform(0.1, 1.0, 4000),
                         rng.uniform(3.0, 6.0, 4000), rng.uniform(0.0, 0.8, 4000)])
    right = rng.random(4000) < 1 / (1 + np.exp(-(4.0 * f[:, 0] - 2.0)))
    plain = S.fit_score_weights(f, right)
    shifted = S.fit_score_weights(f, right, evidence=1.5)
    # Within L-BFGS-B's tolerance.
    np.testing.assert_allclose(shifted[:-1], plain[:-1], atol=2e-3)
    np.testing.assert_allclose(shifted[-1], plain[-1] - 1.5, atol=5e-3)
    parts = np.repeat([1, 2], 2000)
    per = S.fit_part_weights(f, right, parts, evidence=np.full(4000, -0.5))
    for p in (1, 2):
        mine = parts == p
        np.testing.assert_allclose(per[p], S.fit_score_weights(f[mine], right[mine])
                                   + np.eye(9)[8] * 0.5, atol=5e-3)
    np.testing.assert_allclose(S.calibrated_score(f[:5], plain, evidence=0.7),
                               S.calibrated_score(f[:5], plain[:-1].tolist() + [plain[-1] + 0.7]),
                               rtol=1e-12)


def test_the_shipped_verifier_adds_its_evidence_to_the_score(scene, cache, monkeypatch):
    """Without a verifier the evidence is zero; with the shipped one (the default, with the
    shared score or a cell's calibration) each detection's score is the logistic model of its
    candidate's features plus the verifier's evidence on its crop and render (by hand), the
    same candidates otherwise, from the same search (the evidence is added after it); inside
    ``shared_searches`` a detector of the same search with a cell's calibration reuses that
    evidence (the verifier's inputs built once)."""
    from infer.shape_detect import shared_searches

    img, _, objects, detector = scene
    assert detector.verifier is None and detector.rasters == []
    plain = detector.candidates(img, K)
    np.testing.assert_array_equal(plain.evidence, 0.0)
    checked = ShapeSearchDetector(objects, depth_range=(330.0, 500.0), score_threshold=0.1,
                                  max_detections=10, settings=SMALL,
                                  cache_dir=cache / "contours")
    assert checked.verifier is not None
    calibrated = ShapeSearchDetector(objects, settings=SMALL, cache_dir=cache / "contours",
                                     score_weights={1: S.SCORE_WEIGHTS})
    assert calibrated.verifier is not None
    assert checked._search.digest() == detector._search.digest()
    c = checked.candidates(img, K)
    np.testing.assert_array_equal(c.poses, plain.poses)
    np.testing.assert_array_equal(c.features, plain.features)
    x = S.score_inputs(c.features).astype(np.float32)
    crops, renders = S.verifier_inputs(img, K, c.poses, c.obj, c.xyxy, checked.rasters)
    evidence = np.asarray(checked.verifier(crops, renders, x))
    np.testing.assert_allclose(c.evidence, evidence, atol=1e-5)
    assert np.abs(evidence).max() > 1e-3
    z = x.astype(np.float64) @ np.asarray(S.SCORE_WEIGHTS)[:-1] + S.SCORE_WEIGHTS[-1]
    want = 1 / (1 + np.exp(-(z + evidence)))
    for d in checked.detect(img, K):
        assert np.min(np.abs(want - d.score)) < 1e-5
    same_search = ShapeSearchDetector(objects, depth_range=(330.0, 500.0), settings=SMALL,
                                      cache_dir=cache / "contours",
                                      score_weights={1: S.SCORE_WEIGHTS})
    built = []
    inputs = D.verifier_inputs
    monkeypatch.setattr(D, "verifier_inputs", lambda *a: built.append(1) or inputs(*a))
    with shared_searches():
        shared, alone = checked.candidates(img, K), detector.candidates(img, K)
        assert shared.poses is alone.poses  # one search
        np.testing.assert_allclose(shared.evidence, evidence, atol=1e-5)
        np.testing.assert_array_equal(alone.evidence, 0.0)
        assert same_search.candidates(img, K).evidence is shared.evidence and len(built) == 1
    np.testing.assert_array_equal(same_search.candidates(img, K).evidence, shared.evidence)
    assert len(built) == 2  # outside it, computed again
    with pytest.raises(ValueError, match="verifier must be"):
        ShapeSearchDetector(objects, settings=SMALL, cache_dir=cache / "contours",
                            verifier="mine")
