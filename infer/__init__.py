"""3PT inference: ``load`` the trained models once, then ``run_scene``, ``refine`` or ``track`` (see
:mod:`infer.api`)."""

from infer.api import Camera, Models, TrackedFrame, load, refine, run_scene, track

__all__ = ["Camera", "Models", "TrackedFrame", "load", "refine", "run_scene", "track"]
