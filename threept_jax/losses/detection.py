"""3PT-D training losses: presence, boxes, contrastive orientation, soft-scaled matching.

The third loss layer (docs/design.md habit 5): :func:`detection_loss` builds the cost matrix
(:func:`~threept_jax.losses.matcher.detection_cost`), matches hypotheses to targets on the
host (:func:`~threept_jax.losses.matcher.hungarian_match`) and assembles, for a batch of tiles
each queried with one object (docs/design.md section 1.1, "Training"):

* **Presence** (every hypothesis): sigmoid focal loss, positive for matched hypotheses.
  **Soft-scaled matching**: an unmatched hypothesis p with ``u_p = max_g IoU(box_p, gt_g)``
  over the valid targets g of its tile has the negative term of its focal loss multiplied by

      w_p = 1 - lambda * u_p        (lambda = ``soft_matching``, default 1; u_p under stop_gradient)

  so a near miss is penalised less, in proportion to its IoU, rather than counted as a full
  negative (w_p = 1 when it overlaps nothing, 1 - lambda at a perfect overlap).
* **Boxes** (matched pairs): L1 on normalised cxcywh and 1 - GIoU.
* **Orientation** (every hypothesis): sigmoid focal loss on the hypothesis embedding's logits
  against the tile's sampled templates, ``scale * cos + bias`` [T]. A matched hypothesis has
  one positive, the template nearest to the ground-truth rotation of its target taking the
  object's symmetries into account (:func:`threept_jax.geometry.symmetry.nearest_templates`,
  computed by the input pipeline in float64 and passed as ``template_index``); every other
  template is a negative. An unmatched hypothesis has every template negative, each negative
  term weighted by the same soft-scaled ``w_p`` as its presence term: the paper's detection
  score is the maximum template logit, which inference takes on every patch, so every patch's
  logits are trained. **Hard negatives**: with ``orientation_negatives`` = k > 0 only the k
  negatives of highest logit per hypothesis (the templates most similar to it; selection
  under stop_gradient) enter the loss beside the positive, so the loss acts on the maximum
  that inference reads rather than on many easy negatives (k = 0 or k >= T: all).

**One-to-many matching** (``matches_per_target`` = k > 1, off by default): every target is
repeated k times before the Hungarian matching, so k hypotheses per instance are positives
for all three terms (the hybrid matching of H-DETR, Jia et al. CVPR 2023, and Group-DETR).
With k = 1 only the patch nearest an object's centre is positive and its neighbours on the
same object are negatives whose boxes are never trained, so the soft-scaled weights stay
near 1 and a small model trained from scratch learns presence very slowly; k > 1 gives it
dense positives. Duplicates cost nothing at inference, which runs NMS anyway.

**Centre assignment** (``assignment="centre"``, :func:`centre_assignment`): positives by place
instead of by cost, as one-stage detectors assign them (FCOS, Tian et al. ICCV 2019, centre
sampling): the patches over the central ``centre_radius`` of each box, at least the one holding
its centre. No Hungarian matching (no host callback), and a patch stays the positive of the
same object from step to step, where the matching moves the positives with the predictions.

Each term is summed and divided by the number of positive hypotheses in the batch (DETR's
normalisation; under ``jit`` with a sharded batch the sum is global). Weights and focal
parameters come from :class:`DetectorLossConfig` (or any object with the same attribute names,
e.g. an ``ml_collections.ConfigDict``).

Shapes: B tiles, P hypotheses, M padded targets per tile, T templates, E embedding dim.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp

from threept_jax.geometry.boxes import box_iou, cxcywh_to_xyxy, generalized_box_iou, xyxy_to_cxcywh
from threept_jax.losses.focal import sigmoid_focal_loss
from threept_jax.losses.matcher import detection_cost, hungarian_match

Array = jax.Array


#: How hypotheses become positives: DETR's Hungarian matching or the patches at a box's centre.
ASSIGNMENTS = ("hungarian", "centre")


@dataclasses.dataclass(frozen=True)
class DetectorLossConfig:
    """Matching costs, loss weights and focal parameters of 3PT-D training.

    Matching costs and box weights are DETR's (class 2, L1 5, GIoU 2, as in Deformable-DETR
    and OWL-ViT); focal alpha 0.25, gamma 2 (RetinaNet). ``soft_matching`` is lambda of the
    soft-scaled matching loss (0 turns it off).
    ``matches_per_target``: hypotheses matched to each target (1: DETR's one-to-one).
    ``orientation_negatives``: hard negatives per hypothesis in the orientation term (0: all
    templates of the tile).
    """

    cost_class: float = 2.0
    cost_l1: float = 5.0
    cost_giou: float = 2.0
    presence_weight: float = 2.0
    l1_weight: float = 5.0
    giou_weight: float = 2.0
    orientation_weight: float = 1.0
    focal_alpha: float | None = 0.25
    focal_gamma: float = 2.0
    orientation_alpha: float | None = 0.25
    orientation_gamma: float = 2.0
    soft_matching: float = 1.0
    matches_per_target: int = 1
    orientation_negatives: int = 8
    assignment: str = "hungarian"
    centre_radius: float = 0.5

    def __post_init__(self):
        if not 0.0 <= self.soft_matching <= 1.0:
            raise ValueError(f"soft_matching (lambda) must be in [0, 1], got {self.soft_matching}")
        if self.matches_per_target < 1:
            raise ValueError(f"matches_per_target must be >= 1, got {self.matches_per_target}")
        if self.assignment not in ASSIGNMENTS:
            raise ValueError(f"assignment must be one of {ASSIGNMENTS}, got {self.assignment!r}")
        if self.assignment == "centre" and self.matches_per_target != 1:
            raise ValueError("matches_per_target repeats targets for the Hungarian matching; "
                             "with assignment='centre' leave it at 1")
        if not 0.0 < self.centre_radius <= 1.0:
            raise ValueError(f"centre_radius must be in (0, 1], got {self.centre_radius}")
        if self.orientation_negatives < 0:
            raise ValueError(f"orientation_negatives must be >= 0 (0: all templates), got "
                             f"{self.orientation_negatives}")


# -- targets ------------------------------------------------------------------------------


def make_targets(
    boxes_xyxy: Array,
    image_hw: tuple[int, int],
    mask: Array,
    template_index: Array | None = None,
) -> dict[str, Array]:
    """Per-tile targets the loss consumes.

    Args:
      boxes_xyxy: [B, M, 4] ground-truth boxes in tile pixels (pixel-edge xyxy), padded.
      image_hw: (H, W) of the tile the boxes refer to.
      mask: [B, M] True for real instances.
      template_index: [B, M] the positive template of each instance (nearest to the ground
        truth up to symmetry), needed by the orientation term.

    Returns a dict with ``boxes`` [B, M, 4] normalised cxcywh (amodal: not clipped to the
    tile, issue 13 item 1.4; zero where padded), ``mask`` [B, M] and, when given, ``template_index``.
    """
    boxes_xyxy = jnp.asarray(boxes_xyxy, jnp.float32)
    mask = jnp.asarray(mask, bool)
    if boxes_xyxy.ndim != 3 or boxes_xyxy.shape[-1] != 4 or mask.shape != boxes_xyxy.shape[:2]:
        raise ValueError(f"boxes_xyxy must be [B, M, 4] and mask [B, M], got "
                         f"{boxes_xyxy.shape} and {mask.shape}")
    if template_index is not None and jnp.shape(template_index) != mask.shape:
        raise ValueError(f"template_index must be [B, M] = {mask.shape}, got "
                         f"{jnp.shape(template_index)}")
    h, w = image_hw
    scale = jnp.asarray([w, h, w, h], jnp.float32)
    norm = boxes_xyxy / scale
    out = {"boxes": jnp.where(mask[..., None], xyxy_to_cxcywh(norm), 0.0), "mask": mask}
    if template_index is not None:
        out["template_index"] = jnp.asarray(template_index, jnp.int32)
    return out


def repeat_targets(targets: dict[str, Array], k: int) -> dict[str, Array]:
    """Every per-instance field [B, M, ...] of :func:`make_targets` output tiled to [B, k*M, ...]
    (one-to-many matching); copy j of instance m sits at j * M + m."""
    if k == 1:
        return targets
    return {name: jnp.concatenate([jnp.asarray(v)] * k, axis=1) for name, v in targets.items()}


# -- loss pieces --------------------------------------------------------------------------


def centre_assignment(target_boxes: Array, target_mask: Array, num_patches: int, *,
                      radius: float) -> Array:
    """[B, M, P] positives by place (FCOS-style centre sampling on the patch grid).

    Patch p (centre c_p on the square grid of ``num_patches`` row-major patches) is a positive
    of target m when ``|c_p - c_m| <= max(radius * size_m / 2, half a patch)`` on both axes:
    the patches over the central ``radius`` of the box, and at least the patch holding its
    centre. A centre outside the tile (amodal boxes) is first moved to the nearest patch centre
    inside it, so every valid target has a positive. A patch claimed by several targets goes
    to the smallest box (FCOS). target_boxes [B, M, 4] normalised cxcywh, target_mask [B, M].
    """
    g = math.isqrt(num_patches)
    if g * g != num_patches:
        raise ValueError(f"centre assignment needs a square patch grid, got {num_patches} patches")
    y, x = jnp.meshgrid(jnp.arange(g), jnp.arange(g), indexing="ij")
    centres = (jnp.stack([x.reshape(-1), y.reshape(-1)], -1) + 0.5) / g  # [P, 2]
    half = 0.5 / g
    box_centre = jnp.clip(target_boxes[..., :2], half, 1.0 - half)  # [B, M, 2]
    reach = jnp.maximum(radius * target_boxes[..., 2:] / 2, half + 1e-6)  # [B, M, 2]
    inside = jnp.all(jnp.abs(centres[None, None] - box_centre[:, :, None]) <= reach[:, :, None],
                     -1) & target_mask[..., None]  # [B, M, P]
    area = jnp.where(target_mask, target_boxes[..., 2] * target_boxes[..., 3], jnp.inf)
    owner = jnp.argmin(jnp.where(inside, area[..., None], jnp.inf), axis=1)  # [B, P]
    return inside & (owner[:, None, :] == jnp.arange(target_boxes.shape[1])[None, :, None])


def soft_negative_weights(pred_boxes: Array, target_boxes: Array, target_mask: Array,
                          matched: Array, strength: float) -> Array:
    """Weights [B, P] of the negative terms of presence and orientation (soft-scaled matching).

    ``w_p = 1 - strength * max_g IoU(pred_p, gt_g)`` over valid targets for unmatched
    hypotheses, 1 for matched ones (whose negative term is zero anyway). pred_boxes [B, P, 4]
    and target_boxes [B, M, 4] normalised cxcywh; target_mask [B, M]; matched [B, P] bool.
    No gradient flows through the weights.
    """
    iou = box_iou(cxcywh_to_xyxy(pred_boxes), cxcywh_to_xyxy(target_boxes))  # [B, P, M]
    u = jnp.max(jnp.where(target_mask[:, None, :], iou, 0.0), axis=-1, initial=0.0)
    w = jnp.where(matched, 1.0, 1.0 - strength * u)
    return jax.lax.stop_gradient(w)


def _paired_giou(a: Array, b: Array) -> Array:
    """GIoU of aligned pairs: [..., 4], [..., 4] (cxcywh) -> [...]."""
    a, b = cxcywh_to_xyxy(a)[..., None, :], cxcywh_to_xyxy(b)[..., None, :]
    return generalized_box_iou(a, b)[..., 0, 0]


def _orientation_logits(outputs: dict[str, Array]) -> Array:
    """[B, P, T] ``scale * cos + bias`` of every hypothesis against its tile's templates."""
    bank = outputs["template_bank"].astype(jnp.float32)
    emb = outputs["embeddings"].astype(jnp.float32)
    emb = emb / jnp.maximum(jnp.linalg.norm(emb, axis=-1, keepdims=True), 1e-6)
    eq = "bpe,te->bpt" if bank.ndim == 2 else "bpe,bte->bpt"
    return outputs["logit_scale"] * jnp.einsum(eq, emb, bank) + outputs["logit_bias"]


def orientation_loss(logits: Array, positive_index: Array, negative_weight: Array, *,
                     num_negatives: int, alpha: float | None,
                     gamma: float) -> tuple[Array, Array]:
    """Per-hypothesis orientation focal loss [B, P] and the positive mask [B, P, T].

    logits [B, P, T]; positive_index [B, P] is the positive template of a matched hypothesis,
    -1 for an unmatched one (all its templates negative); negative_weight [B, P] scales every
    negative term of a hypothesis (soft-scaled matching). With 0 < num_negatives < T only the
    ``num_negatives`` negatives of highest logit per hypothesis count (hard negatives, chosen
    under stop_gradient); the positive always counts.
    """
    num_t = logits.shape[-1]
    positives = positive_index[..., None] == jnp.arange(num_t)  # [B, P, T]
    fl = sigmoid_focal_loss(logits, positives, alpha=alpha, gamma=gamma,
                            negative_weight=negative_weight[..., None])
    if not 0 < num_negatives < num_t:
        return jnp.sum(fl, -1), positives
    ranked = jnp.where(positives, -jnp.inf, jax.lax.stop_gradient(logits))
    _, hard = jax.lax.top_k(ranked, num_negatives)  # [B, P, k]
    hard_loss = jnp.take_along_axis(fl, hard, -1)
    hard_is_negative = ~jnp.take_along_axis(positives, hard, -1)
    per_hyp = (jnp.sum(jnp.where(positives, fl, 0.0), -1)
               + jnp.sum(jnp.where(hard_is_negative, hard_loss, 0.0), -1))
    return per_hyp, positives


def _check_orientation_inputs(outputs, targets, config) -> None:
    """Fail before any compute when the orientation term lacks an input."""
    if not config.orientation_weight:
        return
    for key in ("template_bank", "logit_scale", "logit_bias", "embeddings"):
        if key not in outputs:
            raise ValueError(
                f"orientation loss needs outputs[{key!r}]: call the detector with a "
                "template_bank, or set orientation_weight=0")
    if "template_index" not in targets:
        raise ValueError("orientation loss needs targets['template_index'] (see make_targets), "
                         "or orientation_weight=0")


def detection_loss(outputs: dict[str, Array], targets: dict[str, Array],
                   config: Any) -> tuple[Array, dict[str, Array]]:
    """Total 3PT-D loss and metrics for one batch (formulas in the module docstring).

    Args:
      outputs: ``Detector.__call__`` outputs: ``boxes`` [B, P, 4], ``presence_logits``
        [B, P], ``embeddings`` [B, P, E] and, for the orientation term, ``template_bank``
        [B, T, E] or [T, E], ``logit_scale`` and ``logit_bias``.
      targets: :func:`make_targets` output; the orientation term needs ``template_index``.
      config: :class:`DetectorLossConfig` or an object with the same fields.

    Returns ``(loss, metrics)``; ``metrics`` holds each weighted-free term, the number of
    matched targets, the mean IoU of matched pairs and the orientation top-1 accuracy.
    """
    _check_orientation_inputs(outputs, targets, config)
    if config.assignment == "hungarian":
        targets = repeat_targets(targets, int(config.matches_per_target))
    pred_boxes = outputs["boxes"].astype(jnp.float32)
    presence = outputs["presence_logits"].astype(jnp.float32)
    tgt_boxes = targets["boxes"].astype(jnp.float32)
    tgt_mask = jnp.asarray(targets["mask"], bool)
    b, p = presence.shape
    if tgt_boxes.shape[0] != b or tgt_mask.shape != tgt_boxes.shape[:2]:
        raise ValueError(f"targets for {tgt_boxes.shape[0]} tiles, outputs for {b}")

    if config.assignment == "centre":
        onehot = centre_assignment(tgt_boxes, tgt_mask, p, radius=config.centre_radius)
    else:
        cost = detection_cost(
            jax.lax.stop_gradient(pred_boxes), jax.lax.stop_gradient(presence), tgt_boxes,
            class_weight=config.cost_class, l1_weight=config.cost_l1,
            giou_weight=config.cost_giou, focal_alpha=config.focal_alpha,
            focal_gamma=config.focal_gamma)
        matched_pred = hungarian_match(cost, tgt_mask)  # [B, M], -1: unmatched
        onehot = (matched_pred[..., None] == jnp.arange(p)) & tgt_mask[..., None]
    # Every positive hypothesis has exactly one target: its box, per hypothesis.
    is_matched = jnp.any(onehot, axis=1)  # [B, P]
    num_boxes = jnp.maximum(jnp.sum(is_matched), 1).astype(jnp.float32)
    hyp_target = jnp.einsum("bmp,bmc->bpc", onehot.astype(jnp.float32), tgt_boxes)  # [B, P, 4]

    # Presence, with soft-scaled negatives.
    w_neg = soft_negative_weights(pred_boxes, tgt_boxes, tgt_mask, is_matched, config.soft_matching)
    loss_presence = jnp.sum(sigmoid_focal_loss(
        presence, is_matched, alpha=config.focal_alpha, gamma=config.focal_gamma,
        negative_weight=w_neg)) / num_boxes

    # Boxes of the positive hypotheses.
    l1 = jnp.sum(jnp.abs(pred_boxes - hyp_target), -1)
    giou = _paired_giou(pred_boxes, hyp_target)
    loss_l1 = jnp.sum(jnp.where(is_matched, l1, 0.0)) / num_boxes
    loss_giou = jnp.sum(jnp.where(is_matched, 1.0 - giou, 0.0)) / num_boxes
    iou = box_iou(cxcywh_to_xyxy(pred_boxes)[..., None, :],
                  cxcywh_to_xyxy(hyp_target)[..., None, :])[..., 0, 0]
    metrics = {
        "loss_presence": loss_presence,
        "loss_l1": loss_l1,
        "loss_giou": loss_giou,
        "num_boxes": jnp.sum(is_matched).astype(jnp.float32),
        "matched_iou": jnp.sum(jnp.where(is_matched, iou, 0.0)) / num_boxes,
    }
    loss = (config.presence_weight * loss_presence + config.l1_weight * loss_l1
            + config.giou_weight * loss_giou)

    if config.orientation_weight:
        # The target matched to each hypothesis gives its positive template; -1: unmatched.
        tgt_template = jnp.asarray(targets["template_index"], jnp.int32)
        pos_index = jnp.where(is_matched,
                              jnp.sum(jnp.where(onehot, tgt_template[..., None], 0), axis=1), -1)
        logits = _orientation_logits(outputs)  # [B, P, T]
        per_hyp, positives = orientation_loss(
            logits, pos_index, w_neg, num_negatives=config.orientation_negatives,
            alpha=config.orientation_alpha, gamma=config.orientation_gamma)
        loss_orient = jnp.sum(per_hyp) / num_boxes
        top1 = jnp.take_along_axis(positives, jnp.argmax(logits, -1)[..., None], -1)[..., 0]
        metrics["loss_orientation"] = loss_orient
        metrics["loss_orientation_unmatched"] = (
            jnp.sum(jnp.where(is_matched, 0.0, per_hyp)) / num_boxes)
        metrics["orientation_top1"] = jnp.sum(is_matched & top1) / num_boxes
        loss = loss + config.orientation_weight * loss_orient

    metrics["loss"] = loss
    return loss, metrics
