"""Tracking with the contour refiner (issue 36): frames per second and drift on a rendered path.

A T-LESS part (``../shared/meshes``, grey, no texture) is rendered by the project's rasterizer
(headlight shading) over a cluttered colour background (blurred colour noise, a new noise of
sensor grain per frame), 640 x 480, while the camera circles it (``--deg-per-frame`` degrees
of azimuth per frame, elevation swinging between 25 and 45 degrees, distance 400-460 mm).
``infer.track`` follows it from the first frame's truth moved by 3 degrees / 5 mm, each frame
refined from the previous frame's pose by the contour refiner of ``--settings``:

* ``default``: :class:`~threept_jax.pipeline.contour.ContourSettings` as ``--refiner contour``
  uses them (four coarse-to-fine levels, 16 Gauss-Newton iterations);
* ``fine``: only the two finest levels, 2 iterations each (4 Gauss-Newton steps): what a
  tracker could use when frame-to-frame motion is small.

Printed per setting: the first frame (compilation) apart, warm frames per second (median and
90th percentile latency of ``infer.track``'s frames), median and final rotation / translation
error against the truth, frames lost (error over 10 degrees or 10 % of the diameter), and the
ratio of the median errors to the reference in the same process: the pose held at the start
(no tracking). The ``cv2.rapid`` rows run OpenCV contrib's GOS / OLS / RAPID trackers on the same
frames from the same start, one ``compute`` per frame, as a tracker runs.

    python bench/contour_track.py [--frames 120] [--obj 5] [--settings default fine]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import sys
import time

import cv2
import numpy as np
from tqdm import tqdm

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import infer  # noqa: E402
from bench.contour_refine import jitter  # noqa: E402
from infer.refine import refine_objects  # noqa: E402
from threept_jax.geometry.camera import look_at  # noqa: E402
from threept_jax.pipeline.contour import ContourSettings  # noqa: E402
from threept_jax.render.mesh import to_raster_mesh  # noqa: E402
from threept_jax.render.raster import render  # noqa: E402

HW = (480, 640)
K = np.array([[600.0, 0, 319.5], [0, 600.0, 239.5], [0, 0, 1]])
SHARED = ROOT.parent / "shared" / "meshes" / "bop" / "tless" / "models"
LOST_DEG, LOST_DIAMETER = 10.0, 0.1


def sequence(mesh, frames: int, deg_per_frame: float, seed: int = 0):
    """(uint8 frames [F, H, W, 3], true T_cam_obj [F, 4, 4]) of the camera path."""
    rng = np.random.default_rng(seed)
    noise = rng.random((HW[0] // 16, HW[1] // 16, 3)).astype(np.float32)
    background = cv2.resize(noise, HW[::-1], interpolation=cv2.INTER_CUBIC)
    background = np.clip(0.25 + 0.5 * cv2.GaussianBlur(background, (0, 0), 3), 0, 1)
    center = np.asarray(mesh.center, np.float64)
    rm = to_raster_mesh(mesh)
    images, poses = [], []
    for f in range(frames):
        az = np.radians(deg_per_frame * f)
        el = np.radians(35 + 10 * np.sin(2 * np.pi * f / 90))
        dist = 430 + 30 * np.sin(2 * np.pi * f / 70)
        eye = center + dist * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az),
                                        np.sin(el)])
        T = np.asarray(look_at(eye, center, (0, 0, 1.0)), np.float64)
        out = render(rm, T.astype(np.float32), K.astype(np.float32), HW, ("rgb", "mask"),
                     ambient=0.5)
        grain = 0.02 * rng.standard_normal(HW + (3,))
        img = np.where(np.asarray(out["mask"])[..., None], np.asarray(out["rgb"]), background)
        images.append(np.round(np.clip(img + grain, 0, 1) * 255).astype(np.uint8))
        poses.append(T)
    return np.stack(images), np.stack(poses)


def errors(T, T_gt):
    dR = T[:3, :3].T @ T_gt[:3, :3]
    return (float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))),
            float(np.linalg.norm(T[:3, 3] - T_gt[:3, 3])))


def summarise(name, poses, truth, latencies, diameter, held):
    err = np.array([errors(p, t) for p, t in zip(poses, truth)])
    lost = int(np.sum((err[:, 0] > LOST_DEG) | (err[:, 1] > LOST_DIAMETER * diameter)))
    warm = np.asarray(latencies[1:])
    row = {"name": name, "cold_s": float(latencies[0]),
           "fps": float(1 / np.median(warm)), "median_ms": float(1e3 * np.median(warm)),
           "p90_ms": float(1e3 * np.percentile(warm, 90)),
           "rot_median": float(np.median(err[:, 0])), "trans_median": float(np.median(err[:, 1])),
           "rot_final": float(err[-1, 0]), "trans_final": float(err[-1, 1]), "lost": lost,
           "per_frame": err.round(2).tolist()}
    if held is not None:
        row["rot_ratio"] = row["rot_median"] / held["rot_median"]
        row["trans_ratio"] = row["trans_median"] / held["trans_median"]
    return row


def track_contour(settings, frames, truth, objects, start):
    models = dataclasses.replace(infer.load(None, refiner="contour", cache_dir=None),
                                 refiner=settings)
    poses, latencies = [], []
    tracked = infer.track(frames, [K], objects, models, init=[(objects[0].obj_id, start)],
                          min_score=-np.inf)
    for frame in tqdm(tracked, total=len(frames), desc="track", leave=False):
        poses.append(frame.poses[0].T_world_obj)
        latencies.append(frame.latency_s)
    return poses, latencies


def track_opencv(kind, frames, mesh, start):
    from threept_jax.render.mesh import prepare_mesh

    small = prepare_mesh(mesh, max_faces=2048, texture_size=None)
    pts = np.ascontiguousarray(small.vertices, np.float32)
    tris = np.ascontiguousarray(small.faces, np.int32)
    tracker = {"rapid": cv2.rapid.Rapid, "ols": cv2.rapid.OLSTracker,
               "gos": cv2.rapid.GOSTracker}[kind].create(pts, tris)
    rvec = cv2.Rodrigues(start[:3, :3])[0]
    tvec = start[:3, 3:4].copy()
    poses, latencies = [], []
    for img in frames:
        t = time.perf_counter()
        try:
            _, r, tv = tracker.compute(cv2.cvtColor(img, cv2.COLOR_RGB2BGR), 100, 20, K, rvec,
                                       tvec)
            if np.all(np.isfinite(r)) and np.all(np.isfinite(tv)):
                rvec, tvec = r, tv
        except cv2.error:
            pass
        latencies.append(time.perf_counter() - t)
        T = np.eye(4)
        T[:3, :3] = cv2.Rodrigues(np.asarray(rvec, np.float64))[0]
        T[:3, 3] = np.asarray(tvec, np.float64).ravel()
        poses.append(T)
    return poses, latencies


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--frames", type=int, default=120)
    p.add_argument("--obj", type=int, default=5, help="T-LESS object id")
    p.add_argument("--deg-per-frame", type=float, default=1.5,
                   help="camera azimuth step (1.5 deg: ~11 mm of camera motion per frame)")
    p.add_argument("--settings", nargs="+", default=["default", "fine"],
                   choices=["default", "fine"])
    p.add_argument("--no-opencv", action="store_true")
    p.add_argument("--out", type=pathlib.Path, default=None, help="JSON of the rows")
    args = p.parse_args(argv)

    (obj,) = refine_objects({args.obj: SHARED / f"obj_{args.obj:06d}.ply"})
    t = time.perf_counter()
    frames, truth = sequence(obj.mesh, args.frames, args.deg_per_frame)
    print(f"{args.frames} frames of T-LESS obj {args.obj} rendered in "
          f"{time.perf_counter() - t:.1f} s", flush=True)
    diameter = float(obj.mesh.diameter)
    # The first frame's truth turned by 3 degrees about its centre and moved by 5 mm.
    start = jitter(truth[0], np.asarray(obj.mesh.center, np.float64), 3.0, 5.0,
                   np.random.default_rng(1))
    held = summarise("held at the start (reference)", [start] * len(truth), truth,
                     [0.0] * len(truth), diameter, None)
    rows = [held]
    for name in args.settings:
        settings = (ContourSettings() if name == "default"
                    else ContourSettings(scales=(0.01, 0.005), iterations=2))
        poses, lat = track_contour(settings, frames, truth, [obj], start)
        rows.append(summarise(f"contour ({name})", poses, truth, lat, diameter, held))
    if not args.no_opencv:
        for kind in ("gos", "ols", "rapid"):
            poses, lat = track_opencv(kind, frames, obj.mesh, start)
            rows.append(summarise(f"cv2.rapid {kind}", poses, truth, lat, diameter, held))

    print(f"\n{args.frames} frames, 640x480, 1 view, 1 object (diameter {diameter:.0f} mm); "
          f"lost: error > {LOST_DEG:g} deg or > {LOST_DIAMETER:g} diameter")
    print("| tracker | cold first frame s | warm fps (median ms, p90 ms) | median rot deg "
          "(ratio) | median trans mm (ratio) | final rot / trans | frames lost |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        ratio = (f" ({r['rot_ratio']:.2f})", f" ({r['trans_ratio']:.2f})") if "rot_ratio" in r \
            else ("", "")
        speed = ("-" if r is held else
                 f"{r['fps']:.1f} ({r['median_ms']:.1f}, {r['p90_ms']:.1f})")
        cold = "-" if r is held else f"{r['cold_s']:.2f}"
        print(f"| {r['name']} | {cold} | {speed} | {r['rot_median']:.2f}{ratio[0]} | "
              f"{r['trans_median']:.1f}{ratio[1]} | {r['rot_final']:.1f} / "
              f"{r['trans_final']:.1f} | {r['lost']} |")
    if args.out:
        args.out.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
