"""The run config of 3PT-D training: its schema, its check, and the library configs built from it.

A run config (``train/configs/<name>.py``) is an ``ml_collections.ConfigDict`` made by
:func:`default_config`, which fills every key from the dataclass that owns it, so a config
file states only its overrides (big_vision's ``Model(**config.model)``):

============================  =================================================================
``model``                     :class:`~threept_jax.models.configs.DetectorConfig` (``dtype`` may
                              also be ``"auto"``: :func:`resolve_dtype`)
``loss``                      :class:`~threept_jax.losses.detection.DetectorLossConfig`
``data``                      :class:`~threept_jax.data.detector_input.ExampleConfig` less the fields
                              the trainer derives (:data:`DERIVED_EXAMPLE_FIELDS`), and
                              :class:`InputConfig`
``data.photometric``          :class:`~threept_jax.data.detector_input.PhotometricConfig`
``optim`` / ``eval``          :class:`OptimConfig` / :class:`EvalConfig`
``checkpoint`` / ``mesh``     :class:`CheckpointConfig` / :class:`MeshConfig`
top level                     :class:`RunSettings`
============================  =================================================================

:func:`check_config` refuses any key outside this schema, in a config file or on the command
line, with one line naming the key and the valid ones. The trainer (``trainer_detector``) and
the evaluator (``eval_detector``) build their configs here, so neither imports the other.
"""

from __future__ import annotations

import dataclasses
import typing
from typing import Any

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from threept_jax.data.detector_input import ExampleConfig, PhotometricConfig
from threept_jax.losses.detection import DetectorLossConfig
from threept_jax.models.configs import DetectorConfig


@dataclasses.dataclass(frozen=True)
class RunSettings:
    """Top-level keys. ``batch_size`` is global (over all processes and devices); ``data_dir``
    is a records folder (``train/``, ``val/``, ``objects.json``, ``banks/``) written by
    ``python -m datagen.pack``. ``distributed``: ``"auto"`` calls
    ``jax.distributed.initialize()`` when the cluster's environment shows several processes;
    True / False force it."""

    trainer: str = "detector"  # which train/trainer_<name>.py launch.py runs
    seed: int = 0
    total_steps: int = 1000
    batch_size: int = 8
    data_dir: str = ""
    distributed: str = "auto"
    log_every: int = 50
    progress_bar: bool = True


@dataclasses.dataclass(frozen=True)
class InputConfig:
    """Input pipeline settings of ``data`` beside the ExampleConfig fields."""

    num_train_templates: int = 16  # ExampleConfig.num_templates of training examples
    num_train_records: int = -1  # -1: every record of the split
    num_workers: int = 0  # grain multiprocess prefetch workers per process (0: in-process)
    worker_buffer_size: int = 2
    read_threads: int = 4
    prefetch_buffer_size: int = 16


@dataclasses.dataclass(frozen=True)
class OptimConfig:
    """AdamW with linear warmup and cosine decay to ``learning_rate * end_lr_factor``; weight
    decay on matrices only (ndim >= 2), not biases, norms or scalars."""

    learning_rate: float = 1e-3
    warmup_steps: int = 50
    end_lr_factor: float = 0.01
    b1: float = 0.9
    b2: float = 0.999
    eps: float = 1e-8
    weight_decay: float = 0.05
    grad_clip_norm: float = 1.0


@dataclasses.dataclass(frozen=True)
class EvalConfig:
    """Periodic held-out evaluation (``train/eval_detector.py``)."""

    every_steps: int = 500  # 0: no periodic evaluation
    num_examples: int = 256  # tiles from the val split (each queried with one object)
    batch_size: int = 16
    num_templates: int = -1  # templates of the bank used for orientation (-1: all)
    template_chunk: int = 256  # templates embedded per chunk when building the banks
    max_detections: int = 20
    nms_iou: float = 0.5
    orientation_threshold_deg: float = 15.0
    match_iou: float = 0.5
    seed: int = 1


@dataclasses.dataclass(frozen=True)
class CheckpointConfig:
    """Checkpoints every ``every_steps`` (and at the end and on SIGTERM); the latest
    ``max_to_keep`` and the best by ``best_metric`` are kept."""

    every_steps: int = 500
    max_to_keep: int = 3
    best_metric: str = "eval/ap50"
    best_mode: str = "max"
    async_save: bool = True


@dataclasses.dataclass(frozen=True)
class MeshConfig:
    """Device mesh ("data", "fsdp"); -1 = all remaining devices. Parameters (and optimizer
    moments) with at least ``fsdp_min_size`` elements are sharded over "fsdp" on their largest
    divisible axis; the batch is sharded over both axes."""

    data: int = -1
    fsdp: int = 1
    fsdp_min_size: int = 2**14


#: ExampleConfig fields the trainer sets itself (from the model and the split), not ``data``.
DERIVED_EXAMPLE_FIELDS = ("tile_size", "render_size", "num_templates", "split")

#: section path -> the dataclasses whose fields are its keys.
SECTIONS: dict[str, tuple[type, ...]] = {
    "model": (DetectorConfig,),
    "loss": (DetectorLossConfig,),
    "data": (ExampleConfig, InputConfig),
    "data.photometric": (PhotometricConfig,),
    "optim": (OptimConfig,),
    "eval": (EvalConfig,),
    "checkpoint": (CheckpointConfig,),
    "mesh": (MeshConfig,),
}


class ConfigError(ValueError):
    """A config key outside the schema (the message is one line)."""


def _fields(section: str) -> list[dataclasses.Field]:
    out = []
    for cls in SECTIONS[section]:
        out += [f for f in dataclasses.fields(cls)
                if not (cls is ExampleConfig and f.name in DERIVED_EXAMPLE_FIELDS)]
    return out


def valid_keys(section: str = "") -> list[str]:
    """Keys a section (``""``: the top level, ``"data.photometric"``: nested) may hold."""
    if not section:
        return sorted([f.name for f in dataclasses.fields(RunSettings)]
                      + [s for s in SECTIONS if "." not in s])
    if section not in SECTIONS:
        raise ConfigError(f"unknown config section {section!r}; sections: "
                          f"{', '.join(sorted(SECTIONS))}")
    keys = [f.name for f in _fields(section)]
    keys += [s.rpartition(".")[2] for s in SECTIONS if s.rpartition(".")[0] == section]
    return sorted(keys)


def check_key(path: str) -> None:
    """Raise :class:`ConfigError` unless ``path`` (``"model.variant"``) is in the schema."""
    parts = path.split(".")
    for i in range(len(parts)):
        section, key = ".".join(parts[:i]), parts[i]
        keys = valid_keys(section)
        if key not in keys:
            where = f"of {section}" if section else "at the top level"
            raise ConfigError(f"unknown config key {path!r}; valid keys {where}: "
                              f"{', '.join(keys)}")
        if ".".join(parts[:i + 1]) not in SECTIONS:
            if i != len(parts) - 1:
                raise ConfigError(f"config key {'.'.join(parts[:i + 1])!r} is a value, not a "
                                  f"section, so {path!r} does not exist")
            return


def check_config(config: ml_collections.ConfigDict) -> None:
    """Raise :class:`ConfigError` on the first key of ``config`` outside the schema."""

    def walk(node, prefix):
        for key in sorted(node.keys()):
            path = f"{prefix}{key}"
            check_key(path)
            if path in SECTIONS:
                if not isinstance(node[key], (ml_collections.ConfigDict, dict)):
                    raise ConfigError(f"config key {path!r} must be a section (a ConfigDict), "
                                      f"got {node[key]!r}")
                walk(node[key], path + ".")

    walk(config, "")


def _config_value(value: Any, hint: Any) -> Any:
    """A dataclass default as a ConfigDict value that command-line overrides can set."""
    if isinstance(value, (type, np.dtype)):  # jnp.float32 and friends: by name
        return np.dtype(value).name
    if value is None:
        # A typed None, so that --config.model.embed_dim=256 parses as an int.
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        return ml_collections.FieldReference(None, field_type=args[0] if args else str)
    return value


def _section_defaults(section: str) -> ml_collections.ConfigDict:
    out = ml_collections.ConfigDict()
    for cls in SECTIONS[section]:
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            if cls is ExampleConfig and f.name in DERIVED_EXAMPLE_FIELDS:
                continue
            default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
            out[f.name] = _config_value(default, hints[f.name])
    return out


def default_config() -> ml_collections.ConfigDict:
    """Every key of the schema at its dataclass default (config files override from here)."""
    c = ml_collections.ConfigDict(dataclasses.asdict(RunSettings()))
    for section in SECTIONS:
        parent, _, name = section.rpartition(".")
        (c[parent] if parent else c)[name] = _section_defaults(section)
    return c


# --------------------------------------------------------------------------- config -> objects


def resolve_dtype(name: Any) -> Any:
    """``"auto"`` -> bfloat16 on accelerators, float32 on CPU; otherwise the named dtype."""
    if isinstance(name, str) and name == "auto":
        return jnp.bfloat16 if jax.default_backend() != "cpu" else jnp.float32
    return jnp.dtype(name)


def model_config(config: ml_collections.ConfigDict) -> DetectorConfig:
    """``DetectorConfig(**config.model)`` with ``dtype`` resolved."""
    fields = config.model.to_dict()
    if "dtype" in fields:
        fields["dtype"] = resolve_dtype(fields["dtype"])
    return DetectorConfig(**fields)


def loss_config(config: ml_collections.ConfigDict) -> DetectorLossConfig:
    """``DetectorLossConfig(**config.loss)``."""
    return DetectorLossConfig(**config.loss.to_dict())


def example_config(config: ml_collections.ConfigDict, *, split: str, num_templates: int
                   ) -> ExampleConfig:
    """The data section's ExampleConfig fields, with the tile and render sizes of the model."""
    model = model_config(config)
    names = {f.name for f in dataclasses.fields(ExampleConfig)} - set(DERIVED_EXAMPLE_FIELDS)
    fields = {k: v for k, v in config.data.to_dict().items() if k in names}
    if "scale_prior" in fields:
        fields["scale_prior"] = tuple(fields["scale_prior"])
    return ExampleConfig(**fields, tile_size=model.image_size, render_size=model.render_size,
                         num_templates=num_templates, split=split)


def photometric_config(config: ml_collections.ConfigDict) -> PhotometricConfig:
    """``PhotometricConfig(**config.data.photometric)`` (defaults when the config has none)."""
    return PhotometricConfig(**config.data.get("photometric", ml_collections.ConfigDict())
                             .to_dict())
