"""Symmetry transformations of an object model, built exactly as the BOP toolkit does.

Reproduces `bop_toolkit_lib/misc.py::get_symmetry_transformations` (with
`transform.rotation_matrix` for the axis-angle rotations): the identity followed by the
``symmetries_discrete`` of ``models_info.json``; each continuous symmetry discretised into
``ceil(pi / max_sym_disc_step)`` rotations by ``i * 2 pi / n`` about its axis through its
offset (``t = offset - R offset``); the result is every composition ``cont o disc`` (for each
discrete transform, for each continuous step: ``R = R_c R_d``, ``t = R_c t_d + t_c``), or the
discrete set alone when there is no continuous symmetry. The order matches the toolkit's, so
ties in the minimum over symmetries resolve the same way.
"""

from __future__ import annotations

import math

import numpy as np

from threept_jax.data.bop import Symmetries

__all__ = ["axis_angle_rotation", "symmetry_transforms", "MAX_SYM_DISC_STEP"]

# `scripts/eval_bop19_pose.py` / `eval_bop24_pose.py`: p["max_sym_disc_step"].
MAX_SYM_DISC_STEP = 0.01


def axis_angle_rotation(angle: float, direction) -> np.ndarray:
    """Rotation [3, 3] by ``angle`` (rad) about ``direction`` [3], with the same floating-point
    operations as `bop_toolkit_lib/transform.py::rotation_matrix`."""
    sina = math.sin(angle)
    cosa = math.cos(angle)
    d = np.array(direction[:3], dtype=np.float64, copy=True)
    d /= math.sqrt(np.dot(d, d))
    R = np.diag([cosa, cosa, cosa])
    R += np.outer(d, d) * (1.0 - cosa)
    d *= sina
    R += np.array([[0.0, -d[2], d[1]], [d[2], 0.0, -d[0]], [-d[1], d[0], 0.0]])
    return R


def symmetry_transforms(
    symmetries: Symmetries, max_sym_disc_step: float = MAX_SYM_DISC_STEP
) -> tuple[np.ndarray, np.ndarray]:
    """All symmetry transforms of a model: rotations [S, 3, 3] and translations [S, 3] (mm),
    identity first (see the module docstring for the construction and order)."""
    disc = [(np.eye(3), np.zeros(3))]
    for m in symmetries.discrete:
        disc.append((np.array(m[:3, :3]), np.array(m[:3, 3])))
    cont = []
    for sym in symmetries.continuous:
        offset = np.asarray(sym.offset, np.float64)
        steps = int(np.ceil(np.pi / max_sym_disc_step))
        step = 2.0 * np.pi / steps
        for i in range(steps):
            R = axis_angle_rotation(i * step, sym.axis)
            cont.append((R, -R.dot(offset) + offset))
    out = []
    for Rd, td in disc:
        if cont:
            for Rc, tc in cont:
                out.append((Rc.dot(Rd), Rc.dot(td) + tc))
        else:
            out.append((Rd, td))
    Rs = np.stack([r for r, _ in out]).astype(np.float64)
    ts = np.stack([t for _, t in out]).astype(np.float64)
    return Rs, ts
