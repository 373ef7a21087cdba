"""Mesh loading cost: load time and peak RSS of ``load_mesh`` on UV spheres (every vertex on
the hull: the worst case for the diameter) of about 82k, 500k and 2M faces, each in a fresh
process, against the former exact diameter (convex hull, then all hull pairs) timed in this
process on a 5k-face sphere as the reference.

    python bench/meshes.py
"""

from __future__ import annotations

import pathlib
import subprocess
import sys
import tempfile
import time

import numpy as np
import trimesh
from scipy.spatial import ConvexHull

ROOT = pathlib.Path(__file__).resolve().parents[1]
SIZES = {"82k": 143, "500k": 354, "2M": 708}  # UV sphere count -> about 4 * count^2 faces

_CHILD = """
import resource, sys, time, warnings
t0 = time.perf_counter()
from threept_jax.render.mesh import load_mesh
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
t = time.perf_counter()
with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    m = load_mesh(sys.argv[1])
dt = time.perf_counter() - t
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(m.num_faces, dt, peak / 1024, (peak - base) / 1024)
"""


def old_exact_diameter(v: np.ndarray) -> float:
    """The former method: hull vertices, then every pair in blocks of 1024 rows."""
    v = v[ConvexHull(v).vertices]
    best = 0.0
    for s in range(0, len(v), 1024):
        best = max(best, float(np.linalg.norm(v[s : s + 1024, None] - v[None], axis=-1).max()))
    return best


def main() -> None:
    small = np.asarray(trimesh.creation.uv_sphere(radius=50.0, count=[50, 50]).vertices)
    t = time.perf_counter()
    old_exact_diameter(small)
    ref = time.perf_counter() - t
    print(f"reference: former exact diameter, {len(small)} vertices (~5k faces): {ref:.3f} s")
    print(f"{'mesh':>6} {'faces':>9} {'load s':>8} {'x ref':>8} {'peak RSS MB':>12} "
          f"{'above imports MB':>17}")
    with tempfile.TemporaryDirectory() as tmp:
        for name, count in SIZES.items():
            path = pathlib.Path(tmp) / f"sphere_{name}.ply"
            trimesh.creation.uv_sphere(radius=50.0, count=[count, count]).export(path)
            out = subprocess.run([sys.executable, "-c", _CHILD, str(path)], cwd=ROOT,
                                 env={"PYTHONPATH": str(ROOT), "JAX_PLATFORMS": "cpu",
                                      "PATH": "/usr/bin:/bin"},
                                 capture_output=True, text=True, check=True)
            faces, dt, peak, extra = out.stdout.split()
            print(f"{name:>6} {int(faces):>9} {float(dt):>8.2f} {float(dt) / ref:>8.2f} "
                  f"{float(peak):>12.0f} {float(extra):>17.0f}")


if __name__ == "__main__":
    main()
