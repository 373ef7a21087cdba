"""Single-view object generation against poses used to synthesise the boxes (cv2 projection)."""

import cv2
import jax
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from threept_jax.geometry.camera import ray_rotation
from threept_jax.geometry.grids import super_fibonacci_rotations
from threept_jax.geometry.rotations import geodesic_angle
from threept_jax.pipeline.object_generation import single_view_hypotheses, translation_from_box


def _box_cv2(points, R, t, K):
    uv, _ = cv2.projectPoints(points.astype(np.float64), cv2.Rodrigues(R.astype(np.float64))[0],
                              t.astype(np.float64), K.astype(np.float64), None)
    uv = uv[:, 0] + 0.5  # pixel-edge coordinates
    return np.concatenate([uv.min(0), uv.max(0)])


@pytest.fixture(scope="module")
def model_points():
    rng = np.random.default_rng(0)
    # An elongated, asymmetric point set (a 120 x 60 x 30 mm box plus a handle).
    pts = rng.uniform([-60, -30, -15], [60, 30, 15], (400, 3))
    return np.concatenate([pts, rng.uniform([40, 30, -5], [60, 70, 5], (50, 3))]).astype(np.float32)


@pytest.mark.parametrize("seed", range(4))
def test_translation_from_box_recovers_pose(model_points, seed):
    rng = np.random.default_rng(seed)
    K = np.array([[610.0, 0, 330.0], [0, 590.0, 235.0], [0, 0, 1]], np.float32)  # fx != fy
    R = Rotation.random(8, random_state=seed).as_matrix().astype(np.float32)
    t = np.stack([rng.uniform(-150, 150, 8), rng.uniform(-100, 100, 8), rng.uniform(400, 1200, 8)], -1)
    boxes = np.stack([_box_cv2(model_points, r, tt, K) for r, tt in zip(R, t)]).astype(np.float32)
    got = np.asarray(jax.jit(translation_from_box)(boxes, np.broadcast_to(K, (8, 3, 3)), R, model_points))
    np.testing.assert_allclose(got, t, rtol=2e-4, atol=0.05)


def test_single_view_hypotheses(model_points):
    K = np.array([[600.0, 0, 320.0], [0, 600.0, 240.0], [0, 0, 1]], np.float32)
    templates = super_fibonacci_rotations(512)
    gt = 137
    t_gt = np.array([90.0, -60.0, 700.0])  # off-axis: the camera sees the object turned by the ray
    R_cam = ray_rotation(t_gt) @ templates[gt]
    box = _box_cv2(model_points, R_cam, t_gt, K).astype(np.float32)
    # Scores peaked at the ground-truth template, with a second mode 90 degrees away.
    ang_gt = np.asarray(geodesic_angle(templates, templates[gt][None]))
    other = templates[gt] @ Rotation.from_euler("x", 90, degrees=True).as_matrix().astype(np.float32)
    ang_other = np.asarray(geodesic_angle(templates, other[None]))
    scores = np.exp(-ang_gt**2 / 0.05) + 0.5 * np.exp(-ang_other**2 / 0.05)
    T, s, valid = single_view_hypotheses(box, K, scores.astype(np.float32), templates, model_points, 4, 45.0)
    T, s, valid = map(np.asarray, (T, s, valid))
    assert valid.all() and np.all(np.diff(s) <= 0)
    # The box centre's ray is not exactly the ray through the object origin: a small error.
    assert np.degrees(float(geodesic_angle(T[0, :3, :3], R_cam))) < 0.5
    np.testing.assert_allclose(T[0, :3, 3], t_gt, rtol=5e-3)
    other_cam = ray_rotation(t_gt) @ other
    assert np.degrees(float(geodesic_angle(T[1, :3, :3], other_cam))) < 15.0
    angles = np.degrees(np.asarray(geodesic_angle(T[:, None, :3, :3], T[None, :, :3, :3])))
    assert angles[~np.eye(4, dtype=bool)].min() >= 45.0
