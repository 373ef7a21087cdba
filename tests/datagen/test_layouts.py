"""Scene layouts: settled drops rest on their support without interpenetrating, floating scenes do
not overlap, packed grids are statically stable, everything is reproducible.

All contact checks are made on the real meshes, independently of MuJoCo and of the collision
pieces: inside/outside from the generalised winding number (Jacobson et al. 2013) and depths from
brute-force point-triangle distances (Ericson, Real-Time Collision Detection 5.1.5), both
checked here against the analytic distance field of a box.
"""

import warnings

import numpy as np
import pytest
import trimesh
from scipy.spatial import ConvexHull, Delaunay

from datagen import layouts as L
from datagen import procedural as P

TOL = 1.0  # mm, the bound for resting contact and interpenetration


# ------------------------------------------------------------------------------------------
# Independent geometry: winding numbers and point-triangle distances, brute force in float64.


def winding_number(points: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Generalised winding number [P] of points [P, 3] w.r.t. a closed triangle soup [F, 3, 3]."""
    out = np.empty(len(points))
    for s in range(0, len(points), 256):
        p = points[s : s + 256, None]
        a, b, c = tris[None, :, 0] - p, tris[None, :, 1] - p, tris[None, :, 2] - p
        la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
        det = np.einsum("pfi,pfi->pf", a, np.cross(b, c))
        dot = lambda x, y: np.einsum("pfi,pfi->pf", x, y)  # noqa: E731
        den = la * lb * lc + dot(a, b) * lc + dot(b, c) * la + dot(c, a) * lb
        out[s : s + 256] = np.arctan2(det, den).sum(1) / (2 * np.pi)
    return out


def point_triangle_distance(points: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Distance [P] from points [P, 3] to the nearest triangle of [F, 3, 3]."""
    out = np.empty(len(points))
    A, B, C = tris[None, :, 0], tris[None, :, 1], tris[None, :, 2]
    ab, ac = B - A, C - A
    for s in range(0, len(points), 256):
        q = points[s : s + 256, None]
        ap, bp, cp = q - A, q - B, q - C
        d1, d2 = (ab * ap).sum(-1), (ac * ap).sum(-1)
        d3, d4 = (ab * bp).sum(-1), (ac * bp).sum(-1)
        d5, d6 = (ab * cp).sum(-1), (ac * cp).sum(-1)
        va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
        den = va + vb + vc
        den = np.where(np.abs(den) < 1e-300, 1e-300, den)
        closest = A + ab * (vb / den)[..., None] + ac * (vc / den)[..., None]  # interior
        safe = lambda x: np.where(np.abs(x) < 1e-300, 1e-300, x)  # noqa: E731
        # Regions from lowest to highest priority (Ericson's early returns, reversed).
        m = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
        closest = np.where(
            m[..., None], B + ((d4 - d3) / safe(d4 - d3 + d5 - d6))[..., None] * (C - B), closest
        )
        m = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
        closest = np.where(m[..., None], A + (d2 / safe(d2 - d6))[..., None] * ac, closest)
        closest = np.where(((d6 >= 0) & (d5 <= d6))[..., None], C, closest)
        m = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
        closest = np.where(m[..., None], A + (d1 / safe(d1 - d3))[..., None] * ab, closest)
        closest = np.where(((d3 >= 0) & (d4 <= d3))[..., None], B, closest)
        closest = np.where(((d1 <= 0) & (d2 <= 0))[..., None], A, closest)
        out[s : s + 256] = np.linalg.norm(q - closest, axis=-1).min(1)
    return out


def test_reference_geometry_matches_a_box_distance_field():
    box = trimesh.creation.box(extents=(2.0, 4.0, 6.0))
    p = np.random.default_rng(0).uniform(-5, 5, (1500, 3))
    q = np.abs(p) - (1.0, 2.0, 3.0)
    inside = q.max(1) < 0
    exact = np.where(inside, -q.max(1), np.linalg.norm(np.maximum(q, 0), axis=1))
    tris = box.vertices[box.faces]
    np.testing.assert_allclose(point_triangle_distance(p, tris), exact, atol=1e-12)
    np.testing.assert_array_equal(winding_number(p, tris) > 0.5, inside)


# ------------------------------------------------------------------------------------------
# Helpers on placed scenes.


def _world_meshes(meshes, layout):
    out = []
    for i, T in zip(layout.mesh_index, layout.T_world_obj):
        m = meshes[i].copy()
        m.apply_transform(T)
        out.append(m)
    return out


def _surface_points(m, n=300):
    return np.concatenate([m.vertices, trimesh.sample.sample_surface(m, n, seed=0)[0]])


def _max_penetration(world):
    """Deepest point of any mesh inside any other (0 if none), mm."""
    pts = [_surface_points(m) for m in world]
    worst = 0.0
    for a, ma in enumerate(world):
        for b, mb in enumerate(world):
            if (
                a == b
                or (
                    np.maximum(ma.bounds[0], mb.bounds[0])
                    > np.minimum(ma.bounds[1], mb.bounds[1]) + TOL
                ).any()
            ):
                continue
            tris = mb.vertices[mb.faces]
            inside = winding_number(pts[a], tris) > 0.5
            if inside.any():
                worst = max(worst, point_triangle_distance(pts[a][inside], tris).max())
    return worst


def _wall_penetration(world, b: L.Bin) -> float:
    """Deepest surface point inside a bin wall (analytic box distance), mm; 0 if none."""
    pts = np.concatenate([_surface_points(m) for m in world])
    worst = 0.0
    for centre, half in b.wall_boxes():
        depth = -(np.abs(pts - centre) - half).max(1)  # > 0 inside: distance to the nearest face
        worst = max(worst, float(depth.max()))
    return worst


def _assert_proper_rigid(T):
    R = T[:, :3, :3]
    np.testing.assert_allclose(
        R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-9
    )
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-9)
    np.testing.assert_array_equal(T[:, 3], np.broadcast_to([0, 0, 0, 1], (len(T), 4)))


def _assert_resting(world, walls=()):
    """Nothing below the floor; each object on the floor or touching another object / a wall."""
    zmin = np.array([m.vertices[:, 2].min() for m in world])
    assert zmin.min() >= -TOL, f"an object sinks {-zmin.min():.3f} mm into the floor"
    for a in np.flatnonzero(zmin > TOL):
        pts = _surface_points(world[a])
        others = [m for b, m in enumerate(world) if b != a] + list(walls)
        gap = min(point_triangle_distance(pts, m.vertices[m.faces]).min() for m in others)
        assert gap <= TOL, f"object {a} floats {zmin[a]:.1f} mm up, {gap:.2f} mm from any support"


# ------------------------------------------------------------------------------------------
# Fixtures: a few low-poly industrial parts of different families, and one scene of each kind.

FAMILIES = ("l_profile", "u_profile", "bolt", "nut", "washer", "plate", "bracket", "shaft")


@pytest.fixture(scope="module")
def parts():
    rng = np.random.default_rng(11)
    return [P.generate_part(rng, fam, max_faces=600) for fam in FAMILIES]


@pytest.fixture(scope="module")
def shapes(parts):
    return [L.collision_shape(p.mesh, p.family) for p in parts]


@pytest.fixture(scope="module")
def meshes(parts):
    return [p.mesh for p in parts]


@pytest.fixture(scope="module")
def instances():
    return L.choose_instances(np.random.default_rng(1), len(FAMILIES), 14, num_distinct=6)


@pytest.fixture(scope="module")
def plane_drop(shapes, instances):
    return L.drop_layout(np.random.default_rng(2), shapes, instances, area=(250.0, 250.0))


@pytest.fixture(scope="module")
def bin_drop(shapes, instances):
    # Inner size above the largest part's diameter (~210 mm), so every part fits inside.
    b = L.Bin((300.0, 260.0), height=150.0, wall=10.0)
    return L.drop_layout(np.random.default_rng(3), shapes, instances, bin=b)


# ------------------------------------------------------------------------------------------
# Collision shapes.


def test_collision_pieces_cover_the_real_surface(parts, shapes):
    for part, shape in zip(parts, shapes):
        assert _coverage(part.mesh, shape.pieces) == 1.0, part.family


def _coverage(mesh, pieces, n=3000):
    """Fraction of surface points inside at least one piece hull."""
    pts = _surface_points(mesh, n)
    covered = np.zeros(len(pts), bool)
    scale = np.ptp(pts, axis=0).max()
    for piece in pieces:
        eq = ConvexHull(piece).equations
        covered |= (pts @ eq[:, :3].T + eq[:, 3]).max(1) <= 1e-7 * scale
    return covered.mean()


def test_cuts_chosen_on_a_decimated_proxy_still_cover_the_full_mesh(parts, bop_models_dir):
    bracket = parts[FAMILIES.index("bracket")].mesh
    pieces = L.convex_pieces(bracket, proxy_faces=150)
    assert len(pieces) >= 2 and _coverage(bracket, pieces) == 1.0
    # A real industrial CAD model (ITODD), decomposed through a proxy of 500 faces.
    real = trimesh.load(
        bop_models_dir / "itodd" / "models" / "obj_000005.ply", force="mesh", process=False
    )
    assert len(real.faces) > 500
    pieces = L.convex_pieces(real, proxy_faces=500)
    assert _coverage(real, pieces) == 1.0
    single = ConvexHull(real.vertices).volume
    assert sum(ConvexHull(p).volume for p in pieces) < single


def test_l_profile_splits_into_its_two_legs(parts, shapes):
    part, shape = parts[0], shapes[0]
    assert part.family == "l_profile"
    q = part.params
    a, b, t, length = q["leg_a"], q["leg_b"], q["thickness"], q["length"]
    hand_volume = (a * t + (b - t) * t) * length
    assert part.mesh.volume == pytest.approx(hand_volume, rel=1e-9)
    assert len(shape.pieces) == 2
    # Two boxes: their hulls add up to the solid's volume (cuts are 1e-4 of the extent off the
    # inner face, so one leg keeps a hair of the other).
    assert sum(ConvexHull(p).volume for p in shape.pieces) == pytest.approx(hand_volume, rel=1e-3)
    assert shape.volume == pytest.approx(hand_volume, rel=1e-9)


def test_bad_meshes_are_skipped_for_physics_with_a_warning(shapes):
    flat = trimesh.Trimesh([[0, 0, 0], [10, 0, 0], [0, 10, 0], [10, 10, 0]], [[0, 1, 2], [1, 3, 2]])
    nan = trimesh.Trimesh(
        [[0, 0, 0], [1, 0, 0], [0, np.nan, 0], [0, 0, 1]],
        [[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]],
    )
    with pytest.warns(RuntimeWarning) as rec:
        out, skipped = L.collision_shapes(
            [flat, nan, P.generate_part(np.random.default_rng(0), "nut").mesh],
            names=["flat_part", "nan_part", "nut"],
        )
    assert skipped == 2 and out[0] is None and out[1] is None and out[2] is not None
    messages = [str(w.message) for w in rec]
    assert any("flat_part" in m and "flat" in m for m in messages)
    assert any("nan_part" in m and "non-finite" in m for m in messages)
    # Instances of skipped meshes are left out of the scene; the rest is placed.
    lay = L.float_layout(np.random.default_rng(0), out, [0, 1, 2, 2])
    assert lay.mesh_index.tolist() == [2, 2]


def test_choose_instances_has_duplicates_and_every_chosen_mesh():
    idx = L.choose_instances(np.random.default_rng(0), 50, 40, num_distinct=7)
    assert len(idx) == 40 and idx.min() >= 0 and idx.max() < 50
    values, counts = np.unique(idx, return_counts=True)
    assert len(values) == 7 and counts.max() > 1
    again = L.choose_instances(np.random.default_rng(0), 50, 40, num_distinct=7)
    assert idx.tobytes() == again.tobytes()


# ------------------------------------------------------------------------------------------
# Drops.


def test_drop_on_plane_settles_at_rest_on_the_support(meshes, plane_drop, instances):
    lay = plane_drop
    assert lay.settled
    assert len(lay.mesh_index) + lay.removed == len(instances)
    assert len(lay.mesh_index) >= len(instances) - 2
    _assert_proper_rigid(lay.T_world_obj)
    world = _world_meshes(meshes, lay)
    _assert_resting(world)
    # Most objects lie directly on the floor: their lowest vertex within 1 mm of it.
    on_floor = np.array([abs(m.vertices[:, 2].min()) <= TOL for m in world])
    assert on_floor.mean() > 0.5


def test_drop_on_plane_real_meshes_do_not_interpenetrate(meshes, plane_drop):
    assert _max_penetration(_world_meshes(meshes, plane_drop)) <= TOL


def test_drop_into_bin_stays_inside_without_interpenetration(meshes, bin_drop):
    lay = bin_drop
    assert lay.settled and lay.support.bin is not None and lay.support.plane_z == 0.0
    world = _world_meshes(meshes, lay)
    walls = lay.support.meshes()[1:]
    assert len(walls) == 4
    # No part goes into a wall (a part may lean on the rim), and every centre is inside.
    assert _wall_penetration(world, lay.support.bin) <= TOL
    ix, iy = lay.support.bin.inner_size[0] / 2, lay.support.bin.inner_size[1] / 2
    assert (np.abs(lay.T_world_obj[:, 0, 3]) <= ix).all() and (
        np.abs(lay.T_world_obj[:, 1, 3]) <= iy
    ).all()
    _assert_resting(world, walls)
    assert _max_penetration(world) <= TOL


def test_drop_is_deterministic(shapes, instances, plane_drop):
    again = L.drop_layout(np.random.default_rng(2), shapes, instances, area=(250.0, 250.0))
    assert again.T_world_obj.tobytes() == plane_drop.T_world_obj.tobytes()
    assert again.mesh_index.tobytes() == plane_drop.mesh_index.tobytes()
    other = L.drop_layout(np.random.default_rng(4), shapes, instances[:4], area=(250.0, 250.0))
    assert other.T_world_obj.tobytes() != plane_drop.T_world_obj[:4].tobytes()


# ------------------------------------------------------------------------------------------
# Floating and packing.


def test_float_layout_has_no_overlaps_and_stays_in_its_box(meshes, shapes):
    center, half = np.array([0.0, 0.0, 300.0]), np.array([120.0, 120.0, 80.0])
    idx = L.choose_instances(np.random.default_rng(5), len(shapes), 12, num_distinct=5)
    lay = L.float_layout(
        np.random.default_rng(6), shapes, idx, center=center, half_extents=half, gap=2.0
    )
    assert len(lay.mesh_index) + lay.removed == 12 and len(lay.mesh_index) >= 10
    assert lay.support.plane_z is None
    _assert_proper_rigid(lay.T_world_obj)
    assert (np.abs(lay.T_world_obj[:, :3, 3] - center) <= half).all()
    world = _world_meshes(meshes, lay)
    assert _max_penetration(world) == 0.0
    # Vertices keep at least the gap from every other surface (separation of the piece hulls).
    for a, ma in enumerate(world):
        for b, mb in enumerate(world):
            if a != b:
                assert (
                    point_triangle_distance(ma.vertices, mb.vertices[mb.faces]).min() >= 2.0 - 1e-6
                )
    again = L.float_layout(
        np.random.default_rng(6), shapes, idx, center=center, half_extents=half, gap=2.0
    )
    assert again.T_world_obj.tobytes() == lay.T_world_obj.tobytes()


def test_pack_grid_is_tight_flat_and_statically_stable(parts, shapes):
    bracket = FAMILIES.index("bracket")
    idx = [bracket] * 9
    lay = L.pack_layout(np.random.default_rng(7), shapes, idx, mode="grid", gap=2.0)
    assert len(lay.mesh_index) == 9 and lay.support.plane_z == 0.0
    world = _world_meshes([p.mesh for p in parts], lay)
    boxes = [m.bounds for m in world]
    for m in world:
        assert m.vertices[:, 2].min() == pytest.approx(0.0, abs=1e-9)
    # Footprints (xy boxes) never overlap: at least one axis separated by the gap.
    for a in range(9):
        for b in range(a + 1, 9):
            sep = np.maximum(
                boxes[b][0][:2] - boxes[a][1][:2], boxes[a][0][:2] - boxes[b][1][:2]
            ).max()
            assert sep >= 2.0 - 1e-9
    # Tight: the block's area is within a small factor of the footprints' total area.
    lo, hi = np.min([b[0] for b in boxes], 0), np.max([b[1] for b in boxes], 0)
    area = sum((b[1][0] - b[0][0]) * (b[1][1] - b[0][1]) for b in boxes)
    assert (hi[0] - lo[0]) * (hi[1] - lo[1]) < 2.5 * area
    # Statically stable: the centre of mass projects inside the contact polygon.
    com = parts[bracket].mesh.center_mass
    for T, m in zip(lay.T_world_obj, world):
        contact = m.vertices[m.vertices[:, 2] < 1e-6, :2]
        c = (T[:3, :3] @ com + T[:3, 3])[:2]
        assert Delaunay(contact).find_simplex(c) >= 0
    # And physics agrees: after half a second nothing has moved by a millimetre.
    T1, _, _ = L.simulate(
        shapes,
        lay.mesh_index,
        lay.T_world_obj,
        lay.support,
        np.random.default_rng(0),
        L.PhysicsConfig(max_time=0.5, settle_speed=0.0),
    )
    radius = shapes[bracket].radius
    moved = np.linalg.norm(T1[:, :3, 3] - lay.T_world_obj[:, :3, 3], axis=1)
    angle = np.arccos(
        np.clip((np.einsum("oij,oij->o", T1[:, :3, :3], lay.T_world_obj[:, :3, :3]) - 1) / 2, -1, 1)
    )
    assert (moved + angle * radius).max() < TOL


def test_pack_pile_drops_duplicates_into_a_fitted_bin(parts, shapes):
    nut = FAMILIES.index("nut")
    lay = L.pack_layout(np.random.default_rng(8), shapes, [nut] * 10, mode="pile")
    assert lay.support.bin is not None and lay.settled
    assert len(lay.mesh_index) + lay.removed == 10 and len(lay.mesh_index) >= 9
    world = _world_meshes([p.mesh for p in parts], lay)
    assert _wall_penetration(world, lay.support.bin) <= TOL
    _assert_resting(world, lay.support.meshes()[1:])
    assert _max_penetration(world) <= TOL
    # Dense: the parts' footprints (xy boxes at rest) add up to more than the bin floor, so they
    # lie in more than one layer.
    ix, iy = lay.support.bin.inner_size
    footprint = sum(np.prod(m.extents[:2]) for m in world)
    assert footprint > 1.0 * ix * iy


def test_bad_arguments_raise():
    with pytest.raises(ValueError, match="pack mode"):
        L.pack_layout(np.random.default_rng(0), [], [], mode="heap")
    with pytest.raises(ValueError, match="mesh_index"):
        L.drop_layout(np.random.default_rng(0), [None], [3])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        empty = L.drop_layout(np.random.default_rng(0), [None], [0])
    assert empty.T_world_obj.shape == (0, 4, 4)
