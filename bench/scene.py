"""Benchmark of end-to-end inference latency by stage: detection + object generation, then
render-and-compare refinement (cold, warm, per iteration), for N objects in V views.

Untrained networks at the CPU sizes (only shapes matter for time): the detector of
``train/configs/detector.py:tiny`` ("tiny/16", 128 px tiles, 32 px renders) and the refiner of
``train/configs/refiner.py:<--refiner-config>`` with its ``RefineSettings`` (tiny and cpu:
64 matches, 1024-face renders, no sub-pixel fit). The scene: 640x480 images of a random
blocky texture, V cameras 900 mm from a common point (``look_at``, 50 degrees elevation,
azimuths 120 degrees apart), the T-LESS CAD models of ``../shared/meshes/bop/tless/models``
(object ids cycled) placed on a grid around that point.

Per (objects N, views V), all warm times are medians of ``--repeats`` calls:

* detection + object generation: ``infer.scene.find_instances(with_masks=False)`` (one
  pan-and-scan pass per query object and view; for V > 1 the multi-view fusion too). The
  detector holds N query objects (one T-LESS mesh onboarded with the inference bank, repeated
  under the N ids: the detection cost does not depend on what the renders show) and keeps the
  N best detections per view (``score_threshold=0``): an untrained detector's detection count
  is arbitrary, so the table says how many it found and fused.
* refinement: ``infer.refine.SceneRefiner`` called directly with exactly N instances of K = 8
  hypotheses each (random rotations, translations around the instance's grid point): cold
  (first call: compilation included) and warm for the full loop (3 iterations), and per
  iteration as DIFFERENCES of warm times of loops with ``LoopSettings(iterations=1, 2, 3)``
  (one SceneRefiner each, timed in interleaved rounds): iter 1 = t(1) (so it carries the
  per-call overhead: padding, host transfer, mask pasting), iter 2 = t(2) - t(1), iter 3 =
  t(3) - t(2).
* renders per call: N x (8 + 4 + 2) x V at the default halving; the loop pads N to a bin
  (``pad_to_bin``: 5 -> 8, 20 -> 32) and computes the padding too, so ms per render divides the
  warm time by the padded count. If time follows renders (objects x views) rather than Python
  loops, ms per render stays flat across rows.

A last line compares the warm refinement time of the largest (N, V) with the smallest against
their renders ratios.

    python bench/scene.py [--objects 1 5 20] [--views 1 3] [--repeats 3]
        [--refiner-config tiny|cpu] [--skip-iterations]
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import pathlib
import statistics
import sys
import time
import warnings

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import jax  # noqa: E402
from flax import nnx  # noqa: E402
from flops import cold_and_warm  # noqa: E402

from infer.detect import SceneDetector  # noqa: E402
from infer.onboarding import ONBOARD_TEMPLATES, Onboarder  # noqa: E402
from infer.refine import NUM_HYPOTHESES, SceneRefiner, refine_objects  # noqa: E402
from infer.scene import find_instances  # noqa: E402
from threept_jax.geometry.camera import look_at  # noqa: E402
from threept_jax.geometry.rotations import random_rotations  # noqa: E402
from threept_jax.models.detector import Detector  # noqa: E402
from threept_jax.models.refiner import Refiner  # noqa: E402
from threept_jax.pipeline.refine_loop import LoopSettings, pad_to_bin  # noqa: E402
from train.configs import detector as detector_configs  # noqa: E402
from train.configs import refiner as refiner_configs  # noqa: E402
from train.run_config import model_config, refine_settings  # noqa: E402

MODELS = ROOT.parent / "shared" / "meshes" / "bop" / "tless" / "models"
IMAGE_W, IMAGE_H = 640, 480
DISTANCE_MM = 900.0
SPACING_MM = 100.0


def mesh_paths(n: int) -> dict[int, pathlib.Path]:
    """The first n object ids of the T-LESS models present, cycled when there are fewer; the
    ids of repeats are offset by 1000 so that every instance has its own object."""
    paths = sorted(MODELS.glob("obj_*.ply"))
    if not paths:
        raise SystemExit(f"error: no obj_*.ply meshes in {MODELS}")
    out = {}
    for i in range(n):
        p = paths[i % len(paths)]
        out[int(p.stem.split("_")[1]) + 1000 * (i // len(paths))] = p
    return out


def cameras(num_views: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ks [V, 3, 3], T_cam_world [V, 4, 4] of cameras around the origin, and images [V, H, W, 3]
    uint8 (random 8x8-pixel blocks, a texture with edges at every scale of the crops)."""
    f = 1.2 * IMAGE_W
    K = np.array([[f, 0, (IMAGE_W - 1) / 2], [0, f, (IMAGE_H - 1) / 2], [0, 0, 1]], np.float32)
    elevation = np.radians(50.0)
    T = []
    for v in range(num_views):
        azimuth = 2 * np.pi * v / max(num_views, 1)
        eye = DISTANCE_MM * np.array([np.cos(elevation) * np.cos(azimuth),
                                      np.cos(elevation) * np.sin(azimuth), np.sin(elevation)])
        T.append(np.asarray(look_at(eye, np.zeros(3)), np.float32))
    rng = np.random.default_rng(0)
    blocks = rng.integers(0, 256, (num_views, IMAGE_H // 8, IMAGE_W // 8, 3), dtype=np.uint8)
    images = blocks.repeat(8, axis=1).repeat(8, axis=2)
    return np.tile(K, (num_views, 1, 1)), np.stack(T), images


def hypotheses(n: int, rng: np.random.Generator) -> list[np.ndarray]:
    """n instances of K = 8 hypotheses [8, 4, 4] (world frame, mm): random rotations, the
    translation 10 mm around the instance's point on a grid in the z = 0 plane."""
    cols = int(np.ceil(np.sqrt(n)))
    out = []
    for i in range(n):
        centre = SPACING_MM * np.array([i % cols - (cols - 1) / 2, i // cols - (cols - 1) / 2, 0])
        T = np.tile(np.eye(4), (NUM_HYPOTHESES, 1, 1))
        T[:, :3, :3] = random_rotations(rng, NUM_HYPOTHESES)
        T[:, :3, 3] = centre + rng.normal(0, 10.0, (NUM_HYPOTHESES, 3))
        out.append(T.astype(np.float32))
    return out


def seconds(call) -> float:
    t0 = time.perf_counter()
    call()
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--objects", type=int, nargs="+", default=[1, 5, 20])
    ap.add_argument("--views", type=int, nargs="+", default=[1, 3])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--refiner-config", default="tiny", choices=["tiny", "cpu"])
    ap.add_argument("--skip-iterations", action="store_true",
                    help="time the full loop only (no per-iteration differences)")
    args = ap.parse_args()
    if min(args.objects) < 1 or min(args.views) < 1 or args.repeats < 1:
        ap.error("--objects, --views and --repeats must be >= 1")

    dcfg = model_config(detector_configs.get_config("tiny"))
    rconfig = refiner_configs.get_config(args.refiner_config)
    rcfg, settings = model_config(rconfig), refine_settings(rconfig)
    detector = Detector(dcfg, rngs=nnx.Rngs(0))
    refiner = Refiner(rcfg, rngs=nnx.Rngs(0))

    n_max = max(args.objects)
    paths = mesh_paths(n_max)
    ids = list(paths)
    t0 = time.perf_counter()
    with warnings.catch_warnings():  # T-LESS's duplicate faces and open meshes: not timed here
        warnings.simplefilter("ignore", UserWarning)
        objects = refine_objects(paths)
    onboarder = Onboarder(detector, dcfg, "bench@0", cache_dir=None,
                          num_templates=ONBOARD_TEMPLATES)
    one = onboarder.onboard(ids[0], objects[0].mesh)
    onboarded = [dataclasses.replace(one, obj_id=i) for i in ids]
    schedule = LoopSettings().schedule(NUM_HYPOTHESES)
    settings_by_iters = [3] if args.skip_iterations else [1, 2, 3]
    refiners = {it: SceneRefiner(refiner, rcfg, settings, objects, LoopSettings(iterations=it))
                for it in settings_by_iters}
    setup_s = time.perf_counter() - t0

    device = jax.devices()[0]
    print(f"device: {device.platform} ({device.device_kind}), {jax.device_count()} device(s)")
    print(f"detector: {dcfg.variant} at {dcfg.image_size} px tiles, {ONBOARD_TEMPLATES} "
          f"templates; refiner: {args.refiner_config} ({rcfg.variant}, {rcfg.crop_size} px "
          f"crops, {settings.num_matches} matches, {settings.max_faces} faces, dtype "
          f"{np.dtype(rcfg.dtype).name}); K = {NUM_HYPOTHESES} -> {schedule}")
    print(f"scene: {IMAGE_W}x{IMAGE_H} images, T-LESS objects {ids[:n_max]}; setup (meshes, "
          f"onboarding, {len(refiners)} refiners) {setup_s:.1f} s; warm = median of "
          f"{args.repeats}")
    if not args.skip_iterations:
        print("per-iteration figures are DIFFERENCES of warm loops with 1, 2, 3 iterations "
              "(iter 1 = t(1), with the per-call overhead)")
    print(f"{'N':>3} {'V':>2} {'dets/view':>9} {'fused':>5} {'detect s':>9} | {'refine cold':>11} "
          f"{'warm s':>7} {'iter1':>6} {'iter2':>6} {'iter3':>6} | {'renders':>7} "
          f"{'(padded)':>8} {'ms/render':>9}")
    warm_of, renders_of = {}, {}
    rng = np.random.default_rng(1)
    for V in args.views:
        Ks, T_cw, images = cameras(V)
        for n in args.objects:
            det = SceneDetector(detector, dcfg, onboarded[:n], score_threshold=0.0,
                                max_detections=n)
            detect = functools.partial(find_instances, det, list(images), list(Ks), T_cw,
                                       with_masks=False)
            found = detect()
            dets = [len(det.detect(im, k)) for im, k in zip(images, Ks)]
            det_warm = cold_and_warm(detect, args.repeats)[1]

            hyps = hypotheses(n, rng)
            call = {it: functools.partial(r, list(images), Ks, T_cw, ids[:n], hyps)
                    for it, r in refiners.items()}
            cold = seconds(call[3])
            for it in settings_by_iters[:-1]:
                call[it]()  # compilation
            # Rounds of 1, 2, 3 iterations in turn, so that load drifting on the shared cores
            # hits the three alike and their differences stay meaningful.
            runs = {it: [] for it in call}
            for _ in range(args.repeats):
                for it in settings_by_iters:
                    runs[it].append(seconds(call[it]))
            t_it = {it: statistics.median(r) for it, r in runs.items()}
            warm = t_it[3]
            iters = ([t_it[1], t_it[2] - t_it[1], t_it[3] - t_it[2]]
                     if len(t_it) == 3 else [float("nan")] * 3)
            renders = n * sum(schedule[:-1]) * V
            padded = pad_to_bin(n) * sum(schedule[:-1]) * V
            warm_of[n, V], renders_of[n, V] = warm, (renders, padded)
            print(f"{n:>3} {V:>2} {'/'.join(map(str, dets)):>9} {len(found):>5} "
                  f"{det_warm:>9.3f} | {cold:>11.1f} {warm:>7.3f} {iters[0]:>6.3f} "
                  f"{iters[1]:>6.3f} {iters[2]:>6.3f} | {renders:>7} {padded:>8} "
                  f"{1e3 * warm / padded:>9.2f}", flush=True)

    lo = min(warm_of, key=lambda k: renders_of[k][0])
    hi = max(warm_of, key=lambda k: renders_of[k][0])
    if hi != lo:
        (r_hi, p_hi), (r_lo, p_lo) = renders_of[hi], renders_of[lo]
        print(f"ratio (N={hi[0]}, V={hi[1]}) / (N={lo[0]}, V={lo[1]}): warm refinement "
              f"{warm_of[hi] / warm_of[lo]:.1f}x; renders {r_hi / r_lo:.0f}x "
              f"({p_hi / p_lo:.0f}x padded)")


if __name__ == "__main__":
    main()
