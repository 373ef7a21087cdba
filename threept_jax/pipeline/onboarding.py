"""Object onboarding renders: an object's views at given rotations with the bank camera.

3PT-D's object tower (DESIGN.md section 1.1) consumes, per object, 12 prior renders and a bank
of templates at rotations covering SO(3). Training (``datagen``) and inference onboarding both
render them with :func:`render_object_views`, so the two see identical images.

The camera is the render-bank camera of :mod:`threept_jax.data.banks`: an object-centred view
from ``DISTANCE_FACTOR`` bounding-sphere radii, with a focal length that makes the sphere span
``FILL`` of the image side (``banks.render_camera``), and poses ``T_cam_obj = [R | (0, 0, d) -
R c]`` (``banks.render_pose``). Images are the renderer's shaded ``rgb`` output (texture,
vertex colours or neutral grey under headlight Lambert shading; ``threept_jax.render``) on a
black background.

Shapes: N rotations, h w render size.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from threept_jax.data import banks
from threept_jax.render import Mesh, Renderer

__all__ = ["object_camera", "render_object_views"]


def object_camera(
    mesh: Mesh, hw: tuple[int, int], sphere: tuple[Any, float] | None = None
) -> tuple[np.ndarray, np.ndarray, float]:
    """(K [3, 3], sphere centre c [3], distance d) of the bank camera for ``mesh`` at ``hw``.

    ``sphere`` (centre [3], radius) defaults to ``banks.bounding_sphere`` of the mesh vertices;
    pass the full-resolution model's sphere when rendering a decimated copy, so the camera is
    the one recorded in the bank.
    """
    if sphere is None:
        centre, radius = banks.bounding_sphere(np.asarray(mesh.vertices, np.float64))
    else:
        centre, radius = np.asarray(sphere[0], np.float64).reshape(3), float(sphere[1])
    K, distance = banks.render_camera(hw, radius)
    return K, centre, distance


def render_object_views(
    mesh: Mesh | Renderer,
    rotations: Any,
    hw: tuple[int, int],
    backend: str = "jax",
    *,
    sphere: tuple[Any, float] | None = None,
    chunk: int = 64,
    ambient: float = 0.3,
) -> np.ndarray:
    """uint8 [N, h, w, 3] renders of ``mesh`` at R_cam_obj ``rotations`` [N, 3, 3].

    Args:
      mesh: a :class:`Mesh` (millimetres), or a :class:`Renderer` already built for it (its
        backend is used).
      rotations: [N, 3, 3] R_cam_obj, e.g. ``grids.prior_view_rotations()`` or
        ``grids.super_fibonacci_rotations(T)``.
      hw: (h, w) render size.
      backend: "jax" or "mitsuba" (ignored when a Renderer is given).
      sphere: (centre [3], radius) of the bank camera (see :func:`object_camera`).
      chunk: views rendered per call; every call renders exactly ``chunk`` views (the last
        one padded), so the JAX backend compiles once per mesh bucket and image size whatever
        N is, and memory stays bounded. Lower it for a handful of views.
      ambient: ambient term of the headlight shading.

    Background pixels are 0. Colours are ``round(255 * rgb)``.
    """
    R = np.asarray(rotations, np.float64)
    if R.ndim != 3 or R.shape[1:] != (3, 3):
        raise ValueError(f"rotations must be [N, 3, 3], got {R.shape}")
    if chunk < 1:
        raise ValueError(f"chunk must be >= 1, got {chunk}")
    h, w = int(hw[0]), int(hw[1])
    renderer = mesh if isinstance(mesh, Renderer) else Renderer(mesh, backend)
    if sphere is None:
        sphere = banks.bounding_sphere(np.asarray(_mesh_of(renderer, mesh).vertices, np.float64))
    K, distance = banks.render_camera((h, w), float(sphere[1]))
    T = banks.render_pose(R, np.asarray(sphere[0], np.float64), distance)
    n = len(T)
    out = np.zeros((n, h, w, 3), np.uint8)
    for start in range(0, n, chunk):
        part = T[start : start + chunk]
        k = len(part)
        if k < chunk:  # pad with copies so every call has the same shape
            part = np.concatenate([part, np.repeat(part[-1:], chunk - k, 0)])
        rgb = renderer.render(part.astype(np.float32), K.astype(np.float32), (h, w), ("rgb",),
                              ambient=ambient)["rgb"]
        rgb = np.asarray(rgb, np.float32)[:k]
        out[start : start + k] = np.clip(np.round(rgb * 255.0), 0, 255).astype(np.uint8)
    return out


def _mesh_of(renderer: Renderer, given: Any) -> Mesh:
    """The Mesh behind a Renderer (for its bounding sphere)."""
    if isinstance(given, Mesh):
        return given
    if isinstance(renderer.mesh, Mesh):
        return renderer.mesh
    raise ValueError(
        "a Renderer built from a RasterMesh does not know its vertices; pass sphere=(centre, "
        "radius) of the model (banks.bounding_sphere of its vertices)"
    )
