"""Boxes and NMS against brute-force Python loops."""

import jax
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from threept_jax.geometry import boxes as bx


def _random_boxes(rng, n, size=100.0):
    xy = rng.uniform(0, size, (n, 2))
    wh = rng.uniform(1, size / 3, (n, 2))
    return np.concatenate([xy, xy + wh], -1).astype(np.float32)


def _iou_loop(a, b):
    out = np.zeros((len(a), len(b)))
    for i, p in enumerate(a):
        for j, q in enumerate(b):
            iw = max(0.0, min(p[2], q[2]) - max(p[0], q[0]))
            ih = max(0.0, min(p[3], q[3]) - max(p[1], q[1]))
            inter = iw * ih
            union = (p[2] - p[0]) * (p[3] - p[1]) + (q[2] - q[0]) * (q[3] - q[1]) - inter
            out[i, j] = inter / union
    return out


def _giou_loop(a, b):
    iou = _iou_loop(a, b)
    out = np.zeros_like(iou)
    for i, p in enumerate(a):
        for j, q in enumerate(b):
            hull = (max(p[2], q[2]) - min(p[0], q[0])) * (max(p[3], q[3]) - min(p[1], q[1]))
            iw = max(0.0, min(p[2], q[2]) - max(p[0], q[0]))
            ih = max(0.0, min(p[3], q[3]) - max(p[1], q[1]))
            union = (p[2] - p[0]) * (p[3] - p[1]) + (q[2] - q[0]) * (q[3] - q[1]) - iw * ih
            out[i, j] = iou[i, j] - (hull - union) / hull
    return out


def _nms_loop(boxes, scores, thr, max_out):
    order = sorted(range(len(scores)), key=lambda i: (-scores[i], i))
    keep = []
    for i in order:
        if len(keep) == max_out:
            break
        if all(_iou_loop(boxes[i : i + 1], boxes[k : k + 1])[0, 0] <= thr for k in keep):
            keep.append(i)
    return keep


def test_conversions_roundtrip():
    b = _random_boxes(np.random.default_rng(0), 20)
    c = np.asarray(bx.xyxy_to_cxcywh(b))
    np.testing.assert_allclose(c[:, :2], (b[:, :2] + b[:, 2:]) / 2, atol=1e-5)
    np.testing.assert_allclose(c[:, 2:], b[:, 2:] - b[:, :2], atol=1e-5)
    np.testing.assert_allclose(bx.cxcywh_to_xyxy(c), b, atol=1e-4)


@pytest.mark.parametrize("seed", range(3))
def test_iou_and_giou_match_loops(seed):
    rng = np.random.default_rng(seed)
    a, b = _random_boxes(rng, 13), _random_boxes(rng, 7)
    np.testing.assert_allclose(bx.box_iou(a, b), _iou_loop(a, b), atol=1e-6)
    np.testing.assert_allclose(bx.generalized_box_iou(a, b), _giou_loop(a, b), atol=1e-6)
    # Batched leading axis.
    got = bx.box_iou(np.stack([a, a]), np.stack([b, b]))
    assert got.shape == (2, 13, 7)


def test_giou_hand_case():
    # Disjoint unit squares 1 apart: IoU 0, hull 3x1 = 3, union 2 -> GIoU = -1/3.
    a = np.array([[0, 0, 1, 1]], np.float32)
    b = np.array([[2, 0, 3, 1]], np.float32)
    np.testing.assert_allclose(bx.generalized_box_iou(a, b), [[-1 / 3]], atol=1e-6)


_nms = jax.jit(bx.nms, static_argnames=("max_outputs",))


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 60), thr=st.sampled_from([0.3, 0.5, 0.7]))
def test_nms_matches_bruteforce(seed, n, thr):
    rng = np.random.default_rng(seed)
    boxes = _random_boxes(rng, n, size=60.0)
    # Quantised scores create ties, which must break towards the lower index.
    scores = np.round(rng.uniform(0, 1, n), 1).astype(np.float32)
    idx, valid = _nms(boxes, scores, thr, max_outputs=16)
    got = [int(i) for i, v in zip(idx, valid) if v]
    assert got == _nms_loop(boxes, scores, thr, 16)
    assert not np.any(np.asarray(valid)[len(got):])


def test_nms_score_threshold_and_vmap():
    boxes = np.array([[0, 0, 10, 10], [1, 1, 11, 11], [50, 50, 60, 60]], np.float32)
    scores = np.array([0.9, 0.8, 0.05], np.float32)
    idx, valid = bx.nms(boxes, scores, 0.5, 3, score_threshold=0.1)
    assert list(np.asarray(idx)[np.asarray(valid)]) == [0]
    idx, valid = jax.vmap(lambda b, s: bx.nms(b, s, 0.5, 3))(np.stack([boxes, boxes]), np.stack([scores, scores[::-1]]))
    assert list(np.asarray(idx[0])[np.asarray(valid[0])]) == [0, 2]
    assert list(np.asarray(idx[1])[np.asarray(valid[1])]) == [2, 1]
