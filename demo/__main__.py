"""The main job on built-in defaults: ``python -m demo`` (what ``make demo`` runs).

The whole pipeline on a CPU in about six minutes (2 cores), with nothing downloaded:

1. **Synthetic data** (``datagen.generate``): procedural CAD meshes in millimetres, split by
   hash into training objects and held-out objects; path-traced scenes of each (Mitsuba).
2. **Records and render banks** (``datagen.pack``): ArrayRecord shards, 12 prior renders and a
   512-template bank per object.
3. **Training** (``train.trainer_detector``): the ``tiny`` 3PT-D config, with progress bar,
   TensorBoard logs and checkpoints, held-out evaluation at the end.
4. **Inference and BOP evaluation** (``python -m infer bop``): the trained detector is
   onboarded on the held-out meshes (never seen in training), detects them and estimates
   their 6D poses in the held-out scenes; writes the BOP CSV and COCO JSON, overlay PNGs and
   the BOP evaluator's scores.

Every stage resumes: run the same command again and finished stages are skipped, a killed
data generation redoes only its unfinished scene and a killed training restarts from its last
checkpoint. Outputs go to ``--out`` (default ``runs/demo``). The tiny model is trained for
minutes on 80 images, so its scores are low but clearly above an untrained model's (README,
"Known limits"); the ``small`` and ``paper`` configs are the ones that train real detectors.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time
from collections.abc import Sequence

#: Scene settings shared by the training and held-out datasets (small renders, CPU).
_SCENE_ARGS = ["--resolution", "160", "128", "--spp", "4", "--max-depth", "3",
               "--instances", "8", "--distinct", "2", "6", "--val-fraction", "0.25", "--quiet"]


def _stage(name: str) -> float:
    print(f"\n== {name}", flush=True)
    return time.perf_counter()


def _done(start: float) -> None:
    print(f"   ({time.perf_counter() - start:.0f} s)", flush=True)


def generate(out: pathlib.Path, meshes: str, train_scenes: int, val_scenes: int) -> None:
    from datagen import generate as G

    for split, scenes, per_scene in (("train", train_scenes, 4), ("val", val_scenes, 2)):
        G.main(["--meshes", meshes, "--out", str(out / split), "--split", split,
                "--num-scenes", str(scenes), "--images-per-scene", str(per_scene), *_SCENE_ARGS])


def pack(data: pathlib.Path, records: pathlib.Path) -> None:
    from datagen import pack as Pk

    for split in ("train", "val"):
        if (records / split / "index.json").exists():
            print(f"   {records / split} exists, skipped")
            continue
        Pk.main(["--scenes", str(data / split / f"{split}_pbr"), "--out", str(records),
                 "--name", split, "--split-label", split, "--bank-size", "32",
                 "--num-templates", "512", "--quiet"])


def train_config(records: pathlib.Path, steps: int):
    from train.configs.detector import get_config

    config = get_config("tiny")
    config.data_dir = str(records)
    config.total_steps = steps
    config.eval.update(every_steps=steps, num_examples=128, batch_size=16)
    config.checkpoint.every_steps = max(steps // 4, 1)
    config.log_every = max(steps // 10, 1)
    return config


def main(argv: Sequence[str] | None = None) -> dict:
    p = argparse.ArgumentParser(prog="python -m demo", description=__doc__.split("\n")[0])
    p.add_argument("--out", type=pathlib.Path, default=pathlib.Path("runs/demo"))
    p.add_argument("--meshes", default="procedural:24",
                   help="mesh sources for datagen.generate (default: 24 procedural meshes)")
    p.add_argument("--train-scenes", type=int, default=20, help="4 images each")
    p.add_argument("--val-scenes", type=int, default=6, help="2 images each")
    p.add_argument("--steps", type=int, default=1000, help="training steps (batch 16)")
    args = p.parse_args(argv)
    for name in ("train_scenes", "val_scenes", "steps"):
        if getattr(args, name) < 1:
            p.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    out = args.out
    data, records, workdir = out / "data", out / "records", out / "train"
    total = time.perf_counter()

    start = _stage(f"1/4 synthetic data -> {data}")
    generate(data, args.meshes, args.train_scenes, args.val_scenes)
    _done(start)

    start = _stage(f"2/4 records and render banks -> {records}")
    pack(data, records)
    _done(start)

    start = _stage(f"3/4 training (tiny config, {args.steps} steps) -> {workdir}")
    from train import trainer_detector

    held_out = trainer_detector.train(train_config(records, args.steps), workdir)["eval"]
    if not held_out:  # trained by an earlier run: its last evaluation is in the checkpoint
        from infer.checkpoint import saved_metrics

        held_out = saved_metrics(workdir, args.steps)
        print("   already trained to the last step (delete the folder to retrain)")
    print("   held-out evaluation (full images; tile_diagnostic/* on ground-truth crops): " + ", ".join(
        f"{k.removeprefix('eval/')}={v:.3f}" for k, v in held_out.items()))
    _done(start)

    start = _stage(f"4/4 inference + BOP evaluation on held-out objects -> {out / 'results'}")
    from infer.cli import main as infer_main

    result = infer_main(["bop", "--workdir", str(workdir), "--step", "latest",
                         "--dataset-dir", str(data / "val"), "--split", "val_pbr",
                         "--targets", "all", "--evaluate", "--num-templates", "512",
                         # Every image's 20 best detections, whatever their score: AP ranks them.
                         "--score-threshold", "0", "--max-detections", "20",
                         "--out", str(out / "results"), "--overlays", "4",
                         "--cache-dir", str(out / "cache")])
    _done(start)

    report = {"train_eval": held_out, "bop": result,
              "minutes": (time.perf_counter() - total) / 60}
    (out / "report.json").write_text(json.dumps(report, indent=1, default=float))
    pose, boxes = result.get("pose", {}), result.get("detection", {}).get("bbox", {})
    print(f"\ndone in {report['minutes']:.1f} min. Held-out objects, full images: box AP50 "
          f"{boxes.get('ap50', float('nan')):.3f}, BOP 6D AP {pose.get('ap', float('nan')):.4f} "
          f"(diagnostic, crops anchored on a ground-truth instance: tile AP50 "
          f"{held_out.get('eval/tile_diagnostic/ap50', float('nan')):.3f})."
          f"\nReport {out / 'report.json'}, overlays {out / 'results' / 'overlays'}")
    return report


if __name__ == "__main__":
    main()
