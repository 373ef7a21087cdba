"""``python -m infer track``: track objects through an image sequence or a video, refining every
frame (the contour refiner by default, or a 3PT-R run).

Each frame refines every tracked instance from its pose in the previous frame
(:func:`infer.track`); the first frame starts from ``--init`` poses, or from a detection
(``--workdir``, a 3PT-D run; the shipped detector by default) when there are none. With a
detector (loaded without ``--init``, with ``--min-score`` or ``--workdir``), a frame where an instance's
refiner score falls under ``--min-score``, or where nothing is tracked, runs detection, object
generation and refinement again (:func:`infer.run_scene`).

Writes ``--out/track.jsonl``, one line per frame::

    {"index": 0, "redetected": false, "compiled": true, "latency_s": 0.81,
     "instances": [{"obj_id": 1, "T_world_obj": 4x4 (mm), "T_world_obj_initial": 4x4,
                    "score": 2.3}]}

``T_world_obj_initial`` is the pose the frame's refinement started from (the previous frame's,
``--init``'s on frame 0, or object generation's after a detection); ``score`` the refiner's
score logit (higher is better; not calibrated across objects); ``compiled``: the frame traced
the refinement loop (a new instance-count bin or image size). With one view the world frame is
the camera's. Overlays of the first ``--overlays`` frames show the tracked contours (the
refiner's masks) and the projected box of each pose. The summary printed at the end splits the
latency of warm frames from frame 0 and from frames that re-detected or compiled.
"""

from __future__ import annotations

import argparse
import itertools
import json
import pathlib
import re
from collections.abc import Iterator

import cv2
import numpy as np

from infer.api import prepare_views, track
from infer.options import (
    camera_options,
    cameras_from_args,
    common_options,
    detector_options,
    int_at_least,
    load_models,
    number_in,
    parse_meshes,
    read_rgb,
    refiner_options,
)
from threept_jax.geometry.validate import validate_rigid

#: Image files ``--frames`` reads (by suffix, case-insensitive).
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")


def add_track_parser(sub) -> argparse.ArgumentParser:
    """Register ``track`` on the ``python -m infer`` subparsers ``sub``."""
    p = sub.add_parser("track", help="track objects through image sequences or a video "
                                     "(refined every frame)",
                       formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    common_options(p, workdir_when="without --init (the first frame is detected) and for re-detection "
                            "(--min-score, or nothing tracked)")
    refiner_options(p, "refine every tracked object in every frame")
    p.add_argument("--mesh", action="append", required=True, metavar="ID=PATH",
                   help="an object to track (repeat): integer id and mesh file")
    p.add_argument("--units", default="mm", choices=("mm", "cm", "m", "in"),
                   help="length unit of the mesh files")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--frames", type=pathlib.Path, nargs="+", metavar="DIR",
                     help="folders of frames, one per camera, the same number of images in "
                          "each, in natural name order (frame2 before frame10)")
    src.add_argument("--video", type=pathlib.Path, metavar="FILE",
                     help="a video file (one view; any format OpenCV reads)")
    p.add_argument("--max-frames", type=int_at_least(1), default=None,
                   help="stop after this many frames")
    camera_options(p, "view")
    p.add_argument("--init", type=pathlib.Path, metavar="FILE",
                   help='initial poses: JSON list of {"obj_id": int, "T_world_obj": 4x4 (mm; '
                        'the camera frame for one view)}; without it the first frame is '
                        "detected (--workdir)")
    p.add_argument("--min-score", type=number_in(np.isfinite, "a finite number"), default=None,
                   help="re-detect (needs --workdir) when a tracked instance's refiner score "
                        "falls under this; default: never. The contour refiner's score is in "
                        "[0, 1] (on held-out cell scenes good poses score ~0.65, wrong "
                        "detections ~0.15: 0.3 is a start); a 3PT-R's is an uncalibrated logit "
                        "(pick a threshold from the scores of track.jsonl)")
    return p


def _natural_key(path: pathlib.Path):
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", path.name)]


def frame_files(dirs) -> list[list[pathlib.Path]]:
    """[V][F] image files of ``--frames DIR ...``; ValueError when a folder is empty or the
    folders hold different numbers of images."""
    views = []
    for d in dirs:
        if not d.is_dir():
            raise FileNotFoundError(f"--frames {d}: no such folder")
        files = sorted((f for f in d.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES),
                       key=_natural_key)
        if not files:
            raise ValueError(f"--frames {d} holds no image file ({', '.join(IMAGE_SUFFIXES)})")
        views.append(files)
    counts = {len(f) for f in views}
    if len(counts) > 1:
        listed = ", ".join(f"{d}: {len(f)}" for d, f in zip(dirs, views))
        raise ValueError(f"--frames folders hold different numbers of images ({listed}): give "
                         "one folder per camera with one image per frame in each")
    return views


def _video_frames(cap: cv2.VideoCapture) -> Iterator[list[np.ndarray]]:
    while True:
        ok, bgr = cap.read()
        if not ok:
            return
        yield [cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)]


def open_frames(args) -> tuple[Iterator[list[np.ndarray]], int | None, int]:
    """(frames: an iterator of V RGB images per frame, read lazily, the frame count when known,
    V) of ``--frames`` or ``--video``."""
    if args.video is not None:
        if not args.video.is_file():
            raise FileNotFoundError(f"--video {args.video}: no such file")
        cap = cv2.VideoCapture(str(args.video))
        if not cap.isOpened():
            raise ValueError(f"--video {args.video}: OpenCV cannot open it (not a video, or a "
                             "codec this OpenCV build lacks); convert it, e.g. ffmpeg -i "
                             f"{args.video.name} -c:v libx264 out.mp4, or extract frames to a "
                             "folder for --frames")
        count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        return _video_frames(cap), count if count > 0 else None, 1
    views = frame_files(args.frames)
    frames = ([read_rgb(v[i]) for v in views] for i in range(len(views[0])))
    return frames, len(views[0]), len(views)


def read_init(path: pathlib.Path, obj_ids) -> list[tuple[int, np.ndarray]]:
    """``--init``: [(obj_id, T_world_obj [4, 4])] checked against the ``--mesh`` ids."""
    try:
        entries = json.loads(path.read_text())
    except FileNotFoundError:
        raise FileNotFoundError(f"--init {path}: no such file") from None
    except json.JSONDecodeError as e:
        raise ValueError(f"--init {path} is not valid JSON: {e}") from None
    if not isinstance(entries, list) or not entries:
        raise ValueError(f'--init {path} must hold a non-empty JSON list of {{"obj_id": int, '
                         '"T_world_obj": 4x4}')
    out = []
    for i, e in enumerate(entries):
        where = f"--init {path} entry {i}"
        if not isinstance(e, dict) or not {"obj_id", "T_world_obj"} <= set(e):
            raise ValueError(f'{where} must be {{"obj_id": int, "T_world_obj": 4x4}}, got {e}')
        if not isinstance(e["obj_id"], int) or isinstance(e["obj_id"], bool):
            raise ValueError(f"{where}: obj_id must be an integer, got {e['obj_id']!r}")
        if e["obj_id"] not in obj_ids:
            raise ValueError(f"{where}: object {e['obj_id']} has no mesh; add --mesh "
                             f"{e['obj_id']}=PATH (given: {sorted(obj_ids)})")
        out.append((e["obj_id"], validate_rigid(e["T_world_obj"], f"{where} T_world_obj")))
    return out


def _overlay(images, cameras, Ks, objects, poses) -> list[np.ndarray]:
    """One overlay per view: each pose's refiner-mask contour and projected box."""
    from infer.bop_runner import model_box
    from infer.detect import Detection
    from infer.visualize import draw_detections

    meshes = {o.obj_id: o.mesh for o in objects}
    out = []
    for v, (img, cam, K) in enumerate(zip(images, cameras, Ks)):
        T_cw = np.eye(4) if cam.T_cam_world is None else np.asarray(cam.T_cam_world)
        drawn, masks = [], []
        for p in poses:
            T = T_cw @ p.T_world_obj
            mesh = meshes[p.obj_id]
            if (T[:3, :3] @ mesh.center + T[:3, 3])[2] <= 0:  # behind this camera
                continue
            box = model_box(mesh.vertices, T, K)
            drawn.append(Detection(p.obj_id, box, p.score, T[None], np.zeros(1), np.zeros(0)))
            masks.append(p.masks.get(v, np.zeros(img.shape[:2], bool)))
        out.append(draw_detections(img, drawn, masks))
    return out


def summarize(records: list[dict]) -> dict:
    """Latency summary of ``track.jsonl`` records: warm frames (after frame 0, no
    re-detection, no compilation) apart from frame 0 and the re-detecting or compiling ones."""
    def stats(rows):
        t = np.array([r["latency_s"] for r in rows], float)
        return {"frames": len(t), "median_s": float(np.median(t)) if len(t) else None,
                "p90_s": float(np.percentile(t, 90)) if len(t) else None}

    later = records[1:]
    return {
        "frames": len(records),
        "redetections": sum(r["redetected"] for r in records),
        "first_frame_s": records[0]["latency_s"] if records else None,
        "warm": stats([r for r in later if not r["redetected"] and not r["compiled"]]),
        "redetected": stats([r for r in later if r["redetected"]]),
        "compiled": stats([r for r in later if r["compiled"] and not r["redetected"]]),
    }


def _print_summary(s: dict, path: pathlib.Path) -> None:
    print(f"{s['frames']} frames, {s['redetections']} re-detections -> {path}")
    if not s["frames"]:
        return
    w = s["warm"]
    print(f"latency, warm frames ({w['frames']}): " + (
        f"median {w['median_s']:.3f} s, p90 {w['p90_s']:.3f} s" if w["frames"] else "none"))
    parts = [f"frame 0 {s['first_frame_s']:.3f} s"]
    for key, what in (("redetected", "re-detecting"), ("compiled", "compiling")):
        if s[key]["frames"]:
            parts.append(f"{s[key]['frames']} later {what} frames: median "
                         f"{s[key]['median_s']:.3f} s")
    print("apart: " + "; ".join(parts))


def run_track(args) -> dict:
    """Run ``python -m infer track`` (module docstring); returns the printed summary."""
    from tqdm import tqdm

    from infer.refine import refine_objects

    meshes = parse_meshes(args.mesh)
    frames, count, V = open_frames(args)
    if args.max_frames is not None:
        frames = itertools.islice(frames, args.max_frames)
        count = args.max_frames if count is None else min(count, args.max_frames)
    if args.cameras is None and len(args.K or ()) != V:
        raise ValueError(f"{len(args.K or ())} --K for {V} view(s): give one --K fx,fy,cx,cy "
                         "per view or --cameras FILE")
    cameras = cameras_from_args(args, V)
    if V > 1 and any(c.T_cam_world is None for c in cameras):
        raise ValueError(f"{V} views need each camera's pose: --cameras FILE with "
                         '"T_cam_world" (4x4, world -> camera, mm) for every view')
    first = next(frames, None)
    if first is None:
        raise ValueError(f"--video {args.video}: no frame could be read")
    Ks, _ = prepare_views(first, cameras)  # K against the frame size, before the slow work
    init = None if args.init is None else read_init(args.init, set(meshes))
    if str(args.refiner) == "none":
        raise ValueError("track refines every frame: drop --refiner none (the default refiner) "
                         "or pass --refiner contour|RUN")
    # The detector finds the first frame's objects (no --init) and re-detects (--min-score).
    detecting = init is None or args.min_score is not None or args.workdir is not None
    models = load_models(args, detector=detecting)
    objects = (models.onboard(meshes, units=args.units) if models.detector is not None
               else refine_objects(meshes, units=args.units))
    min_score = -np.inf if args.min_score is None else args.min_score
    refiner = models.scene_refiner(objects)

    shown: list = []

    def remembered():
        for images in itertools.chain([first], frames):
            shown[:] = images
            yield images

    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "track.jsonl"
    records, traces = [], refiner.traces
    tracked = track(remembered(), cameras, objects, models, init, min_score=min_score,
                    **detector_options(args))
    with path.open("w") as f:
        for fr in tqdm(tracked, total=count, desc="frames", unit="frame", dynamic_ncols=True):
            compiled, traces = refiner.traces > traces, refiner.traces
            rec = {"index": fr.index, "redetected": fr.redetected, "compiled": compiled,
                   "latency_s": fr.latency_s,
                   "instances": [{"obj_id": p.obj_id, "T_world_obj": p.T_world_obj.tolist(),
                                  "T_world_obj_initial": p.history[0].tolist(),
                                  "score": p.score} for p in fr.poses]}
            f.write(json.dumps(rec) + "\n")
            f.flush()
            records.append(rec)
            if fr.index < args.overlays:
                for v, canvas in enumerate(_overlay(shown, cameras, Ks, objects, fr.poses)):
                    cv2.imwrite(str(args.out / f"overlay_{fr.index:05d}_v{v}.png"),
                                cv2.cvtColor(canvas, cv2.COLOR_RGB2BGR))
    summary = summarize(records)
    _print_summary(summary, path)
    return summary
