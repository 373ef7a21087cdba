"""The 3PT-R refinement step with an oracle network (issue 14, section 3 acceptance tests).

A T-LESS mesh painted with its own object coordinates (``testing.refiner_oracle``) is rendered at
the ground-truth pose into crops around the current hypothesis (``crop_boxes``); the oracle's
descriptors are a peaked kernel of 3D distance. Poses and errors are computed in float64
NumPy/SciPy, independently of the step's geometry code.
"""

import warnings

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from threept_jax.geometry.camera import crop_intrinsics, look_at
from threept_jax.geometry.framing import crop_boxes
from threept_jax.pipeline.refinement import (
    RefineSettings,
    reciprocal_matches,
    refine_step,
    render_hypotheses,
)
from threept_jax.render.mesh import load_mesh, prepare_mesh, to_raster_mesh
from threept_jax.render.raster import render
from threept_jax.testing.refiner_oracle import make_oracle, xyz_colored

MESH = "/work/shared/meshes/bop/tless/models/obj_000018.ply"  # no symmetry, 111 mm
CROP = MAP = 32
NUM_MATCHES = 128
K_FULL = np.array([[800.0, 0, 320], [0, 800.0, 240], [0, 0, 1]], np.float32)
EYES = np.array([[500, 0, 150], [-250, 430, 100], [-250, -430, -100]], np.float32)  # mm

ORACLE = make_oracle(MAP)
NOISE = 0.1  # the noisy oracle's descriptor noise (make_oracle)
TRACES = []


def _step(noise, mesh, crops, crop_K, T_cam_world, hypotheses):
    """One refinement step with the oracle of descriptor noise ``noise`` (traced: the clean and
    the noisy oracle share one compilation per view count)."""
    TRACES.append(crops.shape)  # runs only while tracing
    return refine_step(make_oracle(MAP, noise=noise), mesh, crops, crop_K, T_cam_world,
                       hypotheses, output_size=MAP,
                       settings=RefineSettings(num_matches=NUM_MATCHES, ambient=1.0))


STEP = jax.jit(_step)


@pytest.fixture(scope="module")
def scene():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the T-LESS file repeats faces
        mesh = xyz_colored(prepare_mesh(load_mesh(MESH), max_faces=1024))
    T_cw = np.stack([np.asarray(look_at(e, np.zeros(3))) for e in EYES]).astype(np.float64)
    R = Rotation.random(random_state=1).as_matrix()
    T_gt = np.eye(4)
    T_gt[:3, :3] = R
    T_gt[:3, 3] = -R @ mesh.center + [5.0, -3.0, 2.0]
    return mesh, to_raster_mesh(mesh), T_cw, T_gt


def _perturbed(T_gt, T_cw0, seed, depth_sign):
    """20 degrees about a random axis; the centre moved 10 % of its depth along view 0's ray."""
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    T = T_gt.copy()
    T[:3, :3] = T_gt[:3, :3] @ Rotation.from_rotvec(np.deg2rad(20.0) * axis).as_matrix()
    c = T_cw0[:3, :3] @ T_gt[:3, 3] + T_cw0[:3, 3]
    T[:3, 3] = T_cw0[:3, :3].T @ (c * (1.0 + 0.1 * depth_sign) - T_cw0[:3, 3])
    return T


def _errors(T, T_gt, T_cw0):
    """(rotation deg, translation mm, depth mm along view 0's optical axis)."""
    rot = np.rad2deg(Rotation.from_matrix(T[:3, :3] @ T_gt[:3, :3].T).magnitude())
    d = T[:3, 3] - T_gt[:3, 3]
    return rot, float(np.linalg.norm(d)), float(abs(T_cw0[2, :3] @ d))


def _refine(scene, noise, T, views, iterations=3):
    """Crop around the hypothesis, render the real crops at the ground truth, step; repeat."""
    mesh, rmesh, T_cw, T_gt = scene
    T_cw = T_cw[:views]
    Kf = np.repeat(K_FULL[None], views, 0)
    errors = []
    for _ in range(iterations):
        box = crop_boxes(mesh, T, T_cw, Kf)
        crop_K = crop_intrinsics(jnp.asarray(Kf), box, (CROP, CROP))
        crops = render(rmesh, T_cw @ T_gt, crop_K, (CROP, CROP), ("rgb",), ambient=1.0)["rgb"]
        out = STEP(jnp.float32(noise), rmesh, crops, crop_K, jnp.asarray(T_cw, jnp.float32),
                   jnp.asarray(T[None], jnp.float32))
        T = np.asarray(out.hypotheses[0], np.float64)
        errors.append(_errors(T, T_gt, T_cw[0]))
    return np.asarray(errors)


@pytest.mark.parametrize("views", [1, 3])
def test_oracle_converges_to_ground_truth(scene, views):
    """20 degrees and 10 % of depth off -> under 0.1 degree and 1 mm within 3 iterations."""
    _, _, T_cw, T_gt = scene
    table = []
    for seed, sign in [(0, 1), (1, -1), (2, 1)]:
        T0 = _perturbed(T_gt, T_cw[0], seed, sign)
        table.append(_refine(scene, 0.0, T0, views))
    table = np.asarray(table)  # [hypothesis, iteration, (deg, mm, depth mm)]
    msg = f"{views} view(s): errors per iteration (deg, mm, depth mm):\n{np.round(table, 4)}"
    assert np.all(table[:, -1, 0] < 0.1), msg
    assert np.all(table[:, -1, 1] < 1.0), msg


def test_noisy_oracle_three_views_beat_one_on_depth(scene):
    """Descriptor noise (0.1 of the norm), six starts: 3 views cut the median depth error at
    least 3-fold and keep every start under 0.2 mm. Measured on 2 cores (errors after 3
    iterations, mm): 1 view 0.05-3.0, median 0.61; 3 views 0.04-0.094, median 0.069 (8.8x).
    One start alone is no test: there 1 view can beat 3 (0.054 vs 0.09 mm), and the 5-fold
    margin on three starts this test used to require failed at 4.0x on some machines."""
    _, _, T_cw, T_gt = scene
    depth = {views: np.array([
        _refine(scene, NOISE, _perturbed(T_gt, T_cw[0], seed, (-1) ** seed), views)[-1, 2]
        for seed in range(6)]) for views in (1, 3)}
    msg = f"depth errors after 3 iterations (mm): {depth}"
    assert np.median(depth[3]) * 3 < np.median(depth[1]), msg
    assert np.all(depth[3] < 0.2), msg


def test_step_traces_once(scene):
    """Two different inputs of the same shapes reuse one trace."""
    mesh, rmesh, T_cw, T_gt = scene
    outs = []
    for seed in (3, 4):
        T = _perturbed(T_gt, T_cw[0], seed, 1)
        crop_K = crop_intrinsics(jnp.asarray(K_FULL[None]), crop_boxes(mesh, T, T_cw[:1],
                                                                       K_FULL[None]), (CROP, CROP))
        crops = render(rmesh, T_cw[:1] @ T_gt, crop_K, (CROP, CROP), ("rgb",), ambient=1.0)["rgb"]
        outs.append(STEP(jnp.float32(0.0), rmesh, crops, crop_K, jnp.asarray(T_cw[:1], jnp.float32),
                         jnp.asarray(T[None], jnp.float32)))
        if seed == 3:
            traces = len(TRACES)
    assert len(TRACES) == traces
    assert not np.allclose(outs[0].hypotheses, outs[1].hypotheses)


def test_matches_reproject_onto_their_real_pixels_at_ground_truth(scene):
    """Crop 64, map 32, no sub-pixel fit: at the ground truth a match's 3D point, projected with
    crop_K (cv2), lands on its real pixel converted to crop pixels."""
    mesh, rmesh, T_cw, T_gt = scene
    crop, size = 64, 32
    oracle = make_oracle(size)
    box = crop_boxes(mesh, T_gt, T_cw[:1], K_FULL[None])
    crop_K = crop_intrinsics(jnp.asarray(K_FULL[None]), box, (crop, crop))
    rend = render_hypotheses(rmesh, crop_K, T_cw[:1], T_gt[None], crop_size=crop,
                             output_size=size, ambient=1.0)
    out = oracle(rend.rgb[:, 0][None], rend.rgb[None])  # real crops = the render at the truth
    m = reciprocal_matches(out["real_desc"][0], out["render_desc"][0], rend.xyz, rend.mask,
                           rend.edge, rend.pixel_mm, num_matches=64, crop_size=crop,
                           subpixel=False)
    T = T_cw[0] @ T_gt
    uv, _ = cv2.projectPoints(np.asarray(m.points_3d[0, 0], np.float64),
                              cv2.Rodrigues(T[:3, :3])[0], T[:3, 3],
                              np.asarray(crop_K[0], np.float64), None)
    w = np.asarray(m.weights[0, 0]) > 0
    err = np.linalg.norm(uv[:, 0] - np.asarray(m.points_2d[0, 0]), axis=-1)[w]
    assert w.sum() >= 32
    assert np.mean(err < 1e-2) >= 0.95, np.sort(err)[-5:]


def test_crop_boxes_hold_the_projected_mesh(scene):
    """Square, centred on the sphere centre's projection, holding every projected vertex."""
    mesh, _, T_cw, T_gt = scene
    boxes = np.asarray(crop_boxes(mesh, T_gt, T_cw, np.repeat(K_FULL[None], 3, 0)))
    for v in range(3):
        T = T_cw[v] @ T_gt
        uv, _ = cv2.projectPoints(mesh.vertices.astype(np.float64), cv2.Rodrigues(T[:3, :3])[0],
                                  T[:3, 3], K_FULL.astype(np.float64), None)
        uv = uv[:, 0] + 0.5  # pixel-edge coordinates
        c = T[:3, :3] @ mesh.center + T[:3, 3]
        half = 1.2 * 800.0 * mesh.radius / c[2]
        center = K_FULL[:2, :2] @ (c[:2] / c[2]) + K_FULL[:2, 2] + 0.5
        np.testing.assert_allclose(boxes[v], np.r_[center - half, center + half], rtol=1e-5)
        assert np.all(uv >= boxes[v, :2]) and np.all(uv <= boxes[v, 2:])


def test_subpixel_points_are_closer_to_what_the_real_pixel_sees(scene):
    """A hypothesis 0.3 map pixels off the truth: the fitted 3D points are at least 3 times
    closer than the render pixels' own coordinates to the points the real pixels see."""
    mesh, rmesh, T_cw, T_gt = scene
    box = crop_boxes(mesh, T_gt, T_cw[:1], K_FULL[None])
    crop_K = crop_intrinsics(jnp.asarray(K_FULL[None]), box, (CROP, CROP))
    c = T_cw[0, :3, :3] @ (T_gt[:3, :3] @ mesh.center + T_gt[:3, 3]) + T_cw[0, :3, 3]
    shift = 0.3 * c[2] / float(crop_K[0, 0, 0]) * CROP / MAP  # 0.3 map pixels in x, in mm
    T = T_gt.copy()
    T[:3, 3] += T_cw[0, :3, :3].T @ np.array([shift, 0.5 * shift, 0.0])
    real = render_hypotheses(rmesh, crop_K, T_cw[:1], T_gt[None], crop_size=CROP,
                             output_size=MAP, ambient=1.0)
    rend = render_hypotheses(rmesh, crop_K, T_cw[:1], T[None], crop_size=CROP,
                             output_size=MAP, ambient=1.0)
    out = ORACLE(real.rgb[:, 0][None], rend.rgb[None])
    kw = dict(num_matches=64, crop_size=CROP)
    args = (out["real_desc"][0], out["render_desc"][0], rend.xyz, rend.mask, rend.edge,
            rend.pixel_mm)
    fit = reciprocal_matches(*args, **kw, subpixel=True)
    raw = reciprocal_matches(*args, **kw, subpixel=False)
    w = np.asarray(fit.weights[0, 0]) > 0
    seen = np.asarray(real.xyz[0, 0]).reshape(-1, 3)[np.asarray(fit.real_pixel[0, 0])]
    err_fit = np.linalg.norm(np.asarray(fit.points_3d[0, 0]) - seen, axis=-1)[w]
    err_raw = np.linalg.norm(np.asarray(raw.points_3d[0, 0]) - seen, axis=-1)[w]
    assert w.sum() >= 32
    assert np.median(err_fit) * 3 < np.median(err_raw), (np.median(err_fit), np.median(err_raw))
