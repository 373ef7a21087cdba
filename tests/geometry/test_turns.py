"""``threept_jax.geometry.turns``: the near-symmetric turns of a part.

References: a 12-tooth gear with one short tooth built by hand (``tests/fixtures/gear.py``: its
turns by 30 degrees about its axis are the near symmetries, by construction); every turn returned checked by a brute
force independent of the function (trimesh's exact closest points, every triangle tried); a
box's half-turns and a 64-sided cylinder's roundness derived by hand.
"""

import numpy as np
import pytest
import trimesh
from fixtures.gear import gear

from threept_jax.geometry.symmetry import axis_angle_rotation
from threept_jax.geometry.turns import near_symmetry_turns, surface_samples


def _surface_fits(v, f, T, tol):
    """Brute force: the 95th percentile of the exact distances from 1000 turned surface samples
    to the surface, within ``tol`` of the box diagonal."""
    mesh = trimesh.Trimesh(v, f, process=False)
    p = surface_samples(v, f, 1000, np.random.default_rng(7))
    q = p @ T[:3, :3].T + T[:3, 3]
    d = trimesh.proximity.closest_point_naive(mesh, q)[1]
    return np.quantile(d, 0.95) <= tol * np.linalg.norm(v.max(0) - v.min(0))


def test_a_gears_teeth_are_its_near_symmetries_and_every_turn_is_one():
    v, f = gear()
    turns = near_symmetry_turns(v, f, np.eye(4)[None])
    z = [T for T in turns if abs(T[2, 2] - 1) < 1e-9]  # about the axis (others: turned over)
    angles = sorted(np.degrees(np.arctan2(T[1, 0], T[0, 0])) % 360 for T in z)
    np.testing.assert_allclose(angles, 30.0 * np.arange(1, 12), atol=1e-6)
    for T in turns:  # each a rigid turn about the centre that the surface nearly keeps
        np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)
        assert _surface_fits(v, f, T, 0.004)
    half = np.eye(4)
    half[:3, :3] = axis_angle_rotation(np.radians(15.0), [0, 0, 1])
    assert not _surface_fits(v, f, half, 0.004)  # half a pitch: the teeth miss each other
    # Declared symmetries are not near symmetries: declaring the 30-degree turns removes them.
    declared = np.concatenate([np.eye(4)[None], np.stack(z)])
    rest = near_symmetry_turns(v, f, declared)
    assert len(rest) == len(turns) - 11


def test_a_box_and_a_cylinder():
    box = trimesh.creation.box((60.0, 42.0, 30.0))
    v, f = np.asarray(box.vertices), np.asarray(box.faces)
    turns = near_symmetry_turns(v, f, np.eye(4)[None])
    # The three half-turns about its axes, by hand: diag(1, -1, -1) and its permutations.
    got = sorted(tuple(np.round(np.diag(T[:3, :3])).astype(int)) for T in turns)
    assert got == [(-1, -1, 1), (-1, 1, -1), (1, -1, -1)]
    halves = np.stack([np.diag([*d, 1.0]) for d in got])
    assert len(near_symmetry_turns(v, f, np.concatenate([np.eye(4)[None], halves]))) == 0
    cyl = trimesh.creation.cylinder(radius=20.0, height=70.0, sections=64)
    turns = near_symmetry_turns(np.asarray(cyl.vertices), np.asarray(cyl.faces))
    # Round about its axis (64-fold passes at 120): no turn about z; half-turns about x, y.
    assert all(abs(T[2, 2] + 1) < 1e-6 for T in turns) and len(turns) <= 2


def test_a_mesh_without_area_is_refused():
    with pytest.raises(ValueError, match="no area"):
        surface_samples(np.zeros((3, 3)), np.array([[0, 1, 2]]), 10, np.random.default_rng(0))
