"""Full-image evaluation (train/eval_detector.py): hand-made cases with known AP, and the same
detections scored by stock pycocotools from the raw record fields (an independent path)."""

import contextlib
import io

import numpy as np
import pytest
import trimesh
from pycocotools.coco import COCO
from pycocotools.cocoeval import COCOeval

from threept_jax.eval.pose_error import prepare_model
from threept_jax.models.detector import DEFAULT_SCORE_MODE
from train.eval_detector import full_image_metrics, held_out_image

H, W = 64, 80
OBJ_IDS = [3, 7]


def _record(rng=None):
    """Three instances of objects 3 and 7 (a 40 x 20 x 10 mm box); the third is 5 % visible."""
    inst = np.zeros((H, W), np.uint16)
    boxes = np.array([[4, 6, 30, 40], [40, 10, 76, 50], [10, 44, 40, 62]], np.float32)
    inst[8:38, 6:28] = 1
    inst[12:48, 42:74] = 2
    inst[44:46, 10:12] = 3
    poses = np.tile(np.eye(4, dtype=np.float32), (3, 1, 1))
    poses[:, :3, 3] = [[-30, -10, 400], [40, 0, 500], [-20, 30, 450]]
    return {"rgb": np.zeros((H, W, 3), np.uint8), "instances": inst,
            "K": np.array([[100.0, 0, 39.5], [0, 100, 31.5], [0, 0, 1]], np.float32),
            "obj_id": np.array([3, 7, 3], np.int32), "T_cam_obj": poses, "bbox_obj": boxes,
            "bbox_visib": boxes, "visib_fract": np.array([0.9, 0.8, 0.05], np.float32)}


def _outputs(boxes, scores, objects, poses=None):
    d = len(boxes)
    out = {"boxes": np.asarray(boxes, np.float32).reshape(d, 4),
           "scores": np.asarray(scores, np.float32), "valid": np.ones(d, bool),
           "object": np.asarray(objects, np.int64)}
    if poses is not None:
        out["poses"] = np.asarray(poses, np.float32)[:, None]
    return out


def _models():
    v = np.asarray(trimesh.creation.box((40, 20, 10)).vertices)
    return {o: prepare_model(points=v, diameter=float(np.linalg.norm([40, 20, 10])))
            for o in OBJ_IDS}


def test_perfect_detections_score_one_and_none_score_zero():
    rec = _record()
    im = held_out_image(rec, 0)
    # Perfect: the two counted instances with their boxes and poses; the 5 %-visible one is
    # ignored (BOP rule), so missing it costs nothing.
    perfect = _outputs(rec["bbox_obj"][:2], [0.9, 0.8], [0, 1], rec["T_cam_obj"][:2])
    m = full_image_metrics([{"product": perfect, "presence": perfect, "template": perfect}], [im], OBJ_IDS, _models())
    assert m["eval/ap50"] == pytest.approx(1.0) and m["eval/ap"] == pytest.approx(1.0)
    assert m["eval/ap50_product"] == m["eval/ap50_presence"] == pytest.approx(1.0)
    assert m["eval/bop6d_ap"] == pytest.approx(1.0)
    assert m["eval/num_gt"] == 2 and m["eval/num_images"] == 1
    none = _outputs(np.zeros((0, 4)), [], [], np.zeros((0, 4, 4)))
    m = full_image_metrics([{DEFAULT_SCORE_MODE: none}], [im], OBJ_IDS, _models())
    assert m["eval/ap50"] == 0.0 and m["eval/ap"] == 0.0 and m["eval/bop6d_ap"] == 0.0
    # Boxes right, every object swapped: box AP 0 (categories are object ids).
    swapped = _outputs(rec["bbox_obj"][:2], [0.9, 0.8], [1, 0])
    assert full_image_metrics([{DEFAULT_SCORE_MODE: swapped}], [im], OBJ_IDS)["eval/ap50"] == 0.0


def test_ap_equals_stock_pycocotools_on_the_same_detections():
    rng = np.random.default_rng(0)
    rec = _record()
    rec["visib_fract"][2] = 0.5  # every instance counted: stock COCOeval has no ignore flag
    images = [held_out_image(rec, i) for i in range(2)]
    outputs = []
    for _ in images:  # jittered true boxes and false positives, random scores and objects
        gt = np.repeat(rec["bbox_obj"], 2, 0) + rng.normal(0, 3, (6, 4))
        fp = np.sort(rng.uniform(0, 60, (3, 2, 2)), axis=1).reshape(3, 4)
        boxes = np.concatenate([gt, fp])
        objs = np.concatenate([np.repeat([0, 1, 0], 2), rng.integers(0, 2, 3)])
        objs[rng.random(9) < 0.2] ^= 1
        outputs.append({DEFAULT_SCORE_MODE: _outputs(boxes, rng.random(9), objs)})
    m = full_image_metrics(outputs, images, OBJ_IDS)

    gt, dt = [], []
    for n, out in enumerate(outputs):
        for i in range(3):
            x0, y0, x1, y1 = (float(v) for v in rec["bbox_obj"][i])
            gt.append({"id": len(gt) + 1, "image_id": n + 1, "category_id": int(rec["obj_id"][i]),
                       "bbox": [x0, y0, x1 - x0, y1 - y0], "iscrowd": 0,
                       "area": float((rec["instances"] == i + 1).sum())})
        o = out[DEFAULT_SCORE_MODE]
        for b, s, j in zip(o["boxes"], o["scores"], o["object"], strict=True):
            dt.append({"image_id": n + 1, "category_id": OBJ_IDS[j], "score": float(s),
                       "bbox": [float(b[0]), float(b[1]), float(b[2] - b[0]), float(b[3] - b[1])]})
    with contextlib.redirect_stdout(io.StringIO()):
        coco = COCO()
        coco.dataset = {"images": [{"id": n + 1, "width": W, "height": H} for n in range(2)],
                        "annotations": gt, "categories": [{"id": o} for o in OBJ_IDS]}
        coco.createIndex()
        ev = COCOeval(coco, coco.loadRes(dt), "bbox")
        ev.evaluate()
        ev.accumulate()
        ev.summarize()
    assert 0.1 < ev.stats[1] < 0.99  # a case that tells right from wrong
    assert m["eval/ap"] == pytest.approx(ev.stats[0], abs=1e-12)
    assert m["eval/ap50"] == pytest.approx(ev.stats[1], abs=1e-12)
    assert m["eval/ap75"] == pytest.approx(max(ev.stats[2], 0.0), abs=1e-12)
