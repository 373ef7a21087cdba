"""3PT inference: ``load`` the trained models once, then ``run_scene`` (see :mod:`infer.api`)."""

from infer.api import Camera, Models, load, run_scene

__all__ = ["Camera", "Models", "load", "run_scene"]
