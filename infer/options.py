"""The options the ``python -m infer`` commands share (``bop``, ``images``, ``track``) and the
readers of what they name: argparse types that refuse bad values with a message naming the rule,
the common detector/output options, the refiner and camera options, cameras from ``--K`` or
``--cameras``, ``--mesh ID=PATH``, images, and the models a command loads.

:mod:`infer.cli` (the parser and ``images``), :mod:`infer.bop_runner` and :mod:`infer.track_cli`
import this module; it imports none of them.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
from collections.abc import Sequence

import cv2
import numpy as np

from infer.api import (
    DEFAULT_CACHE,
    DETECTORS,
    SCORE_THRESHOLDS,
    Camera,
    default_detector,
    load,
)
from infer.onboarding import ONBOARD_TEMPLATES
from infer.shipped import default_refiner, describe, shipped
from threept_jax.geometry.validate import validate_intrinsics, validate_rigid


def int_at_least(low: int):
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


def number_in(accepts, rule: str):
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


fraction = number_in(lambda v: 0.0 <= v <= 1.0, "in [0, 1]")
positive = number_in(lambda v: 0.0 < v < float("inf"), "a finite number > 0")


def checkpoint_step(text: str) -> str | int:
    """An argparse ``type``: ``best``, ``latest`` or a checkpoint step >= 0."""
    if text in ("best", "latest"):
        return text
    try:
        return int_at_least(0)(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(
            f"must be best, latest or a step number >= 0, got {text!r}") from None


def common_options(p: argparse.ArgumentParser, workdir_when: str | None = None) -> None:
    """The options every subcommand shares. ``workdir_when``: when the subcommand needs a
    detector only sometimes, the help's words for when."""
    p.add_argument("--workdir", type=pathlib.Path, default=None,
                   help="a 3PT-D training run (train/launch.py --workdir) or exported model "
                        "(implies --detector 3pt), or a cell detector's run (python -m "
                        "train.cell_detector; implies --detector cell); with --detector 3pt, "
                        "default: "
                        f"{describe('detector')}"
                        + ("" if workdir_when is None else f"; used {workdir_when}"))
    p.add_argument("--detector", choices=DETECTORS, default=None,
                   help="templates: no network, the parts found from their CAD models alone "
                        "(selective-search proposals, contour templates fitted to each, the best "
                        "poses verified by the contour refiner; one view); 3pt: the 3PT-D "
                        "network of --workdir, default the shipped one (needed for a rig's "
                        "views); cell: a cell's own trained detector (--workdir), its boxes "
                        "posed by the templates' fit. Default: the kind of --workdir's run, "
                        "else templates")
    p.add_argument("--templates-score", type=pathlib.Path, default=None, metavar="FILE",
                   help="the templates detector's score calibrated on the cell's own parts "
                        "(python -m train.templates_score --cell DATA --out FILE: a logistic "
                        "model per part, no network), with --detector templates or cell (its "
                        "templates' poses and detections); default: the shared score, fitted "
                        "on cells of other parts")
    p.add_argument("--templates-verifier", action=argparse.BooleanOptionalAction,
                   help="the shipped learned verifier's correction to the templates' score "
                        "(models/templates-verifier: the image around each candidate against "
                        "its part rendered at its pose; about 0.35 s an image), with --detector "
                        "templates or cell, with or without --templates-score. Default: on "
                        "(docs/inference.md)")
    p.add_argument("--step", type=checkpoint_step, default="best",
                   help="checkpoint: best, latest or a step number")
    p.add_argument("--num-templates", type=int_at_least(1), default=ONBOARD_TEMPLATES,
                   help="templates per object: 1024 covers rotations to 22 deg, half the 45 deg "
                        "between pose hypotheses; 5140 (the paper's bank, 12.8 deg) onboards 5x "
                        "slower")
    p.add_argument("--depth-range", type=positive, nargs=2, metavar=("ZMIN", "ZMAX"),
                   help="distance range of the objects from the camera (mm): pan-and-scan "
                        "uses the one scale (or the few) that puts their projected diameters "
                        "(diameter * f / z) at the sizes the detector was trained on; without "
                        "it, the scales cover objects from 64 px to the whole image. bop: "
                        "default from the dataset's cell.json when it has one (datagen "
                        "--layout cell)")
    p.add_argument("--num-scales", type=int_at_least(1), default=None,
                   help="pan-and-scan scales (default: the fewest that cover the object sizes: "
                        "3 for a 640x480 image without --depth-range)")
    p.add_argument("--score-threshold", type=fraction, default=None,
                   help="keep detections scoring above this, in [0, 1] (default: 0.4 with the "
                        "templates detector, whose candidates on a noisy featureless image "
                        "score up to 0.35; 0.1 with 3PT-D; 0.25 with the cell detector, its "
                        "network's boxes: the templates detector's detections it adds keep "
                        "0.4)")
    p.add_argument("--max-detections", type=int_at_least(1), default=100, help="per image")
    p.add_argument("--cache-dir", type=pathlib.Path, default=DEFAULT_CACHE,
                   help="onboarding and compilation cache (env THREEPT_CACHE)")
    p.add_argument("--out", type=pathlib.Path, required=True, help="output folder")
    p.add_argument("--overlays", type=int_at_least(0), default=10,
                   help="overlay PNGs written (0: none)")


def refiner_options(p: argparse.ArgumentParser, what: str) -> None:
    """``--refiner contour|RUN`` (``what`` it does for the subcommand) and ``--refiner-step``."""
    p.add_argument("--refiner", type=pathlib.Path, default=None, metavar="contour|RUN",
                   help=f"'contour': the training-free contour refiner (colour statistics and "
                        f"edges along the projected outline, no network); or a 3PT-R training "
                        f"run (train/launch.py --config train/configs/refiner.py:tiny) or "
                        f"exported model: {what}; default: {describe('refiner')}; 'none': no "
                        f"refiner")
    p.add_argument("--refiner-step", type=checkpoint_step, default="best",
                   help="refiner checkpoint: best, latest or a step number")


def camera_options(p: argparse.ArgumentParser, per: str) -> None:
    """``--K`` / ``--cameras`` / ``--calibration-size``: the cameras, one per ``per`` (image,
    view), read by ``cameras_from_args``."""
    p.add_argument("--K", action="append", metavar="fx,fy,cx,cy",
                   help=f"intrinsics in pixels, one per {per} (or use --cameras)")
    p.add_argument("--cameras", type=pathlib.Path,
                   help=f'JSON list, one per {per}: {{"K": 3x3, "T_cam_world": 4x4 (mm, needed '
                        'for several views), "calibration_size": [W, H] (optional)}')
    p.add_argument("--calibration-size", type=int_at_least(1), nargs=2, metavar=("W", "H"),
                   help=f"image size the intrinsics were calibrated at, when the {per}s are "
                        "resized: K is rescaled to each image (pixel centres at integers: "
                        "cx' = (cx + 0.5) * sx - 0.5)")


def detector_kind(args) -> str:
    """``templates``, ``3pt`` or ``cell``: ``--detector``, else the kind of the run
    ``--workdir`` names (:func:`infer.api.default_detector`), else ``templates``."""
    return args.detector or default_detector(args.workdir)


def default_score_threshold(args) -> None:
    """Set ``--score-threshold`` when not given to the default of the command's detector (the
    two probabilities are calibrated on different data)."""
    if hasattr(args, "score_threshold") and args.score_threshold is None:
        args.score_threshold = SCORE_THRESHOLDS[detector_kind(args)]


def load_models(args, detector: bool = True):
    """The command's models (``infer.load``), with the onboarding and compilation caches: the
    detector of ``--detector`` (when ``detector``): the training-free templates detector by
    default, 3PT-D with ``--detector 3pt`` or ``--workdir`` (default the shipped network); and,
    when the command has the option, the refiner of ``--refiner`` (default
    :func:`infer.shipped.default_refiner`: the shipped 3PT-R when one ships, else the contour
    refiner; ``none``: no refiner)."""
    import jax

    jax.config.update("jax_compilation_cache_dir", str(args.cache_dir / "jax"))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
    refining = hasattr(args, "refiner") and str(args.refiner) != "none"
    refiner = (args.refiner or default_refiner()) if refining else None
    kind = detector_kind(args)
    if kind == "templates" and args.workdir is not None:
        raise ValueError("--workdir is a detector run; --detector templates needs no network: "
                         "drop one of them")
    if getattr(args, "templates_score", None) is not None and kind == "3pt":
        raise ValueError("--templates-score calibrates the templates detector (alone or in "
                         "the cell detector); 3PT-D scores with its network: drop it or pass "
                         "--detector templates")
    if getattr(args, "templates_verifier", False) and kind == "3pt":
        raise ValueError("--templates-verifier checks the templates detector's candidates "
                         "(alone or in the cell detector); 3PT-D scores with its network: drop "
                         "it or pass --detector templates")
    if not detector and refiner is None:
        raise ValueError("no model to load: --refiner none leaves this command nothing to run; "
                         "drop it (the default refiner) or pass --refiner contour|RUN")
    workdir = None
    if detector and kind == "3pt":
        workdir = args.workdir or shipped("detector")
    elif detector and kind == "cell":
        workdir = args.workdir
    models = load(workdir, args.step, refiner=refiner,
                  refiner_step=getattr(args, "refiner_step", "best"), cache_dir=args.cache_dir,
                  num_templates=args.num_templates, detector=kind if detector else None,
                  templates_score=args.templates_score if detector else None,
                  templates_verifier=getattr(args, "templates_verifier", None)
                  if detector else None)
    return models if refining else dataclasses.replace(models, refiner=None)


def detector_options(args) -> dict:
    options = dict(depth_range=args.depth_range, score_threshold=args.score_threshold,
                   max_detections=args.max_detections)
    if args.num_scales is not None:
        options["num_scales"] = args.num_scales
    return options


def read_rgb(path) -> np.ndarray:
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise FileNotFoundError(f"cannot read image {path}")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def cameras_from_args(args, n: int) -> list[Camera]:
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
