"""The campaign's detector trained on a lent GPU machine (docs/training.md: the H100 run).

The campaign (``python -m train.campaign``) makes its data on this machine (Mitsuba, 2 cores,
about an hour) and trains where it made it. A lent GPU machine has no Mitsuba, no network and
takes at most 64 MiB of files per call, for minutes. So the training data travels as a subset
of the campaign's records re-encoded as JPEG, and the GPU machine renders the banks itself (the
JAX rasterizer, from the carried meshes) and trains the ``cpu`` config with a larger batch for
the minutes it is given:

    # here, after the campaign's data stage
    python scripts/gpu_detector.py subset --records runs/campaign/records --out .gpu/records \\
        --images 1000 --quality 75
    # on the GPU machine (its own jax), with the wheels of the missing packages installed
    python scripts/gpu_detector.py train --records .gpu/records --workdir /tmp/w \\
        --minutes 6 --batch-size 64 --workers 12
    # here: python bench/model_card.py --campaign runs/campaign --detector RUN
"""

from __future__ import annotations

import argparse
import json
import pathlib
import shutil
import time

import numpy as np


def subset(records: pathlib.Path, out: pathlib.Path, images: int, val_images: int,
           quality: int) -> None:
    """``images`` training and ``val_images`` held-out records of ``records`` (evenly spaced,
    so every layout keeps its share), re-encoded as JPEG, with the object table, the cell
    description and the meshes they use (no banks: ``datagen.banks`` renders them)."""
    from array_record.python.array_record_data_source import ArrayRecordDataSource
    from array_record.python.array_record_module import ArrayRecordWriter

    from threept_jax.data.detector_input import find_shards
    from threept_jax.data.records import FORMAT_VERSION, decode_example, encode_example

    table = json.loads((records / "objects.json").read_text())
    used: set[int] = set()
    for split, count in (("train", images), ("val", val_images)):
        source = ArrayRecordDataSource(find_shards(records, split))
        total = len(source)
        picks = np.unique(np.linspace(0, total - 1, min(count, total)).round().astype(int))
        folder = out / split
        folder.mkdir(parents=True, exist_ok=True)
        name = "shard-00000-of-00001.array_record"
        writer = ArrayRecordWriter(str(folder / name), "group_size:1")
        for i in picks:
            example = decode_example(source[int(i)])
            used.update(int(o) for o in example["obj_id"])
            writer.write(encode_example(example, "jpg", quality))
        writer.close()
        source_index = records / split / "index.json"
        index = json.loads(source_index.read_text()) if source_index.exists() else {}
        index.update(format_version=FORMAT_VERSION, num_records=len(picks),
                     shards={name: len(picks)}, image_format="jpg",
                     subset_of=str(records / split), subset_records=picks.tolist())
        (folder / "index.json").write_text(json.dumps(index, indent=1, sort_keys=True))
    kept = {k: v for k, v in table.items() if int(k) in used}
    (out / "objects.json").write_text(json.dumps(kept, indent=1, sort_keys=True))
    if (records / "cell.json").exists():
        shutil.copy2(records / "cell.json", out / "cell.json")
    for entry in kept.values():
        if "mesh" in entry:
            (out / entry["mesh"]).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(records / entry["mesh"], out / entry["mesh"])
    print(f"{out}: {images} + {val_images} images, {len(kept)} objects", flush=True)


def train(records: pathlib.Path, workdir: pathlib.Path, minutes: float, batch_size: int,
          workers: int, learning_rate: float) -> None:
    """The ``cpu`` detector config on ``records`` for ``minutes`` of steps at ``batch_size``
    (steps from the warm step time measured here; no held-out evaluation on this machine: the
    model card's figures are measured afterwards on full images)."""
    import jax

    from train import stages
    from train.configs.detector import get_config
    from train.trainers import trainer_class

    print(f"devices: {jax.devices()}", flush=True)
    config = get_config("cpu")
    config.data_dir = str(records.resolve())
    config.batch_size = batch_size
    config.data.num_workers = workers
    config.optim.learning_rate = learning_rate
    config.optim.warmup_steps = 500
    config.eval.every_steps = 0
    config.progress_bar = False
    start = time.perf_counter()
    step_s = stages.measure_step_seconds(config)
    steps = int(minutes * 60 / step_s)
    print(f"{step_s * 1e3:.1f} ms per step of batch {batch_size} (measured in "
          f"{time.perf_counter() - start:.0f} s): {steps} steps in {minutes:g} minutes",
          flush=True)
    config.total_steps = steps
    config.checkpoint.every_steps = max(1, steps // 4)
    config.log_every = max(1, steps // 40)
    start = time.perf_counter()
    summary = trainer_class(config)(config, workdir).run()
    print(f"trained {steps} steps in {time.perf_counter() - start:.0f} s: {summary['train']}",
          flush=True)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(prog="python scripts/gpu_detector.py",
                                description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    s = sub.add_parser("subset", help="JPEG subset of a campaign's records (here)")
    s.add_argument("--records", type=pathlib.Path, required=True)
    s.add_argument("--out", type=pathlib.Path, required=True)
    s.add_argument("--images", type=int, default=800)
    s.add_argument("--val-images", type=int, default=8)
    s.add_argument("--quality", type=int, default=75, help="JPEG quality")
    t = sub.add_parser("train", help="train the cpu config for --minutes (the GPU machine)")
    t.add_argument("--records", type=pathlib.Path, required=True)
    t.add_argument("--workdir", type=pathlib.Path, required=True)
    t.add_argument("--minutes", type=float, required=True)
    t.add_argument("--batch-size", type=int, default=64)
    t.add_argument("--workers", type=int, default=12, help="grain data workers")
    t.add_argument("--learning-rate", type=float, default=1e-3)
    args = p.parse_args(argv)
    if args.command == "subset":
        subset(args.records, args.out, args.images, args.val_images, args.quality)
    else:
        train(args.records, args.workdir, args.minutes, args.batch_size, args.workers,
              args.learning_rate)


if __name__ == "__main__":
    main()
