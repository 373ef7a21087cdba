"""Adapted 3PT-D against a standard detector at equal CPU minutes (issue 38).

Each arm trains the demo's adapted detector (``train/configs/detector.py:tiny`` from scratch,
as ``python -m demo`` does) on the same records with one change, for the steps that fit
``--minutes`` at its measured step time (``train.adapt``'s budget: 85 % of the minutes for
steps), with four held-out evaluations on the way (full-image val AP50 and the GT-anchored tile
AP50, a diagnostic); then every arm, and YOLOv8n when ``--yolo-python`` names an environment
with Ultralytics (``bench/yolo_reference.py``), is scored on the same test images by the
project's evaluator: box AP50 / AP with every part queried, the default inference path
(``train.adapt``'s test stage, no refinement). Prints one row per arm and each arm's AP50 as a
ratio of the first arm's (the reference run, in this process).

    python bench/adapt_pace.py --records runs/demo/adapted/records \\
        --test runs/demo/adapted/data/test --minutes 10 --arms patch conv \\
        [--yolo-python /path/to/venv/bin/python] [--out runs/bench/adapt_pace]

The arms (:data:`ARMS`) are config overrides; ``--set KEY=VALUE`` adds to every arm.
``--dense ARM ... --seeds S ...`` also trains the dense cell detector (``train.cell_detector``,
:data:`DENSE_ARMS`) for the same minutes at each seed, with its held-out curve on ``--val``
(four points), scored by the same evaluator on the same test images:

    python bench/adapt_pace.py --arms conv --dense dense --seeds 0 1 \
        --val runs/demo/adapted/data/val --minutes 10
"""

from __future__ import annotations

import argparse
import json
import pathlib
import subprocess
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

#: arm name -> overrides of the ``tiny`` detector config (dotted keys).
ARMS = {
    "patch": {},  # the demo's detector as it is
    "conv": {"model.stem": "conv"},  # early convolutions instead of the patch convolution
    "tile256": {"model.image_size": 256},  # 4x the pixels per part, 4x the tokens
    "lr3e-3": {"optim.learning_rate": 3e-3},  # a faster schedule for a 10-minute budget
    # Capacity: the cpu config's mini/16 ViT (width 128, depth 4: 4x the parameters).
    "mini": {"model.stem": "conv", "model.variant": "mini/16"},
    # Positives by place (FCOS centre sampling) instead of Hungarian matching.
    "centre": {"model.stem": "conv", "loss.assignment": "centre", "loss.matches_per_target": 1},
    # Both levers that fit one cell image faster: positives by place and a 3x learning rate.
    "centre_lr3e-3": {"model.stem": "conv", "loss.assignment": "centre",
                      "loss.matches_per_target": 1, "optim.learning_rate": 3e-3},
}


def _set(config, key: str, value) -> None:
    *path, last = key.split(".")
    node = config
    for k in path:
        node = node[k]
    node[last] = type(node[last])(value) if node[last] is not None else value


def train_arm(name: str, overrides: dict, records: pathlib.Path, test: pathlib.Path,
              minutes: float, out: pathlib.Path) -> dict:
    from threept_jax.data.run_dir import RunDir
    from train import adapt, stages
    from train.configs.detector import get_config

    config = get_config("tiny")
    config.data_dir = str(records.resolve())
    config.progress_bar = False
    for k, v in overrides.items():
        _set(config, k, v)
    step_s = stages.measure_step_seconds(config)
    steps = max(adapt.NUM_EVALS, int(minutes * 60 * (1 - stages.EVAL_SHARE) / step_s))
    work = out / name
    print(f"{name}: {step_s:.3f} s per step -> {steps} steps in {minutes:g} min", flush=True)
    start = time.perf_counter()
    stages.train_to(config, steps, work, evals=adapt.NUM_EVALS)
    train_s = time.perf_counter() - start
    run = RunDir(work)
    curve = []
    for s in run.checkpoint_steps():
        m = run.saved_metrics(s)
        curve.append({"step": s, "minute": round(s * step_s / 60 / (1 - stages.EVAL_SHARE), 2),
                      "val_ap50": m.get("eval/ap50"),
                      "tile_ap50": m.get("eval/tile_diagnostic/ap50")})
    keep = adapt.max_detections(adapt.INSTANCES)
    figs = adapt.figures(adapt.infer_bop(work, test, out / f"{name}_test", out / "cache", keep))
    return {"arm": name, "overrides": overrides, "step_seconds": step_s, "steps": steps,
            "train_minutes": train_s / 60, "curve": curve, "test_ap50": figs["box_ap50"],
            "test_ap": figs["box_ap"],
            "test_ap50_any_part": any_part_ap50(test, *(out / f"{name}_test").glob("*.json"))}


#: The dense cell detector's arms: keyword arguments of ``train.cell_detector.train``, built
#: when called (the augmentation settings are dataclasses of the package).
DENSE_ARMS = {
    "dense": lambda: {},  # train.cell_detector as it is
    # Scales drawn from 0.5-1.5 (YOLO's) instead of 0.75-1.33: the recipe's first measurement.
    "dense_wide": lambda: {"augment": _augment(scale=(0.5, 1.5))},
}


def _augment(**kw):
    from threept_jax.data.dense_input import DenseAugment

    return DenseAugment(**kw)


def dense_arm(name: str, records: pathlib.Path, test: pathlib.Path, minutes: float,
              out: pathlib.Path, val: pathlib.Path | None, seed: int) -> dict:
    """The dense cell detector (``python -m train.cell_detector``: every part at every place of
    full images, mosaics, task-aligned assignment) trained for ``minutes``, scored by the same
    evaluator on the same test images (the network's boxes alone, as the other arms')."""
    from train import cell_detector

    work = out / f"{name}_seed{seed}"
    info = cell_detector.train(records, work, minutes=minutes, seed=seed, test=test, val=val,
                               **DENSE_ARMS[name]())
    return {"arm": f"{name} (seed {seed})", "steps": info["steps"],
            "train_minutes": info["train_minutes"],
            "curve": [{"step": c["step"], "minute": c["minutes"],
                       "val_ap50": c.get("val", {}).get("ap50")} for c in info["curve"]],
            "test_ap50": info["test"]["ap50"], "test_ap": info["test"]["ap"],
            "test_ap50_any_part": info["test"]["ap50_any_part"]}


def any_part_ap50(test: pathlib.Path, results: pathlib.Path) -> float:
    """The diagnostic box AP50 of a 2D results file with any part's box counted right (found,
    maybe misnamed)."""
    from threept_jax.eval.bop_eval import evaluate_results_file

    return evaluate_results_file(test, results, split="val_pbr", any_part=True)["bbox"]["ap50"]


def yolo_arm(python: str, records: pathlib.Path, test: pathlib.Path, minutes: float,
             out: pathlib.Path) -> dict:
    from threept_jax.eval.bop_eval import evaluate_results_file

    data = json.loads((records / "train" / "index.json").read_text())["sources"][0]["scenes"]
    val = json.loads((records / "val" / "index.json").read_text())["sources"][0]["scenes"]
    work = out / "yolo"
    subprocess.run([python, str(ROOT / "bench" / "yolo_reference.py"), "--train", data,
                    "--val", val, "--test", str(test / "val_pbr"), "--minutes", str(minutes),
                    "--out", str(work)], check=True)
    scores = evaluate_results_file(test, work / "detections.json", split="val_pbr")
    box = scores["bbox"]
    info = json.loads((work / "yolo.json").read_text())
    return {"arm": "yolov8n", "train_minutes": info["train_seconds"] / 60,
            "test_ap50": box["ap50"], "test_ap": box["ap"],
            "test_ap50_any_part": any_part_ap50(test, work / "detections.json")}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--records", type=pathlib.Path, default=ROOT / "runs/demo/adapted/records")
    p.add_argument("--test", type=pathlib.Path, default=ROOT / "runs/demo/adapted/data/test",
                   help="BOP dataset whose val_pbr images are the test images")
    p.add_argument("--minutes", type=float, default=10.0)
    p.add_argument("--arms", nargs="*", default=list(ARMS), choices=list(ARMS))
    p.add_argument("--dense", nargs="*", default=[], choices=list(DENSE_ARMS),
                   help="also train these arms of the dense cell detector (train.cell_detector)")
    p.add_argument("--seeds", type=int, nargs="+", default=[0],
                   help="the dense arms' seeds")
    p.add_argument("--val", type=pathlib.Path, default=None,
                   help="BOP dataset of held-out images for the dense arms' curves")
    p.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                   help="config overrides for every arm")
    p.add_argument("--yolo-python", default=None,
                   help="python of an environment with ultralytics (bench/yolo_reference.py)")
    p.add_argument("--out", type=pathlib.Path, default=ROOT / "runs/bench/adapt_pace")
    args = p.parse_args(argv)
    from train.stages import log_friendly_progress

    log_friendly_progress()
    extra = dict(kv.split("=", 1) for kv in args.set)
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in args.arms:
        rows.append(train_arm(name, {**ARMS[name], **extra}, args.records, args.test,
                              args.minutes, args.out))
        (args.out / "results.json").write_text(json.dumps(rows, indent=1))
    for name in args.dense:
        for seed in args.seeds:
            rows.append(dense_arm(name, args.records, args.test, args.minutes, args.out, args.val,
                                  seed))
        (args.out / "results.json").write_text(json.dumps(rows, indent=1))
    if args.yolo_python:
        rows.append(yolo_arm(args.yolo_python, args.records, args.test, args.minutes, args.out))
        (args.out / "results.json").write_text(json.dumps(rows, indent=1))
    ref = rows[0]["test_ap50"]
    print(f"\n{args.minutes:g} CPU minutes each, test images of {args.test}:")
    print("| arm | steps | train min | val AP50 by eval | test box AP50 / AP | AP50 / first | "
          "diagnostic: AP50 with any part |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        curve = " / ".join(f"{c['val_ap50']:.3f}" for c in r.get("curve", [])
                           if c["val_ap50"] is not None)
        ratio = r["test_ap50"] / ref if ref > 0 else float("nan")
        print(f"| {r['arm']} | {r.get('steps', '')} | {r['train_minutes']:.1f} | {curve} | "
              f"{r['test_ap50']:.3f} / {r['test_ap']:.3f} | {ratio:.2f} | "
              f"{r['test_ap50_any_part']:.3f} |")


if __name__ == "__main__":
    main()
