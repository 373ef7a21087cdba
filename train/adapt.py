"""Adapt 3PT-D to your own parts: ``python -m train.adapt --meshes DIR --workdir W``.

3PT finds parts it has never seen (zero-shot). An industrial cell, though, handles a fixed set
of parts, and the best BOP-Industrial entries train a few minutes per part. This command does
that with our own data engine, in five stages that each resume when the command is run again:

1. **Scenes** (``datagen.generate``): path-traced scenes of exactly the given meshes (drop,
   float and pack layouts, distractors, random materials), in three disjoint sets of one mesh
   pool: ``W/data/train`` (training), ``W/data/val`` (checkpoint selection and the score
   threshold of the overlays) and ``W/data/test`` (the report; neither training nor selection
   sees it).
2. **Records** (``datagen.pack``): ArrayRecord shards and render banks at the model's render
   size -> ``W/records``.
3. **Budget**: the warm step time of this config on this machine is measured once (a few
   compiled steps of a throw-away state) and the number of steps that fits ``--minutes`` is
   fixed in ``W/adapt.json``, so that a resumed run keeps its learning-rate schedule.
4. **Training** (``train.trainer_detector``), from scratch or from ``--from RUN``'s best
   checkpoint (fine-tuning: the model section is that run's). ``W`` is an ordinary run
   directory (``config.json``, ``checkpoints/``, ``tb/``): ``python -m infer images --workdir W``
   loads it, and a killed run resumes from its last checkpoint.
5. **Test**: the best checkpoint (by full-image AP50 on the val scenes) runs ``python -m infer
   bop`` on the val scenes, whose best-F1 score becomes the overlay threshold, then on the test
   scenes: full images, every part queried. Box AP / AP50 (COCO, BOP ignore rule) and BOP 6D
   AP (MSSD/MSPD, object generation alone) -> ``W/report.json``; overlays (boxes and pose
   contours, at least 640 px wide) under ``W/test/overlays``.

``--meshes`` takes what ``datagen.generate`` takes: BOP models folders, trees of mesh files
(``--mesh-units`` when not mm), or ``procedural:N`` (N parts of ``--seed``; the demo's parts).
"""

from __future__ import annotations

import argparse
import json
import pathlib
import tempfile
import time
from collections.abc import Sequence

#: Share of ``--minutes`` kept for the periodic evaluations and checkpoints of the run.
EVAL_SHARE = 0.15
#: Evaluations (full val images) and checkpoints over the run.
NUM_EVALS = 4
#: Steps timed for the budget (after one compiling step and two warm-up steps).
TIMED_STEPS = 8
CONFIGS = ("tiny", "cpu", "small", "paper")


def _stage(text: str) -> float:
    print(f"\n== {text}", flush=True)
    return time.perf_counter()


def _done(start: float) -> float:
    seconds = time.perf_counter() - start
    print(f"   ({seconds:.0f} s)", flush=True)
    return seconds


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m train.adapt", description=__doc__.split("\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--meshes", nargs="+", required=True,
                   help="the parts: BOP models folders, trees of mesh files, or procedural:N")
    p.add_argument("--mesh-units", default="mm", choices=("mm", "cm", "m", "in"),
                   help="units of the mesh files")
    p.add_argument("--workdir", type=pathlib.Path, required=True,
                   help="run folder: data/, records/, the training run, test/, report.json")
    p.add_argument("--minutes", type=float, default=10.0, help="training budget (wall clock)")
    p.add_argument("--from", dest="init_from", type=pathlib.Path, default=None,
                   help="a detector training run to fine-tune (its best checkpoint); default: "
                        "train from scratch")
    p.add_argument("--config", default="cpu", choices=CONFIGS,
                   help="train/configs/detector.py config (ignored for the model with --from)")
    p.add_argument("--train-scenes", type=int, default=40, help="4 images each")
    p.add_argument("--test-scenes", type=int, default=6,
                   help="2 images each, and as many val scenes")
    p.add_argument("--resolution", type=int, nargs=2, default=(320, 240), metavar=("W", "H"))
    p.add_argument("--spp", type=int, default=4, help="path-tracing samples per pixel")
    p.add_argument("--instances", type=int, default=8, help="mean part instances per scene")
    p.add_argument("--seed", type=int, default=0, help="scenes (and procedural parts)")
    p.add_argument("--overlays", type=int, default=6, help="test overlays written")
    args = p.parse_args(argv)
    for name in ("train_scenes", "test_scenes", "spp", "instances"):
        if getattr(args, name) < 1:
            p.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    if not 0 < args.minutes <= 24 * 60:
        p.error(f"--minutes must be in (0, 1440], got {args.minutes:g}")
    if min(args.resolution) < 64:
        p.error(f"--resolution must be at least 64 x 64, got {args.resolution}")
    if args.init_from is not None and not (args.init_from / "detector.json").exists():
        p.error(f"--from {args.init_from} is not a detector training run (no detector.json); "
                "pass the --workdir of a train/launch.py or train.adapt run")
    return args


# --------------------------------------------------------------------------- stages 1-2


def generate(args, data: pathlib.Path, sets: Sequence[str] = ("train", "val", "test")) -> None:
    """Scenes of ``args.meshes``: ``train``, and ``val`` and ``test`` as the two shards of one
    held-out set (disjoint scenes of the same mesh pool)."""
    from datagen import generate as G

    common = ["--meshes", *args.meshes, "--mesh-units", args.mesh_units,
              "--resolution", *map(str, args.resolution), "--spp", str(args.spp),
              "--max-depth", "3", "--instances", str(args.instances),
              "--distinct", "1", str(min(args.instances, 6)), "--val-fraction", "0",
              "--seed", str(args.seed), "--quiet"]
    runs = {"train": ["--split", "train", "--num-scenes", str(args.train_scenes),
                      "--images-per-scene", "4"]}
    for shard, name in enumerate(("val", "test")):
        runs[name] = ["--split", "val", "--num-scenes", str(2 * args.test_scenes),
                      "--images-per-scene", "2", "--num-shards", "2", "--shard", str(shard)]
    for name in sets:
        print(f"   {name}: {data / name}", flush=True)
        G.main(["--out", str(data / name), *runs[name], *common])


def pack(data: pathlib.Path, records: pathlib.Path, render_size: int) -> None:
    from datagen import pack as Pk

    for name, folder in (("train", "train_pbr"), ("val", "val_pbr")):
        if (records / name / "index.json").exists():
            print(f"   {records / name} exists, skipped")
            continue
        # No --split-label: every part is trained on and evaluated.
        Pk.main(["--scenes", str(data / name / folder), "--out", str(records), "--name", name,
                 "--bank-size", str(render_size), "--num-templates", "512", "--quiet"])


# --------------------------------------------------------------------------- stages 3-4


def base_config(args, records: pathlib.Path):
    """The training config: ``--config``'s, with the model of ``--from``'s run."""
    from threept_jax.data.run_dir import RunDir
    from train.configs.detector import get_config

    config = get_config(args.config)
    if args.init_from is not None:
        model = RunDir(args.init_from).read_model_config().to_dict()
        config.model.update({k: v for k, v in model.items() if k in config.model})
        config.init_from = str(args.init_from.resolve())
    config.data_dir = str(records.resolve())
    config.progress_bar = True
    return config


def measure_step_seconds(config) -> float:
    """Warm seconds per train step of ``config`` here (a throw-away run in a temp folder)."""
    import jax

    from train.trainer_detector import DetectorTrainer

    probe = config.copy_and_resolve_references()
    probe.eval.every_steps = 0
    probe.init_from = ""
    with tempfile.TemporaryDirectory() as tmp:
        trainer = DetectorTrainer(probe, tmp)
        try:
            for i in range(3 + TIMED_STEPS):
                if i == 3:
                    start = time.perf_counter()
                jax.block_until_ready(trainer.train_step(trainer.next_batch()))
            return (time.perf_counter() - start) / TIMED_STEPS
        finally:
            trainer.close()


def plan(args, config, workdir: pathlib.Path) -> dict:
    """Steps that fit the budget, measured once and kept in ``W/adapt.json``."""
    path = workdir / "adapt.json"
    if path.exists():
        saved = json.loads(path.read_text())
        print(f"   {saved['steps']} steps ({saved['step_seconds']:.3f} s each), from {path}")
        if saved["minutes"] != args.minutes:
            print(f"   note: this run was planned for {saved['minutes']:g} minutes; --minutes "
                  f"{args.minutes:g} is ignored so that the resumed run keeps its schedule "
                  "(use a new --workdir to train with another budget)")
        return saved
    step_s = measure_step_seconds(config)
    steps = max(NUM_EVALS, int(args.minutes * 60 * (1 - EVAL_SHARE) / step_s))
    saved = {"steps": steps, "step_seconds": step_s, "minutes": args.minutes,
             "config": args.config, "meshes": args.meshes,
             "from": None if args.init_from is None else str(args.init_from)}
    workdir.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(saved, indent=1))
    print(f"   {step_s:.3f} s per step of batch {config.batch_size}: {steps} steps in "
          f"{args.minutes:g} minutes")
    return saved


def train(config, steps: int, workdir: pathlib.Path) -> dict:
    from train import trainer_detector

    config.total_steps = steps
    every = max(steps // NUM_EVALS, 1)
    config.eval.every_steps = every
    config.checkpoint.every_steps = every
    config.log_every = max(steps // 20, 1)
    return trainer_detector.train(config, workdir)


# --------------------------------------------------------------------------- stage 5


def infer_bop(workdir: pathlib.Path, dataset: pathlib.Path, out: pathlib.Path, cache: pathlib.Path,
              overlays: int = 0, overlay_threshold: float | None = None) -> dict:
    from infer.cli import main as infer_main

    argv = ["bop", "--workdir", str(workdir), "--step", "best", "--dataset-dir", str(dataset),
            "--split", "val_pbr", "--targets", "all", "--evaluate", "--num-templates", "512",
            # Every image's 20 best detections whatever their score: AP ranks them.
            "--score-threshold", "0", "--max-detections", "20", "--out", str(out),
            "--overlays", str(overlays), "--cache-dir", str(cache)]
    if overlay_threshold is not None:
        argv += ["--overlay-threshold", f"{overlay_threshold:.6g}"]
    return infer_main(argv)


def figures(result: dict) -> dict:
    """The headline numbers of an ``infer bop --evaluate`` result."""
    box = result.get("detection", {}).get("bbox", {})
    pose = result.get("pose", {})
    return {"box_ap": box.get("ap"), "box_ap50": box.get("ap50"), "box_f1": box.get("f1"),
            "box_f1_threshold": box.get("f1_threshold"), "pose_ap": pose.get("ap"),
            "pose_ap_mssd": pose.get("ap_mssd"), "pose_ap_mspd": pose.get("ap_mspd")}


def test(workdir: pathlib.Path, data: pathlib.Path, out: pathlib.Path, cache: pathlib.Path,
         overlays: int) -> dict:
    """The best checkpoint of ``workdir`` on ``data/val`` (whose best-F1 score becomes the
    overlay threshold) and on ``data/test``: figures, threshold and the overlays' folder."""
    val = figures(infer_bop(workdir, data / "val", out / "val", cache))
    threshold = val["box_f1_threshold"]
    print(f"   overlay threshold {threshold:.3f} (best F1 {val['box_f1']:.3f} on the val scenes)")
    result = figures(infer_bop(workdir, data / "test", out / "test", cache, overlays=overlays,
                               overlay_threshold=threshold))
    return {"test": result, "val": val, "overlay_threshold": threshold,
            "overlays": str(out / "test" / "overlays")}


def main(argv: Sequence[str] | None = None) -> dict:
    args = parse_args(argv)
    w = args.workdir
    data, records, cache = w / "data", w / "records", w / "cache"
    minutes: dict[str, float] = {}

    start = _stage(f"1/5 scenes of {' '.join(args.meshes)} -> {data}")
    generate(args, data)
    minutes["scenes"] = _done(start) / 60

    config = base_config(args, records)
    start = _stage(f"2/5 records and render banks -> {records}")
    pack(data, records, int(config.model.render_size))
    minutes["records"] = _done(start) / 60

    start = _stage(f"3/5 budget: steps of the {config.model.variant} detector in "
                   f"{args.minutes:g} minutes")
    budget = plan(args, config, w)
    minutes["budget"] = _done(start) / 60

    start = _stage(f"4/5 training ({budget['steps']} steps, "
                   f"{'from ' + str(args.init_from) if args.init_from else 'from scratch'}) -> {w}")
    train(config, budget["steps"], w)
    minutes["training"] = _done(start) / 60

    start = _stage(f"5/5 full-image test on new scenes -> {w / 'test'}")
    report = test(w, data, w, cache, args.overlays)
    test_figures = report["test"]
    minutes["test"] = _done(start) / 60
    report.update(steps=budget["steps"], config=config.model.variant, minutes=minutes)
    (w / "report.json").write_text(json.dumps(report, indent=1, default=float))
    print(f"\nadapted detector, test scenes (full images, all parts queried): box AP50 "
          f"{test_figures['box_ap50']:.3f}, AP {test_figures['box_ap']:.3f}, BOP 6D AP "
          f"{test_figures['pose_ap']:.3f}"
          f"\nreport {w / 'report.json'}, overlays {w / 'test' / 'overlays'}")
    return report


if __name__ == "__main__":
    main()
