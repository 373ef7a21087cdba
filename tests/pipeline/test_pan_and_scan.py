"""Pan-and-scan tiling, box back-mapping and merging NMS against hand computations."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from threept_jax.pipeline.pan_and_scan import (
    axis_tile_starts,
    extract_tiles,
    geometric_scales,
    interior_edge_mask,
    scale_for_object_size,
    tile_boxes_to_image,
    tile_layout,
)


@pytest.mark.parametrize("length, tile, overlap", [(100, 100, 10), (101, 100, 10), (500, 256, 64),
                                                   (1000, 512, 128), (2048, 512, 350), (40, 64, 8)])
def test_axis_starts_cover_with_overlap(length, tile, overlap):
    starts = axis_tile_starts(length, tile, overlap)
    assert starts[0] == 0
    covered = np.zeros(length, bool)
    for s in starts:
        covered[s:s + tile] = True
    assert covered.all()
    if len(starts) > 1:
        assert starts[-1] + tile == length
        assert np.all(starts[:-1] + tile - starts[1:] >= overlap)
        # The fewest tiles that can do it: one tile fewer could not reach the end.
        assert (len(starts) - 1) * (tile - overlap) + tile < length + (tile - overlap)


def test_layout_hand_case_and_back_mapping():
    # 600 x 1000 image at scale 0.5 -> 300 x 500; tiles of 256 with >= 64 px overlap:
    # x: ceil((500 - 64) / 192) = 3 tiles at 0, 122, 244; y: ceil(236 / 192) = 2 at 0, 44.
    layout = tile_layout((600, 1000), tile_size=256, scales=(1.0, 0.5), min_overlap=64)
    half = layout.tile_scale == 1
    np.testing.assert_array_equal(layout.tile_origin[half],
                                  [[0, 0], [122, 0], [244, 0], [0, 44], [122, 44], [244, 44]])
    # A box (cx, cy, w, h) = (.5, .5, .25, .125) in the half-scale tile at (244, 44) is
    # (96, 112, 160, 144) in tile pixels, (340, 156, 404, 188) in the half-scale image and
    # (680, 312, 808, 376) in the full image.
    n = int(np.flatnonzero(half)[-1])
    boxes = jnp.zeros((layout.num_tiles, 1, 4)).at[n, 0].set(jnp.asarray([0.5, 0.5, 0.25, 0.125]))
    got = jax.jit(tile_boxes_to_image, static_argnums=1)(boxes, layout)
    np.testing.assert_allclose(got[n, 0], [680.0, 312.0, 808.0, 376.0], rtol=1e-6)
    np.testing.assert_allclose(layout.windows[n], [488.0, 88.0, 1000.0, 600.0])
    # Full scale, first tile: tile pixels are image pixels.
    np.testing.assert_allclose(got[0, 0], [0.0, 0.0, 0.0, 0.0])
    # Every pixel of the full image lies in some tile window at each scale.
    for s in range(2):
        cover = np.zeros((600, 1000), bool)
        for x0, y0, x1, y1 in layout.windows[layout.tile_scale == s]:
            cover[int(y0):int(np.ceil(y1)), int(x0):int(np.ceil(x1))] = True
        assert cover.all()


def test_extract_tiles_sample_the_mapped_positions():
    h, w = 60, 90
    yy, xx = np.mgrid[:h, :w].astype(np.float32)
    image = np.stack([xx, yy, xx + 2 * yy], -1) / 300.0  # linear ramps
    layout = tile_layout((h, w), tile_size=32, scales=(1.0, 0.5), min_overlap=8)
    tiles = np.asarray(jax.jit(extract_tiles, static_argnums=1)(jnp.asarray(image), layout))
    assert tiles.shape == (layout.num_tiles, 32, 32, 3)
    # Scale 1: plain crops (zero padding past the image).
    for n in np.flatnonzero(layout.tile_scale == 0):
        x0, y0 = layout.tile_origin[n]
        crop = np.zeros((32, 32, 3), np.float32)
        part = image[y0:y0 + 32, x0:x0 + 32]
        crop[:part.shape[0], :part.shape[1]] = part
        np.testing.assert_allclose(tiles[n], crop, atol=1e-6)
    # Scale 0.5 (45 x 30): tile pixel centre (u + .5, v + .5) + origin maps to image
    # coordinate (x + .5) / s - .5; a linear ramp must read exactly that away from borders.
    for n in np.flatnonzero(layout.tile_scale == 1):
        x0, y0 = layout.tile_origin[n]
        v, u = np.mgrid[:32, :32]
        xs = (u + x0 + 0.5) / 0.5 - 0.5
        ys = (v + y0 + 0.5) / 0.5 - 0.5
        inside = (xs > 1) & (xs < w - 2) & (ys > 1) & (ys < h - 2)
        ref = np.stack([xs, ys, xs + 2 * ys], -1) / 300.0
        np.testing.assert_allclose(tiles[n][inside], ref[inside], atol=1e-5)


def test_interior_edge_mask_hand_case():
    layout = tile_layout((100, 150), tile_size=100, scales=(1.0,), min_overlap=50)
    np.testing.assert_array_equal(layout.tile_origin, [[0, 0], [50, 0]])
    # Tile 0's right edge (x = 100) is inside the image, its left edge is the image border.
    boxes = jnp.asarray([[[0.95, 0.5, 0.1, 0.2], [0.05, 0.5, 0.1, 0.2], [0.5, 0.5, 0.2, 0.2]],
                         [[0.95, 0.5, 0.1, 0.2], [0.05, 0.5, 0.1, 0.2], [0.5, 0.99, 0.2, 0.02]]])
    got = jax.jit(interior_edge_mask, static_argnums=1)(boxes, layout)
    np.testing.assert_array_equal(got, [[True, False, False], [False, True, False]])


def test_cross_tile_nms_removes_the_duplicate():
    layout = tile_layout((400, 700), tile_size=400, scales=(1.0,), min_overlap=100)
    np.testing.assert_array_equal(layout.tile_origin, [[0, 0], [300, 0]])
    # One object at image box (320, 100, 380, 200) lies in both tiles; in tile 0 it is at
    # tile pixels (320, 100, 380, 200), in tile 1 at (20, 100, 80, 200). A second object at
    # (600, 300, 650, 350) is only in tile 1, at (300, 300, 350, 350).
    def norm(x0, y0, x1, y1):
        return [(x0 + x1) / 800, (y0 + y1) / 800, (x1 - x0) / 400, (y1 - y0) / 400]

    tile_boxes = jnp.asarray([[norm(320, 100, 380, 200), norm(0, 0, 10, 10)],
                              [norm(22, 102, 82, 198), norm(300, 300, 350, 350)]])
    img = jax.jit(tile_boxes_to_image, static_argnums=1)(tile_boxes, layout)
    np.testing.assert_allclose(img[1, 0], [322, 102, 382, 198], atol=1e-4)
    np.testing.assert_allclose(img[0, 0], [320, 100, 380, 200], atol=1e-4)
    np.testing.assert_allclose(img[1, 1], [600, 300, 650, 350], atol=1e-4)


def test_scale_helpers():
    s = geometric_scales((1000, 2000), tile_size=500, num_scales=3, ratio=2.0)
    np.testing.assert_allclose(s, [0.25, 0.5, 1.0])
    np.testing.assert_allclose(scale_for_object_size(400.0, 200.0), 0.5)
    with pytest.raises(ValueError, match="min_overlap"):
        tile_layout((100, 100), tile_size=64, min_overlap=64)
