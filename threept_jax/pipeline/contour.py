"""Region-based pose refinement from contour evidence: no training, the image alone.

The training-free refiner of render-and-compare, after the region-based trackers RBOT (Tjaden
et al., TPAMI 2018) and SRT3D (Stoiber et al., IJCV 2022): the object's silhouette contour,
projected at a pose hypothesis, should lie where the image changes from the object's colours
to the background's. Three parts:

1. **Contour model** (:func:`contour_model`, once per mesh, NumPy + the JAX rasterizer): the
   mesh seen from ``num_views`` directions of a Fibonacci sphere; per view ``N`` points sampled
   evenly along the silhouette's contours (OpenCV ``findContours``), lifted to 3D with the
   rendered depth, with their outward contour normals, in the object frame.
2. **Correspondence lines** (:func:`line_evidence`): at a pose, each view takes the stored view
   whose direction is nearest to its camera's (in the object frame), projects the points and
   normals, and samples the image along each normal (``2 M`` samples, spacing ``step`` px).
   Foreground / background colour histograms come from the inner / outer halves of the lines
   (8^3 RGB bins); each sample gets P(foreground | colour). A line's likelihood of the contour
   lying at offset d is prod_k [h_f(s_k - d) P_f(y_k) + h_b(s_k - d) P_b(y_k)] with smoothed
   step functions h (SRT3D eq. 9) (``evidence="region"``); or the colour change between
   consecutive samples (``"edges"``); or both (product). Its posterior over ``2 J + 1``
   offsets gives a mean mu and variance sigma^2 per line.
3. **Gauss-Newton** (:func:`refine_poses`): each line asks its projected contour point to move
   mu along its normal, with weight 1 / sigma^2; the 6 pose parameters (rotation about the
   object's centre scaled by its radius, so all six are mm of surface motion, and translation)
   solve the damped normal equations summed over lines **and views** (a rig constrains depth,
   one view only through size). Coarse to fine: ``scales`` are line spacings as fractions of the
   object's projected diameter. Samples on another instance that is nearer the camera
   (``occluder`` maps) and outside the image are ignored.

The **score** of a pose (:func:`contour_score`) is the mean, over valid lines at the finest
spacing, of the posterior mass within one step of the projected contour, times the share of
lines that are valid: about 1 when the outline sits on the object's boundary all round, near 0
for a pose off the object. The refinement keeps a hypothesis's start where the refined pose
scores lower (never worse than the start by the image's own evidence).

Shapes: P poses (instances x hypotheses), V views, O objects, D stored views, N contour points,
S = 2 M samples per line, C = 2 J + 1 candidate offsets.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from threept_jax.geometry.camera import look_at
from threept_jax.geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle, skew
from threept_jax.render.mesh import Mesh, bucket_size, prepare_mesh, to_raster_mesh
from threept_jax.render.raster import render

Array = jax.Array


# --------------------------------------------------------------------------- contour model


class ContourModel(NamedTuple):
    """Contour points of O objects seen from D directions (object frame, mm).

    directions [O, D, 3]: unit vectors from the object's centre towards the camera;
    points [O, D, N, 3]: contour points; normals [O, D, N, 3]: unit outward contour normals;
    valid [O, D, N] bool (a view with a short contour repeats points and marks none invalid;
    a view with no contour marks all invalid); center [O, 3], radius [O] (bounding sphere, mm).
    """

    directions: Array
    points: Array
    normals: Array
    valid: Array
    center: Array
    radius: Array


def fibonacci_directions(n: int) -> np.ndarray:
    """[n, 3] unit vectors spread evenly over the sphere (Fibonacci lattice)."""
    i = np.arange(n, dtype=np.float64) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = np.pi * (1.0 + 5.0 ** 0.5) * i
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)


def _sample_contours(mask: np.ndarray, num_points: int):
    """(pixels [N, 2] (u, v), outward normals [N, 2]) evenly spaced along the contours of a
    bool mask, or None when it has none."""
    import cv2

    m = mask.astype(np.uint8)
    contours, _ = cv2.findContours(m, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    pts, nrm = [], []
    for c in contours:
        c = c[:, 0, :].astype(np.float64)
        if len(c) < 8:
            continue
        # Tangent from neighbours two steps apart along the closed contour, normal turned 90 deg.
        t = np.roll(c, -2, 0) - np.roll(c, 2, 0)
        n = np.stack([t[:, 1], -t[:, 0]], -1)
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-9)
        # Outward: two pixels along n must leave the silhouette.
        probe = np.rint(c + 2.0 * n).astype(int)
        inside = m[np.clip(probe[:, 1], 0, m.shape[0] - 1), np.clip(probe[:, 0], 0, m.shape[1] - 1)]
        n[inside > 0] *= -1.0
        pts.append(c)
        nrm.append(n)
    if not pts:
        return None
    pts, nrm = np.concatenate(pts), np.concatenate(nrm)
    idx = np.floor(np.linspace(0, len(pts), num_points, endpoint=False)).astype(int)
    return pts[idx], nrm[idx]


def mesh_contours(mesh: Mesh, num_views: int = 1000, num_points: int = 200,
                  render_size: int = 256, max_faces: int | None = 4096) -> dict[str, np.ndarray]:
    """The contour points of one mesh (mm), as NumPy arrays ``directions`` [D, 3], ``points``
    and ``normals`` [D, N, 3], ``valid`` [D, N], ``center`` [3], ``radius`` []: silhouettes
    rendered by the JAX rasterizer from ``num_views`` Fibonacci directions at ``render_size``
    px, by a distant camera (10 radii) so that each is nearly the orthographic one;
    ``num_points`` points per view. The mesh is decimated to ``max_faces`` for the renders."""
    dirs = fibonacci_directions(num_views)
    prepared = prepare_mesh(mesh, max_faces=max_faces, texture_size=None)
    # One face bucket for every mesh under the budget: one compiled renderer for all.
    rm = to_raster_mesh(prepared, face_bucket=bucket_size(max(prepared.num_faces,
                                                              max_faces or 0)))
    c = np.asarray(prepared.center, np.float64)
    r = float(prepared.radius)
    dist = 10.0 * r
    f = 0.45 * render_size * dist / r
    K = np.array([[f, 0, (render_size - 1) / 2], [0, f, (render_size - 1) / 2], [0, 0, 1]])
    ups = np.where(np.abs(dirs[:, 2:3]) > 0.9, [[1.0, 0, 0]], [[0, 0, 1.0]])
    T = np.asarray(jax.vmap(look_at)(jnp.asarray(c + dist * dirs, jnp.float32),
                                     jnp.broadcast_to(jnp.asarray(c, jnp.float32), dirs.shape),
                                     jnp.asarray(ups, jnp.float32)), np.float64)
    depth = []
    for s in range(0, num_views, 128):  # bounded memory
        depth.append(np.asarray(render(rm, T[s:s + 128].astype(np.float32), K,
                                       (render_size, render_size), ("depth",))["depth"]))
    depth = np.concatenate(depth)
    P = np.zeros((num_views, num_points, 3))
    Nn = np.zeros((num_views, num_points, 3))
    valid = np.zeros((num_views, num_points), bool)
    for v in range(num_views):
        got = _sample_contours(depth[v] > 0, num_points)
        if got is None:
            continue
        uv, n2 = got
        z = depth[v][uv[:, 1].astype(int), uv[:, 0].astype(int)]
        x_cam = np.stack([(uv[:, 0] - K[0, 2]) * z / f, (uv[:, 1] - K[1, 2]) * z / f, z], -1)
        R, t = T[v, :3, :3], T[v, :3, 3]
        P[v] = (x_cam - t) @ R  # R^T (x - t)
        Nn[v] = np.concatenate([n2, np.zeros((num_points, 1))], -1) @ R
        valid[v] = z > 0
    return {"directions": dirs, "points": P, "normals": Nn, "valid": valid, "center": c,
            "radius": np.float64(r)}


def stack_contours(per_mesh: Sequence[dict[str, np.ndarray]]) -> ContourModel:
    """One :class:`ContourModel` of the :func:`mesh_contours` of several meshes (same view
    and point counts)."""
    def stack(k, dtype=jnp.float32):
        return jnp.asarray(np.stack([np.asarray(m[k]) for m in per_mesh]), dtype)

    return ContourModel(directions=stack("directions"), points=stack("points"),
                        normals=stack("normals"), valid=stack("valid", bool),
                        center=stack("center"), radius=stack("radius"))


def contour_model(meshes: Sequence[Mesh], **options) -> ContourModel:
    """The :class:`ContourModel` of ``meshes`` (options of :func:`mesh_contours`)."""
    return stack_contours([mesh_contours(m, **options) for m in meshes])


# --------------------------------------------------------------------------- settings


@dataclasses.dataclass(frozen=True)
class ContourSettings:
    """Options of the contour refinement (hashable: a static argument of ``jit``).

    scales: line spacing of each coarse-to-fine level, as a fraction of the object's projected
      diameter (never under ``min_step_px``); iterations: Gauss-Newton steps per level.
    samples: samples per line (2 M, even); offsets: candidate contour offsets each side (J < M).
    bins: histogram bins per colour channel.
    evidence: "region" (colour statistics), "edges" (colour change along the line) or "both".
    slope: smoothness of the step functions, in line steps; certainty: their amplitude
      (h_f runs from 0.5 + certainty / 2 inside to 0.5 - certainty / 2 outside).
    damping: Levenberg-Marquardt damping (times the diagonal of the normal matrix).
    prior: weight of a pull back to the start pose, times the mean of the normal matrix's
      diagonal: directions the contour constrains well (the image plane) follow the evidence,
      those it barely sees (depth and out-of-plane turns in one view) stay near the start
      instead of drifting over the iterations (the damping alone anchors each step at the
      pose it starts from, not at the start). 0 turns it off.
    max_step_deg, max_step_diameter: a trust region: one iteration turns the pose by at most
      this many degrees and moves it by at most this share of the diameter (a step is scaled
      down as a whole to fit).
    max_move_deg, max_move_diameter: the reach of a refinement: a refined pose turned further
      than this from its start, or whose centre moved further than this share of the
      diameter, is not a refinement of that start but another object or a strong edge
      elsewhere (a tray's rim, a striped border) that pulled it away: the start is kept.
    """

    scales: tuple[float, ...] = (0.04, 0.02, 0.01, 0.005)
    iterations: int = 4
    min_step_px: float = 0.5
    samples: int = 24
    offsets: int = 8
    bins: int = 8
    evidence: str = "both"
    slope: float = 0.5
    certainty: float = 0.9
    edge_gain: float = 2.0
    damping: float = 0.1
    prior: float = 0.05
    max_step_deg: float = 10.0
    max_step_diameter: float = 0.2
    max_move_deg: float = 30.0
    max_move_diameter: float = 1.0

    def __post_init__(self):
        if self.evidence not in ("region", "edges", "both"):
            raise ValueError(f"evidence must be region, edges or both, got {self.evidence!r}")
        if self.samples % 2 or not 0 < self.offsets < self.samples // 2:
            raise ValueError(f"samples must be even and 0 < offsets < samples / 2, got "
                             f"{self.samples} and {self.offsets}")
        if not self.scales or min(self.scales) <= 0 or self.iterations < 1:
            raise ValueError("scales must be positive fractions and iterations >= 1")
        if not (self.damping >= 0 and self.prior >= 0):
            raise ValueError(f"damping and prior are weights and must be >= 0 (0 turns one "
                             f"off), got {self.damping} and {self.prior}")


# --------------------------------------------------------------------------- evidence


class LineEvidence(NamedTuple):
    """Per (pose, view, line): mu, var [P, V, N] (px, along the outward normal), weight
    [P, V, N] (0 for invalid lines), a [P, V, N, 6] d(offset)/d(pose parameters), near_mass
    [P, V, N] the posterior mass within one step of the projected contour."""

    mu: Array
    var: Array
    weight: Array
    a: Array
    near_mass: Array


def _bilinear(image: Array, uv: Array) -> tuple[Array, Array]:
    """image [H, W, C] float sampled at uv [..., 2] (pixel-centre convention) -> ([..., C],
    inside [...])."""
    H, W = image.shape[:2]
    u, v = uv[..., 0], uv[..., 1]
    inside = (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
    u, v = jnp.clip(u, 0, W - 1), jnp.clip(v, 0, H - 1)
    u0, v0 = jnp.floor(u), jnp.floor(v)
    du, dv = (u - u0)[..., None], (v - v0)[..., None]
    u0i, v0i = u0.astype(jnp.int32), v0.astype(jnp.int32)
    u1i, v1i = jnp.minimum(u0i + 1, W - 1), jnp.minimum(v0i + 1, H - 1)
    top = image[v0i, u0i] * (1 - du) + image[v0i, u1i] * du
    bot = image[v1i, u0i] * (1 - du) + image[v1i, u1i] * du
    return top * (1 - dv) + bot * dv, inside


def _nearest(image: Array, uv: Array) -> Array:
    H, W = image.shape[:2]
    u = jnp.clip(jnp.round(uv[..., 0]).astype(jnp.int32), 0, W - 1)
    v = jnp.clip(jnp.round(uv[..., 1]).astype(jnp.int32), 0, H - 1)
    return image[v, u]


def line_evidence(image: Array, K: Array, T_cam_obj: Array, points: Array, normals: Array,
                  valid: Array, center: Array, radius: Array, frac: Array, instance: Array,
                  occ_id: Array, occ_depth: Array, settings: ContourSettings) -> LineEvidence:
    """The contour evidence of one pose in one view (vmapped over poses and views).

    image [H, W, 3] float in [0, 1]; K [3, 3]; T_cam_obj [4, 4]; points, normals [N, 3] and
    valid [N] of the stored view nearest the camera's direction; center [3], radius [] of the
    object; frac [] the line spacing as a fraction of the projected diameter; instance []
    int32 this pose's instance; occ_id [h, w] int32 nearest instance per pixel (-1 none) and
    occ_depth [h, w] its depth (mm), at any resolution (scaled to the image).
    """
    M, J = settings.samples // 2, settings.offsets
    R, t = T_cam_obj[:3, :3], T_cam_obj[:3, 3]
    Xc = points @ R.T + t  # [N, 3]
    nc = normals @ R.T
    z = Xc[:, 2]
    zs = jnp.maximum(z, 1e-3)
    fx, fy = K[0, 0], K[1, 1]
    # d(u, v)/d(camera point) [N, 2, 3]
    Ju = jnp.stack([
        jnp.stack([fx / zs, jnp.zeros_like(zs), -fx * Xc[:, 0] / zs ** 2], -1),
        jnp.stack([jnp.zeros_like(zs), fy / zs, -fy * Xc[:, 1] / zs ** 2], -1)], 1)
    uv = jnp.stack([fx * Xc[:, 0] / zs + K[0, 2], fy * Xc[:, 1] / zs + K[1, 2]], -1)
    n2 = jnp.einsum("nij,nj->ni", Ju, nc)
    n2 = n2 / jnp.maximum(jnp.linalg.norm(n2, axis=-1, keepdims=True), 1e-9)
    zc = (R @ center + t)[2]
    diam_px = 2.0 * radius * jnp.sqrt(fx * fy) / jnp.maximum(zc, 1e-3)
    step = jnp.maximum(frac * diam_px, settings.min_step_px)
    s = (jnp.arange(2 * M, dtype=jnp.float32) - M + 0.5) * step  # [S] along the outward normal
    where = uv[:, None, :] + s[None, :, None] * n2[:, None, :]  # [N, S, 2]
    colors, inside = _bilinear(image, where)  # [N, S, 3], [N, S]
    # Samples on a nearer other instance are hidden from this one.
    H, W = image.shape[:2]
    h, w = occ_id.shape
    scale = jnp.array([(w - 1) / max(W - 1, 1), (h - 1) / max(H - 1, 1)], jnp.float32)
    oid = _nearest(occ_id, where * scale)
    odepth = _nearest(occ_depth, where * scale)
    hidden = (oid >= 0) & (oid != instance) & (odepth < z[:, None])
    ok = inside & ~hidden & valid[:, None] & (z[:, None] > 0)  # [N, S]

    # Colour histograms from the inner and outer halves of every line.
    b = settings.bins
    q = jnp.clip((colors * b).astype(jnp.int32), 0, b - 1)
    idx = (q[..., 0] * b + q[..., 1]) * b + q[..., 2]  # [N, S]
    inner = (s < 0)[None, :] & ok
    outer = (s > 0)[None, :] & ok
    hf = jnp.zeros(b ** 3).at[idx.ravel()].add(inner.ravel().astype(jnp.float32))
    hb = jnp.zeros(b ** 3).at[idx.ravel()].add(outer.ravel().astype(jnp.float32))
    hf = (hf + 0.5) / (hf.sum() + 0.5 * b ** 3)
    hb = (hb + 0.5) / (hb.sum() + 0.5 * b ** 3)
    pf = hf[idx] / (hf[idx] + hb[idx])  # [N, S] P(foreground | colour)

    d = (jnp.arange(2 * J + 1, dtype=jnp.float32) - J) * step  # [C] candidate offsets
    logp = jnp.zeros(uv.shape[:1] + d.shape)
    if settings.evidence in ("region", "both"):
        x = (s[None, :] - d[:, None]) / step  # [C, S] in steps
        h_f = 0.5 - 0.5 * settings.certainty * jnp.tanh(x / (2.0 * settings.slope))
        lik = h_f[None] * pf[:, None, :] + (1.0 - h_f[None]) * (1.0 - pf[:, None, :])
        logp = logp + jnp.sum(jnp.where(ok[:, None, :], jnp.log(lik), 0.0), -1)
    if settings.evidence in ("edges", "both"):
        # Candidate j sits between samples M - J - 1 + j and M - J + j.
        k0 = M - J - 1 + jnp.arange(2 * J + 1)
        change = jnp.linalg.norm(colors[:, k0 + 1] - colors[:, k0], axis=-1)  # [N, C]
        both_ok = ok[:, k0 + 1] & ok[:, k0]
        change = jnp.where(both_ok, change, 0.0)
        mean = jnp.sum(change, -1, keepdims=True) / jnp.maximum(
            jnp.sum(both_ok, -1, keepdims=True), 1)
        logp = logp + settings.edge_gain * change / jnp.maximum(mean, 1e-3)
    post = jax.nn.softmax(logp, -1)  # [N, C]
    mu = jnp.sum(post * d, -1)
    var = jnp.sum(post * (d - mu[:, None]) ** 2, -1) + step ** 2 / 12.0
    near_mass = jnp.sum(jnp.where(jnp.abs(d) <= step * 1.01, post, 0.0), -1)
    # A line counts when its centre half is seen: the candidates' own samples.
    centre_ok = jnp.mean(ok[:, M - J:M + J].astype(jnp.float32), -1) >= 0.75
    weight = jnp.where(centre_ok, 1.0 / var, 0.0)

    # d(offset along n2)/d(pose): rotation w (scaled by the radius) about the centre, then
    # translation v, both in the object frame: dX = (w x (X - c)) / r + v.
    Xo = points - center
    dX_dw = -jnp.einsum("ij,njk->nik", R, skew(Xo)) / radius  # [N, 3, 3] camera frame
    dX_dv = jnp.broadcast_to(R, (points.shape[0], 3, 3))
    dX = jnp.concatenate([dX_dw, dX_dv], -1)  # [N, 3, 6]
    a = jnp.einsum("ni,nij,njk->nk", n2, Ju, dX)
    return LineEvidence(mu=mu, var=var, weight=weight, a=a,
                        near_mass=jnp.where(centre_ok, near_mass, 0.0))


# --------------------------------------------------------------------------- refinement


def _select_views(model: ContourModel, obj: Array, T_cam_obj: Array):
    """Stored view of object ``obj`` nearest to the camera's direction at T_cam_obj [4, 4]."""
    R, t = T_cam_obj[:3, :3], T_cam_obj[:3, 3]
    cam_obj = -R.T @ t  # camera centre in the object frame
    d = cam_obj - model.center[obj]
    d = d / jnp.maximum(jnp.linalg.norm(d), 1e-9)
    k = jnp.argmax(model.directions[obj] @ d)
    return model.points[obj, k], model.normals[obj, k], model.valid[obj, k]


def _evidence(model: ContourModel, images: Array, Ks: Array, T_cam_world: Array, poses: Array,
              obj: Array, instance: Array, occ_id: Array, occ_depth: Array, view_mask: Array,
              frac: Array, settings: ContourSettings) -> LineEvidence:
    """LineEvidence [P, V, N] of poses [P, 4, 4] (world) in images [V, H, W, 3] (float)."""

    def one(T_wo, o, inst, vm):
        def view(image, K, T_cw, oid, odepth, m):
            T = T_cw @ T_wo
            pts, nrm, val = _select_views(model, o, T)
            ev = line_evidence(image, K, T, pts, nrm, val & m, model.center[o], model.radius[o],
                               frac, inst, oid, odepth, settings)
            return ev
        return jax.vmap(view)(images, Ks, T_cam_world, occ_id, occ_depth, vm)

    return jax.vmap(one)(poses, obj, instance, view_mask)


def _offset(poses: Array, starts: Array, center: Array, radius: Array) -> Array:
    """[P, 6] where poses are from their starts, in the step's coordinates (rotation about the
    object's centre times the radius, then the centre's shift, both in the pose's object
    frame): to first order a step delta moves the offset to offset + delta."""
    R, R0 = poses[:, :3, :3], starts[:, :3, :3]
    turn = matrix_to_axis_angle(jnp.einsum("pji,pjk->pik", R0, R)) * radius[:, None]
    world = (jnp.einsum("pij,pj->pi", R - R0, center) + poses[:, :3, 3] - starts[:, :3, 3])
    return jnp.concatenate([turn, jnp.einsum("pji,pj->pi", R, world)], -1)


def _update(poses: Array, starts: Array, ev: LineEvidence, center: Array, radius: Array,
            settings: ContourSettings) -> Array:
    """One damped Gauss-Newton step of poses [P, 4, 4] from their evidence [P, V, N], pulled
    towards ``starts`` [P, 4, 4] by ``settings.prior``."""
    w = ev.weight
    H = jnp.einsum("pvn,pvni,pvnj->pij", w, ev.a, ev.a)
    g = jnp.einsum("pvn,pvni,pvn->pi", w, ev.a, ev.mu)
    diag = jnp.diagonal(H, axis1=-2, axis2=-1)
    floor = 1e-6 * jnp.maximum(jnp.max(diag, -1, keepdims=True), 1e-12)
    pull = settings.prior * jnp.mean(diag, -1, keepdims=True)  # [P, 1]
    g = g - pull * _offset(poses, starts, center, radius)
    Hd = H + jax.vmap(jnp.diag)(settings.damping * diag + pull + floor)
    delta = jnp.linalg.solve(Hd, g[..., None])[..., 0]  # [P, 6]
    delta = jnp.where(jnp.isfinite(delta).all(-1, keepdims=True), delta, 0.0)
    angle = jnp.linalg.norm(delta[:, :3], axis=-1) / radius
    shift = jnp.linalg.norm(delta[:, 3:], axis=-1) / (2.0 * radius)
    scale = jnp.minimum(1.0, jnp.minimum(
        np.radians(settings.max_step_deg) / jnp.maximum(angle, 1e-12),
        settings.max_step_diameter / jnp.maximum(shift, 1e-12)))
    delta = delta * scale[:, None]
    w_rot = delta[:, :3] / radius[:, None]
    dR = axis_angle_to_matrix(w_rot)
    R, t = poses[:, :3, :3], poses[:, :3, 3]
    # X' = c + dR (X - c) + v in the object frame, then the old pose.
    t_obj = center - jnp.einsum("pij,pj->pi", dR, center) + delta[:, 3:]
    new = poses.at[:, :3, :3].set(R @ dR)
    return new.at[:, :3, 3].set(t + jnp.einsum("pij,pj->pi", R, t_obj))


def within_reach(poses: Array, starts: Array, center: Array, radius: Array,
                 settings: ContourSettings) -> Array:
    """[P] whether poses [P, 4, 4] stay within ``settings``' reach of their starts: turned by
    at most ``max_move_deg`` and the object's centre moved by at most ``max_move_diameter``
    diameters (2 ``radius``)."""
    R, R0 = poses[:, :3, :3], starts[:, :3, :3]
    cos = (jnp.trace(jnp.einsum("pji,pjk->pik", R0, R), axis1=-2, axis2=-1) - 1.0) / 2.0
    turn = jnp.degrees(jnp.arccos(jnp.clip(cos, -1.0, 1.0)))
    moved = jnp.linalg.norm(jnp.einsum("pij,pj->pi", R - R0, center)
                            + poses[:, :3, 3] - starts[:, :3, 3], axis=-1)
    return (turn <= settings.max_move_deg) & (moved <= settings.max_move_diameter * 2.0 * radius)


class ContourResult(NamedTuple):
    """poses [P, 4, 4] (each the refined pose, or its start where that scored higher or the
    refined pose left its reach, :func:`within_reach`), scores
    [P] (:func:`contour_score` of those), start_scores [P], refined_scores [P], lines [P]
    (valid lines over the views at the finest spacing)."""

    poses: Array
    scores: Array
    start_scores: Array
    refined_scores: Array
    lines: Array


def contour_score(ev: LineEvidence, view_mask: Array) -> tuple[Array, Array]:
    """[P] score (module docstring) and [P] valid line count of evidence [P, V, N]."""
    valid = ev.weight > 0
    n_valid = jnp.sum(valid, (-2, -1))
    total = jnp.maximum(jnp.sum(view_mask, -1) * valid.shape[-1], 1)
    mass = jnp.sum(ev.near_mass, (-2, -1)) / jnp.maximum(n_valid, 1)
    return mass * n_valid / total, n_valid


def refine_poses(model: ContourModel, images: Array, Ks: Array, T_cam_world: Array,
                 poses: Array, obj: Array, instance: Array, occ_id: Array, occ_depth: Array,
                 view_mask: Array, settings: ContourSettings = ContourSettings()
                 ) -> ContourResult:
    """Refine poses [P, 4, 4] (T_world_obj, mm) of objects ``obj`` [P] (rows of ``model``),
    instance ids [P] (for occlusion), in views ``images`` [V, H, W, 3] (uint8 or float in
    [0, 1]) with Ks [V, 3, 3], T_cam_world [V, 4, 4], occluder maps ``occ_id`` [V, h, w]
    (nearest instance, -1 none) and ``occ_depth`` [V, h, w] (mm), and ``view_mask`` [P, V]
    (views that see the pose's instance). Jit-able; the schedule of ``settings`` is unrolled
    as a scan over its levels."""
    images = jnp.asarray(images)
    if images.dtype == jnp.uint8:
        images = images.astype(jnp.float32) / 255.0
    poses = jnp.asarray(poses, jnp.float32)
    center, radius = model.center[obj], model.radius[obj]

    def evidence(p, frac):
        return _evidence(model, images, Ks, T_cam_world, p, obj, instance, occ_id, occ_depth,
                         view_mask, jnp.float32(frac), settings)

    fracs = jnp.repeat(jnp.asarray(settings.scales, jnp.float32), settings.iterations)

    def body(p, frac):
        ev = evidence(p, frac)
        return _update(p, poses, ev, center, radius, settings), None

    refined, _ = jax.lax.scan(body, poses, fracs)
    finest = min(settings.scales)
    s0, _ = contour_score(evidence(poses, finest), view_mask)
    s1, lines = contour_score(evidence(refined, finest), view_mask)
    keep = ((s1 >= s0) & jnp.isfinite(refined).all((-2, -1))
            & within_reach(refined, poses, center, radius, settings))
    out = jnp.where(keep[:, None, None], refined, poses)
    return ContourResult(poses=out, scores=jnp.maximum(s0, jnp.where(keep, s1, s0)),
                         start_scores=s0, refined_scores=s1, lines=lines)


def occluder_maps(meshes, mesh_index: Array, poses: Array, Ks: Array, T_cam_world: Array,
                  hw: tuple[int, int], instance_mask: Array) -> tuple[Array, Array]:
    """(ids [V, h, w] int32 nearest instance or -1, depth [V, h, w] mm) of instances at poses
    [B, 4, 4] (world), rendered by the rasterizer at ``hw`` (a reduced image size: the maps
    only decide which samples another instance hides). ``meshes``: a stacked RasterMesh
    (``RefinerMeshes.stacked``); instances outside ``instance_mask`` [B] are left out."""

    def one(i, T_wo):
        mesh = jax.tree.map(lambda x: x[i], meshes)
        T = jnp.einsum("vij,jk->vik", T_cam_world, T_wo)
        return render(mesh, T, Ks, hw, ("depth",))["depth"]  # [V, h, w]

    depth = jax.vmap(one)(mesh_index, poses)  # [B, V, h, w]
    depth = jnp.where((depth > 0) & instance_mask[:, None, None, None], depth, jnp.inf)
    ids = jnp.argmin(depth, 0).astype(jnp.int32)
    near = jnp.min(depth, 0)
    ids = jnp.where(jnp.isfinite(near), ids, -1)
    return ids, jnp.where(jnp.isfinite(near), near, 0.0)
