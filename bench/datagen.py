"""Benchmark: images/s of the data generator at the demo's settings (a robot cell, 640x480).

Each image is the full pipeline of ``datagen.scene.generate_scene`` as ``python -m train.adapt``
(and so ``make demo``) runs it: the demo's five procedural parts (``procedural:5``, seed 7) and
their cell (``datagen/cell.py``), about 8 instances and a few distractors dropped into the tray
(MuJoCo), random materials and textures, cell lights, one camera, path traced with Mitsuba
(``llvm_ad_rgb`` on CPU, path length 3) and, by default, denoised (Open Image Denoise), the
instance-id and depth AOVs, amodal masks, and the BOP files (JPEG rgb). Time is split into

* physics: mesh choice and the MuJoCo drop,
* compose: materials, procedural textures, lights, cameras, the Mitsuba scene description,
* render: path tracing + denoising + the AOV pass (one ``MitsubaScene.render`` call),
* annotate: amodal masks (per-instance ray casts),
* write: BOP PNG/JPEG/JSON files.

Rows: the demo's setting (2 spp, denoised) and the demo's setting before denoising (8 spp raw),
4 captures per scene as the demo (the scene build and kernel compilation of each scene are
shared by its captures; figures are per image).
The reference, measured in the same process right after each scene on the same scene and
camera, is a bare Mitsuba path trace (``MitsubaScene.render(outputs=("rgb",))`` of the built
scene at the row's spp: no scene building, denoising, AOV or annotation): the ratio says how
much of the generator's time is the path tracer itself. Cold = the first scene (Mitsuba
kernel compilation, mesh export and collision shapes included); warm = mean of the others.
The CPU-hours for 900k images are extrapolated from the process CPU time of warm scenes.

    python bench/datagen.py [--scenes 6]
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

from datagen import generate as G  # noqa: E402
from datagen import scene as S  # noqa: E402

STAGES = ("physics", "compose", "render", "annotate", "write")
#: (spp, denoise): the demo's setting, then the demo's setting before denoising.
SETTINGS = ((2, True), (8, False))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", type=int, default=6, help="scenes per setting")
    p.add_argument("--seed", type=int, default=7, help="the demo's adapted parts")
    p.add_argument("--images-per-scene", type=int, default=4, help="captures per scene (demo: 4)")
    args = p.parse_args()

    import drjit as dr

    from threept_jax.render.mitsuba_backend import load_mitsuba

    mi = load_mitsuba()
    print(f"Mitsuba {mi.__version__} variant {mi.variant()}, Dr.Jit threads "
          f"{dr.thread_count()}, os.cpu_count() {os.cpu_count()}")
    pool = G.build_pool(["procedural:5"], args.seed)
    cell = G.design_cell(pool, args.seed, (640, 480))
    print(f"pool: the demo's {len(pool)} procedural parts; cell at {cell.working_distance:.0f} mm, "
          f"640x480, about 8 instances per image, path length 3")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = pathlib.Path(tmp)
        assets = S.AssetCache(pool, tmp / "models")
        first = True
        summary = {}
        for spp, denoise in SETTINGS:
            cfg = S.SceneConfig(resolution=(640, 480), spp=spp, layout="cell", cell=cell,
                                instances=8, distinct=(1, 5), max_depth=3, denoise=denoise,
                                images_per_scene=args.images_per_scene)
            warm = []
            for k in range(args.scenes):
                rng = np.random.default_rng(np.random.SeedSequence([args.seed, spp, k]))
                w0, c0 = time.perf_counter(), time.process_time()
                res = S.generate_scene(tmp / f"{spp}_{k:06d}", k, rng, assets,
                                       list(range(len(pool))), cfg)
                n = args.images_per_scene  # figures per image from here on
                wall, cpu = (time.perf_counter() - w0) / n, (time.process_time() - c0) / n
                t = S.Timings(**{s: getattr(res.timings, s) / n for s in STAGES})
                scene, K, T, hw = res.last_view
                b0 = time.perf_counter()
                scene.render(K, T, hw, spp=spp, seed=1, outputs=("rgb",))
                bare = time.perf_counter() - b0
                parts_s = ", ".join(f"{s} {getattr(t, s):.2f}" for s in STAGES)
                tag = "cold" if first else "warm"
                print(f"  spp {spp}{' denoised' if denoise else ''} scene {k} ({tag}), per "
                      f"image: {wall:6.2f} s wall, {cpu:6.2f} s CPU [{parts_s}] "
                      f"{res.info['num_targets']} objects; bare trace {bare:.2f} s")
                if not first:
                    warm.append((wall, cpu, dataclasses.asdict(t), bare))
                first = False
            wall = float(np.mean([w[0] for w in warm]))
            cpu = float(np.mean([w[1] for w in warm]))
            stages = {s: float(np.mean([w[2][s] for w in warm])) for s in STAGES}
            summary[(spp, denoise)] = (wall, cpu, stages, float(np.mean([w[3] for w in warm])))
        print()
        print("| setting | images/s | s/image (wall) | physics | compose | render | "
              "amodal masks | write | bare Mitsuba trace | bare / total | CPU-h per 900k |")
        print("|---|---|---|---|---|---|---|---|---|---|---|")
        for (spp, denoise), (wall, cpu, st, bare) in summary.items():
            print(f"| {spp} spp{', denoised' if denoise else ' raw'} | {1 / wall:.3f} | "
                  f"{wall:.2f} | {st['physics']:.2f} | {st['compose']:.2f} | "
                  f"{st['render']:.2f} | {st['annotate']:.2f} | {st['write']:.2f} | "
                  f"{bare:.2f} | {bare / wall:.2f} | {cpu * 900_000 / 3600:,.0f} |")


if __name__ == "__main__":
    main()
