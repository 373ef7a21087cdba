"""3PT-R training losses: dense matching (the paper's eq. (1)), hypothesis classification,
visible-mask segmentation (docs/design.md section 1.3, "Training").

One function per term, each returning ``(loss, metrics)`` (a float32 scalar and a dict of
float32 scalars); the caller weights and sums the terms. All are pure ``jnp``, jit- and
vmap-able, and compute in float32 whatever the network's dtype.

Shapes: B instances, J jittered hypotheses, h x w the descriptor / mask map, C the descriptor
dimension; ``...`` any leading dimensions (e.g. B, K, V), broadcast between the arguments.

**Map pixels.** Pixel (i, j) of an h x w map (row i, column j) is sampled at
(u, v) = (j, i) of ``K_map``, the map's own intrinsics (OpenCV pixel centres, the convention
of :mod:`threept_jax.geometry.camera`; the refiner contract gives ``K_map`` by scaling the
crop's K with the pixel-centre rule). A projected point (u, v) belongs to the *nearest* map
pixel, ``(i, j) = (floor(v + 0.5), floor(u + 0.5))``: a tie at exactly half a pixel goes to
the higher index, and the point lies inside the map iff ``-0.5 <= u < w - 0.5`` and
``-0.5 <= v < h - 0.5``.

**Temperature.** :data:`MATCHING_TEMPERATURE` = 0.05, fixed. The descriptors are unit
vectors, so the logits Z . F / tau lie in [-1/tau, 1/tau] = [-20, 20]. With h * w = 4096
candidates a confident match needs its logit about log 4096 = 8.3 above the field: at
tau = 0.05 a correct match with orthogonal negatives reaches a loss of
log(1 + 4095 e^-20) = 1e-5, while tau = 0.1 (LoFTR's dual softmax, SimCLR) floors it at
log(1 + 4095 e^-10) = 0.17 and keeps pushing on the whole map after the match is right. The
neighbours of the ground-truth pixel, which a DPT decoder makes similar (cosine ~0.9), weigh
e^-2 = 0.14 of the target at tau = 0.05 but e^-1 = 0.37 at 0.1, so the smaller tau lets the
loss resolve single pixels, which is what PnP needs. Between MoCo's 0.07 and the ~0.01 that
CLIP's learned temperature settles at. Fixed rather than learned because inference matches by
reciprocal nearest neighbour on cosine, which tau does not change: tau only shapes training,
so a learned one adds a parameter (and, as CLIP's clipping at 1/100 shows, a bound to guard)
without changing what inference reads. A caller that wants it learned passes a traced scalar
as ``temperature``; the loss is differentiable in it (tested).
"""

from __future__ import annotations

import dataclasses
import numbers

import jax
import jax.numpy as jnp

Array = jax.Array

MATCHING_TEMPERATURE = 0.05
"""Softmax temperature tau of the matching loss (module docstring: why 0.05)."""

WITHIN_PX = 2.0
"""Radius, in map pixels, of the matching metric ``within_2px``."""


def _check_temperature(temperature) -> None:
    if isinstance(temperature, numbers.Real) and not (0.0 < float(temperature) < float("inf")):
        raise ValueError(
            f"matching_loss: temperature must be a finite number > 0, got {temperature}; "
            f"the default is MATCHING_TEMPERATURE = {MATCHING_TEMPERATURE}")


def _ground_truth_pixels(render_xyz: Array, render_mask: Array, T_cam_obj_gt: Array,
                         K_map: Array, visible_mask: Array) -> tuple[Array, Array]:
    """Ground-truth real pixel of every render pixel: flat index [N, h*w] int32, valid bool.

    render_xyz [N, h, w, 3], render_mask [N, h, w], T [N, 4, 4], K [N, 3, 3], visible [N, h, w].
    """
    n, h, w = render_mask.shape
    x = render_xyz.reshape(n, h * w, 3)
    R, t = T_cam_obj_gt[:, :3, :3], T_cam_obj_gt[:, :3, 3]
    p_cam = jnp.einsum("nij,npj->npi", R, x) + t[:, None, :]
    p_img = jnp.einsum("nij,npj->npi", K_map, p_cam)
    z = p_cam[..., 2]
    in_front = z > 0.0
    denom = jnp.where(in_front, p_img[..., 2], 1.0)
    u = p_img[..., 0] / denom
    v = p_img[..., 1] / denom
    # Nearest map pixel; non-finite u, v (NaN xyz off the render mask) fail both bounds.
    col = jnp.floor(u + 0.5)
    row = jnp.floor(v + 0.5)
    inside = in_front & (col >= 0) & (col <= w - 1) & (row >= 0) & (row <= h - 1)
    col_i = jnp.where(inside, col, 0).astype(jnp.int32)
    row_i = jnp.where(inside, row, 0).astype(jnp.int32)
    index = row_i * w + col_i
    seen = jnp.take_along_axis(visible_mask.reshape(n, h * w), index, axis=1)
    valid = render_mask.reshape(n, h * w) & inside & seen
    return jnp.where(valid, index, 0), valid


def _pair_sums(w: int, temperature, args) -> Array:
    """One (real, render) pair: [loss sum, top-1 count, within-2-px count] over valid pixels.

    Materialises the pair's [h*w, h*w] logits once (float32); rematerialised in the backward
    pass by the caller's ``jax.checkpoint``.
    """
    real, render, index, valid = args  # [P, C], [P, C], [P], [P]
    logits = jnp.einsum("pc,qc->pq", render, real) / temperature  # [P render, P real]
    target = jnp.take_along_axis(logits, index[:, None], axis=1)[:, 0]
    nll = jax.nn.logsumexp(logits, axis=1) - target
    best = jnp.argmax(logits, axis=1)
    di = (best // w - index // w).astype(jnp.float32)
    dj = (best % w - index % w).astype(jnp.float32)
    top1 = best == index
    near = di * di + dj * dj <= WITHIN_PX * WITHIN_PX
    own = jnp.arange(index.shape[0])  # each render pixel's own place in the real map
    si = (own // w - index // w).astype(jnp.float32)
    sj = (own % w - index % w).astype(jnp.float32)
    same_place = si * si + sj * sj <= WITHIN_PX * WITHIN_PX
    return jnp.stack([jnp.sum(jnp.where(valid, nll, 0.0)),
                      jnp.sum(valid & top1).astype(jnp.float32),
                      jnp.sum(valid & near).astype(jnp.float32),
                      jnp.sum(valid & same_place).astype(jnp.float32)])


def matching_loss(real_desc: Array, render_desc: Array, render_xyz: Array, render_mask: Array,
                  T_cam_obj_gt: Array, K_map: Array, visible_mask: Array, *,
                  temperature=MATCHING_TEMPERATURE) -> tuple[Array, dict[str, Array]]:
    """The paper's eq. (1): softmax over real-map pixels, target the ground-truth correspondence.

    real_desc [..., h, w, C] F and render_desc [..., h, w, C] Z (unit descriptors), render_xyz
    [..., h, w, 3] (object frame, mm), render_mask [..., h, w] bool, T_cam_obj_gt [..., 4, 4],
    K_map [..., 3, 3] (the map's intrinsics), visible_mask [..., h, w] bool (ground-truth
    visible mask of the real crop at map resolution); leading dimensions broadcast.

    A render pixel (x, y) is *valid* when it is inside ``render_mask`` and its point
    ``render_xyz``, moved by ``T_cam_obj_gt`` (in front of the camera) and projected with
    ``K_map``, lands inside the map on a pixel (i, j) (nearest pixel, module docstring) where
    ``visible_mask`` is set. Its loss is

        -log softmax_{(i', j') in all h*w real pixels}(Z_xy . F_i'j' / tau) at (i, j),

    and the loss is the mean over all valid render pixels of all pairs (0 when there are none,
    with zero, finite gradients). Self-occlusion at the ground-truth pose is not tested (no
    ground-truth depth here): a render point hidden behind the object's own front at the true
    pose but projecting inside its visible mask keeps that pixel as its target.

    ``temperature``: tau, :data:`MATCHING_TEMPERATURE` by default (module docstring); a traced
    scalar makes it learnable.

    Metrics: ``loss``; ``num_valid`` (valid render pixels); ``top1`` (share of valid render
    pixels whose argmax real pixel is the ground-truth one); ``within_2px`` (share whose argmax
    is within 2 map pixels, Euclidean, of it); ``within_2px_same_place`` (share whose
    ground-truth pixel is within 2 map pixels of the render pixel's own place: what matching
    by position alone reaches, the baseline ``within_2px`` must beat for the descriptors to
    carry more than where a pixel is). Shares are 0 with no valid pixel.

    Memory: the logits of one pair are [h*w, h*w] float32 (64 x 64 maps: 16.8M entries,
    64 MiB). Pairs are processed one after another (``lax.map``) with the pair's matrix
    rematerialised in the backward pass, so at most one pair's matrix is live, or one per
    example when the caller vmaps this function.
    """
    _check_temperature(temperature)
    real = jnp.asarray(real_desc, jnp.float32)
    render = jnp.asarray(render_desc, jnp.float32)
    xyz = jnp.asarray(render_xyz, jnp.float32)
    rmask = jnp.asarray(render_mask, bool)
    vmask = jnp.asarray(visible_mask, bool)
    T = jnp.asarray(T_cam_obj_gt, jnp.float32)
    K = jnp.asarray(K_map, jnp.float32)
    h, w, c = real.shape[-3:]
    shapes = {"render_desc": (render.shape[-3:], (h, w, c)),
              "render_xyz": (xyz.shape[-3:], (h, w, 3)),
              "render_mask": (rmask.shape[-2:], (h, w)),
              "visible_mask": (vmask.shape[-2:], (h, w)),
              "T_cam_obj_gt": (T.shape[-2:], (4, 4)), "K_map": (K.shape[-2:], (3, 3))}
    for name, (got, want) in shapes.items():
        if tuple(got) != want:
            raise ValueError(f"matching_loss: {name} must end in {want} (real_desc is "
                             f"{tuple(real.shape)}), got shape ending in {tuple(got)}")
    lead = jnp.broadcast_shapes(real.shape[:-3], render.shape[:-3], xyz.shape[:-3],
                                rmask.shape[:-2], vmask.shape[:-2], T.shape[:-2], K.shape[:-2])
    n = 1
    for d in lead:
        n *= d

    def flat(a, tail):
        return jnp.broadcast_to(a, (*lead, *tail)).reshape(n, *tail)

    index, valid = _ground_truth_pixels(flat(xyz, (h, w, 3)), flat(rmask, (h, w)),
                                        flat(T, (4, 4)), flat(K, (3, 3)), flat(vmask, (h, w)))
    pair = jax.checkpoint(lambda args: _pair_sums(w, temperature, args))
    sums = jax.lax.map(pair, (flat(real, (h, w, c)).reshape(n, h * w, c),
                              flat(render, (h, w, c)).reshape(n, h * w, c), index, valid))
    total = jnp.sum(sums, axis=0)
    count = jnp.sum(valid).astype(jnp.float32)
    denom = jnp.maximum(count, 1.0)
    loss = total[0] / denom
    return loss, {"loss": loss, "num_valid": count, "top1": total[1] / denom,
                  "within_2px": total[2] / denom, "within_2px_same_place": total[3] / denom}


def classification_loss(scores: Array, errors: Array,
                        valid: Array) -> tuple[Array, dict[str, Array]]:
    """Which jittered hypothesis ends closest: scores [B, J] logits, errors [B, J], valid [B].

    ``errors``: the pose error of each hypothesis after one refinement step (e.g. MSSD in mm),
    lower is better. Softmax cross-entropy of ``scores`` with target ``argmin(errors)`` (the
    first on a tie); a non-finite error (a failed step) counts as +inf, and an instance with
    no finite error is left out like an invalid one. Mean over the instances kept, 0 when none.

    Metrics: ``loss``; ``accuracy`` (share of kept instances with argmax score == target).
    """
    s = jnp.asarray(scores, jnp.float32)
    e = jnp.asarray(errors, jnp.float32)
    if s.ndim != 2 or e.shape != s.shape:
        raise ValueError(f"classification_loss: scores and errors must both be [B, J], got "
                         f"{tuple(s.shape)} and {tuple(e.shape)}")
    keep = jnp.asarray(valid, bool)
    if keep.shape != s.shape[:1]:
        raise ValueError(f"classification_loss: valid must be [B] = {s.shape[:1]}, got "
                         f"{tuple(keep.shape)}")
    finite = jnp.isfinite(e)
    e = jnp.where(finite, e, jnp.inf)
    keep = keep & jnp.any(finite, axis=1)
    target = jnp.argmin(e, axis=1)
    nll = jax.nn.logsumexp(s, axis=1) - jnp.take_along_axis(s, target[:, None], axis=1)[:, 0]
    correct = jnp.argmax(s, axis=1) == target
    denom = jnp.maximum(jnp.sum(keep), 1).astype(jnp.float32)
    loss = jnp.sum(jnp.where(keep, nll, 0.0)) / denom
    accuracy = jnp.sum(keep & correct).astype(jnp.float32) / denom
    return loss, {"loss": loss, "accuracy": accuracy}


def segmentation_loss(mask_logits: Array, visible_mask: Array,
                      valid: Array) -> tuple[Array, dict[str, Array]]:
    """Per-pixel binary cross-entropy of the visible mask of the real crop.

    mask_logits [..., h, w], visible_mask [..., h, w] bool, valid [...] bool (whole maps;
    leading dimensions broadcast, e.g. a visible mask [B, 1, V, h, w] against logits
    [B, K, V, h, w]). BCE(x, t) = softplus(x) - t x, finite for any logit; mean over the
    pixels of the valid maps, 0 when none.

    Metrics: ``loss``; ``iou``, the mean over valid maps of the IoU between ``logits > 0`` and
    the visible mask (1 for a map where both are empty), 0 when no map is valid.
    """
    x = jnp.asarray(mask_logits, jnp.float32)
    t = jnp.asarray(visible_mask, bool)
    keep = jnp.asarray(valid, bool)
    lead = jnp.broadcast_shapes(x.shape[:-2], t.shape[:-2], keep.shape)
    if t.shape[-2:] != x.shape[-2:]:
        raise ValueError(f"segmentation_loss: visible_mask must end in {x.shape[-2:]} like "
                         f"mask_logits, got {tuple(t.shape)}")
    hw = x.shape[-2:]
    x = jnp.broadcast_to(x, (*lead, *hw))
    t = jnp.broadcast_to(t, (*lead, *hw))
    keep = jnp.broadcast_to(keep, lead)
    bce = jax.nn.softplus(x) - jnp.where(t, x, 0.0)
    per_map = jnp.mean(bce, axis=(-2, -1))
    maps = jnp.maximum(jnp.sum(keep), 1).astype(jnp.float32)
    loss = jnp.sum(jnp.where(keep, per_map, 0.0)) / maps
    pred = x > 0
    inter = jnp.sum(pred & t, axis=(-2, -1))
    union = jnp.sum(pred | t, axis=(-2, -1))
    iou = jnp.where(union > 0, inter / jnp.maximum(union, 1), 1.0)
    return loss, {"loss": loss, "iou": jnp.sum(jnp.where(keep, iou, 0.0)) / maps}


def mssd_errors(T_est: Array, T_gt: Array, points: Array, point_mask: Array, symmetries: Array,
                symmetry_mask: Array) -> Array:
    """Symmetry-aware pose error (BOP's MSSD, mm) of J estimates of one instance: [J].

    T_est [J, 4, 4], T_gt [4, 4] (same frame, mm); points [P, 3] object-frame model points with
    point_mask [P] (padding False); symmetries [Ns, 4, 4] object-frame transforms S with
    symmetry_mask [Ns] (the identity among them). MSSD = min over S of max over points of
    ``|T_est x - T_gt S x|``, as :func:`threept_jax.eval.pose_error.mssd` on the same points
    (the classification target uses the corners of the prepared mesh, a close stand-in for
    every vertex). Not differentiated (the target sits under ``stop_gradient``).
    """
    T_est = jnp.asarray(T_est, jnp.float32)
    T_gt = jnp.asarray(T_gt, jnp.float32)
    x = jnp.asarray(points, jnp.float32)
    Tg = jnp.einsum("ij,sjk->sik", T_gt, jnp.asarray(symmetries, jnp.float32))  # [Ns, 4, 4]
    xe = jnp.einsum("jab,pb->jpa", T_est[:, :3, :3], x) + T_est[:, None, :3, 3]  # [J, P, 3]
    xg = jnp.einsum("sab,pb->spa", Tg[:, :3, :3], x) + Tg[:, None, :3, 3]  # [Ns, P, 3]
    d2 = jnp.sum(jnp.square(xe[:, None] - xg[None]), -1)  # [J, Ns, P]
    d2 = jnp.max(jnp.where(jnp.asarray(point_mask, bool), d2, 0.0), -1)
    d2 = jnp.min(jnp.where(jnp.asarray(symmetry_mask, bool), d2, jnp.inf), -1)
    return jnp.sqrt(d2)


@dataclasses.dataclass(frozen=True)
class RefinerLossConfig:
    """Weights of the three 3PT-R terms and the matching temperature.

    total = matching_weight * matching + classification_weight * classification
            + segmentation_weight * segmentation.

    ``temperature``: tau of :func:`matching_loss` (module docstring: why 0.05).
    """

    matching_weight: float = 1.0
    classification_weight: float = 0.5
    segmentation_weight: float = 1.0
    temperature: float = MATCHING_TEMPERATURE

    def __post_init__(self):
        for name in ("matching_weight", "classification_weight", "segmentation_weight"):
            if not float(getattr(self, name)) >= 0:
                raise ValueError(f"RefinerLossConfig.{name} must be >= 0, got "
                                 f"{getattr(self, name)}")
        _check_temperature(self.temperature)
