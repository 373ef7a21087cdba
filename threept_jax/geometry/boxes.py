"""Axis-aligned boxes: conversions, IoU, generalised IoU and a fixed-size, jit-able NMS.

Boxes are xyxy in pixel-edge coordinates at the edges of the system and normalised cxcywh
inside the detector (see ``camera`` for the pixel convention). Shapes: N, M boxes.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

Array = jax.Array


def xyxy_to_cxcywh(b: Array) -> Array:
    """[..., 4] (x0, y0, x1, y1) -> [..., 4] (cx, cy, w, h)."""
    b = jnp.asarray(b)
    x0, y0, x1, y1 = jnp.moveaxis(b, -1, 0)
    return jnp.stack([(x0 + x1) / 2, (y0 + y1) / 2, x1 - x0, y1 - y0], -1)


def cxcywh_to_xyxy(b: Array) -> Array:
    """[..., 4] (cx, cy, w, h) -> [..., 4] (x0, y0, x1, y1)."""
    b = jnp.asarray(b)
    cx, cy, w, h = jnp.moveaxis(b, -1, 0)
    return jnp.stack([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2], -1)


def box_area(b: Array) -> Array:
    """[..., 4] xyxy -> [...] area (0 for inverted boxes)."""
    b = jnp.asarray(b)
    return jnp.clip(b[..., 2] - b[..., 0], 0) * jnp.clip(b[..., 3] - b[..., 1], 0)


def _intersection_union(a: Array, b: Array) -> tuple[Array, Array]:
    """a [..., N, 4], b [..., M, 4] -> intersection, union [..., N, M]."""
    a, b = jnp.asarray(a), jnp.asarray(b)
    lt = jnp.maximum(a[..., :, None, :2], b[..., None, :, :2])
    rb = jnp.minimum(a[..., :, None, 2:], b[..., None, :, 2:])
    wh = jnp.clip(rb - lt, 0)
    inter = wh[..., 0] * wh[..., 1]
    union = box_area(a)[..., :, None] + box_area(b)[..., None, :] - inter
    return inter, union


def box_iou(a: Array, b: Array, eps: float = 1e-9) -> Array:
    """Pairwise IoU: a [..., N, 4], b [..., M, 4] (xyxy) -> [..., N, M]."""
    inter, union = _intersection_union(a, b)
    return inter / jnp.maximum(union, eps)


def generalized_box_iou(a: Array, b: Array, eps: float = 1e-9) -> Array:
    """Pairwise generalised IoU (Rezatofighi et al. 2019) in [-1, 1]: [..., N, 4], [..., M, 4] -> [..., N, M]."""
    a, b = jnp.asarray(a), jnp.asarray(b)
    inter, union = _intersection_union(a, b)
    iou = inter / jnp.maximum(union, eps)
    lt = jnp.minimum(a[..., :, None, :2], b[..., None, :, :2])
    rb = jnp.maximum(a[..., :, None, 2:], b[..., None, :, 2:])
    wh = jnp.clip(rb - lt, 0)
    hull = wh[..., 0] * wh[..., 1]
    return iou - (hull - union) / jnp.maximum(hull, eps)


def nms(
    boxes: Array,
    scores: Array,
    iou_threshold: float,
    max_outputs: int,
    score_threshold: float = -jnp.inf,
) -> tuple[Array, Array]:
    """Greedy non-maximum suppression with a fixed output size.

    boxes [N, 4] xyxy, scores [N] -> (indices [max_outputs] int32, valid [max_outputs] bool).
    Repeatedly keeps the highest remaining score (ties: lowest index) and drops every box whose
    IoU with it exceeds ``iou_threshold``. Slots past the last kept box have ``valid=False`` and
    index 0. Memory is O(N) and time O(max_outputs * N), so it suits the few thousand
    candidates of one pan-and-scan pass; vmap it over images or classes.
    """
    boxes = jnp.asarray(boxes)
    scores = jnp.asarray(scores)
    alive = scores > score_threshold

    def body(i, state):
        alive, idx, valid = state
        masked = jnp.where(alive, scores, -jnp.inf)
        best = jnp.argmax(masked)
        ok = alive[best]
        iou = box_iou(boxes[best][None], boxes)[0]
        suppress = (iou > iou_threshold) | (jnp.arange(boxes.shape[0]) == best)
        alive = alive & ~(suppress & ok)
        return alive, idx.at[i].set(jnp.where(ok, best, 0)), valid.at[i].set(ok)

    idx = jnp.zeros((max_outputs,), jnp.int32)
    valid = jnp.zeros((max_outputs,), bool)
    _, idx, valid = jax.lax.fori_loop(0, max_outputs, body, (alive, idx, valid))
    return idx, valid
