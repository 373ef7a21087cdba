"""Command line (``python -m infer``): ``python -m infer bop ...`` (a BOP split -> BOP result files) and
``python -m infer images ...`` (your images + meshes -> JSON and overlays) and ``python -m infer
track ...`` (image sequences or a video -> tracked poses, :mod:`infer.track_cli`).

Run ``python -m infer bop --help`` / ``python -m infer images --help`` /
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

from infer.api import DEFAULT_CACHE, Camera, load, prepare_views, run_scene
from infer.onboarding import ONBOARD_TEMPLATES
from threept_jax.geometry.diameter import MeshUnitsError
from threept_jax.geometry.validate import validate_intrinsics, validate_rigid


def _int_at_least(low: int):
    """An argparse ``type``: an integer >= ``low`` (argparse prints ``error: argument --flag:
    ...`` and exits 2 otherwise)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be an integer, got {text!r}") from None
        if value < low:
            raise argparse.ArgumentTypeError(f"must be >= {low}, got {value}")
        return value

    return parse


def _number_in(accepts, rule: str):
    """An argparse ``type``: a float for which ``accepts(value)`` holds (NaN never does);
    ``rule`` says which, e.g. "in [0, 1]"."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be a number, got {text!r}") from None
        if not accepts(value):
            raise argparse.ArgumentTypeError(f"must be {rule}, got {text}")
        return value

    return parse


_fraction = _number_in(lambda v: 0.0 <= v <= 1.0, "in [0, 1]")
_positive = _number_in(lambda v: 0.0 < v < float("inf"), "a finite number > 0")


def _step(text: str) -> str | int:
    """An argparse ``type``: ``best``, ``latest`` or a checkpoint step >= 0."""
    if text in ("best", "latest"):
        return text
    try:
        return _int_at_least(0)(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(
            f"must be best, latest or a step number >= 0, got {text!r}") from None


def _common(p: argparse.ArgumentParser, workdir_when: str | None = None) -> None:
    """The options every subcommand shares. ``workdir_when``: when the detector run is optional,
    the help's words for when it is needed (``--workdir`` is required otherwise)."""
    p.add_argument("--workdir", required=workdir_when is None,
                   help="a detector training run (train/launch.py --workdir)"
                   + ("" if workdir_when is None else f"; needed {workdir_when}"))
    p.add_argument("--step", type=_step, default="best",
                   help="checkpoint: best, latest or a step number")
    p.add_argument("--num-templates", type=_int_at_least(1), default=ONBOARD_TEMPLATES,
                   help="templates per object: 1024 covers rotations to 22 deg, half the 45 deg "
                        "between pose hypotheses; 5140 (the paper's bank, 12.8 deg) onboards 5x "
                        "slower")
    p.add_argument("--depth-range", type=_positive, nargs=2, metavar=("ZMIN", "ZMAX"),
                   help="distance range of the objects from the camera (mm): pan-and-scan "
                        "uses the one scale (or the few) that puts their projected diameters "
                        "(diameter * f / z) at the sizes the detector was trained on; without "
                        "it, the scales cover objects from 64 px to the whole image. bop: "
                        "default from the dataset's cell.json when it has one (datagen "
                        "--layout cell)")
    p.add_argument("--num-scales", type=_int_at_least(1), default=None,
                   help="pan-and-scan scales (default: the fewest that cover the object sizes: "
                        "3 for a 640x480 image without --depth-range)")
    p.add_argument("--score-threshold", type=_fraction, default=0.1,
                   help="keep detections scoring above this, in [0, 1]")
    p.add_argument("--max-detections", type=_int_at_least(1), default=100, help="per image")
    p.add_argument("--cache-dir", type=pathlib.Path, default=DEFAULT_CACHE,
                   help="onboarding and compilation cache (env THREEPT_CACHE)")
    p.add_argument("--out", type=pathlib.Path, required=True, help="output folder")
    p.add_argument("--overlays", type=_int_at_least(0), default=10,
                   help="overlay PNGs written (0: none)")


def refiner_options(p: argparse.ArgumentParser, what: str, required: bool = False) -> None:
    """``--refiner RUN`` (``what`` it does for the subcommand) and ``--refiner-step``."""
    p.add_argument("--refiner", type=pathlib.Path, required=required, default=None,
                   metavar="RUN", help="a 3PT-R training run (train/launch.py --config "
                                       f"train/configs/refiner.py:tiny): {what}")
    p.add_argument("--refiner-step", type=_step, default="best",
                   help="refiner checkpoint: best, latest or a step number")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m infer", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    b = sub.add_parser("bop", help="run on a BOP split, write BOP 6D CSV + 2D JSON",
                       formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    _common(b, workdir_when="unless --refine-only")
    b.add_argument("--dataset-dir", type=pathlib.Path, required=True)
    b.add_argument("--split", default="test")
    b.add_argument("--targets", default="bop24", choices=("bop24", "bop19", "all", "multiview"),
                   help="which images: a test_targets file, every image of the split, or "
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
    b.add_argument("--obj-ids", type=_int_at_least(0), nargs="*",
                   help="query only these objects (default: the targets' objects, or all)")
    b.add_argument("--scene-ids", type=_int_at_least(0), nargs="*", help="only these scenes")
    b.add_argument("--max-images", type=_int_at_least(1), default=None)
    b.add_argument("--models-subdir", default="models", help="meshes to onboard")
    b.add_argument("--method", default="threept", help="method name in the result file names")
    b.add_argument("--evaluate", action="store_true", help="also run the BOP evaluator")
    b.add_argument("--overlay-threshold", type=_fraction, default=None,
                   help="draw only detections scoring at least this on the overlays (default: "
                        "--score-threshold); e.g. the f1_threshold --evaluate prints for a "
                        "validation split, while a low --score-threshold keeps every detection "
                        "for AP")
    i = sub.add_parser("images", help="run on images with given meshes and cameras",
                       formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    _common(i)
    i.add_argument("--mesh", action="append", required=True, metavar="ID=PATH",
                   help="an object to find (repeat): integer id and mesh file (PLY/OBJ/GLB/STL)")
    i.add_argument("--units", default="mm", choices=("mm", "cm", "m", "in"),
                   help="length unit of the mesh files")
    i.add_argument("--image", action="append", required=True, help="an RGB image (repeat for views)")
    camera_options(i, "image")
    from infer.track_cli import add_track_parser

    add_track_parser(sub)
    return parser


def camera_options(p: argparse.ArgumentParser, per: str) -> None:
    """``--K`` / ``--cameras`` / ``--calibration-size``: the cameras, one per ``per`` (image,
    view), read by ``_cameras``."""
    p.add_argument("--K", action="append", metavar="fx,fy,cx,cy",
                   help=f"intrinsics in pixels, one per {per} (or use --cameras)")
    p.add_argument("--cameras", type=pathlib.Path,
                   help=f'JSON list, one per {per}: {{"K": 3x3, "T_cam_world": 4x4 (mm, needed '
                        'for several views), "calibration_size": [W, H] (optional)}')
    p.add_argument("--calibration-size", type=_int_at_least(1), nargs=2, metavar=("W", "H"),
                   help=f"image size the intrinsics were calibrated at, when the {per}s are "
                        "resized: K is rescaled to each image (pixel centres at integers: "
                        "cx' = (cx + 0.5) * sx - 0.5)")


def load_models(args):
    """The run's models (``infer.load``: the detector of ``--workdir`` and, when the command has
    one, the refiner of ``--refiner``) with the onboarding and compilation caches."""
    import jax

    jax.config.update("jax_compilation_cache_dir", str(args.cache_dir / "jax"))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
    return load(args.workdir, args.step, refiner=getattr(args, "refiner", None),
                refiner_step=getattr(args, "refiner_step", "best"), cache_dir=args.cache_dir,
                num_templates=args.num_templates)


def detector_options(args) -> dict:
    return dict(num_scales=args.num_scales, depth_range=args.depth_range,
                score_threshold=args.score_threshold,
                max_detections=args.max_detections)


def _read_rgb(path) -> np.ndarray:
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise FileNotFoundError(f"cannot read image {path}")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def _cameras(args, n: int) -> list[Camera]:
    """One Camera per image, from --cameras FILE or --K (single view); ValueError names a bad
    entry."""
    default_hw = None if args.calibration_size is None else tuple(args.calibration_size[::-1])
    if args.cameras is not None:
        path = args.cameras
        try:
            cams = json.loads(path.read_text())
        except json.JSONDecodeError as e:
            raise ValueError(f"{path} is not valid JSON: {e}") from None
        if not isinstance(cams, list):
            raise ValueError(f"{path} must hold a JSON list of cameras, one per image")
        if len(cams) != n:
            raise ValueError(f"{path} has {len(cams)} cameras for {n} images (--image)")
        out = []
        for i, c in enumerate(cams):
            where = f"{path} camera {i}"
            if not isinstance(c, dict) or "K" not in c:
                raise ValueError(f'{where} has no "K" (3x3 in pixels)')
            K = validate_intrinsics(c["K"], f"{where} K")
            T = c.get("T_cam_world")
            if T is not None:
                T = validate_rigid(T, f"{where} T_cam_world (world -> camera, mm)")
            hw = default_hw
            if c.get("calibration_size") is not None:
                size = np.ravel(c["calibration_size"])
                if size.size != 2 or not all(float(v).is_integer() and v > 0 for v in size):
                    raise ValueError(f'{where} "calibration_size" must be [W, H] in pixels, got '
                                     f"{c['calibration_size']}")
                hw = (int(size[1]), int(size[0]))
            out.append(Camera(K, T_cam_world=T, calibration_hw=hw))
        return out
    if not args.K or len(args.K) != n:
        raise ValueError(f"{len(args.K or ())} --K for {n} --image: give one --K fx,fy,cx,cy "
                         "per image or --cameras FILE")
    cameras = []
    for k in args.K:
        try:
            fx, fy, cx, cy = (float(v) for v in k.split(","))
        except ValueError:
            raise ValueError(f"--K {k!r} must be four numbers fx,fy,cx,cy (pixels)") from None
        K = validate_intrinsics([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], f"--K {k}")
        cameras.append(Camera(K, calibration_hw=default_hw))
    return cameras


def parse_meshes(items: Sequence[str]) -> dict[int, str]:
    """``--mesh ID=PATH`` (repeated) -> {obj_id: path}; errors name the bad item."""
    meshes = {}
    for item in items:
        key, _, path = item.partition("=")
        if not key.isdigit() or not path:
            raise ValueError(f"--mesh {item!r} must be ID=PATH with an integer id")
        if not pathlib.Path(path).is_file():
            raise FileNotFoundError(f"--mesh {item}: no mesh file {path}")
        meshes[int(key)] = path
    return meshes


def run_images(args) -> list:
    from infer.detect import Detection
    from infer.visualize import draw_detections, empty_caption

    meshes = parse_meshes(args.mesh)
    cameras = _cameras(args, len(args.image))
    images = [_read_rgb(p) for p in args.image]
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
    if args.depth_range is not None and args.depth_range[0] > args.depth_range[1]:
        parser.error(f"argument --depth-range: ZMIN must be <= ZMAX, got {args.depth_range[0]:g} "
                     f"{args.depth_range[1]:g}")
    if args.command == "bop":
        if args.refine_only is not None and args.refiner is None:
            parser.error("--refine-only needs --refiner RUN (the 3PT-R run that refines)")
        if args.refine_only is not None and args.workdir is not None:
            parser.error("--refine-only refines another method's results without the detector: "
                         "drop --workdir")
        if args.refine_only is None and args.workdir is None:
            parser.error("the following arguments are required: --workdir (or --refine-only "
                         "RESULTS.csv with --refiner)")
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
