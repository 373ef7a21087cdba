"""Overlays: detections drawn on their image (box, label, silhouette contour of the pose), and a
caption (such as :func:`empty_caption`) so an image without detections does not look like an
untouched input."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import cv2
import numpy as np

from infer.detect import Detection


def _colour(obj_id: int) -> tuple[int, int, int]:
    hue = (obj_id * 47) % 180
    bgr = cv2.cvtColor(np.uint8([[[hue, 200, 255]]]), cv2.COLOR_HSV2BGR)[0, 0]
    return tuple(int(c) for c in bgr[::-1])  # RGB


def empty_caption(threshold: float, best_score: float) -> str:
    """What to say for an image without detections, e.g. ``0 detections above threshold 0.1
    (best score 0.034)``; ``best_score`` is -inf when there was no candidate at all."""
    best = f"best score {best_score:.3f}" if np.isfinite(best_score) else "no candidates"
    return f"0 detections above threshold {threshold:g} ({best})"


def caption_band_height(image_hw: tuple[int, int]) -> int:
    """Height in pixels of the band at the top of an overlay that a caption is drawn in."""
    return 18 * max(1, round(max(image_hw) / 640))


#: Overlays narrower than this are enlarged by a whole factor (readable labels and contours).
MIN_OVERLAY_WIDTH = 640


def draw_detections(image: np.ndarray, detections: Sequence[Detection],
                    masks: Sequence[np.ndarray] | None = None,
                    names: Mapping[int, str] | None = None, max_draw: int = 50,
                    caption: str | None = None,
                    before_masks: Sequence[np.ndarray] = ()) -> np.ndarray:
    """uint8 RGB copy of ``image`` with boxes, ``name score`` labels and mask contours, and
    ``caption`` (if given) in white on a black band at the top (:func:`caption_band_height`).
    ``before_masks`` (e.g. the silhouettes before refinement) are outlined in white under the
    detections' coloured contours.

    An image narrower than :data:`MIN_OVERLAY_WIDTH` is enlarged by the smallest whole factor
    that reaches it (bilinear; masks nearest, boxes scaled), so that labels stay legible."""
    image = np.asarray(image, np.uint8)
    up = max(1, -(-MIN_OVERLAY_WIDTH // image.shape[1]))
    if up > 1:
        image = cv2.resize(image, None, fx=up, fy=up, interpolation=cv2.INTER_LINEAR)
        def grow(m):
            return cv2.resize(m.astype(np.uint8), None, fx=up, fy=up,
                              interpolation=cv2.INTER_NEAREST)

        masks = None if masks is None else [grow(m) for m in masks]
        before_masks = [grow(m) for m in before_masks]
    canvas = np.ascontiguousarray(image.copy())
    scale = max(1, round(max(canvas.shape[:2]) / 640))
    for m in before_masks[:max_draw]:
        contours, _ = cv2.findContours(m.astype(np.uint8), cv2.RETR_EXTERNAL,
                                       cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(canvas, contours, -1, (255, 255, 255), scale, cv2.LINE_AA)
    if caption:
        band = caption_band_height(canvas.shape[:2])
        canvas[:band] = 0
        cv2.putText(canvas, caption, (4 * scale, band - 5 * scale), cv2.FONT_HERSHEY_SIMPLEX,
                    0.4 * scale, (255, 255, 255), scale, cv2.LINE_AA)
    for i, det in enumerate(detections[:max_draw]):
        colour = _colour(det.obj_id)
        if masks is not None:
            contours, _ = cv2.findContours(masks[i].astype(np.uint8), cv2.RETR_EXTERNAL,
                                           cv2.CHAIN_APPROX_NONE)
            cv2.drawContours(canvas, contours, -1, colour, scale, cv2.LINE_AA)
        x0, y0, x1, y1 = (int(round(v * up)) for v in det.box)
        cv2.rectangle(canvas, (x0, y0), (x1, y1), colour, scale)
        label = f"{(names or {}).get(det.obj_id, det.obj_id)} {det.score:.2f}"
        cv2.putText(canvas, label, (x0, max(12 * scale, y0 - 3)), cv2.FONT_HERSHEY_SIMPLEX,
                    0.4 * scale, colour, scale, cv2.LINE_AA)
    return canvas
