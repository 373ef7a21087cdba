"""3PT-D trainer: one pure, sharded train step and a short loop around it.

``train(config, workdir)`` (what ``train/launch.py`` runs) builds a :class:`DetectorTrainer`
and runs it to ``config.total_steps``:

* **Input** (:mod:`threept_jax.data.detector_input`): grain ``MapDataset`` over the train shards,
  sliced per process, shuffled, repeated, one tile per example, batched per process;
  ``to_iter_dataset`` with read threads and, with ``data.num_workers > 0``, multiprocess
  prefetch. Each process's batch becomes its slice of global arrays sharded over the mesh.
* **Step** (:func:`make_train_step`): ``train_step(state, batch) -> (state, metrics)`` with
  ``state = {"step", "params", "opt_state"}`` (params as a plain nested dict of fp32 arrays;
  the model runs in ``model.dtype``), under ``jax.jit`` with explicit in/out shardings and the
  state donated; compiled once. The object tower embeds each example's 12 prior renders and
  its sampled templates, the image tower detects, and ``detection_loss`` gives the loss, run
  per batch shard in ``shard_map`` so that each device's Hungarian matching (a host callback)
  sees only its own tiles (:func:`sharded_detection_loss`). AdamW with linear warmup + cosine
  decay, global-norm clipping, weight decay on matrices only. All randomness lives in the
  data pipeline (seeded per element), so the step needs no key and a resumed run is exact.
* **Checks**: each step's metrics are fetched one step late (so the host never stalls the
  device) and a non-finite loss or gradient norm stops the run naming the step and the terms.
* **Config** (:mod:`train.run_config`): the library's dataclasses built from the config
  sections; keys outside the schema are refused. The compiled step lives in a
  :class:`StepCache` owned by the trainer (or handed to several trainers).
* **Checkpoints** (:mod:`train.checkpointing`, layout :mod:`threept_jax.data.run_dir`) every
  ``checkpoint.every_steps``, at the end and on SIGTERM (then the run stops), with the grain
  iterator; the run resumes from the latest one in ``workdir``, refusing a config that changes
  what the run computes (:func:`train.run_config.check_resume_config`; every change of a
  resume is kept in ``config_history.json``).
* **Evaluation** (:mod:`train.eval_detector`) every ``eval.every_steps`` and at the end: full
  held-out images detected as inference does (``eval/ap50`` ranks the checkpoints by default,
  ``checkpoint.best_metric``), and the tile diagnostic (``eval/tile_diagnostic/...``).
* **Logs** (:mod:`train.logging_utils`): loss terms, learning rate, grad/param norms,
  examples/s to TensorBoard (``<workdir>/tb``) and the console, and a progress bar.
"""

from __future__ import annotations

import collections
import dataclasses
import json
import math
import pathlib
import time
from collections.abc import Callable, Iterable, Mapping
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
from threept_jax.data.run_dir import RunDir
from threept_jax.losses.detection import DetectorLossConfig, detection_loss, make_targets
from threept_jax.models.configs import DetectorConfig
from threept_jax.models.detector import Detector
from train import sharding
from train.checkpointing import Checkpointer, Preemption, abstract_with_shardings
from train.eval_detector import DetectorEvaluator
from train.logging_utils import MetricLogger
from train.run_config import (
    OptimConfig,
    check_config,
    check_resume_config,
    example_config,
    loss_config,
    model_config,
    photometric_config,
)

#: Batch fields the train step reads; the others stay on the host.
STEP_FIELDS = ("image", "prior_rgb", "template_rgb", "template_index", "boxes", "mask")

#: hook(step, host_batch, host_metrics), called once per step after its metrics arrive.
Hook = Callable[[int, Mapping[str, np.ndarray], Mapping[str, float]], None]


# --------------------------------------------------------------------------- optimizer


def make_optimizer(optim: Mapping[str, Any], total_steps: int
                   ) -> tuple[optax.GradientTransformation, optax.Schedule]:
    """AdamW (decay on ndim >= 2 only) after global-norm clipping, warmup + cosine schedule.

    ``optim``: fields of :class:`train.run_config.OptimConfig` (``config.optim``).
    """
    o = OptimConfig(**dict(optim))
    warmup = int(min(o.warmup_steps, max(total_steps - 1, 0)))
    schedule = optax.warmup_cosine_decay_schedule(
        init_value=0.0, peak_value=o.learning_rate, warmup_steps=warmup,
        decay_steps=max(total_steps, warmup + 1), end_value=o.learning_rate * o.end_lr_factor)
    tx = optax.chain(
        optax.clip_by_global_norm(o.grad_clip_norm),
        optax.adamw(schedule, b1=o.b1, b2=o.b2, eps=o.eps, weight_decay=o.weight_decay,
                    mask=lambda p: jax.tree.map(lambda x: x.ndim >= 2, p)),
    )
    return tx, schedule


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
        updates, opt_state = tx.update(grads, state["opt_state"], state["params"])
        params = optax.apply_updates(state["params"], updates)
        metrics = dict(metrics)
        metrics["grad_norm"] = optax.tree.norm(grads)
        metrics["param_norm"] = optax.tree.norm(params)
        metrics["learning_rate"] = jnp.asarray(schedule(state["step"]), jnp.float32)
        new_state = {"step": state["step"] + 1, "params": params, "opt_state": opt_state}
        return new_state, metrics

    return train_step


@dataclasses.dataclass
class CompiledStep:
    """The jitted step and what it needs (:func:`build_step`)."""

    graphdef: nnx.GraphDef
    abstract_state: Any
    state_shardings: Any
    init: Callable[[], Any]
    step: Callable[[Any, Any], Any]
    schedule: optax.Schedule
    trace_counter: list[int]


def build_step(model_cfg: DetectorConfig, loss_cfg: DetectorLossConfig,
               optim: Mapping[str, Any], total_steps: int, seed: int, mesh: jax.sharding.Mesh,
               fsdp_min_size: int) -> CompiledStep:
    """Model graph, abstract state, shardings, jitted init and jitted step (compiled on its
    first call). ``optim``: ``config.optim``. :class:`StepCache` keeps them for reuse."""
    tx, schedule = make_optimizer(optim, total_steps)

    def init():
        model = Detector(model_cfg, rngs=nnx.Rngs(seed))
        graphdef, params, rest = nnx.split(model, nnx.Param, ...)
        if jax.tree.leaves(rest):
            raise ValueError("the detector holds non-parameter state, which this trainer does "
                             "not carry; extend the train state")
        params = nnx.to_pure_dict(params)
        return {"step": jnp.zeros((), jnp.int32), "params": params,
                "opt_state": tx.init(params)}

    graphdef = nnx.graphdef(nnx.eval_shape(lambda: Detector(model_cfg, rngs=nnx.Rngs(seed))))
    abstract_state = jax.eval_shape(init)
    shardings = sharding.tree_shardings(abstract_state, mesh, fsdp_min_size)
    counter = [0]
    step_fn = make_train_step(graphdef, tx, schedule, loss_cfg,
                              (model_cfg.image_size, model_cfg.image_size), mesh, counter)
    jitted = jax.jit(step_fn, in_shardings=(shardings, sharding.batch_sharding(mesh)),
                     out_shardings=(shardings, sharding.replicated(mesh)), donate_argnums=0)
    init_jit = jax.jit(init, out_shardings=shardings)
    return CompiledStep(graphdef, abstract_state, shardings, init_jit, jitted, schedule, counter)


class StepCache:
    """Built steps (:func:`build_step`) by everything they depend on, owned by its holder.

    A trainer makes its own unless given one; tests and benchmarks hand one cache to several
    trainers so that a trainer rebuilt in the same process (a resume) reuses the compiled
    executable instead of compiling again. Holds at most ``maxsize`` steps (least recently
    used dropped first).
    """

    def __init__(self, maxsize: int = 4):
        self.maxsize = maxsize
        self._steps: collections.OrderedDict[Any, CompiledStep] = collections.OrderedDict()

    def get(self, config: ml_collections.ConfigDict, mesh: jax.sharding.Mesh) -> CompiledStep:
        model_cfg, loss_cfg = model_config(config), loss_config(config)
        optim = config.optim.to_dict()
        key = (model_cfg, loss_cfg, json.dumps(optim, sort_keys=True), int(config.total_steps),
               int(config.seed), mesh, int(config.mesh.fsdp_min_size))
        if key in self._steps:
            self._steps.move_to_end(key)
        else:
            self._steps[key] = build_step(model_cfg, loss_cfg, optim, *key[3:])
            while len(self._steps) > self.maxsize:
                self._steps.popitem(last=False)
        return self._steps[key]


# --------------------------------------------------------------------------- checks


def check_finite(step: int, metrics: Mapping[str, float]) -> None:
    """Stop with a clear message when the loss or the gradient norm is not finite."""
    if math.isfinite(metrics.get("loss", 0.0)) and math.isfinite(metrics.get("grad_norm", 0.0)):
        return
    bad = {k: v for k, v in metrics.items() if not math.isfinite(v)}
    terms = ", ".join(f"{k}={v}" for k, v in sorted(bad.items()))
    raise FloatingPointError(
        f"non-finite training metrics at step {step}: {terms}. The run stopped before saving "
        "this state; the last checkpoint is intact. Try a lower --config.optim.learning_rate, a "
        "tighter --config.optim.grad_clip_norm or a longer warmup, and check the data (boxes "
        "inside the tiles, renders not blank) by iterating threept_jax.data.detector_input."
        "detection_dataset by hand.")


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


class DetectorTrainer:
    """State, data, step, checkpoints and logs of one 3PT-D run (module docstring)."""

    def __init__(self, config: ml_collections.ConfigDict, workdir, *, devices=None,
                 step_cache: StepCache | None = None, allow_config_change: bool = False):
        """``allow_config_change``: resume even when ``config`` changes keys of the run's
        config.json that a resume must keep (:func:`train.run_config.check_resume_config`);
        every change of a resume is recorded in the run's config history either way."""
        check_config(config)
        self.config = config
        self.workdir = pathlib.Path(workdir)
        self.run_dir = RunDir(workdir)
        if not config.data_dir:
            raise ValueError(
                "config.data_dir is empty: pass --config.data_dir=<records folder> (written by "
                "`python -m datagen.pack`; it holds train/, val/, objects.json and banks/)")
        self.mesh = sharding.make_mesh(config.mesh.data, config.mesh.fsdp, devices)
        self.local_batch = sharding.check_batch_size(config.batch_size, self.mesh)
        if config.eval.every_steps > 0:
            # The evaluator is built at the first evaluation: refuse its batch now, not then.
            sharding.check_batch_size(config.eval.batch_size, self.mesh, "eval.batch_size")
        self.table = load_object_table(config.data_dir)
        validate_data(config.data_dir, self.table, config.data.num_train_templates)

        self.model_cfg = model_config(config)
        self.loss_cfg = loss_config(config)
        saved_steps = self.run_dir.checkpoint_steps()
        changes, forced = {}, []
        if saved_steps:
            # Before Orbax meets parameters of other shapes.
            self.run_dir.check_same_model(self.model_cfg)
            saved = self.run_dir.read_config()
            changes, forced = check_resume_config(saved, config,
                                                  allow_change=allow_config_change,
                                                  config_file=self.run_dir.config_file)
        if jax.process_index() == 0:
            if changes:
                self.run_dir.record_config_change(saved_steps[-1], changes, saved, forced=forced)
            self.run_dir.write_config(config.to_json_best_effort(indent=2, sort_keys=True))
            self.run_dir.write_model_config(self.model_cfg)
        self.step_cache = StepCache() if step_cache is None else step_cache
        self.compiled = self.step_cache.get(config, self.mesh)

        self.dataset = self._train_dataset()
        self.iterator = iter(self._iter_dataset(self.dataset))
        self.checkpointer = Checkpointer(
            self.workdir, max_to_keep=config.checkpoint.max_to_keep,
            best_metric=config.checkpoint.best_metric, best_mode=config.checkpoint.best_mode,
            async_save=config.checkpoint.async_save)
        latest = self.checkpointer.latest_step()
        if latest is None:
            self.state = self.compiled.init()
            if config.init_from:
                self.state["params"] = self._params_from(config.init_from)
            self.start_step = 0
        else:
            target = abstract_with_shardings(self.compiled.abstract_state,
                                             self.compiled.state_shardings)
            self.state = self.checkpointer.restore(latest, target, self.iterator)
            self.start_step = int(latest)
        self._evaluator = None

    def _params_from(self, run: str) -> Any:
        """The best checkpoint's parameters of another run of the same model (``init_from``)."""
        source = RunDir(run)
        if not source.model_file.exists():
            raise FileNotFoundError(
                f"config.init_from={run!r} is not a training run (no {source.model_file}); pass "
                "the --workdir of a detector run")
        source.check_same_model(self.model_cfg, fix=(
            "Fine-tuning keeps the model: train with that run's model section "
            f"({source.model_file})"))
        step = source.best_step()
        target = abstract_with_shardings(self.compiled.abstract_state["params"],
                                         self.compiled.state_shardings["params"])
        return source.restore_params(step, target)

    # -- data ----------------------------------------------------------------------------

    def _train_dataset(self) -> grain.MapDataset:
        c = self.config
        photometric = photometric_config(c)
        return detection_dataset(
            c.data_dir, "train",
            example_config(c, split="train", num_templates=c.data.num_train_templates),
            seed=c.seed, batch_size=self.local_batch, photometric=photometric,
            process_index=jax.process_index(), process_count=jax.process_count(),
            num_records=None if c.data.num_train_records < 0 else c.data.num_train_records,
            table=self.table)

    def _iter_dataset(self, ds: grain.MapDataset) -> grain.IterDataset:
        d = self.config.data
        it = ds.to_iter_dataset(grain.ReadOptions(num_threads=d.read_threads,
                                                  prefetch_buffer_size=d.prefetch_buffer_size))
        if d.num_workers > 0:
            from absl import flags

            # Grain's workers read absl flags; programs that did not parse any (tests, a demo
            # calling train()) get the defaults.
            if not flags.FLAGS.is_parsed():
                flags.FLAGS.mark_as_parsed()
            it = it.mp_prefetch(grain.MultiprocessingOptions(
                num_workers=d.num_workers, per_worker_buffer_size=d.worker_buffer_size))
        return it

    def next_batch(self) -> dict[str, np.ndarray]:
        """This process's next batch (host arrays, every pipeline field)."""
        return next(self.iterator)

    # -- steps ---------------------------------------------------------------------------

    @property
    def step(self) -> int:
        return int(jax.device_get(self.state["step"]))

    def train_step(self, host_batch: Mapping[str, np.ndarray]) -> dict[str, jax.Array]:
        """Run one step on a host batch; returns the step's metrics (device arrays)."""
        batch = sharding.global_batch({k: host_batch[k] for k in STEP_FIELDS}, self.mesh)
        self.state, metrics = self.compiled.step(self.state, batch)
        return metrics

    @property
    def evaluator(self):
        if self._evaluator is None:
            self._evaluator = DetectorEvaluator(self.config, self.compiled.graphdef, self.mesh,
                                                self.table)
        return self._evaluator

    def evaluate(self) -> dict[str, float]:
        return self.evaluator(self.state["params"])

    def save(self, metrics: Mapping[str, float] | None = None) -> None:
        self.checkpointer.save(self.step, self.state, self.iterator, metrics)

    def close(self) -> None:
        """Finish pending checkpoint writes and stop the input workers."""
        self.checkpointer.close()
        self.iterator.close()

    # -- loop ----------------------------------------------------------------------------

    def run(self, hooks: Iterable[Hook] = ()) -> dict[str, Any]:
        """Train to ``total_steps``, or until SIGTERM (then save and return early).

        Returns the last logged train and eval metrics, and under ``"preempted"`` the step
        saved on SIGTERM (None when the run reached ``total_steps``).
        """
        c = self.config
        hooks = list(hooks)
        is_main = jax.process_index() == 0
        logger = MetricLogger(self.workdir, total_steps=c.total_steps,
                              start_step=self.start_step, examples_per_step=c.batch_size,
                              enabled=is_main, progress_bar=c.progress_bar)
        if self.start_step:
            logger.print(f"resumed from {self.checkpointer.directory}/{self.start_step}")
        summary: dict[str, Any] = {"train": {}, "eval": {}, "preempted": None}
        pending = None
        preemption = Preemption(self.checkpointer.manager)
        preemption.install()

        def finish(item):
            step, host_batch, metrics = item
            host = {k: float(v) for k, v in jax.device_get(metrics).items()}
            check_finite(step, host)
            logger.update(host)
            for hook in hooks:
                hook(step, host_batch, host)
            if step % c.log_every == 0 or step == c.total_steps:
                summary["train"] = logger.flush(step)

        try:
            for step in range(self.start_step + 1, c.total_steps + 1):
                host_batch = self.next_batch()
                metrics = self.train_step(host_batch)
                if step == self.start_step + 1:
                    jax.block_until_ready(metrics)  # compilation: keep it out of examples/s
                    logger.reset_clock()
                if pending is not None:
                    finish(pending)
                pending = (step, host_batch if hooks else None, metrics)
                last = step == c.total_steps
                do_eval = c.eval.every_steps > 0 and (step % c.eval.every_steps == 0 or last)
                do_save = last or (c.checkpoint.every_steps > 0
                                   and step % c.checkpoint.every_steps == 0)
                if do_eval or do_save:
                    finish(pending)
                    pending = None
                eval_metrics = None
                if do_eval:
                    t0 = time.perf_counter()
                    eval_metrics = self.evaluate()
                    eval_metrics["eval/time_s"] = time.perf_counter() - t0
                    summary["eval"] = eval_metrics
                    logger.write(step, eval_metrics)
                if do_save:
                    self.save(eval_metrics)
                if do_eval or do_save:
                    logger.reset_clock()
                if preemption.reached(step):
                    if pending is not None:
                        finish(pending)
                        pending = None
                    if not do_save:
                        self.save()
                    summary["preempted"] = step
                    logger.print(f"SIGTERM: saved step {step} to {self.checkpointer.directory}; "
                                 "start the same command again to resume")
                    break
            if pending is not None:
                finish(pending)
        finally:
            preemption.uninstall()
            self.close()
            logger.close()
        return summary


def train(config: ml_collections.ConfigDict, workdir, hooks: Iterable[Hook] = (),
          devices=None, step_cache: StepCache | None = None,
          allow_config_change: bool = False) -> dict[str, Any]:
    """Build a :class:`DetectorTrainer` from ``config`` (resuming from ``workdir``) and run it."""
    return DetectorTrainer(config, workdir, devices=devices, step_cache=step_cache,
                           allow_config_change=allow_config_change).run(hooks)
