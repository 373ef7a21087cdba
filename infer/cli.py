"""Command line (``python -m infer``): ``python -m infer bop ...`` (a BOP split -> BOP result files) and
``python -m infer images ...`` (your images + meshes -> JSON and overlays) and ``python -m infer
track ...`` (image sequences or a video -> tracked poses, :mod:`infer.track_cli`).

Without ``--workdir`` / ``--refiner`` the commands use the models that ship in ``models/``
(:mod:`infer.shipped`). Run ``python -m infer bop --help`` / ``python -m infer images --help`` /
``python -m infer track --help``.
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

from infer.api import prepare_views, run_scene
from infer.options import (
    camera_options,
    cameras_from_args,
    common_options,
    default_score_threshold,
    detector_options,
    fraction,
    int_at_least,
    load_models,
    parse_meshes,
    read_rgb,
    refiner_options,
)
from infer.track_cli import add_track_parser
from threept_jax.geometry.diameter import MeshUnitsError


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m infer", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    b = sub.add_parser("bop", help="run on a BOP split, write BOP 6D CSV + 2D JSON",
                       formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    common_options(b, workdir_when="unless --refine-only")
    b.add_argument("--dataset-dir", type=pathlib.Path, required=True)
    b.add_argument("--split", default="test")
    b.add_argument("--targets", default="bop24", choices=("bop24", "bop19", "all", "multiview"),
                   help="which images: a test_targets file (bop19: each image queried with "
                        "the objects its targets name, unless --obj-ids), every image of the "
                        "split, or "
                        "multiview: the groups of test_targets_multiview_bop25.json, each group "
                        "one multi-view run_scene (cameras from cam_R_w2c/cam_t_w2c); an "
                        "instance is written to a view's rows when its centre projects inside "
                        "that image in front of the camera; --max-images counts groups")
    refiner_options(b, "refine every instance; the results hold the refined poses and the "
                       "refiner's masks, and {method}-initial_* files the poses before "
                       "refinement")
    b.add_argument("--refine-only", type=pathlib.Path, default=None, metavar="RESULTS.csv",
                   help="refine another method's BOP 6D results with --refiner (no detector): "
                        "writes {its method}-3ptr_{dataset}-{split}.csv/.json, scores kept, "
                        "time = its time + the refinement's")
    b.add_argument("--obj-ids", type=int_at_least(0), nargs="*",
                   help="query only these objects (default: the targets' objects, or all)")
    b.add_argument("--scene-ids", type=int_at_least(0), nargs="*", help="only these scenes")
    b.add_argument("--max-images", type=int_at_least(1), default=None)
    b.add_argument("--models-subdir", default="models", help="meshes to onboard")
    b.add_argument("--method", default="threept", help="method name in the result file names")
    b.add_argument("--evaluate", action="store_true", help="also run the BOP evaluator")
    b.add_argument("--overlay-threshold", type=fraction, default=None,
                   help="draw only detections scoring at least this on the overlays (default: "
                        "--score-threshold); e.g. the f1_threshold --evaluate prints for a "
                        "validation split, while a low --score-threshold keeps every detection "
                        "for AP")
    i = sub.add_parser("images", help="run on images with given meshes and cameras",
                       formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    common_options(i)
    i.add_argument("--mesh", action="append", required=True, metavar="ID=PATH",
                   help="an object to find (repeat): integer id and mesh file (PLY/OBJ/GLB/STL)")
    i.add_argument("--units", default="mm", choices=("mm", "cm", "m", "in"),
                   help="length unit of the mesh files")
    i.add_argument("--image", action="append", required=True, help="an RGB image (repeat for views)")
    camera_options(i, "image")
    add_track_parser(sub)
    return parser


def bop_args(dataset_dir, out, **options) -> argparse.Namespace:
    """The options of ``python -m infer bop`` for a call from Python,
    ``infer.bop_runner.run_bop(bop_args(...))``: every flag's default, then ``options`` by the
    flags' names in Python (``refiner=pathlib.Path("contour")``, ``score_threshold=0.0``,
    ``obj_ids=[1, 2]``), then the defaults that follow from them (the detector's score
    threshold)."""
    args = build_parser().parse_args(["bop", "--dataset-dir", str(dataset_dir), "--out", str(out)])
    unknown = sorted(set(options) - set(vars(args)))
    if unknown:
        raise TypeError(f"not options of python -m infer bop: {unknown}")
    vars(args).update(options)
    default_score_threshold(args)
    return args


def run_images(args) -> list:
    from infer.detect import Detection
    from infer.visualize import draw_detections, empty_caption

    meshes = parse_meshes(args.mesh)
    cameras = cameras_from_args(args, len(args.image))
    images = [read_rgb(p) for p in args.image]
    prepare_views(images, cameras)  # K against each image's size, before the slow work
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
    caption = None
    if not instances:
        caption = empty_caption(args.score_threshold, instances.best_score)
        if instances.best_score > args.score_threshold:
            caption = (f"0 instances: no detection above threshold {args.score_threshold:g} "
                       "was matched across enough views")
    for v, (img, path) in enumerate(zip(images, args.image)):
        if v >= args.overlays:
            break
        T_cw = np.eye(4) if cameras[v].T_cam_world is None else cameras[v].T_cam_world
        drawn = [Detection(x.obj_id, x.boxes.get(v, np.zeros(4)), x.score, (T_cw @ x.T_world_obj)[None],
                           x.hypothesis_scores[:1], np.zeros(0)) for x in instances]
        canvas = draw_detections(img, drawn, [x.masks[v] for x in instances], caption=caption)
        cv2.imwrite(str(args.out / f"overlay_{v}_{pathlib.Path(path).stem}.png"),
                    cv2.cvtColor(canvas, cv2.COLOR_RGB2BGR))
    if caption:
        print(caption)
    print(f"{len(instances)} instances in {elapsed:.2f} s -> {args.out / 'instances.json'}")
    return instances


def main(argv: Sequence[str] | None = None):
    parser = build_parser()
    args = parser.parse_args(argv)
    default_score_threshold(args)
    if args.depth_range is not None and args.depth_range[0] > args.depth_range[1]:
        parser.error(f"argument --depth-range: ZMIN must be <= ZMAX, got {args.depth_range[0]:g} "
                     f"{args.depth_range[1]:g}")
    if args.command == "bop":
        if args.refine_only is not None and str(args.refiner) == "none":
            parser.error("--refine-only refines with a refiner: drop --refiner none (the "
                         "default refiner) or pass --refiner contour|RUN")
        if args.refine_only is not None and args.workdir is not None:
            parser.error("--refine-only refines another method's results without the detector: "
                         "drop --workdir")
        if args.refine_only is not None and args.targets == "multiview":
            parser.error("--refine-only refines single-view results (camera frame): drop "
                         "--targets multiview")
    try:
        if args.command == "bop":
            from infer.bop_runner import run_bop

            return run_bop(args)
        if args.command == "track":
            from infer.track_cli import run_track

            return run_track(args)
        return run_images(args)
    except MeshUnitsError as e:  # name this CLI's flag, not the Python argument
        fix = e.message("--units {}") if args.command in ("images", "track") else (
            f"{e}; BOP models are in mm: rescale the models folder")
        print(f"error: {fix}", file=sys.stderr)
        raise SystemExit(2) from e
    except (FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        raise SystemExit(2) from e
