"""Benchmark of first calls (compilation included) against warm calls, for what a process pays
before its first answer: the JAX rasterizer at the shapes onboarding and refinement use, and a
second full-image detector of the same model (another ``infer`` run or adapt's test scenes after
its val scenes), which shares the first one's compiled function (docs/testing.md).

Rows, each a fresh shape in this process: cold = first call, warm = median of ``--reps`` calls,
ratio cold / warm. The detector row: the first call of a second ``FullImageDetector`` built
from a new, differently initialised model of the same config, against the first detector's
first call (ratio second / first: near 0 when nothing is compiled again). The refiner row: the
same for ``infer.refine.SceneRefiner`` (the tiny 3PT-R, three instances of K = 8 in one 640 x
480 view), the second refiner holding another model of the config and another object set of
the same shapes.

    python bench/first_calls.py [--reps 5]
"""

from __future__ import annotations

import argparse
import pathlib
import sys
import time
import warnings

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
from flax import nnx  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from threept_jax.models.configs import DetectorConfig  # noqa: E402
from threept_jax.models.detector import Detector  # noqa: E402
from threept_jax.pipeline.detection import (  # noqa: E402
    DetectionSettings,
    FullImageDetector,
)
from threept_jax.render import raster  # noqa: E402
from threept_jax.render.mesh import load_mesh, prepare_mesh, to_raster_mesh  # noqa: E402
from threept_jax.testing.detector import random_queries  # noqa: E402

MESH = ROOT.parent / "shared" / "meshes" / "bop" / "tless" / "models" / "obj_000018.ply"


def timed(fn, reps: int) -> tuple[float, float]:
    t = time.perf_counter()
    jax.block_until_ready(fn())
    cold = time.perf_counter() - t
    warm = []
    for _ in range(reps):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        warm.append(time.perf_counter() - t)
    return cold, float(np.median(warm))


def render_rows(reps: int) -> None:
    if not MESH.exists():
        raise SystemExit(f"{MESH} not found: the shared BOP meshes sit beside the checkout")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the T-LESS file repeats faces
        mesh = to_raster_mesh(prepare_mesh(load_mesh(MESH), max_faces=1024))
    for n, hw, outputs, z in ((64, (96, 96), ("rgb",), 300.0),
                              (8, (480, 640), ("depth", "mask", "xyz", "normal"), 400.0),
                              (16, (64, 64), ("rgb", "mask"), 120.0)):
        T = np.tile(np.eye(4, dtype=np.float32), (n, 1, 1))
        T[:, :3, :3] = Rotation.random(n, random_state=1).as_matrix()
        T[:, 2, 3] = z
        K = np.array([[2.0 * hw[1], 0, hw[1] / 2], [0, 2.0 * hw[1], hw[0] / 2], [0, 0, 1]],
                     np.float32)
        cold, warm = timed(lambda T=T, K=K, hw=hw, o=outputs: raster.render(mesh, T, K, hw, o), reps)
        print(f"render {n} x {hw[1]}x{hw[0]} {'+'.join(outputs):22s} cold {cold:5.2f} s  "
              f"warm {warm * 1e3:6.1f} ms  cold/warm {cold / warm:6.1f}", flush=True)
    f = jax.jit(jax.vmap(lambda T: raster.render(mesh, T, K, (64, 64), ("rgb", "mask"))))
    TT = jnp.asarray(np.stack([T, T]))
    cold, warm = timed(lambda: f(TT), reps)
    print(f"render vmapped in jit (2 x 16 x 64x64)     cold {cold:5.2f} s  warm {warm * 1e3:6.1f} "
          f"ms  cold/warm {cold / warm:6.1f}", flush=True)


def detector_row() -> None:
    cfg = DetectorConfig(variant="tiny/16", image_size=128, render_size=32)
    rng = np.random.default_rng(0)
    queries = random_queries(cfg, 3, 64, 64, rng)
    image = rng.integers(0, 256, (480, 640, 3), dtype=np.uint8)
    K = np.array([[600.0, 0, 319.5], [0, 600.0, 239.5], [0, 0, 1]], np.float32)
    firsts = []
    for seed in (0, 1):  # two models of one config, two detectors
        graphdef, params = nnx.split(Detector(cfg, rngs=nnx.Rngs(seed)))
        detector = FullImageDetector(graphdef, cfg.image_size, DetectionSettings(), num_scales=3)
        t = time.perf_counter()
        jax.block_until_ready(detector(params, image, K, queries))
        firsts.append(time.perf_counter() - t)
    print(f"detector 640x480, 3 parts: first detector's first call {firsts[0]:5.2f} s, a second "
          f"detector's {firsts[1]:5.2f} s  second/first {firsts[1] / firsts[0]:.2f}", flush=True)


def refiner_row() -> None:
    import trimesh

    from infer.refine import RefineObject, SceneRefiner
    from threept_jax.models.configs import get_refiner_config
    from threept_jax.models.refiner import Refiner
    from threept_jax.pipeline.refinement import RefineSettings
    from threept_jax.render.mesh import Mesh

    def box(extents, name):
        tm = trimesh.creation.box(extents)
        return Mesh(np.asarray(tm.vertices, np.float32), np.asarray(tm.faces, np.int32),
                    name=name)

    cfg, settings = get_refiner_config("tiny"), RefineSettings()
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (480, 640, 3), dtype=np.uint8)
    K = np.array([[[600.0, 0, 319.5], [0, 600.0, 239.5], [0, 0, 1]]], np.float32)
    pose = np.eye(4)
    pose[:3, 3] = [0.0, 0.0, 600.0]
    firsts = []
    for seed, ids in ((0, (1, 2)), (1, (3, 4))):  # two models of one config, two object sets
        objects = [RefineObject(i, box((60 + 10 * i, 40, 30), f"box{i}"), np.eye(4)[None])
                   for i in ids]
        refiner = SceneRefiner(Refiner(cfg, rngs=nnx.Rngs(seed)), cfg, settings, objects)
        t = time.perf_counter()
        refiner([image], K, None, [ids[0], ids[1], ids[0]], [pose, pose, pose])
        firsts.append(time.perf_counter() - t)
    print(f"refiner 640x480, 3 instances: first refiner's first call {firsts[0]:5.2f} s, a "
          f"second refiner's {firsts[1]:5.2f} s  second/first {firsts[1] / firsts[0]:.2f}",
          flush=True)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--reps", type=int, default=5, help="warm calls per row (median)")
    args = p.parse_args()
    if args.reps < 1:
        p.error(f"--reps must be >= 1, got {args.reps}")
    render_rows(args.reps)
    detector_row()
    refiner_row()


if __name__ == "__main__":
    main()
