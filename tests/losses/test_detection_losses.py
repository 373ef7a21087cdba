"""Detection loss assembly, soft-scaled matching, targets and symmetry-aware positives."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from threept_jax.losses.detection import (
    DetectorLossConfig,
    centre_assignment,
    detection_loss,
    make_targets,
    orientation_loss,
    soft_negative_weights,
)


def iou_xyxy(a, b):
    iw = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    ih = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = iw * ih
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / union


def focal(x, t, alpha=0.25, gamma=2.0, w_neg=1.0):
    p = 1.0 / (1.0 + math.exp(-x))
    if t:
        return alpha * (1 - p) ** gamma * -math.log(p)
    return w_neg * (1 - alpha) * p**gamma * -math.log(1 - p)


def cxcywh(xyxy):
    x0, y0, x1, y1 = xyxy
    return [(x0 + x1) / 2, (y0 + y1) / 2, x1 - x0, y1 - y0]


def test_make_targets_hand_case():
    # A 64 x 128 (H x W) tile; box (16, 32, 48, 64) px -> xyxy (.125, .5, .375, 1).
    boxes = jnp.asarray([[[16.0, 32.0, 48.0, 64.0], [0.0, 0.0, 500.0, 500.0]]])
    t = jax.jit(make_targets, static_argnums=1)(
        boxes, (64, 128), jnp.asarray([[True, False]]), template_index=jnp.asarray([[3, 0]]))
    np.testing.assert_allclose(t["boxes"], [[[0.25, 0.75, 0.25, 0.5], [0, 0, 0, 0]]])
    np.testing.assert_array_equal(t["template_index"], [[3, 0]])
    with pytest.raises(ValueError, match=r"template_index must be \[B, M\]"):
        make_targets(boxes, (64, 128), jnp.ones((1, 2), bool), template_index=jnp.zeros(2))


def test_soft_negative_weights_hand_case():
    gt = [0.2, 0.2, 0.6, 0.6]
    preds = [[0.2, 0.2, 0.6, 0.6], [0.2, 0.2, 0.6, 0.4], [0.7, 0.7, 0.9, 0.9]]
    # IoU of the near miss: intersection .4 x .2 = .08, union .16 -> 0.5. Far box: 0.
    assert iou_xyxy(preds[1], gt) == pytest.approx(0.5)
    pred = jnp.asarray([[cxcywh(b) for b in preds]])
    tgt = jnp.asarray([[cxcywh(gt), cxcywh(preds[2])]])  # the second target is padding
    mask = jnp.asarray([[True, False]])
    matched = jnp.asarray([[True, False, False]])
    f = jax.jit(soft_negative_weights, static_argnums=4)
    np.testing.assert_allclose(f(pred, tgt, mask, matched, 1.0), [[1.0, 0.5, 1.0]], atol=1e-6)
    np.testing.assert_allclose(f(pred, tgt, mask, matched, 0.5), [[1.0, 0.75, 1.0]], atol=1e-6)


def _unit_rows(rng, n, d):
    x = rng.normal(size=(n, d))
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def _hand_case():
    gt = [0.2, 0.2, 0.6, 0.64]
    preds = [[0.2, 0.2, 0.6, 0.6], [0.2, 0.2, 0.6, 0.4], [0.7, 0.7, 0.9, 0.9]]
    presence = [2.0, 0.5, -1.0]
    rng = np.random.default_rng(0)
    emb, bank = _unit_rows(rng, 3, 4), _unit_rows(rng, 3, 4)
    outputs = {
        "boxes": jnp.asarray([[cxcywh(b) for b in preds]], jnp.float32),
        "presence_logits": jnp.asarray([presence], jnp.float32),
        "embeddings": jnp.asarray(emb[None], jnp.float32),
        "template_bank": jnp.asarray(bank[None], jnp.float32),
        "logit_scale": jnp.asarray(5.0),
        "logit_bias": jnp.asarray(-1.0),
    }
    # The padded target sits exactly on hypothesis 2: were it not ignored, hypothesis 2 would
    # be matched or have its negative weight cut to 0.
    targets = {
        "boxes": jnp.asarray([[cxcywh(gt), cxcywh(preds[2])]], jnp.float32),
        "mask": jnp.asarray([[True, False]]),
        "template_index": jnp.asarray([[1, 0]], jnp.int32),
    }
    return gt, preds, presence, emb, bank, outputs, targets


def test_detection_loss_hand_case():
    gt, preds, presence, emb, bank, outputs, targets = _hand_case()
    cfg = DetectorLossConfig()
    loss, m = jax.jit(detection_loss, static_argnums=2)(outputs, targets, cfg)
    # Hypothesis 0 is matched (it is inside the ground truth and the most confident).
    u1 = iou_xyxy(preds[1], gt)  # 0.08 / 0.176
    presence_ref = (focal(presence[0], 1) + (1 - u1) * focal(presence[1], 0)
                    + focal(presence[2], 0))
    l1_ref = sum(abs(a - b) for a, b in zip(cxcywh(preds[0]), cxcywh(gt), strict=True))  # .02 + .04
    giou_ref = 0.16 / 0.176  # prediction inside the target: hull = target, GIoU = IoU
    # Orientation: every hypothesis (3 templates, under the default 8 hard negatives: all);
    # the unmatched ones have every template negative, weighted like their presence term.
    logits = 5.0 * emb @ bank.T - 1.0  # [3 hypotheses, 3 templates]
    orient_ref = sum(focal(float(x), t == 1) for t, x in enumerate(logits[0]))
    orient_ref += sum(w * focal(float(x), 0, w_neg=1.0)
                      for w, row in zip((1 - u1, 1.0), logits[1:], strict=True) for x in row)
    np.testing.assert_allclose(float(m["loss_presence"]), presence_ref, rtol=1e-5)
    np.testing.assert_allclose(float(m["loss_l1"]), l1_ref, rtol=1e-5)
    np.testing.assert_allclose(float(m["loss_giou"]), 1 - giou_ref, rtol=1e-5)
    np.testing.assert_allclose(float(m["loss_orientation"]), orient_ref, rtol=1e-5)
    np.testing.assert_allclose(float(m["matched_iou"]), giou_ref, rtol=1e-5)
    assert float(m["num_boxes"]) == 1.0
    assert float(m["orientation_top1"]) == float(np.argmax(logits[0]) == 1)
    total = 2.0 * presence_ref + 5.0 * l1_ref + 2.0 * (1 - giou_ref) + orient_ref
    np.testing.assert_allclose(float(loss), total, rtol=1e-5)


def test_detection_loss_gradients_are_finite_and_skip_padding():
    _, _, _, _, _, outputs, targets = _hand_case()
    cfg = DetectorLossConfig()

    def f(out):
        return detection_loss(out, targets, cfg)[0]

    grads = jax.jit(jax.grad(f))(outputs)
    for g in jax.tree_util.tree_leaves(grads):
        assert np.isfinite(np.asarray(g)).all()
    # Only the matched hypothesis gets a box gradient; the soft weights carry none.
    g_boxes = np.asarray(grads["boxes"])[0]
    assert np.abs(g_boxes[0]).sum() > 0 and np.abs(g_boxes[1:]).sum() == 0
    assert float(grads["logit_scale"]) != 0.0


def test_orientation_inputs_are_checked():
    _, _, _, _, _, outputs, targets = _hand_case()
    cfg = DetectorLossConfig()
    with pytest.raises(ValueError, match="template_index"):
        detection_loss(outputs, {k: v for k, v in targets.items() if k != "template_index"}, cfg)
    with pytest.raises(ValueError, match="orientation_weight=0"):
        detection_loss({k: outputs[k] for k in ("boxes", "presence_logits")}, targets, cfg)


def test_config_validation():
    with pytest.raises(ValueError, match="soft_matching"):
        DetectorLossConfig(soft_matching=2.0)


def test_one_to_many_matching_hand_case():
    # k = 2: the target is repeated twice, so the two cheapest hypotheses (0 and 1: inside the
    # ground truth, most confident) are both positives and the far one (2) stays a negative
    # with full weight (it overlaps nothing).
    gt, preds, presence, emb, bank, outputs, targets = _hand_case()
    cfg = DetectorLossConfig(matches_per_target=2)
    loss, m = jax.jit(detection_loss, static_argnums=2)(outputs, targets, cfg)
    presence_ref = (focal(presence[0], 1) + focal(presence[1], 1) + focal(presence[2], 0)) / 2
    l1_ref = sum(sum(abs(a - b) for a, b in zip(cxcywh(p), cxcywh(gt), strict=True))
                 for p in preds[:2]) / 2
    ious = [iou_xyxy(p, gt) for p in preds[:2]]  # both inside the target: GIoU = IoU
    logits = 5.0 * emb @ bank.T - 1.0  # [3 hypotheses (2 matched), 3 templates]
    orient_ref = sum(focal(float(x), t == 1 and i < 2)
                     for i, row in enumerate(logits) for t, x in enumerate(row)) / 2
    assert float(m["num_boxes"]) == 2.0
    np.testing.assert_allclose(float(m["loss_presence"]), presence_ref, rtol=1e-5)
    np.testing.assert_allclose(float(m["loss_l1"]), l1_ref, rtol=1e-5)
    np.testing.assert_allclose(float(m["loss_giou"]), 1 - sum(ious) / 2, rtol=1e-5)
    np.testing.assert_allclose(float(m["loss_orientation"]), orient_ref, rtol=1e-5)
    with pytest.raises(ValueError, match="matches_per_target"):
        DetectorLossConfig(matches_per_target=0)


def _centre_assignment_loop(boxes, mask, g, radius):
    """Brute force over patches and targets, float64, written from the rule's wording."""
    b, m = mask.shape
    out = np.zeros((b, m, g * g), bool)
    for bi in range(b):
        for p in range(g * g):
            px, py = (p % g + 0.5) / g, (p // g + 0.5) / g
            best, best_area = None, math.inf
            for mi in range(m):
                if not mask[bi, mi]:
                    continue
                cx, cy, w, h = (float(v) for v in boxes[bi, mi])
                cx = min(max(cx, 0.5 / g), 1 - 0.5 / g)
                cy = min(max(cy, 0.5 / g), 1 - 0.5 / g)
                near = (abs(px - cx) <= max(radius * w / 2, 0.5 / g + 1e-6)
                        and abs(py - cy) <= max(radius * h / 2, 0.5 / g + 1e-6))
                if near and w * h < best_area:
                    best, best_area = mi, w * h
            if best is not None:
                out[bi, best, p] = True
    return out


@pytest.mark.parametrize("radius", [0.25, 0.5, 1.0])
def test_centre_assignment_matches_a_loop(radius):
    rng = np.random.default_rng(4)
    boxes = np.concatenate([rng.uniform(-0.3, 1.3, (6, 5, 2)), rng.uniform(0.02, 0.9, (6, 5, 2))],
                           -1).astype(np.float32)
    mask = rng.random((6, 5)) < 0.8
    got = np.asarray(centre_assignment(jnp.asarray(boxes), jnp.asarray(mask), 64, radius=radius))
    np.testing.assert_array_equal(got, _centre_assignment_loop(boxes, mask, 8, radius))
    # Every valid target owns at least one patch unless a smaller box took all of its own.
    assert got.any(-1)[mask].mean() > 0.8 and not got[~mask].any()
    with pytest.raises(ValueError, match="square patch grid"):
        centre_assignment(jnp.asarray(boxes), jnp.asarray(mask), 60, radius=radius)


def test_centre_assignment_hand_case_loss():
    # A 2 x 2 grid, one target over the left half: patches 0 and 2 (left column) are its
    # positives whatever the predictions, and every positive regresses the target's box.
    gt = jnp.asarray([[[0.25, 0.5, 0.5, 1.0]]])
    preds = np.array([[0.3, 0.4, 0.4, 0.8], [0.75, 0.25, 0.5, 0.5], [0.2, 0.6, 0.5, 0.9],
                      [0.75, 0.75, 0.5, 0.5]], np.float32)
    presence = np.array([0.5, 2.0, -1.0, -3.0], np.float32)
    outputs = {"boxes": jnp.asarray(preds)[None], "presence_logits": jnp.asarray(presence)[None]}
    targets = {"boxes": gt, "mask": jnp.asarray([[True]])}
    cfg = DetectorLossConfig(assignment="centre", orientation_weight=0.0, soft_matching=0.0)
    _, m = detection_loss(outputs, targets, cfg)
    presence_ref = sum(focal(float(x), i in (0, 2)) for i, x in enumerate(presence)) / 2
    l1_ref = sum(np.abs(preds[i] - np.asarray(gt[0, 0])).sum() for i in (0, 2)) / 2
    assert float(m["num_boxes"]) == 2.0
    np.testing.assert_allclose(float(m["loss_presence"]), presence_ref, rtol=1e-5)
    np.testing.assert_allclose(float(m["loss_l1"]), l1_ref, rtol=1e-5)
    with pytest.raises(ValueError, match="leave it at 1"):
        DetectorLossConfig(assignment="centre", matches_per_target=4)
    with pytest.raises(ValueError, match="assignment must be one of"):
        DetectorLossConfig(assignment="nearest")


# -- orientation of every hypothesis, hard negatives (float64 NumPy reference) --------------


def focal64(x, t, alpha=0.25, gamma=2.0):
    """Element-wise focal loss in float64 NumPy (positive where t)."""
    x = np.asarray(x, np.float64)
    p = 1.0 / (1.0 + np.exp(-x))
    return np.where(t, alpha * (1 - p) ** gamma * np.log1p(np.exp(-x)),
                    (1 - alpha) * p**gamma * np.log1p(np.exp(x)))


def orientation_ref(logits, positive, weight, k):
    """Per-hypothesis orientation loss by brute force: the positive plus the k negatives of
    highest logit (all when k = 0), each negative times the hypothesis' soft weight."""
    out = []
    for row, pos, w in zip(logits, positive, weight, strict=True):
        negatives = [t for t in range(len(row)) if t != pos]
        negatives.sort(key=lambda t: -row[t])
        keep = negatives if k == 0 else negatives[:k]
        total = sum(w * focal64(row[t], False) for t in keep)
        out.append(total + (focal64(row[pos], True) if pos >= 0 else 0.0))
    return np.asarray(out)


def _four_hypotheses():
    """One target (template 3 of 6) and four hypotheses: 0 matched (inside the target, most
    confident), 1 a near miss, 2 far away, 3 a partial overlap; one padded target."""
    gt = [0.2, 0.2, 0.6, 0.6]
    preds = [[0.22, 0.2, 0.6, 0.58], [0.2, 0.2, 0.6, 0.4], [0.7, 0.7, 0.9, 0.9],
             [0.4, 0.4, 0.8, 0.8]]
    rng = np.random.default_rng(3)
    emb, bank = _unit_rows(rng, 4, 5), _unit_rows(rng, 6, 5)
    outputs = {
        "boxes": jnp.asarray([[cxcywh(b) for b in preds]], jnp.float32),
        "presence_logits": jnp.asarray([[3.0, 0.0, -1.0, -0.5]], jnp.float32),
        "embeddings": jnp.asarray(emb[None], jnp.float32),
        "template_bank": jnp.asarray(bank[None], jnp.float32),
        "logit_scale": jnp.asarray(4.0),
        "logit_bias": jnp.asarray(-2.0),
    }
    targets = {"boxes": jnp.asarray([[cxcywh(gt), cxcywh(preds[2])]], jnp.float32),
               "mask": jnp.asarray([[True, False]]),
               "template_index": jnp.asarray([[3, 0]], jnp.int32)}
    return gt, preds, emb, bank, outputs, targets


@pytest.mark.parametrize("k", [0, 2])
def test_orientation_trains_every_hypothesis_float64(k):
    gt, preds, emb, bank, outputs, targets = _four_hypotheses()
    lam = 0.5
    # u_p by hand: near miss .4 x .2 / .16 = 0.5; far box 0; partial .2 x .2 / (.32 - .04).
    u = [iou_xyxy(b, gt) for b in preds]
    np.testing.assert_allclose(u[1:], [0.5, 0.0, 0.04 / 0.28], rtol=1e-12)
    weight = [1.0, 1 - lam * u[1], 1.0, 1 - lam * u[3]]
    logits = 4.0 * emb.astype(np.float64) @ bank.T - 2.0  # [4, 6]
    per_hyp = orientation_ref(logits, [3, -1, -1, -1], weight, k)
    cfg = DetectorLossConfig(soft_matching=lam, orientation_negatives=k, matches_per_target=1)
    _, m = jax.jit(detection_loss, static_argnums=2)(outputs, targets, cfg)
    assert float(m["num_boxes"]) == 1.0
    np.testing.assert_allclose(float(m["loss_orientation"]), per_hyp.sum(), rtol=1e-5)
    np.testing.assert_allclose(float(m["loss_orientation_unmatched"]), per_hyp[1:].sum(),
                               rtol=1e-5)


def test_hard_negative_selection_brute_force():
    # Gradients wrt the logits are non-zero exactly at the positive and at the k negatives
    # of highest logit (found here by sorting), scaled by the soft weight on negatives.
    rng = np.random.default_rng(7)
    logits = rng.normal(size=(2, 3, 9)) * 3.0
    positive = np.asarray([[4, -1, 0], [-1, 8, -1]])
    weight = rng.uniform(0.2, 1.0, size=(2, 3))
    k = 3

    def f(x):
        return orientation_loss(x, jnp.asarray(positive), jnp.asarray(weight, jnp.float32),
                                num_negatives=k, alpha=0.25, gamma=2.0)[0]

    per_hyp = jax.jit(f)(jnp.asarray(logits, jnp.float32))
    ref = orientation_ref(logits.reshape(6, 9), positive.ravel(), weight.ravel(), k)
    np.testing.assert_allclose(np.asarray(per_hyp).ravel(), ref, rtol=1e-5)
    grad = np.asarray(jax.grad(lambda x: jnp.sum(f(x)))(jnp.asarray(logits, jnp.float32)))
    for b in range(2):
        for p in range(3):
            row, pos = logits[b, p], positive[b, p]
            negatives = sorted((t for t in range(9) if t != pos), key=lambda t: -row[t])
            expected = set(negatives[:k]) | ({pos} if pos >= 0 else set())
            assert set(np.flatnonzero(grad[b, p])) == expected, (b, p)


def test_gradients_reach_template_logits_of_unmatched_hypotheses():
    _, _, _, _, outputs, targets = _four_hypotheses()
    cfg = DetectorLossConfig(presence_weight=0.0, l1_weight=0.0, giou_weight=0.0)
    grads = jax.jit(jax.grad(lambda o: detection_loss(o, targets, cfg)[0]))(outputs)
    g = np.abs(np.asarray(grads["embeddings"]))[0].sum(-1)  # [4 hypotheses]
    assert (g > 0).all(), g  # the matched one and the three unmatched ones
    with pytest.raises(ValueError, match="orientation_negatives"):
        DetectorLossConfig(orientation_negatives=-1)
