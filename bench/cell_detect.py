"""The cell detector's path against the templates detector alone: seconds per image and box AP.

On a BOP split of a cell with ground truth (default: the demo's adapted test images,
``runs/demo/adapted/data/test``, and its cell detector run, ``runs/demo/adapted/cell``, both
written by ``make demo``), every image queried with all of the cell's parts, the cell's depth
range from its ``cell.json``, in one process:

* **templates** (the reference): the training-free detector alone
  (:class:`infer.shape_detect.ShapeSearchDetector`), the search over the whole image;
* **cell, network's boxes only** (``CellDetector(templates_threshold=None)``): the trained
  network's boxes, each posed by the templates' fit in its copies;
* **cell** (the default ``--detector cell``): the same, joined by the templates detector's own
  detections and merged (:func:`infer.cell_detect.merge`).

For each: the first image (cold: compilation of the shapes it meets) and the median of the
others (warm) in seconds, the ratio of warm seconds to the templates detector's, and box AP50 /
AP (COCO, every part a category) of the detections as they come (before refinement, which
``python -m infer bop --evaluate`` adds with the 6D figures). The detectors share one contour
cache, so onboarding is not in the figures (``bench/shape_search.py`` times it).

    python bench/cell_detect.py [--run runs/demo/adapted/cell] [--data DIR] [--images 8]
        [--templates-score FILE] [--out F.json]
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from shape_search import box_ap, run  # noqa: E402

from infer.api import DEFAULT_CACHE  # noqa: E402
from infer.cell_detect import CellDetector  # noqa: E402
from infer.refine import refine_objects  # noqa: E402
from infer.shape_detect import ShapeSearchDetector, load_score_weights  # noqa: E402
from threept_jax.data import bop, dense_run  # noqa: E402


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--run", type=pathlib.Path, default=ROOT / "runs/demo/adapted/cell",
                   help="a cell detector's run (python -m train.cell_detector, train.adapt)")
    p.add_argument("--data", type=pathlib.Path, default=ROOT / "runs/demo/adapted/data/test")
    p.add_argument("--split", default="val_pbr")
    p.add_argument("--images", type=int, default=8)
    p.add_argument("--templates-score", type=pathlib.Path, default=None, metavar="FILE",
                   help="the cell's score calibration (train.adapt's WORKDIR/templates_score.json)")
    p.add_argument("--cache-dir", type=pathlib.Path, default=DEFAULT_CACHE)
    p.add_argument("--out", type=pathlib.Path, default=None)
    args = p.parse_args(argv)
    for path, what in ((args.run, "--run"), (args.data, "--data")):
        if not path.exists():
            sys.exit(f"{path} not found ({what}): run `make demo` first, or pass {what}")
    if args.images < 2:
        sys.exit("--images must be at least 2 (one cold, the others warm)")
    ds = bop.BopDataset(args.data)
    split = ds.split(args.split)
    cell = bop.load_cell(args.data)
    depth = None if cell is None else tuple(cell["depth_range_mm"])
    keys = [(s, im) for s in split.scene_ids for im in split.scene(s).image_ids][:args.images]
    objects = refine_objects({k: m.path for k, m in ds.models().items()})
    weights = None if args.templates_score is None else load_score_weights(args.templates_score)
    network, class_ids, _ = dense_run.load(args.run)
    common = dict(depth_range=depth, max_detections=30, score_weights=weights,
                  cache_dir=args.cache_dir / "contours")
    detectors = {
        "templates": ShapeSearchDetector(objects, score_threshold=0.0, **common),
        "cell, network's boxes only": CellDetector(network, class_ids, objects,
                                                   score_threshold=0.0, templates_threshold=None,
                                                   **common),
        "cell": CellDetector(network, class_ids, objects, score_threshold=0.0, **common)}
    result = {"run": str(args.run), "data": str(args.data), "images": len(keys),
              "parts": len(objects), "depth_range": depth,
              "templates_score": None if weights is None else str(args.templates_score)}
    for name, detector in detectors.items():
        dets, seconds = run(detector.detect, split, keys)
        ap50, ap = box_ap(args.data, args.split, dets)
        result[name] = {"cold_s": seconds[0], "warm_s": float(np.median(seconds[1:])),
                        "box_ap50": ap50, "box_ap": ap}
    ref = result["templates"]["warm_s"]
    for name in detectors:
        r = result[name]
        r["ratio"] = r["warm_s"] / ref
        print(f"{name}: cold {r['cold_s']:.1f} s, warm {r['warm_s']:.2f} s/image "
              f"({r['ratio']:.2f} x the templates detector), box AP50 {r['box_ap50']:.3f}, "
              f"AP {r['box_ap']:.3f} ({len(keys)} images, {len(objects)} parts, before "
              "refinement)")
    if args.out:
        args.out.write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
