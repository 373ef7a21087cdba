"""Load a trained 3PT-D or 3PT-R from a training workdir for inference.

The workdir's format (``detector.json`` or ``refiner.json``, ``config.json``, Orbax steps under
``checkpoints/`` with the train state in the ``state`` item, the best step) is defined by
:mod:`threept_jax.data.run_dir`, which the trainers write through. Inference restores the
parameters alone, on the default device, without the optimizer state or the data iterator.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping

from threept_jax.data.run_dir import RunDir
from threept_jax.models.configs import DetectorConfig, RefinerConfig
from threept_jax.models.detector import Detector
from threept_jax.models.refiner import Refiner
from threept_jax.pipeline.refinement import RefineSettings


def saved_metrics(workdir, step: int) -> dict[str, float]:
    """The evaluation metrics saved with checkpoint ``step`` of a training run ({} if none)."""
    return RunDir(workdir).saved_metrics(step)


def load_detector(workdir, step: int | str = "best", dtype: str | None = None
                  ) -> tuple[Detector, DetectorConfig, int]:
    """Detector with trained parameters from ``workdir``.

    Args:
      workdir: a training run's folder (``--workdir`` of ``train/launch.py``).
      step: ``"best"`` (best saved ``checkpoint.best_metric`` among kept checkpoints, held-out
        AP50 by default, else the latest), ``"latest"`` or a step number.
      dtype: compute dtype override (e.g. ``"bfloat16"`` on GPU); parameters stay float32.

    Returns (model, config, step).
    """
    return RunDir(workdir).load_model(step, dtype)


class RefinerWarning(UserWarning):
    """A refiner checkpoint whose own held-out evaluation says it makes poses worse."""


def heldout_check(metrics: Mapping[str, float]) -> str | None:
    """What is wrong with a refiner checkpoint by the held-out metrics saved with it
    (``train.eval_refiner``): its steps lower the MSSD recall of the poses they start from.
    None when they do not, or when the checkpoint has no such metrics."""
    before, after = metrics.get("eval/ar_mssd_before"), metrics.get("eval/ar_mssd_after")
    if before is None or after is None or after >= before:
        return None
    return (f"on its held-out evaluation this refiner makes poses worse (MSSD recall "
            f"{before:.3f} before its steps, {after:.3f} after): refined poses may be less "
            "accurate than the ones given; train it longer or on more parts, or run without "
            "--refiner")


def load_refiner(workdir, step: int | str = "best", dtype: str | None = None
                 ) -> tuple[Refiner, RefinerConfig, int, RefineSettings]:
    """Refiner with trained parameters from a refiner ``workdir`` (``train/configs/refiner.py``).

    ``step`` and ``dtype`` as :func:`load_detector` (``"best"``: held-out MSSD recall after
    refinement by default). Returns (model, config, step, the run's ``RefineSettings``: the
    refinement step is run at inference with the options it was trained with). Warns
    (:class:`RefinerWarning`) when the checkpoint's held-out metrics say it makes poses worse
    (:func:`heldout_check`).
    """
    run = RunDir(workdir, model="refiner")
    model, cfg, step = run.load_model(step, dtype)
    problem = heldout_check(run.saved_metrics(step))
    if problem:
        warnings.warn(f"{workdir} step {step}: {problem}", RefinerWarning, stacklevel=2)
    return model, cfg, step, RefineSettings(**run.read_config().get("refine", {}))
