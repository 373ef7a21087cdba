"""Rotations against scipy.spatial.transform.Rotation (float64 reference)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from threept_jax.geometry import rotations as rot


@pytest.fixture(scope="module")
def ref():
    r = Rotation.random(500, random_state=0)
    # Add rotations near the singular places of each parameterisation: identity, angle pi.
    extra = Rotation.from_rotvec(
        np.concatenate([np.zeros((1, 3)), np.eye(3) * np.pi, np.eye(3) * (np.pi - 1e-4), np.eye(3) * 1e-6])
    )
    return Rotation.concatenate([r, extra])


def test_quaternion_to_matrix(ref):
    q_xyzw = ref.as_quat()
    q_wxyz = np.concatenate([q_xyzw[:, 3:], q_xyzw[:, :3]], -1)
    R = rot.quaternion_to_matrix(jnp.asarray(q_wxyz * 3.0, jnp.float32))  # any norm
    np.testing.assert_allclose(R, ref.as_matrix(), atol=2e-6)


def test_matrix_to_quaternion(ref):
    q = np.asarray(rot.matrix_to_quaternion(jnp.asarray(ref.as_matrix(), jnp.float32)))
    q_ref = ref.as_quat(canonical=True)  # xyzw with w >= 0
    q_ref = np.concatenate([q_ref[:, 3:], q_ref[:, :3]], -1)
    # At angle pi (w = 0) both signs are the same rotation: compare up to sign there.
    sign = np.where(np.sum(q * q_ref, -1) < 0, -1.0, 1.0)[:, None]
    np.testing.assert_allclose(q * sign, q_ref, atol=2e-6)
    assert np.all(q[:, 0] >= 0)


def test_axis_angle_roundtrip(ref):
    v = ref.as_rotvec()
    R = rot.axis_angle_to_matrix(jnp.asarray(v, jnp.float32))
    np.testing.assert_allclose(R, ref.as_matrix(), atol=2e-6)
    v_back = np.asarray(rot.matrix_to_axis_angle(jnp.asarray(ref.as_matrix(), jnp.float32)))
    # Compare as rotations (v and -v are the same at angle pi).
    np.testing.assert_allclose(Rotation.from_rotvec(v_back).as_matrix(), ref.as_matrix(), atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(v_back, axis=-1), ref.magnitude(), atol=1e-5)


def test_rotation_6d(ref):
    M = ref.as_matrix()
    x = np.concatenate([M[:, :, 0] * 2.0, M[:, :, 1] + 0.3 * M[:, :, 0]], -1)  # unnormalised columns
    np.testing.assert_allclose(rot.rotation_6d_to_matrix(jnp.asarray(x, jnp.float32)), M, atol=2e-6)


def test_geodesic_angle(ref):
    other = Rotation.random(len(ref), random_state=1)
    expected = (ref.inv() * other).magnitude()
    got = rot.geodesic_angle(ref.as_matrix().astype(np.float32), other.as_matrix().astype(np.float32))
    np.testing.assert_allclose(got, expected, atol=1e-5)
    # Tiny angles keep their precision (arccos of the trace would return 0 or ~3e-4 here).
    small = Rotation.from_rotvec([[1e-5, 0, 0]]).as_matrix().astype(np.float32)
    np.testing.assert_allclose(rot.geodesic_angle(np.eye(3, dtype=np.float32)[None], small), [1e-5], rtol=1e-2)


def test_project_to_so3_on_noisy_matrices(ref):
    rng = np.random.default_rng(0)
    M = ref.as_matrix() + 0.05 * rng.standard_normal((len(ref), 3, 3))
    R = np.asarray(rot.project_to_so3(jnp.asarray(M, jnp.float32)), np.float64)
    # Reference: orthogonal Procrustes in float64 (scipy's polar decomposition picks R = U V^T).
    from scipy.linalg import polar

    ref_R = []
    for m in M:
        u, _ = polar(m)
        if np.linalg.det(u) < 0:  # nearest proper rotation: flip the smallest singular direction
            U, S, Vt = np.linalg.svd(m)
            u = U @ np.diag([1, 1, -1]) @ Vt
        ref_R.append(u)
    np.testing.assert_allclose(R, np.stack(ref_R), atol=1e-5)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-5)
    # A reflection is mapped to a proper rotation too.
    refl = np.diag([1.0, 1.0, -1.0]).astype(np.float32)
    np.testing.assert_allclose(np.linalg.det(rot.project_to_so3(refl)), 1.0, atol=1e-6)


def test_jit_and_batch_shapes():
    key = jax.random.key(0)
    R = rot.random_rotations(key, (2, 3))
    assert R.shape == (2, 3, 3, 3)
    q = jax.jit(rot.matrix_to_quaternion)(R)
    assert q.shape == (2, 3, 4)
    np.testing.assert_allclose(jax.jit(rot.quaternion_to_matrix)(q), R, atol=2e-6)
    np.testing.assert_allclose(jnp.einsum("...ji,...jk->...ik", R, R), np.broadcast_to(np.eye(3), R.shape), atol=2e-6)


def test_random_rotations_from_a_numpy_generator_are_rotations_and_reproducible():
    a = rot.random_rotations(np.random.default_rng(3), (4, 2))
    b = rot.random_rotations(np.random.default_rng(3), (4, 2))
    assert a.shape == (4, 2, 3, 3) and a.dtype == np.float64
    np.testing.assert_array_equal(a, b)
    np.testing.assert_allclose(a @ np.swapaxes(a, -1, -2), np.broadcast_to(np.eye(3), a.shape),
                               atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(a), 1.0, atol=1e-12)
    assert rot.random_rotations(np.random.default_rng(0), 0).shape == (0, 3, 3)
