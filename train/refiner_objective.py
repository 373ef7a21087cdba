"""The 3PT-R objective on a batch: renders, one forward pass, the three losses, the step's target.

Shared by the refiner's train step (:mod:`train.trainer_refiner`) and its held-out evaluation
(:mod:`train.eval_refiner`), so both compute the same thing. A batch (``refiner_input``
fields, B instances, J hypotheses, V views):

1. **Renders inside the jitted step** (:func:`render_batch`): each instance's mesh row is
   gathered from the stacked, face-padded meshes (:class:`RefinerAssets`) and its J hypotheses
   are rasterised into its V crops by
   :func:`threept_jax.pipeline.refinement.render_hypotheses` (colour at the crop size for the
   network; object coordinates, mask and edges at the map size): no host round trip.
2. **One forward pass** of the network on the real crops and the J x V renders.
3. **Losses** (:mod:`threept_jax.losses.refiner`): matching (eq. (1)) over every (hypothesis,
   view) pair against the ground-truth pose; segmentation of the real crop's visible mask
   under every hypothesis; classification of the J scores, whose target is the hypothesis with
   the lowest MSSD after one refinement step, each hypothesis keeping its start where the step
   made it worse (:func:`kept_errors`; the inference loop keeps the start when the refined
   pose scores lower, and a target that follows a step that moves poses at random would be
   noise): the step's matching and PnP
   (:func:`~threept_jax.pipeline.refinement.update_hypotheses`, the function inference runs)
   applied to the same forward pass under ``stop_gradient``.

Invalid examples (``valid`` False: an image without a usable instance) have an empty visible
mask, so they add no matching pixel, and are masked out of the other two terms.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import jax
import jax.numpy as jnp
import numpy as np

from threept_jax.data.refiner_input import RefinerMeshes
from threept_jax.losses.refiner import (
    RefinerLossConfig,
    classification_loss,
    matching_loss,
    mssd_errors,
    segmentation_loss,
)
from threept_jax.pipeline.refinement import (
    RefineResult,
    RefineSettings,
    Renders,
    render_hypotheses,
    update_hypotheses,
)
from threept_jax.render.mesh import RasterMesh

Array = jax.Array

#: Batch fields the objective reads (the others stay on the host).
STEP_FIELDS = ("crops", "crop_K", "T_cam_world", "T_world_obj_gt", "hypotheses", "visible_mask",
               "mesh_index", "symmetries", "symmetry_mask", "valid")

#: Most model points per object in the classification target's MSSD (face corners, strided).
MAX_MODEL_POINTS = 1024


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class RefinerAssets:
    """What the jitted step reads besides the batch: every object's mesh and model points.

    mesh: a :class:`RasterMesh` with a leading object axis [O] (``RefinerMeshes.stacked``).
    points: [O, P, 3] object-frame model points for MSSD: the corners of the prepared mesh's
      faces, every s-th so that P <= :data:`MAX_MODEL_POINTS`; point_mask [O, P] (padding
      faces False).
    """

    mesh: RasterMesh
    points: Array
    point_mask: Array

    @classmethod
    def from_meshes(cls, meshes: RefinerMeshes) -> RefinerAssets:
        geom = np.asarray(meshes.stacked.face_geom)  # [O, Fp, 18]
        o, f = geom.shape[:2]
        corners = geom[..., :9].reshape(o, f * 3, 3)
        mask = np.repeat(np.asarray(meshes.stacked.face_mask), 3, axis=1)
        stride = -(-corners.shape[1] // MAX_MODEL_POINTS)
        return cls(mesh=meshes.stacked, points=jnp.asarray(corners[:, ::stride], jnp.float32),
                   point_mask=jnp.asarray(mask[:, ::stride]))


def render_batch(assets: RefinerAssets, batch: Mapping[str, Array], *, crop_size: int,
                 output_size: int, ambient: float, hypotheses: Array | None = None) -> Renders:
    """Renders [B, J, V, ...] of every instance's hypotheses (``batch["hypotheses"]`` unless
    ``hypotheses`` [B, J, 4, 4] is given) into its crops."""
    hyps = batch["hypotheses"] if hypotheses is None else hypotheses

    def one(index, crop_K, T_cam_world, h):
        mesh = jax.tree.map(lambda x: x[index], assets.mesh)
        return render_hypotheses(mesh, crop_K, T_cam_world, h, crop_size=crop_size,
                                 output_size=output_size, ambient=ambient)

    return jax.vmap(one)(batch["mesh_index"], batch["crop_K"], batch["T_cam_world"], hyps)


def gt_cam_obj(batch: Mapping[str, Array]) -> Array:
    """Ground-truth T_cam_obj [B, V, 4, 4] of every view."""
    return jnp.einsum("bvij,bjk->bvik", batch["T_cam_world"].astype(jnp.float32),
                      batch["T_world_obj_gt"].astype(jnp.float32))


def refine_batch(outputs: Mapping[str, Array], rend: Renders, assets: RefinerAssets,
                 batch: Mapping[str, Array], hypotheses: Array, settings: RefineSettings
                 ) -> RefineResult:
    """:func:`update_hypotheses` of every instance ([B] leading axis on every field)."""

    def one(out, r, index, crops, crop_K, T_cam_world, h):
        mesh = jax.tree.map(lambda x: x[index], assets.mesh)
        return update_hypotheses(out, r, mesh, crops, crop_K, T_cam_world, h, settings)

    return jax.vmap(one)(dict(outputs), rend, batch["mesh_index"], batch["crops"],
                         batch["crop_K"], batch["T_cam_world"], hypotheses)


def pose_errors(assets: RefinerAssets, batch: Mapping[str, Array], poses: Array) -> Array:
    """MSSD (mm) [B, J] of poses [B, J, 4, 4] (world frame) against the ground truth."""
    pts = assets.points[batch["mesh_index"]]
    mask = assets.point_mask[batch["mesh_index"]]
    return jax.vmap(mssd_errors)(poses, batch["T_world_obj_gt"], pts, mask,
                                 batch["symmetries"], batch["symmetry_mask"])


def kept_errors(before: Array, after: Array) -> Array:
    """The error [B, J] each hypothesis ends with when the better of its start and its refined
    pose is kept, as the inference loop keeps its start when refinement scores lower: the
    classification target's error. A non-finite ``after`` (a failed step) keeps ``before``."""
    after = jnp.where(jnp.isfinite(after), after, jnp.inf)
    return jnp.minimum(before, after)


def objective(outputs: Mapping[str, Array], rend: Renders, assets: RefinerAssets,
              batch: Mapping[str, Array], loss_cfg: RefinerLossConfig,
              settings: RefineSettings) -> tuple[Array, dict[str, Array], RefineResult]:
    """(total loss, metrics, the refinement step's result) of one forward pass (module
    docstring). Metrics: ``loss``, ``matching/...``, ``classification/...``,
    ``segmentation/...`` (each term's own metrics) and ``mssd_before`` / ``mssd_after`` (mean
    over valid instances and hypotheses, mm)."""
    valid = batch["valid"].astype(bool)
    T_gt = gt_cam_obj(batch)[:, None]  # [B, 1, V, 4, 4]
    vis = batch["visible_mask"].astype(bool)[:, None]  # [B, 1, V, h, w]
    m_loss, m_metrics = matching_loss(
        outputs["real_desc"], outputs["render_desc"], rend.xyz, rend.mask, T_gt,
        rend.K_map[:, None], vis, temperature=loss_cfg.temperature)
    s_loss, s_metrics = segmentation_loss(outputs["mask_logits"], vis, valid[:, None, None])

    hyps = batch["hypotheses"].astype(jnp.float32)
    step = refine_batch(jax.lax.stop_gradient(dict(outputs)), rend, assets, batch, hyps,
                        settings)
    step = jax.lax.stop_gradient(step)
    after = pose_errors(assets, batch, step.hypotheses)
    before = jax.lax.stop_gradient(pose_errors(assets, batch, hyps))
    c_loss, c_metrics = classification_loss(outputs["scores"], kept_errors(before, after), valid)

    total = (loss_cfg.matching_weight * m_loss + loss_cfg.segmentation_weight * s_loss
             + loss_cfg.classification_weight * c_loss)
    n = jnp.maximum(jnp.sum(valid), 1).astype(jnp.float32)
    mean_valid = lambda e: jnp.sum(jnp.where(valid[:, None], e, 0.0)) / (n * e.shape[1])  # noqa: E731
    metrics = {"loss": total, "num_valid": jnp.sum(valid).astype(jnp.float32),
               "mssd_before": mean_valid(before),
               "mssd_after": mean_valid(jnp.where(jnp.isfinite(after), after, 0.0))}
    for name, terms in (("matching", m_metrics), ("classification", c_metrics),
                        ("segmentation", s_metrics)):
        metrics.update({f"{name}/{k}": v for k, v in terms.items()})
    return total, metrics, step
