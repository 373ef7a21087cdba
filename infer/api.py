"""The public inference API: load the models once, then ``run_scene`` on any number of scenes.

    import infer
    models = infer.load("runs/demo/train")                 # a training run directory
    objects = models.onboard({1: "bracket.ply"}, units="mm")  # cached on disk per mesh
    for image, K in camera_stream:
        instances = infer.run_scene([image], [K], objects, models)

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

from infer.checkpoint import load_detector
from infer.detect import SceneDetector
from infer.masks import PoseRenderer
from infer.onboarding import ONBOARD_TEMPLATES, OnboardedObject, Onboarder
from infer.scene import Instances, find_instances
from threept_jax.data.bop import Camera
from threept_jax.geometry.validate import validate_intrinsics
from threept_jax.models.configs import DetectorConfig
from threept_jax.models.detector import Detector
from threept_jax.render import Mesh

DEFAULT_CACHE = pathlib.Path(os.environ.get("THREEPT_CACHE", "~/.cache/threept_jax")).expanduser()

__all__ = ["Camera", "Models", "load", "run_scene", "DEFAULT_CACHE"]


@dataclasses.dataclass
class Models:
    """The trained networks of a run, loaded once, and what is built from them per object set.

    Attributes:
      detector: the 3PT-D network; config: its ``DetectorConfig``; step: the checkpoint step.
      onboarder: turns meshes into :class:`OnboardedObject` (cached on disk under the model).
    """

    detector: Detector
    config: DetectorConfig
    step: int
    onboarder: Onboarder
    _scene_detectors: dict = dataclasses.field(default_factory=dict, repr=False)
    _pose_renderers: dict = dataclasses.field(default_factory=dict, repr=False)

    def onboard(self, meshes: Mapping[int, str | os.PathLike | Mesh], units: str = "mm"
                ) -> list[OnboardedObject]:
        """Onboard ``{obj_id: mesh file or Mesh}`` (mesh units checked on load)."""
        return self.onboarder.onboard_all(dict(meshes), units=units)

    def scene_detector(self, objects: Sequence[OnboardedObject], **options: Any) -> SceneDetector:
        """The :class:`SceneDetector` of these objects and options, built once and reused, so
        its compiled functions (one per image size) survive across calls."""
        key = (tuple(o.obj_id for o in objects),
               tuple(sorted((k, tuple(np.ravel(v)) if np.ndim(v) else v)
                            for k, v in options.items())))
        if key not in self._scene_detectors:
            self._scene_detectors[key] = SceneDetector(self.detector, self.config, objects,
                                                       **options)
        return self._scene_detectors[key]

    def pose_renderer(self, objects: Sequence[OnboardedObject]) -> PoseRenderer:
        """The mask renderer of these objects, built once (its meshes are prepared once)."""
        key = tuple(o.obj_id for o in objects)
        if key not in self._pose_renderers:
            self._pose_renderers[key] = PoseRenderer(objects)
        return self._pose_renderers[key]


def load(workdir, step: int | str = "best", *, cache_dir=DEFAULT_CACHE,
         num_templates: int = ONBOARD_TEMPLATES) -> Models:
    """Load a training run's detector (``step``: ``"best"``, ``"latest"`` or a number) and an
    onboarder whose cache lives under ``cache_dir/onboarding`` (None: no disk cache)."""
    model, cfg, step = load_detector(workdir, step)
    model_id = f"{pathlib.Path(workdir).resolve()}@{step}"
    cache = None if cache_dir is None else pathlib.Path(cache_dir) / "onboarding"
    return Models(model, cfg, step, Onboarder(model, cfg, model_id, cache_dir=cache,
                                              num_templates=num_templates))


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
              min_views: int = 3, **detector_options: Any) -> Instances:
    """Every instance of the objects in a scene seen by one or several calibrated RGB views.

    Args:
      images: V uint8 RGB images [H, W, 3].
      cameras: V cameras: a ``Camera`` (K [3, 3] in pixels of that image, or of the image
        size ``calibration_hw`` (H, W) it was calibrated at, then rescaled to the image; for
        several views ``T_cam_world`` [4, 4], world -> camera, mm), or a bare K.
      objects: onboarded objects, or ``{obj_id: mesh}`` to onboard (``units`` of the meshes).
      models: from :func:`load`.
      with_masks, min_views: see :func:`infer.scene.find_instances`.
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
    detector = models.scene_detector(objects, **detector_options)
    renderer = models.pose_renderer(objects) if with_masks else None
    return find_instances(detector, images, Ks, T_cam_world, with_masks=with_masks,
                          min_views=min_views, renderer=renderer)
