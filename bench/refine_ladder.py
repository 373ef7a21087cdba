"""The noise ladder of 3PT-R (issue 25, item 1): does refinement ever make a pose worse?

The inference loop (``refine_instances``, 3 iterations, K = 1: refine-only and tracking) driven
by the oracle network made worse rung by rung: descriptor noise (noise-to-signal norm ratio) and
outlier rates (share of real pixels whose descriptor belongs to a random other point of the
part), from 1 and from 3 views, on one T-LESS part painted with its object coordinates
(``threept_jax.testing.refine_ladder``). Starting poses are drawn as refiner training draws
them (15 degrees half-normal, 2 % of the diameter across, 5 % of the depth along the ray).

For every rung it prints the median rotation (degrees) and translation (mm) error after the
loop and their ratio to the start's (the reference, same starts, same process); "worse" is the
share of starts whose rotation error grew by more than 0.5 degrees. With ``--compare`` the same
ladder runs again with the updates' outline check off (``RefineSettings.check_outline=False``)
and with their consensus test off (``RefineSettings.min_agreement=0``) to show what each buys
and costs. Times are the warm loop (the first rung of each view count compiles;
its time is printed apart).

    python bench/refine_ladder.py [--views 1 3] [--starts 16] [--compare] [--out ladder.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import sys
import time
import warnings

import numpy as np
from tqdm import tqdm

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from threept_jax.pipeline.refinement import RefineSettings  # noqa: E402
from threept_jax.render.mesh import load_mesh, prepare_mesh  # noqa: E402
from threept_jax.testing.refine_ladder import (  # noqa: E402
    make_scene,
    pose_errors,
    run_ladder,
    start_poses,
)

MESH = ROOT.parent / "shared/meshes/bop/tless/models/obj_000018.ply"  # no symmetry, 111 mm
NOISE = (0.0, 0.5, 1.0, 2.0, 4.0)
OUTLIERS = (0.0, 0.5, 0.8, 1.0)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--views", type=int, nargs="+", default=[1, 3], choices=(1, 3))
    p.add_argument("--starts", type=int, default=16, help="starting poses per rung")
    p.add_argument("--mesh", type=pathlib.Path, default=MESH, help="a PLY in mm")
    p.add_argument("--compare", action="store_true",
                   help="also run with the outline check off (check_outline=False) and with "
                        "the consensus test off (min_agreement=0)")
    p.add_argument("--out", type=pathlib.Path, default=None, help="write the rows as JSON")
    args = p.parse_args(argv)
    if args.starts < 1:
        p.error(f"--starts must be >= 1, got {args.starts}")
    if not args.mesh.is_file():
        p.error(f"--mesh {args.mesh} does not exist (the BOP meshes live in ../shared/meshes)")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the T-LESS file repeats faces
        mesh = prepare_mesh(load_mesh(args.mesh), max_faces=1024)

    rungs = [(n, o) for n in NOISE for o in OUTLIERS]
    variants = {"safe": RefineSettings(ambient=1.0)}
    if args.compare:
        variants["no outline check"] = dataclasses.replace(variants["safe"], check_outline=False)
        variants["no consensus test"] = dataclasses.replace(variants["safe"], min_agreement=0.0)
    rows = []
    for views in args.views:
        scene = make_scene(mesh, views)
        starts = start_poses(scene, args.starts, seed=1)
        e0 = pose_errors(starts, scene.T_gt)
        print(f"\n{views} view(s), {args.starts} starts: median start error "
              f"{np.median(e0[:, 0]):.2f} deg, {np.median(e0[:, 1]):.2f} mm")
        for name, settings in variants.items():
            t0 = time.perf_counter()
            first = run_ladder(scene, starts, rungs[:1], settings=settings)
            cold = time.perf_counter() - t0
            t0 = time.perf_counter()
            rest = [run_ladder(scene, starts, [r], settings=settings)
                    for r in tqdm(rungs[1:], desc=f"{views} view(s), {name}", leave=False)]
            warm = (time.perf_counter() - t0) / max(len(rungs) - 1, 1)
            errors = np.concatenate([first] + rest)
            print(f"  {name}: first rung {cold:.1f} s (compiles), then {warm:.2f} s per rung")
            print("  | noise | outliers | deg after | mm after | deg / start | mm / start | worse |")
            print("  |---|---|---|---|---|---|---|")
            for (noise, outliers), e in zip(rungs, errors):
                deg, mm = np.median(e[:, 0]), np.median(e[:, 1])
                worse = float(np.mean(e[:, 0] > e0[:, 0] + 0.5))
                print(f"  | {noise:.1f} | {outliers:.2f} | {deg:.2f} | {mm:.2f} | "
                      f"{deg / np.median(e0[:, 0]):.2f} | {mm / np.median(e0[:, 1]):.2f} | "
                      f"{worse:.2f} |")
                rows.append(dict(views=views, variant=name, noise=noise, outliers=outliers,
                                 deg_start=float(np.median(e0[:, 0])),
                                 mm_start=float(np.median(e0[:, 1])), deg=float(deg),
                                 mm=float(mm), worse=worse))
    if args.out:
        args.out.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
