"""Load a trained 3PT-D or 3PT-R from a training workdir for inference.

The workdir's format (``detector.json`` or ``refiner.json``, ``config.json``, Orbax steps under
``checkpoints/`` with the train state in the ``state`` item, the best step) is defined by
:mod:`threept_jax.data.run_dir`, which the trainers write through. Inference restores the
parameters alone, on the default device, without the optimizer state or the data iterator.
"""

from __future__ import annotations

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


def load_refiner(workdir, step: int | str = "best", dtype: str | None = None
                 ) -> tuple[Refiner, RefinerConfig, int, RefineSettings]:
    """Refiner with trained parameters from a refiner ``workdir`` (``train/configs/refiner.py``).

    ``step`` and ``dtype`` as :func:`load_detector` (``"best"``: held-out MSSD recall after
    refinement by default). Returns (model, config, step, the run's ``RefineSettings``: the
    refinement step is run at inference with the options it was trained with).
    """
    run = RunDir(workdir, model="refiner")
    model, cfg, step = run.load_model(step, dtype)
    return model, cfg, step, RefineSettings(**run.read_config().get("refine", {}))
