"""Export a training run as a model to ship: ``python -m train.export --run W/detector --out
models/detector-NAME``.

The model folder is a run directory (:mod:`threept_jax.data.run_dir`) that holds only what
inference and the card need, so ``infer.load("models/detector-NAME")`` reads it like any run:

* ``config.json``, ``config_history.json`` (when the run has one) and ``detector.json`` /
  ``refiner.json``: the run's configs;
* ``checkpoints/<best>/``: the best checkpoint's parameters alone (no optimizer state, no data
  iterator), with the held-out metrics it was ranked by;
* while the run has not reached its ``total_steps``, also its latest checkpoint whole
  (optimizer state and data iterator), so a campaign can go on from the repository on a fresh
  machine (``python -m train.campaign ... --resume-from models/detector-NAME``); a finished
  run's model carries no training state;
* ``campaign.json``: the campaign's plan (data settings, steps, sessions), with ``--campaign``;
* ``SHA256SUMS``: the checksums every load verifies (a missing or damaged file is named);
* ``MODEL_CARD.md`` (and any other ``*.md``) already in ``--out`` is kept: the card is written
  by hand from the figures measured on the model.

The folder is assembled beside ``--out`` and renamed onto it, so a killed export leaves the old
model or none.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import shutil
import tempfile
from collections.abc import Sequence

import numpy as np

from threept_jax.data.run_dir import (
    CONFIG_FILE,
    CONFIG_HISTORY_FILE,
    MODEL_FILES,
    STATE_ITEM,
    RunDir,
)


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m train.export", description=__doc__.split("\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--run", type=pathlib.Path, required=True, help="a training run's --workdir")
    p.add_argument("--out", type=pathlib.Path, required=True,
                   help="the model folder, e.g. models/detector-NAME (replaced; *.md kept)")
    p.add_argument("--campaign", type=pathlib.Path, default=None,
                   help="the campaign's campaign.json, copied into the model")
    args = p.parse_args(argv)
    kinds = [k for k, (name, _) in MODEL_FILES.items() if (args.run / name).exists()]
    if len(kinds) != 1:
        p.error(f"--run {args.run} is not a training run (no {' or '.join(n for n, _ in MODEL_FILES.values())})")
    args.model = kinds[0]
    if args.campaign is not None and not args.campaign.is_file():
        p.error(f"--campaign {args.campaign}: no such file")
    return args


def total_steps(run: RunDir) -> int:
    """The run's planned steps (``total_steps`` of config.json; 0 when it names none: a run
    without a plan is exported as finished)."""
    return int(run.read_config().get("total_steps", 0))


def write_params(run: RunDir, step: int, out: pathlib.Path) -> None:
    """Checkpoint ``step``'s parameters alone, with its saved metrics, under ``out``'s
    checkpoints (the layout the trainer writes, without ``opt_state`` and ``data``)."""
    import jax
    import orbax.checkpoint as ocp
    from flax import nnx

    model, _, _ = run.load_model(step)
    params = jax.tree.map(np.asarray, nnx.to_pure_dict(nnx.state(model, nnx.Param)))
    metrics = run.saved_metrics(step)
    metric, mode = run.best_metric()
    options = ocp.CheckpointManagerOptions(
        best_fn=None if metric is None else (lambda m: float(m[metric])), best_mode=mode,
        enable_async_checkpointing=False)
    with ocp.CheckpointManager(RunDir(out, run.model).checkpoint_dir, options=options) as mgr:
        mgr.save(step, args=ocp.args.Composite(**{STATE_ITEM: ocp.args.StandardSave(
            {"step": np.int64(step), "params": params})}),
            metrics=metrics if metric in metrics else None)
        mgr.wait_until_finished()


def export(run_path, out, campaign=None, model: str = "detector") -> dict:
    """Write the model folder ``out`` from the run at ``run_path`` (module docstring); returns
    what it holds: ``{"best", "latest", "resumable", "megabytes"}``."""
    run, out = RunDir(run_path, model), pathlib.Path(out)
    best, steps = run.best_step(), run.checkpoint_steps()
    latest = steps[-1]
    resumable = latest < total_steps(run)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = pathlib.Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        for name in (CONFIG_FILE, CONFIG_HISTORY_FILE, MODEL_FILES[model][0]):
            if (run.path / name).exists():
                shutil.copy2(run.path / name, tmp / name)
        if campaign is not None:
            shutil.copy2(campaign, tmp / "campaign.json")
        if out.is_dir():
            for card in out.glob("*.md"):
                shutil.copy2(card, tmp / card.name)
        if resumable:
            shutil.copytree(run.checkpoint_dir / str(latest),
                            RunDir(tmp, model).checkpoint_dir / str(latest))
        if best != latest or not resumable:
            write_params(run, best, tmp)
        RunDir(tmp, model).write_checksums()
        old = out.with_name(f".{out.name}.old")
        if out.exists():
            out.rename(old)
        tmp.rename(out)
        shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    return {"best": best, "latest": latest, "resumable": resumable,
            "megabytes": round(size / 1e6, 1)}


def main(argv: Sequence[str] | None = None) -> dict:
    args = parse_args(argv)
    info = export(args.run, args.out, args.campaign, args.model)
    state = (f"and the training state of step {info['latest']} (the run goes on: "
             f"train.campaign --resume-from {args.out})" if info["resumable"]
             else "(the run is finished: no training state)")
    print(f"{args.out}: the {args.model}'s best step {info['best']} {state}; "
          f"{info['megabytes']} MB", flush=True)
    print(json.dumps(info))
    return info


if __name__ == "__main__":
    main()
