"""3PT-R at inference: render-and-compare refinement of pose hypotheses in calibrated views.

:class:`SceneRefiner` holds a trained refiner and one object set's meshes, prepared once (the
refiner run's face budget, ``RefineSettings.max_faces``) and stacked so that one compiled loop
serves every object. A call refines N instances, each with K hypotheses (world frame, best
first), in V views, through :func:`threept_jax.pipeline.refine_loop.refine_instances`: each
iteration crops every view around the instance's best hypothesis, renders the active
hypotheses, runs 3PT-R, matches, solves multi-view PnP (each update kept only when the
matches back it) and keeps the better-scored half, duplicates up to symmetry dropped first,
beside the start carried unrefined; a last look keeps the refined best only when it scores above
the start. Shapes are padded so that scenes with other counts
reuse the compiled loop: instances to a bin of :func:`~threept_jax.pipeline.refine_loop.
pad_to_bin` (masked), hypotheses to ``num_hypotheses`` (repeating the last, a duplicate the
loop drops), views are the scene's. One compilation per (instance bin, views, image size,
object count), shared by every refiner of the same network structure and settings in the
process (another object set, another ``infer`` call).

Outputs per instance (:class:`RefinedPose`): the refined pose, the refiner's score logit of
it, the pose before refinement and after each iteration, and one visible mask per view from the
refiner's mask head, pasted back into the image.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import pathlib
from collections.abc import Callable, Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from threept_jax.data.banks import bank_symmetries
from threept_jax.data.detector_input import pad_symmetries
from threept_jax.data.refiner_input import RefinerMeshes
from threept_jax.models.configs import RefinerConfig
from threept_jax.models.refiner import Refiner
from threept_jax.pipeline.refine_loop import LoopSettings, pad_to_bin, paste_masks, refine_instances
from threept_jax.pipeline.refinement import RefineSettings
from threept_jax.render.mesh import Mesh, load_mesh, prepare_mesh

#: Hypotheses per instance entering the loop (the paper's K = 8: 8 -> 4 -> 2 -> 1).
NUM_HYPOTHESES = 8


@dataclasses.dataclass(frozen=True)
class RefineObject:
    """What refinement needs of an object: its id, mesh (mm) and symmetry transforms [S, 4, 4]
    (identity first). :class:`infer.onboarding.OnboardedObject` has the same fields."""

    obj_id: int
    mesh: Mesh
    symmetries: np.ndarray

    @property
    def center(self) -> np.ndarray:
        """[3] the centre of the mesh's bounding box (mm, object frame), as
        :class:`~infer.onboarding.OnboardedObject`'s ``center``."""
        return np.asarray(self.mesh.center, np.float64)


def refine_objects(meshes: Mapping[int, str | os.PathLike | Mesh], units: str = "mm"
                   ) -> list[RefineObject]:
    """``{obj_id: mesh file or Mesh}`` -> :class:`RefineObject` (units and mesh checks of
    ``load_mesh``; symmetries from the mesh's ``models_info.json`` when it has one)."""
    out = []
    for obj_id, m in sorted(meshes.items()):
        mesh = m if isinstance(m, Mesh) else load_mesh(pathlib.Path(m), units=units)
        out.append(RefineObject(int(obj_id), mesh, bank_symmetries(mesh.symmetries)))
    return out


@dataclasses.dataclass(frozen=True)
class RefinedPose:
    """One instance after refinement.

    Attributes:
      obj_id: object id.
      T_world_obj: [4, 4] refined pose (world frame; the camera frame for one view), mm.
      score: the refiner's score logit of that pose (higher is better; comparable between
        hypotheses of one instance, not calibrated across objects).
      history: [iterations + 2, 4, 4] the pose given, the refined best after each iteration,
        and last the pose kept (``T_world_obj``: the start where refinement did not score higher).
      masks: {view: bool [H, W]} the refiner's visible mask of the object in each view.
    """

    obj_id: int
    T_world_obj: np.ndarray
    score: float
    history: np.ndarray
    masks: dict


class SceneRefiner:
    """A trained 3PT-R and one object set, ready to refine poses (module docstring)."""

    def __init__(self, model: Refiner | Callable, config: RefinerConfig, settings: RefineSettings,
                 objects: Sequence, loop: LoopSettings | None = None,
                 num_hypotheses: int = NUM_HYPOTHESES):
        """``model``: the 3PT-R network, or any function ``network(real, renders) -> outputs``
        of the refiner contract (``threept_jax.models.refiner``; e.g. the oracle of
        ``threept_jax.testing.refiner_oracle`` for upper bounds). ``objects``:
        :class:`RefineObject` or :class:`infer.onboarding.OnboardedObject` (their ``obj_id``,
        ``mesh`` and ``symmetries`` are read)."""
        if not objects:
            raise ValueError("SceneRefiner needs at least one object")
        loop = LoopSettings() if loop is None else loop
        self.config, self.settings, self.loop = config, settings, loop
        self.num_hypotheses = int(num_hypotheses)
        meshes = {o.obj_id: prepare_mesh(o.mesh, max_faces=settings.max_faces, texture_size=256)
                  for o in objects}
        self.meshes = RefinerMeshes.from_meshes(meshes)
        ns = max(len(o.symmetries) for o in objects)
        self.symmetries = {o.obj_id: pad_symmetries(np.asarray(o.symmetries, np.float32), ns)
                           for o in objects}
        if isinstance(model, nnx.Module):
            network, self._params = nnx.split(model)
        else:  # a pure function of the refiner contract, e.g. testing.refiner_oracle
            network, self._params = model, None
        self._run, self._traces = _compiled_loop(network, config.crop_size, config.output_size,
                                                 settings, loop)

    @property
    def traces(self) -> int:
        """How many times the compiled loop was traced (shared by every refiner of the same
        network, sizes and settings in the process, :func:`_compiled_loop`): a call that
        traced added one."""
        return self._traces[0]

    def __call__(self, images: Sequence[np.ndarray], Ks: np.ndarray,
                 T_cam_world: np.ndarray | None, obj_ids: Sequence[int],
                 hypotheses: Sequence[np.ndarray]) -> list[RefinedPose]:
        """Refine instances ``obj_ids[i]`` from ``hypotheses[i]`` ([K_i, 4, 4] or [4, 4], world
        frame, best first) in the views ``images`` (uint8 [H, W, 3], one size) with intrinsics
        ``Ks`` [V, 3, 3] and extrinsics ``T_cam_world`` [V, 4, 4] (None: one view)."""
        padded = pad_instances(images, Ks, T_cam_world, obj_ids, hypotheses,
                               self.meshes.obj_ids, self.num_hypotheses)
        if padded is None:
            return []
        T_cw, hyps, ids, inst_mask = padded
        N, V = len(ids), len(images)
        mesh_index = np.array([self.meshes.index(o) for o in ids], np.int32)
        sym = np.stack([self.symmetries[o][0] for o in ids])
        sym_mask = np.stack([self.symmetries[o][1] for o in ids])
        view_mask = np.ones((N, V), bool)
        out = self._run(self._params, self.meshes.stacked, mesh_index,
                        jnp.asarray(np.stack(images)), np.asarray(Ks, np.float32), T_cw, hyps,
                        sym, sym_mask, inst_mask, view_mask)
        out = jax.device_get(out)
        hw = np.shape(images[0])[:2]
        result = []
        for i in range(len(obj_ids)):
            masks = paste_masks(np.asarray(out.mask_logits[i]), np.asarray(out.boxes[i]), hw)
            result.append(RefinedPose(obj_id=int(obj_ids[i]),
                                      T_world_obj=np.asarray(out.poses[i], np.float64),
                                      score=float(out.scores[i]),
                                      history=np.asarray(out.history[i], np.float64),
                                      masks={v: masks[v] for v in range(V)}))
        return result


@functools.lru_cache(maxsize=16)
def _compiled_loop(network, crop_size: int, output_size: int, settings: RefineSettings,
                   loop: LoopSettings):
    """(the jitted ``refine_instances`` of one network, trace counter [1]), built once per
    process for each network structure (an ``nnx.GraphDef``, compared by value: another
    refiner of the same model) or network function, sizes and settings, so that a second
    :class:`SceneRefiner` of the same model (another object set, another ``infer`` call)
    compiles only shapes it has not seen."""
    traces = [0]

    def run(params, stacked, *args):
        traces[0] += 1  # runs only while tracing
        net = nnx.merge(network, params) if params is not None else network
        return refine_instances(net, stacked, *args, crop_size=crop_size,
                                output_size=output_size, settings=settings, loop=loop)

    return jax.jit(run), traces


def pad_instances(images: Sequence[np.ndarray], Ks: np.ndarray, T_cam_world: np.ndarray | None,
                  obj_ids: Sequence[int], hypotheses: Sequence[np.ndarray], known: np.ndarray,
                  num_hypotheses: int):
    """The checked, padded inputs of a refiner call (:class:`SceneRefiner`,
    :class:`infer.contour_refine.ContourRefiner`): ``(T_cam_world [V, 4, 4] float32, hypotheses
    [N, K, 4, 4] float32, obj_ids [N], instance_mask [N])`` with N the instance bin of
    :func:`pad_to_bin` and K = ``num_hypotheses`` (each set cut to K or padded by repeating its
    last; padding instances sit 1 m in front of the cameras); None when there is no instance.
    Raises ValueError naming what is wrong (image shapes, camera counts, non-finite poses) and
    KeyError for objects outside ``known``."""
    V = len(images)
    if V == 0:
        raise ValueError("refinement needs at least one image")
    shapes = {np.shape(im) for im in images}
    if len(shapes) != 1 or len(next(iter(shapes))) != 3:
        raise ValueError(f"the views must be uint8 [H, W, 3] images of one size, got "
                         f"{sorted(shapes)}")
    T_cw = (np.tile(np.eye(4, dtype=np.float32), (1, 1, 1)) if T_cam_world is None
            else np.asarray(T_cam_world, np.float32))
    if T_cw.shape != (V, 4, 4) or np.shape(Ks) != (V, 3, 3):
        raise ValueError(f"{V} views need Ks [V, 3, 3] and T_cam_world [V, 4, 4], got "
                         f"{np.shape(Ks)} and {T_cw.shape}")
    n = len(obj_ids)
    if n != len(hypotheses):
        raise ValueError(f"{n} objects but {len(hypotheses)} hypothesis sets")
    if n == 0:
        return None
    unknown = sorted({int(o) for o in obj_ids} - set(np.asarray(known).tolist()))
    if unknown:
        raise KeyError(f"objects {unknown} are not in this refiner's object set "
                       f"{np.asarray(known).tolist()}")
    N, K = pad_to_bin(n), int(num_hypotheses)
    hyps = np.tile(np.eye(4, dtype=np.float32), (N, K, 1, 1))
    hyps[:, :, 2, 3] = 1000.0  # padding instances: any pose in front of the cameras
    for i, h in enumerate(hypotheses):
        h = np.asarray(h, np.float32).reshape(-1, 4, 4)[:K]
        if not np.all(np.isfinite(h)):
            raise ValueError(f"hypotheses of instance {i} (object {obj_ids[i]}) are not "
                             "finite")
        hyps[i, :len(h)] = h
        hyps[i, len(h):] = h[-1]
    ids = [int(o) for o in obj_ids] + [int(obj_ids[0])] * (N - n)
    return T_cw, hyps, ids, np.arange(N) < n
