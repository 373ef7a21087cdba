"""What the orchestrating commands share (``train.adapt``, ``train.campaign``, the demo): the
training-budget constants, the warm step time of a config measured here, stage headings with
their times, and progress bars that stay readable in a log file."""

from __future__ import annotations

import functools
import os
import sys
import tempfile
import time

#: Share of each training budget kept for the periodic evaluations and checkpoints of the run.
EVAL_SHARE = 0.15
#: Steps timed for the budget (after one compiling step and two warm-up steps).
TIMED_STEPS = 8
#: The configs of train/configs/detector.py and refiner.py.
CONFIGS = ("tiny", "cpu", "small", "paper")


@functools.cache
def _step_cache():
    """This process's compiled train steps (``train.trainer.StepCache``): a later run of the
    same model and config in one process (``campaign.main`` or ``adapt.main`` called again
    from Python, a notebook, the tests) reuses the compiled step and initialisation."""
    from train.trainer import StepCache

    return StepCache(maxsize=2)


def log_friendly_progress() -> None:
    """Progress bars written to a file rather than a terminal (a CI or ``make demo > log``)
    redraw every 30 s instead of 10 times a second: a readable log, not megabytes of
    carriage returns. tqdm reads ``TQDM_MININTERVAL`` when it is imported, so call this first."""
    if not sys.stderr.isatty():
        os.environ.setdefault("TQDM_MININTERVAL", "30")


def stage(text: str) -> float:
    """Print a stage heading; its start time."""
    print(f"\n== {text}", flush=True)
    return time.perf_counter()


def done(start: float) -> float:
    """Print and return the seconds since ``start``."""
    seconds = time.perf_counter() - start
    print(f"   ({seconds:.0f} s)", flush=True)
    return seconds


def measure_step_seconds(config) -> float:
    """Warm seconds per train step of ``config`` (detector or refiner) here: a throw-away run
    of its trainer in a temp folder."""
    import jax

    from train.trainers import trainer_class

    probe = config.copy_and_resolve_references()
    probe.eval.every_steps = 0
    probe.init_from = ""
    with tempfile.TemporaryDirectory() as tmp:
        trainer = trainer_class(probe)(probe, tmp)
        try:
            for i in range(3 + TIMED_STEPS):
                if i == 3:
                    start = time.perf_counter()
                jax.block_until_ready(trainer.train_step(trainer.next_batch()))
            return (time.perf_counter() - start) / TIMED_STEPS
        finally:
            trainer.close()


def train_to(config, steps: int, workdir, *, evals: int, checkpoint_every: int | None = None,
             log_every: int | None = None) -> dict | None:
    """Train ``config``'s model to ``steps`` in ``workdir``, resuming from its last checkpoint:
    ``evals`` held-out evaluations over the run, a checkpoint at each of them (or every
    ``checkpoint_every`` steps) and on SIGTERM. The trainer's summary, or None when the last
    checkpoint is already at ``steps``."""
    from threept_jax.data.run_dir import RunDir
    from train.trainers import trainer_class

    finished = RunDir(workdir, model=config.trainer).checkpoint_steps()
    if finished and finished[-1] >= steps:
        print(f"   finished (checkpoint at step {finished[-1]}), skipped", flush=True)
        return None
    config.total_steps = steps
    config.eval.every_steps = max(steps // evals, 1)
    config.checkpoint.every_steps = max(1, min(steps, checkpoint_every or steps // evals))
    config.log_every = max(1, min(log_every or steps // 20, config.checkpoint.every_steps))
    return trainer_class(config)(config, workdir, step_cache=_step_cache()).run()

