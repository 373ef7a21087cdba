"""The run config of 3PT-D training: its schema, its check, and the library configs built from it.

A run config (``train/configs/<name>.py``) is an ``ml_collections.ConfigDict`` made by
:func:`default_config` for one trainer (``config.trainer``: ``"detector"`` or ``"refiner"``),
which fills every key from the dataclass that owns it, so a config file states only its
overrides (big_vision's ``Model(**config.model)``). :data:`SCHEMAS` maps each trainer's
sections to their dataclasses:

==================  ======================================  ======================================
section             detector                                refiner
==================  ======================================  ======================================
``model``           ``models.configs.DetectorConfig``       ``models.configs.RefinerConfig``
                    (``dtype`` may also be ``"auto"``:      (idem)
                    :func:`resolve_dtype`)
``loss``            ``losses.detection.DetectorLossConfig`` ``losses.refiner.RefinerLossConfig``
``data``            ``detector_input.ExampleConfig`` less   ``refiner_input.RefinerExampleConfig``
                    the fields the trainer derives          less the derived fields, and
                    (:data:`DERIVED_EXAMPLE_FIELDS`), and   :class:`InputConfig`
                    :class:`InputConfig`
``data.photometric`` ``detector_input.PhotometricConfig``   (none)
``refine``          (none)                                  ``pipeline.refinement.RefineSettings``
``eval``            :class:`EvalConfig`                     :class:`RefinerEvalConfig`
``optim``,          :class:`OptimConfig`,                   (the same)
``checkpoint``,     :class:`CheckpointConfig`,
``mesh``            :class:`MeshConfig`
top level           :class:`RunSettings`                    (the same)
==================  ======================================  ======================================

:func:`check_config` refuses any key outside this schema, in a config file or on the command
line, with one line naming the key and the valid ones, and out-of-range numbers of the sections
whose dataclasses do not check themselves (:data:`VALUE_RULES`). :func:`check_resume_config`
decides which keys a resumed run may change (:data:`RESUME_FREE_KEYS`). The trainer (``trainer_detector``) and
the evaluator (``eval_detector``) build their configs here, so neither imports the other.
"""

from __future__ import annotations

import dataclasses
import json
import math
import typing
from collections.abc import Callable, Mapping
from typing import Any

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from threept_jax.data.detector_input import ExampleConfig, PhotometricConfig
from threept_jax.data.refiner_input import RefinerExampleConfig
from threept_jax.data.run_dir import COMPUTE_ONLY_FIELDS, CONFIG_FILE, CONFIG_HISTORY_FILE
from threept_jax.losses.detection import DetectorLossConfig
from threept_jax.losses.refiner import RefinerLossConfig
from threept_jax.models.configs import DetectorConfig, RefinerConfig
from threept_jax.pipeline.refinement import RefineSettings


@dataclasses.dataclass(frozen=True)
class RunSettings:
    """Top-level keys. ``batch_size`` is global (over all processes and devices); ``data_dir``
    is a records folder (``train/``, ``val/``, ``objects.json``, ``banks/``) written by
    ``python -m datagen.pack``. ``distributed``: ``"auto"`` calls
    ``jax.distributed.initialize()`` when the cluster's environment shows several processes;
    True / False force it. ``init_from``: a training run (its folder) whose best checkpoint
    initialises the parameters of a fresh run (fine-tuning, ``python -m train.adapt --from``);
    the model config must be the same; ignored once the run has its own checkpoint."""

    trainer: str = "detector"  # which train/trainer_<name>.py launch.py runs (SCHEMAS)
    seed: int = 0
    total_steps: int = 1000
    batch_size: int = 8
    data_dir: str = ""
    init_from: str = ""
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
    decay on matrices only (ndim >= 2), not biases, norms or scalars. ``freeze``: top-level
    parameter groups held at their initial values (comma-separated, e.g. ``"stem"``, the
    refiner's pretrained stem): no gradient reaches them and no weight decay; to fine-tune
    them afterwards, start a run with ``init_from`` the frozen one and ``freeze=""``."""

    learning_rate: float = 1e-3
    warmup_steps: int = 50
    end_lr_factor: float = 0.01
    b1: float = 0.9
    b2: float = 0.999
    eps: float = 1e-8
    weight_decay: float = 0.05
    grad_clip_norm: float = 1.0
    freeze: str = ""


@dataclasses.dataclass(frozen=True)
class EvalConfig:
    """Periodic held-out evaluation (``train/eval_detector.py``)."""

    every_steps: int = 500  # 0: no periodic evaluation
    num_images: int = 16  # full val images detected as inference does (the headline metrics)
    num_scales: int = 3  # pan-and-scan scales of the full-image evaluation
    candidates_per_object: int = 64  # patches per object kept before the full-image NMS
    num_examples: int = 256  # tiles from the val split (each queried with one object)
    batch_size: int = 16
    num_templates: int = -1  # templates of the bank used for orientation (-1: all)
    template_chunk: int = 256  # templates embedded per chunk when building the banks
    max_detections: int = 20  # per tile and per full image
    nms_iou: float = 0.5
    orientation_threshold_deg: float = 15.0
    match_iou: float = 0.5
    seed: int = 1


@dataclasses.dataclass(frozen=True)
class RefinerEvalConfig:
    """Periodic held-out evaluation of 3PT-R (``train/eval_refiner.py``).

    ``data_dir``: a records folder whose objects training never saw (``""``: the ``val``
    split of ``config.data_dir``); ``split``: its split read.
    """

    every_steps: int = 500  # 0: no periodic evaluation
    data_dir: str = ""
    split: str = "val"
    num_examples: int = 64  # instances evaluated (one per image, as training samples them)
    batch_size: int = 8
    num_steps: int = 3  # refinement iterations measured (reported after 1 and after this many)
    seed: int = 1


@dataclasses.dataclass(frozen=True)
class CheckpointConfig:
    """Checkpoints every ``every_steps`` (and at the end and on SIGTERM); the latest
    ``max_to_keep`` and the best by ``best_metric`` are kept."""

    every_steps: int = 500
    max_to_keep: int = 3
    best_metric: str = "eval/ap50"  # full-image box AP50 (train/eval_detector.py)
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


#: Example-config fields the trainer sets itself (from the model and the split), not ``data``.
DERIVED_EXAMPLE_FIELDS = {
    ExampleConfig: ("tile_size", "render_size", "num_templates", "split"),
    RefinerExampleConfig: ("crop_size", "output_size"),
}

_COMMON_SECTIONS: dict[str, tuple[type, ...]] = {
    "optim": (OptimConfig,),
    "checkpoint": (CheckpointConfig,),
    "mesh": (MeshConfig,),
}

#: trainer -> section path -> the dataclasses whose fields are its keys.
SCHEMAS: dict[str, dict[str, tuple[type, ...]]] = {
    "detector": {
        "model": (DetectorConfig,),
        "loss": (DetectorLossConfig,),
        "data": (ExampleConfig, InputConfig),
        "data.photometric": (PhotometricConfig,),
        "eval": (EvalConfig,),
        **_COMMON_SECTIONS,
    },
    "refiner": {
        "model": (RefinerConfig,),
        "loss": (RefinerLossConfig,),
        "data": (RefinerExampleConfig, InputConfig),
        "refine": (RefineSettings,),
        "eval": (RefinerEvalConfig,),
        **_COMMON_SECTIONS,
    },
}


def sections(trainer: str) -> dict[str, tuple[type, ...]]:
    """The sections of ``trainer``'s config; :class:`ConfigError` for an unknown trainer."""
    if trainer not in SCHEMAS:
        raise ConfigError(f"unknown trainer {trainer!r}; known trainers: "
                          f"{', '.join(sorted(SCHEMAS))} (config key 'trainer')")
    return SCHEMAS[trainer]


class ConfigError(ValueError):
    """A config key outside the schema or a value out of range (the message is one line)."""


def _fields(cls: type) -> list[dataclasses.Field]:
    derived = DERIVED_EXAMPLE_FIELDS.get(cls, ())
    return [f for f in dataclasses.fields(cls) if f.name not in derived]


def valid_keys(section: str = "", trainer: str = "detector") -> list[str]:
    """Keys a section (``""``: the top level, ``"data.photometric"``: nested) may hold."""
    schema = sections(trainer)
    if not section:
        return sorted([f.name for f in dataclasses.fields(RunSettings)]
                      + [s for s in schema if "." not in s])
    if section not in schema:
        raise ConfigError(f"unknown config section {section!r} of the {trainer} trainer; "
                          f"sections: {', '.join(sorted(schema))}")
    keys = [f.name for cls in schema[section] for f in _fields(cls)]
    keys += [s.rpartition(".")[2] for s in schema if s.rpartition(".")[0] == section]
    return sorted(keys)


def check_key(path: str, trainer: str = "detector") -> None:
    """Raise :class:`ConfigError` unless ``path`` (``"model.variant"``) is in ``trainer``'s
    schema."""
    schema = sections(trainer)
    parts = path.split(".")
    for i in range(len(parts)):
        section, key = ".".join(parts[:i]), parts[i]
        keys = valid_keys(section, trainer)
        if key not in keys:
            where = f"of {section}" if section else "at the top level"
            raise ConfigError(f"unknown config key {path!r}; valid keys {where}: "
                              f"{', '.join(keys)}")
        if ".".join(parts[:i + 1]) not in schema:
            if i != len(parts) - 1:
                raise ConfigError(f"config key {'.'.join(parts[:i + 1])!r} is a value, not a "
                                  f"section, so {path!r} does not exist")
            return


def check_config(config: ml_collections.ConfigDict) -> None:
    """Raise :class:`ConfigError` on an unknown ``trainer``, then on the first key of
    ``config`` outside that trainer's schema, then on the values that break
    :data:`VALUE_RULES` (all of them, in one line)."""
    trainer = config.get("trainer", "detector")
    schema = sections(trainer)

    def walk(node, prefix):
        for key in sorted(node.keys()):
            path = f"{prefix}{key}"
            check_key(path, trainer)
            if path in schema:
                if not isinstance(node[key], (ml_collections.ConfigDict, dict)):
                    raise ConfigError(f"config key {path!r} must be a section (a ConfigDict), "
                                      f"got {node[key]!r}")
                walk(node[key], path + ".")

    walk(config, "")
    check_values(config)


# --------------------------------------------------------------------------- values


def _is_int(v: Any) -> bool:
    return isinstance(v, (int, np.integer)) and not isinstance(v, (bool, np.bool_))


def _is_num(v: Any) -> bool:
    return (_is_int(v) or isinstance(v, (float, np.floating))) and math.isfinite(v)


def _int_at_least(lo: int, *, or_minus_one: bool = False) -> tuple[Callable[[Any], bool], str]:
    what = f"an integer >= {lo}" + (" (or -1)" if or_minus_one else "")
    return (lambda v: _is_int(v) and (v >= lo or (or_minus_one and v == -1))), what


def _number_in(lo: float, hi: float = math.inf, *, lo_open: bool, hi_open: bool = True
               ) -> tuple[Callable[[Any], bool], str]:
    what = (f"a number in {'(' if lo_open else '['}{lo}, {hi}{')' if hi_open else ']'}"
            if math.isfinite(hi) else f"a number {'>' if lo_open else '>='} {lo}")
    return (lambda v: _is_num(v) and (v > lo if lo_open else v >= lo)
            and (v < hi if hi_open else v <= hi)), what


#: key -> (check, what it must be), for the keys whose dataclass does not check itself (the
#: model, loss and example sections raise from their own ``__post_init__`` when the trainer
#: builds them).
VALUE_RULES: dict[str, tuple[Callable[[Any], bool], str]] = {
    "total_steps": _int_at_least(1),
    "batch_size": _int_at_least(1),
    "seed": _int_at_least(0),
    "log_every": _int_at_least(1),
    "distributed": (lambda v: isinstance(v, bool) or isinstance(v, str)
                    and v.lower() in ("auto", "true", "false"), "'auto', True or False"),
    "data.num_train_templates": _int_at_least(1),
    "data.num_train_records": _int_at_least(1, or_minus_one=True),
    "data.num_workers": _int_at_least(0),
    "data.worker_buffer_size": _int_at_least(1),
    "data.read_threads": _int_at_least(0),
    "data.prefetch_buffer_size": _int_at_least(0),
    "optim.learning_rate": _number_in(0, lo_open=True),
    "optim.warmup_steps": _int_at_least(0),
    "optim.end_lr_factor": _number_in(0, lo_open=False),
    "optim.b1": _number_in(0, 1, lo_open=False),
    "optim.b2": _number_in(0, 1, lo_open=False),
    "optim.eps": _number_in(0, lo_open=False),
    "optim.weight_decay": _number_in(0, lo_open=False),
    "optim.grad_clip_norm": _number_in(0, lo_open=True),
    "eval.every_steps": _int_at_least(0),
    "eval.num_images": _int_at_least(1),
    "eval.num_scales": _int_at_least(1),
    "eval.candidates_per_object": _int_at_least(1),
    "eval.num_examples": _int_at_least(1),
    "eval.batch_size": _int_at_least(1),
    "eval.num_templates": _int_at_least(1, or_minus_one=True),
    "eval.template_chunk": _int_at_least(1),
    "eval.max_detections": _int_at_least(1),
    "eval.nms_iou": _number_in(0, 1, lo_open=True, hi_open=False),
    "eval.orientation_threshold_deg": _number_in(0, 180, lo_open=True, hi_open=False),
    "eval.match_iou": _number_in(0, 1, lo_open=True, hi_open=False),
    "eval.seed": _int_at_least(0),
    "eval.num_steps": _int_at_least(1),
    "eval.split": (lambda v: v in ("train", "val"), "'train' or 'val'"),
    "checkpoint.every_steps": _int_at_least(0),
    "checkpoint.max_to_keep": _int_at_least(1),
    "checkpoint.best_mode": (lambda v: v in ("max", "min"), "'max' or 'min'"),
    "mesh.data": _int_at_least(1, or_minus_one=True),
    "mesh.fsdp": _int_at_least(1, or_minus_one=True),
    "mesh.fsdp_min_size": _int_at_least(0),
}


def _get(config: Mapping[str, Any], path: str) -> Any:
    node = config
    for part in path.split("."):
        node = node[part]
    return node


def check_values(config: ml_collections.ConfigDict) -> None:
    """Raise :class:`ConfigError` naming every value of ``config`` that breaks
    :data:`VALUE_RULES` (keys the config lacks keep their valid defaults and are skipped)."""
    bad = []
    for path, (ok, what) in VALUE_RULES.items():
        try:
            value = _get(config, path)
        except (KeyError, AttributeError):
            continue
        if not ok(value):
            bad.append(f"{path}={value!r} (must be {what})")
    if bad:
        raise ConfigError(f"invalid config value{'s' if len(bad) > 1 else ''}: "
                          + "; ".join(bad))


# --------------------------------------------------------------------------- resuming

#: Keys a resumed run may change freely: how long it runs and how it is logged, checkpointed,
#: laid out on the devices and read (without changing the batches), not what it computes.
#: ``total_steps`` extends (or shortens) a run; the cosine schedule is then stretched over the
#: new length from the resumed step on. Every other key (seed, batch_size, data_dir, the data,
#: loss and optimizer settings, the evaluation that ranks checkpoints, the best metric) is
#: refused by :func:`check_resume_config` unless the change is explicitly allowed; model
#: fields other than :data:`COMPUTE_ONLY_FIELDS` are refused always
#: (``RunDir.check_same_model``). ``data.num_workers`` is refused: the saved data iterator's
#: state depends on the worker count.
RESUME_FREE_KEYS = frozenset({
    "total_steps", "log_every", "progress_bar", "distributed",
    "checkpoint.every_steps", "checkpoint.max_to_keep", "checkpoint.async_save",
    "eval.every_steps", "eval.batch_size", "eval.template_chunk",
    "data.worker_buffer_size", "data.read_threads", "data.prefetch_buffer_size",
    "mesh.data", "mesh.fsdp", "mesh.fsdp_min_size",
    *(f"model.{k}" for k in COMPUTE_ONLY_FIELDS),
})

#: The trainer's option that allows the refused changes (``train/launch.py`` flag).
ALLOW_CHANGE_FLAG = "--allow_config_change"


def flatten_config(tree: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"a": {"b": 1}}`` -> ``{"a.b": 1}`` (a saved config.json as override keys)."""
    out = {}
    for key, value in tree.items():
        if isinstance(value, Mapping):
            out.update(flatten_config(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def check_resume_config(saved: Mapping[str, Any], config: ml_collections.ConfigDict, *,
                        allow_change: bool, config_file: Any = CONFIG_FILE
                        ) -> tuple[dict[str, tuple[Any, Any]], list[str]]:
    """``(changes, refused)``: the keys whose value in ``config`` differs from the run's saved
    config.json (``saved``, a plain dict), as ``key -> (old, new)`` in their JSON form, and
    those of them outside :data:`RESUME_FREE_KEYS`. Keys the saved config lacks (a run from
    before they existed) appear with old ``None`` and are never refused.

    Raises :class:`ConfigError` naming each refused key with its old and new values and
    :data:`ALLOW_CHANGE_FLAG`, unless ``allow_change``.
    """
    old = flatten_config(saved)
    new = flatten_config(json.loads(config.to_json_best_effort()))
    changes = {k: (old.get(k), new.get(k)) for k in sorted(set(old) | set(new))
               if old.get(k) != new.get(k)}
    refused = [k for k in changes if k in old and k not in RESUME_FREE_KEYS]
    if refused and not allow_change:
        listed = ", ".join(f"{k}={changes[k][0]!r} (now {changes[k][1]!r})" for k in refused)
        raise ConfigError(
            f"the config differs from the resumed run's {config_file} in {listed}; resume with "
            f"the run's own values, pass {ALLOW_CHANGE_FLAG} to resume with the new ones (the "
            f"old config is kept in {CONFIG_HISTORY_FILE}), or pass a fresh --workdir")
    return changes, refused


def _config_value(value: Any, hint: Any) -> Any:
    """A dataclass default as a ConfigDict value that command-line overrides can set."""
    if isinstance(value, (type, np.dtype)):  # jnp.float32 and friends: by name
        return np.dtype(value).name
    if value is None:
        # A typed None, so that --config.model.embed_dim=256 parses as an int.
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        return ml_collections.FieldReference(None, field_type=args[0] if args else str)
    return value


def _section_defaults(classes: tuple[type, ...]) -> ml_collections.ConfigDict:
    out = ml_collections.ConfigDict()
    for cls in classes:
        hints = typing.get_type_hints(cls)
        for f in _fields(cls):
            default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
            out[f.name] = _config_value(default, hints[f.name])
    return out


def default_config(trainer: str = "detector") -> ml_collections.ConfigDict:
    """Every key of ``trainer``'s schema at its dataclass default (config files override from
    here)."""
    c = ml_collections.ConfigDict(dataclasses.asdict(RunSettings(trainer=trainer)))
    for section, classes in sections(trainer).items():
        parent, _, name = section.rpartition(".")
        (c[parent] if parent else c)[name] = _section_defaults(classes)
    return c


# --------------------------------------------------------------------------- config -> objects


def resolve_dtype(name: Any) -> Any:
    """``"auto"`` -> bfloat16 on accelerators, float32 on CPU; otherwise the named dtype."""
    if isinstance(name, str) and name == "auto":
        return jnp.bfloat16 if jax.default_backend() != "cpu" else jnp.float32
    return jnp.dtype(name)


def _trainer(config: ml_collections.ConfigDict) -> str:
    return config.get("trainer", "detector")


def model_config(config: ml_collections.ConfigDict) -> DetectorConfig | RefinerConfig:
    """The trainer's model config (``DetectorConfig(**config.model)`` or ``RefinerConfig``)
    with ``dtype`` resolved."""
    fields = config.model.to_dict()
    if "dtype" in fields:
        fields["dtype"] = resolve_dtype(fields["dtype"])
    (cls,) = sections(_trainer(config))["model"]
    return cls(**fields)


def loss_config(config: ml_collections.ConfigDict) -> DetectorLossConfig | RefinerLossConfig:
    """The trainer's loss config built from ``config.loss``."""
    (cls,) = sections(_trainer(config))["loss"]
    return cls(**config.loss.to_dict())


def refiner_example_config(config: ml_collections.ConfigDict) -> RefinerExampleConfig:
    """The refiner's ``RefinerExampleConfig``: the data section's fields with the crop and map
    sizes of the model."""
    model = model_config(config)
    names = {f.name for f in _fields(RefinerExampleConfig)}
    fields = {k: v for k, v in config.data.to_dict().items() if k in names}
    return RefinerExampleConfig(**fields, crop_size=model.crop_size,
                                output_size=model.output_size)


def refine_settings(config: ml_collections.ConfigDict) -> RefineSettings:
    """``RefineSettings(**config.refine)``."""
    return RefineSettings(**config.refine.to_dict())


def example_config(config: ml_collections.ConfigDict, *, split: str, num_templates: int
                   ) -> ExampleConfig:
    """The data section's ExampleConfig fields, with the tile and render sizes of the model."""
    model = model_config(config)
    names = {f.name for f in _fields(ExampleConfig)}
    fields = {k: v for k, v in config.data.to_dict().items() if k in names}
    if "scale_prior" in fields:
        fields["scale_prior"] = tuple(fields["scale_prior"])
    return ExampleConfig(**fields, tile_size=model.image_size, render_size=model.render_size,
                         num_templates=num_templates, split=split)


def photometric_config(config: ml_collections.ConfigDict) -> PhotometricConfig:
    """``PhotometricConfig(**config.data.photometric)`` (defaults when the config has none)."""
    return PhotometricConfig(**config.data.get("photometric", ml_collections.ConfigDict())
                             .to_dict())
