"""Command line (``python -m infer``): ``python -m infer bop ...`` (a BOP split -> BOP result files) and
``python -m infer images ...`` (your images + meshes -> JSON and overlays).

Run ``python -m infer bop --help`` / ``python -m infer images --help``.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time
from collections.abc import Sequence

import cv2
import numpy as np

from infer.api import DEFAULT_CACHE, Camera, load, run_scene


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--workdir", required=True, help="a detector training run (train/launch.py --workdir)")
    p.add_argument("--step", default="best", help="checkpoint: best, latest or a step number")
    p.add_argument("--num-templates", type=int, default=1024,
                   help="templates per object: 1024 covers rotations to 22 deg, half the 45 deg "
                        "between pose hypotheses; 5140 (the paper's bank, 12.8 deg) onboards 5x "
                        "slower")
    p.add_argument("--num-scales", type=int, default=3,
                   help="pan-and-scan scales (3 for an unknown depth range)")
    p.add_argument("--score-threshold", type=float, default=0.1)
    p.add_argument("--max-detections", type=int, default=100, help="per image")
    p.add_argument("--cache-dir", type=pathlib.Path, default=DEFAULT_CACHE,
                   help="onboarding and compilation cache (env THREEPT_CACHE)")
    p.add_argument("--out", type=pathlib.Path, required=True, help="output folder")
    p.add_argument("--overlays", type=int, default=10, help="overlay PNGs written (0: none)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m infer", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    b = sub.add_parser("bop", help="run on a BOP split, write BOP 6D CSV + 2D JSON",
                       formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    _common(b)
    b.add_argument("--dataset-dir", type=pathlib.Path, required=True)
    b.add_argument("--split", default="test")
    b.add_argument("--targets", default="bop24", choices=("bop24", "bop19", "all"),
                   help="which images: a test_targets file, or every image of the split")
    b.add_argument("--obj-ids", type=int, nargs="*", help="query only these objects (default all)")
    b.add_argument("--scene-ids", type=int, nargs="*", help="only these scenes")
    b.add_argument("--max-images", type=int, default=None)
    b.add_argument("--models-subdir", default="models", help="meshes to onboard")
    b.add_argument("--method", default="threept", help="method name in the result file names")
    b.add_argument("--evaluate", action="store_true", help="also run the BOP evaluator")
    i = sub.add_parser("images", help="run on images with given meshes and cameras",
                       formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    _common(i)
    i.add_argument("--mesh", action="append", required=True, metavar="ID=PATH",
                   help="an object to find (repeat): integer id and mesh file (PLY/OBJ/GLB/STL)")
    i.add_argument("--units", default="mm", choices=("mm", "cm", "m", "in"),
                   help="length unit of the mesh files")
    i.add_argument("--image", action="append", required=True, help="an RGB image (repeat for views)")
    i.add_argument("--K", action="append", metavar="fx,fy,cx,cy",
                   help="intrinsics in pixels, one per image (or use --cameras)")
    i.add_argument("--cameras", type=pathlib.Path,
                   help='JSON list, one per image: {"K": 3x3, "T_cam_world": 4x4 (mm, multi-view)}')
    return parser


def load_models(args):
    """The run's models (``infer.load``) with the onboarding and compilation caches."""
    import jax

    jax.config.update("jax_compilation_cache_dir", str(args.cache_dir / "jax"))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
    return load(args.workdir, args.step, cache_dir=args.cache_dir,
                num_templates=args.num_templates)


def detector_options(args) -> dict:
    return dict(num_scales=args.num_scales, score_threshold=args.score_threshold,
                max_detections=args.max_detections)


def _read_rgb(path) -> np.ndarray:
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise FileNotFoundError(f"cannot read image {path}")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def _cameras(args, n: int) -> list[Camera]:
    """One Camera per image, from --cameras FILE or --K (single view)."""
    if args.cameras is not None:
        cams = json.loads(args.cameras.read_text())
        if len(cams) != n:
            raise SystemExit(f"error: {args.cameras} has {len(cams)} cameras for {n} images")
        for i, c in enumerate(cams):
            if not isinstance(c, dict) or "K" not in c:
                raise SystemExit(f"error: {args.cameras} camera {i} has no \"K\" (3x3 in pixels)")
        return [Camera(c["K"], T_cam_world=c.get("T_cam_world")) for c in cams]
    if not args.K or len(args.K) != n:
        raise SystemExit(f"error: give one --K fx,fy,cx,cy per image ({n}) or --cameras FILE")
    cameras = []
    for k in args.K:
        try:
            fx, fy, cx, cy = (float(v) for v in k.split(","))
        except ValueError:
            raise SystemExit(f"error: --K {k!r} must be four numbers fx,fy,cx,cy (pixels)") from None
        cameras.append(Camera(np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])))
    return cameras


def run_images(args) -> list:
    from infer.detect import Detection
    from infer.visualize import draw_detections

    meshes = {}
    for item in args.mesh:
        key, _, path = item.partition("=")
        if not key.isdigit() or not path:
            raise SystemExit(f"error: --mesh {item!r} must be ID=PATH with an integer id")
        meshes[int(key)] = path
    images = [_read_rgb(p) for p in args.image]
    cameras = _cameras(args, len(images))
    models = load_models(args)
    objects = models.onboard(meshes, units=args.units)
    start = time.perf_counter()
    instances = run_scene(images, cameras, objects, models, **detector_options(args))
    elapsed = time.perf_counter() - start
    args.out.mkdir(parents=True, exist_ok=True)
    rows = [{"obj_id": x.obj_id, "score": x.score, "T_world_obj": x.T_world_obj.tolist(),
             "boxes_xyxy": {str(v): b.tolist() for v, b in x.boxes.items()},
             "hypotheses": x.hypotheses.tolist(), "hypothesis_scores": x.hypothesis_scores.tolist()}
            for x in instances]
    (args.out / "instances.json").write_text(json.dumps({"time_s": elapsed, "instances": rows}, indent=1))
    for v, (img, path) in enumerate(zip(images, args.image)):
        if v >= args.overlays:
            break
        T_cw = np.eye(4) if cameras[v].T_cam_world is None else cameras[v].T_cam_world
        drawn = [Detection(x.obj_id, x.boxes.get(v, np.zeros(4)), x.score, (T_cw @ x.T_world_obj)[None],
                           x.hypothesis_scores[:1], np.zeros(0)) for x in instances]
        canvas = draw_detections(img, drawn, [x.masks[v] for x in instances])
        cv2.imwrite(str(args.out / f"overlay_{v}_{pathlib.Path(path).stem}.png"),
                    cv2.cvtColor(canvas, cv2.COLOR_RGB2BGR))
    print(f"{len(instances)} instances in {elapsed:.2f} s -> {args.out / 'instances.json'}")
    return instances


def main(argv: Sequence[str] | None = None):
    args = build_parser().parse_args(argv)
    try:
        if args.command == "bop":
            from infer.bop_runner import run_bop

            return run_bop(args)
        return run_images(args)
    except (FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        raise SystemExit(2) from e

