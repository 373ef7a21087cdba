"""The run directory of a training run (3PT-D or 3PT-R): the one home of its on-disk format.

Training (``train/``) writes it, inference (``infer/checkpoint.py``) reads it; neither imports the
other, both import this module::

    <workdir>/
      config.json            the whole run config (ml_collections JSON), CONFIG_FILE
      config_history.json    the configs a resume replaced, CONFIG_HISTORY_FILE: a JSON list of
                             {"step", "time", "forced" (keys changed with the trainer's
                             permission), "changes": {key: {"old", "new"}}, "previous_config"},
                             oldest first (written only when a resume changed the config)
      detector.json          the model config, ``MODEL_FILES[model]``: ``detector.json`` (the
      or refiner.json        DetectorConfig) or ``refiner.json`` (the RefinerConfig), from
                             ``to_dict()``: inference rebuilds the model from it
      checkpoints/<step>/    one Orbax ``CheckpointManager`` step, CHECKPOINT_DIR, holding the
                             composite items
        state/               {"step", "params", "opt_state"} (STATE_ITEM, ``StandardSave``)
        data/                the grain iterator, one JSON file per process (DATA_ITEM)
        metrics/             the evaluation metrics saved with the step (Orbax's own item,
                             written when the manager has a ``best_fn``)
      tb/                    TensorBoard event files, TB_DIR
      SHA256SUMS             an exported model's checksums (``train.export``), CHECKSUM_FILE:
                             ``sha256sum`` lines for every file but itself and the ``*.md``
                             cards; a run that has one is verified before it is loaded

The best checkpoint is the one with the best ``checkpoint.best_metric`` of config.json
(``checkpoint.best_mode`` "max" or "min") among the kept steps saved with that metric
(:func:`best_step`); the preservation policy of training and the choice of inference use the same
:func:`metric_fn`. Writes are atomic (:mod:`threept_jax.data.files`).
"""

from __future__ import annotations

import datetime
import hashlib
import json
import pathlib
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from threept_jax.data.files import atomic_write_bytes, atomic_write_json
from threept_jax.models.configs import DetectorConfig, RefinerConfig

CONFIG_FILE = "config.json"
CONFIG_HISTORY_FILE = "config_history.json"
#: model kind (``config.trainer``) -> (its model-config file, its config class).
MODEL_FILES: dict[str, tuple[str, type]] = {
    "detector": ("detector.json", DetectorConfig),
    "refiner": ("refiner.json", RefinerConfig),
}
CHECKPOINT_DIR = "checkpoints"
TB_DIR = "tb"
CHECKSUM_FILE = "SHA256SUMS"
STATE_ITEM = "state"
DATA_ITEM = "data"

#: Model-config fields that change how the model computes, not its parameters: a run may
#: resume (or be loaded) with other values.
COMPUTE_ONLY_FIELDS = ("dtype", "attention_impl", "remat")


class RunDir:
    """Paths, side files and checkpoint listing of one run directory (module docstring)."""

    def __init__(self, workdir, model: str = "detector"):
        """``model``: the kind of run, a key of :data:`MODEL_FILES` (``config.trainer``)."""
        if model not in MODEL_FILES:
            raise ValueError(f"unknown model kind {model!r}; known: {', '.join(MODEL_FILES)}")
        # Orbax refuses relative paths; resolve once here for every reader and writer.
        self.path = pathlib.Path(workdir).expanduser().resolve()
        self.model = model

    @property
    def config_file(self) -> pathlib.Path:
        return self.path / CONFIG_FILE

    @property
    def config_history_file(self) -> pathlib.Path:
        return self.path / CONFIG_HISTORY_FILE

    @property
    def model_file(self) -> pathlib.Path:
        return self.path / MODEL_FILES[self.model][0]

    @property
    def checkpoint_dir(self) -> pathlib.Path:
        return self.path / CHECKPOINT_DIR

    @property
    def tb_dir(self) -> pathlib.Path:
        return self.path / TB_DIR

    # -- side files ----------------------------------------------------------------------

    def write_config(self, config_json: str) -> None:
        """``config.json``: the whole run config as JSON text (``to_json_best_effort``)."""
        atomic_write_bytes(self.config_file, config_json.encode())

    def read_config_history(self) -> list[dict[str, Any]]:
        """The entries of ``config_history.json``, oldest first ([] when there is none)."""
        f = self.config_history_file
        return json.loads(f.read_text()) if f.exists() else []

    def record_config_change(self, step: int, changes: Mapping[str, tuple[Any, Any]],
                             previous_config: Mapping[str, Any], *,
                             forced: Sequence[str] = ()) -> None:
        """Append an entry to ``config_history.json`` before a resume at ``step`` replaces
        config.json: ``changes`` maps each changed key (``"optim.learning_rate"``) to its
        (old, new) value, ``previous_config`` is the replaced config.json, ``forced`` names
        the changed keys that needed the trainer's explicit permission."""
        entry = {
            "step": int(step),
            "time": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "forced": sorted(forced),
            "changes": {k: {"old": old, "new": new} for k, (old, new) in changes.items()},
            "previous_config": dict(previous_config),
        }
        atomic_write_json(self.config_history_file, [*self.read_config_history(), entry],
                          indent=2)

    def write_model_config(self, model_cfg: DetectorConfig | RefinerConfig) -> None:
        """``detector.json`` / ``refiner.json``: the model config inference rebuilds the model
        from."""
        atomic_write_json(self.model_file, model_cfg.to_dict(), indent=2, sort_keys=True)

    def read_config(self) -> dict[str, Any]:
        """The run config as a plain dict ({} when the run wrote none)."""
        return json.loads(self.config_file.read_text()) if self.config_file.exists() else {}

    def read_model_config(self, dtype: str | None = None) -> DetectorConfig | RefinerConfig:
        """The run's model config, with the compute ``dtype`` replaced when given."""
        if not self.model_file.exists():
            raise FileNotFoundError(
                f"{self.model_file} not found: {self.path} is not a {self.model} training "
                f"workdir (train one with `python train/launch.py --config "
                f"train/configs/{self.model}.py:tiny --workdir DIR`)")
        fields = json.loads(self.model_file.read_text())
        if dtype is not None:
            fields["dtype"] = dtype
        return MODEL_FILES[self.model][1](**fields)

    def check_same_model(self, model_cfg: DetectorConfig | RefinerConfig,
                         fix: str | None = None) -> None:
        """Refuse to resume a run of another model into this workdir, naming both.

        Refuses a workdir that holds a run of another kind (its model file), then compares
        ``model_cfg`` with the saved model config, ignoring :data:`COMPUTE_ONLY_FIELDS`; does
        nothing when the workdir holds no model config. A field the saved config lacks (added
        to the model since the run was saved) counts at its default, as loading the run reads
        it. ``fix`` replaces the advice that ends the message.
        """
        for kind, (name, _) in MODEL_FILES.items():
            if kind != self.model and (self.path / name).exists():
                raise ValueError(
                    f"{self.path} holds a {kind} run ({name}), not a {self.model} run; pass a "
                    "fresh --workdir")
        if not self.model_file.exists():
            return
        saved = self.read_model_config().to_dict()
        new = model_cfg.to_dict()
        diff = sorted(k for k in set(saved) | set(new)
                      if k not in COMPUTE_ONLY_FIELDS and saved.get(k) != new.get(k))
        if diff:
            changes = ", ".join(f"{k}={saved.get(k)!r} (config: {new.get(k)!r})" for k in diff)
            raise ValueError(
                f"this workdir holds a {saved.get('variant')} run whose model differs from the "
                f"config's {new.get('variant')}: {changes}. " + (fix or (
                    f"Resume it with the run's own config ({self.config_file}) or pass a fresh "
                    "--workdir")))

    # -- checksums (exported models) ---------------------------------------------------

    def checksummed_files(self) -> list[pathlib.Path]:
        """The files :meth:`write_checksums` covers: all but the checksum file and ``*.md``."""
        return sorted(p for p in self.path.rglob("*") if p.is_file()
                      and p.name != CHECKSUM_FILE and p.suffix != ".md")

    def write_checksums(self) -> None:
        """``SHA256SUMS`` in ``sha256sum`` format (``sha256sum -c SHA256SUMS`` checks it)."""
        lines = [f"{sha256(p)}  {p.relative_to(self.path).as_posix()}\n"
                 for p in self.checksummed_files()]
        atomic_write_bytes(self.path / CHECKSUM_FILE, "".join(lines).encode())

    def verify(self, restore: str = "export it again (python -m train.export)") -> None:
        """Check an exported model against its ``SHA256SUMS`` (nothing to do without one).

        Raises :class:`ModelFileError` naming the first file that is missing, differs from its
        checksum or is not listed; ``restore`` says how to get the folder back.
        """
        sums = self.path / CHECKSUM_FILE
        if not sums.exists():
            return
        expected = {}
        for line in sums.read_text().splitlines():
            digest, _, name = line.partition("  ")
            expected[name] = digest
        for name, digest in expected.items():
            f = self.path / name
            problem = ("is missing" if not f.is_file() else
                       None if sha256(f) == digest else "differs from its SHA-256 in "
                       f"{CHECKSUM_FILE} (corrupt or changed)")
            if problem:
                raise ModelFileError(f"{f} {problem}: the model {self.path} cannot be trusted; "
                                     f"{restore}")
        for f in self.checksummed_files():
            if f.relative_to(self.path).as_posix() not in expected:
                raise ModelFileError(f"{f} is not part of the model {self.path} (not in "
                                     f"{CHECKSUM_FILE}): remove it, or {restore}")

    # -- checkpoints ---------------------------------------------------------------------

    def checkpoint_steps(self) -> list[int]:
        """Steps with a finished checkpoint (Orbax's commit marker or a state item), sorted."""
        if not self.checkpoint_dir.is_dir():
            return []
        return sorted(int(p.name) for p in self.checkpoint_dir.iterdir() if p.name.isdigit()
                      and ((p / "commit_success.txt").exists() or (p / STATE_ITEM).is_dir()))

    def best_metric(self) -> tuple[str | None, str]:
        """(``checkpoint.best_metric``, ``checkpoint.best_mode``) of config.json."""
        ckpt = self.read_config().get("checkpoint", {})
        return ckpt.get("best_metric") or None, ckpt.get("best_mode", "max")

    def _metrics_manager(self):
        """A read-only view of the metrics saved with each step (None: the run tracks none)."""
        import orbax.checkpoint as ocp

        metric, mode = self.best_metric()
        if metric is None or not self.checkpoint_dir.is_dir():
            return None
        options = ocp.CheckpointManagerOptions(best_fn=metric_fn(metric), best_mode=mode,
                                               read_only=True)
        return ocp.CheckpointManager(self.checkpoint_dir, options=options)

    def saved_metrics(self, step: int) -> dict[str, float]:
        """The evaluation metrics saved with checkpoint ``step`` ({} if none)."""
        manager = self._metrics_manager()
        if manager is None:
            return {}
        with manager:
            return dict(manager.metrics(step) or {})

    def best_step(self) -> int:
        """The kept step with the best saved ``best_metric``, else the latest step."""
        steps = self.checkpoint_steps()
        if not steps:
            raise FileNotFoundError(f"no checkpoint under {self.checkpoint_dir}: the run saved "
                                    "none yet")
        manager = self._metrics_manager()
        if manager is None:
            return steps[-1]
        with manager:
            best = manager.best_step()
        return steps[-1] if best is None or best not in steps else int(best)

    def resolve_step(self, step: int | str) -> int:
        """``"best"``, ``"latest"`` or a step number -> a step that has a checkpoint."""
        if step == "best":
            return self.best_step()
        steps = self.checkpoint_steps()
        if not steps:
            raise FileNotFoundError(f"no checkpoint under {self.checkpoint_dir}: the run saved "
                                    "none yet")
        if step == "latest":
            return steps[-1]
        if isinstance(step, str) and not step.isdigit() or int(step) not in steps:
            raise ValueError(f"no checkpoint at step {step!r} in {self.checkpoint_dir}; "
                             f"available: {steps} (or 'best', 'latest')")
        return int(step)

    def restore_params(self, step: int, target: Any) -> Any:
        """The parameters of checkpoint ``step`` (a step of :meth:`resolve_step`) restored into
        ``target``, a pytree of ``jax.ShapeDtypeStruct`` with shardings; the optimizer state
        and the data iterator stay on disk (inference, and a run initialised from another)."""
        import warnings

        import orbax.checkpoint as ocp

        with ocp.CheckpointManager(self.checkpoint_dir) as manager, warnings.catch_warnings():
            # Only the parameters are restored, with their shardings given; Orbax still warns
            # about the other items it skips.
            warnings.filterwarnings("ignore", message="Sharding info not provided")
            restored = manager.restore(step, args=ocp.args.Composite(**{
                STATE_ITEM: ocp.args.PyTreeRestore(item={"params": target},
                                                   partial_restore=True)}))
        return restored[STATE_ITEM]["params"]

    def load_model(self, step: int | str = "best", dtype: str | None = None):
        """(network with the parameters of ``step`` on the default device, its config, the
        resolved step): the run's ``Detector`` or ``Refiner`` (``self.model``), for inference
        and evaluation; ``dtype`` overrides the compute dtype."""
        import jax
        from flax import nnx

        self.verify()
        if self.model == "refiner":
            from threept_jax.models.refiner import Refiner as cls
        else:
            from threept_jax.models.detector import Detector as cls
        cfg = self.read_model_config(dtype)
        step = self.resolve_step(step)
        abstract = nnx.eval_shape(lambda: cls(cfg, rngs=nnx.Rngs(0)))
        graphdef, abstract_params = nnx.split(abstract, nnx.Param)
        device = jax.sharding.SingleDeviceSharding(jax.devices()[0])
        target = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=device),
                              nnx.to_pure_dict(abstract_params))
        nnx.replace_by_pure_dict(abstract_params, self.restore_params(step, target))
        return nnx.merge(graphdef, abstract_params), cfg, step


class ModelFileError(FileNotFoundError):
    """A file of an exported model is missing, corrupt or foreign (:meth:`RunDir.verify`)."""


def sha256(path) -> str:
    """The SHA-256 of a file's bytes, as ``sha256sum`` prints it."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def metric_fn(name: str) -> Callable[[Mapping[str, float]], float]:
    """The value checkpoints are ranked by: ``metrics[name]`` as a float."""
    return lambda metrics: float(metrics[name])
