"""Object symmetries: the type, its JSON form, and the transforms, in one place.

An object's symmetries are stored as BOP's ``models_info.json`` stores them, and every file of
the project that carries symmetries (``models_info.json``, the packed object table, datagen's
mesh manifest, onboarding caches) uses that same JSON form through :meth:`Symmetries.from_json`
and :meth:`Symmetries.to_json`::

    "symmetries_discrete":   [[16 floats, row-major 4x4, translation in mm], ...]
    "symmetries_continuous": [{"axis": [3], "offset": [3] (mm)}, ...]

:func:`symmetry_transforms` builds the finite set of transforms exactly as the BOP toolkit
does (`bop_toolkit_lib/misc.py::get_symmetry_transformations`, with
`transform.rotation_matrix` for the axis-angle rotations): the identity followed by the
discrete symmetries; each continuous symmetry discretised into ``ceil(pi / max_sym_disc_step)``
rotations by ``i * 2 pi / n`` about its axis through its offset (``t = offset - R offset``);
the result is every composition ``cont o disc`` (for each discrete transform, for each
continuous step: ``R = R_c R_d``, ``t = R_c t_d + t_c``), or the discrete set alone when there is
no continuous symmetry. The order matches the toolkit's, so ties in the minimum over symmetries
resolve the same way.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping

import numpy as np

from threept_jax.geometry.validate import validate_rotation

__all__ = [
    "ContinuousSymmetry",
    "Symmetries",
    "axis_angle_rotation",
    "symmetry_transforms",
    "nearest_templates",
    "symmetric_angle_deg",
    "MAX_SYM_DISC_STEP",
]

# `scripts/eval_bop19_pose.py` / `eval_bop24_pose.py`: p["max_sym_disc_step"].
MAX_SYM_DISC_STEP = 0.01


def _readonly(a) -> np.ndarray:
    a = np.array(a, dtype=np.float64)
    a.setflags(write=False)
    return a


@dataclasses.dataclass(frozen=True, eq=False)
class ContinuousSymmetry:
    """A continuous rotational symmetry: rotation axis [3] through point offset [3] (mm)."""

    axis: np.ndarray
    offset: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))

    def __post_init__(self):
        object.__setattr__(self, "axis", _readonly(np.reshape(self.axis, 3)))
        object.__setattr__(self, "offset", _readonly(np.reshape(self.offset, 3)))


@dataclasses.dataclass(frozen=True, eq=False)
class Symmetries:
    """Symmetries of an object: discrete [S, 4, 4] (identity excluded; translations in mm) and
    continuous ones."""

    discrete: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 4, 4)))
    continuous: tuple[ContinuousSymmetry, ...] = ()

    def __post_init__(self):
        object.__setattr__(self, "discrete", _readonly(np.reshape(self.discrete, (-1, 4, 4))))
        object.__setattr__(self, "continuous", tuple(self.continuous))

    @property
    def is_symmetric(self) -> bool:
        return len(self.discrete) > 0 or len(self.continuous) > 0

    @classmethod
    def from_json(cls, info: Mapping, where: str = "symmetries") -> Symmetries:
        """Parse the ``symmetries_discrete`` / ``symmetries_continuous`` entries of a mapping
        (absent entries mean none), checking each value; ``where`` prefixes error messages."""
        disc = info.get("symmetries_discrete", []) or []
        mats = []
        for i, m in enumerate(disc):
            m = np.asarray(m, np.float64)
            if m.size != 16:
                raise ValueError(
                    f"{where}: symmetries_discrete[{i}] must have 16 values (4x4 row-major), "
                    f"got {m.size}")
            m = m.reshape(4, 4)
            validate_rotation(m[:3, :3], f"{where} symmetries_discrete[{i}]")
            mats.append(m)
        cont = []
        for i, s in enumerate(info.get("symmetries_continuous", []) or []):
            if not isinstance(s, Mapping):
                raise ValueError(f"{where}: symmetries_continuous[{i}] must be an object "
                                 '{"axis": [3], "offset": [3]}')
            axis = np.asarray(s.get("axis", []), np.float64)
            if axis.shape != (3,) or not np.all(np.isfinite(axis)) or not np.linalg.norm(axis) > 0:
                raise ValueError(
                    f"{where}: symmetries_continuous[{i}] needs a non-zero 3-vector axis")
            offset = np.asarray(s.get("offset", [0.0, 0.0, 0.0]), np.float64)
            if offset.shape != (3,) or not np.all(np.isfinite(offset)):
                raise ValueError(f"{where}: symmetries_continuous[{i}] offset must be 3 numbers")
            cont.append(ContinuousSymmetry(axis, offset))
        return cls(np.reshape(mats, (-1, 4, 4)), cont)

    def scaled(self, scale: float) -> Symmetries:
        """The same symmetries for the mesh scaled by ``scale`` (translations and offsets)."""
        disc = self.discrete.copy()
        disc[:, :3, 3] *= scale
        return Symmetries(disc, [ContinuousSymmetry(s.axis, s.offset * scale)
                                 for s in self.continuous])

    def to_json(self) -> dict:
        """The BOP JSON entries (only those that are non-empty, as BOP writes them)."""
        out = {}
        if len(self.discrete):
            out["symmetries_discrete"] = [m.reshape(-1).tolist() for m in self.discrete]
        if self.continuous:
            out["symmetries_continuous"] = [
                {"axis": s.axis.tolist(), "offset": s.offset.tolist()} for s in self.continuous]
        return out


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


def nearest_templates(rotations: np.ndarray, template_rotations: np.ndarray,
                      symmetries: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """The template nearest to each rotation up to the object's symmetries (float64).

    rotations [M, 3, 3] (R_cam_obj), template_rotations [T, 3, 3], symmetries [S, 4, 4] or
    [S, 3, 3] (object frame, identity included, e.g. from :func:`symmetry_transforms`).
    Returns ``(index [M], equivalents)``: ``index[m] = argmin_t min_s angle(template_t,
    R_m S_s)``, and ``equivalents[m]`` the nearest template of every ``R_m S_s`` (they render
    like the nearest one). The geodesic angle decreases with trace(A^T B), so both are argmaxes
    of one [T, 9] x [9, S] product per rotation.
    """
    R = np.asarray(rotations, np.float64).reshape(-1, 3, 3)
    tmpl = np.asarray(template_rotations, np.float64).reshape(-1, 9)
    sym = np.asarray(symmetries, np.float64)[:, :3, :3]
    index = np.zeros(len(R), np.int64)
    equivalents = []
    for i, r in enumerate(R):
        cands = np.einsum("ij,sjk->sik", r, sym).reshape(len(sym), 9)
        score = tmpl @ cands.T  # [T, S]
        index[i] = int(np.argmax(score.max(axis=1)))
        equivalents.append(np.unique(np.argmax(score, axis=0)))
    return index, equivalents


def symmetric_angle_deg(R_a: np.ndarray, R_b: np.ndarray, symmetries: np.ndarray) -> np.ndarray:
    """min_s angle(R_a, R_b S_s) in degrees, float64: R_a [N, 3, 3], R_b [N, 3, 3], symmetries
    [S, 4, 4] or [S, 3, 3] (object frame, identity included)."""
    sym = np.asarray(symmetries, np.float64)[:, :3, :3]
    cands = np.einsum("nij,sjk->nsik", np.asarray(R_b, np.float64), sym)  # [N, S, 3, 3]
    tr = np.einsum("nij,nsij->ns", np.asarray(R_a, np.float64), cands)  # trace(R_a^T R_b S)
    cos = np.clip((tr.max(axis=1) - 1.0) / 2.0, -1.0, 1.0)
    return np.degrees(np.arccos(cos))
