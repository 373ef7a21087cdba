"""Object diameter and the unit bounds it is checked against: one definition for the project.

The diameter is BOP's (`bop_toolkit_lib/misc.py::calc_pts_diameter`): the largest distance
between two vertices, in millimetres. Every place that computes or checks one (mesh loading,
BOP ``models_info.json``, procedural parts, the mesh pool) uses this module.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull, QhullError

__all__ = ["mesh_diameter", "MIN_DIAMETER_MM", "MAX_DIAMETER_MM"]

#: A diameter below this is almost surely a mesh in metres (BOP meshes are in mm).
MIN_DIAMETER_MM = 1.0
#: A diameter above this (5 m) is almost surely a mesh in micrometres or a wrong scale.
MAX_DIAMETER_MM = 5000.0


def mesh_diameter(vertices: np.ndarray) -> float:
    """Largest distance between two vertices [N, 3] (float64), exact.

    The farthest pair lies on the convex hull, so only hull vertices are compared (in blocks,
    to bound memory); flat or degenerate point sets, which have no 3-D hull, compare all.
    """
    v = np.asarray(vertices, np.float64).reshape(-1, 3)
    if len(v) < 2:
        return 0.0
    try:
        v = v[ConvexHull(v).vertices]
    except (QhullError, ValueError):
        pass
    best = 0.0
    for start in range(0, len(v), 1024):
        d = np.linalg.norm(v[start : start + 1024, None, :] - v[None, :, :], axis=-1)
        best = max(best, float(d.max()))
    return best
