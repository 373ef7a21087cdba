"""Masks of estimated poses: the silhouettes of the CAD model rendered at each detection's best
pose (3PT-R's learned masks replace them once the refiner lands), visible parts only."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from infer.detect import Detection
from infer.onboarding import OnboardedObject
from threept_jax.render import Renderer


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
