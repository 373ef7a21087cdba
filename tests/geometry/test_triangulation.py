"""Triangulation and cross-view matching against OpenCV, SciPy and known synthetic scenes."""

import cv2
import jax
import numpy as np
import pytest
from scipy.optimize import least_squares

from threept_jax.geometry.triangulation import (
    fuse_ray_estimates,
    match_across_views,
    reprojection_errors,
    triangulate,
)

K640 = np.array([[600.0, 0.0, 319.5], [0.0, 600.0, 239.5], [0.0, 0.0, 1.0]])


def _look_at(eye, target=None):
    target = np.zeros(3) if target is None else target
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, -R @ eye
    return T


def _ring(num_views, radius=800.0, height=600.0, jitter=0.0, rng=None):
    """T_cam_world [V, 4, 4] of cameras on a ring above a bin at the world origin."""
    Ts = []
    for v in range(num_views):
        az = 2 * np.pi * v / num_views + (rng.uniform(-jitter, jitter) if rng is not None else 0)
        eye = np.array([radius * np.cos(az), radius * np.sin(az), height])
        Ts.append(_look_at(eye))
    return np.stack(Ts)


def _project(X, K, T):
    p = T[:3, :3] @ X + T[:3, 3]
    uv = K @ p
    return uv[:2] / uv[2]


tri = jax.jit(jax.vmap(triangulate, in_axes=(0, None, None, 0)))


def test_triangulate_exact_on_noise_free_data():
    rng = np.random.default_rng(0)
    V = 4
    T = _ring(V, jitter=0.2, rng=rng)
    K = np.stack([K640] * V)
    X = rng.uniform([-200, -150, 0], [200, 150, 100], (32, 3))
    uv = np.stack([[_project(x, K640, T[v]) for v in range(V)] for x in X])
    valid = np.ones((32, V), bool)
    valid[::3, 1] = False  # some points seen in 3 views only
    got = np.asarray(tri(uv.astype(np.float32), K.astype(np.float32), T.astype(np.float32), valid))
    np.testing.assert_allclose(got, X, atol=1e-2)
    # Two-view reference from OpenCV (float64).
    ref = cv2.triangulatePoints(K640 @ T[0, :3], K640 @ T[2, :3], uv[:, 0].T, uv[:, 2].T)
    ref = (ref[:3] / ref[3]).T
    two = np.asarray(tri(uv.astype(np.float32), K.astype(np.float32), T.astype(np.float32),
                         np.tile([True, False, True, False], (32, 1))))
    np.testing.assert_allclose(two, ref, atol=1e-2)


def test_refinement_reaches_float64_least_squares_optimum():
    rng = np.random.default_rng(1)
    V = 5
    T = _ring(V, jitter=0.3, rng=rng)
    Ks = np.stack([K640] * V)
    X = rng.uniform([-200, -150, 0], [200, 150, 100], (16, 3))
    uv = np.stack([[_project(x, K640, T[v]) for v in range(V)] for x in X])
    uv = uv + rng.normal(scale=1.0, size=uv.shape)
    valid = np.ones((16, V), bool)
    got = np.asarray(tri(uv.astype(np.float32), Ks.astype(np.float32), T.astype(np.float32), valid),
                     np.float64)
    for i in range(16):
        def resid(x, i=i):
            return np.concatenate([_project(x, K640, T[v]) - uv[i, v] for v in range(V)])

        ref = least_squares(resid, X[i], xtol=1e-12, ftol=1e-12).x
        assert np.linalg.norm(got[i] - ref) < 0.05
        assert np.sum(resid(got[i]) ** 2) <= np.sum(resid(ref) ** 2) * (1 + 1e-3) + 1e-6
    err = np.asarray(reprojection_errors(got[0].astype(np.float32), uv[0].astype(np.float32),
                                         Ks.astype(np.float32), T.astype(np.float32)))
    ref_err = [np.linalg.norm(_project(got[0], K640, T[v]) - uv[0, v]) for v in range(V)]
    np.testing.assert_allclose(err, ref_err, atol=1e-3)


def test_invalid_views_are_ignored():
    V = 4
    T = _ring(V)
    K = np.stack([K640] * V)
    x = np.array([30.0, -40.0, 50.0])
    uv = np.stack([_project(x, K640, T[v]) for v in range(V)])
    uv[3] = [1e4, -7.0]  # garbage in an invalid view
    valid = np.array([True, True, True, False])
    tri1 = jax.jit(triangulate)
    got = np.asarray(tri1(uv.astype(np.float32), K, T, valid))
    np.testing.assert_allclose(got, x, atol=1e-2)
    assert np.all(np.isfinite(np.asarray(tri1(uv.astype(np.float32), K, T, np.zeros(V, bool)))))
    assert np.isinf(float(reprojection_errors(np.array([0.0, 0, 2000.0]), uv[:1], K[:1], T[:1])[0]))


def _bin_scene(rng, num_objects=10, spurious_frac=0.1, noise_px=0.5, V=4):
    T = _ring(V, jitter=0.2, rng=rng)
    X = rng.uniform([-200, -150, 0], [200, 150, 100], (num_objects, 3))
    centers, truth = [], []  # truth[v][k]: index of object k's detection in view v
    for v in range(V):
        c = np.stack([_project(x, K640, T[v]) for x in X]) + rng.normal(scale=noise_px,
                                                                        size=(num_objects, 2))
        n_spur = int(round(spurious_frac * num_objects))
        c = np.concatenate([c, rng.uniform([0, 0], [640, 480], (n_spur, 2))])
        perm = rng.permutation(len(c))
        centers.append(c[perm])
        truth.append(np.argsort(perm)[:num_objects])
    return X, T, centers, np.stack(truth, axis=1)  # truth [O, V]


def test_match_across_views_recovers_bin_objects():
    rng = np.random.default_rng(3)
    X, T, centers, truth = _bin_scene(rng)
    tracks = match_across_views(centers, np.stack([K640] * 4), T, max_epipolar_px=5.0)
    assert len(tracks.points) == len(X)
    assert np.all(tracks.num_views == 4)
    got = {tuple(d) for d in tracks.detections.tolist()}
    assert got == {tuple(t) for t in truth.tolist()}
    for p, d in zip(tracks.points, tracks.detections):
        k = int(np.flatnonzero((truth == d).all(1))[0])
        assert np.linalg.norm(p - X[k]) < 3.0
    assert np.all(tracks.reprojection_error_px < 2.0)
    # Deterministic: the same input gives the same output.
    again = match_across_views(centers, np.stack([K640] * 4), T, max_epipolar_px=5.0)
    np.testing.assert_array_equal(again.detections, tracks.detections)


def test_match_across_views_padded_labels_and_missed_detections():
    rng = np.random.default_rng(4)
    X, T, centers, truth = _bin_scene(rng, num_objects=8, spurious_frac=0.25)
    labels = [np.zeros(len(c), np.int64) for c in centers]
    for v in range(4):
        labels[v][truth[:4, v]] = 1  # objects 0-3 are of class 1, the rest (and spurious) 0
    # Object 0 is missed in view 1 (three views left), object 1 in views 1 and 2 (two left).
    valid = [np.ones(len(c), bool) for c in centers]
    valid[1][truth[0, 1]] = valid[1][truth[1, 1]] = valid[2][truth[1, 2]] = False
    N = max(len(c) for c in centers)
    padded = np.full((4, N, 2), np.nan)
    lab = np.full((4, N), -1)
    mask = np.zeros((4, N), bool)
    for v, c in enumerate(centers):
        padded[v, : len(c)], lab[v, : len(c)], mask[v, : len(c)] = c, labels[v], valid[v]
    tracks = match_across_views(padded, np.stack([K640] * 4), T, valid=mask, labels=lab,
                                max_epipolar_px=5.0, min_views=3)
    want = {k: truth[k].copy() for k in range(8) if k != 1}
    want[0][1] = -1
    assert {tuple(d) for d in tracks.detections.tolist()} == {tuple(w) for w in want.values()}
    for d, lab_k in zip(tracks.detections.tolist(), tracks.labels.tolist()):
        k = next(k for k, w in want.items() if tuple(w) == tuple(d))
        assert lab_k == (1 if k < 4 else 0)
    assert sorted(tracks.num_views.tolist()) == [3] + [4] * 6


def test_match_bad_inputs_raise():
    K = np.stack([K640] * 2)
    T = _ring(2)
    with pytest.raises(ValueError, match="centers has 3 views"):
        match_across_views([np.zeros((1, 2))] * 3, K, T)
    with pytest.raises(ValueError, match="min_views"):
        match_across_views([np.zeros((1, 2))] * 2, K, T, min_views=1)
    with pytest.raises(ValueError, match="uv must be"):
        triangulate(np.zeros((2, 3)), K, T, np.ones(2, bool))


def test_fuse_ray_estimates_is_the_weighted_least_squares_point():
    """Against SciPy minimising sum_v (x - p_v)^T A_v (x - p_v) directly; two rays at right
    angles, each estimate wrong only along its ray, meet where they cross; estimates along one
    ray average their depths by inverse variance (hand-derived)."""
    rng = np.random.default_rng(3)
    p = rng.normal(0, 50, (4, 3)) + [0, 0, 500]
    o = rng.normal(0, 200, (4, 3))
    dep, lat = rng.uniform(5, 30, 4), rng.uniform(0.5, 3, 4)

    def residuals(x):
        out = []
        for pv, ov, d, s in zip(p, o, dep, lat):
            r = (pv - ov) / np.linalg.norm(pv - ov)
            e = x - pv
            along = r @ e
            out += [along / d, *((e - along * r) / s)]
        return np.array(out)

    want = least_squares(residuals, p.mean(0), xtol=1e-14, ftol=1e-14, gtol=1e-14).x
    np.testing.assert_allclose(fuse_ray_estimates(p, o, dep, lat), want, atol=1e-6)

    cross = np.array([10.0, -20.0, 400.0])
    origins = np.array([[-400.0, -20.0, 400.0], [10.0, -20.0, 0.0]])  # along x, along z
    rays = (cross - origins) / np.linalg.norm(cross - origins, axis=1, keepdims=True)
    wrong = cross + rays * np.array([[35.0], [-60.0]])
    np.testing.assert_allclose(fuse_ray_estimates(wrong, origins, [20.0, 20.0], [0.01, 0.01]),
                               cross, atol=0.01)

    origin = np.zeros((2, 3))
    along = np.array([[0.0, 0.0, 400.0], [0.0, 0.0, 440.0]])
    got = fuse_ray_estimates(along, origin, [10.0, 20.0], [1.0, 1.0])
    np.testing.assert_allclose(got, [0, 0, (400 / 100 + 440 / 400) / (1 / 100 + 1 / 400)],
                               atol=1e-9)
