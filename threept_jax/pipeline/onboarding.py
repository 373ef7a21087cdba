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

import pathlib
import warnings
from typing import Any

import numpy as np

from threept_jax.data import banks
from threept_jax.geometry.grids import prior_view_rotations, super_fibonacci_rotations
from threept_jax.geometry.symmetry import Symmetries
from threept_jax.render import Mesh, Renderer, load_mesh, prepare_mesh

__all__ = ["object_camera", "render_bank", "render_object_views"]


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


def render_bank(
    mesh: Mesh | str | pathlib.Path,
    obj_id: int,
    diameter: float,
    symmetries: Symmetries,
    size: int = banks.BANK_SIZE,
    num_templates: int = banks.BANK_TEMPLATES,
    *,
    max_faces: int | None = 20000,
    chunk: int = 64,
    backend: str = "jax",
    on_views=None,
) -> banks.RenderBank:
    """The :class:`~threept_jax.data.banks.RenderBank` of a model (a Mesh in mm, or its file):
    the 12 prior views and ``num_templates`` super-Fibonacci templates, ``size`` x ``size``.

    Datagen stores banks for training (``python -m datagen.banks``); inference onboarding
    renders the same images for unseen objects. ``on_views(n)`` reports progress.
    """
    if not isinstance(mesh, Mesh):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # duplicated BOP faces, open meshes: noise here
            mesh = load_mesh(mesh, models_info=None)
    centre, radius = banks.bounding_sphere(np.asarray(mesh.vertices, np.float64))
    work = mesh if max_faces is None or mesh.num_faces <= max_faces else prepare_mesh(
        mesh, max_faces=max_faces)
    renderer = Renderer(work, backend)
    prior_R = prior_view_rotations()
    tmpl_R = super_fibonacci_rotations(num_templates)
    # Priors and templates in one sequence of equal chunks: one compiled renderer per mesh
    # bucket, progress reported every few chunks.
    all_R = np.concatenate([prior_R, tmpl_R])
    chunk = max(1, min(chunk, len(all_R)))
    parts = []
    step = 8 * chunk
    for start in range(0, len(all_R), step):
        R = all_R[start : start + step]
        parts.append(render_object_views(renderer, R, (size, size), sphere=(centre, radius),
                                         chunk=chunk))
        if on_views is not None:
            on_views(len(R))
    images = np.concatenate(parts)
    return banks.RenderBank(
        obj_id=int(obj_id),
        prior_rgb=images[: len(prior_R)],
        prior_rotations=prior_R,
        template_rgb=images[len(prior_R) :],
        template_rotations=tmpl_R,
        symmetries=banks.bank_symmetries(symmetries),
        diameter=float(diameter),
        center=centre.astype(np.float32),
        radius=radius,
    )
