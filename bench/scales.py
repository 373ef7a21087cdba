"""Benchmark: pan-and-scan tiles per object and detection time per image for each way of
choosing scales, against the old scales (0.8, 2.19, 5.98 on 640 x 480: the whole image in one
tile, then x350/128 twice, tiles overlapping by 128 px of a 512 tile) measured in the same
process.

Modes (``threept_jax.pipeline.pan_and_scan.plan_layout``):
- ``old``: the reference above;
- ``unknown``: nothing known (BOP), the fewest scales covering objects of 64 px to the whole
  image (3 at 640 x 480, 4 at 2048 x 1536), and the same with 3 scales at 2048 x 1536;
- ``depth``: a known depth range: a ``--diameter`` mm object at ``--depth ZMIN ZMAX`` mm seen
  with f = ``--focal`` x the image width (``projected_size_range``).

Tile counts are printed for the paper's 512 px tile and for the detector's own tile
(``--image-size``; the prior scales with it). Times: ``SceneDetector.detect`` with an untrained
detector (``--variant``; only shapes matter), one object, cold (first call, compilation
included) and warm (median of ``--repeats``), and the warm ratio old / mode.

    python bench/scales.py [--variant tiny/16 --image-size 128] [--sizes 640x480 2048x1536]
"""

from __future__ import annotations

import argparse
import pathlib
import sys
import warnings

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import trimesh  # noqa: E402
from flax import nnx  # noqa: E402
from flops import cold_and_warm  # noqa: E402

from infer.detect import SceneDetector  # noqa: E402
from infer.onboarding import Onboarder  # noqa: E402
from threept_jax.geometry.framing import SCALE_PRIOR  # noqa: E402
from threept_jax.models.configs import DetectorConfig  # noqa: E402
from threept_jax.models.detector import Detector  # noqa: E402
from threept_jax.pipeline import pan_and_scan as pns  # noqa: E402
from threept_jax.render import Mesh  # noqa: E402


def old_layout(image_hw, tile):
    """The scales and overlap inference used before: fit, then x350/128 per level."""
    lo, hi = SCALE_PRIOR
    fit = tile / max(image_hw)
    return pns.tile_layout(image_hw, tile, [fit * (hi / lo) ** k for k in range(3)],
                           min(int(lo), tile // 4))


def layouts(image_hw, tile, args):
    """{mode: TileLayout} for one image size and tile."""
    h, w = image_hw
    K = np.array([[args.focal * w, 0, w / 2 - 0.5], [0, args.focal * w, h / 2 - 0.5], [0, 0, 1]])
    sizes = pns.projected_size_range([args.diameter], args.depth, K)
    out = {"old": old_layout(image_hw, tile), "unknown": pns.plan_layout(image_hw, tile)}
    if len(out["unknown"].scales) != 3:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            out["unknown S=3"] = pns.plan_layout(image_hw, tile, num_scales=3)
    out[f"depth {args.depth[0]:g}-{args.depth[1]:g} mm"] = pns.plan_layout(
        image_hw, tile, object_sizes=sizes)
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--variant", default="tiny/16")
    p.add_argument("--image-size", type=int, default=128, help="the detector's tile")
    p.add_argument("--sizes", nargs="+", default=["640x480", "2048x1536"], help="WxH")
    p.add_argument("--diameter", type=float, default=100.0, help="mm, depth mode")
    p.add_argument("--depth", type=float, nargs=2, default=(500.0, 800.0), help="mm")
    p.add_argument("--focal", type=float, default=0.9, help="f as a share of the width")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--no-time", action="store_true", help="tile counts only")
    args = p.parse_args(argv)
    sizes = [tuple(int(v) for v in s.lower().split("x"))[::-1] for s in args.sizes]

    print("tiles per object (scales)")
    for hw in sizes:
        for tile in sorted({512, args.image_size}):
            for mode, lay in layouts(hw, tile, args).items():
                print(f"  {hw[1]}x{hw[0]} tile {tile:4d} {mode:24s} {lay.num_tiles:5d}  "
                      f"({', '.join(f'{s:.3f}' for s in lay.scales)})")
    if args.no_time:
        return

    cfg = DetectorConfig(variant=args.variant, image_size=args.image_size, render_size=32)
    model = Detector(cfg, rngs=nnx.Rngs(0))
    tm = trimesh.creation.box((args.diameter / np.sqrt(3),) * 3)
    mesh = Mesh(np.asarray(tm.vertices, np.float32), np.asarray(tm.faces, np.int32), name="cube")
    objects = Onboarder(model, cfg, "untrained@0", cache_dir=None,
                        num_templates=48).onboard_all({1: mesh}, show_progress=False)
    rng = np.random.default_rng(0)
    print(f"\ndetection seconds per image ({args.variant}, {args.image_size} px tile, untrained, "
          "1 object)")
    for hw in sizes:
        h, w = hw
        K = np.array([[args.focal * w, 0, w / 2 - 0.5], [0, args.focal * w, h / 2 - 0.5],
                      [0, 0, 1]])
        warm_ref = None
        for mode, lay in layouts(hw, args.image_size, args).items():
            det = SceneDetector(model, cfg, objects, score_threshold=0.0)
            det.layout = lambda image_hw, K=None, lay=lay: lay
            image = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
            cold, warm = cold_and_warm(lambda det=det, image=image, K=K: det.detect(image, K),
                                       args.repeats)
            warm_ref = warm if warm_ref is None else warm_ref
            print(f"  {w}x{h} {mode:24s} tiles {lay.num_tiles:5d}  cold {cold:7.2f}  "
                  f"warm {warm:7.3f}  old/this {warm_ref / warm:5.2f}x", flush=True)


if __name__ == "__main__":
    main()
