"""Cost matrix and Hungarian matching of hypotheses to ground-truth instances.

The first two of the three loss layers (docs/design.md habit 5, after scenic's
``owl_vit/losses.compute_cost`` and ``matchers/common.cpu_matcher``):

1. :func:`detection_cost` (pure jnp): DETR's matching cost, ``w_class * focal cost +
   w_l1 * L1(cxcywh) - w_giou * GIoU`` for every (hypothesis, target) pair.
2. :func:`hungarian_match`: optimal one-to-one assignment on the host with
   ``scipy.optimize.linear_sum_assignment`` through ``jax.pure_callback``. Padded targets are
   sliced off the matrix before the call and come back unmatched; the result carries no
   gradient (the cost is wrapped in ``stop_gradient``).

Shapes: B batch, P hypotheses (patches), M padded targets.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import scipy.optimize

from threept_jax.geometry.boxes import cxcywh_to_xyxy, generalized_box_iou
from threept_jax.losses.focal import focal_matching_cost

Array = jax.Array


def detection_cost(
    pred_boxes: Array,
    presence_logits: Array,
    target_boxes: Array,
    *,
    class_weight: float,
    l1_weight: float,
    giou_weight: float,
    focal_alpha: float | None = 0.25,
    focal_gamma: float = 2.0,
) -> Array:
    """Matching cost [B, P, M] of hypotheses vs targets.

    pred_boxes [B, P, 4] and target_boxes [B, M, 4] are normalised cxcywh; presence_logits
    [B, P]. Padded targets are not treated here: :func:`hungarian_match` drops them.
    """
    cost_class = focal_matching_cost(presence_logits, alpha=focal_alpha, gamma=focal_gamma)
    cost_l1 = jnp.sum(jnp.abs(pred_boxes[:, :, None, :] - target_boxes[:, None, :, :]), -1)
    giou = generalized_box_iou(cxcywh_to_xyxy(pred_boxes), cxcywh_to_xyxy(target_boxes))
    return class_weight * cost_class[:, :, None] + l1_weight * cost_l1 - giou_weight * giou


def _match_one(cost: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """cost [P, M], mask [M] -> row matched to each column [M], -1 for padded/unmatched."""
    out = np.full(cost.shape[1], -1, np.int32)
    cols = np.flatnonzero(mask)
    if cols.size == 0 or cost.shape[0] == 0:
        return out
    sub = np.asarray(cost[:, cols], np.float64)
    finite = np.isfinite(sub)
    if not finite.all():
        # Non-finite costs (a diverged prediction) would make SciPy reject the matrix; such
        # pairs become the most expensive finite choice instead.
        big = (np.abs(sub[finite]).max() if finite.any() else 0.0) * 2.0 + 1.0
        sub = np.where(finite, sub, big)
    rows, matched_cols = scipy.optimize.linear_sum_assignment(sub)
    out[cols[matched_cols]] = rows
    return out


def _match_host(cost: np.ndarray, mask: np.ndarray) -> np.ndarray:
    cost, mask = np.asarray(cost), np.asarray(mask, bool)
    batch = cost.shape[:-2]
    p, m = cost.shape[-2:]
    flat_cost = cost.reshape(-1, p, m)
    flat_mask = np.broadcast_to(mask, (*batch, m)).reshape(-1, m)
    out = np.zeros((flat_cost.shape[0], m), np.int32)
    for i, (c, k) in enumerate(zip(flat_cost, flat_mask, strict=True)):
        out[i] = _match_one(c, k)
    return out.reshape(*batch, m).astype(np.int32)


def hungarian_match(cost: Array, target_mask: Array) -> Array:
    """Optimal assignment: cost [..., P, M], target_mask [..., M] -> matched [..., M] int32.

    ``matched[..., m]`` is the hypothesis assigned to target m, or -1 when target m is
    padding (mask False) or could not be matched (more valid targets than hypotheses). Only
    the valid columns are passed to ``scipy.optimize.linear_sum_assignment``, so padded
    targets never influence the assignment. Works under ``jit`` and ``vmap`` (host callback);
    gradients through ``cost`` are zero.
    """
    cost = jax.lax.stop_gradient(jnp.asarray(cost, jnp.float32))
    target_mask = jnp.asarray(target_mask, bool)
    if cost.ndim < 2 or target_mask.shape[-1] != cost.shape[-1]:
        raise ValueError(
            f"cost [..., P, M] and target_mask [..., M] disagree: {cost.shape} vs "
            f"{target_mask.shape}"
        )
    target_mask = jnp.broadcast_to(target_mask, (*cost.shape[:-2], cost.shape[-1]))
    out_shape = jax.ShapeDtypeStruct((*cost.shape[:-2], cost.shape[-1]), jnp.int32)
    return jax.pure_callback(_match_host, out_shape, cost, target_mask,
                             vmap_method="broadcast_all")
