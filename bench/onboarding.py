"""Benchmark: seconds per object of inference onboarding, split into rendering (at the model's
render size, supersampled) and embedding, for the inference default bank
(``infer.onboarding.ONBOARD_TEMPLATES``) against the paper's 5140 templates, in the same
process.

Objects are BOP meshes from ../shared/meshes/bop (YCB-V objects 1, 2, ...: 15.7k faces each
once welded, one face bucket, so the first object is cold (compilation included) and the
others warm); procedural tori when the shared meshes are absent. The detector is untrained
(``--variant``, ``--render-size``): only its shapes matter for time. No disk cache.

Rows per bank size: cold (first object) and warm (median of the others) seconds per object,
by stage (``Onboarder.timings``) and in total (mesh loading and the rest included), then the
ratio of warm totals (reference / default). A second table times the template renders of one
object at the rasterizer's old fixed 64 views per call against the face-bucket chunk
(``threept_jax.pipeline.onboarding.render_chunk``). ``--coverage`` prints the covering radius
of the super-Fibonacci grid against 200k random rotations (float64, brute force).

    python bench/onboarding.py [--objects 3] [--variant tiny/16 --render-size 32]
        [--reference 5140] [--coverage]
"""

from __future__ import annotations

import argparse
import os
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

from infer.onboarding import ONBOARD_TEMPLATES, Onboarder  # noqa: E402
from threept_jax.data.banks import BANK_TEMPLATES  # noqa: E402
from threept_jax.geometry.grids import super_fibonacci_rotations  # noqa: E402
from threept_jax.models.configs import DetectorConfig  # noqa: E402
from threept_jax.models.detector import Detector  # noqa: E402
from threept_jax.pipeline.onboarding import (  # noqa: E402
    DEVICE_CHUNK,
    SUPERSAMPLE,
    BankRenderer,
)
from threept_jax.render import Mesh, load_mesh  # noqa: E402

SHARED = ROOT.parent / "shared" / "meshes" / "bop" / "ycbv" / "models"
STAGES = ("render", "embed")


def bench_meshes(n: int) -> dict[int, Mesh]:
    out = {}
    for i in range(1, n + 1):
        path = SHARED / f"obj_{i:06d}.ply"
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            if path.is_file():
                out[i] = load_mesh(path)
            else:
                import trimesh

                t = trimesh.creation.torus(major_radius=40.0 + i, minor_radius=15.0,
                                           major_sections=128, minor_sections=60)
                out[i] = Mesh(t.vertices, t.faces, name=f"torus{i}")
    return out


def time_bank(model, cfg, meshes, num_templates: int) -> list[dict]:
    """Per object: seconds by stage and in total, for one Onboarder (fresh jit caches)."""
    ob = Onboarder(model, cfg, "bench@0", cache_dir=None, num_templates=num_templates)
    rows = []
    for oid, mesh in meshes.items():
        t0 = time.perf_counter()
        ob.onboard(oid, mesh)
        rows.append(dict(ob.timings[oid], total=time.perf_counter() - t0))
    return rows


def report(name: str, rows: list[dict]) -> float:
    """Print cold / warm rows; return the warm total (cold when there is one object)."""
    warm = rows[1:] or rows
    med = {k: statistics.median(r[k] for r in warm) for k in (*STAGES, "total")}
    for label, r in (("cold", rows[0]), ("warm", med)):
        print(f"{name:>16} {label:>5} " + " ".join(f"{r[k]:8.2f}" for k in (*STAGES, "total")))
    return med["total"]


def coverage() -> None:
    from scipy.spatial.transform import Rotation

    q = Rotation.random(200_000, random_state=0).as_quat()
    print("\ncovering radius of super_fibonacci_rotations(n), degrees (200k random rotations)")
    for n in (512, 768, 1024, 1536, 2048, 5140):
        g = Rotation.from_matrix(super_fibonacci_rotations(n).astype(np.float64)).as_quat()
        best = np.concatenate([np.abs(q[s : s + 20_000] @ g.T).max(1)
                               for s in range(0, len(q), 20_000)])
        ang = np.degrees(2 * np.arccos(np.clip(best, -1.0, 1.0)))
        print(f"  n={n:5d}  max {ang.max():5.1f}  p99 {np.percentile(ang, 99):5.1f}  "
              f"mean {ang.mean():5.1f}")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--objects", type=int, default=3, help="objects per bank size (>= 2: warm)")
    p.add_argument("--variant", default="tiny/16", help="detector ViT (S/16: the small config)")
    p.add_argument("--render-size", type=int, default=32)
    p.add_argument("--reference", type=int, default=BANK_TEMPLATES, help="reference bank size")
    p.add_argument("--coverage", action="store_true", help="also print the grid coverage table")
    args = p.parse_args()
    if args.objects < 1:
        raise SystemExit("error: --objects must be >= 1")

    print(f"jax {jax.__version__} on {jax.default_backend()} ({os.cpu_count()} CPUs), "
          f"detector {args.variant} render {args.render_size}px (supersampled "
          f"{SUPERSAMPLE}x)")
    cfg = DetectorConfig(variant=args.variant, image_size=512, render_size=args.render_size,
                         dtype="float32")
    model = Detector(cfg, rngs=nnx.Rngs(0))
    meshes = bench_meshes(args.objects)
    print(f"objects: {', '.join(f'{m.name} ({m.num_faces} faces)' for m in meshes.values())}")
    print(f"\nseconds per object{'':>7} " + " ".join(f"{k:>8}" for k in (*STAGES, "total")))
    ref = report(f"{args.reference} templates",
                 time_bank(model, cfg, meshes, args.reference))
    new = report(f"{ONBOARD_TEMPLATES} templates",
                 time_bank(model, cfg, meshes, ONBOARD_TEMPLATES))
    print(f"ratio warm total {args.reference} / {ONBOARD_TEMPLATES}: {ref / new:.2f}x")

    mesh = next(iter(meshes.values()))
    R = super_fibonacci_rotations(ONBOARD_TEMPLATES)
    auto = BankRenderer(mesh, args.render_size)
    fixed = BankRenderer(mesh, args.render_size, chunk=DEVICE_CHUNK)
    print(f"\n{ONBOARD_TEMPLATES} template renders of {mesh.name} "
          f"({auto.renderer.mesh.num_faces_padded} padded faces), warm ms per view:")
    times = {}
    for render in (fixed, auto):
        render(R[: render.chunk])  # compile
    for _ in range(2):  # alternate so both see the same machine load
        for label, render in (("fixed", fixed), ("bucket", auto)):
            t0 = time.perf_counter()
            render(R)
            times.setdefault(label, []).append(time.perf_counter() - t0)
    ms = {k: 1e3 * min(v) / len(R) for k, v in times.items()}
    print(f"  {DEVICE_CHUNK} views per call: {ms['fixed']:.2f}   {auto.chunk} views per call "
          f"(render_chunk): {ms['bucket']:.2f}   ratio {ms['fixed'] / ms['bucket']:.2f}x")
    if args.coverage:
        coverage()


if __name__ == "__main__":
    main()
