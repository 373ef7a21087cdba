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

    python -m train.templates_score [--workdir runs/templates_score] [--out score.json]
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
from collections.abc import Sequence

import numpy as np
from tqdm import tqdm

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


def collect(data: pathlib.Path, per_image: bool, cache: pathlib.Path, name: str):
    """Features [P, F] and rightness [P] of every verified candidate of every image."""
    from infer.refine import refine_objects
    from infer.shape_detect import ShapeSearchDetector
    from threept_jax.data import bop
    from threept_jax.geometry.boxes import box_iou

    dataset = bop.BopDataset(data)
    split = dataset.split("val_pbr")
    cell = bop.load_cell(data)
    depth = None if cell is None else tuple(cell["depth_range_mm"])
    objects = refine_objects({k: m.path for k, m in dataset.models().items()})
    by_id = {o.obj_id: o for o in objects}
    detectors = {}

    def detector(ids):
        if ids not in detectors:
            detectors[ids] = ShapeSearchDetector([by_id[i] for i in ids], depth_range=depth,
                                                 cache_dir=cache)
        return detectors[ids]

    feats, right = [], []
    keys = [(s, im) for s in split.scene_ids for im in split.scene(s).image_ids]
    for s, im in tqdm(keys, desc=name, leave=False):
        scene = split.scene(s)
        gt_ids = np.array([g.obj_id for g in scene.gt[im]])
        gt_box = np.array([[b[0], b[1], b[0] + b[2], b[1] + b[3]]
                           for b in (i.bbox_obj for i in scene.gt_info[im])], np.float64)
        det = detector(tuple(sorted(set(gt_ids.tolist())) if per_image else sorted(by_id)))
        c = det.candidates(scene.image(im), scene.cameras[im].K)
        if c is None:
            continue
        ids = np.array([o.obj_id for o in det.objects])[c.obj]
        iou = np.asarray(box_iou(c.xyxy, gt_box.reshape(-1, 4)))
        iou = np.where(ids[:, None] == gt_ids[None], iou, 0.0)
        feats.append(c.features)
        right.append(iou.max(1, initial=0.0) >= 0.5)
    if not feats:
        sys.exit(f"{data}: no image gave a candidate (no proposal or no part outline): check "
                 f"its images and meshes, or delete the folder to make it again")
    return np.concatenate(feats), np.concatenate(right)


def main(argv: Sequence[str] | None = None) -> dict:
    from infer.api import DEFAULT_CACHE
    from threept_jax.pipeline.shape_search import FEATURES, fit_score_weights

    p = argparse.ArgumentParser(prog="python -m train.templates_score",
                                description=__doc__.split("\n")[0])
    p.add_argument("--workdir", type=pathlib.Path, default=pathlib.Path("runs/templates_score"))
    p.add_argument("--out", type=pathlib.Path, default=None, help="weights and figures (JSON)")
    p.add_argument("--cache-dir", type=pathlib.Path, default=DEFAULT_CACHE)
    args = p.parse_args(argv)
    feats, right = [], []
    for data, per_image in generate(args.workdir):
        f, r = collect(data, per_image, args.cache_dir / "contours",
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
        args.out.write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
