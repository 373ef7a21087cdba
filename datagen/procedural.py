"""Procedural industrial parts: the project's own, unlimited and licence-free mesh supply.

3PT trains on ~110k meshes (docs/design.md section 1); public CAD sets are few and small, so
the data generator can mix in parts built here from random dimensions: L-, T- and U-profiles,
plates with hole patterns, bent brackets, spur gears (involute flanks), hex bolts and socket
screws, hex nuts, washers, flanges, pipe elbows and stepped shafts.

Every part is built with manifold3d (exact, always manifold constructive solid geometry), in
millimetres, and returned as a ``trimesh.Trimesh`` that is

* watertight and consistently oriented (outward normals, positive volume),
* centred at its bounding-box centre, as BOP models are,
* within a face budget: a part that comes out too fine is rebuilt, with the same random
  dimensions, at a coarser resolution (fewer circle segments, for gears and flanges fewer teeth
  and holes); manifold3d's ``simplify`` (which keeps the mesh manifold, but can blur exact
  symmetries by up to 2% of the diameter) is only a last resort,
* of diameter (largest vertex distance) within ``DIAMETER_RANGE_MM``,

together with the symmetries known by construction, in BOP ``models_info.json`` form: the
symmetry losses of 3PT need them (a washer looks the same after any rotation about its axis).
Only *proper* rotations are listed (BOP convention); mirror symmetries are not rotations and
are left out. Dimensions follow common engineering practice (ISO 4014/4032-like bolt and nut
proportions, module-based gears) so the parts look plausible at their true metric size.

Everything is a deterministic function of the ``np.random.Generator`` passed in.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from typing import Any

import manifold3d as mf
import numpy as np
import trimesh

from threept_jax.geometry.diameter import mesh_diameter
from threept_jax.geometry.symmetry import ContinuousSymmetry, Symmetries
from threept_jax.render.mesh import MAX_MESH_FACES

DIAMETER_RANGE_MM = (20.0, 250.0)
DEFAULT_MAX_FACES = 5000
#: The fewest faces every part family fits in.
MIN_MAX_FACES = 500

# A symmetry: a 4x4 proper rigid transform (mm) in a part's construction frame.
_Sym = np.ndarray


@dataclasses.dataclass(frozen=True, eq=False)
class Part:
    """One procedural part.

    Attributes:
      mesh: watertight ``trimesh.Trimesh`` in mm, centred at its bounding-box centre.
      family: the family name (one of ``FAMILIES``).
      params: the sampled dimensions (mm) and options, for provenance.
      symmetries: discrete ones are proper rigid transforms (mm) mapping the mesh onto itself,
        identity excluded; a continuous one leaves the mesh invariant to any rotation about the
        line through its ``offset`` along its ``axis``.
      diameter: largest distance between two vertices, mm.
    """

    mesh: trimesh.Trimesh
    family: str
    params: dict[str, Any]
    symmetries: Symmetries
    diameter: float


# --------------------------------------------------------------------------------------------
# Small geometry helpers.


def _rotation(axis: Sequence[float], angle: float, point: Sequence[float] = (0, 0, 0)) -> _Sym:
    """4x4 rotation by ``angle`` (rad) about the line through ``point`` along ``axis``."""
    a = np.asarray(axis, np.float64)
    a = a / np.linalg.norm(a)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    R = np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * (K @ K)
    p = np.asarray(point, np.float64)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = p - R @ p
    return T


def _cyclic(n: int, axis=(0, 0, 1), point=(0, 0, 0)) -> list[_Sym]:
    """The n-1 non-identity rotations of an n-fold axis."""
    return [_rotation(axis, 2 * math.pi * k / n, point) for k in range(1, n)]


def _flips(n: int, point=(0, 0, 0), phase: float = 0.0) -> list[_Sym]:
    """Half turns about the n in-plane (z = point z) axes at angles phase + pi k / n."""
    return [
        _rotation(
            (math.cos(phase + math.pi * k / n), math.sin(phase + math.pi * k / n), 0),
            math.pi,
            point,
        )
        for k in range(n)
    ]


def _segments(n: int, multiple: int = 1) -> int:
    """Round a circle segment count up to a multiple of ``multiple`` (keeps n-fold symmetry)."""
    n = max(int(n), 3)
    return int(math.ceil(n / multiple) * multiple)


def _polygon_prism(points: Sequence[Sequence[float]], height: float) -> mf.Manifold:
    """Extrude a simple CCW polygon [N, 2] along +z from 0 to ``height``."""
    return mf.Manifold.extrude(mf.CrossSection([np.asarray(points, np.float64)]), height)


def _revolve(profile: Sequence[Sequence[float]], segments: int) -> mf.Manifold:
    """Revolve a (r, z) profile polygon [N, 2] (r >= 0) about the z axis."""
    return mf.CrossSection([np.asarray(profile, np.float64)]).revolve(segments)


def _cylinder(h: float, r: float, segments: int, z0: float = 0.0) -> mf.Manifold:
    return mf.Manifold.cylinder(h, r, r, segments).translate((0.0, 0.0, z0))


def _to_trimesh(m: mf.Manifold) -> trimesh.Trimesh:
    mesh = m.to_mesh64()
    vertices = np.ascontiguousarray(np.asarray(mesh.vert_properties, np.float64)[:, :3])
    faces = np.ascontiguousarray(mesh.tri_verts, np.int64)
    return trimesh.Trimesh(vertices, faces, process=False)


# --------------------------------------------------------------------------------------------
# Families. Each returns (manifold, params, discrete symmetries [4x4 list], continuous
# symmetries [(axis, point)]) in its own construction frame; `generate_part` centres and checks.

_Build = tuple[mf.Manifold, dict[str, Any], list[_Sym], list[tuple[np.ndarray, np.ndarray]]]


def _l_profile(rng: np.random.Generator, budget: int) -> _Build:
    a = rng.uniform(20, 100)
    equal = bool(rng.random() < 0.5)
    b = a if equal else a * rng.uniform(0.4, 0.8)
    t = rng.uniform(0.06, 0.15) * min(a, b)
    length = rng.uniform(30, 220)
    m = _polygon_prism([(0, 0), (a, 0), (a, t), (t, t), (t, b), (0, b)], length)
    # Equal legs: a half turn about the bisector of the legs swaps them and flips z.
    syms = [_rotation((1, 1, 0), math.pi, (0, 0, length / 2))] if equal else []
    return m, dict(leg_a=a, leg_b=b, thickness=t, length=length, equal_legs=equal), syms, []


def _t_profile(rng: np.random.Generator, budget: int) -> _Build:
    w = rng.uniform(20, 100)
    h = w * rng.uniform(0.6, 1.2)
    tf = rng.uniform(0.08, 0.15) * w
    tw = rng.uniform(0.08, 0.15) * w
    length = rng.uniform(30, 220)
    pts = [
        (-tw / 2, 0),
        (tw / 2, 0),
        (tw / 2, h - tf),
        (w / 2, h - tf),
        (w / 2, h),
        (-w / 2, h),
        (-w / 2, h - tf),
        (-tw / 2, h - tf),
    ]
    m = _polygon_prism(pts, length)
    syms = [_rotation((0, 1, 0), math.pi, (0, 0, length / 2))]
    return m, dict(width=w, height=h, flange=tf, web=tw, length=length), syms, []


def _u_profile(rng: np.random.Generator, budget: int) -> _Build:
    w = rng.uniform(20, 120)
    h = w * rng.uniform(0.4, 1.0)
    t = rng.uniform(0.06, 0.12) * w
    length = rng.uniform(30, 220)
    pts = [
        (-w / 2, 0),
        (w / 2, 0),
        (w / 2, h),
        (w / 2 - t, h),
        (w / 2 - t, t),
        (-w / 2 + t, t),
        (-w / 2 + t, h),
        (-w / 2, h),
    ]
    m = _polygon_prism(pts, length)
    syms = [_rotation((0, 1, 0), math.pi, (0, 0, length / 2))]
    return m, dict(width=w, height=h, thickness=t, length=length), syms, []


def _plate(rng: np.random.Generator, budget: int) -> _Build:
    width = rng.uniform(20, 120)
    # Length at least 1.2 x width so the plate has exactly the symmetries of a rectangle (D2).
    length = width * rng.uniform(1.2, 2.2)
    t = rng.uniform(2, 12)
    r_corner = rng.uniform(0.0, 0.2) * width
    nx, ny = int(rng.integers(1, 5)), int(rng.integers(1, 3))
    pitch_x = length / (nx + 1)
    pitch_y = width / (ny + 1)
    d_hole = min(pitch_x, pitch_y) * rng.uniform(0.3, 0.6)
    hole_segments = _segments(min(32, max(8, budget // (40 * nx * ny))), 4)
    if r_corner > 0.5:
        outline = mf.CrossSection.square((length - 2 * r_corner, width - 2 * r_corner), True)
        outline = outline.offset(r_corner, mf.JoinType.Round, 2.0, 32)
    else:
        outline = mf.CrossSection.square((length, width), True)
    holes = [
        mf.CrossSection.circle(d_hole / 2, hole_segments).translate(
            (-length / 2 + pitch_x * (i + 1), -width / 2 + pitch_y * (j + 1))
        )
        for i in range(nx)
        for j in range(ny)
    ]
    asymmetric = bool(rng.random() < 0.3)
    if asymmetric:
        # A small extra hole near one corner: a real part often has a locating hole like this,
        # and it removes every rotation symmetry.
        r_extra = min(d_hole, t, width * 0.1) * 0.5 + 1.0
        holes.append(
            mf.CrossSection.circle(r_extra, 12).translate(
                (length / 2 - pitch_x * 0.5, width / 2 - pitch_y * 0.5)
            )
        )
    section = mf.CrossSection.batch_boolean([outline, *holes], mf.OpType.Subtract)
    m = mf.Manifold.extrude(section, t)
    centre = (0, 0, t / 2)
    syms = [] if asymmetric else [_rotation(ax, math.pi, centre) for ax in np.eye(3)]
    params = dict(
        length=length,
        width=width,
        thickness=t,
        corner_radius=r_corner,
        holes_x=nx,
        holes_y=ny,
        hole_diameter=d_hole,
        locating_hole=asymmetric,
    )
    return m, params, syms, []


def _bracket(rng: np.random.Generator, budget: int) -> _Build:
    a = rng.uniform(20, 120)  # base leg along x
    b = a * rng.uniform(1.25, 1.9)  # upright along z; unequal legs: no rotation symmetry
    w = rng.uniform(15, 80)  # width along y
    t = rng.uniform(0.05, 0.1) * a + 1.5
    base = mf.Manifold.cube((a, w, t))
    upright = mf.Manifold.cube((t, w, b))
    parts = [base, upright]
    gusset = bool(rng.random() < 0.5)
    if gusset:
        g = min(a, b) * rng.uniform(0.35, 0.6)
        tg = t
        tri = _polygon_prism([(t, t), (t + g, t), (t, t + g)], tg)
        # Put the triangle (drawn in x-y) into the x-z plane and centre it across the width.
        parts.append(tri.rotate((90, 0, 0)).translate((0, w / 2 + tg / 2, 0)))
    solid = mf.Manifold.batch_boolean(parts, mf.OpType.Add)
    d_hole = min(w * rng.uniform(0.2, 0.4), 0.35 * a)
    segs = _segments(min(24, max(8, budget // 60)), 4)
    n_base = int(max(1, min(3, (a - t) // (2.5 * d_hole))))
    n_up = int(max(1, min(3, (b - t) // (2.5 * d_hole))))
    y_hole = w / 4 if gusset else w / 2
    holes = []
    for i in range(n_base):
        x = t + (a - t) * (i + 1) / (n_base + 1)
        holes.append(_cylinder(t + 2, d_hole / 2, segs, -1).translate((x, y_hole, 0)))
    for j in range(n_up):
        z = t + (b - t) * (j + 1) / (n_up + 1)
        holes.append(
            _cylinder(t + 2, d_hole / 2, segs, -1).rotate((0, 90, 0)).translate((0, y_hole, z))
        )
    m = mf.Manifold.batch_boolean([solid, *holes], mf.OpType.Subtract)
    params = dict(
        base=a,
        upright=b,
        width=w,
        thickness=t,
        gusset=gusset,
        hole_diameter=d_hole,
        holes_base=n_base,
        holes_upright=n_up,
    )
    return m, params, [], []


def _involute_gear_outline(n_teeth: int, module: float, flank_points: int) -> np.ndarray:
    """Outline [P, 2] (CCW) of a spur gear with involute flanks, 20 degree pressure angle.

    Tooth k is centred on the angle 2 pi k / n, so the outline is symmetric about every
    line through the centre at angle pi j / n.
    """
    r_pitch = module * n_teeth / 2
    r_base = r_pitch * math.cos(math.radians(20))
    r_tip = r_pitch + module
    r_root = max(r_pitch - 1.25 * module, 0.5 * r_pitch)

    def inv(r):
        alpha = math.acos(min(1.0, r_base / r))
        return math.tan(alpha) - alpha

    half_pitch = math.pi / (2 * n_teeth)  # half tooth thickness (angle) on the pitch circle
    r_start = max(r_base, r_root)
    radii = np.linspace(r_start, r_tip, flank_points)
    psi = np.array([half_pitch + inv(r_pitch) - inv(r) for r in radii])
    psi = np.maximum(psi, 0.02 * half_pitch)
    # Root half angle equals the start-of-flank half angle (radial line from root to base circle).
    pts = []
    for k in range(n_teeth):
        c = 2 * math.pi * k / n_teeth
        # Right flank (angle c - psi) from root to tip, then left flank back down.
        flank_r = [(r, c - p) for r, p in zip(radii, psi)]
        flank_l = [(r, c + p) for r, p in zip(radii[::-1], psi[::-1])]
        tooth = [(r_root, c - psi[0])] if r_root < r_start - 1e-9 else []
        tooth += flank_r + flank_l
        if r_root < r_start - 1e-9:
            tooth.append((r_root, c + psi[0]))
        pts += tooth
    return np.array([(r * math.cos(a), r * math.sin(a)) for r, a in pts])


def _gear(rng: np.random.Generator, budget: int) -> _Build:
    # Fewer teeth for small face budgets (each tooth costs ~20 faces at the coarsest).
    n = min(int(rng.integers(12, 49)), max(12, budget // 20))
    d_out = rng.uniform(25, 220)
    module = d_out / (n + 2)
    thickness = module * rng.uniform(4, 10)
    flank_points = int(np.clip(budget // (16 * n), 2, 6))
    outline = mf.CrossSection([_involute_gear_outline(n, module, flank_points)])
    r_root = max(module * n / 2 - 1.25 * module, 0.25 * module * n)
    bore = rng.uniform(0.2, 0.4) * r_root
    segs = min(64, max(8, budget // 40))
    # A multiple of 2n keeps the bore polygon exactly n-fold and mirror symmetric.
    segs = _segments(segs, 2 * n) if 2 * n <= segs else _segments(segs, 4)
    section = outline - mf.CrossSection.circle(bore, segs)
    keyway = bool(rng.random() < 0.3)
    if keyway:
        kw = bore * 0.5
        section = section - mf.CrossSection.square((bore * 0.5, kw), True).translate((bore, 0))
    m = mf.Manifold.extrude(section, thickness).translate((0, 0, -thickness / 2))
    hub = bool(rng.random() < 0.4)
    if hub:
        r_hub = min(r_root * rng.uniform(0.55, 0.85), r_root - 1.0)
        h_hub = thickness * rng.uniform(0.3, 0.8)
        hub_m = _cylinder(h_hub, r_hub, segs, thickness / 2 - 0.01)
        m = m + hub_m
        m = m - _cylinder(thickness + h_hub + 2, bore, segs, -thickness / 2 - 1)
        if keyway:
            cutter = mf.Manifold.cube((bore * 0.5, bore * 0.5, thickness + h_hub + 2), True)
            m = m - cutter.translate((bore, 0, h_hub / 2))
    syms: list[_Sym] = []
    if not keyway:
        syms += _cyclic(n)
    if not hub:
        # Tooth 0 and the keyway lie on the x axis: with a keyway only that half turn survives.
        syms += _flips(1) if keyway else _flips(n)
    params = dict(
        teeth=n,
        module=module,
        outer_diameter=module * (n + 2),
        thickness=thickness,
        bore=2 * bore,
        keyway=keyway,
        hub=hub,
    )
    return m, params, syms, []


_METRIC = {  # nominal d: (pitch, across flats s, head height k)  (ISO 4014 / 4032 like)
    3: (0.5, 5.5, 2.0),
    4: (0.7, 7.0, 2.8),
    5: (0.8, 8.0, 3.5),
    6: (1.0, 10.0, 4.0),
    8: (1.25, 13.0, 5.3),
    10: (1.5, 16.0, 6.4),
    12: (1.75, 18.0, 7.5),
    16: (2.0, 24.0, 10.0),
    20: (2.5, 30.0, 12.5),
    24: (3.0, 36.0, 15.0),
    30: (3.5, 46.0, 18.7),
    36: (4.0, 55.0, 22.5),
    42: (4.5, 65.0, 26.0),
    48: (5.0, 75.0, 30.0),
}


def _hex_prism(across_flats: float, h: float, z0: float = 0.0) -> mf.Manifold:
    """Hexagonal prism with vertices at angles 0, 60, ... degrees."""
    r = across_flats / math.sqrt(3)
    return _cylinder(h, r, 6, z0)


def _bolt(rng: np.random.Generator, budget: int) -> _Build:
    d = int(rng.choice([3, 4, 5, 6, 8, 10, 12, 16, 20, 24]))
    pitch, s, k = _METRIC[d]
    lo = max(2 * d, 20.0)
    length = float(np.clip(rng.uniform(lo, min(10 * d, 200)), lo, 200))
    socket = bool(rng.random() < 0.35)
    segs = _segments(min(48, max(12, budget // 80)), 6)
    # Shaft profile (r, z) with a tip chamfer, optionally with thread grooves (revolved rings:
    # they read as threads in images and keep the axial symmetry exact).
    r = d / 2
    c = min(pitch, 0.1 * d + 0.3)
    n_thread = int(length * rng.uniform(0.4, 1.0) / pitch)
    threaded = bool(rng.random() < 0.6) and 4 * n_thread * segs < 0.6 * budget
    profile = [(0.0, 0.0), (r - c, 0.0), (r, c)]
    if threaded:
        depth = 0.3 * pitch
        z = c
        for _ in range(n_thread):
            profile += [(r, z), (r - depth, z + pitch / 2)]
            z += pitch
        profile.append((r, z))
    profile += [(r, length + 0.01), (0.0, length + 0.01)]
    shaft = _revolve(profile, segs)
    if socket:
        # ISO 4762-like socket head cap screw: cylinder head with a hexagon socket.
        dk, kk = 1.5 * d, 1.0 * d
        head = _cylinder(kk, dk / 2, segs, length)
        head = head - _hex_prism(0.8 * d, 0.6 * kk + 0.01, length + 0.4 * kk)
    else:
        head = _hex_prism(s, k, length)
        # Chamfered top edge of the hex head: intersect with a cone.
        r_top = 0.95 * s / 2
        cone = mf.Manifold.cylinder(k + r_top, r_top + k, 0.0, segs).translate((0, 0, length))
        head = head ^ cone
    m = shaft + head
    syms = _cyclic(6)
    params = dict(nominal=d, length=length, socket_head=socket, threaded=threaded, pitch=pitch)
    return m, params, syms, []


def _nut(rng: np.random.Generator, budget: int) -> _Build:
    d = int(rng.choice([10, 12, 16, 20, 24, 30, 36, 42, 48]))
    pitch, s, k = _METRIC[d]
    s *= rng.uniform(0.95, 1.05)
    h = d * rng.uniform(0.5, 1.0)  # jam nut .. heavy nut
    segs = _segments(min(48, max(12, budget // 60)), 12)
    r_v = s / math.sqrt(3)
    body = _hex_prism(s, h, -h / 2)
    # Chamfered faces as the intersection with a 45 degree double cone, as on ISO 4032 nuts;
    # some nuts are chamfered on one face only, which leaves the 6-fold axis but no half turns.
    r_top = s / 2 * rng.uniform(0.9, 1.0)
    cone = mf.Manifold.cylinder(h / 2 + r_top, r_top + h / 2, 0.0, segs)
    both = bool(rng.random() < 0.7)
    lower = cone.mirror((0, 0, 1)) if both else _cylinder(h / 2 + 1, r_v + 1, segs, -h / 2 - 1)
    body = body ^ (cone + lower)
    bore = _cylinder(h + 2, 0.85 * d / 2, segs, -h / 2 - 1)
    m = body - bore
    syms = _cyclic(6) + (_flips(6) if both else [])
    return m, dict(nominal=d, across_flats=s, height=h, chamfer_both=both), syms, []


def _washer(rng: np.random.Generator, budget: int) -> _Build:
    d_out = rng.uniform(20, 150)
    d_in = d_out * rng.uniform(0.35, 0.65)
    t = max(0.8, d_out * rng.uniform(0.03, 0.12))
    segs = _segments(min(96, max(24, budget // 10)), 4)
    m = _cylinder(t, d_out / 2, segs, -t / 2) - _cylinder(t + 2, d_in / 2, segs, -t / 2 - 1)
    return (
        m,
        dict(outer=d_out, inner=d_in, thickness=t),
        _flips(1),
        [(np.array([0.0, 0, 1]), np.zeros(3))],
    )


def _flange(rng: np.random.Generator, budget: int) -> _Build:
    d_out = rng.uniform(60, 230)
    t = d_out * rng.uniform(0.06, 0.12)
    bore = d_out * rng.uniform(0.2, 0.4)
    n_holes = int(rng.choice([4, 6, 8, 12]))
    # Fewer bolt holes for small face budgets (each costs ~60 faces at the coarsest).
    n_holes = min(n_holes, max([k for k in (4, 6, 8, 12) if 60 * k <= budget], default=4))
    r_circle = (bore / 2 + d_out / 2) / 2
    d_hole = min(0.35 * (d_out / 2 - bore / 2), 0.6 * 2 * math.pi * r_circle / n_holes)
    segs = _segments(min(64, max(16, budget // 30)), 2 * n_holes)
    hole_segs = int(np.clip(budget // (16 * n_holes), 6, 16)) // 2 * 2
    section = mf.CrossSection.circle(d_out / 2, segs) - mf.CrossSection.circle(bore / 2, segs)
    for i in range(n_holes):
        angle = 360.0 * i / n_holes
        # Rotate the whole hole (not only its centre) so the n-fold symmetry is exact.
        hole = mf.CrossSection.circle(d_hole / 2, hole_segs).translate((r_circle, 0)).rotate(angle)
        section = section - hole
    m = mf.Manifold.extrude(section, t).translate((0, 0, -t / 2))
    hub = bool(rng.random() < 0.6)
    if hub:
        r_hub = min(
            bore / 2 + 0.6 * (r_circle - d_hole / 2 - bore / 2), r_circle - d_hole / 2 - 1.0
        )
        h_hub = t * rng.uniform(0.8, 2.5)
        neck = _revolve(
            [(bore / 2, 0), (r_hub, 0), (r_hub * 0.85 + bore / 2 * 0.15, h_hub), (bore / 2, h_hub)],
            segs,
        )
        m = m + neck.translate((0, 0, t / 2 - 0.01))
    syms = _cyclic(n_holes) + ([] if hub else _flips(n_holes))
    params = dict(outer=d_out, thickness=t, bore=bore, holes=n_holes, hole_diameter=d_hole, hub=hub)
    return m, params, syms, []


def _elbow(rng: np.random.Generator, budget: int) -> _Build:
    r_out = rng.uniform(8, 45)
    r_in = r_out * rng.uniform(0.6, 0.9)
    bend = r_out * rng.uniform(1.5, 3.0)
    angle = float(rng.choice([45.0, 90.0]))
    ext = r_out * rng.uniform(0.0, 1.5)
    seg_tube = _segments(min(32, max(12, budget // 100)), 4)
    seg_bend = _segments(min(24, max(6, budget // (4 * seg_tube))), 1)
    ring = mf.CrossSection.circle(r_out, seg_tube) - mf.CrossSection.circle(r_in, seg_tube)
    m = ring.translate((bend, 0)).revolve(seg_bend, angle)  # seg_bend segments over the angle
    if ext > 0.5:
        # Straight ends of equal length keep the half-turn symmetry about the bisector.
        straight = mf.Manifold.extrude(ring, ext)  # along +z, centred on the z axis
        # End at angle 0 lies in the x-z plane at y = 0: extend towards -y.
        end0 = straight.rotate((90, 0, 0)).translate((bend, 0, 0))
        # End at `angle`: rotate the same piece about z.
        end1 = straight.rotate((-90, 0, 0)).translate((bend, 0, 0)).rotate((0, 0, angle))
        m = mf.Manifold.batch_boolean([m, end0, end1], mf.OpType.Add)
    half = math.radians(angle) / 2
    syms = [_rotation((math.cos(half), math.sin(half), 0), math.pi)]
    params = dict(outer=2 * r_out, inner=2 * r_in, bend_radius=bend, angle=angle, straight=ext)
    return m, params, syms, []


def _shaft(rng: np.random.Generator, budget: int) -> _Build:
    n_steps = int(rng.integers(1, 5))
    r0 = rng.uniform(6, 40)
    radii = [r0]
    for _ in range(n_steps - 1):
        radii.append(max(3.0, radii[-1] * rng.uniform(0.6, 0.9)))
    lengths = [rng.uniform(0.5, 3.0) * r0 for _ in range(n_steps)]
    palindrome = bool(rng.random() < 0.35)
    if palindrome:
        # Largest step in the middle, mirrored: then a half turn about x is a symmetry too.
        radii = radii[::-1] + radii[1:]
        lengths = lengths[::-1] + lengths[1:]
    chamfer = rng.uniform(0.03, 0.08) * min(radii)
    profile = [(0.0, 0.0)]
    z = 0.0
    for i, (r, h) in enumerate(zip(radii, lengths)):
        c_lo = chamfer if i == 0 or radii[i - 1] < r else 0.0
        c_hi = chamfer if i == len(radii) - 1 or radii[i + 1] < r else 0.0
        profile += [(r - c_lo, z), (r, z + c_lo), (r, z + h - c_hi), (r - c_hi, z + h)]
        z += h
    profile.append((0.0, z))
    # Drop repeated points (zero chamfers) so the polygon is simple.
    clean = [profile[0]]
    for p in profile[1:]:
        if math.dist(p, clean[-1]) > 1e-9:
            clean.append(p)
    segs = _segments(min(64, max(8, budget // (8 * len(clean)))), 4)
    m = _revolve(clean, segs).translate((0, 0, -z / 2))
    syms = _flips(1) if palindrome else []
    params = dict(
        radii=[float(r) for r in radii],
        lengths=[float(h) for h in lengths],
        chamfer=chamfer,
        symmetric=palindrome,
    )
    return m, params, syms, [(np.array([0.0, 0, 1]), np.zeros(3))]


_FAMILIES: dict[str, Callable[[np.random.Generator, int], _Build]] = {
    "l_profile": _l_profile,
    "t_profile": _t_profile,
    "u_profile": _u_profile,
    "plate": _plate,
    "bracket": _bracket,
    "gear": _gear,
    "bolt": _bolt,
    "nut": _nut,
    "washer": _washer,
    "flange": _flange,
    "elbow": _elbow,
    "shaft": _shaft,
}
FAMILIES: tuple[str, ...] = tuple(_FAMILIES)


def generate_part(
    rng: np.random.Generator,
    family: str | None = None,
    *,
    max_faces: int = DEFAULT_MAX_FACES,
    diameter_range: tuple[float, float] = DIAMETER_RANGE_MM,
) -> Part:
    """Build one random part of ``family`` (uniformly chosen from ``FAMILIES`` if None).

    The mesh is centred at its bounding-box centre; symmetry transforms are re-expressed in that
    frame. A part whose diameter falls outside ``diameter_range`` is scaled uniformly into it
    (the factor is recorded in ``params["scale"]``), so sizes stay metric and plausible.
    """
    if family is None:
        family = FAMILIES[int(rng.integers(len(FAMILIES)))]
    if family not in _FAMILIES:
        raise ValueError(f"unknown part family {family!r}; choose one of {FAMILIES}")
    if max_faces < MIN_MAX_FACES:
        raise ValueError(f"max_faces={max_faces} is too small for every part family; use >= "
                         f"{MIN_MAX_FACES}")
    if max_faces > MAX_MESH_FACES:
        raise ValueError(
            f"max_faces={max_faces} (--procedural-max-faces) is above {MAX_MESH_FACES}, more "
            "than a loader takes in bounded memory; lower it (the default is "
            f"{DEFAULT_MAX_FACES})"
        )
    lo, hi = diameter_range
    if not 0 < lo < hi:
        raise ValueError(f"diameter_range {diameter_range} must satisfy 0 < low < high (mm)")

    # Build at the budget; if the part comes out too fine, rebuild the *same* part (same random
    # draws, the generator state is restored) at a coarser resolution. Simplification, which
    # moves surfaces slightly, is only the last resort.
    state = rng.bit_generator.state
    budget = max_faces
    for _ in range(6):
        rng.bit_generator.state = state
        m, params, syms, cont = _FAMILIES[family](rng, budget)
        if m.num_tri() <= max_faces:
            break
        budget = int(budget * 0.7)
    if m.status() != mf.Error.NoError or m.is_empty():
        raise RuntimeError(f"procedural {family} with {params} failed in manifold3d: {m.status()}")

    lo_b, hi_b = np.asarray(m.bounding_box()).reshape(2, 3)
    centre = (lo_b + hi_b) / 2
    m = m.translate(tuple(-centre))
    # A symmetry x -> R x + t of the construction frame, in the centred frame x' = x - c, is
    # x' -> R x' + (R c + t - c).
    S = np.array(syms, np.float64).reshape(-1, 4, 4)
    S[:, :3, 3] += np.einsum("sij,j->si", S[:, :3, :3], centre) - centre
    cont = [(a / np.linalg.norm(a), np.asarray(p, np.float64) - centre) for a, p in cont]

    diameter = mesh_diameter(np.asarray(m.to_mesh64().vert_properties)[:, :3])
    scale = float(np.clip(diameter, lo, hi) / diameter)
    if scale != 1.0:
        m = m.scale((scale, scale, scale))
        S[:, :3, 3] *= scale
        cont = [(a, p * scale) for a, p in cont]
    params["scale"] = scale

    if m.num_tri() > max_faces:
        # manifold3d's simplify keeps the mesh manifold; raise the tolerance until it fits.
        tol = 1e-3 * diameter * scale
        while m.num_tri() > max_faces and tol < 0.02 * diameter * scale:
            m = m.simplify(tol)
            tol *= 1.6
        if m.num_tri() > max_faces:
            raise RuntimeError(
                f"{family} has {m.num_tri()} faces after simplification, above max_faces="
                f"{max_faces}; raise max_faces"
            )

    mesh = _to_trimesh(m)
    # Exact zero for symmetry transforms that are numerically identity-like in translation.
    S[np.abs(S) < 1e-12] = 0.0
    return Part(
        mesh=mesh,
        family=family,
        params=params,
        symmetries=Symmetries(S, [ContinuousSymmetry(a, o) for a, o in cont]),
        diameter=mesh_diameter(mesh.vertices),
    )


def generate_parts(
    rng: np.random.Generator, n: int, families: Sequence[str] | None = None, **kwargs
) -> list[Part]:
    """``n`` parts with families drawn uniformly from ``families`` (default: all)."""
    fams = tuple(families) if families is not None else FAMILIES
    return [generate_part(rng, fams[int(rng.integers(len(fams)))], **kwargs) for _ in range(n)]
