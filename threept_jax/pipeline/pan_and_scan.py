"""Pan-and-scan: overlapping square tiles at several scales, box back-mapping and merging NMS.

3PT-D sees fixed-size tiles (512 x 512 in the paper) in which training put objects at 128-350
px (docs/design.md section 1.1; the scale prior of ``threept_jax/geometry/framing.py``, scaled with
the tile). A full image is resized by each scale s, cut into overlapping tiles, each tile is
queried with each object, and the detections are mapped back to the full image and merged by
NMS across tiles, scales and (optionally) objects.

Scales come from what the user knows (:func:`plan_layout`): with a known depth range, the one
scale (or the few) that puts the objects' projected diameters ``diameter * f / z`` into the
prior (:func:`projected_size_range`); with nothing known (BOP), the fewest scales that cover
objects from 64 px to the whole image, each mapping its share of sizes into the prior
(:func:`scales_for_sizes`): 3 scales and 27 tiles of 512 px per object on a 640 x 480 image.

Conventions: images [H, W, C]; boxes in full-image pixels are xyxy in pixel-edge coordinates
(the image spans [0, W] x [0, H]); detector boxes are normalised cxcywh within a tile. Scaling
an image by s maps pixel-edge coordinate x to x * s (half-pixel-centre resampling, as
``jax.image.resize`` does); because scaled sizes are rounded to whole pixels, each scale's
exact factors are ``(ws / W, hs / H)``. Tiles extending past the scaled image are padded.
Shapes: N tiles, P patches per tile, O query objects, K kept detections.
"""

from __future__ import annotations

import dataclasses
import warnings

import jax
import jax.numpy as jnp
import numpy as np

from threept_jax.geometry.boxes import cxcywh_to_xyxy
from threept_jax.geometry.framing import size_prior

Array = jax.Array

#: Smallest object (pixels of the full image) that the scales for an unknown depth range cover.
MIN_OBJECT_SIZE = 64.0


def axis_tile_starts(length: int, tile: int, min_overlap: int) -> np.ndarray:
    """Start offsets of tiles covering [0, length) with consecutive overlap >= min_overlap.

    One tile at 0 when ``length <= tile``; otherwise the fewest evenly spread tiles, the
    first at 0 and the last ending at ``length``.
    """
    if tile < 1 or not 0 <= min_overlap < tile:
        raise ValueError(f"need tile >= 1 and 0 <= min_overlap < tile, got tile={tile}, "
                         f"min_overlap={min_overlap}")
    if length <= tile:
        return np.zeros(1, np.int64)
    n = int(np.ceil((length - min_overlap) / (tile - min_overlap)))
    while True:
        starts = np.round(np.linspace(0, length - tile, max(n, 2))).astype(np.int64)
        if np.all(np.diff(starts) <= tile - min_overlap):
            return starts
        n += 1


@dataclasses.dataclass(frozen=True, eq=False)
class TileLayout:
    """Where every tile lies. Host-side (NumPy) and static, so tiling compiles once per size.

    Attributes:
      image_hw: (H, W) of the full image.
      tile_size: side t of the square tiles.
      scales: requested scale factors, one per scale level.
      scaled_hw: ((hs, ws), ...) rounded image size at each scale.
      tile_scale: [N] index into ``scales`` of each tile.
      tile_origin: [N, 2] (x0, y0) of each tile's top-left corner in its scaled image.
    """

    image_hw: tuple[int, int]
    tile_size: int
    scales: tuple[float, ...]
    scaled_hw: tuple[tuple[int, int], ...]
    tile_scale: np.ndarray
    tile_origin: np.ndarray

    @property
    def num_tiles(self) -> int:
        return int(self.tile_scale.shape[0])

    @property
    def tile_factors(self) -> np.ndarray:
        """[N, 2] exact (sx, sy) factors from full-image to scaled-image pixels per tile."""
        h, w = self.image_hw
        f = np.array([[ws / w, hs / h] for hs, ws in self.scaled_hw], np.float64)
        return f[self.tile_scale]

    @property
    def windows(self) -> np.ndarray:
        """[N, 4] xyxy full-image pixels each tile sees (may extend past the image)."""
        f = np.concatenate([self.tile_factors] * 2, axis=1)
        o = np.concatenate([self.tile_origin, self.tile_origin + self.tile_size], axis=1)
        return o / f


def tile_layout(image_hw: tuple[int, int], tile_size: int = 512, scales=(1.0,),
                min_overlap: int | None = None) -> TileLayout:
    """Tiles of ``tile_size`` with overlap >= ``min_overlap`` px at each scale, row-major.

    An object of up to ``min_overlap`` pixels (at that scale) lies wholly inside at least one
    tile. The default is the top of the scale prior (:func:`size_prior`), so every object of a
    trained size is seen whole; :func:`plan_layout` lowers it to the largest size its scales
    put an object at.
    """
    if min_overlap is None:
        min_overlap = min(int(np.ceil(size_prior(tile_size)[1])), tile_size - 1)
    h, w = (int(v) for v in image_hw)
    if h < 1 or w < 1:
        raise ValueError(f"image size must be positive, got {image_hw}")
    scales = tuple(float(s) for s in np.atleast_1d(scales))
    if not scales or any(not s > 0 for s in scales):
        raise ValueError(f"scales must be positive, got {scales}")
    scaled, tile_scale, origin = [], [], []
    for i, s in enumerate(scales):
        hs, ws = max(1, round(h * s)), max(1, round(w * s))
        scaled.append((hs, ws))
        ys = axis_tile_starts(hs, tile_size, min_overlap)
        xs = axis_tile_starts(ws, tile_size, min_overlap)
        for y0 in ys:
            for x0 in xs:
                tile_scale.append(i)
                origin.append((x0, y0))
    return TileLayout((h, w), int(tile_size), scales, tuple(scaled),
                      np.asarray(tile_scale, np.int64), np.asarray(origin, np.int64))


def scales_for_sizes(size_min: float, size_max: float, tile_size: int,
                     num_scales: int | None = None) -> tuple[tuple[float, ...], float]:
    """Scales that put objects of ``size_min``-``size_max`` full-image pixels into the prior.

    The size range is split geometrically into S shares of ratio ``r = (max / min)**(1/S)``;
    share k, ``[a_k, a_k r]``, gets the scale ``sqrt(lo hi) / sqrt(a_k * a_k r)``, which maps
    it to ``[sqrt(lo hi / r), sqrt(lo hi r)]``, centred (geometrically) in the prior (lo, hi)
    of :func:`size_prior`. S is ``num_scales``, or by default the fewest whose shares fit,
    ``ceil(log(max / min) / log(hi / lo))``. Returns (scales, smallest first for the largest
    objects, and the largest size in tile pixels any scale puts an object at).

    Raises ValueError when the sizes are not positive or ``num_scales`` shares cannot fit.
    """
    if not 0 < size_min <= size_max < np.inf:
        raise ValueError(f"object sizes must be 0 < min <= max, got {size_min}, {size_max}")
    lo, hi = size_prior(tile_size)
    ratio = size_max / size_min
    fewest = max(1, int(np.ceil(np.log(ratio) / np.log(hi / lo) - 1e-9)))
    if num_scales is None:
        num_scales = fewest
    elif num_scales < fewest:
        raise ValueError(f"{num_scales} scale(s) cannot put object sizes {size_min:.0f}-"
                         f"{size_max:.0f} px into the trained {lo:.0f}-{hi:.0f} px of a "
                         f"{tile_size} px tile: use at least {fewest}")
    r = ratio ** (1.0 / num_scales)
    mid = np.sqrt(lo * hi)
    scales = tuple(float(mid / (size_max / r ** (k + 0.5))) for k in range(num_scales))
    return scales, float(mid * np.sqrt(r))


def projected_size_range(diameters_mm, depth_range_mm, K) -> tuple[float, float]:
    """(min, max) projected object diameters ``diameter * f / z`` in pixels for objects of
    ``diameters_mm`` at depths z in ``depth_range_mm`` (zmin, zmax) seen by intrinsics K
    [3, 3] (f over fx and fy)."""
    d = np.asarray(diameters_mm, np.float64).ravel()
    if d.size == 0 or not np.all(np.isfinite(d) & (d > 0)):
        raise ValueError(f"object diameters must be positive mm, got {d.tolist()}")
    z = np.asarray(depth_range_mm, np.float64).ravel()
    if z.shape != (2,) or not (np.all(np.isfinite(z)) and 0 < z[0] <= z[1]):
        raise ValueError(f"depth range must be (zmin, zmax) in mm with 0 < zmin <= zmax, got "
                         f"{np.ravel(depth_range_mm).tolist()}")
    K = np.asarray(K if K is not None else np.nan, np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or not (K[0, 0] > 0 and K[1, 1] > 0):
        raise ValueError(f"a depth range needs the intrinsics K [3, 3] of the image (fx, fy > 0 "
                         f"px), got {K.tolist()}")
    f = np.array([K[0, 0], K[1, 1]])
    return float(d.min() * f.min() / z[1]), float(d.max() * f.max() / z[0])


def plan_layout(image_hw: tuple[int, int], tile_size: int, *,
                object_sizes: tuple[float, float] | None = None,
                num_scales: int | None = None,
                min_object_size: float = MIN_OBJECT_SIZE) -> TileLayout:
    """The pan-and-scan tiles for what the user knows about object sizes (full-image pixels).

    - Known sizes ``object_sizes`` (min, max), e.g. from a known depth range
      (:func:`projected_size_range`): the fewest scales (or ``num_scales``) mapping them into
      the prior (:func:`scales_for_sizes`).
    - Nothing known (``None``): sizes from ``min_object_size`` to the whole image
      (``max(H, W)``): 3 scales for 640 x 480, 4 for 2048 x 1536. An explicit ``num_scales``
      too few for that range covers its top (the biggest objects), with a warning.

    The tiles overlap by the largest size the scales put an object at, so every object in the
    range lies wholly inside a tile of its scale (detections on interior tile edges are
    dropped).
    """
    if object_sizes is None:
        top = float(max(image_hw))
        bottom = min(float(min_object_size), top)
        if num_scales is not None:
            lo, hi = size_prior(tile_size)
            reach = top / (hi / lo) ** num_scales
            if reach > bottom:
                warnings.warn(f"{num_scales} scale(s) on a {image_hw[1]} x {image_hw[0]} image "
                              f"cover objects of {reach:.0f}-{top:.0f} px, not down to "
                              f"{bottom:.0f} px: raise num_scales", stacklevel=2)
                bottom = reach
        object_sizes = (bottom, top)
    scales, overlap = scales_for_sizes(*object_sizes, tile_size, num_scales)
    return tile_layout(image_hw, tile_size, scales,
                       min(int(np.ceil(overlap - 1e-6)), tile_size - 1))


def extract_tiles(image: Array, layout: TileLayout, pad_value: float = 0.0) -> Array:
    """[H, W, C] image -> [N, t, t, C] float32 tiles in ``layout`` order.

    uint8 input is scaled to [0, 1]. Each scale is resampled once with antialiased bilinear
    interpolation (``jax.image.resize``), padded with ``pad_value`` past its bottom/right
    edge, and cropped at the static tile origins, so the whole function jit-compiles.
    """
    image = jnp.asarray(image)
    if image.ndim != 3 or tuple(image.shape[:2]) != layout.image_hw:
        raise ValueError(f"image must be [H, W, C] with (H, W) = {layout.image_hw}, got "
                         f"{image.shape}; build the layout for this image size")
    uint8 = image.dtype == jnp.uint8
    image = image.astype(jnp.float32) / (255.0 if uint8 else 1.0)
    t = layout.tile_size
    tiles = []
    for i, (hs, ws) in enumerate(layout.scaled_hw):
        scaled = image if (hs, ws) == layout.image_hw else jax.image.resize(
            image, (hs, ws, image.shape[2]), method="linear", antialias=True)
        sel = layout.tile_origin[layout.tile_scale == i]
        ph = max(0, int(sel[:, 1].max()) + t - hs)
        pw = max(0, int(sel[:, 0].max()) + t - ws)
        scaled = jnp.pad(scaled, ((0, ph), (0, pw), (0, 0)), constant_values=pad_value)
        tiles += [scaled[y0:y0 + t, x0:x0 + t] for x0, y0 in sel]
    return jnp.stack(tiles)


def tile_boxes_to_image(boxes: Array, layout: TileLayout, clip: bool = True) -> Array:
    """Tile-normalised cxcywh [N, P, 4] -> full-image xyxy pixels [N, P, 4].

    x_image = (x_tile_px + x0) / sx for every coordinate, with (x0, y0) the tile origin in its
    scaled image and (sx, sy) the scale's exact factors; optionally clipped to the image.
    """
    boxes = jnp.asarray(boxes, jnp.float32)
    if boxes.ndim != 3 or boxes.shape[0] != layout.num_tiles:
        raise ValueError(f"boxes must be [N={layout.num_tiles}, P, 4], got {boxes.shape}")
    px = cxcywh_to_xyxy(boxes) * layout.tile_size
    origin = jnp.asarray(np.tile(layout.tile_origin, 2), jnp.float32)[:, None]
    factor = jnp.asarray(np.tile(layout.tile_factors, 2), jnp.float32)[:, None]
    out = (px + origin) / factor
    if clip:
        h, w = layout.image_hw
        out = jnp.clip(out, 0.0, jnp.asarray([w, h, w, h], jnp.float32))
    return out


def interior_edge_mask(boxes: Array, layout: TileLayout, margin_px: float = 2.0) -> Array:
    """[N, P] True where a tile-normalised cxcywh box [N, P, 4] touches a tile edge that lies
    inside the scaled image (within ``margin_px`` tile pixels): such a box may see only part
    of its object, which another tile or scale sees whole."""
    boxes = jnp.asarray(boxes, jnp.float32)
    t = layout.tile_size
    xyxy = cxcywh_to_xyxy(boxes) * t
    scaled = np.asarray(layout.scaled_hw, np.int64)[layout.tile_scale]  # [N, 2] (hs, ws)
    x0, y0 = layout.tile_origin[:, 0], layout.tile_origin[:, 1]
    inner = np.stack([x0 > 0, y0 > 0, x0 + t < scaled[:, 1], y0 + t < scaled[:, 0]], -1)
    near = jnp.stack([xyxy[..., 0] <= margin_px, xyxy[..., 1] <= margin_px,
                      xyxy[..., 2] >= t - margin_px, xyxy[..., 3] >= t - margin_px], -1)
    return jnp.any(near & jnp.asarray(inner)[:, None, :], -1)
