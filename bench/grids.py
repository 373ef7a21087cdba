"""Benchmark: covering radius of the template grid against random rotations.

The template bank of 3PT-D uses ``super_fibonacci_rotations(5140)``. Its covering radius is the
largest geodesic angle from any rotation to the nearest grid rotation, estimated as the maximum
over ``--queries`` uniformly random query rotations (SciPy, float64, q ~ -q through a KD-tree on
both quaternion signs). The reference, in the same process and with the same queries, is a set
of the same number of uniformly random rotations; the script prints both radii, their ratio,
the mean nearest-grid angle and the time to build the grid (cold: first call, warm: best of 3).

    python bench/grids.py [--n 5140 --queries 120000 --seed 0]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from threept_jax.geometry.grids import super_fibonacci_rotations


def nearest_angles_deg(grid: np.ndarray, queries: Rotation) -> np.ndarray:
    """Geodesic angle (degrees) from each query rotation to its nearest grid rotation."""
    qg = Rotation.from_matrix(np.asarray(grid, np.float64)).as_quat()
    chord, _ = cKDTree(np.concatenate([qg, -qg])).query(queries.as_quat())
    return np.degrees(2 * np.arccos(np.clip(1 - chord**2 / 2, -1, 1)))


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--n", type=int, default=5140, help="grid size (the template bank's)")
    parser.add_argument("--queries", type=int, default=120_000)
    parser.add_argument("--seed", type=int, default=0)
    a = parser.parse_args()

    t0 = time.perf_counter()
    grid = super_fibonacci_rotations(a.n)
    cold = time.perf_counter() - t0
    warm = np.inf
    for _ in range(3):
        t0 = time.perf_counter()
        super_fibonacci_rotations(a.n)
        warm = min(warm, time.perf_counter() - t0)

    queries = Rotation.random(a.queries, random_state=a.seed)
    random_grid = Rotation.random(a.n, random_state=a.seed + 1).as_matrix()
    ours = nearest_angles_deg(grid, queries)
    ref = nearest_angles_deg(random_grid, queries)

    print(f"grid: {a.n} rotations; covering radius = max angle from {a.queries} random "
          f"rotations to the nearest grid rotation")
    print(f"{'grid':28s} {'covering radius deg':>20s} {'mean nearest deg':>17s}")
    print(f"{'super_fibonacci_rotations':28s} {ours.max():20.1f} {ours.mean():17.2f}")
    print(f"{'random rotations (SciPy)':28s} {ref.max():20.1f} {ref.mean():17.2f}")
    print(f"ratio super-Fibonacci / random: covering radius {ours.max() / ref.max():.2f}, "
          f"mean {ours.mean() / ref.mean():.2f}")
    print(f"super_fibonacci_rotations({a.n}): cold {cold * 1e3:.1f} ms, warm {warm * 1e3:.1f} ms")


if __name__ == "__main__":
    main()
