"""Pan-and-scan tiling, box back-mapping and merging NMS against hand computations."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from threept_jax.geometry.framing import size_prior
from threept_jax.pipeline.pan_and_scan import (
    axis_tile_starts,
    extract_tiles,
    interior_edge_mask,
    plan_layout,
    projected_size_range,
    scales_for_sizes,
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


def test_the_prior_is_the_one_the_training_tiles_use():
    from threept_jax.data.detector_input import ExampleConfig

    assert size_prior(512) == (128.0, 350.0)
    assert size_prior(128) == (32.0, 87.5)  # the tiny config's 128 px tile
    for tile in (64, 128, 512):
        assert ExampleConfig(tile_size=tile).size_range == size_prior(tile)
    with pytest.raises(ValueError, match="min_overlap"):
        tile_layout((100, 100), tile_size=64, min_overlap=64)


def _covers(scales, sizes, lo, hi):
    """Brute force: every size (full-image px) is put inside [lo, hi] by some scale."""
    mapped = np.asarray(sizes, np.float64)[:, None] * np.asarray(scales, np.float64)[None]
    return np.all(np.any((mapped >= lo * (1 - 1e-9)) & (mapped <= hi * (1 + 1e-9)), axis=1))


def test_unknown_depth_scales_map_64_px_to_the_image_into_the_prior():
    # 640 x 480, 512 tiles: sizes 64-640 px (ratio 10) need ceil(ln 10 / ln(350/128)) =
    # ceil(2.29) = 3 scales. Shares of ratio r = 10**(1/3): [297.1, 640], [137.9, 297.1],
    # [64, 137.9]; each gets sqrt(128 * 350) / (geometric mean of the share) =
    # 211.66 / 436.1, 211.66 / 202.4, 211.66 / 93.94 = 0.4854, 1.0458, 2.2532, and maps to
    # [211.66 / sqrt(r), 211.66 * sqrt(r)] = [144.2, 310.7] px, inside 128-350.
    layout = plan_layout((480, 640), 512)
    np.testing.assert_allclose(layout.scales, [0.4854, 1.0458, 2.2532], rtol=2e-4)
    r = 10 ** (1 / 3)
    for s, (a, b) in zip(layout.scales, [(640 / r, 640), (64 * r, 640 / r), (64, 64 * r)]):
        np.testing.assert_allclose([a * s, b * s], [144.2, 310.7], rtol=2e-4)
    assert _covers(layout.scales, np.geomspace(64, 640, 2001), 128, 350)
    # The 128 px tile of the tiny config: the same shares into 32-87.5 px, scales / 4.
    np.testing.assert_allclose(plan_layout((480, 640), 128).scales,
                               np.asarray(layout.scales) / 4, rtol=1e-12)
    # 2048 x 1536: ratio 32 needs 4 scales; 3 cover the top 2048 / (350/128)**3 = 100.1 px up.
    assert len(plan_layout((1536, 2048), 512).scales) == 4
    with pytest.warns(UserWarning, match="100-2048 px, not down to 64 px"):
        three = plan_layout((1536, 2048), 512, num_scales=3).scales
    assert _covers(three, np.geomspace(100.2, 2048, 2001), 128, 350)
    assert not _covers(three, [95.0], 128, 350)


@pytest.mark.parametrize("diameters, depth, K, tile, num", [
    ([100.0], (500.0, 800.0), [[600, 0, 320], [0, 600, 240], [0, 0, 1]], 512, 1),
    ([100.0], (500.0, 800.0), [[600, 0, 320], [0, 600, 240], [0, 0, 1]], 128, 1),
    ([80.0, 120.0], (400.0, 900.0), [[600, 0, 320], [0, 610, 240], [0, 0, 1]], 512, 2),
    ([50.0], (300.0, 3000.0), [[1000, 0, 640], [0, 1000, 512], [0, 0, 1]], 512, 3),
])
def test_depth_range_puts_projected_diameters_into_the_prior(diameters, depth, K, tile, num):
    sizes = projected_size_range(diameters, depth, K)
    z = np.linspace(depth[0], depth[1], 301)
    f = np.array([K[0][0], K[1][1]], np.float64)
    projected = (np.asarray(diameters, np.float64)[:, None, None] * f[None, :, None]
                 / z[None, None]).ravel()  # diameter * f / z, float64
    np.testing.assert_allclose(sizes, [projected.min(), projected.max()], rtol=1e-12)
    layout = plan_layout((480, 640), tile, object_sizes=sizes)
    assert len(layout.scales) == num  # the fewest: ceil(ln(max / min) / ln(350 / 128))
    lo, hi = size_prior(tile)
    assert _covers(layout.scales, projected, lo, hi)
    if num == 1:  # one scale, geometrically centred: s = sqrt(lo hi / (min max))
        np.testing.assert_allclose(layout.scales[0], np.sqrt(lo * hi / np.prod(sizes)))
    with pytest.raises(ValueError, match="at least 3"):
        scales_for_sizes(10.0, 10.0 * (350 / 128) ** 2.5, 512, num_scales=2)


@pytest.mark.parametrize("bad", [(0.0, 100.0), (900.0, 400.0), (np.nan, 500.0), (100.0,)])
def test_bad_depth_range_is_refused(bad):
    with pytest.raises(ValueError, match="depth range"):
        projected_size_range([100.0], bad, np.diag([600.0, 600.0, 1.0]))


def _fewest_windows(length, tile, overlap):
    """Brute force: the fewest windows of ``tile`` px, consecutive ones overlapping by at
    least ``overlap``, that span ``length``."""
    n = 1
    while (n - 1) * (tile - overlap) + tile < length:
        n += 1
    return n


@pytest.mark.parametrize("hw, expected", [((480, 640), 27), ((1536, 2048), 435)])
def test_tile_counts_are_what_the_geometry_says(hw, expected):
    # 640 x 480 by hand: overlap ceil(310.7) = 311, stride 201; the scaled images are
    # 311 x 233 (1 tile), 669 x 502 (2 x 1) and 1442 x 1082 (ceil(1131 / 201) = 6 by
    # ceil(771 / 201) = 4): 27 tiles per object, against 93 for the old 0.8, 2.19, 5.98.
    layout = plan_layout(hw, 512)
    assert layout.num_tiles == expected
    t = 512
    lo, hi = size_prior(t)
    r = (max(hw) / 64) ** (1 / len(layout.scales))
    biggest = int(np.ceil(np.sqrt(lo * hi * r) - 1e-6))  # largest object size at any scale
    for i, (hs, ws) in enumerate(layout.scaled_hw):
        origin = layout.tile_origin[layout.tile_scale == i]
        assert len(origin) == _fewest_windows(hs, t, biggest) * _fewest_windows(ws, t, biggest)
        # Every object of the largest size, at every position, lies wholly inside a tile.
        for starts, length in ((np.unique(origin[:, 0]), ws), (np.unique(origin[:, 1]), hs)):
            m = min(biggest, length)
            pos = np.arange(length - m + 1)
            inside = (starts[None] <= pos[:, None]) & (pos[:, None] + m <= starts[None] + t)
            assert inside.any(axis=1).all()
