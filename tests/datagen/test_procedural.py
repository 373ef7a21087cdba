"""Procedural parts: valid solids, metric sizes, true symmetries, face budget, determinism.

References: trimesh's watertightness / winding checks and divergence-theorem volume, SciPy
pdist (brute-force diameter) and cKDTree (Chamfer distances), manifold3d exact booleans
(volume IoU of the part and its transformed copy), and symmetry counts derived by hand from
each construction.
"""

import json
import math

import manifold3d as mf
import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.distance import pdist

from datagen import procedural as P

SEEDS = (0, 1, 2)
MAX_FACES = 3000


@pytest.fixture(scope="module")
def parts():
    return {
        (fam, seed): P.generate_part(np.random.default_rng(seed), fam, max_faces=MAX_FACES)
        for fam in P.FAMILIES
        for seed in SEEDS
    }


def _manifold(mesh: trimesh.Trimesh) -> mf.Manifold:
    m = mf.Manifold(
        mf.Mesh(
            vert_properties=np.asarray(mesh.vertices, np.float32),
            tri_verts=np.asarray(mesh.faces, np.uint32),
        )
    )
    assert m.status() == mf.Error.NoError
    return m


def _volume_iou(mesh: trimesh.Trimesh, S: np.ndarray) -> float:
    """Exact volume IoU of the mesh and its image under the rigid transform S [4, 4]."""
    a = _manifold(mesh)
    b = a.transform(np.asarray(S, np.float64)[:3, :4])
    return (a ^ b).volume() / (a + b).volume()


def _chamfer(mesh: trimesh.Trimesh, S: np.ndarray) -> float:
    """Symmetric mean Chamfer distance between S(samples) and independent samples of the mesh."""
    a, _ = trimesh.sample.sample_surface(mesh, 8000, seed=1)
    b, _ = trimesh.sample.sample_surface(mesh, 8000, seed=2)
    a = a @ S[:3, :3].T + S[:3, 3]
    return max(cKDTree(b).query(a)[0].mean(), cKDTree(a).query(b)[0].mean())


def _rot(axis, angle, point=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Independent axis-angle -> 4x4 about a line (via SciPy's rotation vectors)."""
    from scipy.spatial.transform import Rotation

    axis = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(axis * angle).as_matrix()
    T[:3, 3] = np.asarray(point) - T[:3, :3] @ np.asarray(point)
    return T


def test_at_least_six_families():
    assert len(P.FAMILIES) >= 6


@pytest.mark.parametrize("family", P.FAMILIES)
def test_parts_are_centred_watertight_metric_solids(parts, family):
    for seed in SEEDS:
        part = parts[(family, seed)]
        m = part.mesh
        assert part.family == family
        assert m.is_watertight and m.is_winding_consistent, (family, seed)
        assert m.volume > 0, "outward normals give a positive signed volume"
        # Centred at the bounding-box centre, as BOP models are.
        np.testing.assert_allclose(m.bounds.mean(0), 0.0, atol=1e-9 * part.diameter)
        # Diameter against a brute-force pairwise maximum over all vertices.
        d = pdist(np.asarray(m.vertices)).max()
        assert part.diameter == pytest.approx(d, rel=1e-9)
        assert P.DIAMETER_RANGE_MM[0] - 1e-6 <= d <= P.DIAMETER_RANGE_MM[1] + 1e-6
        assert len(m.faces) <= MAX_FACES


@pytest.mark.parametrize("family", P.FAMILIES)
def test_declared_symmetries_map_the_part_onto_itself(parts, family):
    for seed in SEEDS:
        part = parts[(family, seed)]
        transforms = list(part.symmetries.discrete)
        if len(transforms) > 6:  # gears have up to 95: check an evenly spread subset
            transforms = [transforms[i] for i in np.linspace(0, len(transforms) - 1, 6).astype(int)]
        for c in part.symmetries.continuous:
            axis, offset = c.axis, c.offset
            transforms += [_rot(axis, a, offset) for a in (0.7, 2.1, math.pi)]
        for S in transforms:
            R = S[:3, :3]
            np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
            assert np.linalg.det(R) == pytest.approx(1.0), "BOP symmetries are proper rotations"
            assert _volume_iou(part.mesh, S) > 0.99, (family, seed, S)
        for S in transforms[:2]:
            assert _chamfer(part.mesh, S) < 0.01 * part.diameter


@pytest.mark.parametrize("family", P.FAMILIES)
def test_symmetry_check_rejects_non_symmetries(parts, family):
    """The IoU test can fail: a 2%-of-diameter shift or a 3 degree tilt breaks every part."""
    part = parts[(family, 0)]
    shift = np.eye(4)
    shift[:3, 3] = (0.02 * part.diameter, 0.0, 0.0)
    assert _volume_iou(part.mesh, shift) < 0.99
    assert _volume_iou(part.mesh, _rot((1.0, 0.3, 0.2), math.radians(3))) < 0.99


def test_symmetry_counts_follow_the_construction(parts):
    for seed in SEEDS:
        # Hex nut: 6-fold axis, plus 6 half turns when both faces are chamfered alike.
        nut = parts[("nut", seed)]
        assert len(nut.symmetries.discrete) == (11 if nut.params["chamfer_both"] else 5)
        assert not nut.symmetries.continuous
        # Hex (or hex-socket) bolt: the 6-fold axis only, head on one end.
        assert len(parts[("bolt", seed)].symmetries.discrete) == 5
        # Washer: any rotation about its axis and a half turn that flips it.
        washer = parts[("washer", seed)]
        assert len(washer.symmetries.discrete) == 1 and len(washer.symmetries.continuous) == 1
        np.testing.assert_allclose(np.abs(washer.symmetries.continuous[0].axis), [0, 0, 1])
        # Spur gear with n teeth: n-fold axis unless keyed; n half turns unless it has a hub
        # (one, through the keyway, if keyed).
        gear = parts[("gear", seed)]
        n, key, hub = gear.params["teeth"], gear.params["keyway"], gear.params["hub"]
        expected = (0 if key else n - 1) + (0 if hub else (1 if key else n))
        assert len(gear.symmetries.discrete) == expected
        # Bracket with unequal legs: none.
        assert len(parts[("bracket", seed)].symmetries.discrete) == 0
        # Plate: the rectangle's three half turns, none with the locating hole.
        plate = parts[("plate", seed)]
        assert len(plate.symmetries.discrete) == (0 if plate.params["locating_hole"] else 3)


def test_bop_symmetry_format_round_trips_through_json(parts):
    part = parts[("washer", 0)]
    info = json.loads(json.dumps(part.symmetries.to_json()))
    assert len(info["symmetries_discrete"][0]) == 16
    S = np.array(info["symmetries_discrete"][0]).reshape(4, 4)
    np.testing.assert_allclose(S, part.symmetries.discrete[0])
    np.testing.assert_allclose(S[3], [0, 0, 0, 1])
    assert set(info["symmetries_continuous"][0]) == {"axis", "offset"}
    assert "symmetries_discrete" not in parts[("bracket", 0)].symmetries.to_json()


def test_same_seed_same_part_different_seed_different_part():
    for fam in ("gear", "bracket", "elbow"):
        a = P.generate_part(np.random.default_rng(7), fam)
        b = P.generate_part(np.random.default_rng(7), fam)
        c = P.generate_part(np.random.default_rng(8), fam)
        assert a.mesh.vertices.tobytes() == b.mesh.vertices.tobytes()
        assert a.mesh.faces.tobytes() == b.mesh.faces.tobytes()
        assert a.symmetries.discrete.tobytes() == b.symmetries.discrete.tobytes()
        assert a.params == b.params
        assert a.params != c.params
    fams_a = [p.family for p in P.generate_parts(np.random.default_rng(3), 12)]
    assert fams_a == [p.family for p in P.generate_parts(np.random.default_rng(3), 12)]


def test_small_face_budget_is_met_with_valid_symmetric_solids():
    rng = np.random.default_rng(0)
    for fam in ("gear", "elbow", "flange", "bolt"):
        part = P.generate_part(rng, fam, max_faces=600)
        assert len(part.mesh.faces) <= 600
        assert part.mesh.is_watertight and part.mesh.is_winding_consistent and part.mesh.volume > 0
        for S in part.symmetries.discrete[:2]:
            assert _volume_iou(part.mesh, S) > 0.99


def test_diameter_range_is_enforced_by_uniform_scaling():
    rng = np.random.default_rng(5)
    for fam in ("u_profile", "flange", "nut"):
        part = P.generate_part(rng, fam, diameter_range=(20.0, 40.0))
        d = pdist(np.asarray(part.mesh.vertices)).max()
        assert 20.0 - 1e-6 <= d <= 40.0 + 1e-6
        for S in part.symmetries.discrete[:2]:
            assert _volume_iou(part.mesh, S) > 0.99


def test_bad_arguments_name_the_fix():
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="unknown part family"):
        P.generate_part(rng, "spaceship")
    with pytest.raises(ValueError, match="max_faces"):
        P.generate_part(rng, "gear", max_faces=10)
    with pytest.raises(ValueError, match="diameter_range"):
        P.generate_part(rng, "gear", diameter_range=(50.0, 10.0))


def test_face_budget_above_the_loader_limit_names_the_option():
    from threept_jax.render.mesh import MAX_MESH_FACES

    with pytest.raises(ValueError, match="--procedural-max-faces"):
        P.generate_part(np.random.default_rng(0), "washer", max_faces=MAX_MESH_FACES + 1)
