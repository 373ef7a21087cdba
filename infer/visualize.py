"""Overlays: detections drawn on their image (box, label, silhouette contour of the pose), and
rendered masks of estimated poses."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import cv2
import numpy as np

from threept_jax.render import Renderer

from infer.detect import Detection
from infer.onboarding import OnboardedObject


def _colour(obj_id: int) -> tuple[int, int, int]:
    hue = (obj_id * 47) % 180
    bgr = cv2.cvtColor(np.uint8([[[hue, 200, 255]]]), cv2.COLOR_HSV2BGR)[0, 0]
    return tuple(int(c) for c in bgr[::-1])  # RGB


class PoseRenderer:
    """Silhouettes of estimated poses, one JAX renderer per object (compiled once per size)."""

    def __init__(self, objects: Sequence[OnboardedObject]):
        self._objects = {o.obj_id: o for o in objects}
        self._renderers: dict[int, Renderer] = {}

    def masks(self, obj_id: int, T_cam_obj: np.ndarray, K: np.ndarray, hw: tuple[int, int]
              ) -> np.ndarray:
        """bool [B, H, W] silhouettes of object ``obj_id`` at poses [B, 4, 4]."""
        if obj_id not in self._renderers:
            self._renderers[obj_id] = Renderer(self._objects[obj_id].mesh)
        T = np.asarray(T_cam_obj, np.float32).reshape(-1, 4, 4)
        K = np.broadcast_to(np.asarray(K, np.float32), (len(T), 3, 3))
        return np.asarray(self._renderers[obj_id].render(T, K, hw, ("mask",))["mask"])


def detection_masks(detections: Sequence[Detection], K: np.ndarray, hw: tuple[int, int],
                    renderer: PoseRenderer) -> list[np.ndarray]:
    """bool [H, W] silhouette of each detection's best pose, visible parts only: a pixel covered
    by several silhouettes goes to the higher-scoring detection (detections come best first)."""
    taken = np.zeros(hw, bool)
    out = []
    for det in detections:
        m = renderer.masks(det.obj_id, det.pose[None], K, hw)[0] & ~taken
        taken |= m
        out.append(m)
    return out


def draw_detections(image: np.ndarray, detections: Sequence[Detection],
                    masks: Sequence[np.ndarray] | None = None,
                    names: Mapping[int, str] | None = None, max_draw: int = 50) -> np.ndarray:
    """uint8 RGB copy of ``image`` with boxes, ``name score`` labels and mask contours."""
    canvas = np.ascontiguousarray(np.asarray(image, np.uint8).copy())
    scale = max(1, round(max(canvas.shape[:2]) / 640))
    for i, det in enumerate(detections[:max_draw]):
        colour = _colour(det.obj_id)
        if masks is not None:
            contours, _ = cv2.findContours(masks[i].astype(np.uint8), cv2.RETR_EXTERNAL,
                                           cv2.CHAIN_APPROX_NONE)
            cv2.drawContours(canvas, contours, -1, colour, scale, cv2.LINE_AA)
        x0, y0, x1, y1 = (int(round(v)) for v in det.box)
        cv2.rectangle(canvas, (x0, y0), (x1, y1), colour, scale)
        label = f"{(names or {}).get(det.obj_id, det.obj_id)} {det.score:.2f}"
        cv2.putText(canvas, label, (x0, max(12 * scale, y0 - 3)), cv2.FONT_HERSHEY_SIMPLEX,
                    0.4 * scale, colour, scale, cv2.LINE_AA)
    return canvas
