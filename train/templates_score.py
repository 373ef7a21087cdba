"""Fit the templates detector's score: a logistic model of whether a verified candidate is right.

The training-free detector (``--detector templates``, :mod:`infer.shape_detect`) verifies a few
hundred candidate poses per image; which of them are parts and which are clutter fitted by a
part's outline decides its precision. The contour score alone ranks them poorly: a plate seen
edge-on or a pin is two straight lines that fit the tray's rim and any stripe as well as a part
(docs/benchmarks.md, "Training-free detection"). This script fits
:data:`threept_jax.pipeline.shape_search.SCORE_WEIGHTS`, a weight for each of the candidates'
eight :data:`~threept_jax.pipeline.shape_search.FEATURES` (the contour and template scores, the
outline's LINE-2D similarity, its valid lines, its thinness, elongation and size in the image,
the clutter in its box) and a bias, on cell scenes of parts that no evaluation uses:

* three cells of five procedural parts (``procedural:5``, seeds 3, 4 and 5; the demo's are 7
  and 8), every part queried in every image;
* one cell of T-LESS and ITODD meshes (``../shared/meshes``, seed 21; the evaluation's is 11),
  each image queried with the parts it shows.

A candidate is right when its outline box overlaps a ground-truth box of its part by IoU >= 0.5.
Scenes are generated when missing (path-traced, a few minutes on 2 cores); the weights are
printed as the line to put in ``shape_search.py`` and written with the data's figures to
``--out``. No network is trained: the detector stays training-free, as a detector's score
threshold is tuned on held-out data.

``--cell DATA`` calibrates for one cell instead: a logistic model **per part**, fitted on the
images of a BOP dataset of the cell's own parts with ground truth (``train.adapt`` writes one,
``WORKDIR/data/train``: synthetic scenes, never the images evaluated), every part queried in
every image. What a right candidate looks like differs from part to part (a plate's outline
is as elongated as a checker square seen obliquely, a gear's is round), which one shared model
cannot say; a part with fewer than ten right candidates keeps the shared weights. The file
``--out`` is what ``python -m infer ... --templates-score FILE`` and
``infer.load(templates_score=FILE)`` read. On the demo's cell (its 60 training images, 96 s):
box AP50 0.265 -> 0.369 on its test images, 0.186 -> 0.285 on its val images, 0.290 -> 0.343
on 32 more held-out images; the first 30 images (the default ``--images``, 50 s) do as well
(docs/benchmarks.md, "Training-free detection").

    python -m train.templates_score [--workdir runs/templates_score] [--out score.json]
    python -m train.templates_score --cell runs/demo/adapted/data/train [--images 30] \
        --out cell_score.json
"""

from __future__ import annotations

import argparse
import pathlib
import sys
from collections.abc import Sequence

import numpy as np

from train.cell_score import CELL_IMAGES, TooFewCandidates, calibrate_cell, collect

#: The calibration cells' meshes and seeds (none of them the evaluations').
SHARED = pathlib.Path(__file__).resolve().parents[2] / "shared" / "meshes" / "bop"
PROCEDURAL_SEEDS = (3, 4, 5)
BOP_SEED = 21


def generate(workdir: pathlib.Path) -> list[tuple[pathlib.Path, bool]]:
    """The calibration datasets (generated when missing) and whether each image is queried
    with its own parts."""
    from datagen import generate as G
    from train import adapt

    out = []
    for seed in PROCEDURAL_SEEDS:
        folder = workdir / f"procedural{seed}"
        if not (folder / "data" / "test").exists():
            args = adapt.parse_args(["--meshes", "procedural:5", "--seed", str(seed),
                                     "--workdir", str(folder), "--test-scenes", "4",
                                     "--from", "scratch"])
            adapt.generate(args, folder / "data", sets=("val", "test"))
        out += [(folder / "data" / "val", False), (folder / "data" / "test", False)]
    folder = workdir / "bop_cell"
    if not (folder / "val_pbr").exists():
        meshes = [str(SHARED / "tless" / "models"), str(SHARED / "itodd" / "models")]
        for m in meshes:
            if not pathlib.Path(m).is_dir():
                sys.exit(f"{m} not found: the T-LESS and ITODD meshes of ../shared are needed")
        G.main(["--out", str(folder), "--num-scenes", "8", "--layout", "cell", "--seed",
                str(BOP_SEED), "--instances", "8", "--distinct", "5", "8", "--meshes", *meshes,
                "--resolution", "640", "480", "--spp", "8", "--split", "val",
                "--val-fraction", "0", "--quiet"])
    return out + [(folder, True)]


def main(argv: Sequence[str] | None = None) -> dict:
    from infer.api import DEFAULT_CACHE

    p = argparse.ArgumentParser(prog="python -m train.templates_score",
                                description=__doc__.split("\n")[0])
    p.add_argument("--workdir", type=pathlib.Path, default=pathlib.Path("runs/templates_score"))
    p.add_argument("--out", type=pathlib.Path, default=None, help="weights and figures (JSON)")
    p.add_argument("--cache-dir", type=pathlib.Path, default=DEFAULT_CACHE)
    p.add_argument("--cell", type=pathlib.Path, default=None, metavar="DATA",
                   help="calibrate one cell, a model per part, on this BOP dataset of its own "
                        "parts (e.g. a train.adapt run's WORKDIR/data/train) instead of the "
                        "shared weights on cells of other parts")
    p.add_argument("--split", default=None,
                   help="with --cell: the split to read (default: the dataset's only one)")
    p.add_argument("--images", type=int, default=CELL_IMAGES,
                   help="with --cell: the images fitted on (the split's first)")
    args = p.parse_args(argv)
    if args.cell is not None and args.images < 1:
        p.error("--images must be at least 1")
    try:
        return fit(args)
    except TooFewCandidates as e:
        sys.exit(str(e))


def fit(args: argparse.Namespace) -> dict:
    """The command's work on its parsed arguments (:func:`main`)."""
    from threept_jax.data.files import atomic_write_json
    from threept_jax.pipeline.shape_search import FEATURES, fit_score_weights

    if args.cell is not None:
        result = calibrate_cell(args.cell, args.split, args.cache_dir / "contours", args.images)
        if args.out:
            atomic_write_json(args.out, result, indent=1)
            print(f"wrote {args.out}: pass it as --templates-score")
        return result
    feats, right = [], []
    for data, per_image in generate(args.workdir):
        f, r, _, _ = collect(data, per_image, args.cache_dir / "contours",
                             str(data.relative_to(args.workdir)))
        feats.append(f)
        right.append(r)
        print(f"{data.relative_to(args.workdir)}: {len(r)} candidates, {int(r.sum())} right", flush=True)
    feats, right = np.concatenate(feats), np.concatenate(right)
    weights = fit_score_weights(feats, right)
    result = {"features": [*FEATURES, "bias"], "weights": weights.tolist(),
              "candidates": int(len(right)), "right": int(right.sum())}
    print(f"{len(right)} candidates, {int(right.sum())} right; "
          f"SCORE_WEIGHTS = ({', '.join(f'{w:.4g}' for w in weights)})")
    if args.out:
        atomic_write_json(args.out, result, indent=1)
    return result


if __name__ == "__main__":
    main()
