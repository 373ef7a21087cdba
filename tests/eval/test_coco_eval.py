"""2D detection / segmentation AP with the BOP ignore rule: hand-derived values and the
stock pycocotools evaluator as the reference for what the ignore rule changes."""

import contextlib
import io

import cv2
import numpy as np
import pytest
from pycocotools.coco import COCO
from pycocotools.cocoeval import COCOeval

from threept_jax.data.bop import Detection2D, mask_to_rle
from threept_jax.eval.coco import coco_gt_annotation, evaluate_coco

H, W = 60, 80


def _rect(x0, y0, x1, y1):
    m = np.zeros((H, W), bool)
    m[y0:y1, x0:x1] = True
    return m


def _gt(mask, visib=1.0, obj=1):
    a = coco_gt_annotation(mask, mask, visib)
    a["category_id"] = obj
    return a


def _det(mask, score, obj=1, im=0, bbox=None):
    if bbox is None:
        x, y, w, h = cv2.boundingRect(mask.astype(np.uint8))
        bbox = (x, y, w, h)
    return Detection2D(1, im, obj, score, bbox, mask_to_rle(mask))


def _eval(dets, anns, n_images=1):
    keys = [(1, i) for i in range(n_images)]
    gt = {(1, 0): anns}
    return evaluate_coco(dets, gt, {k: (W, H) for k in keys}, keys, [1, 2])


def test_gt_annotation_box_is_amodal_and_inclusive():
    full = _rect(10, 5, 30, 25)
    vis = _rect(10, 5, 30, 12)
    a = coco_gt_annotation(vis, full, 0.35)
    assert a["bbox"] == [float(v) for v in cv2.boundingRect(full.astype(np.uint8))]
    assert a["area"] == 20 * 7 and a["bop_ignore"] == 0 and a["iscrowd"] == 0
    assert coco_gt_annotation(vis, full, 0.05)["bop_ignore"] == 1
    assert coco_gt_annotation(np.zeros((H, W), bool), full, 0.0) is None


def test_perfect_detections_score_one():
    m1, m2 = _rect(5, 5, 25, 25), _rect(40, 10, 70, 50)
    res = _eval([_det(m1, 0.9), _det(m2, 0.8, obj=2)], [_gt(m1), _gt(m2, obj=2)])
    one = {"ap": pytest.approx(1.0), "ap50": pytest.approx(1.0), "ap75": pytest.approx(1.0),
           "f1": pytest.approx(1.0), "f1_threshold": pytest.approx(0.8)}
    assert res == {"bbox": one, "segm": one}


def test_low_visibility_gt_is_ignored():
    seen, hidden = _rect(5, 5, 25, 25), _rect(40, 10, 70, 50)
    anns = [_gt(seen), _gt(hidden, visib=0.05)]
    # The 5%-visible GT is not a miss ...
    assert _eval([_det(seen, 0.9)], anns)["segm"]["ap"] == pytest.approx(1.0)
    # ... and a detection on it is not a false positive, even ranked first.
    assert _eval([_det(hidden, 0.99), _det(seen, 0.9)], anns)["bbox"]["ap"] == pytest.approx(1.0)
    # Stock pycocotools counts it: recall 1/2 at precision 1 = 51 of 101 recall points.
    coco_anns = []
    for i, a in enumerate(anns):
        a = dict(a, id=i + 1, image_id=1)
        a["segmentation"] = dict(a["segmentation"], counts=a["segmentation"]["counts"].encode())
        coco_anns.append(a)
    with contextlib.redirect_stdout(io.StringIO()):
        gt = COCO()
        gt.dataset = {
            "images": [{"id": 1, "width": W, "height": H}],
            "annotations": coco_anns,
            "categories": [{"id": 1}, {"id": 2}],
        }
        gt.createIndex()
        x, y, w, h = cv2.boundingRect(seen.astype(np.uint8))
        dt = gt.loadRes([{"image_id": 1, "category_id": 1, "score": 0.9, "bbox": [x, y, w, h]}])
        ev = COCOeval(gt, dt, "bbox")
        ev.evaluate()
        ev.accumulate()
        ev.summarize()
    assert ev.stats[0] == pytest.approx(51 / 101)


def test_false_positive_ranked_first_and_iou_thresholds():
    m = _rect(10, 10, 40, 40)
    far = _rect(50, 40, 70, 55)
    # Precisions [0, 1/2] at recalls [0, 1]: 0.5 at every recall point and IoU threshold.
    res = _eval([_det(far, 0.95), _det(m, 0.9)], [_gt(m)])
    assert res["bbox"]["ap"] == pytest.approx(0.5) and res["segm"]["ap"] == pytest.approx(0.5)
    # The GT box shifted by 7 px: IoU = 23*30 / (2*900 - 23*30) = 0.6216, which passes the IoU
    # thresholds 0.50, 0.55 and 0.60 only: AP = 3/10.
    res = _eval([Detection2D(1, 0, 1, 0.9, (17, 10, 30, 30), None)], [_gt(m)])
    assert res["bbox"] == {"ap": pytest.approx(0.3), "ap50": pytest.approx(1.0), "ap75": 0.0,
                           "f1": pytest.approx(1.0), "f1_threshold": pytest.approx(0.9)}
    assert "segm" not in res


def test_duplicates_and_detections_outside_targets():
    m = _rect(10, 10, 40, 40)
    res = _eval([_det(m, 0.9), _det(m, 0.8), _det(m, 0.99, im=5)], [_gt(m)])
    assert res["segm"]["ap"] == pytest.approx(
        1.0
    )  # duplicate after the TP: precision 1 at recall 1


def test_no_detections_score_zero_not_nothing():
    zero = {"ap": 0.0, "ap50": 0.0, "ap75": 0.0, "f1": 0.0, "f1_threshold": 1.0}
    assert _eval([], [_gt(_rect(5, 5, 25, 25))]) == {"bbox": zero, "segm": zero}


def _box_iou(a, b):
    ax0, ay0, aw, ah = a
    bx0, by0, bw, bh = b
    iw = max(0.0, min(ax0 + aw, bx0 + bw) - max(ax0, bx0))
    ih = max(0.0, min(ay0 + ah, by0 + bh) - max(ay0, by0))
    return iw * ih / (aw * ah + bw * bh - iw * ih)


def test_best_f1_matches_a_brute_force_sweep():
    """The F1 operating point against a loop over every threshold with greedy matching (each
    GT taken by the best-scoring unmatched detection of IoU >= 0.5, as COCO does when no two
    candidates compete for one GT, which this layout guarantees)."""
    rng = np.random.default_rng(3)
    gts = [_rect(5 + 25 * i, 8 + 6 * i, 21 + 25 * i, 28 + 6 * i) for i in range(3)]
    gt_boxes = [tuple(float(v) for v in cv2.boundingRect(g.astype(np.uint8))) for g in gts]
    dets = []
    for box in gt_boxes:  # one hit per GT at a random score, plus a near miss
        dets.append(Detection2D(1, 0, 1, float(rng.uniform(0.2, 0.9)), box, None))
        x, y, w, h = box
        dets.append(Detection2D(1, 0, 1, float(rng.uniform(0.2, 0.9)), (x + 0.6 * w, y, w, h),
                                None))
    for _ in range(5):  # background false positives
        dets.append(Detection2D(1, 0, 1, float(rng.uniform(0.0, 1.0)),
                                (float(rng.uniform(0, 60)), 50.0, 6.0, 6.0), None))
    res = _eval(dets, [_gt(g) for g in gts])["bbox"]
    best = (0.0, 1.0)
    for thr in sorted({d.score for d in dets}):
        kept = sorted((d for d in dets if d.score >= thr), key=lambda d: -d.score)
        taken, tp = set(), 0
        for d in kept:
            ious = [(_box_iou(d.bbox, g), j) for j, g in enumerate(gt_boxes) if j not in taken]
            iou, j = max(ious, default=(0.0, -1))
            if iou >= 0.5:
                taken.add(j)
                tp += 1
        p, r = tp / len(kept), tp / len(gt_boxes)
        f1 = 2 * p * r / (p + r) if tp else 0.0
        if f1 > best[0] + 1e-12:
            best = (f1, thr)
    assert 0.3 < best[0] < 1.0
    assert res["f1"] == pytest.approx(best[0]) and res["f1_threshold"] == pytest.approx(best[1])


def test_any_part_scores_right_boxes_of_swapped_parts():
    """Two boxes found where two instances are, each named as the other's part: AP50 0 by
    part (hand-derived: no true positive), 1 with any part."""
    m1, m2 = _rect(5, 5, 25, 25), _rect(40, 10, 70, 50)
    dets = [_det(m1, 0.9, obj=2), _det(m2, 0.8, obj=1)]
    anns = [_gt(m1), _gt(m2, obj=2)]
    keys = [(1, 0)]
    by_part = evaluate_coco(dets, {(1, 0): anns}, {(1, 0): (W, H)}, keys, [1, 2], ("bbox",))
    any_part = evaluate_coco(dets, {(1, 0): anns}, {(1, 0): (W, H)}, keys, [1, 2], ("bbox",),
                             any_part=True)
    assert by_part["bbox"]["ap50"] == 0.0
    assert any_part["bbox"]["ap50"] == pytest.approx(1.0)
    assert dets[0].obj_id == 2 and anns[1]["category_id"] == 2  # the inputs are left alone
