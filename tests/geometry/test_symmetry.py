"""Object symmetries: JSON round trip and errors, nearest templates and symmetric angles
against SciPy brute force."""

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from threept_jax.geometry.symmetry import (
    ContinuousSymmetry,
    Symmetries,
    nearest_templates,
    symmetric_angle_deg,
    symmetry_transforms,
)


def _flip_z() -> np.ndarray:
    """Rotation by pi about z with a 5 mm shift along x, as a BOP 4x4."""
    S = np.eye(4)
    S[:3, :3] = Rotation.from_euler("z", 180, degrees=True).as_matrix()
    S[0, 3] = 5.0
    return S


def test_json_round_trip_and_scaling():
    sym = Symmetries([_flip_z()], [ContinuousSymmetry([0, 0, 1], [1.0, 2.0, 3.0])])
    info = json.loads(json.dumps(sym.to_json()))
    back = Symmetries.from_json(info)
    np.testing.assert_array_equal(back.discrete, sym.discrete)
    np.testing.assert_array_equal(back.continuous[0].offset, [1.0, 2.0, 3.0])
    assert Symmetries().to_json() == {} and not Symmetries.from_json({}).is_symmetric
    scaled = back.scaled(10.0)
    assert scaled.discrete[0, 0, 3] == 50.0 and scaled.continuous[0].offset.tolist() == [10, 20, 30]
    np.testing.assert_array_equal(scaled.discrete[0, :3, :3], sym.discrete[0, :3, :3])


@pytest.mark.parametrize("info, message", [
    ({"symmetries_discrete": [[1, 0, 0]]}, "16 values"),
    ({"symmetries_discrete": [np.diag([2.0, 1, 1, 1]).ravel().tolist()]}, "not orthonormal"),
    ({"symmetries_continuous": [{"axis": [0, 0, 0]}]}, "non-zero 3-vector axis"),
    ({"symmetries_continuous": [[0, 0, 1]]}, "must be an object"),
])
def test_bad_json_names_the_entry(info, message):
    with pytest.raises(ValueError, match=message):
        Symmetries.from_json(info, "models_info.json object 3")


def test_nearest_templates_match_brute_force():
    tmpl = Rotation.random(300, random_state=3).as_matrix()
    sym, _ = symmetry_transforms(Symmetries([_flip_z()]))
    R = Rotation.random(25, random_state=4).as_matrix()
    index, equivalents = nearest_templates(R, tmpl, sym)
    for r, i, eq in zip(R, index, equivalents, strict=True):
        ang = np.stack([(Rotation.from_matrix(tmpl).inv()
                         * Rotation.from_matrix(r @ s)).magnitude() for s in sym])  # [S, T]
        assert i == np.argmin(ang.min(0))
        assert set(eq.tolist()) == set(np.argmin(ang, axis=1).tolist())
    # A symmetric equivalent of a pose has the same nearest template.
    index_sym, _ = nearest_templates(R @ sym[1], tmpl, sym)
    np.testing.assert_array_equal(index_sym, index)


def test_symmetric_angle_matches_scipy():
    a = Rotation.random(10, random_state=5).as_matrix()
    b = Rotation.random(10, random_state=6).as_matrix()
    sym, _ = symmetry_transforms(Symmetries([_flip_z()]))
    got = symmetric_angle_deg(a, b, sym)
    ref = np.min([np.degrees((Rotation.from_matrix(a).inv() * Rotation.from_matrix(b @ s))
                             .magnitude()) for s in sym], axis=0)
    np.testing.assert_allclose(got, ref, atol=1e-6)
    np.testing.assert_allclose(symmetric_angle_deg(a, a @ sym[1].T, sym), 0.0, atol=1e-5)
