"""3PT inference: ``load`` the trained models once, then ``run_scene`` or ``refine`` (see
:mod:`infer.api`)."""

from infer.api import Camera, Models, load, refine, run_scene

__all__ = ["Camera", "Models", "load", "refine", "run_scene"]
