"""A training campaign that spans sessions: ``python -m train.campaign --model detector|refiner
--hours H --workdir W``.

The shipped models are trained on machines that are lent for a few hours at a time and whose
disks do not last: the campaign is one command that can be stopped at any moment (SIGTERM or
Ctrl-C save the training state) and run again, on the same machine or a fresh one, to go on.
Its stages each resume:

1. **Data** (``W/data/<layout>``, ``datagen.generate``): ``--parts`` procedural parts of
   ``--seed``; a fixed share of them (``--heldout``, by a hash of each part's name: datagen's
   ``--val-fraction``) never appears in training. For every layout of :data:`LAYOUTS` (a robot
   cell: one camera above a tray, one image per pile; and mixed: drops, floats and packs seen
   from 4 random views per scene) the training scenes use the other parts (``train_pbr``,
   ``--train-images`` over all layouts) and the held-out scenes only the held-out parts
   (``val_pbr``, ``--heldout-images``: checkpoint selection and the zero-shot figures of the
   model card). Scene ``s`` is drawn from ``(seed, split, s)``, so regenerating gives the same
   images byte for byte: data is never committed, a fresh machine makes it again.
2. **Records** (``W/records``, ``datagen.pack``): every layout's training scenes -> ``train``,
   the held-out scenes -> ``val``, render banks at the model's render size.
3. **Plan** (``W/campaign.json``): the data settings, and per model its config, its warm step
   time measured once on this machine and the steps that fit ``--hours`` of training. Fixed on
   the first run, so a resumed campaign keeps its learning-rate schedule; a later run with
   other data settings is refused (they would change the images), other ``--hours`` are noted
   and ignored.
4. **Training** (``W/<model>``): an ordinary run directory (``python -m infer ... --workdir
   W/detector``, ``--refiner W/refiner``), checkpointed every :data:`CHECKPOINT_MINUTES` of
   steps and on SIGTERM, evaluated :data:`NUM_EVALS` times on the held-out parts (the best
   checkpoint by the model's metric: full-image AP50, or MSSD recall after refinement).
   SIGTERM or Ctrl-C while training save the step reached; while making data they stop at
   once, and the finished scenes are kept (datagen resumes at the first missing scene).

Both models share ``W``'s data: ``--model detector`` then ``--model refiner`` on one workdir
generate it once.

Across machines the training state travels in the repository: ``python -m train.export --run
W/detector --campaign W/campaign.json --out models/detector-NAME`` keeps the latest checkpoint
whole while the run is unfinished, and on the next machine ``--resume-from
models/detector-NAME`` starts ``W`` from it (the plan, the configs and the checkpoints, with
``data_dir`` pointed at this machine's records: the regenerated data is the same).
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import shutil
import signal
import sys
import time
from collections.abc import Sequence

from threept_jax.data.run_dir import RunDir
from train import stages

#: Scene layouts of the data, with the images per scene of each (a cell: one per pile).
LAYOUTS = {"cell": 1, "mixed": 4}
#: Minutes of training between checkpoints (a crash, not a SIGTERM, loses at most this).
CHECKPOINT_MINUTES = 10.0
#: Held-out evaluations over a campaign (each ranks the checkpoint it follows).
NUM_EVALS = 8
#: The data settings a campaign fixes on its first run (``campaign.json``'s ``data``).
DATA_KEYS = ("parts", "seed", "heldout", "train_images", "heldout_images", "resolution", "spp",
             "instances")


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m train.campaign",
                                description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--model", required=True, choices=("detector", "refiner"))
    p.add_argument("--hours", type=float, required=True,
                   help="training budget of the model (wall clock on this machine, over all "
                        "sessions); fixed on the first run")
    p.add_argument("--workdir", type=pathlib.Path, required=True,
                   help="campaign folder: data/, records/, detector/, refiner/, campaign.json")
    p.add_argument("--config", default="tiny", choices=stages.CONFIGS,
                   help="train/configs/<model>.py config")
    p.add_argument("--parts", type=int, default=300, help="procedural parts")
    p.add_argument("--heldout", type=float, default=0.1,
                   help="share of the parts never trained on (the zero-shot figures)")
    p.add_argument("--train-images", type=int, default=1500, help="over all layouts")
    p.add_argument("--heldout-images", type=int, default=64, help="over all layouts")
    p.add_argument("--resolution", type=int, nargs=2, default=(640, 480), metavar=("W", "H"))
    p.add_argument("--spp", type=int, default=2, help="samples per pixel, denoised")
    p.add_argument("--instances", type=int, default=8, help="mean part instances per scene")
    p.add_argument("--seed", type=int, default=0, help="parts and scenes")
    p.add_argument("--resume-from", type=pathlib.Path, default=None, metavar="MODEL",
                   help="an exported model of this campaign (train.export) to go on from when "
                        "--workdir has no checkpoint of the model yet")
    args = p.parse_args(argv)
    if not 0 < args.hours <= 1000:
        p.error(f"--hours must be in (0, 1000], got {args.hours:g}")
    if args.parts < 2:
        p.error(f"--parts must be >= 2 (some to train on, some held out), got {args.parts}")
    if not 0 < args.heldout < 1:
        p.error(f"--heldout must be a share in (0, 1), got {args.heldout:g}")
    for name, low in (("train_images", len(LAYOUTS)), ("heldout_images", len(LAYOUTS)),
                      ("spp", 1), ("instances", 1)):
        if getattr(args, name) < low:
            p.error(f"--{name.replace('_', '-')} must be >= {low}, got {getattr(args, name)}")
    if min(args.resolution) < 64:
        p.error(f"--resolution must be at least 64 x 64, got {args.resolution}")
    args.resolution = list(args.resolution)
    return args


def seed_from(args) -> None:
    """Start ``--workdir`` from ``--resume-from``'s plan, configs and checkpoints (module
    docstring) when it has none of its own; refuses a model that cannot go on."""
    src, run = args.resume_from, args.workdir / args.model
    if src is None or RunDir(run, args.model).checkpoint_steps():
        return
    source = RunDir(src, args.model)
    source.verify(restore=f"restore it with `git checkout -- {src}`")
    if not (src / "campaign.json").exists() or not source.checkpoint_steps():
        raise SystemExit(f"error: --resume-from {src} holds no campaign.json or no checkpoint: "
                         f"export it with python -m train.export --campaign W/campaign.json")
    config = source.read_config()
    latest = source.path / "checkpoints" / str(source.checkpoint_steps()[-1])
    if not (latest / "data").exists():
        raise SystemExit(f"error: {src} is a finished model (no training state in {latest}); "
                         "start a new campaign in a fresh --workdir to train further")
    args.workdir.mkdir(parents=True, exist_ok=True)
    if not (args.workdir / "campaign.json").exists():
        shutil.copy2(src / "campaign.json", args.workdir / "campaign.json")
    run.mkdir(parents=True, exist_ok=True)
    for f in src.iterdir():
        if f.is_file() and f.suffix == ".json" and f.name != "campaign.json":
            shutil.copy2(f, run / f.name)
    config["data_dir"] = str((args.workdir / "records").resolve())
    (run / "config.json").write_text(json.dumps(config, indent=1))
    shutil.copytree(source.checkpoint_dir, RunDir(run, args.model).checkpoint_dir)
    print(f"   {run} starts from {src} (step {source.checkpoint_steps()[-1]})", flush=True)


def data_settings(args) -> dict:
    return {k: getattr(args, k) for k in DATA_KEYS}


def read_plan(args) -> dict:
    """``campaign.json`` (empty before the first run); refuses other data settings."""
    path = args.workdir / "campaign.json"
    if not path.exists():
        return {"data": data_settings(args)}
    plan = json.loads(path.read_text())
    changed = {k: (plan["data"][k], v) for k, v in data_settings(args).items()
               if plan["data"].get(k) != v}
    if changed:
        flags = ", ".join(f"--{k.replace('_', '-')} {old} (given {new})"
                          for k, (old, new) in changed.items())
        raise SystemExit(f"error: {path} fixed the campaign's data with {flags}: run with those "
                         "values to resume, or use a new --workdir for other data")
    return plan


def write_plan(args, plan: dict) -> None:
    args.workdir.mkdir(parents=True, exist_ok=True)
    (args.workdir / "campaign.json").write_text(json.dumps(plan, indent=1))


def share(total: int, index: int, parts: int) -> int:
    """Item ``index``'s part of ``total`` split over ``parts`` (the first get the remainder)."""
    return total // parts + (index < total % parts)


def generate(args, data: pathlib.Path) -> list[pathlib.Path]:
    """Every layout's training and held-out scenes (module docstring, stage 1); the dataset
    folders."""
    from datagen import generate as G

    out = []
    for i, (layout, per_scene) in enumerate(LAYOUTS.items()):
        folder = data / layout
        for split, images in (("train", args.train_images), ("val", args.heldout_images)):
            scenes = max(1, -(-share(images, i, len(LAYOUTS)) // per_scene))
            print(f"   {layout} {split}: {scenes} scenes x {per_scene} image(s) -> {folder}",
                  flush=True)
            G.main(datagen_argv(data, layout, split, scenes, **data_settings(args)))
        out.append(folder)
    return out


def datagen_argv(data: pathlib.Path, layout: str, split: str, scenes: int, *, parts: int,
                 seed: int, heldout: float, resolution, spp: int, instances: int,
                 **_) -> list[str]:
    """``python -m datagen.generate`` arguments of the first ``scenes`` scenes of a layout's
    split, from the campaign's data settings (``campaign.json``'s ``data``): scene ``s`` is the
    same images for any ``scenes`` > ``s``, so a test can remake a campaign's first held-out
    scenes."""
    return ["--out", str(data / layout), "--meshes", f"procedural:{parts}", "--seed", str(seed),
            "--val-fraction", str(heldout), "--layout", layout,
            "--resolution", *map(str, resolution), "--spp", str(spp), "--max-depth", "3",
            "--instances", str(instances), "--distinct", "1", str(min(instances, 6)),
            "--images-per-scene", str(LAYOUTS[layout]), "--quiet", "--split", split,
            "--num-scenes", str(scenes)]


def pack(folders: Sequence[pathlib.Path], records: pathlib.Path, render_size: int) -> None:
    """``train`` and ``val`` records of every layout's scenes (stage 2); objects are merged
    across layouts by mesh, labelled with the split they come from."""
    from datagen import pack as Pk

    for name, split in (("train", "train_pbr"), ("val", "val_pbr")):
        if (records / name / "index.json").exists():
            print(f"   {records / name} exists, skipped", flush=True)
            continue
        Pk.main(["--scenes", *(str(f / split) for f in folders), "--out", str(records),
                 "--name", name, "--split-label",
                 split.removesuffix("_pbr"), "--bank-size", str(render_size),
                 "--num-templates", "512", "--quiet"])


def model_config(args, records: pathlib.Path):
    """The model's training config (``--config`` of ``train/configs/<model>.py``) on
    ``records``."""
    if args.model == "detector":
        from train.configs.detector import get_config
    else:
        from train.configs.refiner import get_config
    config = get_config(args.config)
    config.data_dir = str(records.resolve())
    config.progress_bar = True
    return config


def plan_steps(args, plan: dict, config) -> dict:
    """The model's entry of ``plan``: measured once, then kept (module docstring, stage 3)."""
    entry = plan.get(args.model)
    if entry is not None:
        print(f"   {entry['steps']} steps of {entry['step_seconds']:.3f} s ({entry['hours']:g} "
              f"hours, {entry['config']}), from {args.workdir / 'campaign.json'}", flush=True)
        if entry["hours"] != args.hours or entry["config"] != args.config:
            print(f"   note: the {args.model} was planned as {entry['config']} for "
                  f"{entry['hours']:g} hours; --config {args.config} --hours {args.hours:g} "
                  "are ignored so that the run keeps its schedule", flush=True)
        return entry
    step_s = stages.measure_step_seconds(config)
    steps = max(NUM_EVALS, int(args.hours * 3600 * (1 - stages.EVAL_SHARE) / step_s))
    entry = {"steps": steps, "step_seconds": step_s, "hours": args.hours, "config": args.config}
    print(f"   {step_s:.3f} s per step of batch {config.batch_size}: {steps} steps in "
          f"{args.hours:g} hours", flush=True)
    return entry


def main(argv: Sequence[str] | None = None) -> dict:
    stages.log_friendly_progress()
    args = parse_args(argv)
    seed_from(args)
    plan = read_plan(args)
    write_plan(args, plan)
    w = args.workdir

    start = stages.stage(f"1/4 data: {args.parts} procedural parts ({args.heldout:g} held out), "
                         f"{args.train_images} training images -> {w / 'data'}")
    folders = generate(args, w / "data")
    stages.done(start)

    from train.configs.detector import get_config as detector_config

    config = model_config(args, w / "records")
    start = stages.stage(f"2/4 records -> {w / 'records'}")
    # The render banks serve the detector of the same --config, whichever model runs first.
    pack(folders, w / "records", int(detector_config(args.config).model.render_size))
    stages.done(start)

    start = stages.stage(f"3/4 plan: the {args.config} {args.model} in {args.hours:g} hours")
    plan[args.model] = plan_steps(args, plan, config)
    write_plan(args, plan)
    stages.done(start)

    entry = plan[args.model]
    start = stages.stage(f"4/4 {args.model} training ({entry['steps']} steps) -> {w / args.model}")
    # Ctrl-C while training stops like SIGTERM: the trainer saves the step it reached.
    previous = signal.signal(signal.SIGINT, lambda *_: os.kill(os.getpid(), signal.SIGTERM))
    try:
        every = int(CHECKPOINT_MINUTES * 60 / entry["step_seconds"])
        summary = stages.train_to(config, entry["steps"], w / args.model, evals=NUM_EVALS,
                                  checkpoint_every=every, log_every=min(every, 100))
    finally:
        signal.signal(signal.SIGINT, previous)
    seconds = stages.done(start)
    if summary and summary.get("preempted") is not None:
        print(f"stopped at step {summary['preempted']} (saved); run the same command to go on",
              flush=True)
    plan.setdefault("sessions", []).append(
        {"model": args.model, "ended": time.strftime("%Y-%m-%d %H:%M"),
         "training_minutes": round(seconds / 60, 1)})
    write_plan(args, plan)
    return plan


if __name__ == "__main__":
    try:
        main()
    except KeyboardInterrupt:
        sys.exit("interrupted: finished scenes and checkpoints are kept; run the same command to "
                 "go on")
