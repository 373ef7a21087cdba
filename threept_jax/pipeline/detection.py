"""Full-image detection and single-view object generation (3PT stages 1 and 2), jitted.

The one detection path shared by inference (``infer.detect.SceneDetector``) and the training
evaluation (``train.eval_detector``), so that the checkpoint chosen by training is the one that
detects best the way a user runs it. :class:`FullImageDetector` builds, once per image size,
one jitted function that

1. cuts the image into pan-and-scan tiles (:mod:`threept_jax.pipeline.pan_and_scan`),
2. queries every object in every tile (early fusion; ``jax.lax.map`` over objects), scores every
   patch (:func:`detection_scores`), drops patches whose box touches an interior tile edge, and
   keeps each object's ``candidates_per_object`` best patches,
3. merges all candidates by one NMS across tiles, scales and objects,
4. turns every kept detection into K pose hypotheses (:func:`single_view_hypotheses`: top
   templates at least ``min_angle_deg`` apart, translation fitted to the box).

Several score modes can be evaluated from one forward pass (the training evaluation reports
each); steps 2-4 run once per mode.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from threept_jax.geometry.boxes import nms
from threept_jax.models.detector import (
    DEFAULT_SCORE_MODE,
    SCORE_MODES,
    detection_scores,
    orientation_scores,
)
from threept_jax.pipeline import pan_and_scan as pns
from threept_jax.pipeline.object_generation import single_view_hypotheses

Array = jax.Array

__all__ = ["DEFAULT_SCORE_MODE", "SCORE_MODES", "DetectionSettings", "FullImageDetector",
           "ObjectQueries", "detection_function", "model_points"]
#: Model points kept per object for fitting boxes (object generation).
NUM_POINTS = 1024


def model_points(vertices: np.ndarray, n: int = NUM_POINTS) -> np.ndarray:
    """[n, 3] float32 points of a mesh's vertices [N, 3] for object generation: all vertices
    (the first repeated up to ``n``) or a fixed random subset that keeps the extreme vertices
    of each axis, which decide the boxes."""
    v = np.asarray(vertices, np.float32)
    if len(v) <= n:
        return np.concatenate([v, np.repeat(v[:1], n - len(v), 0)])  # duplicates are harmless
    idx = np.random.default_rng(0).choice(len(v), n, replace=False)
    extremes = np.concatenate([np.argmin(v, 0), np.argmax(v, 0)])
    idx[: len(extremes)] = extremes
    return v[idx]


@dataclasses.dataclass(frozen=True)
class DetectionSettings:
    """How candidates become detections (module docstring).

    ``score_threshold``: detections scoring below it are dropped; ``nms_iou``: NMS overlap;
    ``max_detections``: per image; ``candidates_per_object``: patches kept per object before
    NMS; ``num_hypotheses`` / ``min_angle_deg``: object generation; ``score_modes``: the
    scores to run steps 2-4 with (:data:`SCORE_MODES`); ``generate_objects``: False skips
    step 4 (no model points needed).
    """

    score_threshold: float = 0.1
    nms_iou: float = 0.5
    max_detections: int = 100
    candidates_per_object: int = 256
    num_hypotheses: int = 8
    min_angle_deg: float = 45.0
    score_modes: tuple[str, ...] = (DEFAULT_SCORE_MODE,)
    generate_objects: bool = True

    def __post_init__(self):
        bad = [m for m in self.score_modes if m not in SCORE_MODES]
        if bad or not self.score_modes:
            raise ValueError(f"score_modes {self.score_modes!r}: each must be one of "
                             f"{SCORE_MODES}, at least one")
        if self.max_detections < 1 or self.candidates_per_object < 1:
            raise ValueError("max_detections and candidates_per_object must be >= 1, got "
                             f"{self.max_detections} and {self.candidates_per_object}")


@dataclasses.dataclass(frozen=True)
class ObjectQueries:
    """The onboarded objects queried in every image (O objects, T templates each).

    ``prior_tokens`` [O, Np, D]; ``template_bank`` [O, T, E] unit vectors;
    ``template_rotations`` [T, 3, 3] (shared) or [O, T, 3, 3], object-centred; ``points``
    [O, N, 3] model points (mm), or None when objects are not generated.
    """

    prior_tokens: Array
    template_bank: Array
    template_rotations: Array
    points: Array | None = None

    @property
    def num_objects(self) -> int:
        return int(self.prior_tokens.shape[0])


def detection_function(graphdef: nnx.GraphDef, layout: pns.TileLayout,
                       settings: DetectionSettings):
    """``run(params, image, K, queries) -> {mode: outputs}`` (pure; jit it), for one layout.

    ``image`` [H, W, 3] (uint8 or float in [0, 255]), ``K`` [3, 3] float32. Per score mode,
    with D = ``max_detections``: ``boxes`` [D, 4] (xyxy image pixels), ``scores`` [D],
    ``valid`` [D] (kept by NMS above the threshold, best first), ``object`` [D] (row of the
    queries), ``best_score`` (the best candidate's score, -inf when none survived the edge
    filter), ``template_scores`` [D, T] (cosine with each template of the detection's object)
    and, with ``generate_objects``, ``poses`` [D, K, 4, 4], ``pose_scores`` [D, K].
    """
    s = settings
    modes = tuple(dict.fromkeys(s.score_modes))

    def per_object(params, tiles, prior, bank):
        model = nnx.merge(graphdef, params)
        n = tiles.shape[0]
        out = model(tiles, jnp.broadcast_to(prior, (n, *prior.shape)), bank)
        # Amodal boxes (an object cut by the image border keeps its whole box): object
        # generation's depth rule needs the whole box, so boxes are not clipped to the image.
        boxes = pns.tile_boxes_to_image(out["boxes"], layout, clip=False).reshape(-1, 4)
        edge = pns.interior_edge_mask(out["boxes"], layout)  # [N, P]
        emb = out["embeddings"].reshape(-1, out["embeddings"].shape[-1])
        res = {}
        for mode in modes:
            scores = detection_scores(out["presence_logits"], out["detection_logits"], mode)
            scores = jnp.where(edge, -jnp.inf, scores).reshape(-1)
            top_scores, top = jax.lax.top_k(scores, min(s.candidates_per_object, scores.size))
            res[mode] = (boxes[top], top_scores, emb[top])
        return res

    def finish(boxes, scores, emb, K, queries: ObjectQueries):
        c = scores.shape[1]  # scores [O, C]
        keep, ok = nms(boxes.reshape(-1, 4), scores.reshape(-1), s.nms_iou, s.max_detections,
                       s.score_threshold)
        obj = keep // c
        det_boxes = boxes.reshape(-1, 4)[keep]
        det_emb = emb.reshape(-1, emb.shape[-1])[keep]
        tmpl = orientation_scores(det_emb[:, None], queries.template_bank[obj])[:, 0]  # [D, T]
        out = {"boxes": det_boxes, "scores": scores.reshape(-1)[keep], "valid": ok,
               "best_score": jnp.max(scores), "object": obj, "template_scores": tmpl}
        if s.generate_objects:
            rot = queries.template_rotations
            rot = rot[obj] if rot.ndim == 4 else jnp.broadcast_to(rot, (len(obj), *rot.shape))
            poses, pose_scores, _ = jax.vmap(
                lambda b, t, r, p: single_view_hypotheses(b, K, t, r, p, s.num_hypotheses,
                                                          s.min_angle_deg))(
                    det_boxes, tmpl, rot, queries.points[obj])
            out.update(poses=poses, pose_scores=pose_scores)
        return out

    def run(params, image, K, queries: ObjectQueries):
        if s.generate_objects and queries.points is None:
            raise ValueError("generate_objects needs model points: pass ObjectQueries.points")
        tiles = pns.extract_tiles(image, layout)
        cands = jax.lax.map(lambda x: per_object(params, tiles, x[0], x[1]),
                            (queries.prior_tokens, queries.template_bank))
        return {mode: finish(*cands[mode], K, queries) for mode in modes}

    return run


def _layout(image_hw, tile_size, scales, num_scales, object_sizes) -> pns.TileLayout:
    if scales:
        return pns.tile_layout(image_hw, tile_size, scales)
    return pns.plan_layout(image_hw, tile_size, object_sizes=object_sizes, num_scales=num_scales)


@functools.lru_cache(maxsize=32)
def _jitted(graphdef, settings, image_hw, tile_size, scales, num_scales, object_sizes,
            jit_items):
    """The jitted :func:`detection_function` of one model structure (``GraphDef``s compare by
    value), settings and tile layout, shared by every :class:`FullImageDetector`."""
    layout = _layout(image_hw, tile_size, scales, num_scales, object_sizes)
    return jax.jit(detection_function(graphdef, layout, settings), **dict(jit_items))


jax.tree_util.register_dataclass(
    ObjectQueries, data_fields=["prior_tokens", "template_bank", "template_rotations", "points"],
    meta_fields=[])


class FullImageDetector:
    """The jitted :func:`detection_function` per image size, built once (module docstring).

    ``scales``: pan-and-scan scales; None: planned per image by ``pan_and_scan.plan_layout``
    (``num_scales`` of them, or the fewest that cover the expected object sizes).
    ``jit_kwargs`` go to ``jax.jit`` (the training evaluation replicates the outputs over its
    device mesh). The jitted functions are shared by every detector of the process with the
    same model structure, tiles and settings (:func:`_jitted`): a new detector of the same
    model (another ``infer`` run, adapt's val then test scenes) compiles nothing again.
    """

    def __init__(self, graphdef: nnx.GraphDef, tile_size: int, settings: DetectionSettings, *,
                 num_scales: int | None = None, scales: Sequence[float] | None = None,
                 jit_kwargs: dict | None = None):
        self.graphdef = graphdef
        self.tile_size = int(tile_size)
        self.settings = settings
        self.num_scales = None if num_scales is None else int(num_scales)
        self.scales = None if scales is None else tuple(float(v) for v in scales)
        self.jit_kwargs = dict(jit_kwargs or {})

    def layout(self, image_hw: tuple[int, int],
               object_sizes: tuple[float, float] | None = None) -> pns.TileLayout:
        """The tiles of an image: ``scales`` if given, else planned for the objects' expected
        sizes in pixels (``pan_and_scan.plan_layout``; None: 64 px to the whole image)."""
        return _layout(image_hw, self.tile_size, self.scales, self.num_scales, object_sizes)

    def compiled(self, image_hw: tuple[int, int],
                 object_sizes: tuple[float, float] | None = None):
        """The jitted function for one image size and expected object sizes, built once (the
        layout is planned only then, not per image)."""
        return _jitted(self.graphdef, self.settings, (int(image_hw[0]), int(image_hw[1])),
                       self.tile_size, self.scales, self.num_scales,
                       None if object_sizes is None else tuple(map(float, object_sizes)),
                       tuple(sorted(self.jit_kwargs.items())))

    def __call__(self, params, image, K, queries: ObjectQueries,
                 object_sizes: tuple[float, float] | None = None) -> dict[str, dict[str, Array]]:
        """:func:`detection_function`'s outputs for one image [H, W, 3]."""
        return self.compiled(tuple(np.shape(image)[:2]), object_sizes)(params, image, K, queries)
