"""Train the templates detector's verifier: a small network that looks inside the outline.

The training-free detector (``--detector templates``, :mod:`infer.shape_detect`) ranks its
verified candidates by a logistic model of eight outline features; on the demo's cells that
score, not the search, is what limits box AP (docs/benchmarks.md, "Training-free detection"):
the outline of a plate fits a checker square, a washer's fits a disc. The verifier
(:class:`threept_jax.models.verifier.CandidateVerifier`) reads the image around each candidate
beside the part rendered at its pose (silhouette, geometric edges, shading) with the eight
features, and adds a correction to the logistic model's log-odds.

What it learns from: cells of **other** parts, never the parts it is evaluated on
(the demo's cells are procedural seeds 7 and 8, the T-LESS/ITODD evaluation cell seed 11):

* procedural cells (``procedural:5``, seeds :data:`SEEDS`, each its five parts, path-traced
  as ``train.adapt`` makes a cell's training scenes), every part queried in every image;
* one cell of the IC-BIN, TU Dresden Light and YCB-Video meshes of ``../shared/meshes``
  (:data:`BOP_MESHES`, seed :data:`BOP_SEED`), each image queried with its parts.

A candidate is right when its outline box overlaps a ground-truth box of its part by IoU >=
0.5 (what the score estimates). The cells :data:`VAL_SEEDS` are held out of the fit: the
epoch with the lowest log-loss on them is kept. Materials are random in every scene, so the
crops are standardised and augmented (turns by 90 degrees, flips, colour channels shuffled,
grey) and only shape can be learned.

Every stage resumes: scenes already made and cells already collected
(``WORKDIR/candidates/*.npz``) are kept, and the training state is saved after each epoch and
on SIGTERM, then resumed. The best weights are written to ``--out`` (default
``models/templates-verifier``, what ``ShapeSearchDetector(verifier="shipped")`` loads) with
``SOURCE.json`` (their SHA256 and the run's figures). The shipped weights: 109,844 candidates
of 53 cells (19,321 right), held-out cells' log-loss 0.323 -> 0.277, 10 minutes of training
on 2 cores after about 1.5 hours of scenes and search. The verifier is not the detector's
default: on five held-out sets it raises the mean box AP50 from 0.444 to 0.474 but lowers one.
Trained on 130 cells (:data:`SEEDS` to 184, ``--epochs 3``: 230,144 candidates) it fitted the
held-out cells better (0.254) and boxed no better (mean 0.468), so the 53 stay
(docs/benchmarks.md, "A learned verifier inside the outline", "Renders of 1024 faces").

    python -m train.templates_verifier [--workdir runs/templates_verifier] [--epochs 4]
        [--out models/templates-verifier]
"""

from __future__ import annotations

import argparse
import pathlib
import signal
import sys
import time
from collections.abc import Sequence

import numpy as np

#: Procedural cells (seed, images); the demo's are 7 and 8, the shared score's 3-5.
SEEDS = (tuple((s, 16) for s in range(30, 47)) + ((54, 8), (56, 8), (58, 8))
         + tuple((s, 8) for s in range(74, 108)))
#: Cells held out of the fit: the epoch kept is the one with the lowest log-loss on them.
VAL_SEEDS = (44, 45)
#: The BOP cell's meshes (``../shared/meshes/bop``), its seed and scenes.
BOP_MESHES = ("icbin", "tudl", "ycbv")
BOP_SEED = 40
BOP_SCENES = 24
SHARED = pathlib.Path(__file__).resolve().parents[2] / "shared" / "meshes" / "bop"
#: Candidates per step.
BATCH = 128


def make_cell(workdir: pathlib.Path, name: str) -> tuple[pathlib.Path, str, bool]:
    """The BOP dataset of the cell ``name`` (``s{seed}`` or ``bop{BOP_SEED}``), generated when
    missing (path-traced: a minute or two on 2 cores), its split and whether each image is
    queried with its own parts."""
    from datagen import generate as G
    from train import adapt

    folder = workdir / "cells" / name
    if name.startswith("s"):
        seed = int(name[1:])
        images = dict(SEEDS)[seed]
        split = folder / "data" / "train" / "train_pbr"
        if not split.is_dir() or len(list(split.iterdir())) < images:
            args = adapt.parse_args(["--meshes", "procedural:5", "--seed", str(seed),
                                     "--workdir", str(folder), "--train-scenes", str(images),
                                     "--from", "scratch"])
            adapt.generate(args, folder / "data", sets=("train",))
        return folder / "data" / "train", "train_pbr", False
    if not (folder / "val_pbr").is_dir():
        meshes = [SHARED / m / "models" for m in BOP_MESHES]
        for m in meshes:
            if not m.is_dir():
                sys.exit(f"{m} not found: the BOP meshes of ../shared are needed")
        G.main(["--out", str(folder), "--num-scenes", str(BOP_SCENES), "--layout", "cell",
                "--seed", str(BOP_SEED), "--instances", "8", "--distinct", "5", "8",
                "--meshes", *map(str, meshes), "--resolution", "640", "480", "--spp", "8",
                "--split", "val", "--val-fraction", "0", "--quiet"])
    return folder, "val_pbr", True


#: Every cell's name.
CELLS = tuple(f"s{s}" for s, _ in SEEDS) + (f"bop{BOP_SEED}",)


def collect(data: pathlib.Path, split_name: str, per_image: bool, cache: pathlib.Path,
            out: pathlib.Path) -> None:
    """Every verified candidate of the dataset's images (no verifier: the logistic score's
    candidates) with what the verifier reads, written to ``out`` (npz: ``features``,
    ``right``, ``parts``, ``crops``, ``renders``)."""
    from infer.shape_detect import raster_meshes
    from threept_jax.data.files import atomic_savez
    from threept_jax.pipeline.shape_search import verifier_inputs
    from train.cell_score import searched_images

    rasters, acc = {}, {k: [] for k in ("features", "right", "parts", "crops", "renders")}
    for det, image, K, c, parts, right in searched_images(data, split_name, per_image, cache,
                                                          out.stem):
        key = tuple(o.obj_id for o in det.objects)
        if key not in rasters:
            rasters[key] = raster_meshes(det.objects)
        crops, renders = verifier_inputs(image, K, c.poses, c.obj, c.xyxy, rasters[key])
        acc["features"].append(c.features)
        acc["right"].append(right)
        acc["parts"].append(parts)
        acc["crops"].append(crops)
        acc["renders"].append(renders)
    if not acc["right"]:
        raise SystemExit(f"{data}: no image gave a candidate; delete the folder to make it "
                         f"again")
    atomic_savez(out, **{k: np.concatenate(v) for k, v in acc.items()})


def augment(rng: np.random.Generator, crops: np.ndarray, renders: np.ndarray):
    """The same turn by 90 degrees and flip of crops and renders [B, S, S, 3], the crops'
    colour channels shuffled and, one time in three, grey."""
    k = int(rng.integers(4))
    crops, renders = np.rot90(crops, k, (1, 2)), np.rot90(renders, k, (1, 2))
    if rng.random() < 0.5:
        crops, renders = crops[:, :, ::-1], renders[:, :, ::-1]
    crops = crops[..., rng.permutation(3)]
    if rng.random() < 0.3:
        crops = np.repeat(crops.mean(-1, keepdims=True), 3, -1).astype(np.uint8)
    return np.ascontiguousarray(crops), np.ascontiguousarray(renders)


def load(paths: Sequence[pathlib.Path]) -> dict[str, np.ndarray]:
    parts = [dict(np.load(p)) for p in paths]
    return {k: np.concatenate([d[k] for d in parts]) for k in parts[0]}


def train(workdir: pathlib.Path, train_files: Sequence[pathlib.Path],
          val_files: Sequence[pathlib.Path], epochs: int, seed: int = 0, lr: float = 1e-3,
          weight_decay: float = 1e-3, batch: int = BATCH):
    """The verifier fitted on the candidates of ``train_files``, the epoch with the lowest
    log-loss on ``val_files`` kept; resumes the state ``workdir/state`` holds. Returns the
    best module and the figures."""
    import jax
    import jax.numpy as jnp
    import optax
    from flax import nnx
    from tqdm import tqdm

    from threept_jax.data import dense_run
    from threept_jax.models.verifier import CandidateVerifier
    from threept_jax.pipeline.shape_search import score_inputs, score_logit

    tr, va = load(train_files), load(val_files)

    def inputs(d):
        return (score_inputs(d["features"]).astype(np.float32),
                score_logit(d["features"]).astype(np.float32))

    x_tr, base_tr = inputs(tr)
    x_va, base_va = inputs(va)
    model = CandidateVerifier(rngs=nnx.Rngs(seed))
    model.mean[...] = jnp.asarray(x_tr.mean(0))
    model.std[...] = jnp.asarray(x_tr.std(0) + 1e-6)
    graphdef, params, rest = nnx.split(model, nnx.Param, ...)
    per_epoch = len(x_tr) // batch
    tx = optax.adamw(optax.warmup_cosine_decay_schedule(
        0.0, lr, min(200, epochs * per_epoch // 4), epochs * per_epoch), weight_decay=weight_decay)
    state = {"params": params, "opt": tx.init(params), "best": params}
    progress = {"epoch": 0, "step": 0, "best_loss": None, "best_epoch": None, "losses": []}
    resumed = dense_run.load_state(workdir, state)
    if resumed is not None:
        state, progress = resumed
        print(f"resuming {workdir} at epoch {progress['epoch']} step {progress['step']}",
              flush=True)

    @jax.jit
    def step(params, opt, crops, renders, x, base, y, key):
        def loss_fn(p):
            z = base + nnx.merge(graphdef, p, rest)(crops, renders, x, dropout=key)
            return optax.sigmoid_binary_cross_entropy(z, y).mean()

        loss, g = jax.value_and_grad(loss_fn)(params)
        updates, opt = tx.update(g, opt, params)
        return optax.apply_updates(params, updates), opt, loss

    @jax.jit
    def logits(params, crops, renders, x, base):
        return base + nnx.merge(graphdef, params, rest)(crops, renders, x)

    def log_loss(params, d, x, base):
        z = np.concatenate([np.asarray(logits(params, d["crops"][i:i + 512],
                                              d["renders"][i:i + 512], x[i:i + 512],
                                              base[i:i + 512]))
                            for i in range(0, len(x), 512)])
        y = d["right"].astype(np.float64)
        return float(np.mean(np.logaddexp(0.0, z) - y * z))

    base_loss = float(np.mean(np.logaddexp(0.0, base_va) - va["right"] * base_va))
    stop = []
    previous = signal.signal(signal.SIGTERM, lambda *_: stop.append(True))
    key = jax.random.key(seed)
    try:
        while progress["epoch"] < epochs and not stop:
            e = progress["epoch"]
            order = np.random.default_rng((seed, e)).permutation(len(x_tr))
            bar = tqdm(total=per_epoch, initial=progress["step"], desc=f"epoch {e + 1}/{epochs}",
                       unit="step")
            losses = []
            while progress["step"] < per_epoch and not stop:
                i = progress["step"]
                b = order[i * batch:(i + 1) * batch]
                crops, renders = augment(np.random.default_rng((seed, e, i)), tr["crops"][b],
                                         tr["renders"][b])
                state["params"], state["opt"], loss = step(
                    state["params"], state["opt"], crops, renders, x_tr[b], base_tr[b],
                    tr["right"][b].astype(np.float32),
                    jax.random.fold_in(key, e * per_epoch + i))
                losses.append(float(loss))
                progress["step"] += 1
                bar.update(1)
                if len(losses) % 20 == 0:
                    bar.set_postfix(loss=f"{np.mean(losses[-20:]):.4f}")
            bar.close()
            if progress["step"] == per_epoch:
                val = log_loss(state["params"], va, x_va, base_va)
                progress["losses"].append({"epoch": e + 1, "train": float(np.mean(losses)),
                                           "val": val})
                print(f"epoch {e + 1}: train log-loss {np.mean(losses):.4f}, held-out cells "
                      f"{val:.4f} (the logistic score alone: {base_loss:.4f})", flush=True)
                if progress["best_loss"] is None or val < progress["best_loss"]:
                    progress["best_loss"], progress["best_epoch"] = val, e + 1
                    state["best"] = state["params"]
                progress["epoch"], progress["step"] = e + 1, 0
            dense_run.save_state(workdir, state, progress)
    finally:
        signal.signal(signal.SIGTERM, previous)
    best = nnx.merge(graphdef, state["best"], rest)
    figures = {"train_candidates": int(len(x_tr)), "train_right": int(tr["right"].sum()),
               "val_candidates": int(len(x_va)), "val_right": int(va["right"].sum()),
               "val_log_loss_logistic": base_loss, "val_log_loss": progress["best_loss"],
               "best_epoch": progress["best_epoch"], "epochs": progress["losses"],
               "stopped": bool(stop)}
    return best, figures


def export(model, figures: dict, out: pathlib.Path, command: str) -> None:
    """The weights (``verifier.npz``) and ``SOURCE.json`` (their SHA256, the run's figures)
    that :func:`threept_jax.data.pretrained.load_verifier` reads. A ``MODEL_CARD.md`` in
    ``out`` is kept: it is written by hand, so its figures are to be measured again."""
    from threept_jax.data.files import atomic_savez, atomic_write_json
    from threept_jax.data.pretrained import module_arrays
    from threept_jax.data.run_dir import sha256

    out.mkdir(parents=True, exist_ok=True)
    arrays = module_arrays(model)
    atomic_savez(out / "verifier.npz", **arrays)
    atomic_write_json(out / "SOURCE.json", {
        "arrays": "verifier.npz", "arrays_sha256": sha256(out / "verifier.npz"),
        "parameters": int(sum(a.size for a in arrays.values())),
        "trained_by": command, **figures}, indent=1)


def main(argv: Sequence[str] | None = None) -> dict:
    from infer.api import DEFAULT_CACHE
    from threept_jax.data.pretrained import VERIFIER_DIR

    p = argparse.ArgumentParser(prog="python -m train.templates_verifier",
                                description=__doc__.split("\n")[0])
    p.add_argument("--workdir", type=pathlib.Path,
                   default=pathlib.Path("runs/templates_verifier"))
    p.add_argument("--out", type=pathlib.Path, default=VERIFIER_DIR,
                   help="where the weights go (default: the shipped folder the detector loads)")
    p.add_argument("--epochs", type=int, default=4)
    p.add_argument("--cache-dir", type=pathlib.Path, default=DEFAULT_CACHE)
    args = p.parse_args(argv)
    if args.epochs < 1:
        p.error("--epochs must be at least 1")
    start = time.time()
    files = []
    for name in CELLS:
        out = args.workdir / "candidates" / f"{name}.npz"
        if not out.is_file():
            print(f"cell {name}: scenes and candidates -> {out}", flush=True)
            out.parent.mkdir(parents=True, exist_ok=True)
            collect(*make_cell(args.workdir, name), args.cache_dir / "contours", out)
        files.append(out)
    files = sorted(files)  # by name: the order the fit reads them in
    val = [f for f in files if f.stem in {f"s{s}" for s in VAL_SEEDS}]
    model, figures = train(args.workdir / "state", [f for f in files if f not in val], val,
                           args.epochs)
    figures["minutes"] = round((time.time() - start) / 60, 1)
    if figures["stopped"]:
        print(f"stopped: run the same command to resume ({args.workdir})")
        return figures
    export(model, figures, args.out, "python -m train.templates_verifier " + " ".join(
        argv if argv is not None else sys.argv[1:]))
    print(f"held-out cells' log-loss {figures['val_log_loss']:.4f} (the logistic score alone "
          f"{figures['val_log_loss_logistic']:.4f}); wrote {args.out}", flush=True)
    return figures


if __name__ == "__main__":
    main()
