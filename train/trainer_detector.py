"""3PT-D trainer: the detector's data, its pure sharded train step and its evaluator.

``train(config, workdir)`` (what ``train/launch.py`` runs for ``config.trainer = "detector"``)
builds a :class:`DetectorTrainer` and runs it to ``config.total_steps``; the run itself
(state, optimizer, checkpoints with the data iterator, resume, preemption, finiteness checks,
logs, progress bar) is :class:`train.trainer.Trainer`, shared with the refiner's trainer.

* **Input** (:mod:`threept_jax.data.detector_input`): grain ``MapDataset`` over the train shards,
  sliced per process, shuffled, repeated, one tile per example, batched per process;
  ``to_iter_dataset`` with read threads and, with ``data.num_workers > 0``, multiprocess
  prefetch. Each process's batch becomes its slice of global arrays sharded over the mesh.
* **Step** (:func:`make_train_step`): ``train_step(state, batch) -> (state, metrics)`` under
  ``jax.jit`` with explicit in/out shardings and the state donated; compiled once. The object
  tower embeds each example's 12 prior renders and its sampled templates, the image tower
  detects, and ``detection_loss`` gives the loss, run per batch shard in ``shard_map`` so that
  each device's Hungarian matching (a host callback) sees only its own tiles
  (:func:`sharded_detection_loss`). All randomness lives in the data pipeline (seeded per
  element), so the step needs no key and a resumed run is exact.
* **Config** (:mod:`train.run_config`): the library's dataclasses built from the config
  sections; keys outside the schema are refused.
* **Evaluation** (:mod:`train.eval_detector`) every ``eval.every_steps`` and at the end: full
  held-out images detected as inference does (``eval/ap50`` ranks the checkpoints by default,
  ``checkpoint.best_metric``), and the tile diagnostic (``eval/tile_diagnostic/...``).
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from typing import Any

import grain
import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import optax
from flax import nnx
from jax.sharding import PartitionSpec as P

from threept_jax.data.banks import BankFile, ObjectEntry, load_object_table
from threept_jax.data.detector_input import detection_dataset, find_shards
from threept_jax.losses.detection import DetectorLossConfig, detection_loss, make_targets
from threept_jax.models.configs import DetectorConfig
from threept_jax.models.detector import Detector
from train import sharding
from train.eval_detector import DetectorEvaluator
from train.run_config import example_config, loss_config, model_config, photometric_config
from train.trainer import (
    CompiledStep,
    Hook,
    StepCache,
    Trainer,
    apply_gradients,
    compile_step,
    make_optimizer,
)

#: Batch fields the train step reads; the others stay on the host.
STEP_FIELDS = ("image", "prior_rgb", "template_rgb", "template_index", "boxes", "mask")


# --------------------------------------------------------------------------- the step


def sharded_detection_loss(outputs: dict, targets: dict, loss_cfg: DetectorLossConfig,
                           mesh: jax.sharding.Mesh):
    """``detection_loss`` with the Hungarian matching run per device on its batch shard.

    Under plain ``jit`` the matcher's host callback would gather the whole batch's cost
    matrix onto one device (of one host). Here the loss runs in ``shard_map`` over the batch
    axes, so every device matches its own tiles and each host calls SciPy only for its own
    devices. ``detection_loss`` divides every term by the number of matched targets of its
    (local) batch, floored at 1; each term is turned back into a local sum, summed over the
    mesh and divided by the global count, which gives exactly the unsharded loss.
    """
    spec = lambda x: P() if jnp.ndim(x) == 0 else P(sharding.BATCH_AXES)  # noqa: E731

    def local(outputs, targets):
        _, metrics = detection_loss(outputs, targets, loss_cfg)
        n_local = metrics["num_boxes"]
        n_total = jax.lax.psum(n_local, sharding.BATCH_AXES)
        scale = jnp.maximum(n_local, 1.0)
        out = {k: jax.lax.psum(v * scale, sharding.BATCH_AXES) / jnp.maximum(n_total, 1.0)
               for k, v in metrics.items() if k != "num_boxes"}
        out["num_boxes"] = n_total
        return out["loss"], out

    args = (outputs, targets)
    return jax.shard_map(local, mesh=mesh, in_specs=jax.tree.map(spec, args),
                         out_specs=(P(), P()))(*args)


def make_train_step(graphdef: nnx.GraphDef, tx: optax.GradientTransformation,
                    schedule: optax.Schedule, loss_cfg: DetectorLossConfig,
                    tile_hw: tuple[int, int], mesh: jax.sharding.Mesh,
                    trace_counter: list[int] | None = None):
    """``train_step(state, batch) -> (state, metrics)``, pure (see the module docstring).

    ``batch`` holds :data:`STEP_FIELDS` with a leading batch axis B. ``trace_counter[0]`` is
    incremented each time the function is traced (tests use it to check it compiles once).
    """

    def loss_fn(params, batch):
        model = nnx.merge(graphdef, params)
        prior_tokens = model.embed_object(batch["prior_rgb"])  # [B, Np, D]
        bank = model.embed_templates(batch["template_rgb"])  # [B, Nt, E]
        outputs = model(batch["image"], prior_tokens, bank)
        targets = make_targets(batch["boxes"], tile_hw, batch["mask"],
                               template_index=batch["template_index"])
        return sharded_detection_loss(outputs, targets, loss_cfg, mesh)

    def train_step(state, batch):
        if trace_counter is not None:
            trace_counter[0] += 1
        (_, metrics), grads = jax.value_and_grad(loss_fn, has_aux=True)(state["params"], batch)
        return apply_gradients(state, grads, metrics, tx, schedule)

    return train_step


def build_step(model_cfg: DetectorConfig, loss_cfg: DetectorLossConfig,
               optim: Mapping[str, Any], total_steps: int, seed: int, mesh: jax.sharding.Mesh,
               fsdp_min_size: int) -> CompiledStep:
    """Model graph, abstract state, shardings, jitted init and jitted step (compiled on its
    first call). ``optim``: ``config.optim``."""
    tx, schedule = make_optimizer(optim, total_steps)
    make_model = lambda: Detector(model_cfg, rngs=nnx.Rngs(seed))  # noqa: E731
    graphdef = nnx.graphdef(nnx.eval_shape(make_model))
    counter = [0]
    step_fn = make_train_step(graphdef, tx, schedule, loss_cfg,
                              (model_cfg.image_size, model_cfg.image_size), mesh, counter)
    return compile_step(make_model, step_fn, tx, schedule, mesh, fsdp_min_size, counter)


# --------------------------------------------------------------------------- checks


def validate_data(data_dir, table: Mapping[int, ObjectEntry], num_templates: int,
                  max_banks: int = 64) -> None:
    """Fail early, with the fix, on missing shards, objects or small banks.

    Checks that train/ and val/ hold shards, that the first records use only objects of the
    table, and that the first ``max_banks`` banks of each split hold ``num_templates``
    templates (the pipeline checks every bank again when it opens it).
    """
    from array_record.python.array_record_data_source import ArrayRecordDataSource

    from threept_jax.data.records import decode_example

    for split in ("train", "val"):
        shards = find_shards(data_dir, split)
        source = ArrayRecordDataSource(shards)
        for i in range(min(len(source), 8)):
            ids = np.unique(decode_example(source[i])["obj_id"])
            missing = [int(o) for o in ids if int(o) not in table]
            if missing:
                raise KeyError(
                    f"{data_dir}/{split} record {i} uses objects {missing} that objects.json "
                    "does not list; re-run `python -m datagen.pack` so the table covers every "
                    "object of the shards")
    checked = 0
    for entry in table.values():
        if checked >= max_banks:
            break
        bank = BankFile(entry.bank_path)
        checked += 1
        if bank.num_templates < num_templates:
            raise ValueError(
                f"render bank {bank.path} of object {entry.obj_id} has {bank.num_templates} "
                f"templates but data.num_train_templates={num_templates}; lower "
                "--config.data.num_train_templates or render larger banks")


# --------------------------------------------------------------------------- the trainer


class DetectorTrainer(Trainer):
    """One 3PT-D run (module docstring; the run itself is :class:`train.trainer.Trainer`)."""

    step_fields = STEP_FIELDS
    data_hint = ("boxes inside the tiles, renders not blank (iterate "
                 "threept_jax.data.detector_input.detection_dataset by hand)")

    def prepare_data(self) -> None:
        c = self.config
        self.table = load_object_table(c.data_dir)
        validate_data(c.data_dir, self.table, c.data.num_train_templates)
        self.loss_cfg = loss_config(c)

    def step_key(self):
        c = self.config
        return ("detector", model_config(c), loss_config(c),
                json.dumps(c.optim.to_dict(), sort_keys=True), int(c.total_steps), int(c.seed),
                self.mesh, int(c.mesh.fsdp_min_size))

    def build_step(self) -> CompiledStep:
        c = self.config
        return build_step(model_config(c), loss_config(c), c.optim.to_dict(), int(c.total_steps),
                          int(c.seed), self.mesh, int(c.mesh.fsdp_min_size))

    def train_dataset(self) -> grain.MapDataset:
        c = self.config
        return detection_dataset(
            c.data_dir, "train",
            example_config(c, split="train", num_templates=c.data.num_train_templates),
            seed=c.seed, batch_size=self.local_batch, photometric=photometric_config(c),
            process_index=jax.process_index(), process_count=jax.process_count(),
            num_records=None if c.data.num_train_records < 0 else c.data.num_train_records,
            table=self.table)

    def make_evaluator(self) -> DetectorEvaluator:
        return DetectorEvaluator(self.config, self.compiled.graphdef, self.mesh, self.table)


def train(config: ml_collections.ConfigDict, workdir, hooks: Iterable[Hook] = (),
          devices=None, step_cache: StepCache | None = None,
          allow_config_change: bool = False) -> dict[str, Any]:
    """Build a :class:`DetectorTrainer` from ``config`` (resuming from ``workdir``) and run it."""
    return DetectorTrainer(config, workdir, devices=devices, step_cache=step_cache,
                           allow_config_change=allow_config_change).run(hooks)
