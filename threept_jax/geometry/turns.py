"""Near symmetries: the turns that map a part almost onto itself but are not its symmetries.

A gear of 40 teeth turned by 9 degrees about its axis looks the same in every view except for
its keyway; a hexagonal bar turned by 60 degrees, the same except for a flat or a hole. Its
symmetries (``models_info.json``) say which turns are *exactly* the same part; these are the
ones that are *almost* the same. Silhouette evidence (the contour refiner) cannot tell them
apart: a refined pose of such a part is right up to one of these turns, and the small feature
that decides (the keyway) must be looked for among them (``infer.contour_refine``).

:func:`near_symmetry_turns` finds, about each principal axis of the part's surface through its
bounding-box centre (:func:`principal_axes`), the largest N <= ``max_fold`` for which every turn by ``k * 360 / N``
degrees maps the surface onto itself to within ``tolerance`` of the bounding-box diagonal (the
95th percentile of the distances from turned surface samples to the nearest of a denser set of
samples, against the same figure unturned: the sampling's own spacing). A part that passes at
``max_fold`` about an axis is round about it (a shaft, a plain disc): no finite set of turns
decides its orientation there, and that axis gives none. Turns within ``SAME_DEG`` of a
declared symmetry are dropped: they are the same pose. The turns are about the bounding box's
centre (as every centre of the project): a feature that sets the box's extent off the axis
(a short tooth at the rim's widest point) moves that centre off the axis, and the part then
shows no turns.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from threept_jax.geometry.symmetry import axis_angle_rotation

__all__ = ["near_symmetry_turns", "principal_axes", "surface_samples", "SAME_DEG"]

#: A turn whose rotation is within this angle (degrees) of a declared symmetry's is that
#: symmetry.
SAME_DEG = 2.0


def surface_samples(vertices: np.ndarray, faces: np.ndarray, n: int,
                    rng: np.random.Generator) -> np.ndarray:
    """[n, 3] points drawn uniformly over the area of the triangle mesh (vertices, faces)."""
    tri = np.asarray(vertices, np.float64)[np.asarray(faces)]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if not area.sum() > 0:
        raise ValueError("the mesh has no area to sample")
    which = rng.choice(len(tri), n, p=area / area.sum())
    u, v = rng.random((2, n))
    flip = u + v > 1
    u, v = np.where(flip, 1 - u, u), np.where(flip, 1 - v, v)
    t = tri[which]
    return t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])


def principal_axes(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """[3, 3] columns: the eigenvectors of the surface's second moment about the origin,
    exact (per triangle: area / 12 (aa' + bb' + cc' + ss'), s = a + b + c), so that a
    symmetric part's axes are its symmetry axes to float precision."""
    tri = np.asarray(vertices, np.float64)[np.asarray(faces)]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    s = tri.sum(1)
    M = (np.einsum("f,fvi,fvj->ij", area, tri, tri) + np.einsum("f,fi,fj->ij", area, s, s)) / 12
    return np.linalg.eigh(M)[1]


def _fold(P: np.ndarray, tree: cKDTree, limit: float, axis: np.ndarray, max_fold: int) -> int:
    """The largest N <= ``max_fold`` whose turns about ``axis`` all keep the samples ``P``
    within ``limit`` (95th percentile) of the reference samples in ``tree``; 1 when none."""
    seen: dict[float, bool] = {}

    def fits(angle: float) -> bool:
        key = round(angle % (2 * np.pi), 9)
        if key not in seen:
            R = axis_angle_rotation(angle, axis)
            # The 95th percentile within the limit: at most 5 % of the samples beyond it (a
            # bounded search, far quicker than the distances themselves).
            far = np.isinf(tree.query(P @ R.T, distance_upper_bound=limit)[0])
            seen[key] = bool(far.mean() <= 0.05)
        return seen[key]

    return next((n for n in range(max_fold, 1, -1)
                 if all(fits(2 * np.pi * k / n) for k in range(1, n))), 1)


def near_symmetry_turns(vertices: np.ndarray, faces: np.ndarray,
                        symmetries: np.ndarray | None = None, *, tolerance: float = 0.002,
                        max_fold: int = 120, samples: int = 3000,
                        reference: int = 40000) -> np.ndarray:
    """[M, 4, 4] transforms (object frame, mm) of the part's near-symmetric turns (module
    docstring), none of them the identity or a declared symmetry (``symmetries`` [S, 4, 4]);
    [0, 4, 4] when it has none. Deterministic (fixed sample seeds)."""
    vertices = np.asarray(vertices, np.float64)
    lo, hi = vertices.min(0), vertices.max(0)
    centre, diagonal = 0.5 * (lo + hi), float(np.linalg.norm(hi - lo))
    P = surface_samples(vertices, faces, samples, np.random.default_rng(0)) - centre
    tree = cKDTree(surface_samples(vertices, faces, reference, np.random.default_rng(1)) - centre)
    base = np.quantile(tree.query(P)[0], 0.95)
    limit = base + tolerance * diagonal
    declared = np.zeros((0, 3, 3)) if symmetries is None else np.asarray(symmetries)[:, :3, :3]
    turns = []
    for axis in principal_axes(vertices - centre, faces).T:
        fold = _fold(P, tree, limit, axis, max_fold)
        if fold == max_fold:
            continue  # round about this axis
        for k in range(1, fold):
            R = axis_angle_rotation(2 * np.pi * k / fold, axis)
            cos = (np.einsum("ij,sij->s", R, declared) - 1) / 2
            if np.any(cos >= np.cos(np.radians(SAME_DEG))):
                continue
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R, centre - R @ centre
            turns.append(T)
    return np.stack(turns) if turns else np.zeros((0, 4, 4))
