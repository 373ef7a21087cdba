"""The public inference API: load the models once, then ``run_scene`` on any number of scenes.

    import infer
    models = infer.load()  # templates detector + default refiner; or infer.load("runs/demo/train", refiner=...)
    objects = models.onboard({1: "bracket.ply"}, units="mm")  # cached on disk per mesh
    for image, K in camera_stream:
        instances = infer.run_scene([image], [K], objects, models)

With a refiner (``refiner=``, a 3PT-R training run), ``run_scene`` refines every instance by
render-and-compare (:class:`infer.refine.SceneRefiner`) and its masks come from the refiner;
``refine`` refines poses from any other method without the detector
(``infer.load(refiner="runs/refiner")``).

``run_scene`` takes one view or several (then each camera is a ``Camera`` with ``T_cam_world``)
and returns :class:`infer.scene.Instance` records (object id, pose ``T_world_obj``, score,
hypotheses, per-view boxes and masks). The stages stay callable on their own:
:class:`infer.onboarding.Onboarder`, :class:`infer.detect.SceneDetector` (detection and
single-view object generation), :func:`infer.scene.find_instances` (multi-view fusion and
masks).
"""

from __future__ import annotations

import dataclasses
import os
import pathlib
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from infer.cell_detect import SCORE_THRESHOLD as CELL_SCORE_THRESHOLD
from infer.cell_detect import CellDetector
from infer.checkpoint import load_detector, load_refiner
from infer.contour_refine import ContourRefiner
from infer.detect import SCORE_THRESHOLD as DETECTOR_SCORE_THRESHOLD
from infer.detect import SceneDetector
from infer.masks import PoseRenderer
from infer.onboarding import ONBOARD_TEMPLATES, OnboardedObject, Onboarder
from infer.refine import RefinedPose, SceneRefiner, refine_objects
from infer.scene import Instances, find_instances, render_masks
from infer.shape_detect import SCORE_THRESHOLD as TEMPLATES_SCORE_THRESHOLD
from infer.shape_detect import ShapeSearchDetector, load_score_weights
from infer.shipped import CONTOUR, default_refiner, shipped
from threept_jax.data import dense_run
from threept_jax.data.bop import Camera
from threept_jax.geometry.validate import validate_intrinsics
from threept_jax.models.configs import DetectorConfig, RefinerConfig
from threept_jax.models.detector import Detector
from threept_jax.models.refiner import Refiner
from threept_jax.pipeline.contour import ContourSettings
from threept_jax.pipeline.refinement import RefineSettings
from threept_jax.pipeline.shape_search import ShapeSearchSettings
from threept_jax.render import Mesh

DEFAULT_CACHE = pathlib.Path(os.environ.get("THREEPT_CACHE", "~/.cache/threept_jax")).expanduser()

__all__ = ["Camera", "Models", "TrackedFrame", "load", "run_scene", "refine", "track",
           "DEFAULT_CACHE", "DETECTORS"]

#: The detectors ``load(detector=...)`` and the commands' ``--detector`` name: "3pt", the
#: 3PT-D network (a training run, or the shipped one); "templates", the training-free shape
#: search from the CAD model alone (:mod:`infer.shape_detect`); "cell", a cell's own trained
#: dense detector (:mod:`infer.cell_detect`, ``python -m train.cell_detector``).
DETECTORS = ("3pt", "templates", "cell")
#: Each detector's default score threshold: each scores a probability, calibrated on different
#: data (a noisy featureless image's template candidates score up to 0.35).
SCORE_THRESHOLDS = {"3pt": DETECTOR_SCORE_THRESHOLD, "templates": TEMPLATES_SCORE_THRESHOLD,
                    "cell": CELL_SCORE_THRESHOLD}


def default_detector(workdir) -> str:
    """The detector :func:`load` picks when none is named: the cell detector for a cell
    detector's run, 3PT-D for another run directory, else the training-free templates
    detector."""
    if workdir is None:
        return "templates"
    return "cell" if (pathlib.Path(workdir) / dense_run.RUN_FILE).is_file() else "3pt"


@dataclasses.dataclass
class Models:
    """The trained networks, loaded once, and what is built from them per object set.

    Attributes:
      detector: the 3PT-D network (None when only a refiner was loaded, or with the
        training-free detector); config: its ``DetectorConfig``; step: its checkpoint step.
      onboarder: turns meshes into :class:`OnboardedObject` (cached on disk under the model).
      refiner: the 3PT-R network, with ``refiner_config``, ``refiner_step`` and
        ``refine_settings`` (the options it was trained with); or the training-free contour
        refiner's :class:`~threept_jax.pipeline.contour.ContourSettings`
        (``load(refiner="contour")``, :class:`infer.contour_refine.ContourRefiner`); None: no
        refinement.
      shape_search: the training-free detector's settings (``load(detector="templates")``,
        :class:`infer.shape_detect.ShapeSearchDetector`), None with 3PT-D; templates_score: its
        per-part score weights of a cell's calibration (``load(templates_score=FILE)``), None:
        the shared ones; templates_verifier: the templates detector's ``verifier`` argument
        (``"shipped"``, None with ``load(templates_verifier=False)``).
    """

    detector: Detector | None
    config: DetectorConfig | None
    step: int | None
    onboarder: Onboarder | None
    refiner: Refiner | ContourSettings | None = None
    refiner_config: RefinerConfig | None = None
    refiner_step: int | None = None
    refine_settings: RefineSettings | None = None
    cache_dir: pathlib.Path | None = None
    shape_search: ShapeSearchSettings | None = None
    templates_score: dict[int, tuple[float, ...]] | None = None
    templates_verifier: str | None = "shipped"
    cell: tuple[Any, list[int]] | None = None
    # Per-object-set caches; not init fields, so a dataclasses.replace starts empty ones.
    _scene_detectors: dict = dataclasses.field(default_factory=dict, repr=False, init=False)
    _pose_renderers: dict = dataclasses.field(default_factory=dict, repr=False, init=False)
    _scene_refiners: dict = dataclasses.field(default_factory=dict, repr=False, init=False)

    def onboard(self, meshes: Mapping[int, str | os.PathLike | Mesh], units: str = "mm"
                ) -> list[OnboardedObject]:
        """Onboard ``{obj_id: mesh file or Mesh}`` (mesh units checked on load). The
        training-free detector needs only the meshes (and builds its templates when it first
        sees an object set)."""
        if self.shape_search is not None:  # the templates and cell detectors need no bank
            return refine_objects(dict(meshes), units=units)
        if self.onboarder is None:
            raise ValueError("onboarding needs a detector: infer.load(DETECTOR_RUN, ...)")
        return self.onboarder.onboard_all(dict(meshes), units=units)

    def scene_refiner(self, objects: Sequence) -> SceneRefiner | ContourRefiner:
        """The refiner of these objects, built once (meshes prepared once, its compiled loop
        kept across calls): a :class:`SceneRefiner` for a 3PT-R network, a
        :class:`ContourRefiner` for the contour refiner."""
        if self.refiner is None:
            raise ValueError("no refiner loaded: pass refiner=<a 3PT-R training run> or "
                             "refiner='contour' (no training) to infer.load")
        key = tuple(o.obj_id for o in objects)
        if key not in self._scene_refiners:
            if isinstance(self.refiner, ContourSettings):
                cache = None if self.cache_dir is None else self.cache_dir / "contours"
                self._scene_refiners[key] = ContourRefiner(objects, self.refiner, cache)
            else:
                self._scene_refiners[key] = SceneRefiner(self.refiner, self.refiner_config,
                                                         self.refine_settings, objects)
        return self._scene_refiners[key]

    def scene_detector(self, objects: Sequence[OnboardedObject], **options: Any
                       ) -> SceneDetector | ShapeSearchDetector | CellDetector:
        """The detector of these objects and options, built once and reused, so its compiled
        functions (one per image size) survive across calls: a :class:`SceneDetector` (3PT-D)
        or, with ``load(detector="templates")``, a :class:`ShapeSearchDetector`, or with a cell
        detector's run a :class:`CellDetector` (options ``depth_range``, ``score_threshold``,
        ``max_detections``)."""
        key = (tuple(o.obj_id for o in objects),
               tuple(sorted((k, tuple(np.ravel(v)) if np.ndim(v) else v)
                            for k, v in options.items())))
        if key not in self._scene_detectors:
            if self.shape_search is not None:
                if options.pop("num_scales", None) is not None:
                    raise ValueError("num_scales is a 3PT-D option (pan-and-scan); the templates "
                                     "and cell detectors search the whole image: drop it")
                cache = None if self.cache_dir is None else self.cache_dir / "contours"
            if self.cell is not None:
                self._scene_detectors[key] = CellDetector(
                    *self.cell, objects, settings=self.shape_search, cache_dir=cache,
                    score_weights=self.templates_score, verifier=self.templates_verifier,
                    **options)
            elif self.shape_search is not None:
                self._scene_detectors[key] = ShapeSearchDetector(
                    objects, settings=self.shape_search, cache_dir=cache,
                    score_weights=self.templates_score, verifier=self.templates_verifier,
                    **options)
            else:
                self._scene_detectors[key] = SceneDetector(self.detector, self.config, objects,
                                                           **options)
        return self._scene_detectors[key]

    def pose_renderer(self, objects: Sequence[OnboardedObject]) -> PoseRenderer:
        """The mask renderer of these objects, built once (its meshes are prepared once)."""
        key = tuple(o.obj_id for o in objects)
        if key not in self._pose_renderers:
            self._pose_renderers[key] = PoseRenderer(objects)
        return self._pose_renderers[key]


def load(workdir=None, step: int | str = "best", *, refiner=None,
         refiner_step: int | str = "best", cache_dir=DEFAULT_CACHE,
         num_templates: int = ONBOARD_TEMPLATES, detector: str | None = None,
         templates_score=None, templates_verifier: bool | None = None) -> Models:
    """The models inference runs: a detector and a refiner.

    ``detector``: ``"templates"``, the training-free detector
    (:class:`infer.shape_detect.ShapeSearchDetector`: no network, the parts found from their
    CAD models alone; the default, since it finds parts on held-out cell scenes where the
    shipped 3PT-D does not: docs/benchmarks.md, "Training-free detection"), or ``"3pt"``, a
    3PT-D network: the detector training run or exported model ``workdir`` (``step``:
    ``"best"``, ``"latest"`` or a number; a ``workdir`` implies ``"3pt"``), else the shipped
    one (``models/``, :mod:`infer.shipped`), with an onboarder whose cache lives under
    ``cache_dir/onboarding`` (None: no disk cache); or ``"cell"``, a cell's own trained
    detector (:class:`infer.cell_detect.CellDetector`), the run ``workdir`` of ``python -m
    train.cell_detector`` (a ``workdir`` holding one implies ``"cell"``), with the default
    refiner when none is named.

    ``refiner``: a 3PT-R training run (``refiner_step``), ``"contour"`` (the training-free
    contour refiner, :mod:`infer.contour_refine`, its contours cached under
    ``cache_dir/contours``), or None: with no ``workdir`` the default refiner
    (:func:`infer.shipped.default_refiner`: the shipped 3PT-R when one ships, else the contour
    refiner); with a ``workdir``, none. A missing or damaged shipped file raises an error
    naming it and how to restore it. Drop a refiner with ``dataclasses.replace(models,
    refiner=None)``.

    ``templates_score``: a cell's calibration of the templates detector's score (the file
    ``python -m train.templates_score --cell DATA`` writes: a logistic model per part, fitted
    on scenes of the cell's own parts; docs/inference.md, "Which detector"), or None: the
    shared weights fitted on cells of other parts.

    ``templates_verifier``: whether the shipped learned verifier corrects the templates'
    score (``models/templates-verifier``, its card says what it does and costs): None (the
    default) or True: yes, with the shared score or a cell's ``templates_score``; False: no
    (docs/inference.md, "The learned verifier"). True with 3PT-D is refused."""
    if detector is None:
        detector = default_detector(workdir)
    if detector not in DETECTORS:
        raise ValueError(f"detector must be one of {', '.join(DETECTORS)}, got {detector!r}")
    if detector == "templates" and workdir is not None:
        raise ValueError("a detector run (workdir) is 3PT-D: pass detector='3pt', or drop "
                         "workdir for the training-free templates detector")
    if detector == "cell" and workdir is None:
        raise ValueError("the cell detector is trained per cell: pass its run "
                         "(python -m train.cell_detector --workdir DIR) as workdir")
    if workdir is None or detector == "cell":
        refiner = refiner or default_refiner()
        if detector == "3pt":
            workdir = shipped("detector")
    cache = None if cache_dir is None else pathlib.Path(cache_dir)
    models = Models(None, None, None, None, cache_dir=cache)
    if templates_score is not None and detector == "3pt":
        raise ValueError("templates_score calibrates the templates detector (alone or in the "
                         "cell detector); 3PT-D scores with its network: drop it or pass "
                         "detector='templates'")
    if templates_verifier and detector == "3pt":
        raise ValueError("templates_verifier checks the templates detector's candidates (alone "
                         "or in the cell detector); 3PT-D scores with its network: drop it or "
                         "pass detector='templates'")
    if detector in ("cell", "templates"):
        models.shape_search = ShapeSearchSettings()
        models.templates_verifier = None if templates_verifier is False else "shipped"
        if templates_score is not None:
            models.templates_score = load_score_weights(templates_score)
    if detector == "cell":
        network, class_ids, _ = dense_run.load(workdir)
        models.cell = (network, class_ids)
    elif detector == "3pt":
        model, cfg, step = load_detector(workdir, step)
        model_id = f"{pathlib.Path(workdir).resolve()}@{step}"
        models = Models(model, cfg, step, Onboarder(
            model, cfg, model_id, cache_dir=None if cache is None else cache / "onboarding",
            num_templates=num_templates), cache_dir=cache)
    if str(refiner) == CONTOUR:
        models.refiner = ContourSettings()
    elif refiner is not None:
        net, rcfg, rstep, settings = load_refiner(refiner, refiner_step)
        models = dataclasses.replace(models, refiner=net, refiner_config=rcfg,
                                     refiner_step=rstep, refine_settings=settings)
    return models


def prepare_views(images: Sequence[np.ndarray], cameras: Sequence[Camera | np.ndarray]
                  ) -> tuple[list[np.ndarray], np.ndarray | None]:
    """The checked cameras of a scene (``run_scene`` calls it; CLIs call it before loading
    models): Ks [V] in pixels of each image (rescaled from a camera's ``calibration_hw``) and
    T_cam_world [V, 4, 4] (None when no camera carries one)."""
    if len(cameras) != len(images):
        raise ValueError(f"{len(images)} images but {len(cameras)} cameras: give one per image")
    cams = [c if isinstance(c, Camera) else Camera(np.asarray(c)) for c in cameras]
    Ks = [validate_intrinsics(c.K, f"camera {v} K", image_hw=np.shape(img)[:2],
                              calibration_hw=c.calibration_hw)
          for v, (img, c) in enumerate(zip(images, cams))]
    Ts = [c.T_cam_world for c in cams]
    if all(t is None for t in Ts):
        return Ks, None
    if any(t is None for t in Ts):
        raise ValueError("either every camera carries T_cam_world (several views of one rig) or "
                         "none does (one view)")
    return Ks, np.stack(Ts).astype(np.float32)


def run_scene(images: Sequence[np.ndarray], cameras: Sequence[Camera | np.ndarray],
              objects: Sequence[OnboardedObject] | Mapping[int, str | os.PathLike | Mesh],
              models: Models, *, units: str = "mm", with_masks: bool = True,
              min_views: int = 3, refine: bool = True, **detector_options: Any) -> Instances:
    """Every instance of the objects in a scene seen by one or several calibrated RGB views.

    Args:
      images: V uint8 RGB images [H, W, 3].
      cameras: V cameras: a ``Camera`` (K [3, 3] in pixels of that image, or of the image
        size ``calibration_hw`` (H, W) it was calibrated at, then rescaled to the image; for
        several views ``T_cam_world`` [4, 4], world -> camera, mm), or a bare K.
      objects: onboarded objects, or ``{obj_id: mesh}`` to onboard (``units`` of the meshes).
      models: from :func:`load`.
      with_masks, min_views: see :func:`infer.scene.find_instances`; with a refiner the masks
        are the silhouettes of the refined poses (each pixel to the best-scored instance
        covering it).
      refine: refine every instance with the loaded refiner (when ``models`` has one).
      detector_options: :class:`SceneDetector` options: ``depth_range`` (zmin, zmax) in mm,
        the objects' distance from the camera when known (pan-and-scan then uses the fewest
        scales that put their projected diameters into the trained size range), ``num_scales``,
        ``score_threshold``, ``max_detections``, ...

    Returns :class:`infer.scene.Instances`, best first, with ``best_score`` (the best
    detection score in any view, kept or not).
    """
    Ks, T_cam_world = prepare_views(images, cameras)  # before onboarding: fail fast
    if isinstance(objects, Mapping):
        objects = models.onboard(objects, units=units)
    objects = list(objects)
    if models.detector is None and models.shape_search is None:
        raise ValueError("run_scene needs a detector: infer.load(DETECTOR_RUN, ...) or "
                         "infer.load(detector='templates'); to refine poses from another "
                         "method use infer.refine")
    detector = models.scene_detector(objects, **detector_options)
    refining = refine and models.refiner is not None
    renderer = models.pose_renderer(objects) if with_masks else None
    instances = find_instances(detector, images, Ks, T_cam_world,
                               with_masks=with_masks and not refining, min_views=min_views,
                               renderer=renderer)
    if not refining or not instances:
        return instances
    refined = models.scene_refiner(objects)(
        images, np.stack(Ks), T_cam_world, [x.obj_id for x in instances],
        [x.hypotheses for x in instances])
    # Masks: the refined poses' silhouettes, each pixel to the best-scored instance, as without
    # a refiner: the refiner's own visibility map gave the pixels to whichever instance was
    # nearest, and low-scored candidates in front of real parts took theirs (segm AP 0.32
    # against 0.60 on held-out T-LESS/ITODD cells with every candidate kept).
    masks = (render_masks(instances, [r.T_world_obj for r in refined], images, Ks,
                          np.eye(4)[None] if T_cam_world is None else T_cam_world, renderer)
             if with_masks else [{} for _ in instances])
    return Instances([dataclasses.replace(x, T_world_obj=r.T_world_obj,
                                          T_world_obj_initial=x.T_world_obj,
                                          refine_score=r.score, masks=m)
                      for x, r, m in zip(instances, refined, masks)], instances.best_score)


def refine(images: Sequence[np.ndarray], cameras: Sequence[Camera | np.ndarray],
           objects: Sequence | Mapping[int, str | os.PathLike | Mesh],
           initial_poses: Sequence[tuple[int, np.ndarray]], models: Models, *,
           units: str = "mm") -> list[RefinedPose]:
    """Refine poses from any method by render-and-compare (3PT-R, or the contour refiner of
    ``infer.load(refiner="contour")``), without the detector.

    Args:
      images, cameras: as :func:`run_scene` (one view, or several with ``T_cam_world``).
      objects: ``{obj_id: mesh file or Mesh}`` (``units``), or onboarded / refine objects.
      initial_poses: ``(obj_id, T_world_obj)`` per instance, ``T_world_obj`` [4, 4] or a set of
        hypotheses [K, 4, 4] best first (world frame; the camera frame for one view), mm.
      models: from :func:`load` with ``refiner=``.

    Returns one :class:`infer.refine.RefinedPose` per instance, in the input order.
    """
    Ks, T_cam_world = prepare_views(images, cameras)
    if isinstance(objects, Mapping):
        objects = refine_objects(objects, units=units)
    refiner = models.scene_refiner(list(objects))
    return refiner(images, np.stack(Ks), T_cam_world, [int(o) for o, _ in initial_poses],
                   [np.asarray(p) for _, p in initial_poses])


@dataclasses.dataclass(frozen=True)
class TrackedFrame:
    """One frame of :func:`track`.

    Attributes:
      index: frame number.
      poses: the refined poses (:class:`infer.refine.RefinedPose`), one per tracked instance
        (after a re-detection, ``history`` holds the pose before and after refinement only).
      redetected: True when the frame ran detection (the first frame without ``init``, or a
        tracked score fell under ``min_score``).
      latency_s: wall time of the frame (refinement, plus detection when redetected).
    """

    index: int
    poses: list
    redetected: bool
    latency_s: float


def track(frames, cameras: Sequence[Camera | np.ndarray], objects: Sequence[OnboardedObject],
          models: Models, init: Sequence[tuple[int, np.ndarray]] | None = None, *,
          min_score: float = 0.0, **detector_options: Any):
    """Track objects through a sequence by render-and-compare refinement (the loaded refiner:
    3PT-R or the contour refiner), re-detecting when confidence drops.

    Each frame (a list of V images, or one image for V = 1) refines every instance from its pose
    in the previous frame (:func:`refine`). When ``init`` is None on the first frame, any
    instance's refiner score falls under ``min_score``, or nothing is tracked (the last
    detection found nothing) and a detector is loaded, the frame runs :func:`run_scene`
    (detection, object generation, refinement) instead and the tracked set is replaced by its
    instances. ``objects`` must be onboarded (``models.onboard``) when re-detection may run.
    Yields a :class:`TrackedFrame` per frame, with its latency.
    """
    import time

    current = None if init is None else [(int(o), np.asarray(T)) for o, T in init]
    for index, frame in enumerate(frames):
        images = [frame] if isinstance(frame, np.ndarray) else list(frame)
        t0 = time.perf_counter()
        poses, redetected = [], False
        if current:
            poses = refine(images, cameras, objects, current, models)
        lost = not current and models.detector is not None  # nothing tracked: look again
        if current is None or lost or any(p.score < min_score for p in poses):
            if models.detector is None:
                raise ValueError("track needs a detector to (re)detect: infer.load(DETECTOR_RUN, "
                                 "refiner=...), or give init poses and min_score=-inf")
            found = run_scene(images, cameras, objects, models, **detector_options)
            redetected = True
            poses = [RefinedPose(x.obj_id, x.T_world_obj, x.refine_score,
                                 np.stack([x.T_world_obj_initial, x.T_world_obj]), x.masks)
                     for x in found]
        current = [(p.obj_id, p.T_world_obj) for p in poses]
        yield TrackedFrame(index, poses, redetected, time.perf_counter() - t0)
