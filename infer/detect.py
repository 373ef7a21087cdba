"""Detection and object generation on full images (3PT stages 1 and 2, single view).

``SceneDetector.detect(image, K)`` runs pan-and-scan over the image, queries every onboarded
object in every tile (early fusion), keeps each object's best candidates, merges all of them by
one NMS across tiles, scales and objects, and turns every kept detection into an object with K
pose hypotheses (top templates at least 45 degrees apart, turned by the ray through the model's
bounding-sphere centre as in training, translation fitted to the amodal box). Tiling, the
detector, NMS and object generation are one jitted function per tile layout
(:class:`threept_jax.pipeline.detection.FullImageDetector`, the same path the training
evaluation runs), so repeated calls on a camera's images never recompile.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from infer.onboarding import OnboardedObject
from threept_jax.geometry.validate import validate_intrinsics
from threept_jax.models.configs import DetectorConfig
from threept_jax.models.detector import Detector
from threept_jax.pipeline import pan_and_scan as pns
from threept_jax.pipeline.detection import (
    DEFAULT_SCORE_MODE,
    DetectionSettings,
    FullImageDetector,
    ObjectQueries,
)


@dataclasses.dataclass(frozen=True)
class Detection:
    """One detected instance in one image.

    Attributes:
      obj_id: which onboarded object.
      box: [4] amodal box, xyxy pixel-edge coordinates of the input image.
      score: detection score in [0, 1] (``models.detector.DEFAULT_SCORE_MODE``: the best
        template match).
      poses: [K, 4, 4] T_cam_obj hypotheses, best first (mm).
      pose_scores: [K] template-match score of each hypothesis (invalid ones are -inf).
      template_scores: [T] cosine similarity of the detection's embedding with every template
        of its object (the orientation distribution; multi-view fusion uses it).
      pose_score: the probability that the pose is right, where the detector ranks poses by
        another score than boxes (the cell detector: the calibrated score of the pose's
        outline, where ``score`` is its network's box score); None: ``score`` ranks both.
    """

    obj_id: int
    box: np.ndarray
    score: float
    poses: np.ndarray
    pose_scores: np.ndarray
    template_scores: np.ndarray
    pose_score: float | None = None

    @property
    def pose(self) -> np.ndarray:
        """The best hypothesis T_cam_obj [4, 4]."""
        return self.poses[0]


class Detections(list):
    """The detections of one image (a list of :class:`Detection`, best first) and
    ``best_score``: the highest score of any candidate, kept or not (-inf when no candidate
    survived the tile-edge filter), so an empty list can say how far below the threshold the
    image stayed."""

    def __init__(self, detections=(), best_score: float = -np.inf):
        super().__init__(detections)
        self.best_score = float(best_score)


#: Default detection probability (3PT-D's presence score) a detection must exceed.
SCORE_THRESHOLD = 0.1


class SceneDetector:
    """Detects onboarded objects in images (module docstring); the detection itself is
    :class:`threept_jax.pipeline.detection.FullImageDetector`, the path training evaluates."""

    def __init__(self, model: Detector, config: DetectorConfig, objects: Sequence[OnboardedObject],
                 *, num_scales: int | None = None, scales: Sequence[float] | None = None,
                 depth_range: tuple[float, float] | None = None,
                 score_threshold: float = SCORE_THRESHOLD, nms_iou: float = 0.5,
                 max_detections: int = 100,
                 candidates_per_object: int = 256, num_hypotheses: int = 8,
                 min_angle_deg: float = 45.0):
        if not objects:
            raise ValueError("no objects to detect: onboard at least one mesh")
        t = {len(o.template_bank) for o in objects}
        if len(t) != 1:
            raise ValueError(f"objects were onboarded with different template counts {sorted(t)}")
        self.config = config
        self.objects = list(objects)
        self.depth_range = None if depth_range is None else tuple(float(z) for z in depth_range)
        if self.depth_range is not None:  # checked now, not at the first image
            pns.projected_size_range([o.diameter for o in objects], self.depth_range, np.eye(3))
        self.logit_scale = float(model.logit_scale)
        settings = DetectionSettings(
            score_threshold=float(score_threshold), nms_iou=float(nms_iou),
            max_detections=int(max_detections), candidates_per_object=int(candidates_per_object),
            num_hypotheses=int(num_hypotheses), min_angle_deg=float(min_angle_deg))
        graphdef, self._params = nnx.split(model)
        self._core = FullImageDetector(graphdef, config.image_size, settings,
                                       num_scales=num_scales, scales=scales)
        self._queries = ObjectQueries(
            prior_tokens=jnp.asarray(np.stack([x.prior_tokens for x in self.objects])),
            template_bank=jnp.asarray(np.stack([x.template_bank for x in self.objects])),
            template_rotations=jnp.asarray(self.objects[0].template_rotations),
            points=jnp.asarray(np.stack([x.points for x in self.objects])))

    @property
    def score_threshold(self) -> float:
        return self._core.settings.score_threshold

    @property
    def num_hypotheses(self) -> int:
        return self._core.settings.num_hypotheses

    @property
    def min_angle_deg(self) -> float:
        return self._core.settings.min_angle_deg

    def _object_sizes(self, K: np.ndarray | None) -> tuple[float, float] | None:
        """Expected projected diameters (px) from the depth range, None when unknown."""
        if self.depth_range is None or K is None:
            return None
        return pns.projected_size_range([o.diameter for o in self.objects], self.depth_range, K)

    def layout(self, image_hw: tuple[int, int], K: np.ndarray | None = None) -> pns.TileLayout:
        """The tiles of an image: ``scales`` if given, else planned for the depth range (the
        objects' projected diameters through K) or, without one, for 64 px to the image."""
        return self._core.layout(image_hw, self._object_sizes(K))

    def _compiled(self, image_hw: tuple[int, int], K: np.ndarray | None = None):
        """The jitted detection function for one tile layout, built once per detector."""
        return self._core.compiled(image_hw, self._object_sizes(K))

    def detect(self, image: np.ndarray, K: np.ndarray) -> Detections:
        """Detections in one RGB image [H, W, 3] (uint8) with intrinsics K [3, 3] (pixels of
        this image), best first, with the best candidate score (:class:`Detections`)."""
        image = np.asarray(image)
        if image.ndim != 3 or image.shape[2] != 3:
            raise ValueError(f"image must be RGB [H, W, 3], got shape {image.shape}")
        if image.dtype != np.uint8:
            raise ValueError(f"image must be uint8 RGB, got {image.dtype} (convert with "
                             "(x * 255).round().astype(np.uint8) for float images in [0, 1])")
        hw = image.shape[:2]
        K = validate_intrinsics(K, "K", image_hw=hw).astype(np.float32)
        out = self._core(self._params, image, K, self._queries,
                         self._object_sizes(K))[DEFAULT_SCORE_MODE]
        out = jax.tree.map(np.asarray, out)
        dets = Detections(best_score=out["best_score"])
        for i in np.flatnonzero(out["valid"]):
            o = self.objects[int(out["object"][i])]
            dets.append(Detection(o.obj_id, out["boxes"][i], float(out["scores"][i]),
                                  out["poses"][i], out["pose_scores"][i],
                                  out["template_scores"][i]))
        return dets
