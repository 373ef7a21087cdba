"""What every trainer shares: optimizer, compiled-step cache, finiteness check, and the run.

A model's trainer (``train/trainer_detector.py``, ``train/trainer_refiner.py``) subclasses
:class:`Trainer` and supplies its data, its pure train step and its evaluator; everything
else of a run is here, once:

* **State**: ``{"step", "params", "opt_state"}``, params a plain nested dict of fp32 arrays,
  sharded by :mod:`train.sharding` (FSDP over ``mesh.fsdp`` for large arrays) and donated to
  the jitted step; a fresh run initialises it (or takes another run's best parameters,
  ``config.init_from``).
* **Optimizer** (:func:`make_optimizer`): AdamW after global-norm clipping, linear warmup and
  cosine decay, weight decay on matrices only.
* **Checks**: a config that breaks the schema, a batch the devices do not divide, a resume
  that changes what the run computes (:func:`train.run_config.check_resume_config`) or the
  model are refused before anything runs; each step's metrics are fetched one step late (so
  the host never stalls the device) and a non-finite loss or gradient norm stops the run
  naming the step and the terms (:func:`check_finite`).
* **Checkpoints** (:mod:`train.checkpointing`, layout :mod:`threept_jax.data.run_dir`) every
  ``checkpoint.every_steps``, after every evaluation, at the end and on SIGTERM (then the run
  stops), with the grain iterator, so a resumed run reads the same next batch.
* **Evaluation** every ``eval.every_steps`` and at the end; its metrics are saved with the
  checkpoint of that step and rank the checkpoints (``checkpoint.best_metric``).
* **Logs** (:mod:`train.logging_utils`): TensorBoard, the console and a progress bar.
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import math
import pathlib
import time
from collections.abc import Callable, Hashable, Iterable, Mapping
from typing import Any

import grain
import jax
import ml_collections
import numpy as np
import optax
from flax import nnx

from threept_jax.data.run_dir import RunDir
from train import sharding
from train.checkpointing import Checkpointer, Preemption, abstract_with_shardings
from train.logging_utils import MetricLogger
from train.run_config import OptimConfig, check_config, check_resume_config, model_config

#: hook(step, host_batch, host_metrics), called once per step after its metrics arrive.
Hook = Callable[[int, Mapping[str, np.ndarray], Mapping[str, float]], None]


def make_optimizer(optim: Mapping[str, Any], total_steps: int
                   ) -> tuple[optax.GradientTransformation, optax.Schedule]:
    """AdamW (decay on ndim >= 2 only) after global-norm clipping, warmup + cosine schedule.

    ``optim``: fields of :class:`train.run_config.OptimConfig` (``config.optim``). Its
    ``freeze`` groups get zero updates whatever trainer runs (their gradients are zeroed
    before the clipping, and they get no weight decay); a trainer may also put them behind
    :func:`hold_frozen` to skip their backward pass. With nothing frozen the optimizer state
    is as it was before ``freeze`` existed, so older checkpoints resume.
    """
    o = OptimConfig(**dict(optim))
    frozen = frozen_groups(o.freeze)
    warmup = int(min(o.warmup_steps, max(total_steps - 1, 0)))
    schedule = optax.warmup_cosine_decay_schedule(
        init_value=0.0, peak_value=o.learning_rate, warmup_steps=warmup,
        decay_steps=max(total_steps, warmup + 1), end_value=o.learning_rate * o.end_lr_factor)
    tx = optax.chain(
        optax.clip_by_global_norm(o.grad_clip_norm),
        optax.adamw(schedule, b1=o.b1, b2=o.b2, eps=o.eps, weight_decay=o.weight_decay,
                    mask=functools.partial(decay_mask, frozen=frozen)),
    )
    if frozen:
        tx = optax.chain(optax.masked(optax.set_to_zero(),
                                      functools.partial(frozen_mask, frozen=frozen)), tx)
    return tx, schedule


def decay_mask(params: Mapping[str, Any], frozen: frozenset[str] = frozenset()) -> dict:
    """Weight decay on matrices (ndim >= 2) outside the ``frozen`` groups."""
    return {k: jax.tree.map(lambda x, held=k in frozen: x.ndim >= 2 and not held, v)
            for k, v in params.items()}


def frozen_groups(freeze: str) -> frozenset[str]:
    """``OptimConfig.freeze`` (``"stem"``, ``"stem,encoder"``) as a set of top-level names."""
    return frozenset(k.strip() for k in str(freeze).split(",") if k.strip())


def _check_groups(params: Mapping[str, Any], frozen: frozenset[str]) -> None:
    unknown = sorted(frozen - set(params))
    if unknown:
        raise ValueError(f"optim.freeze names {unknown}, which the model does not have; its "
                         f"parameter groups: {sorted(params)}")


def frozen_mask(params: Mapping[str, Any], frozen: frozenset[str]) -> dict:
    """True on every leaf of the ``frozen`` groups (the optimizer zeroes their updates); an
    unknown name is a ValueError, for every trainer."""
    _check_groups(params, frozen)
    return {k: jax.tree.map(lambda _, held=k in frozen: held, v) for k, v in params.items()}


def hold_frozen(params: Mapping[str, Any], frozen: frozenset[str]) -> dict[str, Any]:
    """``params`` with the ``frozen`` groups behind ``jax.lax.stop_gradient`` (their gradient
    is zero, and XLA drops the backward pass through them); an unknown name is a ValueError."""
    _check_groups(params, frozen)
    return {k: jax.lax.stop_gradient(v) if k in frozen else v for k, v in params.items()}


def apply_gradients(state: Mapping[str, Any], grads: Any, metrics: Mapping[str, jax.Array],
                    tx: optax.GradientTransformation, schedule: optax.Schedule
                    ) -> tuple[dict[str, Any], dict[str, jax.Array]]:
    """The optimizer update of a train step, with the norms and learning rate it logs."""
    updates, opt_state = tx.update(grads, state["opt_state"], state["params"])
    params = optax.apply_updates(state["params"], updates)
    metrics = dict(metrics)
    metrics["grad_norm"] = optax.tree.norm(grads)
    metrics["param_norm"] = optax.tree.norm(params)
    metrics["learning_rate"] = jax.numpy.asarray(schedule(state["step"]), jax.numpy.float32)
    return {"step": state["step"] + 1, "params": params, "opt_state": opt_state}, metrics


def init_state(make_model: Callable[[], nnx.Module], tx: optax.GradientTransformation
               ) -> dict[str, Any]:
    """``{"step": 0, "params", "opt_state"}`` of a fresh model (parameters as a pure dict)."""
    model = make_model()
    _, params, rest = nnx.split(model, nnx.Param, ...)
    if jax.tree.leaves(rest):
        raise ValueError(f"{type(model).__name__} holds non-parameter state, which the trainer "
                         "does not carry; extend the train state")
    return fresh_state(nnx.to_pure_dict(params), tx)


def fresh_state(params: Any, tx: optax.GradientTransformation) -> dict[str, Any]:
    """``{"step": 0, "params", "opt_state"}`` of a run starting at ``params``: the optimizer's
    state at its start (AdamW's moments are zeros whatever the parameters' values)."""
    return {"step": jax.numpy.zeros((), jax.numpy.int32), "params": params,
            "opt_state": tx.init(params)}


@dataclasses.dataclass
class CompiledStep:
    """A jitted ``step(state, batch) -> (state, metrics)`` and what it needs.

    ``jitted`` is the ``jax.jit`` object itself (``jitted(state, batch)``, or
    ``jitted(state, batch, assets)`` with the placed ``assets`` when the step reads some), for
    ahead-of-time ``lower(...).compile()`` in benchmarks; ``step`` binds the assets. ``init()``
    is a fresh state at random parameters; ``start(params)`` one at given parameters
    (``init_from``), without compiling or running the random initialisation.
    """

    graphdef: nnx.GraphDef
    abstract_state: Any
    state_shardings: Any
    init: Callable[[], Any]
    step: Callable[[Any, Any], Any]
    schedule: optax.Schedule
    trace_counter: list[int]
    start: Callable[[Any], Any]
    jitted: Any = None
    assets: Any = None


#: XLA options for a program that runs so few times that compiling it fast matters more than
#: the code it makes: no LLVM optimisation, and on CPU the classic loop emitters instead of the
#: MLIR fusion emitters, which take longer to compile and make faster code (a CPU-only option;
#: other backends ignore it). The jitted initialisation (:func:`compile_step`) runs once per
#: run; the tests use them too (tests/conftest.py).
FAST_COMPILE_OPTIONS = {"xla_backend_optimization_level": 0, "xla_cpu_use_fusion_emitters": False}


def compile_step(make_model: Callable[[], nnx.Module], step_fn: Callable, tx, schedule,
                 mesh: jax.sharding.Mesh, fsdp_min_size: int, counter: list[int],
                 assets: Any = None) -> CompiledStep:
    """Abstract state, shardings, jitted init and jitted ``step_fn`` (state donated).

    ``assets``: a pytree the step reads besides the batch (the refiner's meshes), placed
    replicated on the mesh once and passed as ``step_fn(state, batch, assets)``; the
    returned step still takes ``(state, batch)``.
    """
    graphdef = nnx.graphdef(nnx.eval_shape(make_model))
    init = lambda: init_state(make_model, tx)  # noqa: E731
    abstract_state = jax.eval_shape(init)
    shardings = sharding.tree_shardings(abstract_state, mesh, fsdp_min_size)
    in_shardings = (shardings, sharding.batch_sharding(mesh))
    if assets is not None:
        in_shardings += (sharding.replicated(mesh),)
    jitted = jax.jit(step_fn, in_shardings=in_shardings,
                     out_shardings=(shardings, sharding.replicated(mesh)), donate_argnums=0)
    step, placed = jitted, None
    if assets is not None:
        placed = jax.device_put(assets, sharding.replicated(mesh))
        step = lambda state, batch: jitted(state, batch, placed)  # noqa: E731
    # The initialisation runs once: compiled without LLVM's optimisations (the refiner's tiny
    # config: 13.5 s -> 4.9 s to compile on 2 CPU cores, 0.01 s -> 0.05 s to run).
    init_jit = jax.jit(init, out_shardings=shardings, compiler_options=FAST_COMPILE_OPTIONS)
    start = jax.jit(functools.partial(fresh_state, tx=tx), in_shardings=(shardings["params"],),
                    out_shardings=shardings, donate_argnums=0,
                    compiler_options=FAST_COMPILE_OPTIONS)
    return CompiledStep(graphdef, abstract_state, shardings, init_jit, step, schedule, counter,
                        start, jitted=jitted, assets=placed)


class StepCache:
    """Built steps by everything they depend on (the trainer's ``step_key``), owned by its holder.

    A trainer makes its own unless given one; tests and benchmarks hand one cache to several
    trainers so that a trainer rebuilt in the same process (a resume) reuses the compiled
    executable instead of compiling again. Holds at most ``maxsize`` steps (least recently
    used dropped first).
    """

    def __init__(self, maxsize: int = 4):
        self.maxsize = maxsize
        self._steps: collections.OrderedDict[Any, CompiledStep] = collections.OrderedDict()

    def get(self, key: Hashable, build: Callable[[], CompiledStep]) -> CompiledStep:
        if key in self._steps:
            self._steps.move_to_end(key)
        else:
            self._steps[key] = build()
            while len(self._steps) > self.maxsize:
                self._steps.popitem(last=False)
        return self._steps[key]

    def clear(self) -> None:
        """Drop every step (the next ``get`` of each key builds it again)."""
        self._steps.clear()


def check_finite(step: int, metrics: Mapping[str, float], data_hint: str) -> None:
    """Stop with a clear message when the loss or the gradient norm is not finite."""
    if math.isfinite(metrics.get("loss", 0.0)) and math.isfinite(metrics.get("grad_norm", 0.0)):
        return
    bad = {k: v for k, v in metrics.items() if not math.isfinite(v)}
    terms = ", ".join(f"{k}={v}" for k, v in sorted(bad.items()))
    raise FloatingPointError(
        f"non-finite training metrics at step {step}: {terms}. The run stopped before saving "
        "this state; the last checkpoint is intact. Try a lower --config.optim.learning_rate, a "
        f"tighter --config.optim.grad_clip_norm or a longer warmup, and check the data: {data_hint}")


class Trainer:
    """State, data, step, checkpoints and logs of one run (module docstring).

    Subclasses set :attr:`step_fields` and :attr:`data_hint` and implement
    :meth:`prepare_data`, :meth:`step_key`, :meth:`build_step`, :meth:`train_dataset` and
    :meth:`make_evaluator`.
    """

    #: Batch fields the train step reads; the others stay on the host.
    step_fields: tuple[str, ...] = ()
    #: What to check in the data when the loss is not finite (:func:`check_finite`).
    data_hint: str = ""

    def __init__(self, config: ml_collections.ConfigDict, workdir, *, devices=None,
                 step_cache: StepCache | None = None, allow_config_change: bool = False):
        """``allow_config_change``: resume even when ``config`` changes keys of the run's
        config.json that a resume must keep (:func:`train.run_config.check_resume_config`);
        every change of a resume is recorded in the run's config history either way."""
        check_config(config)
        self.config = config
        self.workdir = pathlib.Path(workdir)
        self.run_dir = RunDir(workdir, model=config.trainer)
        if not config.data_dir:
            raise ValueError(
                "config.data_dir is empty: pass --config.data_dir=<records folder> (written by "
                "`python -m datagen.pack`; it holds train/, val/ and objects.json)")
        self.mesh = sharding.make_mesh(config.mesh.data, config.mesh.fsdp, devices)
        self.local_batch = sharding.check_batch_size(config.batch_size, self.mesh)
        if config.eval.every_steps > 0:
            # The evaluator is built at the first evaluation: refuse its batch now, not then.
            sharding.check_batch_size(config.eval.batch_size, self.mesh, "eval.batch_size")
        self.prepare_data()

        self.model_cfg = model_config(config)
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
        self.compiled = self.step_cache.get(self.step_key(), self.build_step)

        self.dataset = self.train_dataset()
        self.iterator = iter(self._iter_dataset(self.dataset))
        self.checkpointer = Checkpointer(
            self.workdir, max_to_keep=config.checkpoint.max_to_keep,
            best_metric=config.checkpoint.best_metric, best_mode=config.checkpoint.best_mode,
            async_save=config.checkpoint.async_save)
        latest = self.checkpointer.latest_step()
        if latest is None:
            if config.init_from:
                self.state = self.compiled.start(self._params_from(config.init_from))
            else:
                self.state = self.compiled.init()
                self.state["params"] = self.pretrained_params(self.state["params"])
            self.start_step = 0
        else:
            target = abstract_with_shardings(self.compiled.abstract_state,
                                             self.compiled.state_shardings)
            self.state = self.checkpointer.restore(latest, target, self.iterator)
            self.start_step = int(latest)
        self._evaluator = None

    # -- what a model's trainer supplies ------------------------------------------------

    def prepare_data(self) -> None:
        """Load and check what the run reads besides the records (called before the step)."""
        raise NotImplementedError

    def step_key(self) -> Hashable:
        """Everything :meth:`build_step` depends on (the :class:`StepCache` key)."""
        raise NotImplementedError

    def build_step(self) -> CompiledStep:
        raise NotImplementedError

    def train_dataset(self) -> grain.MapDataset:
        """This process's batched training examples (a repeating grain ``MapDataset``)."""
        raise NotImplementedError

    def make_evaluator(self) -> Callable[[Any], dict[str, float]]:
        """``evaluator(params) -> {"eval/...": float}``, built at the first evaluation."""
        raise NotImplementedError

    def pretrained_params(self, params: Any) -> Any:
        """A fresh run's initial parameters with any pretrained part loaded (a stem); by
        default ``params`` as initialised."""
        return params

    # -- shared ---------------------------------------------------------------------------

    def _params_from(self, run: str) -> Any:
        """The best checkpoint's parameters of another run of the same model (``init_from``)."""
        source = RunDir(run, model=self.config.trainer)
        if not source.model_file.exists():
            raise FileNotFoundError(
                f"config.init_from={run!r} is not a training run (no {source.model_file}); pass "
                "the --workdir of a run of the same model")
        source.check_same_model(self.model_cfg, fix=(
            "Fine-tuning keeps the model: train with that run's model section "
            f"({source.model_file})"))
        step = source.best_step()
        target = abstract_with_shardings(self.compiled.abstract_state["params"],
                                         self.compiled.state_shardings["params"])
        return source.restore_params(step, target)

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

    @property
    def step(self) -> int:
        return int(jax.device_get(self.state["step"]))

    def train_step(self, host_batch: Mapping[str, np.ndarray]) -> dict[str, jax.Array]:
        """Run one step on a host batch; returns the step's metrics (device arrays)."""
        batch = sharding.global_batch({k: host_batch[k] for k in self.step_fields}, self.mesh)
        self.state, metrics = self.compiled.step(self.state, batch)
        return metrics

    @property
    def evaluator(self):
        if self._evaluator is None:
            self._evaluator = self.make_evaluator()
        return self._evaluator

    def evaluate(self) -> dict[str, float]:
        return self.evaluator(self.state["params"])

    def save(self, metrics: Mapping[str, float] | None = None) -> None:
        self.checkpointer.save(self.step, self.state, self.iterator, metrics)

    def close(self) -> None:
        """Finish pending checkpoint writes and stop the input workers."""
        self.checkpointer.close()
        self.iterator.close()

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
            check_finite(step, host, self.data_hint)
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
                # An evaluation's metrics rank the checkpoint of its step: always save one.
                do_save = last or do_eval or (c.checkpoint.every_steps > 0
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
