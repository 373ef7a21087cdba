"""The training-free refiner: pose hypotheses refined by the image's own contour evidence.

:class:`ContourRefiner` has the call of :class:`infer.refine.SceneRefiner` (N instances, each
with K hypotheses, world frame, best first, in V calibrated views) and returns the same
:class:`infer.refine.RefinedPose` records, so ``run_scene``, ``refine``, ``track`` and the
commands take either (``infer.load(refiner="contour")``, ``--refiner contour``). It runs
:func:`threept_jax.pipeline.contour.refine_poses` (correspondence lines along the projected
contour, colour statistics and edges, Gauss-Newton summed over views, coarse to fine) on every
hypothesis of every instance in one compiled call, each hypothesis kept at its start where the
refined pose scores lower, and keeps each instance's best-scored hypothesis. Instances hide
each other's lines: an occluder map of every instance at its start pose is rendered first.
Masks are the visible silhouettes at the kept poses (each pixel to the nearest instance).
A part with near-symmetric turns (a gear's teeth: :mod:`threept_jax.geometry.turns`, found
once per mesh and cached) is then turned to whichever of them the edges inside its outline
show best (:mod:`threept_jax.pipeline.turns`): the outline cannot tell them apart.

Compiled once per process per (instance bin, hypothesis bin, views, image size, object count,
settings), whichever refiner calls it.
"""

from __future__ import annotations

import functools
import hashlib
import os
import pathlib
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from infer.refine import RefinedPose, pad_instances
from threept_jax.data.files import atomic_savez
from threept_jax.data.refiner_input import RefinerMeshes
from threept_jax.geometry.turns import near_symmetry_turns
from threept_jax.geometry.validate import scale_intrinsics
from threept_jax.pipeline.contour import (
    ContourSettings,
    mesh_contours,
    occluder_maps,
    refine_poses,
    stack_contours,
)
from threept_jax.pipeline.refine_loop import pad_to_bin
from threept_jax.pipeline.turns import choose_turn
from threept_jax.render import Renderer
from threept_jax.render.mesh import prepare_mesh

#: Longest side of the occluder maps (they only decide which line samples another instance
#: hides, so a reduced image is enough).
OCCLUDER_SIDE = 320


#: Bumped when ``mesh_contours``' output changes, so that old cache files are not read.
CONTOUR_CACHE_VERSION = 1


def hash_mesh(h, mesh) -> None:
    """Feeds a mesh's vertices and faces into the hashlib hash ``h``: what a key of work done
    from the mesh (its contour models, a search with it) depends on."""
    for a in (mesh.vertices, mesh.faces):
        h.update(np.ascontiguousarray(a).tobytes())


def _cached(make, key: str, mesh, cache: pathlib.Path | None, extra: bytes = b"") -> dict:
    """``make()`` (a dict of arrays), read from / written to ``cache`` keyed by ``key``, the
    mesh's arrays and ``extra``."""
    if cache is None:
        return make()
    h = hashlib.sha256(key.encode())
    hash_mesh(h, mesh)
    h.update(extra)
    path = cache / f"{h.hexdigest()[:32]}.npz"
    if path.exists():
        try:
            with np.load(path, allow_pickle=False) as z:
                return {k: z[k] for k in z.files}
        except (OSError, ValueError):  # a damaged file is rebuilt
            pass
    out = make()
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_savez(path, **out)
    return out


def _cached_contours(mesh, cache: pathlib.Path | None) -> dict:
    """``mesh_contours(mesh)``, cached by the mesh's arrays."""
    return _cached(lambda: mesh_contours(mesh), f"contours-v{CONTOUR_CACHE_VERSION}", mesh,
                   cache)


def _cached_turns(obj, cache: pathlib.Path | None) -> np.ndarray:
    """The object's near-symmetric turns [M, 4, 4], cached by its mesh and symmetries."""
    symmetries = getattr(obj, "symmetries", None)
    extra = b"" if symmetries is None else np.ascontiguousarray(symmetries, np.float64).tobytes()
    return _cached(lambda: {"turns": near_symmetry_turns(obj.mesh.vertices, obj.mesh.faces,
                                                         symmetries)},
                   "turns-v1", obj.mesh, cache, extra)["turns"]


#: Traces of :func:`_refine_instances` in this process (tests check that a call with known shapes
#: does not compile again).
TRACES = [0]


@functools.partial(jax.jit, static_argnames=("hw_occ", "settings"))
def _refine_instances(model, meshes, images, Ks, Ks_occ, T_cw, hyps, mesh_index, inst_mask, *,
                      hw_occ, settings):
    """Every hypothesis of every instance refined, each instance's best kept, and the id map of
    the kept poses: (poses [N, 4, 4], scores [N], ids [V, H, W]). One jitted function for every
    :class:`ContourRefiner`: two refiners of the same shapes share its compilation."""
    TRACES[0] += 1  # runs only while tracing
    N, K = hyps.shape[:2]
    V = images.shape[0]
    occ_id, occ_depth = occluder_maps(meshes, mesh_index, hyps[:, 0], Ks_occ, T_cw, hw_occ,
                                      inst_mask)
    flat = hyps.reshape(N * K, 4, 4)
    obj = jnp.repeat(mesh_index, K)
    inst = jnp.repeat(jnp.arange(N, dtype=jnp.int32), K)
    vm = jnp.ones((N * K, V), bool)
    res = refine_poses(model, images, Ks, T_cw, flat, obj, inst, occ_id, occ_depth, vm,
                       settings)
    scores = res.scores.reshape(N, K)
    best = jnp.argmax(scores, -1)
    poses = res.poses.reshape(N, K, 4, 4)[jnp.arange(N), best]
    ids, _ = occluder_maps(meshes, mesh_index, poses, Ks, T_cw, images.shape[1:3], inst_mask)
    return poses, scores[jnp.arange(N), best], ids


class ContourRefiner:
    """Contour-evidence refinement of one object set (module docstring).

    ``objects``: anything with ``obj_id`` and ``mesh`` (:class:`infer.refine.RefineObject`,
    :class:`infer.onboarding.OnboardedObject`). Building it renders each mesh's contours
    (:func:`~threept_jax.pipeline.contour.mesh_contours`, a few seconds per mesh on 2 CPU
    cores), cached under ``cache_dir`` (None: no disk cache) by the mesh's arrays, and finds its
    near-symmetric turns (about a second; ``turns=False``: none, the refined pose as it is,
    which ``bench/turns.py`` times against).
    """

    def __init__(self, objects: Sequence, settings: ContourSettings | None = None,
                 cache_dir: str | os.PathLike | None = None, turns: bool = True):
        if not objects:
            raise ValueError("ContourRefiner needs at least one object")
        self.settings = settings or ContourSettings()
        objects = sorted(objects, key=lambda o: o.obj_id)
        self.obj_ids = np.array([o.obj_id for o in objects], np.int64)
        cache = None if cache_dir is None else pathlib.Path(cache_dir)
        self.model = stack_contours([_cached_contours(o.mesh, cache) for o in objects])
        self.meshes = RefinerMeshes.from_meshes(
            {o.obj_id: prepare_mesh(o.mesh, max_faces=2048, texture_size=None) for o in objects})
        # Parts with near-symmetric turns: the turns, a renderer of their edges, their box.
        self.turns = {}
        for o in objects if turns else ():
            found = _cached_turns(o, cache)
            if len(found):
                lo, hi = o.mesh.bbox
                corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                                    for z in (lo[2], hi[2])], np.float64)
                self.turns[o.obj_id] = (found, Renderer(o.mesh), corners)

    def __call__(self, images: Sequence[np.ndarray], Ks: np.ndarray,
                 T_cam_world: np.ndarray | None, obj_ids: Sequence[int],
                 hypotheses: Sequence[np.ndarray]) -> list[RefinedPose]:
        """Refine instances ``obj_ids[i]`` from ``hypotheses[i]`` ([K_i, 4, 4] or [4, 4], world
        frame, best first) in the views ``images`` (uint8 [H, W, 3], one size) with intrinsics
        ``Ks`` [V, 3, 3] and extrinsics ``T_cam_world`` [V, 4, 4] (None: one view)."""
        k_max = max((np.asarray(h).reshape(-1, 4, 4).shape[0] for h in hypotheses), default=1)
        padded = pad_instances(images, Ks, T_cam_world, obj_ids, hypotheses,
                               self.obj_ids, pad_to_bin(k_max, (1, 2, 4, 8)))
        if padded is None:
            return []
        T_cw, hyps, ids, inst_mask = padded
        mesh_index = np.searchsorted(self.obj_ids, ids).astype(np.int32)
        H, W = np.shape(images[0])[:2]
        s = min(1.0, OCCLUDER_SIDE / max(H, W))
        hw_occ = (max(int(round(H * s)), 1), max(int(round(W * s)), 1))
        Ks = np.asarray(Ks, np.float64)
        Ks_occ = np.stack([scale_intrinsics(K, (H, W), hw_occ) for K in Ks]).astype(np.float32)
        poses, scores, masks_id = jax.device_get(_refine_instances(
            self.model, self.meshes.stacked, jnp.asarray(np.stack(images)),
            Ks.astype(np.float32), Ks_occ, T_cw, hyps, mesh_index, inst_mask, hw_occ=hw_occ,
            settings=self.settings))
        out = []
        for i in range(len(obj_ids)):
            start = np.asarray(hyps[i, 0], np.float64)
            pose = np.asarray(poses[i], np.float64)
            if int(obj_ids[i]) in self.turns:
                turns, renderer, corners = self.turns[int(obj_ids[i])]
                pose = choose_turn(renderer, corners, pose, turns, images, Ks,
                                   np.asarray(T_cw, np.float64))
            out.append(RefinedPose(obj_id=int(obj_ids[i]), T_world_obj=pose,
                                   score=float(scores[i]),
                                   history=np.stack([start, pose, pose]),
                                   masks={v: masks_id[v] == i for v in range(len(images))}))
        return out
