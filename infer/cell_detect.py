"""A cell's trained detector (``--detector cell``): the dense cell detector finds and names the
parts, the shape search poses them, and the templates detector's own search adds what the
network missed.

:class:`CellDetector` has the interface of :class:`infer.detect.SceneDetector` (``objects``,
``detect(image, K)`` -> :class:`infer.detect.Detections`). The network
(:mod:`threept_jax.models.dense`, trained on the cell's own images by ``python -m
train.cell_detector``) gives boxes, parts and scores over the whole image in one pass; each of
the best boxes then gets a pose from its part's contour templates fitted inside it and inside
shifted and rescaled copies of it, refined by the contour refiner
(:meth:`infer.shape_detect.ShapeSearchDetector.poses_in_boxes`), so the render-and-compare
stage starts where that fit ended. The templates detector's own detections of the same image
(:meth:`~infer.shape_detect.ShapeSearchDetector.detect`, above its own threshold) join them,
and where both found the same part at the same place the pose with the better calibrated score
is kept (:func:`merge`).

A detection's ``score`` ranks boxes: the network's for its boxes, the calibrated score for the
templates'; its ``pose_score`` is the calibrated score of the pose's outline (the templates
detector's probability that it is right), which ranks poses: the BOP runner scores the 6D rows
by it and the 2D rows by ``score``. On the demo's test images, one 10-minute run (docs/training.md,
"Poses"): BOP 6D AP 0.066 with the box alone fitted and the rows ranked by the network's
score, 0.271 with its copies and ranked by the pose score, 0.303 with the templates'
detections joined (the templates detector alone 0.265); 2.9 s an image with the contour
refiner, 2 cores.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence

import numpy as np

from infer.detect import Detection, Detections
from infer.shape_detect import SCORE_THRESHOLD as TEMPLATES_SCORE_THRESHOLD
from infer.shape_detect import ShapeSearchDetector
from threept_jax.geometry.validate import validate_intrinsics
from threept_jax.models.dense import DenseDetector
from threept_jax.pipeline.dense import ImageBoxes
from threept_jax.pipeline.shape_search import ShapeSearchSettings

#: Default score a detection must exceed: the network's probability that the place holds the
#: part, trained toward the box's IoU (so a right box scores about its IoU).
SCORE_THRESHOLD = 0.25
#: Two detections of one part are one when their centres are closer than this share of the
#: first's depth (:func:`merge`).
SAME_PLACE = 0.1


def merge(detections: Sequence[Detection], centers: dict[int, np.ndarray],
          most: int) -> list[Detection]:
    """The ``most`` best of ``detections`` by pose score (``pose_score``, else ``score``), one
    per place: a detection is dropped when a better one of the same part has its centre
    (``centers[obj_id]``, object frame, mm, moved by the pose) within :data:`SAME_PLACE` of
    that one's depth."""
    def rank(d):
        return d.score if d.pose_score is None else d.pose_score

    kept, places = [], []
    for d in sorted(detections, key=lambda d: -rank(d)):
        c = d.pose[:3, :3] @ centers[d.obj_id] + d.pose[:3, 3]
        if any(o == d.obj_id and np.linalg.norm(c - q) < SAME_PLACE * q[2] for o, q in places):
            continue
        if len(kept) == most:
            break
        kept.append(d)
        places.append((d.obj_id, c))
    return kept


class CellDetector:
    """Detects a cell's parts with its trained network (module docstring). ``network`` and
    ``class_ids`` (obj_id of each output) from :func:`threept_jax.data.dense_run.load`;
    ``objects``: the parts to find (each ``obj_id`` and ``mesh``, mm), all among the network's.
    ``score_threshold``: the network's score a box must exceed; ``templates_threshold``: the
    calibrated score the templates detector's own detections must exceed to join (its default
    threshold: a featureless noisy image scores up to 0.35), None: the network's boxes
    alone (1.6 s an image on 2 cores, the merged path 2.9 s). ``max_detections``: per image,
    after the merge. ``score_weights``: a cell's calibration of the templates' score
    (:func:`infer.shape_detect.load_score_weights`), for the poses' scores and the templates'
    detections; ``verifier``: the templates detector's (``"shipped"`` or None:
    :class:`infer.shape_detect.ShapeSearchDetector`)."""

    def __init__(self, network: DenseDetector, class_ids: Sequence[int], objects: Sequence, *,
                 depth_range: tuple[float, float] | None = None,
                 score_threshold: float = SCORE_THRESHOLD,
                 templates_threshold: float | None = TEMPLATES_SCORE_THRESHOLD,
                 max_detections: int = 100, settings: ShapeSearchSettings | None = None,
                 cache_dir: str | os.PathLike | None = None,
                 score_weights: Mapping[int, Sequence[float]] | None = None,
                 verifier: str | None = "shipped"):
        if not objects:
            raise ValueError("no objects to detect: give at least one mesh")
        class_ids = [int(c) for c in class_ids]
        unknown = sorted({int(o.obj_id) for o in objects} - set(class_ids))
        if unknown:
            raise ValueError(f"the cell detector was trained on the parts {class_ids}; {unknown} "
                             "are not among them: train it on the cell's records with those "
                             "parts (python -m train.cell_detector), or use --detector templates")
        self.templates_threshold = templates_threshold
        self.shapes = ShapeSearchDetector(
            objects, depth_range=depth_range, settings=settings, cache_dir=cache_dir,
            score_threshold=np.inf if templates_threshold is None else templates_threshold,
            max_detections=max_detections, score_weights=score_weights, verifier=verifier)
        self.objects = self.shapes.objects
        self.score_threshold = float(score_threshold)
        self.max_detections = int(max_detections)
        row = {o.obj_id: i for i, o in enumerate(self.objects)}
        # Output class -> row of ``objects``, -1 for the network's parts not queried.
        self._rows = np.array([row.get(c, -1) for c in class_ids])
        self._boxes = ImageBoxes(network)

    def boxes(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The network's detections of the queried parts: boxes [n, 4] xyxy (image pixels),
        scores [n] and rows of ``objects`` [n], best first, before the threshold."""
        boxes, scores, classes = self._boxes(image)
        rows = self._rows[classes]
        keep = rows >= 0
        return boxes[keep], scores[keep], rows[keep]

    def detect(self, image: np.ndarray, K: np.ndarray) -> Detections:
        """Detections in one RGB image [H, W, 3] (uint8) with intrinsics K [3, 3] (pixels of
        this image), best pose score first (:func:`merge`); ``best_score`` is the best score
        of any box or templates' candidate."""
        image = np.asarray(image)
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise ValueError(f"image must be uint8 RGB [H, W, 3], got {image.dtype} "
                             f"{image.shape}")
        K = validate_intrinsics(K, "K", image_hw=image.shape[:2])
        boxes, scores, rows = self.boxes(image)
        best = float(scores.max()) if len(scores) else -np.inf
        keep = np.flatnonzero(scores > self.score_threshold)
        keep = keep[:min(self.max_detections, self.shapes.max_boxes)]
        poses, fit = self.shapes.poses_in_boxes(image, K, boxes[keep], rows[keep])
        found = []
        for i, pose, f in zip(keep, poses, fit):
            if not np.isfinite(pose).all():
                continue  # no template of the part fits the box
            found.append(Detection(self.objects[rows[i]].obj_id, boxes[i].astype(np.float32),
                                   float(scores[i]), pose[None].astype(np.float32),
                                   np.array([f], np.float32), np.zeros(0, np.float32),
                                   pose_score=float(f)))
        if self.templates_threshold is not None:
            theirs = self.shapes.detect(image, K)
            found += theirs
            best = max(best, theirs.best_score)
        centers = {o.obj_id: c for o, c in zip(self.objects, self.shapes.centers)}
        return Detections(merge(found, centers, self.max_detections), best_score=best)
