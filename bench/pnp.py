"""Benchmark: batched multi-view solve_pnp against a Python loop of OpenCV SQPnP.

Problems follow real use: objects of 50-300 mm at 300-1500 mm, three 640x480 cameras on a ring,
N correspondences per view with 1 px Gaussian noise (``--outliers`` adds gross outliers).
threept_jax solves the harder multi-view problem (all V views at once, robust LM) as one
jit(vmap(solve_pnp)) call over the batch, self-initialised (no initial pose) and, as in 3PT's
refiner, from an initial pose 10 degrees and 2% of the depth off. OpenCV solves the single-view
part (view 0) of the same problems with cv2.solvePnP(SOLVEPNP_SQPNP) in a Python loop. Both are
timed warm, best of ``--repeats``; the compile (cold) time is reported separately.

A second part measures robustness against OpenCV RANSAC on the same problems: ``--acc-batch``
fresh problems with 1 px noise and ``--acc-outliers`` (default 20%) gross outliers, solved by
``solve_pnp`` self-initialised on view 0 alone (the like-for-like single-view comparison) and on
all views, and by ``cv2.solvePnPRansac`` (SQPnP, 500 iterations, 3 px, confidence 0.999, the
settings of tests/geometry/test_pnp.py) on view 0. It prints the median and 99th-percentile
rotation and translation errors and the ratio of our median to RANSAC's.

    python bench/pnp.py [--batch 1024 --views 3 --points 200 --repeats 5 --outliers 0.0]
                        [--acc-batch 512 --acc-outliers 0.2]
"""

from __future__ import annotations

import argparse
import functools
import os
import time

import cv2
import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial.transform import Rotation

from threept_jax.geometry.pnp import solve_pnp


def _look_at(eye: np.ndarray) -> np.ndarray:
    z = -eye / np.linalg.norm(eye)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, -R @ eye
    return T


def make_problems(rng: np.random.Generator, batch: int, views: int, points: int, outliers: float):
    """Float32 arrays X [B, V, N, 3], uv [B, V, N, 2], K [B, V, 3, 3], T_cam_world [B, V, 4, 4],
    and float64 ground truth T_world_obj [B, 4, 4] plus a perturbed initial pose [B, 4, 4]."""
    K = np.array([[600.0, 0.0, 319.5], [0.0, 600.0, 239.5], [0.0, 0.0, 1.0]])
    X = np.empty((batch, views, points, 3))
    uv = np.empty((batch, views, points, 2))
    T_cw = np.empty((batch, views, 4, 4))
    T_wo = np.tile(np.eye(4), (batch, 1, 1))
    init = np.tile(np.eye(4), (batch, 1, 1))
    for b in range(batch):
        size, depth = rng.uniform(50, 300), rng.uniform(300, 1500)
        T_wo[b, :3, :3] = Rotation.random(random_state=rng).as_matrix()
        T_wo[b, :3, 3] = rng.uniform(-0.1, 0.1, 3) * size
        for v in range(views):
            az, el = 2 * np.pi * v / views + rng.uniform(-0.3, 0.3), rng.uniform(0.3, 0.8)
            T_cw[b, v] = _look_at(depth * np.array([np.cos(az) * np.cos(el),
                                                    np.sin(az) * np.cos(el), np.sin(el)]))
            X[b, v] = rng.uniform(-0.5, 0.5, (points, 3)) * size + rng.uniform(-0.2, 0.2, 3) * size
            T = T_cw[b, v] @ T_wo[b]
            p = (X[b, v] @ T[:3, :3].T + T[:3, 3]) @ K.T
            uv[b, v] = p[:, :2] / p[:, 2:] + rng.normal(scale=1.0, size=(points, 2))
            bad = rng.random(points) < outliers
            uv[b, v, bad] = rng.uniform([0, 0], [640, 480], (bad.sum(), 2))
        axis = rng.normal(size=3)
        dR = Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.radians(10.0)).as_matrix()
        shift = rng.normal(size=3)
        init[b, :3, :3] = dR @ T_wo[b, :3, :3]
        init[b, :3, 3] = T_wo[b, :3, 3] + shift / np.linalg.norm(shift) * 0.02 * depth
    Ks = np.broadcast_to(K, (batch, views, 3, 3))
    f32 = functools.partial(np.asarray, dtype=np.float32)
    return f32(X), f32(uv), f32(Ks), f32(T_cw), T_wo, f32(init)


def pose_errors(T: np.ndarray, T_gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-problem rotation error (degrees) and translation error (mm)."""
    rel = np.einsum("bji,bjk->bik", T[:, :3, :3], T_gt[:, :3, :3])
    rot = np.degrees(Rotation.from_matrix(rel).magnitude())
    trans = np.linalg.norm(T[:, :3, 3] - T_gt[:, :3, 3], axis=-1)
    return rot, trans


def errors(T: np.ndarray, T_gt: np.ndarray) -> tuple[float, float]:
    """Median rotation error (degrees) and translation error (mm) over the batch."""
    rot, trans = pose_errors(T, T_gt)
    return float(np.median(rot)), float(np.median(trans))


def time_jax(fn, args, repeats):
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    cold = time.perf_counter() - t0
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - t0)
    return out, cold, best


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--batch", type=int, default=1024)
    parser.add_argument("--views", type=int, default=3)
    parser.add_argument("--points", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--outliers", type=float, default=0.0, help="fraction of gross outliers")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--acc-batch", type=int, default=512,
                        help="problems of the accuracy comparison with OpenCV RANSAC (0 skips it)")
    parser.add_argument("--acc-outliers", type=float, default=0.2,
                        help="fraction of gross outliers in the accuracy comparison")
    a = parser.parse_args()

    affinity = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else "?"
    print(f"machine: {os.cpu_count()} cores ({affinity} usable), jax {jax.__version__} on "
          f"{jax.devices()[0].platform}, opencv {cv2.__version__}")
    print(f"problems: batch {a.batch}, {a.views} views x {a.points} points, 1 px noise, "
          f"{a.outliers:.0%} outliers, float32")
    X, uv, K, T_cw, T_wo, init = make_problems(np.random.default_rng(a.seed), a.batch, a.views,
                                               a.points, a.outliers)
    args = [jnp.asarray(v) for v in (X, uv, K, T_cw, np.ones(X.shape[:3], np.float32))]

    rows = []
    solve = jax.jit(jax.vmap(solve_pnp))
    for name, extra in [("solve_pnp, self-initialised", []),
                        ("solve_pnp, init 10 deg / 2% off", [jnp.asarray(init)])]:
        (T, info), cold, warm = time_jax(solve, args + extra, a.repeats)
        rot, trans = errors(np.asarray(T, np.float64), T_wo)
        conv = float(np.mean(np.asarray(info["converged"])))
        iters = np.asarray(info["iterations"])
        rows.append((name, a.batch / warm, warm, cold, rot, trans))
        print(f"  {name}: cold {cold:.2f} s, converged {conv:.1%}, LM steps mean "
              f"{iters.mean():.1f} max {iters.max()}")

    # OpenCV on view 0 (its single-view part); float64 copies made outside the timing.
    X0 = [np.ascontiguousarray(X[b, 0], np.float64) for b in range(a.batch)]
    uv0 = [np.ascontiguousarray(uv[b, 0], np.float64) for b in range(a.batch)]
    K0 = np.asarray(K[0, 0], np.float64)
    best, T_cv = np.inf, np.tile(np.eye(4), (a.batch, 1, 1))
    for _ in range(a.repeats):
        t0 = time.perf_counter()
        results = [cv2.solvePnP(X0[b], uv0[b], K0, None, flags=cv2.SOLVEPNP_SQPNP)
                   for b in range(a.batch)]
        best = min(best, time.perf_counter() - t0)
    for b, (_, rvec, tvec) in enumerate(results):
        T_cam = np.eye(4)
        T_cam[:3, :3], T_cam[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
        T_cv[b] = np.linalg.inv(T_cw[b, 0].astype(np.float64)) @ T_cam
    rot, trans = errors(T_cv, T_wo)
    cv_rate = a.batch / best
    rows.append(("cv2 SQPnP loop, view 0 only", cv_rate, best, 0.0, rot, trans))

    print(f"{'method':34s} {'problems/s':>11s} {'warm s':>8s} {'cold s':>8s} {'OpenCV/x':>9s} "
          f"{'rot deg':>8s} {'trans mm':>9s}")
    for name, rate, warm, cold, rot, trans in rows:
        print(f"{name:34s} {rate:11.0f} {warm:8.3f} {cold:8.2f} {cv_rate / rate:9.2f} "
              f"{rot:8.3f} {trans:9.3f}")

    if a.acc_batch:
        accuracy_vs_ransac(a)


def accuracy_vs_ransac(a) -> None:
    """Median errors of solve_pnp (view 0 alone, and all views) against cv2.solvePnPRansac."""
    print(f"\naccuracy vs OpenCV RANSAC: {a.acc_batch} new problems, {a.views} views x {a.points} "
          f"points, 1 px noise, {a.acc_outliers:.0%} gross outliers, both self-initialised")
    X, uv, K, T_cw, T_wo, _ = make_problems(np.random.default_rng(a.seed + 1), a.acc_batch,
                                            a.views, a.points, a.acc_outliers)
    solve = jax.jit(jax.vmap(solve_pnp))
    world_from_cam0 = np.linalg.inv(T_cw[:, 0].astype(np.float64))
    rows = []
    # Single view: view 0 in its own camera frame (T_cam_world = identity), lifted to the world.
    args1 = [jnp.asarray(v) for v in (X[:, :1], uv[:, :1], K[:, :1],
                                      np.broadcast_to(np.eye(4, dtype=np.float32),
                                                      (a.acc_batch, 1, 4, 4)),
                                      np.ones(X[:, :1].shape[:3], np.float32))]
    (T1, info1), cold1, warm1 = time_jax(solve, args1, 1)
    T1 = world_from_cam0 @ np.asarray(T1, np.float64)
    rows.append(("solve_pnp, view 0 only", T1, cold1, warm1,
                 float(np.mean(np.asarray(info1["converged"])))))
    argsv = [jnp.asarray(v) for v in (X, uv, K, T_cw, np.ones(X.shape[:3], np.float32))]
    (Tv, infov), coldv, warmv = time_jax(solve, argsv, 1)
    rows.append((f"solve_pnp, {a.views} views", np.asarray(Tv, np.float64), coldv, warmv,
                 float(np.mean(np.asarray(infov["converged"])))))
    cv2.setRNGSeed(0)
    K0 = np.asarray(K[0, 0], np.float64)
    T_cv, failed = np.tile(np.eye(4), (a.acc_batch, 1, 1)), 0
    t0 = time.perf_counter()
    for b in range(a.acc_batch):
        ok, rvec, tvec, _ = cv2.solvePnPRansac(
            X[b, 0].astype(np.float64), uv[b, 0].astype(np.float64), K0, None,
            iterationsCount=500, reprojectionError=3.0, confidence=0.999, flags=cv2.SOLVEPNP_SQPNP)
        failed += not ok
        T_cam = np.eye(4)  # a failure counts as the identity pose (a large error)
        if ok:
            T_cam[:3, :3], T_cam[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
        T_cv[b] = world_from_cam0[b] @ T_cam
    cv_time = time.perf_counter() - t0
    rows.append(("cv2.solvePnPRansac, view 0 only", T_cv, 0.0, cv_time, 1 - failed / a.acc_batch))

    rot_cv, trans_cv = (float(np.median(e)) for e in pose_errors(T_cv, T_wo))
    print(f"{'method':34s} {'rot deg':>8s} {'p99':>7s} {'trans mm':>9s} {'p99':>7s} "
          f"{'rot/RANSAC':>10s} {'trans/RANSAC':>12s} {'>5deg':>6s} {'ok':>6s} {'warm s':>7s} "
          f"{'cold s':>7s}")
    for name, T, cold, warm, ok in rows:
        rot, trans = pose_errors(T, T_wo)
        print(f"{name:34s} {np.median(rot):8.3f} {np.percentile(rot, 99):7.2f} "
              f"{np.median(trans):9.3f} {np.percentile(trans, 99):7.1f} "
              f"{np.median(rot) / rot_cv:10.2f} {np.median(trans) / trans_cv:12.2f} "
              f"{int(np.sum(rot > 5.0)):6d} {ok:6.1%} {warm:7.3f} {cold:7.2f}")
    print("(rot/trans: medians; >5deg: problems with a rotation error above 5 degrees; ok: share "
          "converged for solve_pnp, share returning a pose for RANSAC; warm: one run over the "
          "whole batch, RANSAC as a Python loop)")


if __name__ == "__main__":
    main()
