"""Rotation grids: the detector's template bank and the object tower's prior viewpoints."""

from __future__ import annotations

import numpy as np

from threept_jax.geometry.rotations import quaternion_to_matrix

#: Number of templates of the paper's detector (one unit vector per rotation).
NUM_TEMPLATES = 5140

# Constants of the super-Fibonacci spiral: phi = sqrt(2) and psi, the real root of
# psi^4 = psi + 4 (Alexa, "Super-Fibonacci Spirals", CVPR 2022, eq. 9).
_PHI = np.sqrt(2.0)
_PSI = 1.533751168755204288118041


def super_fibonacci_rotations(n: int = NUM_TEMPLATES) -> np.ndarray:
    """[n, 3, 3] float32 near-uniform rotations from a super-Fibonacci spiral (any n >= 1).

    Alexa (CVPR 2022), algorithm 1: unit quaternions on S^3 spread by two incommensurable
    spirals. The spiral covers the whole 3-sphere, so q and -q (one rotation) are never both
    hit; the 5140-rotation grid has a covering radius of 12.8 degrees (5140 random rotations: 19.6; tests measure it).
    Deterministic: the same n always gives the same grid.
    """
    if n < 1:
        raise ValueError(f"super_fibonacci_rotations needs n >= 1, got {n}")
    s = np.arange(n, dtype=np.float64) + 0.5
    r = np.sqrt(s / n)
    R = np.sqrt(1.0 - s / n)
    alpha = 2.0 * np.pi * s / _PHI
    beta = 2.0 * np.pi * s / _PSI
    q = np.stack([r * np.sin(alpha), r * np.cos(alpha), R * np.sin(beta), R * np.cos(beta)], -1)
    return np.asarray(quaternion_to_matrix(q.astype(np.float32)), dtype=np.float32)


def viewpoint_rotation(direction: np.ndarray, up: np.ndarray = (0.0, 0.0, 1.0)) -> np.ndarray:
    """R_cam_obj [3, 3] of a camera that sits along ``direction`` (object frame) and looks at
    the object's origin, with the object's ``up`` axis pointing up in the image."""
    d = np.asarray(direction, np.float64)
    d = d / np.linalg.norm(d)
    up = np.asarray(up, np.float64)
    if abs(np.dot(d, up)) > 0.99:
        up = np.array([0.0, 1.0, 0.0])
    z = -d  # the camera looks towards the object
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=0)  # rows: camera axes in object coordinates


def prior_view_rotations() -> np.ndarray:
    """[12, 3, 3] float32 R_cam_obj of the object tower's fixed viewpoints.

    Cameras sit on the 12 vertices of an icosahedron around the object, the most even spread
    of 12 directions on the sphere (every pair at least 63.4 degrees apart), each looking at
    the object's centre with its z axis up where possible.
    """
    g = (1.0 + np.sqrt(5.0)) / 2.0
    verts = []
    for a in (-1.0, 1.0):
        for b in (-g, g):
            verts += [(0.0, a, b), (a, b, 0.0), (b, 0.0, a)]
    return np.stack([viewpoint_rotation(v) for v in verts]).astype(np.float32)
