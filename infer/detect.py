"""Detection and object generation on full images (3PT stages 1 and 2, single view).

``SceneDetector.detect(image, K)`` runs pan-and-scan over the image, queries every onboarded
object in every tile (early fusion), keeps each object's best candidates, merges all of them by
one NMS across tiles, scales and objects, and turns every kept detection into an object with K
pose hypotheses (top templates at least 45 degrees apart, turned by the box ray, translation
fitted to the box). Tiling, the detector, NMS and object generation are one jitted function per
image size, so repeated calls on a camera's images never recompile.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from infer.onboarding import OnboardedObject
from threept_jax.geometry.boxes import nms
from threept_jax.geometry.validate import validate_intrinsics
from threept_jax.models.configs import DetectorConfig
from threept_jax.models.detector import Detector, orientation_scores, patch_scores
from threept_jax.pipeline import pan_and_scan as pns
from threept_jax.pipeline.object_generation import single_view_hypotheses


@dataclasses.dataclass(frozen=True)
class Detection:
    """One detected instance in one image.

    Attributes:
      obj_id: which onboarded object.
      box: [4] amodal box, xyxy pixel-edge coordinates of the input image.
      score: detection score in [0, 1] (presence x best template match).
      poses: [K, 4, 4] T_cam_obj hypotheses, best first (mm).
      pose_scores: [K] template-match score of each hypothesis (invalid ones are -inf).
      template_scores: [T] cosine similarity of the detection's embedding with every template
        of its object (the orientation distribution; multi-view fusion uses it).
    """

    obj_id: int
    box: np.ndarray
    score: float
    poses: np.ndarray
    pose_scores: np.ndarray
    template_scores: np.ndarray

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


class SceneDetector:
    """Detects onboarded objects in images (module docstring)."""

    def __init__(self, model: Detector, config: DetectorConfig, objects: Sequence[OnboardedObject],
                 *, num_scales: int | None = None, scales: Sequence[float] | None = None,
                 depth_range: tuple[float, float] | None = None,
                 score_threshold: float = 0.1, nms_iou: float = 0.5, max_detections: int = 100,
                 candidates_per_object: int = 256, num_hypotheses: int = 8,
                 min_angle_deg: float = 45.0):
        if not objects:
            raise ValueError("no objects to detect: onboard at least one mesh")
        t = {len(o.template_bank) for o in objects}
        if len(t) != 1:
            raise ValueError(f"objects were onboarded with different template counts {sorted(t)}")
        self.config = config
        self.objects = list(objects)
        self.num_scales = num_scales
        self.scales = None if scales is None else tuple(float(s) for s in scales)
        self.depth_range = None if depth_range is None else tuple(float(z) for z in depth_range)
        if self.depth_range is not None:  # checked now, not at the first image
            pns.projected_size_range([o.diameter for o in objects], self.depth_range, np.eye(3))
        self.score_threshold = float(score_threshold)
        self.nms_iou = float(nms_iou)
        self.max_detections = int(max_detections)
        self.candidates = int(candidates_per_object)
        self.num_hypotheses = int(num_hypotheses)
        self.min_angle_deg = float(min_angle_deg)
        self.logit_scale = float(model.logit_scale)
        self._graphdef, self._params = nnx.split(model)
        self._prior = jnp.asarray(np.stack([x.prior_tokens for x in self.objects]))
        self._bank = jnp.asarray(np.stack([x.template_bank for x in self.objects]))
        self._points = jnp.asarray(np.stack([x.points for x in self.objects]))
        self._rotations = jnp.asarray(self.objects[0].template_rotations)
        self._steps: dict[tuple, object] = {}

    def layout(self, image_hw: tuple[int, int], K: np.ndarray | None = None) -> pns.TileLayout:
        """The tiles of an image: ``scales`` if given, else planned for the depth range (the
        objects' projected diameters through K) or, without one, for 64 px to the image."""
        tile = self.config.image_size
        if self.scales:
            return pns.tile_layout(image_hw, tile, self.scales)
        sizes = None if self.depth_range is None else pns.projected_size_range(
            [o.diameter for o in self.objects], self.depth_range, K)
        return pns.plan_layout(image_hw, tile, object_sizes=sizes, num_scales=self.num_scales)

    def _compiled(self, image_hw: tuple[int, int], K: np.ndarray | None = None):
        """The jitted detection function for one tile layout, built once per detector."""
        layout = self.layout(image_hw, K)
        key = (image_hw, layout.scales, layout.tile_origin.tobytes())
        if key not in self._steps:
            self._steps[key] = self._build(layout)
        return self._steps[key]

    def _build(self, layout: pns.TileLayout):
        graphdef, cand, max_det = self._graphdef, self.candidates, self.max_detections
        k, min_angle = self.num_hypotheses, self.min_angle_deg
        thr, iou = self.score_threshold, self.nms_iou

        def per_object(params, tiles, prior, bank):
            model = nnx.merge(graphdef, params)
            n = tiles.shape[0]
            out = model(tiles, jnp.broadcast_to(prior, (n, *prior.shape)), bank)
            scores = patch_scores(out["presence_logits"], out["detection_logits"])  # [N, P]
            boxes = pns.tile_boxes_to_image(out["boxes"], layout)  # [N, P, 4]
            scores = jnp.where(pns.interior_edge_mask(out["boxes"], layout), -jnp.inf, scores)
            top_scores, top = jax.lax.top_k(scores.reshape(-1), min(cand, scores.size))
            return boxes.reshape(-1, 4)[top], top_scores, out["embeddings"].reshape(
                -1, out["embeddings"].shape[-1])[top]

        def run(params, image, K, prior_all, bank_all, points_all, rotations):
            tiles = pns.extract_tiles(image, layout)
            boxes, scores, emb = jax.lax.map(
                lambda x: per_object(params, tiles, x[0], x[1]), (prior_all, bank_all))
            c = scores.shape[1]  # scores [O, C]
            keep, ok = nms(boxes.reshape(-1, 4), scores.reshape(-1), iou, max_det, thr)
            obj = keep // c
            det_boxes = boxes.reshape(-1, 4)[keep]
            det_emb = emb.reshape(-1, emb.shape[-1])[keep]
            tmpl = orientation_scores(det_emb[:, None], bank_all[obj])[:, 0]  # [D, T]
            poses, pose_scores, _ = jax.vmap(
                lambda b, s, p: single_view_hypotheses(b, K, s, rotations, p, k, min_angle))(
                    det_boxes, tmpl, points_all[obj])
            return {"boxes": det_boxes, "scores": scores.reshape(-1)[keep], "valid": ok,
                    "best_score": jnp.max(scores),
                    "object": obj, "poses": poses, "pose_scores": pose_scores,
                    "template_scores": tmpl}

        return jax.jit(run)

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
        out = self._compiled(hw, K)(self._params, image, K, self._prior, self._bank, self._points,
                                 self._rotations)
        out = jax.tree.map(np.asarray, out)
        dets = Detections(best_score=out["best_score"])
        for i in np.flatnonzero(out["valid"]):
            o = self.objects[int(out["object"][i])]
            dets.append(Detection(o.obj_id, out["boxes"][i], float(out["scores"][i]),
                                  out["poses"][i], out["pose_scores"][i],
                                  out["template_scores"][i]))
        return dets
