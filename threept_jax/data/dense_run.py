"""The dense cell detector's run directory: what ``python -m train.cell_detector`` writes and
inference loads (``--detector cell``).

    <workdir>/cell_detector.json   the network's DenseConfig, the parts (obj_id per class),
                                   the training it had (steps, minutes, records), held-out figures
    <workdir>/weights/             the averaged weights (Orbax: params and batch statistics)
    <workdir>/state/               the whole train state and where the run stands, for
                                   resuming (Orbax; replaced at each save)
    <workdir>/snapshots/<step>/    the averaged weights at points of the run (the curve)
    <workdir>/metrics.jsonl        the training log
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
from typing import Any

import orbax.checkpoint as ocp
from flax import nnx

from threept_jax.data.files import atomic_write_json
from threept_jax.models.dense import DenseConfig, DenseDetector

RUN_FILE = "cell_detector.json"
WEIGHTS = "weights"
STATE = "state"
SNAPSHOTS = "snapshots"


def config_to_json(cfg: DenseConfig) -> dict:
    d = dataclasses.asdict(cfg)
    d.pop("dtype"), d.pop("param_dtype")
    d["image_size"], d["depths"] = list(cfg.image_size), list(cfg.depths)
    return d


def config_from_json(d: dict) -> DenseConfig:
    d = dict(d)
    d["image_size"], d["depths"] = tuple(d["image_size"]), tuple(d["depths"])
    return DenseConfig(**d)


def _abstract(cfg: DenseConfig):
    """(graph, restore target): the network's structure and its state's shapes, nothing
    computed."""
    model = nnx.eval_shape(lambda: DenseDetector(cfg, rngs=nnx.Rngs(0)))
    graphdef, params, stats = nnx.split(model, nnx.Param, nnx.BatchStat)
    return graphdef, {"params": params, "batch_stats": stats}


def network(cfg: DenseConfig, params: nnx.State, batch_stats: nnx.State) -> DenseDetector:
    """The network of ``cfg`` with these weights (nothing initialised)."""
    graphdef, _ = _abstract(cfg)
    return nnx.merge(graphdef, params, batch_stats)


def save(workdir, cfg: DenseConfig, class_ids, params: nnx.State, batch_stats: nnx.State,
         info: dict[str, Any]) -> None:
    """Write the averaged weights and the run file (replacing earlier ones)."""
    workdir = pathlib.Path(workdir).resolve()
    with ocp.StandardCheckpointer() as ckpt:
        ckpt.save(workdir / WEIGHTS, {"params": params, "batch_stats": batch_stats}, force=True)
    atomic_write_json(workdir / RUN_FILE, {"config": config_to_json(cfg),
                                           "class_ids": [int(c) for c in class_ids], **info})


def load(workdir) -> tuple[DenseDetector, list[int], dict]:
    """(network in eval mode, obj_id per class, the run file) of a trained run; a clear error
    for a folder that is not one."""
    workdir = pathlib.Path(workdir).resolve()
    run_file = workdir / RUN_FILE
    if not run_file.is_file() or not (workdir / WEIGHTS).is_dir():
        raise FileNotFoundError(
            f"{workdir} is not a trained cell detector (no {RUN_FILE} and {WEIGHTS}/): train "
            "one with python -m train.cell_detector --records R --workdir DIR --minutes M")
    info = json.loads(run_file.read_text())
    cfg = config_from_json(info["config"])
    _, target = _abstract(cfg)
    with ocp.StandardCheckpointer() as ckpt:
        restored = ckpt.restore(workdir / WEIGHTS, target)
    model = network(cfg, restored["params"], restored["batch_stats"])
    model.eval()
    return model, [int(c) for c in info["class_ids"]], info


def save_info(workdir, info: dict[str, Any]) -> None:
    """Replace the run file's training record (figures added after training), keeping the
    network's config and parts."""
    path = pathlib.Path(workdir) / RUN_FILE
    data = json.loads(path.read_text())
    atomic_write_json(path, {"config": data["config"], "class_ids": data["class_ids"], **info})


def save_snapshot(workdir, step: int, params: nnx.State, batch_stats: nnx.State) -> None:
    """The averaged weights at ``step`` (a point of the held-out curve)."""
    path = pathlib.Path(workdir).resolve() / SNAPSHOTS / str(int(step))
    with ocp.StandardCheckpointer() as ckpt:
        ckpt.save(path, {"params": params, "batch_stats": batch_stats}, force=True)


def snapshots(workdir, cfg: DenseConfig) -> list[tuple[int, nnx.State, nnx.State]]:
    """(step, params, batch statistics) of every snapshot, by step."""
    folder = pathlib.Path(workdir).resolve() / SNAPSHOTS
    steps = sorted(int(p.name) for p in folder.iterdir() if p.name.isdigit()) \
        if folder.is_dir() else []
    out = []
    _, target = _abstract(cfg)
    with ocp.StandardCheckpointer() as ckpt:
        for n in steps:
            r = ckpt.restore(folder / str(n), target)
            out.append((n, r["params"], r["batch_stats"]))
    return out


def save_state(workdir, state: Any, progress: dict[str, Any]) -> None:
    """The whole train state (any pytree of arrays) and ``progress`` (step, plan, seconds
    spent, the settings a resumed run must share), replacing the previous save."""
    workdir = pathlib.Path(workdir).resolve()
    with ocp.StandardCheckpointer() as ckpt:
        ckpt.save(workdir / STATE, state, force=True)
    atomic_write_json(workdir / f"{STATE}.json", progress)


def load_state(workdir, target: Any) -> tuple[Any, dict[str, Any]] | None:
    """The saved train state restored into the structure of ``target`` and its progress, or
    None when the run has none."""
    workdir = pathlib.Path(workdir).resolve()
    if not (workdir / f"{STATE}.json").is_file() or not (workdir / STATE).is_dir():
        return None
    progress = json.loads((workdir / f"{STATE}.json").read_text())
    with ocp.StandardCheckpointer() as ckpt:
        return ckpt.restore(workdir / STATE, target), progress
