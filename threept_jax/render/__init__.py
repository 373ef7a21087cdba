"""Rendering: one interface, two backends (a JAX rasterizer, Mitsuba 3). docs/design.md section 4.

``render(mesh, T_cam_obj [..., 4, 4], K [..., 3, 3], hw=(H, W), outputs=(...), backend="jax")``
returns a dict of arrays [..., H, W, ...]:

* ``depth`` z in mm (0 = background), ``mask`` bool, ``xyz`` object coordinates in mm,
* ``normal`` unit interpolated vertex normal in the camera frame,
* ``rgb`` float in [0, 1]: texture, vertex colour or neutral grey, with headlight Lambert
  shading (``ambient`` + (1 - ``ambient``) |n . v|),
* ``edge`` bool: silhouette, depth (off the pixel's face plane) and crease (face normal)
  discontinuities, on the occluding side,
* ``face_id`` int32 (-1 = background).

Conventions (``threept_jax.geometry.camera``): millimetres, OpenCV camera axes, ``T_cam_obj``
maps object points into the camera, K maps to pixel centres, so pixel (i, j) is sampled exactly
at (u, v) = (i, j). Any upper-triangular K works (fx != fy, skew, off-centre principal point).
Surfaces at z <= ``near`` are clipped.

Backends: ``"jax"`` (:mod:`threept_jax.render.raster`, jit/vmap-able, returns jax arrays) and
``"mitsuba"`` (:mod:`threept_jax.render.mitsuba_backend`, returns NumPy arrays). A
:class:`Renderer` keeps the backend's prepared mesh (padded device arrays, or a Mitsuba scene)
between calls; ``render`` with a plain :class:`Mesh` builds a throwaway one.
"""

from __future__ import annotations

from typing import Any, Sequence

import jax
import numpy as np

from threept_jax.geometry.validate import validate_intrinsics, validate_rigid
from threept_jax.render.crop import crop_and_resize
from threept_jax.render.mesh import (
    Mesh,
    RasterMesh,
    bucket_size,
    decimate,
    load_mesh,
    prepare_mesh,
    subdivide,
    to_raster_mesh,
)
from threept_jax.render.raster import ALL_OUTPUTS, DEFAULT_OUTPUTS, edges_from_geometry

BACKENDS = ("jax", "mitsuba")

__all__ = [
    "BACKENDS",
    "Mesh",
    "RasterMesh",
    "Renderer",
    "bucket_size",
    "check_pose_and_intrinsics",
    "crop_and_resize",
    "decimate",
    "edges_from_geometry",
    "load_mesh",
    "prepare_mesh",
    "render",
    "subdivide",
    "to_raster_mesh",
]


def _concrete(x) -> np.ndarray | None:
    """NumPy value of x, or None when x is traced (checks then happen at trace time only)."""
    if isinstance(x, jax.core.Tracer):
        return None
    return np.asarray(x, np.float64)


def check_pose_and_intrinsics(T: Any, K: Any, what: str = "T_cam_obj") -> None:
    """Raise a clear ValueError unless T [..., 4, 4] is rigid and K [..., 3, 3] is a valid
    pinhole matrix (:mod:`threept_jax.geometry.validate`). Traced values pass: they are
    checked where they were concrete."""
    Tn = _concrete(T)
    if Tn is not None:
        validate_rigid(Tn, what)
    Kn = None if K is None else _concrete(K)
    if Kn is not None:
        validate_intrinsics(Kn, "K")


class Renderer:
    """A mesh prepared for one backend, reused across calls (Mitsuba scene, padded arrays).

    Args:
      mesh: a :class:`Mesh` (or a :class:`RasterMesh` for the JAX backend).
      backend: "jax" or "mitsuba".
      variant: Mitsuba variant (default: ``cuda_ad_rgb`` with a GPU, else ``llvm_ad_rgb``).
      cull_backfaces: JAX backend only; None culls when the mesh is closed.
    """

    def __init__(
        self,
        mesh: Mesh | RasterMesh,
        backend: str = "jax",
        *,
        variant: str | None = None,
        cull_backfaces: bool | None = None,
    ):
        if backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
        self.backend = backend
        if backend == "jax":
            self.mesh = mesh if isinstance(mesh, RasterMesh) else to_raster_mesh(
                mesh, cull_backfaces=cull_backfaces
            )
        else:
            if not isinstance(mesh, Mesh):
                raise TypeError("the mitsuba backend needs a Mesh, not a RasterMesh")
            from threept_jax.render.mitsuba_backend import MitsubaRenderer

            self.mesh = mesh
            self._mitsuba = MitsubaRenderer(mesh, variant=variant)

    def render(
        self,
        T_cam_obj: Any,
        K: Any,
        hw: tuple[int, int],
        outputs: Sequence[str] = DEFAULT_OUTPUTS,
        **options: Any,
    ) -> dict[str, Any]:
        """Render views T_cam_obj [..., 4, 4] with K [..., 3, 3] (or one K [3, 3] for all).

        ``options``: ``near`` (mm, default 1), ``ambient`` (0.3), ``edge_depth_fraction``
        (0.02 of the diameter), ``edge_angle_deg`` (45); JAX only: ``tile``, ``chunk`` (see
        :func:`threept_jax.render.raster.render`).
        """
        check_pose_and_intrinsics(T_cam_obj, K)
        bad = [o for o in outputs if o not in ALL_OUTPUTS]
        if bad:
            raise ValueError(f"unknown outputs {bad}; choose from {ALL_OUTPUTS}")
        if self.backend == "jax":
            from threept_jax.render import raster

            return raster.render(self.mesh, T_cam_obj, K, hw, outputs, **options)
        return self._mitsuba.render(
            np.asarray(T_cam_obj), np.asarray(K), hw, outputs, **options
        )


def render(
    mesh: Mesh | RasterMesh | Renderer,
    T_cam_obj: Any,
    K: Any,
    hw: tuple[int, int],
    outputs: Sequence[str] = DEFAULT_OUTPUTS,
    backend: str = "jax",
    **options: Any,
) -> dict[str, Any]:
    """Render ``mesh`` at poses T_cam_obj [..., 4, 4] with intrinsics K [..., 3, 3].

    See the module docstring for outputs and conventions. Pass a :class:`Renderer` to reuse a
    prepared mesh across calls (its own backend is used).
    """
    if isinstance(mesh, Renderer):
        return mesh.render(T_cam_obj, K, hw, outputs, **options)
    return Renderer(mesh, backend).render(T_cam_obj, K, hw, outputs, **options)
