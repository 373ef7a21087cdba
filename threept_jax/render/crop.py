"""Crops: resample an image box to a fixed size, consistently with ``crop_intrinsics``.

Pixel convention (``threept_jax.geometry.camera``): K maps to pixel centres, boxes are in
pixel-edge coordinates. Output pixel (i, j) of a crop of ``box = (x0, y0, x1, y1)`` resized to
``(H', W')`` samples the source at ``u = (i + 0.5) / sx + x0 - 0.5``, ``v = (j + 0.5) / sy +
y0 - 0.5`` with ``sx = W' / (x1 - x0)``, ``sy = H' / (y1 - y0)``: exactly the inverse of the
affine map that ``crop_intrinsics`` applies to K. Outside the image the source is 0.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from threept_jax.geometry.camera import crop_intrinsics


def crop_sample_points(box_xyxy: jax.Array, out_hw: tuple[int, int]) -> tuple[jax.Array, jax.Array]:
    """Source pixel coordinates (u [..., W'], v [..., H']) of a crop's output pixel centres."""
    box = jnp.asarray(box_xyxy, jnp.float32)
    out_h, out_w = out_hw
    sx = out_w / (box[..., 2] - box[..., 0])
    sy = out_h / (box[..., 3] - box[..., 1])
    i = jnp.arange(out_w, dtype=jnp.float32)
    j = jnp.arange(out_h, dtype=jnp.float32)
    u = (i + 0.5) / sx[..., None] + box[..., 0, None] - 0.5
    v = (j + 0.5) / sy[..., None] + box[..., 1, None] - 0.5
    return u, v


def _sample_rows_cols(image, u, v, method):
    """image [H, W, C] sampled at the grid v [H'] x u [W'] -> [H', W', C] (zeros outside)."""
    H, W = image.shape[:2]
    if method == "nearest":
        ui = jnp.round(u).astype(jnp.int32)
        vi = jnp.round(v).astype(jnp.int32)
        ok = ((vi >= 0) & (vi < H))[:, None] & ((ui >= 0) & (ui < W))[None, :]
        out = image[jnp.clip(vi, 0, H - 1)][:, jnp.clip(ui, 0, W - 1)]
        return jnp.where(ok[..., None], out, jnp.zeros((), image.dtype))
    u0f, v0f = jnp.floor(u), jnp.floor(v)
    fu = (u - u0f)[None, :, None]
    fv = (v - v0f)[:, None, None]
    u0, v0 = u0f.astype(jnp.int32), v0f.astype(jnp.int32)
    img = image.astype(jnp.float32)

    def tap(vi, ui):
        ok = ((vi >= 0) & (vi < H))[:, None] & ((ui >= 0) & (ui < W))[None, :]
        val = img[jnp.clip(vi, 0, H - 1)][:, jnp.clip(ui, 0, W - 1)]
        return jnp.where(ok[..., None], val, 0.0)

    top = tap(v0, u0) * (1 - fu) + tap(v0, u0 + 1) * fu
    bot = tap(v0 + 1, u0) * (1 - fu) + tap(v0 + 1, u0 + 1) * fu
    return top * (1 - fv) + bot * fv


@functools.partial(jax.jit, static_argnames=("out_hw", "method"))
def _crop(image, box, *, out_hw, method):
    lead = jnp.broadcast_shapes(image.shape[:-3], box.shape[:-1])
    img = jnp.broadcast_to(image, lead + image.shape[-3:]).reshape((-1,) + image.shape[-3:])
    bx = jnp.broadcast_to(box, lead + (4,)).reshape(-1, 4)
    u, v = crop_sample_points(bx, out_hw)
    out = jax.vmap(lambda im, uu, vv: _sample_rows_cols(im, uu, vv, method))(img, u, v)
    return out.reshape(lead + out.shape[1:])


def crop_and_resize(
    image: jax.Array,
    box_xyxy: jax.Array,
    out_hw: tuple[int, int],
    K: jax.Array | None = None,
    method: str = "bilinear",
):
    """Crop boxes of images and resize them: image [..., H, W, C], box [..., 4] -> [..., H', W', C].

    Bilinear (float32 output) or nearest (keeps dtype: masks, ids) sampling at the crop's pixel
    centres mapped back into the image (module docstring); no anti-aliasing, as in
    ``cv2.warpAffine``. With ``K`` [..., 3, 3] also returns the crop's intrinsics,
    ``crop_intrinsics(K, box, out_hw)``, under which a point projects to the same place in the
    crop as it does in the image.
    """
    if method not in ("bilinear", "nearest"):
        raise ValueError(f"method must be 'bilinear' or 'nearest', got {method!r}")
    image = jnp.asarray(image)
    box = jnp.asarray(box_xyxy, jnp.float32)
    if image.ndim < 3:
        raise ValueError(f"image must be [..., H, W, C], got shape {image.shape}")
    if box.shape[-1] != 4:
        raise ValueError(f"box_xyxy must be [..., 4], got shape {box.shape}")
    width = box[..., 2] - box[..., 0]
    height = box[..., 3] - box[..., 1]
    try:
        degenerate = bool(jnp.any((width <= 0) | (height <= 0)))
    except jax.errors.ConcretizationTypeError:
        degenerate = False
    if degenerate:
        raise ValueError("crop boxes need x1 > x0 and y1 > y0 (pixel-edge xyxy)")
    out_hw = (int(out_hw[0]), int(out_hw[1]))
    out = _crop(image, box, out_hw=out_hw, method=method)
    if K is None:
        return out
    return out, crop_intrinsics(jnp.asarray(K, jnp.float32), box, out_hw)
