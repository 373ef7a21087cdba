"""crop_and_resize against cv2.warpAffine, scipy bilinear sampling and crop_intrinsics."""

import cv2
import numpy as np
import pytest
from scipy import ndimage

from threept_jax.geometry.camera import crop_intrinsics, project
from threept_jax.render import crop_and_resize


def _image(h=60, w=80, c=3, seed=0):
    rng = np.random.default_rng(seed)
    small = rng.random((h // 4, w // 4, c)).astype(np.float32)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC).reshape(h, w, c)  # smooth


BOXES = [(10.0, 5.0, 50.0, 45.0), (-8.3, 12.7, 30.1, 70.4), (3.5, 2.25, 79.0, 59.5),
         (20.0, 10.0, 24.0, 13.0)]


@pytest.mark.parametrize("box", BOXES)
@pytest.mark.parametrize("out_hw", [(32, 32), (24, 40)])
def test_matches_scipy_bilinear(box, out_hw):
    img = _image()
    out = np.asarray(crop_and_resize(img, np.array(box), out_hw))
    x0, y0, x1, y1 = box
    sx, sy = out_hw[1] / (x1 - x0), out_hw[0] / (y1 - y0)
    # Output pixel centre i maps to u = (i + 0.5) / sx + x0 - 0.5 (pixel-edge box convention).
    u = (np.arange(out_hw[1]) + 0.5) / sx + x0 - 0.5
    v = (np.arange(out_hw[0]) + 0.5) / sy + y0 - 0.5
    vv, uu = np.meshgrid(v, u, indexing="ij")
    ref = np.stack([ndimage.map_coordinates(img[..., c], [vv, uu], order=1, mode="grid-constant",
                                            cval=0.0) for c in range(3)], -1)
    np.testing.assert_allclose(out, ref, atol=1e-5)


@pytest.mark.parametrize("box", BOXES[:3])
def test_matches_cv2_warp_affine_with_crop_intrinsics_matrix(box):
    """The affine that crop_intrinsics applies to K, used as cv2.warpAffine's forward map."""
    img = _image()
    out_hw = (36, 28)
    S = np.asarray(crop_intrinsics(np.eye(3, dtype=np.float32), np.array(box, np.float32), out_hw))
    ref = cv2.warpAffine(img, S[:2].astype(np.float64), (out_hw[1], out_hw[0]),
                         flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    out = np.asarray(crop_and_resize(img, np.array(box), out_hw))
    # cv2 quantises sub-pixel positions to 1/32 pixel; the image varies by < 0.1 per pixel.
    np.testing.assert_allclose(out, ref, atol=6e-3)


def test_points_land_where_the_crop_intrinsics_project_them():
    """A linear image f(u, v) = a u + b v + c is reproduced exactly by bilinear sampling, so the
    crop's value at each pixel names the source position it came from; that position must be
    the back-projection of the pixel through K_crop and K."""
    K = np.array([[500.0, 0, 41.3], [0, 470.0, 29.8], [0, 0, 1]], np.float32)
    H, W = 60, 80
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    img = np.stack([u, v, np.ones_like(u)], -1).astype(np.float32)
    box = np.array([12.4, 7.9, 61.0, 50.2], np.float32)
    crop, K_crop = crop_and_resize(img, box, (40, 44), K=K)
    crop, K_crop = np.asarray(crop), np.asarray(K_crop, np.float64)
    ii, jj = np.meshgrid(np.arange(44.0), np.arange(40.0))
    back = K.astype(np.float64) @ np.linalg.inv(K_crop)  # crop pixel -> image pixel
    src = np.stack([ii, jj, np.ones_like(ii)], -1) @ back.T
    np.testing.assert_allclose(crop[..., 0], src[..., 0], atol=2e-4)
    np.testing.assert_allclose(crop[..., 1], src[..., 1], atol=2e-4)
    # And a 3-D point projects to corresponding places through K and K_crop.
    X = np.array([[3.0, -2.0, 100.0]], np.float32)
    p, pc = np.asarray(project(X, K))[0], np.asarray(project(X, K_crop.astype(np.float32)))[0]
    sx = 44 / (box[2] - box[0])
    np.testing.assert_allclose(pc[0], (p[0] + 0.5 - box[0]) * sx - 0.5, atol=1e-3)


def test_batched_nearest_and_errors():
    img = _image(c=1)
    imgs = np.stack([img, img[::-1]])
    boxes = np.array([BOXES[0], BOXES[2]], np.float32)
    out = np.asarray(crop_and_resize(imgs, boxes, (16, 16)))
    for k in range(2):
        np.testing.assert_allclose(out[k], np.asarray(crop_and_resize(imgs[k], boxes[k], (16, 16))))
    labels = (np.arange(60 * 80).reshape(60, 80, 1) % 7).astype(np.int32)
    lab = np.asarray(crop_and_resize(labels, np.array(BOXES[1]), (20, 20), method="nearest"))
    assert lab.dtype == np.int32 and set(np.unique(lab)) <= set(range(7))
    x0, y0, x1, y1 = BOXES[1]
    u = np.round((np.arange(20) + 0.5) * (x1 - x0) / 20 + x0 - 0.5).astype(int)
    v = np.round((np.arange(20) + 0.5) * (y1 - y0) / 20 + y0 - 0.5).astype(int)
    ok = (v[:, None] >= 0) & (v[:, None] < 60) & (u[None] >= 0) & (u[None] < 80)
    ref = np.where(ok, labels[np.clip(v, 0, 59)][:, np.clip(u, 0, 79), 0], 0)
    np.testing.assert_array_equal(lab[..., 0], ref)
    with pytest.raises(ValueError, match="x1 > x0"):
        crop_and_resize(img, np.array([10.0, 5.0, 10.0, 20.0]), (8, 8))
