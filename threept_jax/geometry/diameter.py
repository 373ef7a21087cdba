"""Object diameter and the unit bounds it is checked against: one definition for the project.

The diameter is BOP's (`bop_toolkit_lib/misc.py::calc_pts_diameter`): the largest distance
between two vertices, in millimetres. Every place that computes or checks one (mesh loading,
BOP ``models_info.json``, procedural parts, the mesh pool) uses this module, and a diameter
outside the unit bounds raises :class:`MeshUnitsError`, which callers re-phrase with the option
that sets the units (``units=``, ``--units``, ``--mesh-units``).

Cost. Comparing all pairs is quadratic (an 82k-face sphere took 141 s and 3.2 GB). Here every
vertex gets a proven upper bound on its farthest distance from the support function of the
point set in 1281 fixed directions (and their opposites); only vertices whose bound reaches the
best pair found so far can end a diametral pair, and those are compared exactly. For every
mesh whose candidates number at most ``EXACT_MAX_CANDIDATES`` (every BOP model) the result
is exact; for larger round shapes (a finely tessellated sphere: every vertex has an antipode)
it is the best pair found, at most ``DIAMETER_RTOL`` (0.114 %) below the true diameter.
Time and memory are linear in the vertex count: an ordinary 40k-vertex BOP model takes about
0.1 s, a 1M-vertex sphere (the worst case) about 4 s; memory is a few times the vertex array.
"""

from __future__ import annotations

import functools

import numpy as np

__all__ = [
    "mesh_diameter",
    "diameter_bounds",
    "check_units",
    "MeshUnitsError",
    "MIN_DIAMETER_MM",
    "MAX_DIAMETER_MM",
    "DIAMETER_RTOL",
    "EXACT_MAX_CANDIDATES",
]

#: A diameter below this is almost surely a mesh in metres (BOP meshes are in mm).
MIN_DIAMETER_MM = 1.0
#: A diameter above this (5 m) is almost surely a mesh in micrometres or a wrong scale.
MAX_DIAMETER_MM = 5000.0
#: Candidate vertices compared pairwise (exactly): at most about 1.3e8 distances, in blocks.
EXACT_MAX_CANDIDATES = 16384
_BRUTE_FORCE = 1024  # vertices compared pairwise without pruning (5e5 distances)
_BLOCK = 1 << 17  # elements per temporary block (1 MB of float64: stays in cache)


class MeshUnitsError(ValueError):
    """A mesh whose diameter says its units are wrong: outside [low, high] mm.

    Attributes:
      diameter: the measured diameter in mm (after any declared unit conversion).
      path: the file (or the mesh's name) it was measured on.
      low, high: the bounds it was checked against (mm).

    ``str(err)`` names the library argument (``units='m'``); a CLI re-phrases it with
    :meth:`message` and its own flag, e.g. ``err.message("--mesh-units {}")``.
    """

    def __init__(self, diameter: float, path, low: float = MIN_DIAMETER_MM,
                 high: float = MAX_DIAMETER_MM, option: str = "units='{}'"):
        self.diameter = float(diameter)
        self.path = path
        self.low = float(low)
        self.high = float(high)
        super().__init__(self.message(option))

    def message(self, option: str) -> str:
        """The message naming ``option`` (a template: ``{}`` stands for a unit) as the fix."""
        if self.diameter < self.low:
            fix = f"it looks like metres: pass {option.format('m')} to convert it to mm"
        else:
            fix = (
                "it looks like micrometres or a whole scene: rescale the file to mm, or "
                f"pass its units with {option.format('<unit>')}"
            )
        return (
            f"{self.path}: mesh diameter {self.diameter:.4g} mm is outside "
            f"[{self.low:g}, {self.high:g}] mm; {fix} (units: mm, cm, m, in; meshes are "
            "never rescaled silently)"
        )


def check_units(diameter: float, path, low: float = MIN_DIAMETER_MM,
                high: float = MAX_DIAMETER_MM) -> float:
    """``diameter`` (mm) if it lies in [low, high], else raise :class:`MeshUnitsError`."""
    if not (low <= diameter <= high):
        raise MeshUnitsError(diameter, path, low, high)
    return float(diameter)


@functools.cache
def _directions(subdivisions: int) -> tuple[np.ndarray, float]:
    """Half of an icosphere's vertices (one of each antipodal pair) [M, 3] and cos(theta).

    theta is the covering radius of the full set (every unit vector lies within theta of a
    direction or its opposite): the largest angular circumradius of the facets of their convex
    hull, which are the spherical Delaunay triangles, whose circumcentres are the Voronoi
    vertices, where the distance to the nearest direction is largest.
    """
    from scipy.spatial import ConvexHull

    # Icosahedron subdivided (4 times: 2562 vertices), built here to stay dependency-free.
    t = (1 + 5**0.5) / 2
    v = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t),
         (0, -1, -t), (0, 1, -t), (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]  # fmt: skip
    pts = np.asarray(v, np.float64)
    pts /= np.linalg.norm(pts, axis=1, keepdims=True)
    faces = ConvexHull(pts).simplices
    for _ in range(subdivisions):
        e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), 1)
        edges, inv = np.unique(e, axis=0, return_inverse=True)
        mid = pts[edges].sum(1)
        pts = np.concatenate([pts, mid / np.linalg.norm(mid, axis=1, keepdims=True)])
        m = len(pts) - len(edges) + inv.reshape(3, -1).T  # midpoints of edges 01, 12, 20
        a, b, c = faces.T
        faces = np.concatenate([np.stack(r, 1) for r in (
            (a, m[:, 0], m[:, 2]), (m[:, 0], b, m[:, 1]), (m[:, 2], m[:, 1], c), m.T)])  # fmt: skip
    key = np.round(pts, 9)
    upper = (key[:, 2] > 0) | ((key[:, 2] == 0) & ((key[:, 1] > 0) | (
        (key[:, 1] == 0) & (key[:, 0] > 0))))  # fmt: skip
    half = pts[upper]
    both = np.concatenate([half, -half])
    cos_theta = float((-ConvexHull(both).equations[:, 3]).min())
    return np.ascontiguousarray(half), cos_theta


#: Relative bound of the non-exact case: true diameter <= returned * (1 + DIAMETER_RTOL).
DIAMETER_RTOL = 1.0 / _directions(4)[1] - 1.0


def _max_pairwise(p: np.ndarray) -> float:
    """Exact largest distance between two rows of p [N, 3] (float64), in bounded blocks."""
    best = 0.0
    rows = max(1, _BLOCK // max(len(p), 1))
    for s in range(0, len(p), rows):
        a = p[s : s + rows, None, :]
        d2 = (a[..., 0] - p[None, :, 0]) ** 2
        d2 += (a[..., 1] - p[None, :, 1]) ** 2
        d2 += (a[..., 2] - p[None, :, 2]) ** 2
        best = max(best, float(d2.max()))
    return float(np.sqrt(best))


def _prune(v: np.ndarray, subdivisions: int, best: float) -> tuple[np.ndarray, float, float]:
    """One pruning pass over v [N, 3] with the directions of ``_directions(subdivisions)``.

    Returns (mask [N] of the vertices that may end a diametral pair of v, the best pair
    distance found (at least ``best``), an upper bound of the diameter of v).
    """
    ut, cos_theta = _directions(subdivisions)  # [M, 3]
    # Centred for well-conditioned dot products (bounds only; exact distances use v itself),
    # transposed so that reductions over points run along contiguous rows.
    ct = np.ascontiguousarray((v - (v.min(0) + v.max(0)) / 2).T)  # [3, N]
    cols = max(1, _BLOCK // len(ut))
    hi = np.full(len(ut), -np.inf)
    lo = np.full(len(ut), np.inf)
    arg_hi = np.zeros(len(ut), np.int64)
    arg_lo = np.zeros(len(ut), np.int64)
    rows = np.arange(len(ut))
    for s in range(0, len(v), cols):
        d = ut @ ct[:, s : s + cols]  # [M, n]
        i, j = d.argmax(1), d.argmin(1)
        dh, dl = d[rows, i], d[rows, j]
        up, down = dh > hi, dl < lo
        hi, arg_hi = np.where(up, dh, hi), np.where(up, i + s, arg_hi)
        lo, arg_lo = np.where(down, dl, lo), np.where(down, j + s, arg_lo)
    # Best actual pair: the extremes of every direction, then farthest-point steps from it.
    d_ext = np.linalg.norm(v[arg_hi] - v[arg_lo], axis=1)
    k = int(d_ext.argmax())
    p = v[arg_hi[k]]
    best = max(best, float(d_ext[k]))
    for _ in range(4):
        dist = np.linalg.norm(v - p, axis=1)
        q = int(dist.argmax())
        if dist[q] <= best:
            break
        best, p = float(dist[q]), v[q]
    # Any pair (p, q) has a direction u within theta of (q - p) / |q - p| (u or -u in the set),
    # so |q - p| cos(theta) <= max(hi(u) - u.p, u.p - lo(u)) = w(u) + |u.p - mid(u)|, with
    # w the half-width and mid the centre of the extent of v along u.
    half_width = ((hi - lo) / 2)[:, None]
    ut_mid = np.concatenate([ut, -((hi + lo) / 2)[:, None]], 1)  # [M, 4]
    # Slack for rounding in the dot products (relative 1e-9 of the extent; exactness needs
    # only that no diametral vertex is dropped).
    threshold = (best * (1 - 1e-9) - 1e-9 * np.abs(ct).max()) * cos_theta
    keep = np.zeros(len(v), bool)
    for s in range(0, len(v), cols):
        block = ct[:, s : s + cols]
        d = ut_mid @ np.concatenate([block, np.ones((1, block.shape[1]))])  # u.p - mid(u)
        np.abs(d, out=d)
        d += half_width
        keep[s : s + cols] = d.max(0) >= threshold
    return keep, best, float((hi - lo).max()) / cos_theta


def diameter_bounds(vertices: np.ndarray) -> tuple[float, float]:
    """(lower, upper) bounds of the largest distance between two vertices [N, 3]; equal if exact.

    ``lower`` is the distance of an actual vertex pair; ``upper <= lower * (1 + DIAMETER_RTOL)``
    always holds, and ``lower == upper`` (exact) whenever at most ``EXACT_MAX_CANDIDATES``
    vertices can end a diametral pair.
    """
    v = np.asarray(vertices, np.float64).reshape(-1, 3)
    if len(v) < 2:
        return 0.0, 0.0
    if not np.isfinite(v).all():
        raise ValueError("vertices must be finite to have a diameter (found NaN or inf)")
    # A coarse pass (81 directions) drops most vertices of an ordinary mesh cheaply; the fine
    # one (1281) works on what is left: a superset of the diametral vertices has the same
    # diameter, so each pass may prune the previous one's survivors with its own extremes.
    best, upper = 0.0, np.inf
    for subdivisions in (2, 4):
        if len(v) <= _BRUTE_FORCE:
            break
        keep, best, upper = _prune(v, subdivisions, best)
        v = v[keep]
    if len(v) <= EXACT_MAX_CANDIDATES:
        exact = max(best, _max_pairwise(v))
        return exact, exact
    return best, max(best, upper)


def mesh_diameter(vertices: np.ndarray) -> float:
    """Largest distance between two vertices [N, 3] (float64): exact for every normal mesh.

    See :func:`diameter_bounds`: exact unless more than ``EXACT_MAX_CANDIDATES`` vertices can
    end a diametral pair (large round meshes), then at most ``DIAMETER_RTOL`` below the truth.
    """
    return diameter_bounds(vertices)[0]

