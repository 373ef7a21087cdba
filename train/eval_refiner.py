"""Periodic evaluation of 3PT-R on objects training never saw.

The first ``eval.num_examples`` records of ``eval.data_dir`` (``""``: the val split of
``config.data_dir``), split ``eval.split``, cut as training cuts them (one instance per image,
``data.num_hypotheses`` perturbed poses, a fixed seed), each run through the refinement step
as inference runs it: renders, network, reciprocal matches, multi-view PnP
(:func:`~threept_jax.pipeline.refinement.update_hypotheses`), iterated ``eval.num_steps``
times on the same crops. Every pose of every hypothesis is scored against the ground truth.
Metrics (all over valid instances; medians and shares over instances x hypotheses):

* ``eval/match_within_2px``: share of the step's reciprocal edge matches (weight 1, first
  step) whose real pixel (crop frame) lies within 2 crop pixels of the projection of the
  match's 3D point by the ground-truth pose; ``eval/match_within_2px_same_place``: the same
  share had every render pixel been matched to the real pixel at the same place (a network
  that has learnt only where a pixel is reaches it: the baseline to beat);
  ``eval/matches_per_pair``.
* ``eval/rot_deg_{before,after_1,after_N}``: median rotation error, symmetry-aware
  (min over the object's symmetries, ``geometry.symmetry.symmetric_angle_deg``), in degrees;
  ``eval/trans_mm_...``: median ``|t_est - t_gt|`` (mm); ``eval/ar_mssd_...``: BOP's MSSD
  recall averaged over the thresholds 0.05, 0.10, ..., 0.50 of the diameter (MSSD over the
  prepared mesh's face corners, :func:`threept_jax.losses.refiner.mssd_errors`), before
  refinement, after 1 step and after N = ``eval.num_steps`` steps. ``eval/ar_mssd_after``
  (the default best-checkpoint metric) is the last.
* ``eval/ar_mssd_top_before`` / ``eval/ar_mssd_top_after``: the same for the one hypothesis
  per instance that the network's score picks (what inference keeps), before refinement (the
  gain of selection alone) and after N steps.
* ``eval/score_acc``: how often the top-scored of the J hypotheses is the classification
  target: the lowest MSSD after one step, each hypothesis keeping its start where the step
  made it worse (``train.refiner_objective.kept_errors``; chance: 1 / J).
* ``eval/mask_iou``, ``eval/matching_loss``, ``eval/matching_within_2px_map`` (the dense
  argmax of the matching loss, in map pixels: a diagnostic) and its position-only baseline
  ``eval/matching_within_2px_map_same_place``, ``eval/classification_loss``.
* ``eval/num_instances``; ``eval/unseen_share``: share of the evaluated instances whose mesh
  (by content) is not among the objects of the training split (:func:`training_digests`),
  1.0 for a truly held-out set.
"""

from __future__ import annotations

import hashlib
import json
import pathlib
from collections.abc import Mapping

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
from flax import nnx

from threept_jax.data.refiner_input import RefinerMeshes, load_mesh_paths, refiner_dataset
from threept_jax.eval.bop6d import MSSD_THRESHOLDS
from threept_jax.geometry.symmetry import symmetric_angle_deg
from threept_jax.losses.refiner import WITHIN_PX
from threept_jax.pipeline.refinement import map_pixel_centres
from train import sharding
from train.refiner_objective import (
    STEP_FIELDS,
    RefinerAssets,
    gt_cam_obj,
    kept_errors,
    objective,
    pose_errors,
    refine_batch,
    render_batch,
)
from train.run_config import loss_config, model_config, refine_settings, refiner_example_config


def mesh_digests(records_dir) -> dict[int, str]:
    """{obj_id: sha256 of the mesh file} of a records folder's objects."""
    return {k: hashlib.sha256(pathlib.Path(p).read_bytes()).hexdigest()
            for k, p in load_mesh_paths(records_dir).items()}


def training_digests(records_dir) -> set[str]:
    """Mesh digests of the objects the train split uses: those its ``index.json`` sources
    list (``datagen.pack`` writes them), or every object of the table without one."""
    digests = mesh_digests(records_dir)
    index = pathlib.Path(records_dir) / "train" / "index.json"
    if not index.exists():
        return set(digests.values())
    ids = {int(v) for src in json.loads(index.read_text()).get("sources", [])
           for v in src.get("obj_ids", {}).values()}
    return {digests[i] for i in ids if i in digests}


def average_recall(errors: np.ndarray, diameters: np.ndarray) -> float:
    """BOP's AR of an error [N] (mm) against diameters [N]: mean over BOP's
    ``MSSD_THRESHOLDS`` (``threept_jax.eval.bop6d``, fractions of the diameter) of the share
    under ``threshold * diameter`` (0 for N = 0)."""
    if errors.size == 0:
        return 0.0
    e = np.where(np.isfinite(errors), errors, np.inf)
    return float(np.mean(e[None] < MSSD_THRESHOLDS[:, None] * diameters[None]))


def match_accuracy(matches, crop_K: jax.Array, T_cam_obj_gt: jax.Array, *, crop_size: int,
                   map_size: int):
    """(within [B], within_identity [B], total [B]): weighted matches within 2 crop pixels of
    the ground truth, and how many would be if each render pixel were matched to the real
    pixel at the same place (the position-only baseline, which a network that has learnt
    nothing but where a pixel is reaches).

    matches: :class:`~threept_jax.pipeline.refinement.Matches` with leading [B, J, V];
    crop_K [B, V, 3, 3]; T_cam_obj_gt [B, V, 4, 4]; crop_size: H = W of the crops; map_size:
    h = w of the descriptor map.
    """
    X = matches.points_3d  # [B, J, V, N, 3]
    R, t = T_cam_obj_gt[:, None, :, None, :3, :3], T_cam_obj_gt[:, None, :, None, :3, 3]
    p = jnp.einsum("bjvnik,bjvnk->bjvni", jnp.broadcast_to(R, X.shape[:-1] + (3, 3)), X) + t
    uvw = jnp.einsum("bvik,bjvnk->bjvni", crop_K, p)
    uv = uvw[..., :2] / jnp.where(uvw[..., 2:] > 0, uvw[..., 2:], 1.0)
    same_place = map_pixel_centres(matches.render_pixel, map_size, crop_size)

    def near(q):
        return (jnp.sum(jnp.square(uv - q), -1) <= WITHIN_PX**2) & (uvw[..., 2] > 0)

    w = matches.weights > 0
    count = lambda m: jnp.sum(m & w, axis=(1, 2, 3)).astype(jnp.float32)  # noqa: E731
    return count(near(matches.points_2d)), count(near(same_place)), count(jnp.ones_like(w))


class RefinerEvaluator:
    """``evaluator(params) -> {"eval/...": float}`` (module docstring)."""

    def __init__(self, config: ml_collections.ConfigDict, graphdef: nnx.GraphDef,
                 mesh: jax.sharding.Mesh):
        c, e = config, config.eval
        self.mesh = mesh
        self.data_dir = e.data_dir or c.data_dir
        meshes = RefinerMeshes.from_records(self.data_dir, max_faces=c.refine.max_faces)
        self.assets = jax.device_put(RefinerAssets.from_meshes(meshes),
                                     sharding.replicated(mesh))
        train_digests = training_digests(c.data_dir)
        self.unseen = {k: d not in train_digests for k, d in mesh_digests(self.data_dir).items()}
        ds = refiner_dataset(self.data_dir, e.split, refiner_example_config(c), seed=e.seed,
                             batch_size=None, shuffle=False, repeat=False)
        n = min(len(ds), int(e.num_examples))
        if n == 0:
            raise ValueError(f"eval: {self.data_dir}/{e.split} holds no records; set "
                             "--config.eval.data_dir to a records folder of held-out objects")
        self.examples = [ds[i] for i in range(n)]
        self.batch_size = int(e.batch_size)
        self.num_steps = int(e.num_steps)
        self.fn = self._build(graphdef, model_config(c), loss_config(c), refine_settings(c))

    def _build(self, graphdef, model_cfg, loss_cfg, settings):
        num_steps = self.num_steps

        def run(params, batch, assets):
            model = nnx.merge(graphdef, params)
            sizes = dict(crop_size=model_cfg.crop_size, output_size=model_cfg.output_size,
                         ambient=settings.ambient)
            rend = render_batch(assets, batch, **sizes)
            out = model(batch["crops"], rend.rgb)
            _, metrics, step = objective(out, rend, assets, batch, loss_cfg, settings)
            within, same_place, total = match_accuracy(
                step.matches, batch["crop_K"].astype(jnp.float32), gt_cam_obj(batch),
                crop_size=model_cfg.crop_size, map_size=model_cfg.output_size)
            poses = batch["hypotheses"].astype(jnp.float32)
            after_1 = h = step.hypotheses
            for _ in range(num_steps - 1):
                r = render_batch(assets, batch, hypotheses=h, **sizes)
                h = refine_batch(model(batch["crops"], r.rgb), r, assets, batch, h,
                                 settings).hypotheses
            return {
                "poses": jnp.stack([poses, after_1, h], 1),  # [B, 3, J, 4, 4]
                "mssd": jnp.stack([pose_errors(assets, batch, x) for x in (poses, after_1, h)],
                                  1),
                "scores": out["scores"], "within": within, "same_place": same_place,
                "total": total,
                "num_pairs": jnp.full(within.shape, np.prod(rend.mask.shape[1:3]), jnp.float32),
                **{k: jnp.full(within.shape, v) for k, v in metrics.items()},
            }

        rep = sharding.replicated(self.mesh)
        return jax.jit(run, in_shardings=(None, sharding.batch_sharding(self.mesh), rep),
                       out_shardings=rep)

    def _batches(self):
        b = self.batch_size
        for start in range(0, len(self.examples), b):
            chunk = self.examples[start:start + b]
            pad = b - len(chunk)
            # The last batch is padded with invalid copies (left out of every metric).
            chunk = chunk + [{**chunk[0], "valid": np.bool_(False)}] * pad
            yield {k: np.stack([ex[k] for ex in chunk]) for k in chunk[0]}, len(chunk) - pad

    def __call__(self, params) -> dict[str, float]:
        rows: dict[str, list[np.ndarray]] = {}
        for host, n in self._batches():
            batch = sharding.global_batch({k: host[k] for k in STEP_FIELDS}, self.mesh)
            out = jax.device_get(self.fn(params, batch, self.assets))
            out = {k: np.asarray(v)[:n] for k, v in out.items()}
            for k in ("T_world_obj_gt", "diameter", "symmetries", "symmetry_mask", "valid",
                      "obj_id"):
                out[k] = host[k][:n]
            for k, v in out.items():
                rows.setdefault(k, []).append(v)
        r = {k: np.concatenate(v) for k, v in rows.items()}
        return summarize(r, num_steps=self.num_steps, unseen=self.unseen)


def summarize(r: Mapping[str, np.ndarray], *, num_steps: int,
              unseen: Mapping[int, bool]) -> dict[str, float]:
    """The ``eval/...`` metrics (module docstring) from per-instance arrays."""
    keep = r["valid"].astype(bool)
    out = {"eval/num_instances": float(keep.sum())}
    if not keep.any():
        return out
    poses, mssd = r["poses"][keep], r["mssd"][keep].astype(np.float64)  # [N, 3, J, ...]
    gt, diam = r["T_world_obj_gt"][keep].astype(np.float64), r["diameter"][keep]
    n, _, J = mssd.shape
    labels = ("before", "after_1", f"after_{num_steps}")
    for s, label in enumerate(labels):
        rot = np.concatenate([
            symmetric_angle_deg(poses[i, s, :, :3, :3], np.repeat(gt[i][None, :3, :3], J, 0),
                                r["symmetries"][keep][i][r["symmetry_mask"][keep][i]])
            for i in range(n)])
        trans = np.linalg.norm(poses[:, s, :, :3, 3] - gt[:, None, :3, 3], axis=-1).ravel()
        out[f"eval/rot_deg_{label}"] = float(np.median(rot))
        out[f"eval/trans_mm_{label}"] = float(np.median(trans))
        out[f"eval/ar_mssd_{label}"] = average_recall(mssd[:, s].ravel(),
                                                      np.repeat(diam, J).astype(np.float64))
    out["eval/ar_mssd_after"] = out[f"eval/ar_mssd_{labels[-1]}"]
    top = np.argmax(r["scores"][keep], axis=1)
    out["eval/ar_mssd_top_before"] = average_recall(mssd[np.arange(n), 0, top], diam)
    out["eval/ar_mssd_top_after"] = average_recall(mssd[np.arange(n), -1, top], diam)
    target = np.argmin(np.asarray(kept_errors(mssd[:, 0], mssd[:, 1])), axis=1)
    out["eval/score_acc"] = float(np.mean(top == target))
    out["eval/match_within_2px"] = float(r["within"][keep].sum()
                                         / max(r["total"][keep].sum(), 1.0))
    out["eval/match_within_2px_same_place"] = float(r["same_place"][keep].sum()
                                                    / max(r["total"][keep].sum(), 1.0))
    out["eval/matches_per_pair"] = float(r["total"][keep].sum() / r["num_pairs"][keep].sum())
    # The objective's batch means, copied to every row: the mean over valid rows weights each
    # batch by its valid instances.
    for src, name in (("matching/loss", "matching_loss"),
                      ("matching/within_2px", "matching_within_2px_map"),
                      ("matching/within_2px_same_place", "matching_within_2px_map_same_place"),
                      ("classification/loss", "classification_loss"),
                      ("segmentation/iou", "mask_iou")):
        out[f"eval/{name}"] = float(np.mean(r[src][keep]))
    out["eval/unseen_share"] = float(np.mean([unseen.get(int(o), False)
                                              for o in r["obj_id"][keep]]))
    return out


def evaluate_run(workdir, *, step="best", data_dir=None, split: str | None = None,
                 num_examples: int | None = None, subpixel: bool | None = None,
                 untrained: bool = False) -> dict:
    """The held-out metrics (module docstring) of a refiner run's checkpoint ``step`` (or of the
    untrained network of its config): the run's ``eval`` settings, ``data_dir`` / ``split`` /
    ``num_examples`` / ``subpixel`` overriding them when given. Adds ``step``."""
    from threept_jax.data.run_dir import RunDir
    from threept_jax.models.refiner import Refiner
    from train.run_config import default_config, flatten_config

    run = RunDir(workdir, model="refiner")
    if not run.config_file.exists():
        raise FileNotFoundError(f"{workdir} is not a refiner training run (no {run.config_file}); "
                                "pass the workdir of a python -m train.launch --model refiner run")
    config = default_config("refiner")
    config.update_from_flattened_dict(flatten_config(run.read_config()))
    if data_dir:
        config.eval.data_dir = str(data_dir)
    if split:
        config.eval.split = str(split)
    if num_examples:
        config.eval.num_examples = int(num_examples)
    if subpixel is not None:
        config.refine.subpixel = bool(subpixel)
    model, _, loaded = run.load_model(step)
    if untrained:
        model = Refiner(model_config(config), rngs=nnx.Rngs(0))
    graphdef, params = nnx.split(model)
    mesh = sharding.make_mesh(1, 1, jax.devices()[:1])
    config.eval.batch_size = min(int(config.eval.batch_size), int(config.eval.num_examples))
    # The run may have been restored onto every device; the evaluation runs on the first.
    params = jax.device_put(nnx.to_pure_dict(params), sharding.replicated(mesh))
    out = RefinerEvaluator(config, graphdef, mesh)(params)
    out["step"] = "untrained" if untrained else loaded
    return out


def main(argv=None) -> int:
    """``python -m train.eval_refiner --workdir RUN [--step best|latest|N] [--data-dir D]
    [--split train|val] [--num-examples N] [--subpixel on|off] [--untrained]``: the held-out
    evaluation of a refiner run's checkpoint (or of the untrained network of its config) as
    JSON on stdout."""
    import argparse
    import sys

    p = argparse.ArgumentParser(prog="python -m train.eval_refiner", description=main.__doc__)
    p.add_argument("--workdir", required=True, help="a refiner training run")
    p.add_argument("--step", default="best")
    p.add_argument("--data-dir", default=None, help="records of held-out objects (default: the "
                   "run's eval.data_dir, else its data_dir's val split)")
    p.add_argument("--split", choices=("train", "val"), default=None,
                   help="the split of the evaluation's records (default: the run's eval.split)")
    p.add_argument("--num-examples", type=int, default=None)
    p.add_argument("--subpixel", choices=("on", "off"), default=None,
                   help="override the run's refine.subpixel")
    p.add_argument("--untrained", action="store_true", help="evaluate freshly initialised weights")
    args = p.parse_args(argv)
    try:
        out = evaluate_run(args.workdir, step=args.step, data_dir=args.data_dir,
                           split=args.split, num_examples=args.num_examples,
                           subpixel=None if args.subpixel is None else args.subpixel == "on",
                           untrained=args.untrained)
    except FileNotFoundError as e:
        p.error(str(e))
    json.dump(out, sys.stdout, indent=1)
    print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
