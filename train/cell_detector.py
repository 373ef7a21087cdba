"""Train the dense cell detector on a cell's records (issue 38), to a deadline or a step count.

    python -m train.cell_detector --records runs/demo/adapted/records --workdir W --minutes 10 \\
        [--val runs/demo/adapted/data/val] [--test runs/demo/adapted/data/test] [--seed 0]

The cell's parts are the records' objects (``objects.json``); the network
(:class:`threept_jax.models.dense.DenseDetector`) learns them from full images
(:mod:`threept_jax.data.dense_input`: mosaics, scales, flips, colour) with the task-aligned
loss (:mod:`threept_jax.losses.dense`), AdamW with a warm-up and a cosine decay to the planned
last step, and an exponential moving average of the weights, which is what is evaluated and
saved. A deadline (``--minutes``) plans the steps from the measured step time. Writes the
run directory of :mod:`threept_jax.data.dense_run` (the averaged weights, the run file with
the held-out curve and test figures, snapshots, the training log ``metrics.jsonl``); the train
state is saved every :data:`SAVE_EVERY` steps and on SIGTERM (which stops the run), and the
same command resumes it where it stood, with the same batches.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import pathlib
import queue
import signal
import threading
import time
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx

from threept_jax.data import dense_input, dense_run
from threept_jax.losses.dense import dense_loss
from threept_jax.models.dense import DenseConfig, DenseDetector, anchor_points
from threept_jax.pipeline.dense import ImageBoxes

#: Most instances an example keeps (a mosaic of four cell images holds up to ~40).
MAX_INSTANCES = 48


def load_cell(records: pathlib.Path, split: str, canvas_hw) -> dense_input.CellImages:
    import grain

    from threept_jax.data.detector_input import DecodeExample, find_shards

    table = json.loads((records / "objects.json").read_text())
    source = grain.sources.ArrayRecordDataSource(find_shards(records, split))
    ds = grain.MapDataset.source(source).map(DecodeExample())
    return dense_input.CellImages([ds[i] for i in range(len(ds))], sorted(map(int, table)),
                                  canvas_hw)


class TrainState(NamedTuple):
    """What a step updates and a checkpoint saves: the network's ``params`` and
    ``batch_stats``, the optimizer's state, and the moving average (``ema``: params and batch
    statistics) that is evaluated and shipped."""

    params: nnx.State
    batch_stats: nnx.State
    opt_state: optax.OptState
    ema: tuple[nnx.State, nnx.State]


@functools.lru_cache(maxsize=4)
def make_optimizer(lr: float) -> optax.GradientTransformation:
    """AdamW (YOLOv8's momentum and weight decay) after clipping; the learning rate is injected
    each step (:func:`learning_rate`), so the plan can change without a new compiled step."""
    return optax.chain(optax.clip_by_global_norm(10.0),
                       optax.inject_hyperparams(optax.adamw)(learning_rate=lr, b1=0.937,
                                                             weight_decay=5e-4))


def learning_rate(step: int, total: int, peak: float) -> float:
    """Linear warm-up over the first tenth of the steps (at most 100), then a cosine decay to
    5 % of the peak at ``total``."""
    warmup = min(100, max(1, total // 10))
    if step < warmup:
        return peak * (step + 1) / warmup
    t = min(1.0, (step - warmup) / max(1, total - warmup))
    return peak * (0.05 + 0.95 * 0.5 * (1 + np.cos(np.pi * t)))


def ema_decay(step: int) -> float:
    """The moving average's decay, ramped from 0 (YOLOv5's ``ModelEMA``, a 200-step ramp for
    runs of a few thousand steps)."""
    return 0.9999 * (1 - np.exp(-(step + 1) / 200.0))


@functools.lru_cache(maxsize=4)
def make_step(graphdef: nnx.GraphDef, tx: optax.GradientTransformation):
    """The jitted train step ``(state, lr, decay, batch) -> (state, metrics)``, one per network
    structure and optimizer (runs in one process share it: a resumed run does not compile
    again)."""

    @functools.partial(jax.jit, donate_argnums=0)
    def step(state: TrainState, lr, decay, batch):
        model = nnx.merge(graphdef, state.params, state.batch_stats)
        centres = jnp.asarray(anchor_points(model.cfg.image_size)[0])

        def loss_fn(model):
            out = model(batch["image"].astype(jnp.float32) / 255.0)
            return dense_loss(out["logits"], out["boxes"], centres, batch["boxes"],
                              batch["classes"], batch["valid"])

        # nnx.value_and_grad differentiates the Params and carries the BatchNorm statistics'
        # updates out into ``model``.
        (loss, metrics), grads = nnx.value_and_grad(loss_fn, has_aux=True)(model)
        _, _, stats = nnx.split(model, nnx.Param, nnx.BatchStat)
        opt_state = state.opt_state
        opt_state[1].hyperparams["learning_rate"] = lr
        updates, opt_state = tx.update(grads, opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        ema = jax.tree.map(lambda e, p: decay * e + (1 - decay) * p, state.ema, (params, stats))
        metrics = dict(metrics, loss=loss, grad_norm=optax.tree.norm(grads), lr=lr)
        return TrainState(params, stats, opt_state, ema), metrics

    return step


def evaluate(boxes: ImageBoxes, class_ids: Sequence[int], dataset: pathlib.Path,
             out_json: pathlib.Path, split: str = "val_pbr") -> dict:
    """Box AP50 / AP of the network alone on a BOP dataset's images (every part queried, full
    images, every detection kept), scored by the project's evaluator; the detections are
    written as a BOP 2D results file. Also the diagnostic AP50 with any part's box counted
    right (found, maybe misnamed)."""
    import cv2

    from threept_jax.eval.bop_eval import evaluate_results_file

    results = []
    folder = dataset / split
    for scene in sorted(p for p in folder.iterdir() if p.is_dir() and p.name.isdigit()):
        for path in sorted((scene / "rgb").iterdir()):
            image = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)
            t0 = time.perf_counter()
            b, sc, cl = boxes(image)
            dt = time.perf_counter() - t0
            results += [{"scene_id": int(scene.name), "image_id": int(path.stem),
                         "category_id": int(class_ids[c]), "score": float(x),
                         "bbox": [float(x0), float(y0), float(x1 - x0), float(y1 - y0)],
                         "time": dt} for (x0, y0, x1, y1), x, c in zip(b, sc, cl)]
    out_json.write_text(json.dumps(results))
    box = evaluate_results_file(dataset, out_json, split=split)["bbox"]
    any_part = evaluate_results_file(dataset, out_json, split=split, any_part=True)["bbox"]
    return {"ap50": box["ap50"], "ap": box["ap"], "ap50_any_part": any_part["ap50"]}


def _prefetch(it, depth: int = 2):
    """Batches made by a background thread while the step runs; an error making one is
    raised here."""
    q: queue.Queue = queue.Queue(depth)

    def work():
        try:
            for x in it:
                q.put(x)
        except BaseException as e:  # handed to the training loop
            q.put(e)

    threading.Thread(target=work, daemon=True).start()
    while True:
        x = q.get()
        if isinstance(x, BaseException):
            raise x
        yield x


#: Train-state saves for resuming, every this many steps (about 2 minutes on 2 CPU cores).
SAVE_EVERY = 100


def train(records: pathlib.Path, workdir: pathlib.Path, *, minutes: float | None = None,
          steps: int | None = None, batch_size: int = 16, seed: int = 0, lr: float = 2e-3,
          test: pathlib.Path | None = None, val: pathlib.Path | None = None,
          snapshots: int = 4, augment: dense_input.DenseAugment | None = None,
          **cfg_overrides) -> dict:
    """Train to ``minutes`` of training (the steps planned from the measured step time) or to
    ``steps``, resuming the run ``workdir`` holds; then the held-out figures: box AP50 at each
    of ``snapshots`` points of the run on ``val`` (the curve) and at the end on ``test`` (BOP
    datasets whose ``val_pbr`` images are held out). Returns the run file's contents."""
    from tqdm import tqdm

    if (minutes is None) == (steps is None):
        raise ValueError("give one of minutes (a deadline) or steps")
    workdir.mkdir(parents=True, exist_ok=True)
    probe = DenseConfig(num_classes=1, **cfg_overrides)
    cell = load_cell(records, "train", probe.image_size)
    cfg = dataclasses.replace(probe, num_classes=len(cell.class_ids))
    # Initialised in one compiled program, not one per parameter.
    model = nnx.jit(lambda: DenseDetector(cfg, rngs=nnx.Rngs(seed)))()
    model.train()
    graphdef, params, stats = nnx.split(model, nnx.Param, nnx.BatchStat)
    tx = make_optimizer(lr)
    state = jax.jit(lambda p, s: TrainState(p, s, tx.init(p), (p, s)))(params, stats)
    augment = augment or dense_input.DenseAugment()
    settings = {"config": dense_run.config_to_json(cfg), "class_ids": cell.class_ids,
                "seed": seed, "batch_size": batch_size, "learning_rate": lr,
                "augment": json.loads(json.dumps(dataclasses.asdict(augment)))}
    n, total, spent, marks = 0, steps or 10**9, 0.0, []
    resumed = dense_run.load_state(workdir, state)
    if resumed is not None:
        state, progress = resumed
        differ = [k for k in settings if progress["settings"].get(k) != settings[k]]
        if differ:
            raise ValueError(f"{workdir} holds a run with other {', '.join(differ)}: "
                             f"{ {k: progress['settings'].get(k) for k in differ} }; resume it "
                             "with its settings, or train into a new --workdir")
        n, total, spent, marks = (progress["step"], progress["total"], progress["seconds"],
                                  progress["marks"])
        run_file = workdir / dense_run.RUN_FILE
        if n >= total and run_file.is_file() and "curve" in json.loads(run_file.read_text()):
            print(f"{workdir}: trained ({n} steps), found done", flush=True)
            return json.loads(run_file.read_text())
        print(f"resuming {workdir} at step {n} of {total}", flush=True)
    step_fn = make_step(graphdef, tx)
    batches = _prefetch(dense_input.training_batches(
        cell, batch_size, seed, augment, MAX_INSTANCES, start=n))
    stop = threading.Event()
    previous = signal.signal(signal.SIGTERM, lambda *_: stop.set())

    def save_progress():
        dense_run.save_state(workdir, state, {
            "step": n, "total": total, "seconds": spent + time.perf_counter() - start,
            "marks": marks, "settings": settings})

    log = (workdir / "metrics.jsonl").open("a")
    start = time.perf_counter()
    first, t_first = n, None
    bar = tqdm(total=total if total < 10**9 else None, initial=n, desc="cell detector",
               unit="step")
    try:
        while n < total and not stop.is_set():
            batch = next(batches)
            state, metrics = step_fn(state, jnp.float32(learning_rate(n, total, lr)),
                                     jnp.float32(ema_decay(n)), batch)
            n += 1
            bar.update(1)
            if n == first + 1:
                jax.block_until_ready(metrics)
                t_first = time.perf_counter()
            if not marks and (n == first + 21 or steps is not None):
                jax.block_until_ready(metrics)
                if minutes is not None:  # the plan, from the measured step time
                    per_step = (time.perf_counter() - t_first) / (n - first - 1)
                    left = minutes * 60 - spent - (time.perf_counter() - start)
                    total = max(n, n + int(left * 0.95 / per_step))
                    bar.total = total
                marks = sorted({max(1, round(total * k / snapshots))
                                for k in range(1, snapshots)})
            if n in marks:
                dense_run.save_snapshot(workdir, n, *state.ema)
            if n % 50 == 0 or n == total:
                m = {k: float(v) for k, v in jax.device_get(metrics).items()}
                m.update(step=n, seconds=round(spent + time.perf_counter() - start, 1))
                log.write(json.dumps(m) + "\n")
                log.flush()
                bar.set_postfix(loss=f"{m['loss']:.3f}", giou=f"{m['assign/giou']:.2f}")
            if n % SAVE_EVERY == 0:
                save_progress()
    finally:
        signal.signal(signal.SIGTERM, previous)
        bar.close()
        log.close()
    save_progress()
    train_s = spent + time.perf_counter() - start
    dense_run.save_snapshot(workdir, n, *state.ema)
    info = {"steps": n, "planned_steps": total, "train_minutes": round(train_s / 60, 2),
            "stopped": stop.is_set(), "records": str(records.resolve()), **settings}
    del info["config"], info["class_ids"]
    dense_run.save(workdir, cfg, cell.class_ids, *state.ema, info)
    curve = []
    for s_n, p, b in dense_run.snapshots(workdir, cfg):
        point = {"step": s_n, "minutes": round(train_s / 60 * s_n / max(n, 1), 2)}
        if val is not None:
            point["val"] = evaluate(ImageBoxes(dense_run.network(cfg, p, b)), cell.class_ids, val,
                                    workdir / f"val_{s_n}.json")
        curve.append(point)
    info["curve"] = curve
    if test is not None:
        info["test"] = evaluate(ImageBoxes(dense_run.network(cfg, *state.ema)), cell.class_ids, test,
                                workdir / "test_detections.json")
    dense_run.save_info(workdir, info)
    return info


def main(argv: Sequence[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--records", type=pathlib.Path, required=True,
                   help="the cell's records (datagen.pack; train/ and objects.json)")
    p.add_argument("--workdir", type=pathlib.Path, required=True)
    budget = p.add_mutually_exclusive_group(required=True)
    budget.add_argument("--minutes", type=float, help="training minutes (steps planned from "
                        "the measured step time)")
    budget.add_argument("--steps", type=int)
    p.add_argument("--val", type=pathlib.Path, default=None,
                   help="BOP dataset of held-out images (val_pbr) for the curve")
    p.add_argument("--test", type=pathlib.Path, default=None,
                   help="BOP dataset of held-out images (val_pbr) scored at the end")
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--lr", type=float, default=2e-3)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    info = train(args.records, args.workdir, minutes=args.minutes, steps=args.steps,
                 batch_size=args.batch, seed=args.seed, lr=args.lr, test=args.test, val=args.val)
    for point in info["curve"]:
        if "val" in point:
            print(f"step {point['step']} ({point['minutes']:.1f} min): val box AP50 "
                  f"{point['val']['ap50']:.3f}", flush=True)
    if "test" in info:
        t = info["test"]
        print(f"test box AP50 {t['ap50']:.3f}, AP {t['ap']:.3f} (any part: "
              f"{t['ap50_any_part']:.3f})", flush=True)
    return info


if __name__ == "__main__":
    main()
