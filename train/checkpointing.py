"""Orbax checkpoints of a training run: state (model, optimizer, step) and the grain iterator.

One ``ocp.CheckpointManager`` in ``<workdir>/checkpoints`` saves, at each checkpoint step, a
composite of (item names and layout: :mod:`threept_jax.data.run_dir`)

* ``state``: the train state pytree (``step``, ``params``, ``opt_state``), restored straight
  into its shardings (``StandardRestore`` with abstract arrays that carry them), and
* ``data``: the grain ``DatasetIterator`` state (``grain.checkpoint.CheckpointSave``: one JSON
  file per process), so a resumed run reads the same next batch.

Preemption (:class:`Preemption`): SIGTERM, which Slurm, Kubernetes and Cloud TPU send before
they stop a job, makes the trainer save a checkpoint at the next step and return.

Preservation: the latest ``max_to_keep`` checkpoints, plus the best one by ``best_metric``
among those saved with evaluation metrics (``AnyPreservationPolicy(LatestN, BestN)``).
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Mapping
from typing import Any

import grain
import jax
import orbax.checkpoint as ocp
from orbax.checkpoint import checkpoint_managers as policies

from threept_jax.data import run_dir


class Checkpointer:
    """Save / restore of (train state, data iterator) with the module's preservation policy."""

    def __init__(self, workdir, *, max_to_keep: int = 3, best_metric: str | None = "eval/ap50",
                 best_mode: str = "max", async_save: bool = True):
        if max_to_keep < 1:
            raise ValueError(f"checkpoint.max_to_keep must be >= 1, got {max_to_keep}")
        if best_mode not in ("max", "min"):
            raise ValueError(f"checkpoint.best_mode must be 'max' or 'min', got {best_mode!r}")
        self.directory = run_dir.RunDir(workdir).checkpoint_dir
        self.best_metric = best_metric or None
        keep = [policies.LatestN(n=max_to_keep)]
        metric_fn = run_dir.metric_fn(self.best_metric) if self.best_metric else None
        if metric_fn:
            keep.append(policies.BestN(get_metric_fn=metric_fn, reverse=best_mode == "min", n=1,
                                       keep_checkpoints_without_metrics=False))
        # best_fn also makes Orbax store each step's metrics with it (``metrics`` item), so the
        # best checkpoint is still known after a restart and to inference (run_dir.best_step).
        options = ocp.CheckpointManagerOptions(
            preservation_policy=policies.AnyPreservationPolicy(keep),
            best_fn=metric_fn,
            best_mode=best_mode,
            enable_async_checkpointing=async_save,
            create=True,
        )
        self.manager = ocp.CheckpointManager(self.directory, options=options)

    def latest_step(self) -> int | None:
        return self.manager.latest_step()

    def all_steps(self) -> list[int]:
        return list(self.manager.all_steps())

    def save(self, step: int, state: Any, data_iterator: grain.DatasetIterator | None,
             metrics: Mapping[str, float] | None = None) -> None:
        """Save at ``step`` (asynchronously when enabled). ``metrics`` must hold
        ``best_metric`` for the checkpoint to compete for "best"."""
        items = {run_dir.STATE_ITEM: ocp.args.StandardSave(state)}
        if data_iterator is not None:
            items[run_dir.DATA_ITEM] = grain.checkpoint.CheckpointSave(data_iterator)
        if metrics is not None and self.best_metric and self.best_metric not in metrics:
            metrics = None
        self.manager.save(step, args=ocp.args.Composite(**items),
                          metrics=None if metrics is None else {k: float(v) for k, v in
                                                                metrics.items()},
                          force=True)

    def restore(self, step: int, abstract_state: Any,
                data_iterator: grain.DatasetIterator | None) -> Any:
        """Restore ``step`` into ``abstract_state`` (ShapeDtypeStructs with shardings); the
        data iterator, when given, is set to its saved position in place."""
        items = {run_dir.STATE_ITEM: ocp.args.StandardRestore(abstract_state)}
        if data_iterator is not None:
            if not (self.directory / str(step) / run_dir.DATA_ITEM).exists():
                raise FileNotFoundError(
                    f"checkpoint {self.directory / str(step)} has no data iterator state; it was "
                    "not written by this trainer (start from a fresh --workdir)")
            items[run_dir.DATA_ITEM] = grain.checkpoint.CheckpointRestore(data_iterator)
        restored = self.manager.restore(step, args=ocp.args.Composite(**items))
        return restored[run_dir.STATE_ITEM]

    def wait(self) -> None:
        self.manager.wait_until_finished()

    def close(self) -> None:
        self.manager.wait_until_finished()
        self.manager.close()


def abstract_with_shardings(tree: Any, shardings: Any) -> Any:
    """ShapeDtypeStructs of ``tree`` carrying ``shardings`` (restore targets)."""
    return jax.tree.map(
        lambda x, s: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=s), tree, shardings)


class Preemption:
    """``preemption.reached(step)``: has the job been told to stop (SIGTERM) by this step?

    With several processes, ``jax.distributed.initialize()`` starts JAX's preemption sync
    manager, which catches SIGTERM on any host and agrees with the others on the step at which
    all of them save (Orbax's ``CheckpointManager.reached_preemption``, which every process
    must call at every step). With one process that manager does not run; a SIGTERM handler
    sets a flag instead, read at the next step. ``install()`` sets that handler,
    ``uninstall()`` puts the previous one back.
    """

    def __init__(self, manager: ocp.CheckpointManager):
        self.manager = manager
        self.multi_process = jax.process_count() > 1
        self._flag = threading.Event()
        self._previous = None
        self._installed = False

    def install(self) -> None:
        # signal.signal works only on the main thread; elsewhere (a trainer run from a worker
        # thread) SIGTERM keeps its default meaning.
        if not self.multi_process and threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGTERM, self._on_signal)
            self._installed = True

    def uninstall(self) -> None:
        if self._installed:
            # None: the previous handler was not set from Python; SIG_DFL is what it was.
            signal.signal(signal.SIGTERM, self._previous or signal.SIG_DFL)
            self._installed = False

    def _on_signal(self, signum, frame) -> None:
        self._flag.set()

    def reached(self, step: int) -> bool:
        if self.multi_process:
            return bool(self.manager.reached_preemption(step))
        return self._flag.is_set()
