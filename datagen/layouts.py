"""Scene layouts for the synthetic data generator: dropped, floating and densely packed objects.

3PT's training images (docs/design.md section 1; the paper averages ~110 annotated instances
per image) are mostly objects dropped onto a surface or into a bin, some floating in the air and
some tightly packed. This module places instances of meshes in a world frame (millimetres, z up, the
support surface at z = 0) and returns their poses ``T_world_obj``:

* ``drop_layout``: a real rigid-body simulation with MuJoCo. Objects spawn above a plane or a bin
  at random orientations, fall and settle (until every body is slower than a threshold, or a
  step cap). Collision geometry is a set of convex pieces per mesh (``collision_shape``): an
  approximate convex decomposition by axis-aligned cuts whose piece hulls contain the real mesh,
  so settled real meshes can interpenetrate no more than MuJoCo lets the pieces do.
* ``float_layout``: random non-overlapping poses in a box, by rejection sampling (bounding
  spheres first, then an exact convex-piece separation test by linear programming).
* ``pack_layout``: dense scenes, either a tight grid of parts lying on their most stable face
  ("grid") or a pile dropped into a bin sized to just hold them ("pile").

MuJoCo works in SI units: vertices are converted to metres (mm / 1000) inside this module and
poses back to mm on output. Everything is deterministic given the ``np.random.Generator`` and the
inputs (MuJoCo is deterministic on one machine for a fixed model and timestep).
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Sequence

import mujoco
import numpy as np
import trimesh
from scipy.optimize import linprog
from scipy.spatial import ConvexHull
from scipy.spatial.transform import Rotation

from threept_jax.geometry.rotations import random_rotations

# --------------------------------------------------------------------------------------------
# Collision shapes.


@dataclasses.dataclass(frozen=True, eq=False)
class CollisionShape:
    """Everything the layouts need to know about one mesh (object frame, mm).

    Attributes:
      vertices: [N, 3] the real mesh's vertices.
      pieces: tuple of [M_i, 3] convex-hull vertices of the collision pieces; the union of the
        piece hulls contains the mesh surface.
      volume: solid volume, mm^3 (of the hull when the mesh is not watertight).
      com: [3] centre of mass (uniform density), mm.
      inertia: [3, 3] inertia tensor about ``com`` for unit density, mm^5.
      radius: bounding-sphere radius about the object origin, mm.
      rest_rotation: [3, 3] R_world_obj that lays the mesh on its most stable hull facet (the facet
        closest to the centre of mass, which is always stable), facet normal to -z.
      name: for messages.
    """

    vertices: np.ndarray
    pieces: tuple[np.ndarray, ...]
    volume: float
    com: np.ndarray
    inertia: np.ndarray
    radius: float
    rest_rotation: np.ndarray
    name: str = ""


def _hull_volume(points: np.ndarray) -> float:
    try:
        return float(ConvexHull(points).volume)
    except Exception:  # flat or too few points: no volume
        return 0.0


def _piece_points(tris: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unique vertices [V, 3] and unique edges (a [E, 3], b [E, 3]) of triangles [T, 3, 3]."""
    a = tris.reshape(-1, 3)
    b = np.roll(tris, -1, axis=1).reshape(-1, 3)
    # Canonical endpoint order, so that an edge shared by two triangles appears once.
    less = _lex_less(a, b)[:, None]
    edges = np.unique(np.concatenate([np.where(less, a, b), np.where(less, b, a)], 1), axis=0)
    return np.unique(a, axis=0), edges[:, :3], edges[:, 3:]


def _lex_less(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise lexicographic a < b for [N, 3] arrays."""
    lt, gt = a < b, a > b
    return lt[:, 0] | (~gt[:, 0] & (lt[:, 1] | (~gt[:, 1] & lt[:, 2])))


def _split_points(
    points: tuple[np.ndarray, np.ndarray, np.ndarray], axis: int, c: float
) -> tuple[np.ndarray, np.ndarray]:
    """Points of a piece (``_piece_points``) on each side of the plane x_axis = c.

    Each side gets its vertices plus the points where edges cross the plane, so the hull of a
    side contains that side of every triangle (a triangle cut by a plane is the convex hull of
    those points).
    """
    v, a, b = points
    d = v[:, axis] - c
    da = a[:, axis] - c
    db = b[:, axis] - c
    cross = (da * db) < 0
    t = da[cross] / (da[cross] - db[cross])
    x = a[cross] + t[:, None] * (b[cross] - a[cross])
    x[:, axis] = c
    return np.concatenate([v[d <= 0], x]), np.concatenate([v[d >= 0], x])


def _clip_triangles(tris: np.ndarray, axis: int, c: float, keep_below: bool) -> np.ndarray:
    """Clip triangles [T, 3, 3] to the half space x_axis <= c (or >= c); returns [T', 3, 3]."""
    sign = 1.0 if keep_below else -1.0
    d = sign * (tris[..., axis] - c)  # <= 0 is kept
    inside = d <= 0
    n_in = inside.sum(1)
    out = [tris[n_in == 3]]
    for n_keep in (1, 2):
        sel = n_in == n_keep
        if not sel.any():
            continue
        t, dd, ins = tris[sel], d[sel], inside[sel]
        # Rotate each triangle so that the odd vertex (the lone kept one for n_keep = 1, the lone
        # dropped one for n_keep = 2) comes first; the cyclic order (orientation) is preserved.
        odd = ins if n_keep == 1 else ~ins
        first = np.argmax(odd, axis=1)
        idx = (first[:, None] + np.arange(3)[None]) % 3
        t = np.take_along_axis(t, idx[..., None], axis=1)
        dd = np.take_along_axis(dd, idx, axis=1)
        p0, p1, p2 = t[:, 0], t[:, 1], t[:, 2]
        x01 = p0 + (dd[:, 0] / (dd[:, 0] - dd[:, 1]))[:, None] * (p1 - p0)
        x02 = p0 + (dd[:, 0] / (dd[:, 0] - dd[:, 2]))[:, None] * (p2 - p0)
        if n_keep == 1:
            out.append(np.stack([p0, x01, x02], 1))
        else:
            out.append(np.stack([x01, p1, p2], 1))
            out.append(np.stack([x01, p2, x02], 1))
    return np.concatenate(out)


def _cut_candidates(tris: np.ndarray, axis: int, n_faces: int, n_quantiles: int) -> np.ndarray:
    """Cut positions along ``axis`` for a piece (triangles [T, 3, 3]), inside its extent.

    Steps of a part (the inner face of an L, the underside of a bolt head) are planes
    perpendicular to an axis that carry much face area: the ``n_faces`` coordinates with most
    such area are tried just below and just above (a cut exactly in a face plane would give the
    face to both sides), plus ``n_quantiles`` evenly spaced quantiles for curved shapes.
    """
    pts = tris.reshape(-1, 3)
    lo, hi = pts[:, axis].min(), pts[:, axis].max()
    extent = hi - lo
    # Keep pieces at least 2% of the extent (and 0.5 mm) thick: no flat slivers.
    margin = max(0.02 * extent, 0.5)
    eps = 1e-4 * extent
    cross = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    flat = np.abs(cross[:, axis]) > 0.999 * (2 * area + 1e-30)
    coords = np.round(tris[flat, 0, axis], 6)
    cand = []
    if len(coords):
        uniq, inv = np.unique(coords, return_inverse=True)
        weight = np.bincount(inv, weights=area[flat])
        top = uniq[np.argsort(-weight, kind="stable")[:n_faces]]
        cand += [c + d for c in np.sort(top) for d in (-eps, eps)]
    cand += list(np.quantile(pts[:, axis], np.linspace(0, 1, n_quantiles + 2)[1:-1]))
    cand = np.unique(np.asarray(cand, np.float64))
    return cand[(cand > lo + margin) & (cand < hi - margin)]


def convex_pieces(
    mesh: trimesh.Trimesh,
    max_pieces: int = 8,
    min_gain: float = 0.03,
    n_faces: int = 6,
    n_quantiles: int = 4,
    proxy_faces: int = 2000,
) -> list[np.ndarray]:
    """Approximate convex decomposition by greedy axis-aligned cuts; returns hull vertices [M_i, 3].

    Starting from the whole mesh, repeatedly apply the single cut (an axis-aligned plane at a
    candidate of ``_cut_candidates`` in one piece) that most reduces the summed hull volume,
    while the reduction is at least ``min_gain`` of the first hull's volume and there are fewer
    than ``max_pieces`` pieces. Cuts only split triangles, so the union of the piece hulls always
    contains the whole mesh surface: the real mesh can only touch what the pieces touch. This is
    enough for the concavities of industrial parts (L/T/U profiles, brackets, bolt heads);
    holes and curved pockets are not carved out. Axes are the mesh's own (CAD parts are usually
    modelled axis-aligned). Meshes above ``proxy_faces`` faces choose their cuts on a decimated
    copy (fast-simplification) and then apply them to the full mesh, so containment still holds.
    """
    faces = np.asarray(mesh.faces)
    vertices = np.asarray(mesh.vertices, np.float64)
    full = vertices[faces]
    proxy = full
    if len(faces) > proxy_faces:
        import fast_simplification

        # Fresh writable C arrays: the binding rejects read-only (trimesh-cached) buffers.
        pv, pf = fast_simplification.simplify(
            np.array(vertices, np.float64, order="C"),
            np.array(faces, np.int32, order="C"),
            target_count=proxy_faces,
        )
        if len(pf) >= 4:
            proxy = np.asarray(pv, np.float64)[np.asarray(pf)]

    def best_cut(tris: np.ndarray) -> tuple[float, int, float, float]:
        """(gain, axis, position, hull volume) of the best cut of one piece."""
        pts = _piece_points(tris)
        volume = _hull_volume(pts[0])
        best = (-np.inf, 0, 0.0, volume)
        for axis in range(3):
            for c in _cut_candidates(tris, axis, n_faces, n_quantiles):
                below, above = _split_points(pts, axis, float(c))
                gain = volume - _hull_volume(below) - _hull_volume(above)
                if gain > best[0]:
                    best = (gain, axis, float(c), volume)
        return best

    pieces = [proxy]
    bests = [best_cut(proxy)]  # cached per piece: only the two new pieces change per step
    total = bests[0][3]
    cuts = []  # (piece index, axis, position) in order
    while len(pieces) < max_pieces and total > 0:
        i = int(np.argmax([b[0] for b in bests]))
        gain, axis, c, _ = bests[i]
        if gain < min_gain * total:
            break
        cuts.append((i, axis, c))
        p = pieces.pop(i)
        bests.pop(i)
        for keep_below in (False, True):  # inserted at i in turn: below first, then above
            q = _clip_triangles(p, axis, c, keep_below)
            pieces.insert(i, q)
            bests.insert(i, best_cut(q))
    if proxy is not full:
        pieces = [full]
        for i, axis, c in cuts:
            p = pieces.pop(i)
            for keep_below in (False, True):
                pieces.insert(i, _clip_triangles(p, axis, c, keep_below))
    out = []
    for p in pieces:
        pts = np.unique(p.reshape(-1, 3), axis=0)
        if len(pts) < 4:
            continue
        try:
            out.append(pts[ConvexHull(pts).vertices])
        except Exception:
            continue  # a flat piece has no volume to collide with; its neighbours cover it
    return out


def _stable_rotation(hull: trimesh.Trimesh, com: np.ndarray) -> np.ndarray:
    """R that puts the hull facet nearest the centre of mass on the ground (normal to -z).

    The facet (plane of the hull) closest to the centre of mass is always a stable resting face:
    the centre of mass projects inside it, since otherwise a neighbouring facet would be closer.
    """
    normals = np.asarray(hull.face_normals)
    offsets = np.einsum("fi,fi->f", normals, np.asarray(hull.vertices)[hull.faces[:, 0]])
    dist = offsets - normals @ com
    n = normals[int(np.argmin(dist))]
    # Rotation taking n to -z (Rodrigues about n x -z).
    target = np.array([0.0, 0.0, -1.0])
    v = np.cross(n, target)
    s, c = np.linalg.norm(v), float(n @ target)
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    K = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]]) / s
    ang = math.atan2(s, c)
    return np.eye(3) + math.sin(ang) * K + (1 - math.cos(ang)) * (K @ K)


def collision_shape(mesh: trimesh.Trimesh, name: str = "", max_pieces: int = 8) -> CollisionShape:
    """Collision pieces, mass properties and rest pose of ``mesh`` (mm). Raises ValueError if bad.

    Compute it once per mesh and reuse it across scenes (it costs milliseconds to a second).
    """
    vertices = np.asarray(mesh.vertices, np.float64)
    if len(vertices) < 4 or len(mesh.faces) < 4 or not np.isfinite(vertices).all():
        raise ValueError(f"mesh {name!r} has too few or non-finite vertices/faces for physics")
    try:
        hull = trimesh.Trimesh(vertices, process=False).convex_hull
    except Exception as e:
        raise ValueError(
            f"mesh {name!r} is degenerate (flat or a line): no convex hull ({e})"
        ) from e
    if hull.volume <= 1e-6:
        raise ValueError(f"mesh {name!r} has no volume (flat): it cannot be simulated")
    solid = mesh if (mesh.is_watertight and mesh.volume > 0) else hull
    props = solid.mass_properties
    volume = float(props["volume"])
    com = np.asarray(props["center_mass"], np.float64)
    inertia = np.asarray(props["inertia"], np.float64) / props["density"]
    pieces = convex_pieces(mesh, max_pieces=max_pieces)
    if not pieces:
        pieces = [vertices[ConvexHull(vertices).vertices]]
    return CollisionShape(
        vertices=vertices,
        pieces=tuple(pieces),
        volume=volume,
        com=com,
        inertia=inertia,
        radius=float(np.linalg.norm(vertices, axis=1).max()),
        rest_rotation=_stable_rotation(hull, com),
        name=name,
    )


def collision_shapes(
    meshes: Sequence[trimesh.Trimesh], names: Sequence[str] | None = None, max_pieces: int = 8
) -> tuple[list[CollisionShape | None], int]:
    """``collision_shape`` for many meshes; a bad mesh becomes None with a warning and a count.

    Returns (shapes, number skipped). Layouts ignore instances whose shape is None.
    """
    shapes: list[CollisionShape | None] = []
    skipped = 0
    for i, m in enumerate(meshes):
        name = names[i] if names is not None else f"mesh {i}"
        try:
            shapes.append(collision_shape(m, name=name, max_pieces=max_pieces))
        except Exception as e:  # one bad mesh must never abort a scene
            warnings.warn(f"skipping {name} for physics: {e}", RuntimeWarning, stacklevel=2)
            shapes.append(None)
            skipped += 1
    return shapes, skipped


# --------------------------------------------------------------------------------------------
# Supports and results.


@dataclasses.dataclass(frozen=True)
class Bin:
    """An open box on the ground plane, centred on the world origin (mm).

    inner_size (x, y): inner footprint; height: wall height above the floor; wall: thickness.
    """

    inner_size: tuple[float, float]
    height: float
    wall: float = 10.0

    def wall_boxes(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """The four walls as (centre [3], half extents [3]) boxes, mm."""
        ix, iy = self.inner_size[0] / 2, self.inner_size[1] / 2
        w, h = self.wall, self.height
        return [
            (np.array([ix + w / 2, 0.0, h / 2]), np.array([w / 2, iy + w, h / 2])),
            (np.array([-ix - w / 2, 0.0, h / 2]), np.array([w / 2, iy + w, h / 2])),
            (np.array([0.0, iy + w / 2, h / 2]), np.array([ix, w / 2, h / 2])),
            (np.array([0.0, -iy - w / 2, h / 2]), np.array([ix, w / 2, h / 2])),
        ]


@dataclasses.dataclass(frozen=True)
class Support:
    """What the objects rest on: the ground plane z = ``plane_z`` (mm), optionally a bin on it.

    ``plane_z`` is None for floating scenes (no support to render).
    """

    plane_z: float | None = 0.0
    bin: Bin | None = None

    def meshes(self, floor_size: float = 2000.0) -> list[trimesh.Trimesh]:
        """Render/test geometry (mm): a floor square of side ``floor_size`` and the bin walls."""
        out = []
        if self.plane_z is not None:
            s = floor_size / 2
            z = self.plane_z
            v = np.array([[-s, -s, z], [s, -s, z], [s, s, z], [-s, s, z]])
            out.append(trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3]], process=False))
        if self.bin is not None:
            for centre, half in self.bin.wall_boxes():
                box = trimesh.creation.box(extents=2 * half)
                box.apply_translation(centre + np.array([0.0, 0.0, self.plane_z or 0.0]))
                out.append(box)
        return out


@dataclasses.dataclass(frozen=True)
class Layout:
    """Instances of a scene.

    Attributes:
      mesh_index: [O] int, index of each instance's mesh in the list of shapes given.
      T_world_obj: [O, 4, 4] float64, object-to-world poses, translation in mm.
      support: the support geometry (plane and bin) for the renderer.
      settled: drop/pile: every body came to rest before the step cap. True otherwise.
      sim_time: simulated seconds (0 without physics).
      removed: instances dropped (could not be placed, or ended outside the bin / area).
    """

    mesh_index: np.ndarray
    T_world_obj: np.ndarray
    support: Support
    settled: bool = True
    sim_time: float = 0.0
    removed: int = 0


def choose_instances(
    rng: np.random.Generator, num_meshes: int, num_instances: int, num_distinct: int | None = None
) -> np.ndarray:
    """Mesh index per instance [num_instances]: ``num_distinct`` meshes, each at least once.

    Duplicates of a mesh (as in bin picking) come from assigning the remaining instances to the
    chosen meshes uniformly at random. Default ``num_distinct``: random in [1, num_instances].
    """
    if num_meshes < 1 or num_instances < 1:
        raise ValueError(
            f"need at least one mesh and one instance, got {num_meshes}, {num_instances}"
        )
    if num_distinct is None:
        num_distinct = int(rng.integers(1, min(num_meshes, num_instances) + 1))
    num_distinct = min(num_distinct, num_meshes, num_instances)
    chosen = rng.choice(num_meshes, size=num_distinct, replace=False)
    extra = rng.choice(chosen, size=num_instances - num_distinct, replace=True)
    out = np.concatenate([chosen, extra])
    return out[rng.permutation(num_instances)].astype(np.int64)


def _valid(shapes: Sequence[CollisionShape | None], mesh_index: np.ndarray) -> np.ndarray:
    mesh_index = np.asarray(mesh_index, np.int64).reshape(-1)
    if len(mesh_index) and (mesh_index.min() < 0 or mesh_index.max() >= len(shapes)):
        raise ValueError(
            f"mesh_index must lie in [0, {len(shapes)}), got {mesh_index.min()}..{mesh_index.max()}"
        )
    keep = np.array([shapes[i] is not None for i in mesh_index], bool)
    return mesh_index[keep]


# --------------------------------------------------------------------------------------------
# Physics (MuJoCo).


@dataclasses.dataclass(frozen=True)
class PhysicsConfig:
    """Simulation settings (SI units inside MuJoCo).

    MuJoCo contacts are soft: a resting body sinks until the constraint force balances its
    load. The short ``solref`` time constant (3 ms) keeps that under a few tenths of a
    millimetre even under a pile of steel parts; the timestep must stay at or below half the
    time constant for stability. ``margin`` (m) would make contacts act before touching; it is
    0 so that resting parts really touch.
    """

    timestep: float = 0.0015
    solref: tuple[float, float] = (0.003, 1.0)
    solimp: tuple[float, float, float] = (0.95, 0.99, 0.0005)
    margin: float = 0.0  # m
    friction: tuple[float, float] = (0.4, 0.9)  # sliding friction range, per object
    density: tuple[float, float] = (1000.0, 8000.0)  # kg/m^3 range, per object (plastic..steel)
    max_time: float = 6.0  # s of simulated time (step cap)
    # At rest: no point of any body's bounding sphere moved faster than settle_speed (mm/s, on
    # average over each settle_window seconds) for two windows in a row. Displacements, not
    # instantaneous velocities, because resting contacts vibrate at tiny amplitudes.
    settle_speed: float = 2.0
    settle_window: float = 0.05
    # Speed caps (m/s, rad/s), applied every 5 steps: objects raining from up to a metre would
    # otherwise hit at 4 m/s, 8 mm per step, and thin parts (washers) can tunnel into others
    # and stay wedged. The caps act like air drag on the fall and do not change resting poses.
    max_speed: float = 1.0
    max_angular: float = 30.0
    iterations: int = 50
    # The no-slip pass removes the slow frictional creep of soft contacts in piles.
    noslip_iterations: int = 10
    impratio: float = 10.0
    # Torsional and rolling friction (m): without them a disc spinning flat or a cylinder
    # rolling on the plane never comes to rest.
    condim: int = 6
    torsional: float = 0.01
    rolling: float = 0.002


def _quat_wxyz(R: np.ndarray) -> np.ndarray:
    q = Rotation.from_matrix(R).as_quat()  # x, y, z, w
    return np.array([q[3], q[0], q[1], q[2]])


def _build_model(
    shapes: Sequence[CollisionShape],
    mesh_index: np.ndarray,
    R0: np.ndarray,
    t0_mm: np.ndarray,
    support: Support,
    densities: np.ndarray,
    frictions: np.ndarray,
    cfg: PhysicsConfig,
) -> mujoco.MjModel:
    spec = mujoco.MjSpec()
    spec.option.timestep = cfg.timestep
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    spec.option.iterations = cfg.iterations
    spec.option.impratio = cfg.impratio
    spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    spec.compiler.inertiafromgeom = mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_FALSE

    def contact(g, friction):
        g.solref = list(cfg.solref)
        g.solimp = list(cfg.solimp) + [0.5, 2.0]
        g.margin = cfg.margin
        g.condim = cfg.condim
        g.friction = [friction, cfg.torsional, cfg.rolling]

    floor = spec.worldbody.add_geom()
    floor.type = mujoco.mjtGeom.mjGEOM_PLANE
    floor.size = [0.0, 0.0, 1.0]
    floor.pos = [0.0, 0.0, (support.plane_z or 0.0) / 1000]
    contact(floor, float(np.median(cfg.friction)))
    if support.bin is not None:
        for centre, half in support.bin.wall_boxes():
            g = spec.worldbody.add_geom()
            g.type = mujoco.mjtGeom.mjGEOM_BOX
            g.size = list(half / 1000)
            g.pos = list((centre + [0.0, 0.0, support.plane_z or 0.0]) / 1000)
            contact(g, float(np.median(cfg.friction)))

    used = sorted(set(int(i) for i in mesh_index))
    for i in used:
        for k, piece in enumerate(shapes[i].pieces):
            m = spec.add_mesh()
            m.name = f"m{i}_{k}"
            m.uservert = (piece / 1000).reshape(-1).tolist()
            # Inertia comes from the real mesh below; this only keeps the compiler from
            # rejecting thin pieces as having too small a volume.
            m.inertia = mujoco.mjtMeshInertia.mjMESH_INERTIA_SHELL
    for o, i in enumerate(mesh_index):
        s = shapes[int(i)]
        body = spec.worldbody.add_body()
        body.name = f"o{o}"
        body.pos = list(t0_mm[o] / 1000)
        body.quat = list(_quat_wxyz(R0[o]))
        body.add_freejoint()
        body.explicitinertial = True
        mass = densities[o] * s.volume * 1e-9
        body.mass = mass
        body.ipos = list(s.com / 1000)
        inertia = s.inertia * densities[o] * 1e-15  # mm^5 x kg/m^3 -> kg m^2
        body.fullinertia = [
            inertia[0, 0],
            inertia[1, 1],
            inertia[2, 2],
            inertia[0, 1],
            inertia[0, 2],
            inertia[1, 2],
        ]
        for k in range(len(s.pieces)):
            g = body.add_geom()
            g.type = mujoco.mjtGeom.mjGEOM_MESH
            g.meshname = f"m{int(i)}_{k}"
            g.mass = 0.0
            contact(g, frictions[o])
    return spec.compile()


def simulate(
    shapes: Sequence[CollisionShape],
    mesh_index: np.ndarray,
    T_world_obj: np.ndarray,
    support: Support,
    rng: np.random.Generator,
    cfg: PhysicsConfig = PhysicsConfig(),
) -> tuple[np.ndarray, bool, float]:
    """Let instances fall and settle from T_world_obj [O, 4, 4] (mm).

    Returns (T_world_obj [O, 4, 4] at the end, settled, simulated seconds).
    """
    O = len(mesh_index)
    densities = rng.uniform(*cfg.density, size=O)
    frictions = rng.uniform(*cfg.friction, size=O)
    model = _build_model(
        shapes,
        mesh_index,
        T_world_obj[:, :3, :3],
        T_world_obj[:, :3, 3],
        support,
        densities,
        frictions,
        cfg,
    )
    data = mujoco.MjData(model)
    radii = np.array([shapes[int(i)].radius for i in mesh_index])
    window = 5 * max(1, int(round(cfg.settle_window / cfg.timestep / 5)))
    max_steps = int(round(cfg.max_time / cfg.timestep))
    tol = cfg.settle_speed * window * cfg.timestep  # mm per window
    prev = _poses(data.qpos, O)
    calm, steps, settled = 0, 0, False
    while steps < max_steps:
        for _ in range(0, window, 5):
            mujoco.mj_step(model, data, nstep=5)
            _clamp_speeds(data.qvel, O, cfg.max_speed, cfg.max_angular)
        steps += window
        cur = _poses(data.qpos, O)
        # Largest displacement of a point on each bounding sphere: |dt| + angle * radius.
        dt = np.linalg.norm(cur[1] - prev[1], axis=1)
        cos = np.clip((np.einsum("oij,oij->o", cur[0], prev[0]) - 1) / 2, -1.0, 1.0)
        moved = dt + np.arccos(cos) * radii
        prev = cur
        if moved.max() < 5 * tol:
            # Nearly at rest: switch on the no-slip pass (3x the cost of a step) to stop the
            # slow frictional creep of soft contacts that would keep piles from settling.
            model.opt.noslip_iterations = cfg.noslip_iterations
        calm = calm + 1 if moved.max() < tol else 0
        if calm >= 2:
            settled = True
            break
    R, t = _poses(data.qpos, O)
    T = np.tile(np.eye(4), (O, 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = t
    return T, settled, steps * cfg.timestep


def _clamp_speeds(qvel: np.ndarray, O: int, v_max: float, w_max: float) -> None:
    """Scale down, in place, free-joint linear and angular velocities above the caps."""
    q = qvel.reshape(O, 6)
    for sl, cap in ((slice(0, 3), v_max), (slice(3, 6), w_max)):
        speed = np.linalg.norm(q[:, sl], axis=1)
        fast = speed > cap
        if fast.any():
            q[fast, sl] *= (cap / speed[fast])[:, None]


def _poses(qpos: np.ndarray, O: int) -> tuple[np.ndarray, np.ndarray]:
    """Free-joint qpos -> (R [O, 3, 3], t [O, 3] mm)."""
    q = np.asarray(qpos).reshape(O, 7)
    quat = q[:, 3:] / np.linalg.norm(q[:, 3:], axis=1, keepdims=True)  # w, x, y, z
    R = Rotation.from_quat(np.concatenate([quat[:, 1:], quat[:, :1]], 1)).as_matrix()
    return R.reshape(O, 3, 3), q[:, :3] * 1000.0


def _spawn_column(
    rng: np.random.Generator,
    radii: np.ndarray,
    half_area: tuple[float, float],
    z0: float,
    gap: float,
    candidates: int = 8,
) -> np.ndarray:
    """Positions [O, 3] (mm) of non-overlapping spheres raining down onto a rectangle.

    Each sphere tries ``candidates`` random (x, y) in the rectangle |x| <= hx - r, |y| <= hy - r,
    each at the lowest height that clears the floor and every sphere placed before it, and
    keeps the lowest: a compact start means a short fall (and a short simulation).
    """
    O = len(radii)
    pos = np.zeros((O, 3))
    hx, hy = half_area
    for o in range(O):
        r = radii[o]
        x = rng.uniform(-max(hx - r, 0.0), max(hx - r, 0.0), candidates)
        y = rng.uniform(-max(hy - r, 0.0), max(hy - r, 0.0), candidates)
        z = np.full(candidates, z0 + r + gap)
        if o:
            d_xy = np.hypot(pos[None, :o, 0] - x[:, None], pos[None, :o, 1] - y[:, None])
            reach = radii[None, :o] + r + gap
            # Height above each close sphere at which the two just clear each other.
            dz = np.sqrt(np.maximum(reach**2 - d_xy**2, 0.0))
            above = np.where(d_xy < reach, pos[None, :o, 2] + dz, -np.inf)
            z = np.maximum(z, above.max(1))
        k = int(np.argmin(z))
        pos[o] = (x[k], y[k], z[k])
    return pos


def drop_layout(
    rng: np.random.Generator,
    shapes: Sequence[CollisionShape | None],
    mesh_index: Sequence[int] | np.ndarray,
    *,
    area: tuple[float, float] = (400.0, 400.0),
    bin: Bin | None = None,
    cfg: PhysicsConfig = PhysicsConfig(),
    keep_outside: bool = False,
) -> Layout:
    """Drop instances onto the plane z = 0 (in ``area``, mm) or into ``bin``; let them settle.

    Instances start at uniformly random orientations, raining from just above the support
    (bounding spheres never overlap at the start). Unless ``keep_outside``, instances that end
    with their centre outside the bin's inner footprint (bin scenes) or outside ``area`` grown by
    half (plane scenes) are removed and counted in ``removed``.
    """
    mesh_index = _valid(shapes, mesh_index)
    support = Support(plane_z=0.0, bin=bin)
    O = len(mesh_index)
    if O == 0:
        return Layout(np.zeros(0, np.int64), np.zeros((0, 4, 4)), support)
    radii = np.array([shapes[i].radius for i in mesh_index])
    half = (
        (bin.inner_size[0] / 2, bin.inner_size[1] / 2)
        if bin is not None
        else (area[0] / 2, area[1] / 2)
    )
    R0 = random_rotations(rng, O)
    t0 = _spawn_column(rng, radii, half, 0.0, gap=2.0)
    T0 = np.tile(np.eye(4), (O, 1, 1))
    T0[:, :3, :3] = R0
    T0[:, :3, 3] = t0
    T, settled, t = simulate(shapes, mesh_index, T0, support, rng, cfg)
    keep = np.ones(O, bool)
    if not keep_outside:
        lim = np.array(half) * (1.0 if bin is not None else 1.5)
        keep = (np.abs(T[:, 0, 3]) <= lim[0]) & (np.abs(T[:, 1, 3]) <= lim[1])
        if bin is not None:
            keep &= T[:, 2, 3] < bin.height + max(radii.max(), 1.0) * 2
    return Layout(mesh_index[keep], T[keep], support, settled, t, int((~keep).sum()))


# --------------------------------------------------------------------------------------------
# Floating.


def _halfspaces(shape: CollisionShape, T: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Each piece's hull as (normals [F, 3], offsets [F]) in world coordinates: n . x <= b."""
    out = []
    R, t = T[:3, :3], T[:3, 3]
    for piece in shape.pieces:
        eq = ConvexHull(piece).equations  # n . x + d <= 0 inside, |n| = 1
        n = eq[:, :3] @ R.T
        out.append((n, n @ t - eq[:, 3]))
    return out


def _pieces_overlap(ha, hb, gap: float) -> bool:
    """Whether two convex polytopes {n.x <= b} come closer than about ``gap`` (conservative).

    Maximises s subject to n_i . x + s <= b_i for both; s >= 0 iff they intersect. For
    polytopes a distance d apart the optimum is >= -d/2, so s > -gap/2 flags every pair closer
    than gap (and possibly some slightly farther), never missing an overlap.
    """
    (na, ba), (nb, bb) = ha, hb
    A = np.concatenate([np.concatenate([na, nb]), np.ones((len(na) + len(nb), 1))], 1)
    b = np.concatenate([ba, bb])
    res = linprog(
        c=[0, 0, 0, -1], A_ub=A, b_ub=b, bounds=[(None, None)] * 3 + [(None, gap)], method="highs"
    )
    if res.status != 0:
        return True  # be safe: treat solver trouble as an overlap
    return -res.fun > -gap / 2


def float_layout(
    rng: np.random.Generator,
    shapes: Sequence[CollisionShape | None],
    mesh_index: Sequence[int] | np.ndarray,
    *,
    center: Sequence[float] = (0.0, 0.0, 300.0),
    half_extents: Sequence[float] = (250.0, 250.0, 150.0),
    gap: float = 2.0,
    max_tries: int = 200,
) -> Layout:
    """Random non-overlapping poses in the box ``center`` +- ``half_extents`` (mm), no support.

    Object origins are sampled uniformly in the box, orientations uniformly on SO(3). A candidate
    is accepted when it keeps at least ``gap`` mm from every placed instance: bounding spheres
    decide quickly; otherwise every pair of convex pieces is separated by a linear program.
    Instances that cannot be placed in ``max_tries`` candidates are skipped (``removed``).
    """
    mesh_index = _valid(shapes, mesh_index)
    c = np.asarray(center, np.float64)
    h = np.asarray(half_extents, np.float64)
    placed_T: list[np.ndarray] = []
    placed_i: list[int] = []
    placed_h: list[list] = []
    removed = 0
    for i in mesh_index:
        s = shapes[int(i)]
        ok = False
        for _ in range(max_tries):
            T = np.eye(4)
            T[:3, :3] = random_rotations(rng, 1)[0]
            T[:3, 3] = c + rng.uniform(-1, 1, 3) * h
            hs = None
            ok = True
            for Tj, j, hj in zip(placed_T, placed_i, placed_h):
                if np.linalg.norm(Tj[:3, 3] - T[:3, 3]) >= shapes[j].radius + s.radius + gap:
                    continue
                hs = hs if hs is not None else _halfspaces(s, T)
                if any(_pieces_overlap(a, b, gap) for a in hs for b in hj):
                    ok = False
                    break
            if ok:
                placed_T.append(T)
                placed_i.append(int(i))
                placed_h.append(hs if hs is not None else _halfspaces(s, T))
                break
        removed += not ok
    T = np.array(placed_T).reshape(-1, 4, 4)
    return Layout(np.array(placed_i, np.int64), T, Support(plane_z=None), True, 0.0, removed)


# --------------------------------------------------------------------------------------------
# Dense packing.


def pack_layout(
    rng: np.random.Generator,
    shapes: Sequence[CollisionShape | None],
    mesh_index: Sequence[int] | np.ndarray,
    *,
    mode: str = "grid",
    gap: float = 2.0,
    yaw_jitter_deg: float = 5.0,
    fill_layers: float = 2.0,
    wall_height: float | None = None,
    cfg: PhysicsConfig = PhysicsConfig(),
) -> Layout:
    """Densely packed instances (bin picking, kitting trays).

    ``mode="grid"``: parts lie on their most stable face in rows on the plane z = 0, a ``gap``
    (mm) apart, yaw quantised to 0/90/180/270 degrees plus +-``yaw_jitter_deg``; no physics is
    needed, since a part on its stable face is at rest. ``mode="pile"``: the instances are
    dropped into a bin whose footprint holds about ``fill_layers`` layers of them.
    """
    if mode not in ("grid", "pile"):
        raise ValueError(f"pack mode must be 'grid' or 'pile', got {mode!r}")
    mesh_index = _valid(shapes, mesh_index)
    O = len(mesh_index)
    if O == 0:
        return Layout(np.zeros(0, np.int64), np.zeros((0, 4, 4)), Support())
    if mode == "pile":
        # Footprint per instance ~ (1.2 r)^2 x 2 for a random resting pose of a compact part.
        area = sum((1.2 * shapes[i].radius) ** 2 * 2 for i in mesh_index) / fill_layers
        r_max = max(shapes[i].radius for i in mesh_index)
        side = max(math.sqrt(area), 2.2 * r_max)
        aspect = rng.uniform(1.0, 1.5)
        # Deep enough that parts raining in are not deflected over the rim.
        b = Bin(
            (side * math.sqrt(aspect), side / math.sqrt(aspect)),
            height=wall_height if wall_height is not None else max(3.0 * r_max, 40.0),
        )
        return drop_layout(rng, shapes, mesh_index, bin=b, cfg=cfg)

    Rs = []
    boxes = []
    for i in mesh_index:
        s = shapes[int(i)]
        yaw = math.radians(
            90.0 * int(rng.integers(4)) + rng.uniform(-yaw_jitter_deg, yaw_jitter_deg)
        )
        Rz = np.array(
            [[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1]]
        )
        R = Rz @ s.rest_rotation
        v = s.vertices @ R.T
        Rs.append(R)
        boxes.append((v.min(0), v.max(0)))
    # Shelf packing: rows along x, as square a block as the footprints allow.
    sizes = np.array([hi[:2] - lo[:2] for lo, hi in boxes])
    total = float(((sizes + gap).prod(1)).sum())
    row_len = math.sqrt(total) * rng.uniform(0.9, 1.3)
    pos = np.zeros((O, 3))
    x = y = row_depth = 0.0
    for o in range(O):
        w, d = sizes[o]
        if x > 0 and x + w > row_len:
            x, y, row_depth = 0.0, y + row_depth + gap, 0.0
        lo, hi = boxes[o]
        pos[o] = (x - lo[0], y - lo[1], -lo[2])
        x += w + gap
        row_depth = max(row_depth, d)
    # Centre the block on the origin.
    ext_lo = np.min([pos[o, :2] + boxes[o][0][:2] for o in range(O)], 0)
    ext_hi = np.max([pos[o, :2] + boxes[o][1][:2] for o in range(O)], 0)
    pos[:, :2] -= (ext_lo + ext_hi) / 2
    T = np.tile(np.eye(4), (O, 1, 1))
    T[:, :3, :3] = np.array(Rs)
    T[:, :3, 3] = pos
    return Layout(mesh_index, T, Support(plane_z=0.0), True, 0.0, 0)
