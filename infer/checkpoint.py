"""Load a trained 3PT-D from a training workdir for inference.

A training run (``train/launch.py``) leaves in its workdir ``detector.json`` (the
``DetectorConfig``), ``config.json`` (the whole run config) and Orbax checkpoints under
``checkpoints/<step>/state`` holding ``{"step", "params", "opt_state"}``. Inference restores the
parameters alone, on the default device, without the optimizer state or the data iterator.
"""

from __future__ import annotations

import json
import pathlib
import warnings

import jax
import orbax.checkpoint as ocp
from flax import nnx

from threept_jax.models.configs import DetectorConfig
from threept_jax.models.detector import Detector


def _steps(ckpt_dir: pathlib.Path) -> list[int]:
    return sorted(int(p.name) for p in ckpt_dir.iterdir()
                  if p.name.isdigit() and (p / "commit_success.txt").exists()
                  or p.name.isdigit() and (p / "state").is_dir())


def _metrics_manager(workdir: pathlib.Path) -> ocp.CheckpointManager | None:
    """A manager that reads the metrics saved with each step (None: the run tracks none)."""
    config = json.loads((workdir / "config.json").read_text()) if (workdir / "config.json").exists() else {}
    ckpt = config.get("checkpoint", {})
    metric = ckpt.get("best_metric")
    if not metric:
        return None
    options = ocp.CheckpointManagerOptions(best_fn=lambda m: float(m[metric]),
                                           best_mode=ckpt.get("best_mode", "max"))
    return ocp.CheckpointManager(workdir / "checkpoints", options=options)


def saved_metrics(workdir, step: int) -> dict[str, float]:
    """The evaluation metrics saved with checkpoint ``step`` of a training run ({} if none)."""
    manager = _metrics_manager(pathlib.Path(workdir).expanduser().resolve())
    if manager is None:
        return {}
    with manager:
        return dict(manager.metrics(step) or {})


def _best_step(workdir: pathlib.Path, steps: list[int]) -> int:
    """The step with the best saved ``checkpoint.best_metric`` of the run, else the latest."""
    manager = _metrics_manager(workdir)
    if manager is None:
        return steps[-1]
    with manager:
        best = manager.best_step()
    return steps[-1] if best is None or best not in steps else int(best)


def load_detector(workdir, step: int | str = "best", dtype: str | None = None
                  ) -> tuple[Detector, DetectorConfig, int]:
    """Detector with trained parameters from ``workdir``.

    Args:
      workdir: a training run's folder (``--workdir`` of ``train/launch.py``).
      step: ``"best"`` (highest held-out AP50 among kept checkpoints, else the latest),
        ``"latest"`` or a step number.
      dtype: compute dtype override (e.g. ``"bfloat16"`` on GPU); parameters stay float32.

    Returns (model, config, step).
    """
    workdir = pathlib.Path(workdir).expanduser().resolve()  # Orbax needs absolute paths
    cfg_file = workdir / "detector.json"
    if not cfg_file.exists():
        raise FileNotFoundError(
            f"{cfg_file} not found: {workdir} is not a 3PT-D training workdir (train one with "
            "`python train/launch.py --config train/configs/detector.py:tiny --workdir DIR`)")
    fields = json.loads(cfg_file.read_text())
    if dtype is not None:
        fields["dtype"] = dtype
    cfg = DetectorConfig(**fields)
    ckpt_dir = workdir / "checkpoints"
    steps = _steps(ckpt_dir) if ckpt_dir.is_dir() else []
    if not steps:
        raise FileNotFoundError(f"no checkpoint under {ckpt_dir}: the run saved none yet")
    if step == "best":
        step = _best_step(workdir, steps)
    elif step == "latest":
        step = steps[-1]
    elif int(step) not in steps:
        raise ValueError(f"no checkpoint at step {step} in {ckpt_dir}; available: {steps}")
    step = int(step)

    abstract = nnx.eval_shape(lambda: Detector(cfg, rngs=nnx.Rngs(0)))
    graphdef, abstract_params = nnx.split(abstract, nnx.Param)
    device = jax.sharding.SingleDeviceSharding(jax.devices()[0])
    target = {"params": jax.tree.map(
        lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=device),
        nnx.to_pure_dict(abstract_params))}
    with ocp.CheckpointManager(ckpt_dir) as manager, warnings.catch_warnings():
        # Only the parameters are restored, with their shardings given; Orbax still warns about
        # the other items it skips.
        warnings.filterwarnings("ignore", message="Sharding info not provided")
        restored = manager.restore(step, args=ocp.args.Composite(
            state=ocp.args.PyTreeRestore(item=target, partial_restore=True)))
    nnx.replace_by_pure_dict(abstract_params, restored["state"]["params"])
    model = nnx.merge(graphdef, abstract_params)
    return model, cfg, step
