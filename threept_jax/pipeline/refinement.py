"""The refinement step of 3PT-R, shared by training and inference (docs/design.md section 1.3).

One render-and-compare iteration for one object instance seen in V calibrated views, with K pose
hypotheses (issue 14, section 3)::

    hypotheses [K, 4, 4] (T_world_obj) --render--> colour [K, V, H, W, 3] (crop size, network)
                                                   xyz, edge, mask [K, V, h, w] (map size)
    network(real crops, colour renders) --> descriptors F (real), Z (render), mask logits, scores
    reciprocal matching of Z (render edge pixels) against F --> N 2D-3D matches per (k, v)
    multi-view PnP per hypothesis, initialised at it --> PnP's pose
    safety test: keep PnP's pose only where the matches back it --> refined hypotheses

Frames:

* ``hypotheses`` are object poses in the world (mm); view v sees the object at
  ``T_cam_obj = T_cam_world[v] @ T_world_obj``.
* ``crop_K`` [V, 3, 3] are the intrinsics of the H x W crops (pixel-centre convention,
  ``threept_jax.geometry.camera``); the h x w descriptor map has ``K_map = crop_intrinsics(crop_K,
  (0, 0, W, H), (h, w))``, so map pixel (i, j) (row, column) is the crop point
  ((j + 0.5) W / w - 0.5, (i + 0.5) H / h - 0.5), the network contract's rule.
* The 2D point of a match is the real map pixel's centre converted to **crop pixels**, and
  :func:`~threept_jax.geometry.pnp.solve_pnp` runs with ``crop_K`` (its ``huber_px`` and
  ``tukey_px`` are crop pixels). The 3D point is in the object frame (mm): the render's object
  coordinate at the matched render pixel, refined to sub-pixel precision (below).

Match rule (:func:`reciprocal_matches`): cosine similarities S = Z F^T between every render
pixel and every real pixel of one (hypothesis, view) pair (the network's descriptors are unit
vectors; they are normalised again here). A render pixel r and a real pixel q match when q is
r's most similar real pixel and r is q's most similar *rendered object* pixel (mutual nearest
neighbours, render background excluded), and r is an edge pixel of the render (silhouette,
depth discontinuity or crease, ``render.raster.edges_from_geometry``). The N matches of highest
similarity are kept; fewer are padded with weight 0.

Sub-pixel 3D points (``subpixel=True``): with matches between pixel centres only, a hypothesis
within half a map pixel of the truth is a fixed point (every render pixel matches the real pixel
at the same place, and PnP returns the hypothesis), which leaves several mm of depth error. So
the 3D point seen by the real pixel q is estimated from the similarities of F_q to the render
pixels around r, whose object coordinates are known: a fit of s = alpha - b |X - X*|^2 over r's
3 x 3 neighbourhood gives X*. It assumes the similarity is a peaked, locally isotropic function
of 3D distance near its maximum (nearly so for the test oracle, an approximation for a
trained network). X* is kept within 1.5 pixel sizes of X_r. Neighbours off the object, across
a depth step or with unrelated descriptors (similarity under half of r's) are left out; too few
neighbours keep X_r. Working in 3D, creases and slanted faces need no special case.

Safe updates (:func:`update_hypotheses`): a network that does not know the part produces
matches that no single pose explains, and PnP over them still returns *a* pose, anywhere. The
step therefore keeps PnP's pose only when the matches back it: counted by
:func:`agreeing_matches` (a match agrees with a pose that projects its 3D point within
``agree_map_px`` map pixels of its real pixel), PnP's pose must explain at least
``min_agreement`` of the hypothesis' matches (and 6), no fewer than the input pose does, and
lie in front of a camera that sees the instance. Otherwise the hypothesis comes out unchanged
(``RefineResult.accepted`` False). The thresholds are set on the noise ladder
(``threept_jax.testing.refine_ladder``): about 0.9 of an oracle's matches agree with its
update, 0.4-0.55 at descriptor noise 1, 0.22-0.28 at noise 2 and under 0.2 when every
descriptor is an outlier.

The matches cannot catch matches that agree with each other but not with the image: a CPU-
trained network matches most render pixels near their own place, every such set passes the
consensus test, and PnP moves the pose by their noise (docs/training.md, issue 25). So the
step also asks the image (``RefineSettings.check_outline``): PnP's pose must put the object's
outline on the real crops' edges at least as well as the input pose does
(:func:`edge_alignment` of :func:`silhouettes`, rendered 4x supersampled so sub-pixel moves
count). Moves of the matched points under ``OUTLINE_MIN_SHIFT_PX`` (half a crop pixel) are
below what the crops' edges resolve and are left to the matches, so a good network's last
sub-pixel steps go through.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from threept_jax.geometry.camera import crop_intrinsics, invert, project, transform
from threept_jax.geometry.pnp import solve_pnp
from threept_jax.render.mesh import RasterMesh
from threept_jax.render.raster import render

Array = jax.Array
Network = Callable[[Array, Array], dict]


class Renders(NamedTuple):
    """Renders of K hypotheses into V crops (:func:`render_hypotheses`).

    rgb: [K, V, H, W, 3] float32 in [0, 1], shaded colour at the crop size (network input).
    xyz: [K, V, h, w, 3] object coordinates (mm) at the map's pixel centres, 0 on background.
    mask: [K, V, h, w] bool, object pixels of the map.
    edge: [K, V, h, w] bool, edge pixels of the map (silhouette, depth step, crease).
    K_map: [V, 3, 3] intrinsics of the h x w map.
    pixel_mm: [K, V] size of a map pixel at the object: depth of its bounding-sphere centre
      over the map's focal length (mm).
    """

    rgb: Array
    xyz: Array
    mask: Array
    edge: Array
    K_map: Array
    pixel_mm: Array


class Matches(NamedTuple):
    """N 2D-3D matches per (hypothesis, view) pair, padded with weight 0.

    points_3d: [K, V, N, 3] object coordinates (mm) of the render pixels.
    points_2d: [K, V, N, 2] matched real pixels in the crop frame (pixels of ``crop_K``).
    weights: [K, V, N] 1 for a match, 0 for padding.
    similarity: [K, V, N] cosine similarity of the match (-inf for padding).
    render_pixel: [K, V, N] flat index i * w + j of the render map pixel.
    real_pixel: [K, V, N] flat index of the matched real map pixel (before sub-pixel refinement).
    """

    points_3d: Array
    points_2d: Array
    weights: Array
    similarity: Array
    render_pixel: Array
    real_pixel: Array


class RefineResult(NamedTuple):
    """Output of :func:`refine_step`.

    hypotheses: [K, 4, 4] refined T_world_obj; the input pose where the update was refused
      (``accepted`` False).
    scores: [K] score logits of the input hypotheses (the network's ``scores``).
    mask_logits: [K, V, h, w] visible-mask logits of the real crops.
    view_scores: [K, V] per-view score logits.
    matches: the :class:`Matches` fed to PnP.
    pnp: dict of [K] arrays, ``solve_pnp``'s info (``rms_px`` in crop pixels, ``num_inliers``,
      ``converged``, ...).
    agreement: [K, 2] matches that agree with the input pose and with PnP's pose
      (:func:`agreeing_matches`).
    alignment: [K, 2] :func:`edge_alignment` of the input pose and of PnP's pose (NaN with
      ``RefineSettings.check_outline`` off).
    accepted: [K] bool, the update was kept (:func:`update_hypotheses`' safety test).
    """

    hypotheses: Array
    scores: Array
    mask_logits: Array
    view_scores: Array
    matches: Matches
    pnp: dict
    agreement: Array
    alignment: Array
    accepted: Array


def map_pixel_centres(index: Array, map_size: int, crop_size: int) -> Array:
    """Crop pixels [..., 2] (u, v) of the centres of flat map pixels ``index`` (i * w + j) of a
    square map of side ``map_size`` over a crop of side ``crop_size``: the network contract's
    rule, ((j + 0.5) W / w - 0.5, (i + 0.5) H / h - 0.5)."""
    scale = crop_size / map_size
    col = (index % map_size).astype(jnp.float32)
    row = (index // map_size).astype(jnp.float32)
    return jnp.stack([(col + 0.5) * scale - 0.5, (row + 0.5) * scale - 0.5], -1)


def map_intrinsics(crop_K: Array, crop_size: int, output_size: int) -> Array:
    """K [..., 3, 3] of the output_size^2 map of a crop_size^2 crop (pixel-centre rule)."""
    box = jnp.asarray([0.0, 0.0, crop_size, crop_size], jnp.float32)
    return crop_intrinsics(jnp.asarray(crop_K, jnp.float32), box, (output_size, output_size))


def render_hypotheses(mesh: RasterMesh, crop_K: Array, T_cam_world: Array, hypotheses: Array,
                      *, crop_size: int, output_size: int, ambient: float = 0.3) -> Renders:
    """Render K hypotheses [K, 4, 4] into V crops: colour at crop_size, geometry at output_size.

    crop_K [V, 3, 3] and T_cam_world [V, 4, 4] as in :func:`refine_step`. The map's xyz, mask
    and edge are rendered directly at the map resolution with ``K_map``, so map pixel centres
    are exact (no resampling of object coordinates across silhouettes).
    """
    crop_K = jnp.asarray(crop_K, jnp.float32)
    T_cam_obj = jnp.einsum("vij,kjl->kvil", jnp.asarray(T_cam_world, jnp.float32),
                           jnp.asarray(hypotheses, jnp.float32))  # [K, V, 4, 4]
    Kb = jnp.broadcast_to(crop_K, T_cam_obj.shape[:2] + (3, 3))
    K_map = map_intrinsics(crop_K, crop_size, output_size)
    rgb = render(mesh, T_cam_obj, Kb, (crop_size, crop_size), ("rgb",), ambient=ambient)["rgb"]
    geo = render(mesh, T_cam_obj, jnp.broadcast_to(K_map, Kb.shape), (output_size, output_size),
                 ("xyz", "mask", "edge"))
    z = jnp.einsum("kvj,j->kv", T_cam_obj[:, :, 2, :3], mesh.center) + T_cam_obj[:, :, 2, 3]
    pixel_mm = jnp.maximum(z, 1e-3) / jnp.sqrt(K_map[:, 0, 0] * K_map[:, 1, 1])
    return Renders(rgb=rgb, xyz=geo["xyz"], mask=geo["mask"], edge=geo["edge"], K_map=K_map,
                   pixel_mm=pixel_mm)


OUTLINE_MIN_SHIFT_PX = 0.5
"""Updates that move the matched points by less (crop pixels, :func:`outline_shift`) are not
judged by the outline check (:class:`RefineSettings`.check_outline)."""

SILHOUETTE_SUPERSAMPLING = 4
"""Sub-pixels per side of :func:`silhouettes`: outline moves of a quarter pixel change it."""


def silhouettes(mesh: RasterMesh, T_cam_obj: Array, crop_K: Array, crop_size: int) -> Array:
    """[K, V, H, W] float32 object coverage of each crop pixel at poses T_cam_obj [K, V, 4, 4]
    (crop_K [V, 3, 3]): the mask rendered at SILHOUETTE_SUPERSAMPLING x the crop size,
    box-averaged, so that the outline moves with sub-pixel pose changes."""
    a, size = SILHOUETTE_SUPERSAMPLING, crop_size * SILHOUETTE_SUPERSAMPLING
    K_fine = jnp.broadcast_to(map_intrinsics(crop_K, crop_size, size), T_cam_obj.shape[:2] + (3, 3))
    fine = render(mesh, T_cam_obj, K_fine, (size, size), ("mask",))["mask"]
    return fine.reshape(*fine.shape[:2], crop_size, a, crop_size, a).astype(jnp.float32).mean((3, 5))


# NumPy, not jnp: module constants must not start JAX's backend at import.
_SOBEL = np.array([[-1.0, 0.0, 1.0], [-2.0, 0.0, 2.0], [-1.0, 0.0, 1.0]], np.float32)
_GAUSS5 = np.exp(-0.5 * np.arange(-2.0, 3.0) ** 2).astype(np.float32)  # sigma 1 px, 5 taps


def _filter2d(x: Array, kernel: Array) -> Array:
    """[..., H, W] filtered by a 2D kernel (correlation, as OpenCV's filter2D), borders
    reflected without repeating the edge pixel (OpenCV's BORDER_REFLECT_101)."""
    r = kernel.shape[0] // 2
    lead = x.shape[:-2]
    xp = jnp.pad(x, [(0, 0)] * len(lead) + [(r, r), (r, r)], mode="reflect")
    xp = xp.reshape((-1, 1) + xp.shape[-2:])
    k = jnp.asarray(kernel, x.dtype)[None, None]
    out = jax.lax.conv_general_dilated(xp, k, (1, 1), "VALID")
    return out.reshape(lead + x.shape[-2:])


def _gradients(x: Array) -> tuple[Array, Array]:
    """Sobel derivatives (d/du, d/dv) of [..., H, W], OpenCV's 3x3 ``Sobel``."""
    return _filter2d(x, _SOBEL), _filter2d(x, _SOBEL.T)


def edge_alignment(crops: Array, coverage: Array, view_mask: Array | None = None) -> Array:
    """[K] how well the rendered silhouettes (``coverage`` [K, V, H, W] in [0, 1], bool or
    :func:`silhouettes`) lie on edges of the real crops
    [V, H, W, 3] (uint8 or float in [0, 1]), averaged over the views of ``view_mask`` [V].

    Per view: the silhouette, blurred (Gaussian, sigma 1 px), has gradient n across its outline;
    the crop's grey level has gradient g. The alignment is sum |g . n| / sum |n|, the real
    image's contrast across the outline, weighted along it, over the crop's mean gradient
    magnitude: about 1 for an outline placed at random, more where it runs along the object's
    edges (the gradient-orientation similarity of LINE-2D, Hinterstoisser et al. 2012, on the
    silhouette). A view whose render shows nothing scores 0. It reads the image, not the
    network, so it checks poses a network's matches would pass regardless.
    """
    crops = jnp.asarray(crops)
    grey = (crops.astype(jnp.float32) / (255.0 if crops.dtype == jnp.uint8 else 1.0)).mean(-1)
    gu, gv = _gradients(grey)  # [V, H, W]
    sil = jnp.asarray(coverage, jnp.float32)
    g1 = _GAUSS5 / _GAUSS5.sum()
    nu, nv = _gradients(_filter2d(sil, jnp.asarray(np.outer(g1, g1))))  # [K, V, H, W]
    across = jnp.sum(jnp.abs(gu * nu + gv * nv), axis=(-2, -1))
    norm = jnp.sum(jnp.hypot(nu, nv), axis=(-2, -1)) * jnp.mean(jnp.hypot(gu, gv), axis=(-2, -1))
    per_view = jnp.where(norm > 0, across / jnp.where(norm > 0, norm, 1.0), 0.0)  # [K, V]
    vm = jnp.ones(per_view.shape[-1], bool) if view_mask is None else jnp.asarray(view_mask)
    return jnp.sum(jnp.where(vm, per_view, 0.0), -1) / jnp.maximum(jnp.sum(vm), 1)


def _mutual_nn(Z: Array, F: Array, render_mask: Array, block: int):
    """Nearest neighbours both ways between Z [P, C] (render) and F [P, C] (real).

    Returns fwd [P] (best real pixel of each render pixel), fwd_sim [P] and bwd [P] (best
    rendered-object pixel of each real pixel). The P x P similarities are formed ``block``
    render rows at a time, so memory is block x P, not P^2.
    """
    P = Z.shape[0]
    nb = -(-P // block)
    pad = nb * block - P
    Zp = jnp.pad(Z, ((0, pad), (0, 0)))
    mp = jnp.pad(render_mask, (0, pad))

    def body(carry, b):
        best_val, best_idx = carry
        zb = jax.lax.dynamic_slice_in_dim(Zp, b * block, block)
        mb = jax.lax.dynamic_slice_in_dim(mp, b * block, block)
        S = zb @ F.T  # [block, P]
        f_idx = jnp.argmax(S, axis=1)
        f_val = jnp.max(S, axis=1)
        Sm = jnp.where(mb[:, None], S, -jnp.inf)
        col_val = jnp.max(Sm, axis=0)
        col_idx = jnp.argmax(Sm, axis=0) + b * block
        take = col_val > best_val  # strict: ties keep the lower render index
        carry = (jnp.where(take, col_val, best_val), jnp.where(take, col_idx, best_idx))
        return carry, (f_idx, f_val)

    init = (jnp.full((P,), -jnp.inf, F.dtype), jnp.zeros((P,), jnp.int32))
    (_, bwd), (fwd, fwd_sim) = jax.lax.scan(body, init, jnp.arange(nb))
    return fwd.reshape(-1)[:P].astype(jnp.int32), fwd_sim.reshape(-1)[:P], bwd


def _subpixel_points(Z: Array, f: Array, r: Array, xyz: Array, rmask: Array,
                     hw: tuple[int, int], pixel_mm: Array):
    """Sub-pixel 3D points [N, 3] seen by real pixels with descriptors f [N, C].

    Z [h*w, C] render descriptors, r [N] matched render pixels, xyz [h*w, 3] render object
    coordinates, rmask [h*w] render object pixels, pixel_mm [] the size of a map pixel at the
    object (mm). Fits s = alpha - b |Y - delta|^2 to the similarities s of f to the render
    pixels of r's 3 x 3 neighbourhood, Y their coordinates relative to r's (weighted linear
    least squares in (alpha', b, 2 b delta), with a small ridge on delta, which keeps it in the
    neighbours' tangent plane), and returns X_r + delta. Falls back to X_r with fewer than 6
    usable neighbours (in the map, on the object, within 4 pixel sizes in 3D: not across a depth
    step), no maximum (b <= 0) or a peak over 1.5 pixel sizes away.
    """
    h, w = hw
    i, j = r // w, r % w
    d = jnp.arange(-1, 2)
    ii = (i[:, None, None] + d[None, :, None] + 0 * d[None, None, :]).reshape(-1, 9)
    jj = (j[:, None, None] + d[None, None, :] + 0 * d[None, :, None]).reshape(-1, 9)
    inside = (ii >= 0) & (ii < h) & (jj >= 0) & (jj < w)
    nb = jnp.clip(ii, 0, h - 1) * w + jnp.clip(jj, 0, w - 1)  # [N, 9]
    s = jnp.einsum("nkc,nc->nk", Z[nb], f)
    Xr = xyz[r]
    Y = (xyz[nb] - Xr[:, None]) / pixel_mm  # [N, 9, 3] in pixel sizes
    y2 = jnp.sum(Y * Y, -1)
    near = s >= 0.5 * s[:, 4:5]  # in the peak: drops a neighbour whose descriptor is unrelated
    wt = (inside & rmask[nb] & (y2 <= 16.0) & near).astype(jnp.float32)
    phi = jnp.concatenate([jnp.ones_like(y2)[..., None], -y2[..., None], Y], -1)  # [N, 9, 5]
    A = jnp.einsum("nk,nka,nkb->nab", wt, phi, phi)
    A = A + jnp.diag(jnp.asarray([1e-6, 1e-6, 1e-3, 1e-3, 1e-3]))
    sol = jnp.linalg.solve(A, jnp.einsum("nk,nka,nk->na", wt, phi, s)[..., None])[..., 0]
    b = sol[:, 1]
    delta = sol[:, 2:] / (2.0 * jnp.where(b > 0, b, 1.0)[:, None])
    ok = (jnp.sum(wt, -1) >= 6) & (b > 0) & (jnp.sum(delta * delta, -1) <= 1.5**2)
    ok &= jnp.all(jnp.isfinite(delta), -1)
    return Xr + jnp.where(ok[:, None], delta * pixel_mm, 0.0)


def reciprocal_matches(real_desc: Array, render_desc: Array, render_xyz: Array,
                       render_mask: Array, render_edge: Array, pixel_mm: Array, *,
                       num_matches: int, crop_size: int, subpixel: bool = True,
                       block: int = 1024) -> Matches:
    """Mutual-nearest-neighbour matches of render edge pixels, N per (hypothesis, view).

    Args:
      real_desc, render_desc: [K, V, h, w, C] descriptors F and Z (normalised here).
      render_xyz: [K, V, h, w, 3] object coordinates (mm); render_mask, render_edge
        [K, V, h, w] bool.
      pixel_mm: [K, V] size of a map pixel at the object (``Renders.pixel_mm``), the length
        scale of the sub-pixel fit.
      num_matches: N, static.
      crop_size: H = W of the crop, to convert map pixels to crop pixels.
      subpixel: refine each match's 3D point (module docstring); False keeps the render
        pixel's coordinate.
      block: render rows per similarity block (memory block x h w per pair).

    Returns :class:`Matches` with leading [K, V]; see the module docstring for the rule.
    """
    K_, V, h, w, C = real_desc.shape
    P = h * w
    if num_matches > P:
        raise ValueError(f"num_matches={num_matches} exceeds the {h}x{w} map's {P} pixels")
    unit = lambda x: x * jax.lax.rsqrt(jnp.maximum(jnp.sum(x * x, -1, keepdims=True), 1e-24))  # noqa: E731
    F = unit(real_desc.astype(jnp.float32)).reshape(K_ * V, P, C)
    Z = unit(render_desc.astype(jnp.float32)).reshape(K_ * V, P, C)
    xyz = render_xyz.astype(jnp.float32).reshape(K_ * V, P, 3)
    rmask = render_mask.reshape(K_ * V, P)
    edge = render_edge.reshape(K_ * V, P)
    pix = jnp.asarray(pixel_mm, jnp.float32).reshape(K_ * V)
    blk = min(block, P)

    def one(F, Z, xyz, rmask, edge, pix):
        fwd, fwd_sim, bwd = _mutual_nn(Z, F, rmask, blk)
        mutual = bwd[fwd] == jnp.arange(P)
        valid = mutual & rmask & edge
        score = jnp.where(valid, fwd_sim, -jnp.inf)
        sim, r = jax.lax.top_k(score, num_matches)
        keep = jnp.isfinite(sim)
        q = fwd[r]
        X = _subpixel_points(Z, F[q], r, xyz, rmask, (h, w), pix) if subpixel else xyz[r]
        uv = map_pixel_centres(q, w, crop_size)
        return Matches(
            points_3d=jnp.where(keep[:, None], X, 0.0),
            points_2d=jnp.where(keep[:, None], uv, 0.0),
            weights=keep.astype(jnp.float32),
            similarity=sim,
            render_pixel=r.astype(jnp.int32),
            real_pixel=q,
        )

    m = jax.vmap(one)(F, Z, xyz, rmask, edge, pix)
    return jax.tree.map(lambda a: a.reshape((K_, V) + a.shape[1:]), m)


@dataclasses.dataclass(frozen=True)
class RefineSettings:
    """Options of the refinement step, one set for training and inference.

    Attributes:
      num_matches: N matches kept per (hypothesis, view) (:func:`reciprocal_matches`).
      subpixel: sub-pixel refinement of the matched 3D points.
      ambient: ambient term of the renders' headlight shading (training and inference must
        render alike: the network learnt to read these renders).
      huber_px, tukey_px: ``solve_pnp``'s robust scales, in crop pixels.
      pnp_iterations: ``solve_pnp``'s iteration cap.
      block: similarity rows per block in matching (memory block x h w per pair).
      max_faces: the renders' face budget: meshes are decimated to it when prepared
        (``render.mesh.prepare_mesh``), for training and inference alike.
      agree_map_px: a match agrees with a pose when the pose projects its 3D point within this
        many map pixels of its real pixel (:func:`agreeing_matches`).
      min_agreement: the share of a hypothesis' matches that must agree with PnP's pose for the
        update to be kept (and at least 6 matches); :func:`update_hypotheses`.
      check_outline: keep an update only if it puts the object's outline on the real crops'
        edges at least as well as the input pose (:func:`edge_alignment` of
        :func:`silhouettes`), unless it moves the matched points by under
        ``OUTLINE_MIN_SHIFT_PX`` (:func:`outline_shift`); off only to measure what the check
        does.
      depth_test: None (off), or the scale of :func:`depth_tested`'s likelihood-ratio
        statistic S (chi-square, one degree of freedom: 3.84 is its 95 % point): PnP's change
        of depth is kept in the share S / (S + depth_test) that the matches show; the rest of
        the update keeps the input pose's depth along the ray.
    """

    num_matches: int = 128
    subpixel: bool = True
    ambient: float = 0.3
    huber_px: float = 2.0
    tukey_px: float | None = 8.0
    pnp_iterations: int = 10
    block: int = 1024
    max_faces: int = 4096
    agree_map_px: float = 2.0
    min_agreement: float = 0.35
    check_outline: bool = True
    depth_test: float | None = None

    def __post_init__(self):
        if not self.agree_map_px > 0 or not 0.0 <= self.min_agreement <= 1.0:
            raise ValueError("RefineSettings.agree_map_px must be > 0 (map pixels) and "
                             f"min_agreement in [0, 1] (a share of the matches), got "
                             f"{self.agree_map_px} and {self.min_agreement}")
        for name in ("num_matches", "pnp_iterations", "block", "max_faces"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"RefineSettings.{name} must be >= 1, got {getattr(self, name)}")
        if not 0.0 <= self.ambient <= 1.0:
            raise ValueError(f"RefineSettings.ambient must be in [0, 1], got {self.ambient}")
        if self.depth_test is not None and not self.depth_test > 0:
            raise ValueError("RefineSettings.depth_test must be > 0 (a chi-square threshold, "
                             f"3.84 for 95 %) or None, got {self.depth_test}")
        if not self.huber_px > 0 or (self.tukey_px is not None and not self.tukey_px > 0):
            raise ValueError("RefineSettings.huber_px and tukey_px must be > 0 (tukey_px may be "
                             f"None), got {self.huber_px} and {self.tukey_px}")


def project_matches(matches: Matches, crop_K: Array, T_cam_world: Array, poses: Array
                    ) -> tuple[Array, Array]:
    """Where poses [K, 4, 4] put the matches' 3D points [K, V, N, 3] in the crops: pixels
    [K, V, N, 2] (of ``crop_K`` [V, 3, 3]) and camera depth [K, V, N]."""
    T_cam_obj = jnp.einsum("vij,kjl->kvil", T_cam_world, poses)  # [K, V, 4, 4]
    cam = transform(T_cam_obj, matches.points_3d)  # [K, V, N, 3]
    return project(cam, jnp.broadcast_to(crop_K, T_cam_obj.shape[:2] + (3, 3))), cam[..., 2]


def agreeing_matches(matches: Matches, crop_K: Array, T_cam_world: Array, poses: Array,
                     gate_px: float) -> Array:
    """[K] matches (weight > 0) that pose k [K, 4, 4] projects within ``gate_px`` crop pixels of
    their real pixel, over all views; matches [K, V, N], crop_K [V, 3, 3], T_cam_world [V, 4, 4].
    A point behind a camera does not agree."""
    uv, z = project_matches(matches, crop_K, T_cam_world, poses)
    d2 = jnp.sum((uv - matches.points_2d) ** 2, -1)
    ok = (matches.weights > 0) & (z > 0) & (d2 <= gate_px * gate_px)
    return jnp.sum(ok, axis=(1, 2))


def outline_shift(matches: Matches, crop_K: Array, T_cam_world: Array, before: Array,
                  after: Array) -> Array:
    """[K] how far (crop pixels) pose ``after`` moves the matched points' projections from
    where ``before`` puts them: the largest over views of the mean over valid matches (0 for a
    hypothesis without any)."""
    uv0, _ = project_matches(matches, crop_K, T_cam_world, before)
    uv1, _ = project_matches(matches, crop_K, T_cam_world, after)
    shift = jnp.sqrt(jnp.sum((uv1 - uv0) ** 2, -1))  # [K, V, N]
    w = matches.weights > 0
    per_view = jnp.sum(jnp.where(w, shift, 0.0), -1) / jnp.maximum(jnp.sum(w, -1), 1)
    return jnp.max(per_view, -1)


def depth_tested(matches: Matches, crop_K: Array, T_cam_world: Array, center: Array,
                 before: Array, after: Array, view: Array, gate_px: float,
                 threshold: float) -> tuple[Array, Array]:
    """PnP's poses ``after`` [K, 4, 4] with their change of depth kept as far as the matches
    show it (``RefineSettings.depth_test``); returns (those poses, the alternatives) [K, 4, 4]
    each.

    The depth of a small part far away is the least determined of its six degrees of freedom:
    it barely moves the projections, so PnP on noisy matches moves it by their noise. For each
    hypothesis the alternative is ``after`` with the object's centre ``center`` (object frame,
    mm) moved along its ray through camera ``view`` (an index of ``T_cam_world``) back to the
    input pose's depth in that camera, rotation unchanged. Over the n matches that ``after``
    projects within ``gate_px`` crop pixels (its inliers), with c the sum of squared
    reprojection errors, the likelihood-ratio statistic of that one constraint is
    S = ``(c_alternative - c_after) / (c_after / (n - 6))`` (chi-square with one degree of
    freedom when the alternative is right). The pose returned is the alternative moved
    towards ``after`` by S / (S + ``threshold``) of the way (the rotation is PnP's): all of it
    for exact matches, none where the alternative fits the inliers as well, half at S =
    ``threshold``; none with fewer than 7 inliers. (All or nothing at ``threshold`` measured
    worse on every held-out set, docs/training.md.) Where either pose puts the centre behind
    that camera, PnP's pose is returned as it is.
    """
    T_view = T_cam_world[view]
    R = after[:, :3, :3]
    c_after = transform(T_view @ after, center[None])[:, 0]  # [K, 3], camera frame
    c_before = transform(T_view @ before, center[None])[:, 0]
    scale = c_before[:, 2] / jnp.where(c_after[:, 2] > 1e-6, c_after[:, 2], -1.0)
    c_world = transform(invert(T_view), c_after * scale[:, None])  # [K, 3]
    alternative = after.at[:, :3, 3].set(c_world - jnp.einsum("kij,j->ki", R, center))
    uv1, z1 = project_matches(matches, crop_K, T_cam_world, after)
    uv0, _ = project_matches(matches, crop_K, T_cam_world, alternative)
    r1 = jnp.sum((uv1 - matches.points_2d) ** 2, -1)  # [K, V, N]
    r0 = jnp.sum((uv0 - matches.points_2d) ** 2, -1)
    inlier = (matches.weights > 0) & (z1 > 0) & (r1 <= gate_px * gate_px)
    n = jnp.sum(inlier, axis=(1, 2))
    cost1 = jnp.sum(jnp.where(inlier, r1, 0.0), axis=(1, 2))
    cost0 = jnp.sum(jnp.where(inlier, r0, 0.0), axis=(1, 2))
    variance = cost1 / jnp.maximum(n - 6, 1)
    statistic = (cost0 - cost1) / jnp.maximum(variance, 1e-12)
    # The share of PnP's depth change kept: S / (S + threshold), 0 with fewer than 7 inliers.
    # A centre behind the camera (scale <= 0) has no depth to put back along its ray: PnP's
    # pose is left to the step's other tests (in front of a camera).
    evidence = jnp.maximum(statistic, 0.0)
    kept = jnp.where(n >= 7, evidence / (evidence + threshold), 0.0)
    kept = jnp.where(scale <= 0, 1.0, kept)
    t = alternative[:, :3, 3] + kept[:, None] * (after[:, :3, 3] - alternative[:, :3, 3])
    return after.at[:, :3, 3].set(t), alternative


def update_hypotheses(outputs: dict, rend: Renders, mesh: RasterMesh, crops: Array,
                      crop_K: Array, T_cam_world: Array, hypotheses: Array,
                      settings: RefineSettings = RefineSettings(),
                      view_mask: Array | None = None) -> RefineResult:
    """The step after the network: matches from its outputs, multi-view PnP per hypothesis,
    each update checked against the real crops [V, H, W, 3] (module docstring, safe updates).

    ``outputs``: the network's dict for ONE instance, without the batch axis (``real_desc``,
    ``render_desc`` [K, V, h, w, C], ``mask_logits`` [K, V, h, w], ``view_scores`` [K, V],
    ``scores`` [K]); ``rend``: :func:`render_hypotheses` of ``hypotheses`` [K, 4, 4]. The
    trainer calls this on its own forward pass (under ``stop_gradient``) for the
    classification target, so training and inference share the step without a second forward.
    ``view_mask`` [V] bool (None: all views): the matches of a False view get weight 0 in PnP
    (and in the returned ``matches``), and it does not count as a view the pose is in front of.
    """
    s = settings
    crop_size = rend.rgb.shape[-2]
    matches = reciprocal_matches(
        outputs["real_desc"], outputs["render_desc"], rend.xyz, rend.mask, rend.edge,
        rend.pixel_mm, num_matches=s.num_matches, crop_size=crop_size, subpixel=s.subpixel,
        block=s.block)
    vm = jnp.ones(matches.weights.shape[1], bool) if view_mask is None else view_mask
    vm = jnp.asarray(vm, bool)
    matches = matches._replace(weights=jnp.where(vm[None, :, None], matches.weights, 0.0))
    crop_K = jnp.asarray(crop_K, jnp.float32)
    T_cam_world = jnp.asarray(T_cam_world, jnp.float32)
    hypotheses = jnp.asarray(hypotheses, jnp.float32)

    def pnp(p3, p2, wts, init):
        return solve_pnp(p3, p2, crop_K, T_cam_world, wts, init, huber_px=s.huber_px,
                         tukey_px=s.tukey_px, max_iterations=s.pnp_iterations)

    refined, info = jax.vmap(pnp)(matches.points_3d, matches.points_2d, matches.weights,
                                  hypotheses)
    gate = s.agree_map_px * crop_size / rend.xyz.shape[-2]
    if s.depth_test is not None:
        refined, _ = depth_tested(matches, crop_K, T_cam_world, mesh.center, hypotheses, refined,
                                  jnp.argmax(vm), gate, s.depth_test)
    # Safe update: PnP's pose replaces the input only when the image supports it. It must be
    # in front of a camera that sees the instance, and the matches must back it: at least
    # min_agreement of them (and 6) within agree_map_px of where it projects them, and no fewer
    # than agree with the input pose. Matches that no single pose explains (a network that
    # does not know the part) then leave the input as it was instead of moving it at random.
    c = transform(T_cam_world[None], transform(refined, mesh.center[None])[:, None])  # [K,V,1,3]
    in_front = jnp.any((c[..., 0, 2] > 0) & vm[None], axis=1)
    before = agreeing_matches(matches, crop_K, T_cam_world, hypotheses, gate)
    after = agreeing_matches(matches, crop_K, T_cam_world, refined, gate)
    valid = jnp.sum(matches.weights > 0, axis=(1, 2))
    # Image evidence, not the network's: PnP's pose must put the object's outline on the crops'
    # edges at least as well as the input pose does. Matches that agree with each other but
    # not with the image (every pixel matched near its own place) move the outline off them.
    if s.check_outline:
        poses = jnp.concatenate([hypotheses, refined])  # [2K, 4, 4]: input, then PnP's
        cover = silhouettes(mesh, jnp.einsum("vij,kjl->kvil", T_cam_world, poses), crop_K,
                            crop_size)
        aligned = edge_alignment(crops, cover, vm).reshape(2, -1).T  # [K, 2]
        # Moves under half a crop pixel are below what the crops' edges resolve (the check
        # would judge noise and stop a good network's last sub-pixel steps): left to the
        # matches.
        small = (outline_shift(matches, crop_K, T_cam_world, hypotheses, refined)
                 < OUTLINE_MIN_SHIFT_PX)
        seen = (aligned[:, 1] >= aligned[:, 0]) | small
    else:
        aligned = jnp.full((hypotheses.shape[0], 2), jnp.nan)
        seen = True
    accepted = (in_front & (after >= before) & seen
                & (after >= jnp.maximum(6.0, s.min_agreement * valid)))
    refined = jnp.where(accepted[:, None, None], refined, hypotheses)
    return RefineResult(
        hypotheses=refined,
        scores=outputs["scores"],
        mask_logits=outputs["mask_logits"],
        view_scores=outputs["view_scores"],
        matches=matches,
        pnp=info,
        agreement=jnp.stack([before, after], -1),
        alignment=aligned,
        accepted=accepted,
    )


def refine_step(
    network: Network,
    mesh: RasterMesh,
    crops: Array,
    crop_K: Array,
    T_cam_world: Array,
    hypotheses: Array,
    *,
    output_size: int,
    settings: RefineSettings = RefineSettings(),
) -> RefineResult:
    """One 3PT-R iteration: render, encode, match, multi-view PnP (module docstring).

    Args:
      network: ``network(real [1, V, H, W, 3], renders [1, K, V, H, W, 3]) -> dict`` with the
        refiner contract's outputs (``real_desc``, ``render_desc`` [1, K, V, h, w, C],
        ``mask_logits`` [1, K, V, h, w], ``view_scores`` [1, K, V], ``scores`` [1, K]).
      mesh: the prepared mesh (``to_raster_mesh(prepare_mesh(...))``).
      crops: [V, H, W, 3] real crops (H = W), uint8 or float in [0, 1].
      crop_K: [V, 3, 3] intrinsics of the crops (``crop_and_resize(..., K)`` with boxes from
        :func:`~threept_jax.geometry.framing.crop_boxes`).
      T_cam_world: [V, 4, 4] extrinsics (single view: the identity, V = 1).
      hypotheses: [K, 4, 4] T_world_obj (mm).
      output_size: h = w of the network's maps (``RefinerConfig.output_size``).
      settings: :class:`RefineSettings` (matches, renders' shading, PnP).

    Pure and jit-able with ``network``, the sizes and ``settings`` static; gradients are not
    meant to flow through it (the trainer runs :func:`update_hypotheses` under
    ``stop_gradient``).
    """
    crops = jnp.asarray(crops)
    V, H, W = crops.shape[:3]
    if H != W:
        raise ValueError(f"crops must be square (RefinerConfig.crop_size), got {H}x{W}")
    Kh = hypotheses.shape[0]
    if crop_K.shape != (V, 3, 3) or T_cam_world.shape != (V, 4, 4):
        raise ValueError(
            f"crop_K must be [V, 3, 3] and T_cam_world [V, 4, 4] with V={V} crops, got "
            f"{crop_K.shape} and {T_cam_world.shape}"
        )
    if hypotheses.shape != (Kh, 4, 4):
        raise ValueError(f"hypotheses must be [K, 4, 4], got {hypotheses.shape}")
    hypotheses = jnp.asarray(hypotheses, jnp.float32)
    rend = render_hypotheses(mesh, crop_K, T_cam_world, hypotheses, crop_size=H,
                             output_size=output_size, ambient=settings.ambient)
    out = jax.tree.map(lambda x: x[0], network(crops[None], rend.rgb[None]))
    return update_hypotheses(out, rend, mesh, crops, crop_K, T_cam_world, hypotheses, settings)
