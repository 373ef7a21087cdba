"""Multi-view triangulation and cross-view matching of detections.

3PT's multi-view object generation (docs/design.md section 1.2) matches detections across
calibrated views along the epipolar rays through their box centres, triangulates each match and
keeps the objects seen in at least 3 views. This module provides

* :func:`triangulate`: one 3D point from its pixels in V views (DLT, then Gauss-Newton on the
  reprojection error); pure JAX, jit-able and vmap-able over points;
* :func:`reprojection_errors`: pixel distance of a point's projections to its observations;
* :func:`match_across_views`: the data-dependent grouping of per-view detections into tracks,
  on the host in float64 NumPy (its output size depends on the data).

Conventions: millimetres, OpenCV cameras, ``T_cam_world`` maps world points into the camera,
``K`` in pixel-centre coordinates (``threept_jax.geometry.camera``).
"""

from __future__ import annotations

import itertools
from typing import NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

Array = jax.Array


def _project_jnp(X: Array, K: Array, T_cam_world: Array, min_depth: float):
    """World point X [3] -> (pixels [V, 2], depth [V]), depth clamped for the division."""
    p = jnp.einsum("vij,j->vi", T_cam_world[:, :3, :3], X) + T_cam_world[:, :3, 3]
    z = jnp.maximum(p[:, 2], min_depth)
    uv = jnp.einsum("vij,vj->vi", K[:, :2, :], p) / z[:, None]
    return uv, p


def reprojection_errors(point: Array, uv: Array, K: Array, T_cam_world: Array) -> Array:
    """Pixel distance of the projections of ``point`` [3] (world, mm) to ``uv`` [V, 2] -> [V].

    Views where the point is not in front of the camera get +inf.
    """
    point = jnp.asarray(point)
    K = jnp.asarray(K, point.dtype)
    proj, p = _project_jnp(point, K, jnp.asarray(T_cam_world, point.dtype), 1e-9)
    err = jnp.linalg.norm(proj - jnp.asarray(uv, point.dtype), axis=-1)
    return jnp.where(p[:, 2] > 0, err, jnp.inf)


def triangulate(
    uv: Array,
    K: Array,
    T_cam_world: Array,
    valid: Array,
    *,
    refine_iterations: int = 3,
    min_depth: float = 1.0,
) -> Array:
    """Triangulate one world point from its pixels in V views.

    uv [V, 2] pixels, K [V, 3, 3], T_cam_world [V, 4, 4], valid [V] bool (views to use) ->
    point [3] (world, mm), in the dtype of ``uv`` (float32 by default).

    Linear DLT (Hartley & Zisserman, section 12.2) in normalised image coordinates and in a
    world frame centred and scaled on the valid cameras (for float32 conditioning), solved as
    the smallest eigenvector of the 4x4 normal matrix; then ``refine_iterations`` Gauss-Newton
    steps on the reprojection error in pixels, each kept only if it lowers the error (so the
    refinement never makes the DLT worse). Depth is clamped to ``min_depth`` in the refinement.
    With fewer than 2 valid views, or parallel rays, the result is an arbitrary finite point:
    check it with :func:`reprojection_errors`. Jit-able; vmap over points for batches.
    """
    uv = jnp.asarray(uv)
    dtype = jnp.promote_types(uv.dtype, jnp.float32)
    uv = uv.astype(dtype)
    K = jnp.asarray(K, dtype)
    T_cam_world = jnp.asarray(T_cam_world, dtype)
    valid = jnp.asarray(valid, bool)
    if uv.ndim != 2 or uv.shape[-1] != 2:
        raise ValueError(f"uv must be [V, 2] (one point), got {uv.shape}; vmap for many points")
    V = uv.shape[0]
    if K.shape != (V, 3, 3) or T_cam_world.shape != (V, 4, 4) or valid.shape != (V,):
        raise ValueError(
            f"expected K [V, 3, 3], T_cam_world [V, 4, 4], valid [V] with V = {V}; got "
            f"{K.shape}, {T_cam_world.shape}, {valid.shape}"
        )
    w = valid.astype(dtype)
    R = T_cam_world[:, :3, :3]
    t = T_cam_world[:, :3, 3]
    # Camera centres C = -R^T t; normalise the world to their centroid and spread.
    C = -jnp.einsum("vji,vj->vi", R, t)
    n = jnp.maximum(jnp.sum(w), 1.0)
    m = jnp.sum(w[:, None] * C, 0) / n
    s = jnp.sqrt(jnp.sum(w * jnp.sum((C - m) ** 2, -1)) / n)
    s = jnp.where(s > 0, s, 1.0)
    # Normalised coordinates x = K^-1 [u, v, 1] (K upper triangular).
    y = (uv[:, 1] - K[:, 1, 2]) / K[:, 1, 1]
    x = (uv[:, 0] - K[:, 0, 2] - K[:, 0, 1] * y) / K[:, 0, 0]
    # P' = [R s | R m + t] acts on the normalised homogeneous point (X - m) / s.
    P = jnp.concatenate([R * s, (jnp.einsum("vij,j->vi", R, m) + t)[:, :, None]], -1)
    rows = jnp.concatenate([x[:, None] * P[:, 2] - P[:, 0], y[:, None] * P[:, 2] - P[:, 1]], 0)
    rows = rows / jnp.maximum(jnp.linalg.norm(rows, axis=-1, keepdims=True), 1e-30)
    ww = jnp.concatenate([w, w])
    A = jnp.einsum("r,ri,rj->ij", ww, rows, rows, precision=jax.lax.Precision.HIGHEST)
    _, vecs = jnp.linalg.eigh(A)
    h = vecs[:, 0]
    h4 = jnp.where(jnp.abs(h[3]) < 1e-12, jnp.where(h[3] < 0, -1e-12, 1e-12), h[3])
    X = m + s * h[:3] / h4
    X = jnp.where(jnp.all(jnp.isfinite(X)), X, m)

    def cost(X):
        proj, _ = _project_jnp(X, K, T_cam_world, min_depth)
        return jnp.sum(w * jnp.sum((proj - uv) ** 2, -1))

    def gauss_newton(_, carry):
        X, c = carry
        _, p = _project_jnp(X, K, T_cam_world, min_depth)
        z = jnp.maximum(p[:, 2], min_depth)
        proj = jnp.einsum("vij,vj->vi", K[:, :2, :], p) / z[:, None]
        r = proj - uv  # [V, 2]
        # d proj / d p = (K[:2, :3] - proj e3^T) / z, and d p / d X = R.
        Jp = (K[:, :2, :] - proj[:, :, None] * jnp.array([0.0, 0.0, 1.0], dtype)) / z[:, None, None]
        J = jnp.einsum("vij,vjk->vik", Jp, R)  # [V, 2, 3]
        H = jnp.einsum("v,vik,vil->kl", w, J, J, precision=jax.lax.Precision.HIGHEST)
        g = jnp.einsum("v,vik,vi->k", w, J, r, precision=jax.lax.Precision.HIGHEST)
        H = H + 1e-9 * jnp.trace(H) * jnp.eye(3, dtype=dtype)
        X_new = X - jnp.linalg.solve(H, g)
        c_new = cost(X_new)
        better = jnp.isfinite(c_new) & (c_new < c)
        return jnp.where(better, X_new, X), jnp.where(better, c_new, c)

    X, _ = jax.lax.fori_loop(0, refine_iterations, gauss_newton, (X, cost(X)))
    return X


class Tracks(NamedTuple):
    """Objects matched across views by :func:`match_across_views` (M tracks, V views).

    points: [M, 3] float64 triangulated world points (mm).
    detections: [M, V] int, the index of the track's detection in each view, -1 where absent.
    num_views: [M] int, views in the track.
    reprojection_error_px: [M] float64, mean pixel error of the point over the track's views.
    labels: [M] int, the track's label (-1 when no labels were given).
    """

    points: np.ndarray
    detections: np.ndarray
    num_views: np.ndarray
    reprojection_error_px: np.ndarray
    labels: np.ndarray


def _triangulate_np(uv: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Float64 DLT of one point from pixels uv [m, 2] and projections P [m, 3, 4] -> [3]."""
    A = np.concatenate([uv[:, :1] * P[:, 2] - P[:, 0], uv[:, 1:] * P[:, 2] - P[:, 1]], 0)
    A = A / np.linalg.norm(A, axis=-1, keepdims=True)
    h = np.linalg.svd(A)[2][-1]
    return h[:3] / h[3] if abs(h[3]) > 1e-15 else np.full(3, np.nan)


def _refine_np(X: np.ndarray, uv: np.ndarray, K: np.ndarray, T: np.ndarray, iters: int = 5):
    """Float64 Gauss-Newton on the reprojection error of one point seen in [m] views."""
    for _ in range(iters):
        p = np.einsum("vij,j->vi", T[:, :3, :3], X) + T[:, :3, 3]
        if np.any(p[:, 2] <= 0):
            break
        proj = np.einsum("vij,vj->vi", K[:, :2], p) / p[:, 2:3]
        Jp = (K[:, :2] - proj[:, :, None] * np.array([0.0, 0.0, 1.0])) / p[:, 2, None, None]
        J = np.einsum("vij,vjk->vik", Jp, T[:, :3, :3]).reshape(-1, 3)
        step = np.linalg.lstsq(J, (proj - uv).reshape(-1), rcond=None)[0]
        X = X - step
    return X


def _errors_np(X: np.ndarray, uv: np.ndarray, K: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Pixel errors [m] of X in views with K [m], T [m]; inf behind a camera."""
    p = np.einsum("vij,j->vi", T[:, :3, :3], X) + T[:, :3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        proj = np.einsum("vij,vj->vi", K[:, :2], p) / p[:, 2:3]
        err = np.linalg.norm(proj - uv, axis=-1)
    return np.where((p[:, 2] > 0) & np.isfinite(err), err, np.inf)


def match_across_views(
    centers: Sequence[np.ndarray] | np.ndarray,
    K: np.ndarray,
    T_cam_world: np.ndarray,
    *,
    valid: np.ndarray | None = None,
    labels: Sequence[np.ndarray] | np.ndarray | None = None,
    max_epipolar_px: float = 10.0,
    max_reprojection_px: float | None = None,
    min_views: int = 3,
) -> Tracks:
    """Group per-view detection centres into multi-view tracks and triangulate them.

    Args:
      centers: per-view pixel centres, either a list of V arrays [N_v, 2] (N_v may be 0) or a
        padded array [V, N, 2] together with ``valid`` [V, N] (rows with a NaN are padding too).
      K: [V, 3, 3] intrinsics; T_cam_world: [V, 4, 4] extrinsics (world -> camera).
      labels: optional per-view integer labels (object ids), same layout as ``centers``; only
        detections with equal labels are matched.
      max_epipolar_px: symmetric epipolar distance (pixels) under which two detections of two
        views may belong together.
      max_reprojection_px: pixel error under which a view's detection joins a triangulated
        track (default: ``max_epipolar_px``).
      min_views: tracks seen in fewer views are dropped (3PT uses 3).

    Returns:
      :class:`Tracks`, sorted by decreasing number of views, then increasing error.

    Algorithm (deterministic, float64, on the host):

    1. Seeds: every pair of detections from two different views (same label) whose symmetric
       epipolar distance, max(d(x_b, F x_a), d(x_a, F^T x_b)), is below ``max_epipolar_px``.
    2. Each seed is triangulated (DLT + Gauss-Newton); in every other view the nearest
       detection to its projection joins if within ``max_reprojection_px``; the track is
       re-triangulated from all its members and the member with the largest error is dropped
       (and the track re-triangulated) until every member is within ``max_reprojection_px``
       and in front of its camera. Seeds giving the same member set are merged.
    3. Candidate tracks with at least ``min_views`` views are accepted greedily, most views
       first, then lowest mean reprojection error (ties by member indices), skipping any that
       shares a detection with an accepted track. Epipolar geometry alone is ambiguous along
       the line; the reprojection check in a third view is what resolves it, hence
       ``min_views`` >= 3 in practice.
    """
    K = np.asarray(K, np.float64)
    T = np.asarray(T_cam_world, np.float64)
    V = K.shape[0]
    if K.shape != (V, 3, 3) or T.shape != (V, 4, 4):
        raise ValueError(f"K must be [V, 3, 3] and T_cam_world [V, 4, 4]; got {K.shape}, {T.shape}")
    if isinstance(centers, np.ndarray) and centers.ndim == 3:
        if centers.shape[0] != V or centers.shape[-1] != 2:
            raise ValueError(f"padded centers must be [V={V}, N, 2], got {centers.shape}")
        keep = np.all(np.isfinite(centers), -1)
        if valid is not None:
            keep &= np.asarray(valid, bool)
        pts = [np.asarray(centers[v][keep[v]], np.float64) for v in range(V)]
        index = [np.flatnonzero(keep[v]) for v in range(V)]
        labs = None if labels is None else [np.asarray(labels)[v][keep[v]] for v in range(V)]
    else:
        if len(centers) != V:
            raise ValueError(f"centers has {len(centers)} views but K has {V}")
        pts = [np.asarray(c, np.float64).reshape(-1, 2) for c in centers]
        index = [np.arange(len(p)) for p in pts]
        labs = None if labels is None else [np.asarray(lab).reshape(-1) for lab in labels]
        if labs is not None and any(len(lab) != len(p) for lab, p in zip(labs, pts)):
            raise ValueError("labels must have one entry per detection of each view")
    if labs is None:
        labs = [np.full(len(p), -1) for p in pts]
    if min_views < 2:
        raise ValueError(f"min_views must be >= 2 (a point needs two rays), got {min_views}")
    reproj_px = max_epipolar_px if max_reprojection_px is None else max_reprojection_px

    P = np.einsum("vij,vjk->vik", K, T[:, :3, :])  # [V, 3, 4]
    Kinv = np.linalg.inv(K)

    def fundamental(i, j):  # x_j^T F x_i = 0
        T_ji = T[j] @ np.linalg.inv(T[i])
        tx = np.array([[0, -T_ji[2, 3], T_ji[1, 3]], [T_ji[2, 3], 0, -T_ji[0, 3]],
                       [-T_ji[1, 3], T_ji[0, 3], 0]])
        return Kinv[j].T @ tx @ T_ji[:3, :3] @ Kinv[i]

    def evaluate(members: dict[int, int]):
        """Triangulate, grow into other views, prune: -> (members, point, mean error)."""
        for _ in range(2):  # grow from the seed, then once more from the grown track
            views = sorted(members)
            uv = np.stack([pts[v][members[v]] for v in views])
            X = _triangulate_np(uv, P[views])
            if not np.all(np.isfinite(X)):
                return None
            X = _refine_np(X, uv, K[views], T[views])
            lab = labs[views[0]][members[views[0]]]
            for v in range(V):
                if v in members or len(pts[v]) == 0:
                    continue
                err = _errors_np(X, pts[v], K[[v] * len(pts[v])], T[[v] * len(pts[v])])
                err = np.where(labs[v] == lab, err, np.inf)
                best = int(np.argmin(err))
                if err[best] < reproj_px:
                    members[v] = best
        while len(members) >= 2:
            views = sorted(members)
            uv = np.stack([pts[v][members[v]] for v in views])
            X = _triangulate_np(uv, P[views])
            if not np.all(np.isfinite(X)):
                return None
            X = _refine_np(X, uv, K[views], T[views])
            err = _errors_np(X, uv, K[views], T[views])
            worst = int(np.argmax(err))
            if err[worst] < reproj_px:
                return members, X, float(np.mean(err))
            del members[views[worst]]
        return None

    candidates: dict[tuple, tuple] = {}
    for i, j in itertools.combinations(range(V), 2):
        if len(pts[i]) == 0 or len(pts[j]) == 0:
            continue
        F = fundamental(i, j)
        xi = np.concatenate([pts[i], np.ones((len(pts[i]), 1))], 1)  # [Ni, 3]
        xj = np.concatenate([pts[j], np.ones((len(pts[j]), 1))], 1)
        lj = xi @ F.T  # epipolar lines in view j of the detections of view i: [Ni, 3]
        li = xj @ F  # lines in view i of the detections of view j: [Nj, 3]
        d_j = np.abs(lj @ xj.T) / np.linalg.norm(lj[:, :2], axis=-1, keepdims=True)  # [Ni, Nj]
        d_i = np.abs(li @ xi.T).T / np.linalg.norm(li[:, :2], axis=-1)[None, :]
        dist = np.maximum(d_i, d_j)
        dist = np.where(labs[i][:, None] == labs[j][None, :], dist, np.inf)
        for a, b in zip(*np.nonzero(dist < max_epipolar_px)):
            result = evaluate({i: int(a), j: int(b)})
            if result is None or len(result[0]) < min_views:
                continue
            members, X, err = result
            key = tuple(sorted(members.items()))
            if key not in candidates:
                candidates[key] = (X, err)

    order = sorted(candidates, key=lambda k: (-len(k), candidates[k][1], k))
    used: set[tuple[int, int]] = set()
    out_pts, out_det, out_err, out_lab = [], [], [], []
    for key in order:
        if any(m in used for m in key):
            continue
        used.update(key)
        det = np.full(V, -1, np.int64)
        for v, a in key:
            det[v] = index[v][a]
        out_pts.append(candidates[key][0])
        out_det.append(det)
        out_err.append(candidates[key][1])
        v0, a0 = key[0]
        out_lab.append(int(labs[v0][a0]))
    M = len(out_pts)
    return Tracks(
        points=np.asarray(out_pts, np.float64).reshape(M, 3),
        detections=np.asarray(out_det, np.int64).reshape(M, V),
        num_views=np.asarray([np.sum(d >= 0) for d in out_det], np.int64).reshape(M),
        reprojection_error_px=np.asarray(out_err, np.float64).reshape(M),
        labels=np.asarray(out_lab, np.int64).reshape(M),
    )


def fuse_ray_estimates(points: np.ndarray, origins: np.ndarray, depth_sigma: np.ndarray,
                       lateral_sigma: np.ndarray) -> np.ndarray:
    """[3] one point from per-view estimates of it, each sure across its view's ray and unsure
    along it: ``points`` [n, 3] (world, mm), seen from camera centres ``origins`` [n, 3], with
    standard deviations ``depth_sigma`` [n] along the ray and ``lateral_sigma`` [n] across it
    (mm). The weighted least-squares point: argmin_x sum_v (x - p_v)^T A_v (x - p_v) with
    A_v = (I - r r^T) / lateral^2 + r r^T / depth^2, r the unit ray. Rays far apart pin each
    other's depth (triangulation); nearly parallel ones average it. A single-view pose's
    outline fixes where its centre lies in the image far better than how far away (its
    size), which is what the two sigmas say."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    r = p - np.asarray(origins, np.float64).reshape(-1, 3)
    r /= np.linalg.norm(r, axis=-1, keepdims=True)
    rr = np.einsum("ni,nj->nij", r, r)
    lat = 1.0 / np.asarray(lateral_sigma, np.float64).reshape(-1, 1, 1) ** 2
    dep = 1.0 / np.asarray(depth_sigma, np.float64).reshape(-1, 1, 1) ** 2
    A = lat * (np.eye(3) - rr) + dep * rr
    return np.linalg.solve(A.sum(0), np.einsum("nij,nj->i", A, p))
