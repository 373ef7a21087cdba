"""BOP 2D detection / segmentation AP (COCO AP, AP50, AP75) with the BOP ignore rule.

Reproduces `bop_toolkit/scripts/eval_bop22_coco.py`: GT are the instances of the target
images whose visible mask has at least one pixel (`scripts/calc_gt_coco.py`), with the amodal
box of the full silhouette (``[x, y, w, h]`` of the mask pixels, ``w = x_max - x_min + 1``,
`pycoco_utils.bbox_from_binary_mask`), the visible mask as segmentation and its pixel count as
area; a GT with ``visib_fract < 0.1`` carries ``ignore = 1``: it is not counted and detections
matched to it are ignored. Scenes are merged in target order (`pycoco_utils.merge_coco_*`),
categories are all object ids of the models, and the metric is COCOeval's ``stats[0:3]``.

Evaluator: `pycocotools` (the maintained reference COCO API). Stock `COCOeval._prepare`
overwrites every GT's ``ignore`` with ``iscrowd``, which is why BOP ships a fork
(MartinSmeyer/cocoapi) whose only change for BOP is to keep the dataset's ``ignore`` flag.
`BopCOCOeval` is that change as a subclass: it runs the stock `_prepare` and then restores the
flag from ``bop_ignore``; matching, accumulation and summary are stock pycocotools, so the
numbers equal the fork's. (faster-coco-eval 1.8 also overwrites ``ignore`` with ``iscrowd``.)
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import io
from collections.abc import Mapping, Sequence

import numpy as np
from pycocotools.coco import COCO
from pycocotools.cocoeval import COCOeval

from threept_jax.data.bop import Detection2D
from threept_jax.data.bop.results import validate_rle

__all__ = ["BopCOCOeval", "best_f1", "coco_gt_annotation", "evaluate_coco"]


class BopCOCOeval(COCOeval):
    """pycocotools COCOeval that honours a per-GT ``bop_ignore`` flag (the BOP fork's
    behaviour): a GT with the flag is not counted and detections matched to it are ignored."""

    def _prepare(self):
        super()._prepare()
        # Stock _prepare set ignore = iscrowd; restore the dataset's flag (same dict objects).
        for gts in self._gts.values():
            for gt in gts:
                gt["ignore"] = int(gt.get("bop_ignore", 0))


def coco_gt_annotation(
    mask_visib: np.ndarray,
    mask_full: np.ndarray | None,
    visib_fract: float,
    bbox: Sequence[float] | None = None,
) -> dict | None:
    """A COCO GT annotation (without ids) as `calc_gt_coco.py` builds it, or None when the
    visible (or full) mask is empty. ``bbox`` overrides the box when no full mask is given."""
    from threept_jax.data.bop import mask_to_rle

    area = int(np.count_nonzero(mask_visib))
    if area < 1:
        return None
    if mask_full is not None:
        if not np.any(mask_full):
            return None
        rows, cols = np.any(mask_full, axis=1), np.any(mask_full, axis=0)
        r0, r1 = np.where(rows)[0][[0, -1]]
        c0, c1 = np.where(cols)[0][[0, -1]]
        bbox = [int(c0), int(r0), int(c1 - c0 + 1), int(r1 - r0 + 1)]
    if bbox is None:
        raise ValueError("coco_gt_annotation needs a full mask or a bbox")
    return {
        "iscrowd": 0,
        "area": area,
        "bbox": [float(v) for v in bbox],
        "segmentation": mask_to_rle(mask_visib),
        "bop_ignore": int(visib_fract < 0.1),
        "height": int(mask_visib.shape[0]),
        "width": int(mask_visib.shape[1]),
    }


def evaluate_coco(
    detections: Sequence[Detection2D],
    gt: Mapping[tuple[int, int], Sequence[dict]],
    image_sizes: Mapping[tuple[int, int], tuple[int, int]],
    image_order: Sequence[tuple[int, int]],
    category_ids: Sequence[int],
    iou_types: Sequence[str] = ("bbox", "segm"),
    any_part: bool = False,
) -> dict[str, dict[str, float]]:
    """COCO AP / AP50 / AP75 for each iou type in ``iou_types`` ('bbox', 'segm').

    ``any_part=True`` scores every detection against every instance whatever its part (one
    category): a diagnostic that tells a detector that finds parts but names them wrongly
    from one that does not find them; never the figure a user sees.

    ``gt`` maps (scene_id, im_id) to GT annotation dicts (see `coco_gt_annotation`; keys
    ``bbox``, ``segmentation``, ``area``, ``iscrowd``, ``bop_ignore``), ``image_sizes`` to
    (width, height), ``image_order`` lists the target images in the toolkit's merge order.
    Detections outside the target images are dropped; an iou type is skipped when no
    detection carries that field. Undefined AP (no GT at all) is reported as 0."""
    if any_part:
        detections = [dataclasses.replace(d, obj_id=1) for d in detections]
        gt = {k: [dict(a, category_id=1) for a in v] for k, v in gt.items()}
        category_ids = [1]
    img_ids = {key: n + 1 for n, key in enumerate(image_order)}
    images = [
        {"id": img_ids[k], "width": int(image_sizes[k][0]), "height": int(image_sizes[k][1])}
        for k in image_order
    ]
    anns = []
    for k in image_order:
        for a in gt.get(k, []):
            a = dict(a)
            a.update(id=len(anns) + 1, image_id=img_ids[k])
            seg = a.get("segmentation")
            if isinstance(seg, Mapping) and isinstance(seg.get("counts"), str):
                a["segmentation"] = {"counts": seg["counts"].encode("ascii"), "size": seg["size"]}
            anns.append(a)
    cats = [{"id": int(c), "name": str(c)} for c in sorted(set(int(c) for c in category_ids))]
    # Results in the toolkit's order: scenes in target order, file order within a scene.
    scene_rank = {}
    for s, _ in image_order:
        scene_rank.setdefault(s, len(scene_rank))
    dets = [d for d in detections if (d.scene_id, d.im_id) in img_ids]
    for n, d in enumerate(detections):
        # A broken RLE hangs or crashes pycocotools: check it against the GT image size.
        if d.segmentation is not None and (d.scene_id, d.im_id) in img_ids:
            w, h = image_sizes[(d.scene_id, d.im_id)]
            where = f"detection {n} (scene {d.scene_id}, image {d.im_id})"
            validate_rle(d.segmentation, where, (int(h), int(w)))
    dets = sorted(dets, key=lambda d: scene_rank[d.scene_id])
    out: dict[str, dict[str, float]] = {}
    for iou_type in iou_types:
        field_ok = (
            (lambda d: d.bbox is not None)
            if iou_type == "bbox"
            else (lambda d: d.segmentation is not None)
        )
        sel = [d for d in dets if field_ok(d)]
        # A type no detection carries is skipped, but no detections at all scores 0 (not {}).
        if detections and not any(field_ok(d) for d in detections):
            continue
        if not sel:
            out[iou_type] = {"ap": 0.0, "ap50": 0.0, "ap75": 0.0, "f1": 0.0, "f1_threshold": 1.0}
            continue
        res = []
        for d in sel:
            r = {
                "image_id": img_ids[(d.scene_id, d.im_id)],
                "category_id": int(d.obj_id),
                "score": float(d.score),
            }
            if d.bbox is not None:
                r["bbox"] = [float(v) for v in d.bbox]
            if d.segmentation is not None:
                seg = dict(d.segmentation)
                if isinstance(seg.get("counts"), str):
                    seg["counts"] = seg["counts"].encode("ascii")
                r["segmentation"] = seg
            res.append(r)
        with contextlib.redirect_stdout(io.StringIO()):
            coco_gt = COCO()
            coco_gt.dataset = {
                "images": copy.deepcopy(images),
                "annotations": copy.deepcopy(anns),
                "categories": cats,
            }
            coco_gt.createIndex()
            coco_dt = coco_gt.loadRes(res)
            ev = BopCOCOeval(coco_gt, coco_dt, iou_type)
            ev.params.imgIds = sorted(coco_gt.getImgIds())
            ev.evaluate()
            ev.accumulate()
            ev.summarize()
        stats = [max(0.0, float(v)) for v in ev.stats[:3]]
        f1, threshold = best_f1(ev)
        out[iou_type] = {"ap": stats[0], "ap50": stats[1], "ap75": stats[2], "f1": f1,
                         "f1_threshold": threshold}
    return out


def best_f1(ev: COCOeval) -> tuple[float, float]:
    """(F1, score threshold) of the best operating point at IoU 0.5 of an evaluated COCOeval.

    Detections of every image and category are ranked by score; keeping those scoring at
    least the threshold gives precision P = TP / kept and recall R = TP / GT, with COCOeval's
    own matching (IoU >= 0.5, all areas, at most ``maxDets[-1]`` per image and category,
    ignored GT not counted and detections matched to them dropped) and F1 = 2PR / (P + R).
    The threshold is the lowest kept score: a deployment keeps detections scoring at least it
    (``--score-threshold`` is inclusive). (0, 1) when nothing matches.
    """
    t = int(np.argmin(np.abs(ev.params.iouThrs - 0.5)))
    area, max_det = ev.params.areaRng[0], ev.params.maxDets[-1]
    scores, hits, num_gt = [], [], 0
    for e in ev.evalImgs:
        if e is None or list(e["aRng"]) != list(area) or e["maxDet"] != max_det:
            continue
        num_gt += int(np.count_nonzero(~np.asarray(e["gtIgnore"], bool)))
        if len(e["dtIds"]) == 0:
            continue
        keep = ~np.asarray(e["dtIgnore"], bool)[t]
        scores.append(np.asarray(e["dtScores"], np.float64)[keep])
        hits.append((np.asarray(e["dtMatches"])[t] > 0)[keep])
    if not scores or num_gt == 0:
        return 0.0, 1.0
    scores, hits = np.concatenate(scores), np.concatenate(hits)
    order = np.argsort(-scores, kind="mergesort")
    scores, tp = scores[order], np.cumsum(hits[order])
    precision, recall = tp / np.arange(1, len(tp) + 1), tp / num_gt
    f1 = np.where(tp > 0, 2 * precision * recall / np.maximum(precision + recall, 1e-12), 0.0)
    # Equal scores are kept or dropped together: only the last of a run is an operating point.
    last = np.r_[scores[1:] != scores[:-1], True]
    f1 = np.where(last, f1, -1.0)
    i = int(np.argmax(f1))
    return (float(f1[i]), float(scores[i])) if f1[i] > 0 else (0.0, 1.0)
