"""Pinhole cameras and rigid transforms (OpenCV convention, millimetres).

Pixel convention, used by every module of the project:

* ``K`` maps to *pixel-centre* coordinates, as in OpenCV: the centre of pixel (column i,
  row j) is at (u, v) = (i, j). A projected point belongs to pixel ``round(u), round(v)``.
* Boxes (xyxy) are in *pixel-edge* coordinates, as in BOP and COCO: the image spans
  [0, W] x [0, H] and pixel (i, j) covers [i, i+1) x [j, j+1). A BOP ``bbox`` (x, y, w, h)
  is the box (x, y, x + w, y + h). A projected point's box coordinate is (u + 0.5, v + 0.5).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

Array = jax.Array


def transform(T: Array, points: Array) -> Array:
    """Apply rigid transforms: T [..., 4, 4], points [..., N, 3] -> [..., N, 3]."""
    T = jnp.asarray(T)
    points = jnp.asarray(points)
    return jnp.einsum("...ij,...nj->...ni", T[..., :3, :3], points) + T[..., None, :3, 3]


def invert(T: Array) -> Array:
    """Invert rigid transforms [..., 4, 4] exactly (R^T, -R^T t), without a general inverse."""
    T = jnp.asarray(T)
    Rt = jnp.swapaxes(T[..., :3, :3], -1, -2)
    t = -jnp.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    return make_transform(Rt, t)


def make_transform(R: Array, t: Array) -> Array:
    """R [..., 3, 3], t [..., 3] -> T [..., 4, 4]."""
    R = jnp.asarray(R)
    t = jnp.asarray(t, dtype=R.dtype)
    top = jnp.concatenate([R, t[..., :, None]], axis=-1)
    bottom = jnp.broadcast_to(jnp.array([0, 0, 0, 1], dtype=R.dtype), (*top.shape[:-2], 1, 4))
    return jnp.concatenate([top, bottom], axis=-2)


def project(points: Array, K: Array) -> Array:
    """Project camera-frame points [..., N, 3] with K [..., 3, 3] -> pixel coords [..., N, 2].

    Points at or behind the camera (z <= 0) give meaningless coordinates: mask them with z.
    """
    points = jnp.asarray(points)
    p = jnp.einsum("...ij,...nj->...ni", jnp.asarray(K), points)
    z = p[..., 2:3]
    z = jnp.where(jnp.abs(z) < 1e-12, 1e-12, z)
    return p[..., :2] / z


def backproject(uv: Array, depth: Array, K: Array) -> Array:
    """Lift pixels uv [..., N, 2] at depths z [..., N] to camera-frame points [..., N, 3]."""
    uv = jnp.asarray(uv)
    depth = jnp.asarray(depth)
    uv1 = jnp.concatenate([uv, jnp.ones_like(uv[..., :1])], axis=-1)
    rays = jnp.einsum("...ij,...nj->...ni", jnp.linalg.inv(jnp.asarray(K)), uv1)
    # K^-1 [u v 1]^T has z = 1 for any upper-triangular K, so scaling by depth gives z = depth.
    return rays * depth[..., None]


def crop_intrinsics(K: Array, box_xyxy: Array, out_hw: tuple[int, int]) -> Array:
    """K [..., 3, 3] of the image -> K of the crop ``box_xyxy`` [..., 4] resized to ``out_hw``.

    The box is in pixel-edge coordinates (module docstring); the crop's pixel centres keep the
    OpenCV convention, so u' = (u + 0.5 - x0) * sx - 0.5 with sx = W' / (x1 - x0).
    """
    K = jnp.asarray(K)
    box = jnp.asarray(box_xyxy, dtype=K.dtype)
    out_h, out_w = out_hw
    sx = out_w / (box[..., 2] - box[..., 0])
    sy = out_h / (box[..., 3] - box[..., 1])
    zero, one = jnp.zeros_like(sx), jnp.ones_like(sx)
    S = jnp.stack(
        [
            jnp.stack([sx, zero, (0.5 - box[..., 0]) * sx - 0.5], -1),
            jnp.stack([zero, sy, (0.5 - box[..., 1]) * sy - 0.5], -1),
            jnp.stack([zero, zero, one], -1),
        ],
        -2,
    )
    return S @ K


def look_at(eye: Array, target: Array, up: Array = (0.0, 0.0, 1.0)) -> Array:
    """T_cam_world [4, 4] of an OpenCV camera at ``eye`` looking at ``target``.

    ``up`` is the world direction that appears upwards in the image (camera -y); it must not
    be parallel to the viewing direction. JAX input (``eye`` or ``target``) is computed in JAX
    float32; anything else in float64 NumPy, so host code (data generation) gives the same bits
    whatever XLA backend or compile options the process has.
    """
    if not isinstance(eye, jax.Array) and not isinstance(target, jax.Array):
        eye, target = np.asarray(eye, np.float64), np.asarray(target, np.float64)
        z = target - eye
        z = z / np.linalg.norm(z, axis=-1, keepdims=True)
        x = np.cross(z, np.asarray(up, np.float64))
        x = x / np.linalg.norm(x, axis=-1, keepdims=True)
        R_cam_world = np.stack([x, np.cross(z, x), z], axis=-2)
        T = np.zeros((*R_cam_world.shape[:-2], 4, 4))
        T[..., :3, :3] = R_cam_world
        T[..., :3, 3] = -np.einsum("...ij,...j->...i", R_cam_world, eye)
        T[..., 3, 3] = 1.0
        return T
    eye, target = jnp.asarray(eye, jnp.float32), jnp.asarray(target, jnp.float32)
    up = jnp.asarray(up, jnp.float32)
    z = target - eye
    z = z / jnp.linalg.norm(z, axis=-1, keepdims=True)
    x = jnp.cross(z, up)
    x = x / jnp.linalg.norm(x, axis=-1, keepdims=True)
    y = jnp.cross(z, x)
    R_world_cam = jnp.stack([x, y, z], axis=-1)
    return invert(make_transform(R_world_cam, eye))


def ray_rotation(points_cam: Array) -> Array:
    """[..., 3] points (or ray directions) in the camera -> [..., 3, 3] smallest rotation that
    takes the optical axis +z onto their ray.

    Rodrigues' formula about ``z x d`` by the angle between z and d (identity on the axis).
    Object-centred templates (``threept_jax.data.banks``) are related to camera rotations by
    it: ``R_cam_obj = ray_rotation(centre) @ R_template``. NumPy input is computed in float64
    NumPy, JAX input (traced too) in JAX.
    """
    xp = jnp if isinstance(points_cam, jax.Array) else np
    d = xp.asarray(points_cam, None if xp is jnp else np.float64)
    d = d / xp.linalg.norm(d, axis=-1, keepdims=True)
    v = xp.stack([-d[..., 1], d[..., 0], xp.zeros_like(d[..., 0])], -1)  # z x d = sin * axis
    c = d[..., 2]  # cos of the angle
    o = xp.zeros_like(c)
    vx = xp.stack([xp.stack([o, -v[..., 2], v[..., 1]], -1),
                   xp.stack([v[..., 2], o, -v[..., 0]], -1),
                   xp.stack([-v[..., 1], v[..., 0], o], -1)], -2)
    # R = I + [v]x + [v]x^2 / (1 + c); a point in front of the camera never has c = -1.
    denom = xp.maximum(1.0 + c, 1e-12)[..., None, None]
    return xp.eye(3, dtype=vx.dtype) + vx + (vx @ vx) / denom


def object_centred_rotation(R_cam_obj: Array, center_cam: Array) -> Array:
    """R_ray^T R_cam_obj [..., 3, 3]: the rotation a bank template (rendered by a camera looking
    at the object's centre, ``threept_jax.data.banks``) must have to look like an object at
    R_cam_obj whose centre is at ``center_cam`` [..., 3] in the camera. Same array rules as
    :func:`ray_rotation`."""
    R_ray = ray_rotation(center_cam)
    xp = jnp if isinstance(R_ray, jax.Array) else np
    return xp.swapaxes(R_ray, -1, -2) @ xp.asarray(R_cam_obj, R_ray.dtype)


def camera_rotation(R_template: Array, center_cam: Array) -> Array:
    """Inverse of :func:`object_centred_rotation`: R_ray R_template [..., 3, 3], the camera
    rotation of a template seen along the ray through ``center_cam`` [..., 3]."""
    R_ray = ray_rotation(center_cam)
    xp = jnp if isinstance(R_ray, jax.Array) else np
    return R_ray @ xp.asarray(R_template, R_ray.dtype)


def box_center_ray(box_xyxy: Array, K: Array) -> Array:
    """[..., 4] pixel-edge xyxy boxes, K [..., 3, 3] -> [..., 3] ray K^-1 (u, v, 1) through the
    box centre (pixel-centre coordinates: u = (x0 + x1) / 2 - 0.5). Same array rules as
    :func:`ray_rotation`."""
    xp = jnp if isinstance(box_xyxy, jax.Array) or isinstance(K, jax.Array) else np
    dtype = jnp.float32 if xp is jnp else np.float64
    box = xp.asarray(box_xyxy, dtype)
    uv = (box[..., :2] + box[..., 2:]) / 2 - 0.5
    uv1 = xp.concatenate([uv, xp.ones_like(uv[..., :1])], -1)
    return xp.linalg.solve(xp.asarray(K, dtype), uv1[..., None])[..., 0]
