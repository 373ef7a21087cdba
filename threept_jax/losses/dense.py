"""The dense cell detector's loss: task-aligned assignment, then classification and box terms.

Three layers, as the other losses: the cost (each ground-truth box's alignment with each
anchor place), the assignment (top-k places per box, a place claimed by several boxes goes to
the one it overlaps most), the loss (binary cross-entropy of every logit against soft targets,
generalised IoU of the assigned places' boxes). The assignment is TOOD's task-aligned one (Feng
et al., ICCV 2021; YOLOv8's ``TaskAlignedAssigner``): a place is positive for a box when its
centre lies in the box and it is among the ``topk`` places with the highest
``score**alpha * iou**beta``, so the places that already classify and locate the part best are
trained to, and the classification target is that alignment normalised per box to the box's
best IoU, so scores rank boxes by quality. No gradient flows through the assignment.

Shapes: B images, A places, C parts, M ground-truth boxes (padded, ``gt_valid`` masks them).
Boxes are xyxy pixels of the network's input.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import optax

from threept_jax.geometry.boxes import box_iou, generalized_box_iou

Array = jax.Array


def alignment(scores: Array, boxes: Array, centres: Array, gt_boxes: Array, gt_classes: Array,
              gt_valid: Array, *, alpha: float, beta: float) -> tuple[Array, Array, Array]:
    """The cost layer: ``metric`` [B, M, A] (``score**alpha * iou**beta`` where the place's
    centre is inside a valid box, else 0), ``iou`` [B, M, A] and ``inside`` [B, M, A].

    scores [B, A, C] probabilities, boxes [B, A, 4], centres [A, 2], gt_boxes [B, M, 4],
    gt_classes [B, M] int, gt_valid [B, M] bool.
    """
    x, y = centres[:, 0], centres[:, 1]
    g = gt_boxes[..., None, :]  # [B, M, 1, 4]
    inside = ((x > g[..., 0]) & (x < g[..., 2]) & (y > g[..., 1]) & (y < g[..., 3])
              & gt_valid[..., None])
    iou = jnp.clip(box_iou(gt_boxes, boxes), 0.0, 1.0)  # [B, M, A]
    cls = jnp.take_along_axis(jnp.swapaxes(scores, 1, 2),  # [B, C, A]
                              jnp.clip(gt_classes, 0)[..., None], axis=1)  # [B, M, A]
    metric = jnp.where(inside, cls ** alpha * iou ** beta, 0.0)
    return metric, jnp.where(inside, iou, 0.0), inside


def assign(metric: Array, iou: Array, inside: Array, gt_classes: Array, num_classes: int,
           topk: int) -> tuple[Array, Array]:
    """The assignment layer: ``target_scores`` [B, A, C] (soft, in [0, 1]) and ``target_box``
    [B, A] (index of the assigned ground-truth box; meaningful where a target score is > 0)."""
    k = min(topk, metric.shape[-1])
    _, idx = jax.lax.top_k(metric, k)  # [B, M, k]
    chosen = jax.nn.one_hot(idx, metric.shape[-1], dtype=bool).any(-2)  # [B, M, A]
    pos = chosen & inside & (metric > 0)
    # A place claimed by several boxes goes to the box it overlaps most.
    best = jnp.argmax(jnp.where(pos, iou, -1.0), axis=1)  # [B, A]
    pos = pos & (jnp.arange(metric.shape[1])[None, :, None] == best[:, None, :])
    # Per box: alignment scaled so the box's best place gets the box's best IoU.
    m = jnp.where(pos, metric, 0.0)
    norm = m * (jnp.max(jnp.where(pos, iou, 0.0), -1, keepdims=True)
                / (jnp.max(m, -1, keepdims=True) + 1e-9))
    strength = jnp.max(norm, axis=1)  # [B, A]
    cls = jnp.take_along_axis(jnp.clip(gt_classes, 0), best, axis=1)  # [B, A]
    target = jax.nn.one_hot(cls, num_classes) * (strength * pos.any(1))[..., None]
    return target, best


def dense_loss(logits: Array, boxes: Array, centres: Array, gt_boxes: Array, gt_classes: Array,
               gt_valid: Array, *, topk: int = 10, alpha: float = 0.5, beta: float = 6.0,
               cls_weight: float = 0.5, box_weight: float = 7.5) -> tuple[Array, dict]:
    """The loss layer: ``(loss, metrics)`` for logits [B, A, C] and boxes [B, A, 4].

    The classification term is the summed cross-entropy of every logit against its soft
    target, the box term ``1 - GIoU`` of each positive place weighted by its target score; both
    are divided by the sum of the target scores (at least 1), and weighted as YOLOv8 weighs its
    terms (0.5 and 7.5).
    """
    num_classes = logits.shape[-1]
    metric, iou, inside = alignment(
        jax.nn.sigmoid(jax.lax.stop_gradient(logits)), jax.lax.stop_gradient(boxes), centres,
        gt_boxes, gt_classes, gt_valid, alpha=alpha, beta=beta)
    target, best = assign(metric, iou, inside, gt_classes, num_classes, topk)
    target = jax.lax.stop_gradient(target)
    weight = target.sum(-1)  # [B, A]
    norm = jnp.maximum(weight.sum(), 1.0)
    cls_loss = optax.sigmoid_binary_cross_entropy(logits, target).sum() / norm
    tgt_box = jnp.take_along_axis(gt_boxes, best[..., None], axis=1)  # [B, A, 4]
    giou = generalized_box_iou(boxes[..., None, :], tgt_box[..., None, :])[..., 0, 0]
    box_loss = ((1.0 - giou) * weight).sum() / norm
    pos = weight > 0
    metrics = {
        "loss/cls": cls_loss, "loss/box": box_loss,
        "assign/positives_per_box": pos.sum() / jnp.maximum(gt_valid.sum(), 1),
        "assign/giou": jnp.where(pos, giou, 0.0).sum() / jnp.maximum(pos.sum(), 1),
    }
    return cls_weight * cls_loss + box_weight * box_loss, metrics
