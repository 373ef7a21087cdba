"""Benchmark: images/s of the data generator for a 30-object scene at 512x512, 16 and 64 spp.

Each scene is the full pipeline of ``datagen.scene.generate_scene``: 30 procedural parts
dropped on a plane (MuJoCo), random materials and textures, a procedural sky and 1-3 lights,
one single view path traced with Mitsuba (``llvm_ad_rgb`` on CPU), the instance-id and depth
AOVs, amodal masks of all 30 instances, and the BOP files (JPEG rgb). Time is split into

* physics: mesh choice and the MuJoCo drop,
* compose: materials, procedural textures, lights, cameras, the Mitsuba scene description,
* render: path tracing + the AOV pass (one ``MitsubaScene.render`` call),
* masks: amodal masks (per-instance ray casts),
* write: BOP PNG/JPEG/JSON files.

The reference, measured in the same process right after each scene on the same scene and
camera, is a bare Mitsuba path trace (``MitsubaScene.render(outputs=("rgb",))`` of the built
scene: no scene building, AOV or annotation): the ratio says how much of the generator's time
is the path tracer itself. Cold = the first scene (Mitsuba
kernel compilation, mesh export and collision shapes included); warm = mean of the others.
The CPU-hours for 900k images are extrapolated from the process CPU time of warm scenes.

    python bench/datagen.py [--scenes 3] [--spp 16 64] [--resolution 512 512]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import pathlib
import sys
import tempfile
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from datagen import meshes as M  # noqa: E402
from datagen import procedural as P  # noqa: E402
from datagen import scene as S  # noqa: E402

STAGES = ("physics", "compose", "render", "annotate", "write")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", type=int, default=3, help="scenes per spp setting")
    p.add_argument("--spp", type=int, nargs="+", default=[16, 64])
    p.add_argument("--resolution", type=int, nargs=2, default=(512, 512))
    p.add_argument("--objects", type=int, default=30)
    p.add_argument("--parts", type=int, default=20, help="procedural meshes in the pool")
    args = p.parse_args()

    import drjit as dr

    from threept_jax.render.mitsuba_backend import load_mitsuba

    mi = load_mitsuba()
    print(f"Mitsuba {mi.__version__} variant {mi.variant()}, Dr.Jit threads "
          f"{dr.thread_count()}, os.cpu_count() {os.cpu_count()}")
    parts = P.generate_parts(np.random.default_rng(0), args.parts)
    pool = M.build_pool([], parts)
    faces = np.mean([len(part.mesh.faces) for part in parts])
    print(f"pool: {len(pool)} procedural parts, {faces:.0f} faces on average; "
          f"{args.objects} instances per scene, drop on a plane, one view, "
          f"{args.resolution[0]}x{args.resolution[1]}")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = pathlib.Path(tmp)
        assets = S.AssetCache(pool, tmp / "models")
        first = True
        summary = {}
        for spp in args.spp:
            cfg = S.SceneConfig(resolution=tuple(args.resolution), spp=spp, layout="drop",
                                bin_probability=0.0, instances=args.objects, instance_spread=0.0,
                                distinct=(5, 10), distractors=(0, 0), closeup_probability=0.0,
                                image_format="jpg")
            warm = []
            for k in range(args.scenes):
                rng = np.random.default_rng(np.random.SeedSequence([0, spp, k]))
                w0, c0 = time.perf_counter(), time.process_time()
                res = S.generate_scene(tmp / f"{spp}_{k:06d}", k, rng, assets,
                                       list(range(len(pool))), cfg)
                wall, cpu = time.perf_counter() - w0, time.process_time() - c0
                t = res.timings
                scene, K, T, hw = res.last_view
                b0 = time.perf_counter()
                scene.render(K, T, hw, spp=spp, seed=1, outputs=("rgb",))
                bare = time.perf_counter() - b0
                parts_s = ", ".join(f"{s} {getattr(t, s):.2f}" for s in STAGES)
                tag = "cold" if first else "warm"
                print(f"  spp {spp:3d} scene {k} ({tag}): {wall:6.2f} s wall, {cpu:6.2f} s CPU "
                      f"[{parts_s}] {res.info['num_targets']} objects; bare trace {bare:.2f} s")
                if not first:
                    warm.append((wall, cpu, dataclasses.asdict(t), bare))
                first = False
            wall = float(np.mean([w[0] for w in warm]))
            cpu = float(np.mean([w[1] for w in warm]))
            stages = {s: float(np.mean([w[2][s] for w in warm])) for s in STAGES}
            summary[spp] = (wall, cpu, stages, float(np.mean([w[3] for w in warm])))
        print()
        print("| spp | images/s | s/image (wall) | physics | compose | render (trace+AOV) | "
              "amodal masks | write | bare Mitsuba trace | bare / total | CPU-h per 900k |")
        print("|---|---|---|---|---|---|---|---|---|---|---|")
        for spp, (wall, cpu, st, bare) in summary.items():
            print(f"| {spp} | {1 / wall:.3f} | {wall:.2f} | {st['physics']:.2f} | "
                  f"{st['compose']:.2f} | {st['render']:.2f} | {st['annotate']:.2f} | "
                  f"{st['write']:.2f} | {bare:.2f} | {bare / wall:.2f} | "
                  f"{cpu * 900_000 / 3600:,.0f} |")


if __name__ == "__main__":
    main()
