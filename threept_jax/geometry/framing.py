"""How objects are framed in what the networks see: the detector's scale prior and the
refiner's crop around a pose.

Training (``threept_jax/data``: the detector's tiles, the refiner's crops) and inference
(``threept_jax/pipeline``: pan-and-scan scales, the refinement loop's crops) must frame objects
the same way; both read these definitions here, so neither layer imports the other.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from threept_jax.geometry.camera import transform

Array = jax.Array

#: The scale prior: object sizes (longer side of the amodal box, pixels) that detector training
#: puts objects at on a ``SCALE_REFERENCE_TILE`` tile (docs/design.md section 1.1); a tile of side t
#: scales it by t / ``SCALE_REFERENCE_TILE`` (:func:`size_prior`). Training crops its tiles to
#: it (``data/detector_input.py``); pan-and-scan chooses its scales to map objects into it.
SCALE_PRIOR = (128.0, 350.0)
SCALE_REFERENCE_TILE = 512


def size_prior(tile_size: int) -> tuple[float, float]:
    """(lo, hi) object sizes in pixels of a ``tile_size`` tile that training puts objects at."""
    f = tile_size / SCALE_REFERENCE_TILE
    return SCALE_PRIOR[0] * f, SCALE_PRIOR[1] * f


def crop_boxes(mesh, T_world_obj: Array, T_cam_world: Array, K: Array, *,
               margin: float = 1.2) -> Array:
    """Square crop boxes [..., V, 4] (pixel-edge xyxy) around an object's projected bounding sphere.

    Args:
      mesh: anything with the bounding sphere ``center`` [3] and ``radius`` (mm, object frame):
        a :class:`~threept_jax.render.mesh.Mesh` or :class:`~threept_jax.render.mesh.RasterMesh`.
      T_world_obj: [..., 4, 4] the pose around which to crop (e.g. the best hypothesis).
      T_cam_world: [V, 4, 4] extrinsics; K: [V, 3, 3] full-image intrinsics.
      margin: half-side of the box over the sphere's projected radius.

    The box is centred on the projection of the sphere's centre, with half-side
    ``margin * max(fx, fy) * radius / z`` (z the centre's depth), so the crop's scale follows
    the object's distance and not its rotation. At ``margin >= 1`` the whole object fits for
    centres near the optical axis (the exact projection of a sphere is slightly larger off-axis
    and closer than ~3 radii). Feed the boxes to ``crop_and_resize(image, box, (H, W), K)``,
    which also returns ``crop_K``. The step's caller recomputes them at every iteration.
    """
    T_world_obj = jnp.asarray(T_world_obj, jnp.float32)
    T_cam_world = jnp.asarray(T_cam_world, jnp.float32)
    K = jnp.asarray(K, jnp.float32)
    center = jnp.asarray(mesh.center, jnp.float32)
    radius = jnp.asarray(mesh.radius, jnp.float32)
    c_world = transform(T_world_obj, center[None])[..., 0, :]  # [..., 3]
    c_cam = jnp.einsum("vij,...j->...vi", T_cam_world[:, :3, :3], c_world) + T_cam_world[:, :3, 3]
    z = jnp.maximum(c_cam[..., 2], 1e-6)
    u = (K[..., 0, 0] * c_cam[..., 0] + K[..., 0, 1] * c_cam[..., 1]) / z + K[..., 0, 2]
    v = K[..., 1, 1] * c_cam[..., 1] / z + K[..., 1, 2]
    half = margin * jnp.maximum(K[..., 0, 0], K[..., 1, 1]) * radius / z
    # Pixel centre (u, v) is at pixel-edge coordinate (u + 0.5, v + 0.5).
    return jnp.stack([u + 0.5 - half, v + 0.5 - half, u + 0.5 + half, v + 0.5 + half], -1)
