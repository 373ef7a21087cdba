"""Object onboarding renders: an object's views at given rotations with the bank camera.

3PT-D's object tower (docs/design.md section 1.1) consumes, per object, 12 prior renders and a bank
of templates at rotations covering SO(3). Training (``datagen``) and inference onboarding both
render them with :func:`render_object_views`, so the two see identical images.

**One size, one anti-aliasing rule** (issue 13 item 1.3). Renders are made at the detector's
``render_size`` and never resized afterwards: training banks are packed at that size
(``python -m datagen.pack --bank-size``, checked by the training input) and inference
onboarding renders at it. Every render is anti-aliased the same way whatever the backend:
rendered at ``SUPERSAMPLE`` x the size (the bank camera of the larger size) and box-averaged
over ``SUPERSAMPLE`` x ``SUPERSAMPLE`` blocks, 9 samples per pixel, so the JAX rasterizer (one
sample per pixel) gives smooth edges like Mitsuba's.

The camera is the render-bank camera of :mod:`threept_jax.data.banks`: an object-centred view
from ``DISTANCE_FACTOR`` bounding-sphere radii, with a focal length that makes the sphere span
``FILL`` of the image side (``banks.render_camera``), and poses ``T_cam_obj = [R | (0, 0, d) -
R c]`` (``banks.render_pose``). Images are the renderer's shaded ``rgb`` output (texture,
vertex colours or neutral grey under headlight Lambert shading; ``threept_jax.render``) on a
black background.

**Batching.** The JAX rasterizer's working set grows with (views per call) x (padded faces);
on CPU large calls are slower per view, not faster: 96x96 renders of a 15.7k-face YCB-V model
take 2.4 ms per view at 2 views per call against 4.3 ms at 64 (2-core CPU,
``python bench/onboarding.py``). So :func:`render_chunk` sizes CPU calls by the mesh's face
bucket (``CPU_FACE_VIEWS``); accelerators keep ``DEVICE_CHUNK`` views per call.

Shapes: N rotations, h w render size.
"""

from __future__ import annotations

import pathlib
import warnings
from typing import Any

import jax
import numpy as np

from threept_jax.data import banks
from threept_jax.geometry.grids import prior_view_rotations, super_fibonacci_rotations
from threept_jax.geometry.symmetry import Symmetries
from threept_jax.render import Mesh, Renderer, load_mesh, prepare_mesh

__all__ = ["BankRenderer", "object_camera", "render_bank", "render_chunk", "render_object_views"]

#: Face budget of the models that banks are rendered from (datagen and inference alike).
BANK_MAX_FACES = 20000
#: CPU: (views per rasterizer call) x (padded faces) kept near this (module docstring; 16k to
#: 64k measured fastest for 1.5k- and 16k-face buckets).
CPU_FACE_VIEWS = 32768
#: Views per rasterizer call on accelerators and for the Mitsuba backend.
DEVICE_CHUNK = 64
#: Anti-aliasing: renders are made at this many times the output side and box-averaged.
SUPERSAMPLE = 3


def render_chunk(renderer: Renderer) -> int:
    """Views per render call for ``renderer``: ``CPU_FACE_VIEWS`` // padded faces (1..64) for
    the JAX backend on CPU, ``DEVICE_CHUNK`` otherwise. Depends only on the face bucket, so it
    adds no compilation."""
    if renderer.backend != "jax" or jax.default_backend() != "cpu":
        return DEVICE_CHUNK
    return max(1, min(DEVICE_CHUNK, CPU_FACE_VIEWS // renderer.mesh.num_faces_padded))


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
    chunk: int | None = None,
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
      chunk: views rendered per call (default :func:`render_chunk`); every call renders
        exactly ``chunk`` views (the last one padded), so the JAX backend compiles once per
        mesh bucket and image size whatever N is, and memory stays bounded.
      ambient: ambient term of the headlight shading.

    Background pixels are 0. Colours are ``round(255 * rgb)`` of the mean of the
    ``SUPERSAMPLE`` x ``SUPERSAMPLE`` samples of each pixel (module docstring): the render at
    ``SUPERSAMPLE`` x (h, w) with the bank camera of that size, whose pixel blocks average to
    the pixels of the (h, w) bank camera exactly (same focal length per output pixel, same
    principal point).
    """
    R = np.asarray(rotations, np.float64)
    if R.ndim != 3 or R.shape[1:] != (3, 3):
        raise ValueError(f"rotations must be [N, 3, 3], got {R.shape}")
    if chunk is not None and chunk < 1:
        raise ValueError(f"chunk must be >= 1, got {chunk}")
    h, w = int(hw[0]), int(hw[1])
    renderer = mesh if isinstance(mesh, Renderer) else Renderer(mesh, backend)
    chunk = render_chunk(renderer) if chunk is None else int(chunk)
    if sphere is None:
        sphere = banks.bounding_sphere(np.asarray(_mesh_of(renderer, mesh).vertices, np.float64))
    s = SUPERSAMPLE
    K, distance = banks.render_camera((s * h, s * w), float(sphere[1]))
    T = banks.render_pose(R, np.asarray(sphere[0], np.float64), distance)
    n = len(T)
    out = np.zeros((n, h, w, 3), np.uint8)
    for start in range(0, n, chunk):
        part = T[start : start + chunk]
        k = len(part)
        if k < chunk:  # pad with copies so every call has the same shape
            part = np.concatenate([part, np.repeat(part[-1:], chunk - k, 0)])
        rgb = renderer.render(part.astype(np.float32), K.astype(np.float32), (s * h, s * w),
                              ("rgb",), ambient=ambient)["rgb"]
        rgb = np.asarray(rgb, np.float32)[:k].reshape(k, h, s, w, s, 3).mean((2, 4))
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


class BankRenderer:
    """The bank camera's renders of one model (mm), at any rotations: the images of
    :func:`render_bank`, for callers that render in blocks (inference onboarding).

    The camera is fixed by the full model's bounding sphere; rendering uses a copy decimated to
    ``max_faces`` (None: the full model).
    """

    def __init__(self, mesh: Mesh, size: int = banks.BANK_SIZE, *,
                 max_faces: int | None = BANK_MAX_FACES, backend: str = "jax",
                 chunk: int | None = None):
        self.size = int(size)
        self.sphere = banks.bounding_sphere(np.asarray(mesh.vertices, np.float64))
        work = mesh if max_faces is None or mesh.num_faces <= max_faces else prepare_mesh(
            mesh, max_faces=max_faces)
        self.renderer = Renderer(work, backend)
        self.chunk = render_chunk(self.renderer) if chunk is None else int(chunk)

    def __call__(self, rotations: Any) -> np.ndarray:
        """uint8 [N, size, size, 3] renders at R_cam_obj ``rotations`` [N, 3, 3]."""
        return render_object_views(self.renderer, rotations, (self.size, self.size),
                                   sphere=self.sphere, chunk=self.chunk)


def render_bank(
    mesh: Mesh | str | pathlib.Path,
    obj_id: int,
    diameter: float,
    symmetries: Symmetries,
    size: int = banks.BANK_SIZE,
    num_templates: int = banks.BANK_TEMPLATES,
    *,
    max_faces: int | None = BANK_MAX_FACES,
    chunk: int | None = None,
    backend: str = "jax",
    on_views=None,
) -> banks.RenderBank:
    """The :class:`~threept_jax.data.banks.RenderBank` of a model (a Mesh in mm, or its file):
    the 12 prior views and ``num_templates`` super-Fibonacci templates, ``size`` x ``size``.

    Datagen stores banks for training (``python -m datagen.banks``); inference onboarding
    renders the same images for unseen objects (:class:`BankRenderer`). ``on_views(n)``
    reports progress; ``chunk``: views per render call (default :func:`render_chunk`).
    """
    if not isinstance(mesh, Mesh):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # duplicated BOP faces, open meshes: noise here
            mesh = load_mesh(mesh, models_info=None)
    render = BankRenderer(mesh, size, max_faces=max_faces, backend=backend, chunk=chunk)
    prior_R = prior_view_rotations()
    tmpl_R = super_fibonacci_rotations(num_templates)
    all_R = np.concatenate([prior_R, tmpl_R])
    parts = []
    step = 512  # progress every few hundred views
    for start in range(0, len(all_R), step):
        R = all_R[start : start + step]
        parts.append(render(R))
        if on_views is not None:
            on_views(len(R))
    images = np.concatenate(parts)
    centre, radius = render.sphere
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
