"""Rotation parameterisations and distances on SO(3).

Rotations are 3x3 matrices at every API boundary (docs/design.md section 3); quaternions are
(w, x, y, z) with w >= 0 on output. All functions are batched over leading axes, jit-able and
accept NumPy or JAX arrays.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial.transform import Rotation

Array = jax.Array


def skew(v: Array) -> Array:
    """[..., 3] -> [..., 3, 3] cross-product matrix: skew(a) @ b == cross(a, b)."""
    v = jnp.asarray(v)
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    o = jnp.zeros_like(x)
    return jnp.stack(
        [jnp.stack([o, -z, y], -1), jnp.stack([z, o, -x], -1), jnp.stack([-y, x, o], -1)], -2
    )


def quaternion_to_matrix(q: Array) -> Array:
    """[..., 4] (w, x, y, z), any norm > 0 -> [..., 3, 3] rotation matrix."""
    q = jnp.asarray(q)
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return jnp.stack([jnp.stack(r, -1) for r in rows], -2)


def matrix_to_quaternion(R: Array) -> Array:
    """[..., 3, 3] rotation -> [..., 4] unit quaternion (w, x, y, z) with w >= 0.

    Shepperd's method without branches: the four candidate formulas are all evaluated and the
    one with the largest (hence best conditioned) denominator is kept.
    """
    R = jnp.asarray(R)
    m00, m01, m02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    m10, m11, m12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    m20, m21, m22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    # 4 * component^2 for w, x, y, z.
    sq = jnp.stack(
        [1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1
    )
    # Candidate quaternions, each scaled by 4 * (its pivot component).
    cand = jnp.stack(
        [
            jnp.stack([sq[..., 0], m21 - m12, m02 - m20, m10 - m01], -1),
            jnp.stack([m21 - m12, sq[..., 1], m10 + m01, m02 + m20], -1),
            jnp.stack([m02 - m20, m10 + m01, sq[..., 2], m12 + m21], -1),
            jnp.stack([m10 - m01, m20 + m02, m21 + m12, sq[..., 3]], -1),
        ],
        -2,
    )
    best = jnp.argmax(sq, axis=-1)
    q = jnp.take_along_axis(cand, best[..., None, None], axis=-2)[..., 0, :]
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    return jnp.where(q[..., :1] < 0, -q, q)


def axis_angle_to_matrix(v: Array) -> Array:
    """[..., 3] rotation vector (axis * angle, radians) -> [..., 3, 3] (Rodrigues, exp map)."""
    v = jnp.asarray(v)
    theta2 = jnp.sum(v * v, axis=-1)[..., None, None]
    small = theta2 < 1e-8
    safe2 = jnp.where(small, 1.0, theta2)
    theta = jnp.sqrt(safe2)
    # sin(t)/t and (1 - cos(t))/t^2 with their Taylor series near 0.
    a = jnp.where(small, 1.0 - theta2 / 6.0, jnp.sin(theta) / theta)
    b = jnp.where(small, 0.5 - theta2 / 24.0, (1.0 - jnp.cos(theta)) / safe2)
    S = skew(v)
    eye = jnp.eye(3, dtype=S.dtype)
    return eye + a * S + b * (S @ S)


def matrix_to_axis_angle(R: Array) -> Array:
    """[..., 3, 3] -> [..., 3] rotation vector with angle in [0, pi] (log map, stable at pi)."""
    q = matrix_to_quaternion(R)
    xyz = q[..., 1:]
    s = jnp.linalg.norm(xyz, axis=-1, keepdims=True)
    angle = 2.0 * jnp.arctan2(s, q[..., :1])
    small = s < 1e-7
    # angle / s -> 2 / w as s -> 0.
    scale = jnp.where(small, 2.0 / jnp.maximum(q[..., :1], 1e-12), angle / jnp.where(small, 1.0, s))
    return xyz * scale


def rotation_6d_to_matrix(x: Array) -> Array:
    """[..., 6] -> [..., 3, 3]: the continuous 6D representation of Zhou et al. (CVPR 2019).

    The six numbers are the first two columns of R before Gram-Schmidt; the third column is
    their cross product.
    """
    x = jnp.asarray(x)
    a1, a2 = x[..., :3], x[..., 3:]
    b1 = a1 / jnp.linalg.norm(a1, axis=-1, keepdims=True)
    a2 = a2 - jnp.sum(b1 * a2, axis=-1, keepdims=True) * b1
    b2 = a2 / jnp.linalg.norm(a2, axis=-1, keepdims=True)
    b3 = jnp.cross(b1, b2)
    return jnp.stack([b1, b2, b3], axis=-1)


def geodesic_angle(R1: Array, R2: Array) -> Array:
    """[..., 3, 3], [..., 3, 3] -> [...] angle of R1^T R2 in radians, in [0, pi].

    Uses atan2(sin, cos) rather than arccos of the trace, which loses all precision near 0.
    """
    M = jnp.einsum("...ji,...jk->...ik", jnp.asarray(R1), jnp.asarray(R2))
    cos = (M[..., 0, 0] + M[..., 1, 1] + M[..., 2, 2] - 1.0) / 2.0
    sin_vec = jnp.stack(
        [M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0], M[..., 1, 0] - M[..., 0, 1]], -1
    )
    sin = 0.5 * jnp.linalg.norm(sin_vec, axis=-1)
    return jnp.arctan2(sin, cos)


def project_to_so3(M: Array) -> Array:
    """[..., 3, 3] any matrix -> nearest rotation in Frobenius norm (SVD, det fixed to +1)."""
    U, _, Vt = jnp.linalg.svd(jnp.asarray(M))
    d = jnp.sign(jnp.linalg.det(U @ Vt))
    d = jnp.where(d == 0, 1.0, d)
    D = jnp.concatenate([jnp.ones_like(d)[..., None], jnp.ones_like(d)[..., None], d[..., None]], -1)
    return (U * D[..., None, :]) @ Vt


def random_rotations(key: Array | np.random.Generator, shape: tuple[int, ...] | int,
                     dtype=jnp.float32) -> Array | np.ndarray:
    """Haar-uniform random rotations [*shape, 3, 3] (normalised Gaussian quaternions).

    ``key`` is a JAX PRNG key (JAX array of ``dtype``) or a ``np.random.Generator`` (float64
    NumPy, drawn as ``scipy.spatial.transform.Rotation.random`` draws them, for host code such
    as data generation).
    """
    shape = (shape,) if isinstance(shape, int) else tuple(shape)
    if isinstance(key, np.random.Generator):
        n = math.prod(shape)
        if n == 0:
            return np.zeros((*shape, 3, 3))
        return Rotation.random(n, random_state=key).as_matrix().reshape(*shape, 3, 3)
    q = jax.random.normal(key, (*shape, 4), dtype=dtype)
    return quaternion_to_matrix(q)
