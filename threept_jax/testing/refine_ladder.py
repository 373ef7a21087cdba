"""The noise ladder of 3PT-R: the inference loop driven by the oracle network made worse step by
step, to show that refinement never makes a pose worse than its start (issue 25, item 1).

A rung is a descriptor noise level and an outlier rate of the oracle
(:func:`~threept_jax.testing.refiner_oracle.make_oracle`: ``noise`` is the noise-to-signal norm
ratio of every descriptor, ``outliers`` the share of real pixels whose descriptor is that of a
random other point of the part). The scene: one part painted with its object coordinates in
``views`` 640 x 480 images from cameras about 500 mm away; ``num`` starting poses drawn as
refiner training draws them (``data.refiner_input.perturb_poses`` in the first camera's frame),
each refined as its own instance with K = 1 (refine-only, tracking) through
:func:`~threept_jax.pipeline.refine_loop.refine_instances`, the loop inference runs. The oracle's
score (mask IoU of render and real crop) is a good score: the ladder tests the safety of the
updates, not the score head.

Every rung of one view count runs in one compilation (the oracle is made inside ``jit`` with
traced levels). Pure: ``bench/refine_ladder.py`` prints the table and ``tests/pipeline/
test_refine_ladder.py`` checks it.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial.transform import Rotation

from threept_jax.data.refiner_input import RefinerExampleConfig, RefinerMeshes, perturb_poses
from threept_jax.geometry.camera import look_at
from threept_jax.pipeline.refine_loop import LoopSettings, refine_instances
from threept_jax.pipeline.refinement import RefineSettings
from threept_jax.render.mesh import Mesh, to_raster_mesh
from threept_jax.render.raster import render
from threept_jax.testing.refiner_oracle import make_oracle, xyz_colored

IMAGE_HW = (480, 640)
K_IMAGE = np.array([[800.0, 0, 319.5], [0, 800.0, 239.5], [0, 0, 1]], np.float32)
# Three cameras about 500 mm from the part, 120 degrees apart around it; one view uses the first.
EYES = np.array([[500, 0, 150], [-250, 430, 100], [-250, -430, -100]], np.float64)


@dataclasses.dataclass(frozen=True)
class LadderScene:
    """One part in V views: ``mesh`` (painted, prepared), ``images`` uint8 [V, H, W, 3], ``Ks``
    [V, 3, 3], ``T_cam_world`` [V, 4, 4], ``T_gt`` [4, 4] T_world_obj (mm)."""

    mesh: Mesh
    images: np.ndarray
    Ks: np.ndarray
    T_cam_world: np.ndarray
    T_gt: np.ndarray


def make_scene(mesh: Mesh, views: int, seed: int = 0) -> LadderScene:
    """``mesh`` (prepared, mm) painted with its coordinates at a random orientation, its centre
    at the world origin, seen by the first ``views`` (1 or 3) cameras of ``EYES``."""
    if views not in (1, 3):
        raise ValueError(f"the ladder has 1 or 3 views, got {views}")
    painted = xyz_colored(mesh)
    R = Rotation.random(random_state=seed).as_matrix()
    T_gt = np.eye(4)
    T_gt[:3, :3], T_gt[:3, 3] = R, -R @ np.asarray(painted.center, np.float64)
    T_cw = np.stack([np.asarray(look_at(e, np.zeros(3)), np.float64) for e in EYES[:views]])
    rm = to_raster_mesh(painted)
    images = np.stack([
        np.round(np.asarray(render(rm, (T @ T_gt).astype(np.float32), K_IMAGE, IMAGE_HW,
                                   ("rgb",), ambient=1.0)["rgb"]) * 255).astype(np.uint8)
        for T in T_cw])
    return LadderScene(painted, images, np.tile(K_IMAGE, (views, 1, 1)), T_cw, T_gt)


def start_poses(scene: LadderScene, num: int, seed: int = 0) -> np.ndarray:
    """float64 [num, 4, 4] T_world_obj: the refiner's training perturbation of the truth in the
    first camera's frame (15 degrees half-normal, 2 % of the diameter across, 5 % of the depth
    along the ray)."""
    T_cw0 = scene.T_cam_world[0]
    cam = perturb_poses(T_cw0 @ scene.T_gt, np.asarray(scene.mesh.center), 2.0 *
                        float(scene.mesh.radius), num, RefinerExampleConfig(),
                        np.random.default_rng(seed))
    return np.linalg.inv(T_cw0) @ cam


def pose_errors(T: np.ndarray, T_gt: np.ndarray) -> np.ndarray:
    """[..., 2] (rotation degrees, translation mm) of T [..., 4, 4] against T_gt (float64)."""
    T = np.asarray(T, np.float64)
    dR = np.einsum("...ji,jk->...ik", T[..., :3, :3], np.asarray(T_gt, np.float64)[:3, :3])
    cos = np.clip((np.trace(dR, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    return np.stack([np.degrees(np.arccos(cos)),
                     np.linalg.norm(T[..., :3, 3] - T_gt[:3, 3], axis=-1)], -1)


@functools.partial(jax.jit, static_argnames=("crop_size", "output_size", "settings", "loop"))
def _refine(noise, outliers, meshes, images, Ks, T_cam_world, starts, view_mask, *, crop_size,
            output_size, settings, loop):
    network = make_oracle(output_size, noise=noise, outliers=outliers)
    n = starts.shape[0]
    return refine_instances(
        network, meshes, jnp.zeros(n, jnp.int32), images, Ks, T_cam_world, starts[:, None],
        jnp.eye(4)[None, None].repeat(n, 0), jnp.ones((n, 1), bool), jnp.ones(n, bool),
        jnp.broadcast_to(view_mask, (n, view_mask.shape[0])), crop_size=crop_size,
        output_size=output_size, settings=settings, loop=loop).poses


def run_ladder(scene: LadderScene, starts: np.ndarray, rungs, *, views: int | None = None,
               crop_size: int = 64, output_size: int = 32,
               settings: RefineSettings | None = None,
               loop: LoopSettings | None = None) -> np.ndarray:
    """Errors [R, num, 2] (degrees, mm) after the loop for each rung (noise, outliers) of
    ``rungs``, every start [num, 4, 4] refined alone (K = 1). The loop's crops are not
    antialiased by default: the oracle reads a pixel's colour as the coordinate at its centre.
    Defaults: ``RefineSettings(ambient=1.0)`` (the painted renders are unshaded) and
    ``LoopSettings(antialias=1)``. ``views``: refine in the scene's first ``views`` views only,
    the others masked out (the loop's ``view_mask``: no weight in PnP, not in the score), so
    one compiled program runs both view counts; default all."""
    total = len(scene.images)
    views = total if views is None else views
    if not 1 <= views <= total:
        raise ValueError(f"views must be in 1..{total} (the scene's views), got {views}")
    view_mask = jnp.arange(total) < views
    settings = settings or RefineSettings(ambient=1.0)
    loop = loop or LoopSettings(antialias=1)
    meshes = RefinerMeshes.from_meshes({1: scene.mesh}).stacked
    out = []
    for noise, outliers in rungs:
        poses = _refine(jnp.float32(noise), jnp.float32(outliers), meshes, scene.images,
                        scene.Ks.astype(np.float32), scene.T_cam_world.astype(np.float32),
                        jnp.asarray(starts, jnp.float32), view_mask, crop_size=crop_size,
                        output_size=output_size, settings=settings, loop=loop)
        out.append(pose_errors(np.asarray(poses), scene.T_gt))
    return np.stack(out)
