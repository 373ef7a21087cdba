"""The near-symmetric turn check of the contour refiner (issue 37): what it costs an image.

On a BOP split with ground truth (default: the demo's adapted cell's test images,
``runs/demo/adapted/data/test``, written by ``make demo``; its five parts include a 40-tooth
gear), every image queried with all of the dataset's parts at the cell's depth range, the
templates detector's detections (``max_detections``, score threshold 0, as the BOP runs) are
refined by two contour refiners of the same parts in the same process:

* ``ContourRefiner(turns=False)``: the reference, the refined pose as it is;
* ``ContourRefiner()``: each instance of a part with near-symmetric turns (the gear) turned to
  whichever of them the edges inside its outline show best.

Printed: the parts with turns and how many (found once per mesh, cached), the first image of
each (cold: compilation included), the median of the others (warm) in seconds per image, the
warm ratio, and how many instances the check turned. Its accuracy is the BOP 6D AP of
``python -m infer bop ... --evaluate`` (docs/benchmarks.md, "Near-symmetric turns").

    python bench/turns.py [--data DIR] [--split val_pbr] [--images 8] [--max-detections 12]
"""

from __future__ import annotations

import argparse
import pathlib
import statistics
import sys
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from infer.api import DEFAULT_CACHE  # noqa: E402
from infer.contour_refine import ContourRefiner  # noqa: E402
from infer.refine import refine_objects  # noqa: E402
from infer.shape_detect import ShapeSearchDetector  # noqa: E402
from threept_jax.data import bop  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=pathlib.Path, default=ROOT / "runs/demo/adapted/data/test")
    ap.add_argument("--split", default="val_pbr")
    ap.add_argument("--images", type=int, default=8)
    ap.add_argument("--max-detections", type=int, default=12)
    ap.add_argument("--cache-dir", type=pathlib.Path, default=DEFAULT_CACHE)
    args = ap.parse_args()
    if not (args.data / "models").is_dir():
        sys.exit(f"{args.data} holds no BOP dataset (models/); run `make demo` first or pass "
                 "--data DIR --split SPLIT")
    ds = bop.BopDataset(args.data)
    split = ds.split(args.split)
    keys = [(s, i) for s in split.scene_ids for i in split.scene(s).image_ids][:args.images]
    cell = bop.load_cell(args.data)
    depth = None if cell is None else tuple(cell["depth_range_mm"])
    objects = refine_objects({o: args.data / "models" / f"obj_{o:06d}.ply"
                              for o in sorted(ds.models())})
    cache = args.cache_dir / "contours"
    detector = ShapeSearchDetector(objects, depth_range=depth, score_threshold=0.0,
                                   max_detections=args.max_detections, cache_dir=cache)
    t = time.perf_counter()
    with_turns = ContourRefiner(objects, cache_dir=cache)
    onboard = time.perf_counter() - t
    plain = ContourRefiner(objects, cache_dir=cache, turns=False)
    print(f"{args.data} ({split.path.name}), {len(keys)} images, {len(objects)} parts; parts with "
          f"turns: {({o: len(v[0]) for o, v in with_turns.turns.items()}) or 'none'} "
          f"(refiner built in {onboard:.1f} s, turns cached)")
    times: dict[str, list[float]] = {"plain": [], "turns": []}
    turned = instances = 0
    for sid, im in keys:
        scene = split.scene(sid)
        image, K = scene.image(im), scene.cameras[im].K
        dets = detector.detect(image, K)
        ids = [d.obj_id for d in dets]
        hyps = [np.asarray(d.poses, np.float64) for d in dets]
        out = {}
        for name, refiner in (("plain", plain), ("turns", with_turns)):
            t = time.perf_counter()
            out[name] = refiner([image], K[None], None, ids, hyps)
            times[name].append(time.perf_counter() - t)
        instances += len(ids)
        turned += sum(not np.allclose(a.T_world_obj, b.T_world_obj)
                      for a, b in zip(out["plain"], out["turns"]))
    warm = {k: statistics.median(v[1:]) if len(v) > 1 else float("nan") for k, v in times.items()}
    for k in ("plain", "turns"):
        print(f"contour refiner, {'with' if k == 'turns' else 'without'} the turn check: cold "
              f"{times[k][0]:.2f} s, warm {warm[k]:.3f} s an image (median of {len(keys) - 1})")
    print(f"ratio warm with / without: {warm['turns'] / warm['plain']:.2f} x "
          f"(+{warm['turns'] - warm['plain']:.3f} s an image); {turned} of {instances} "
          f"instances turned")


if __name__ == "__main__":
    main()
