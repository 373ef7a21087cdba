"""Camera functions against OpenCV and float64 NumPy."""

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from threept_jax.geometry import camera


def _random_scene(seed, n=50):
    rng = np.random.default_rng(seed)
    K = np.array([[600.0 + 50 * rng.random(), 0.0, 320 + 10 * rng.standard_normal()],
                  [0, 580.0 + 50 * rng.random(), 240 + 10 * rng.standard_normal()],
                  [0, 0, 1]])
    R = Rotation.random(random_state=seed).as_matrix()
    t = np.array([20.0, -10.0, 800.0]) + 30 * rng.standard_normal(3)
    pts = rng.uniform(-100, 100, (n, 3))
    return K, R, t, pts


@pytest.mark.parametrize("seed", range(3))
def test_project_matches_opencv(seed):
    K, R, t, pts = _random_scene(seed)
    ref, _ = cv2.projectPoints(pts, cv2.Rodrigues(R)[0], t, K, None)
    T = camera.make_transform(R.astype(np.float32), t.astype(np.float32))
    uv = camera.project(camera.transform(T, pts.astype(np.float32)), K.astype(np.float32))
    np.testing.assert_allclose(uv, ref[:, 0], atol=2e-3)


def test_backproject_inverts_project():
    K, R, t, pts = _random_scene(5)
    p_cam = pts @ R.T + t
    uv = np.asarray(camera.project(p_cam.astype(np.float32), K.astype(np.float32)))
    back = camera.backproject(uv, p_cam[:, 2].astype(np.float32), K.astype(np.float32))
    np.testing.assert_allclose(back, p_cam, atol=1e-2)


def test_invert_and_transform_batched():
    Rs = Rotation.random(8, random_state=1).as_matrix()
    ts = np.random.default_rng(1).normal(0, 100, (8, 3))
    T = np.asarray(camera.make_transform(Rs.astype(np.float32), ts.astype(np.float32)))
    np.testing.assert_allclose(camera.invert(T), np.linalg.inv(T.astype(np.float64)), atol=1e-4)
    pts = np.random.default_rng(2).normal(0, 50, (8, 20, 3))
    ref = np.einsum("bij,bnj->bni", Rs, pts) + ts[:, None]
    np.testing.assert_allclose(jax.jit(camera.transform)(T, pts.astype(np.float32)), ref, atol=1e-3)


@pytest.mark.parametrize("box,out_hw", [((100, 60, 228, 188), (64, 64)), ((57, 71, 301, 243), (48, 96))])
def test_crop_intrinsics_matches_opencv_resize(box, out_hw):
    """A Gaussian dot drawn at the projection of a point lands, after cropping the box and
    resizing with cv2.resize (pixel-centre aligned), where the crop's K projects the point."""
    H, W = 320, 400
    K = np.array([[500.0, 0, 190.3], [0, 470.0, 150.8], [0, 0, 1]])
    p = np.array([[-12.0, 7.0, 400.0]])
    u, v = (K @ p[0])[:2] / p[0, 2]
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    img = np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * 6.0**2)).astype(np.float32)
    x0, y0, x1, y1 = box
    crop = cv2.resize(img[y0:y1, x0:x1], (out_hw[1], out_hw[0]), interpolation=cv2.INTER_LINEAR)
    cy, cx = np.mgrid[0 : out_hw[0], 0 : out_hw[1]]
    centroid = np.array([(crop * cx).sum(), (crop * cy).sum()]) / crop.sum()
    Kc = camera.crop_intrinsics(K.astype(np.float32), np.array(box, np.float32), out_hw)
    uv_crop = np.asarray(camera.project(p.astype(np.float32), Kc))[0]
    np.testing.assert_allclose(uv_crop, centroid, atol=0.05)


def test_look_at_centres_target():
    eye, target = np.array([300.0, -200.0, 500.0]), np.array([10.0, 20.0, 0.0])
    T = camera.look_at(eye, target, up=(0, 0, 1))
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]], np.float32)
    uv = camera.project(camera.transform(T, target[None].astype(np.float32)), K)
    np.testing.assert_allclose(uv[0], [320, 240], atol=1e-3)
    # The camera sits at eye, and world up points up in the image (smaller v).
    np.testing.assert_allclose(camera.invert(T)[:3, 3], eye, atol=1e-3)
    above = camera.project(camera.transform(T, (target + [0, 0, 50])[None].astype(np.float32)), K)
    assert above[0, 1] < 240
    assert np.linalg.det(np.asarray(T)[:3, :3]) == pytest.approx(1.0, abs=1e-5)
    # NumPy input: float64 NumPy (host code's bits never depend on XLA); JAX input: JAX float32.
    assert isinstance(T, np.ndarray) and T.dtype == np.float64
    Tj = camera.look_at(jnp.asarray(eye, jnp.float32), jnp.asarray(target, jnp.float32))
    assert isinstance(Tj, jax.Array) and Tj.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(Tj), T, atol=1e-3)


def test_box_center_ray_hand_case_numpy_and_jax():
    # Box (10, 20)-(30, 40) pixel edges: centre (19.5, 29.5) in pixel-centre coordinates.
    K = np.array([[100.0, 0, 50], [0, 200.0, 60], [0, 0, 1]])
    box = np.array([10.0, 20.0, 30.0, 40.0])
    want = [(19.5 - 50) / 100, (29.5 - 60) / 200, 1.0]
    from threept_jax.geometry.camera import box_center_ray

    np.testing.assert_allclose(box_center_ray(box, K), want, rtol=1e-12)
    np.testing.assert_allclose(box_center_ray(jnp.asarray(box), jnp.asarray(K)), want, rtol=1e-6)
