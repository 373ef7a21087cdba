"""The dense cell detector: network shapes, the task-aligned loss against a float64 loop, the
decoding against OpenCV's NMS, the mosaic's boxes against the pixels they were drawn from."""

from __future__ import annotations

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from threept_jax.data import dense_input
from threept_jax.losses.dense import alignment, assign, dense_loss
from threept_jax.models.dense import STRIDES, DenseConfig, DenseDetector, anchor_points, decode


def _iou(a, b):
    lt = np.maximum(a[:2], b[:2])
    rb = np.minimum(a[2:], b[2:])
    inter = np.prod(np.clip(rb - lt, 0, None))
    union = np.prod(a[2:] - a[:2]) + np.prod(b[2:] - b[:2]) - inter
    return inter / union


def _assign_loop(scores, boxes, centres, gt_boxes, gt_classes, gt_valid, topk, alpha, beta):
    """TOOD's assignment written as loops in float64 (YOLOv8's TaskAlignedAssigner)."""
    B, A, C = scores.shape
    M = gt_boxes.shape[1]
    target = np.zeros((B, A, C))
    for b in range(B):
        metric = np.zeros((M, A))
        iou = np.zeros((M, A))
        for m in range(M):
            if not gt_valid[b, m]:
                continue
            g = gt_boxes[b, m]
            for a in range(A):
                x, y = centres[a]
                if g[0] < x < g[2] and g[1] < y < g[3]:
                    iou[m, a] = max(0.0, _iou(g, boxes[b, a]))
                    metric[m, a] = scores[b, a, gt_classes[b, m]] ** alpha * iou[m, a] ** beta
        pos = np.zeros((M, A), bool)
        for m in range(M):
            order = np.argsort(-metric[m], kind="stable")[:topk]
            pos[m, order] = metric[m, order] > 0
        for a in range(A):
            claims = np.flatnonzero(pos[:, a])
            if len(claims) > 1:
                keep = claims[np.argmax(iou[claims, a])]
                pos[:, a] = False
                pos[keep, a] = True
        for m in range(M):
            if not pos[m].any():
                continue
            mm = np.where(pos[m], metric[m], 0)
            norm = mm * iou[m][pos[m]].max() / mm.max()
            for a in np.flatnonzero(pos[m]):
                target[b, a, gt_classes[b, m]] = norm[a]
    return target


def test_task_aligned_assignment_matches_a_float64_loop():
    rng = np.random.default_rng(0)
    image_size = (64, 96)
    centres, _ = anchor_points(image_size)
    B, A, C, M = 2, len(centres), 3, 5
    xy = rng.uniform(0, 70, (B, M, 2))
    gt = np.concatenate([xy, xy + rng.uniform(8, 30, (B, M, 2))], -1)
    gt_classes = rng.integers(0, C, (B, M))
    gt_valid = np.array([[1, 1, 1, 0, 1], [1, 0, 1, 1, 1]], bool)
    c = centres[None]
    boxes = np.concatenate([c - rng.uniform(2, 15, (B, A, 2)), c + rng.uniform(2, 15, (B, A, 2))],
                           -1)
    scores = rng.uniform(0.01, 1, (B, A, C))
    metric, iou, inside = alignment(jnp.asarray(scores, jnp.float32),
                                    jnp.asarray(boxes, jnp.float32), jnp.asarray(centres),
                                    jnp.asarray(gt, jnp.float32), jnp.asarray(gt_classes),
                                    jnp.asarray(gt_valid), alpha=0.5, beta=6.0)
    target, _ = assign(metric, iou, inside, jnp.asarray(gt_classes), C, topk=4)
    expected = _assign_loop(scores, boxes, centres, gt, gt_classes, gt_valid, 4, 0.5, 6.0)
    assert (expected > 0).sum() >= 10  # the case exercises real assignments
    np.testing.assert_array_equal(np.asarray(target) > 0, expected > 0)
    np.testing.assert_allclose(np.asarray(target), expected, rtol=2e-4, atol=1e-6)


def test_loss_is_lowest_for_the_true_boxes_and_classes():
    image_size = (64, 64)
    centres, strides = anchor_points(image_size)
    gt = jnp.asarray([[[8.0, 8.0, 40.0, 36.0], [0, 0, 1, 1]]])
    gt_classes = jnp.asarray([[1, 0]])
    gt_valid = jnp.asarray([[True, False]])
    inside = ((centres[:, 0] > 8) & (centres[:, 0] < 40) & (centres[:, 1] > 8)
              & (centres[:, 1] < 36))
    good_logits = np.full((1, len(centres), 2), -6.0, np.float32)
    good_logits[0, inside, 1] = 3.0
    boxes = np.broadcast_to(np.asarray(gt[0, 0]), (1, len(centres), 4)).copy()
    loss_good, m = dense_loss(jnp.asarray(good_logits), jnp.asarray(boxes), jnp.asarray(centres),
                              gt, gt_classes, gt_valid)
    wrong_class = good_logits[..., ::-1].copy()
    loss_cls, _ = dense_loss(jnp.asarray(wrong_class), jnp.asarray(boxes), jnp.asarray(centres),
                             gt, gt_classes, gt_valid)
    shifted = boxes + 6.0
    loss_box, _ = dense_loss(jnp.asarray(good_logits), jnp.asarray(shifted),
                             jnp.asarray(centres), gt, gt_classes, gt_valid)
    assert float(m["assign/giou"]) == pytest.approx(1.0)
    assert float(loss_good) < float(loss_cls)
    assert float(loss_good) < float(loss_box)
    assert np.isfinite(float(loss_good))


def test_network_shapes_and_initial_boxes():
    cfg = DenseConfig(num_classes=3, width=8, depths=(1, 1, 1, 1), neck_width=16,
                      image_size=(64, 96))
    model = DenseDetector(cfg, rngs=nnx.Rngs(0))
    model.eval()
    out = model(jnp.zeros((2, 64, 96, 3)))
    A = sum((64 // s) * (96 // s) for s in STRIDES)
    assert out["logits"].shape == (2, A, 3) and out["boxes"].shape == (2, A, 4)
    np.testing.assert_allclose(jax.nn.sigmoid(out["logits"]).mean(), cfg.class_prior, rtol=0.2)
    # The zero box kernel: each place starts with a box 2 strides to each side of its centre.
    centres, strides = anchor_points(cfg.image_size)
    expected = np.concatenate([centres - 2 * strides[:, None], centres + 2 * strides[:, None]], -1)
    np.testing.assert_allclose(out["boxes"][0], expected, rtol=1e-5)
    with pytest.raises(ValueError, match="letterbox"):
        model(jnp.zeros((1, 32, 32, 3)))
    with pytest.raises(ValueError, match="multiples of 32"):
        DenseConfig(num_classes=1, image_size=(100, 96))


def test_decode_matches_opencv_nms_per_class():
    rng = np.random.default_rng(1)
    A, C = 300, 3
    xy = rng.uniform(0, 200, (A, 2))
    boxes = np.concatenate([xy, xy + rng.uniform(10, 60, (A, 2))], -1).astype(np.float32)
    logits = rng.normal(-2, 2, (A, C)).astype(np.float32)
    out = jax.device_get(decode(jnp.asarray(logits), jnp.asarray(boxes), max_candidates=A * C,
                                max_detections=A * C, nms_iou=0.5))
    got = {(int(c), *map(float, b)) for c, b, v in
           zip(out["classes"], out["boxes"], out["valid"]) if v}
    probs = 1 / (1 + np.exp(-logits.astype(np.float64)))
    expected = set()
    for c in range(C):
        xywh = [[float(b[0]), float(b[1]), float(b[2] - b[0]), float(b[3] - b[1])] for b in boxes]
        keep = np.asarray(cv2.dnn.NMSBoxes(xywh, probs[:, c].tolist(), 0.0, 0.5)).ravel()
        expected |= {(c, *map(float, boxes[i])) for i in keep}
    assert got == expected
    assert list(out["scores"][out["valid"]]) == sorted(out["scores"][out["valid"]], reverse=True)


def test_mosaic_boxes_follow_the_pixels():
    """Each part is a solid rectangle of a colour of its own on grey: after the mosaic, scales
    and flips, every kept box must be the extent of one part's pixels, of the box's class."""
    rng = np.random.default_rng(2)
    examples, colours, classes = [], [], []
    for i in range(6):
        rgb = np.full((120, 160, 3), 128, np.uint8)
        boxes, ids = [], []
        for k in range(3):
            colour = np.array([40 + 35 * i, 30 + 90 * k, 230 - 30 * i], np.uint8)
            x0, y0 = 10 + 48 * k, rng.integers(5, 60)
            w, h = 36, rng.integers(20, 50)
            rgb[y0:y0 + h, x0:x0 + w] = colour
            boxes.append([x0, y0, x0 + w, y0 + h])
            ids.append(k + 1)
            colours.append(colour)
            classes.append(k)
        examples.append({"rgb": rgb, "bbox_obj": np.array(boxes, np.float32),
                         "obj_id": np.array(ids), "visib_fract": np.ones(3, np.float32),
                         "scene_id": 0, "im_id": i})
    colours = np.array(colours, int)
    cell = dense_input.CellImages(examples, [1, 2, 3], (64, 96))
    aug = dense_input.DenseAugment(photometric=dense_input.PhotometricConfig(
        brightness=0, contrast=0, saturation=0, hue=0, noise_std=0, blur_prob=0))
    checked = 0
    for n in range(20):
        ex = dense_input.training_example(cell, np.random.default_rng(n), aug, max_instances=16)
        img = ex["image"].astype(int)
        nearest = np.argmin(np.abs(img[..., None, :] - colours).sum(-1), -1)
        close = np.abs(img - colours[nearest]).sum(-1) < 6
        for b, c, v in zip(ex["boxes"], ex["classes"], ex["valid"]):
            if not v:
                continue
            x0, y0, x1, y1 = np.round(b).astype(int)
            inner = (nearest[y0 + 1:y1 - 1, x0 + 1:x1 - 1][close[y0 + 1:y1 - 1, x0 + 1:x1 - 1]])
            part = np.bincount(inner).argmax()
            assert classes[part] == c, (n, b, c)
            # The part's pixels near the box (a mosaic may show an image twice) span the box
            # and no more (pixel edges: the last pixel ends at its index + 1).
            near = np.zeros_like(close)
            near[max(0, y0 - 3):y1 + 3, max(0, x0 - 3):x1 + 3] = True
            ys, xs = np.nonzero(close & (nearest == part) & near)
            np.testing.assert_allclose([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], b,
                                       atol=2.5)  # blended edge pixels
            checked += 1
    assert checked > 30


def test_a_part_cut_to_a_sliver_loses_its_box():
    image = np.full((40, 40, 3), 128, np.uint8)
    boxes = np.array([[0, 0, 30, 30], [0, 0, 30, 9]], np.float32)
    canvas = np.zeros((40, 40, 3), np.uint8)
    out_boxes, out_classes = [], []
    # Pasted at (0, 0) at scale 1, clipped to x < 9: the first box keeps 9 of 30 columns (under
    # a third of its area), the second 9 x 9 of 30 x 9 (under a third too); at x < 11 both keep
    # more than a third.
    dense_input._place(canvas, out_boxes, out_classes, image, boxes, np.array([0, 1]), 1.0, 0,
                       0, (0, 0, 9, 40))
    assert len(out_boxes[0]) == 0
    dense_input._place(canvas, out_boxes, out_classes, image, boxes, np.array([0, 1]), 1.0, 0,
                       0, (0, 0, 11, 40))
    np.testing.assert_array_equal(out_boxes[1], [[0, 0, 11, 30], [0, 0, 11, 9]])


def test_unknown_parts_are_refused():
    ex = {"rgb": np.zeros((32, 32, 3), np.uint8), "bbox_obj": np.array([[1, 1, 9, 9]], np.float32),
          "obj_id": np.array([7]), "visib_fract": np.ones(1, np.float32), "scene_id": 3,
          "im_id": 4}
    with pytest.raises(ValueError, match=r"parts \[7\].*whole part list"):
        dense_input.CellImages([ex], [1, 2], (32, 32))


def test_run_roundtrip_and_refusals(tmp_path):
    from threept_jax.data import dense_run

    cfg = DenseConfig(num_classes=2, width=8, depths=(1, 1, 1, 1), neck_width=16,
                      image_size=(64, 64))
    model = DenseDetector(cfg, rngs=nnx.Rngs(3))
    _, params, stats = nnx.split(model, nnx.Param, nnx.BatchStat)
    with pytest.raises(FileNotFoundError, match="train.cell_detector"):
        dense_run.load(tmp_path)
    dense_run.save(tmp_path, cfg, [4, 9], params, stats, {"steps": 7})
    loaded, class_ids, info = dense_run.load(tmp_path)
    assert class_ids == [4, 9] and info["steps"] == 7 and loaded.cfg == cfg
    x = jnp.asarray(np.random.default_rng(0).uniform(0, 1, (1, 64, 64, 3)), jnp.float32)
    model.eval()
    np.testing.assert_allclose(loaded(x)["logits"], model(x)["logits"], rtol=1e-6, atol=1e-6)
