"""Camera samplers: realistic intrinsics, views aimed at their target, scenes fully in the image.

References: OpenCV ``cv2.projectPoints`` for every projection, field-of-view formulas derived by
hand, and camera centres recovered as -R^T t in float64.
"""

import math

import cv2
import numpy as np
import pytest

from datagen import cameras as C
from datagen import layouts as L
from datagen import procedural as P


def _project(K, T_cam_world, points):
    """cv2.projectPoints of world points [N, 3] -> (uv [N, 2], depth [N])."""
    rvec, _ = cv2.Rodrigues(np.asarray(T_cam_world[:3, :3], np.float64))
    uv, _ = cv2.projectPoints(
        np.asarray(points, np.float64).reshape(-1, 1, 3),
        rvec,
        np.asarray(T_cam_world[:3, 3], np.float64),
        np.asarray(K, np.float64),
        None,
    )
    depth = points @ T_cam_world[:3, :3].T[:, 2] + T_cam_world[2, 3]
    return uv.reshape(-1, 2), depth


def _inside(uv, width, height):
    """Pixel-centre coordinates: the image spans [-0.5, W - 0.5] x [-0.5, H - 0.5]."""
    return (
        (uv[:, 0] >= -0.5)
        & (uv[:, 0] <= width - 0.5)
        & (uv[:, 1] >= -0.5)
        & (uv[:, 1] <= height - 0.5)
    )


@pytest.mark.parametrize("size", [(640, 480), (480, 640), (1920, 1200)])
def test_intrinsics_are_realistic(size):
    width, height = size
    rng = np.random.default_rng(0)
    for _ in range(100):
        K = C.sample_intrinsics(rng, width, height)
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        assert K[0, 1] == 0 and K[1, 0] == 0 and K[2].tolist() == [0, 0, 1]
        f_long = fx if width >= height else fy
        fov_long = 2 * math.degrees(math.atan(max(width, height) / 2 / f_long))
        assert 40 - 1e-9 <= fov_long <= 70 + 1e-9
        assert 0.97 - 1e-12 <= fy / fx <= 1.03 + 1e-12
        assert (
            abs(cx - (width - 1) / 2) <= 0.02 * width
            and abs(cy - (height - 1) / 2) <= 0.02 * height
        )
        h, v = C.fov_deg(K, width, height)
        assert h == pytest.approx(
            math.degrees(math.atan((cx + 0.5) / fx) + math.atan((width - 0.5 - cx) / fx))
        )
    with pytest.raises(ValueError, match="fov_deg"):
        C.sample_intrinsics(rng, 640, 480, fov_deg=(70, 40))


def test_fit_distance_is_the_tightest_distance_keeping_a_sphere_inside():
    width, height, r = 640, 480, 100.0
    K = np.array([[500.0, 0, 330.0], [0, 520.0, 235.0], [0, 0, 1]])
    # Hand derivation: the sphere's image is an ellipse of semi-axes f rho with
    # rho = r / sqrt(d^2 - r^2); the nearest borders are 309.5 px away in u (fx 500) and
    # 235.5 px in v (fy 520).
    rho = min(309.5 / 500.0, 235.5 / 520.0)
    d = C.fit_distance(K, width, height, r)
    assert d == pytest.approx(r * math.sqrt(1 + 1 / rho**2))
    sphere = np.random.default_rng(0).normal(size=(20000, 3))
    sphere = r * sphere / np.linalg.norm(sphere, axis=1, keepdims=True)
    for scale, all_in in ((1.0, True), (0.97, False)):
        T = np.eye(4)
        T[2, 3] = d * scale  # camera looks at the sphere centre from d along its optical axis
        uv, z = _project(K, T, sphere)
        assert (z > 0).all() and _inside(uv, width, height).all() == all_in


def test_single_views_aim_at_their_target_and_keep_the_scene_in_view():
    width, height = 640, 480
    rng = np.random.default_rng(1)
    target, radius = np.array([30.0, -20.0, 60.0]), 120.0
    cloud = np.random.default_rng(2).normal(size=(4000, 3))
    cloud = target + radius * cloud / np.linalg.norm(cloud, axis=1, keepdims=True)
    for _ in range(30):
        K = C.sample_intrinsics(rng, width, height)
        # No jitter: the optical axis must pass exactly through the target.
        T = C.sample_view(rng, K, width, height, target, radius, target_jitter=0.0)
        R, t = T[:3, :3], T[:3, 3]
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        uv, z = _project(K, T, target[None])
        np.testing.assert_allclose(uv[0], K[:2, 2], atol=1e-3)
        eye = -R.T @ t
        assert np.linalg.norm(eye - target) >= C.fit_distance(K, width, height, radius) - 1e-3
        assert eye[2] > target[2], "cameras look down at the scene"
        uv, z = _project(K, T, cloud)
        assert (z > 0).all() and _inside(uv, width, height).all()
        # With jitter the camera aims elsewhere, yet the whole sphere stays in view.
        T = C.sample_view(rng, K, width, height, target, radius)
        uv, z = _project(K, T, cloud)
        assert (z > 0).all() and _inside(uv, width, height).all()


def test_straight_down_view_is_well_defined():
    K = C.sample_intrinsics(np.random.default_rng(0), 640, 480)
    T = C.sample_view(
        np.random.default_rng(0),
        K,
        640,
        480,
        (0, 0, 0),
        50.0,
        elevation_deg=(90.0, 90.0),
        target_jitter=0.0,
        roll_deg=(0.0, 0.0),
    )
    assert np.isfinite(T).all()
    np.testing.assert_allclose(T[2, :3], [0, 0, -1], atol=1e-6)  # optical axis = world -z
    uv, _ = _project(K, T, np.zeros((1, 3)))
    np.testing.assert_allclose(uv[0], K[:2, 2], atol=1e-3)


@pytest.fixture(scope="module")
def packed_scene():
    """A real layout: 12 parts packed on the plane (no physics needed)."""
    rng = np.random.default_rng(3)
    parts = [
        P.generate_part(rng, fam, max_faces=800) for fam in ("bracket", "nut", "gear", "plate")
    ]
    shapes = [L.collision_shape(p.mesh) for p in parts]
    idx = L.choose_instances(np.random.default_rng(4), len(parts), 12)
    lay = L.pack_layout(np.random.default_rng(5), shapes, idx, mode="grid")
    return np.concatenate(
        [
            parts[i].mesh.vertices @ T[:3, :3].T + T[:3, 3]
            for i, T in zip(lay.mesh_index, lay.T_world_obj)
        ]
    )


def test_ring_rig_views_the_whole_scene_from_every_camera(packed_scene):
    width, height, V = 720, 540, 6
    centre, radius = C.bounding_sphere(packed_scene)
    assert np.linalg.norm(packed_scene - centre, axis=1).max() <= radius + 1e-9
    K, T = C.ring_rig(np.random.default_rng(6), V, width, height, centre, radius)
    assert K.shape == (V, 3, 3) and T.shape == (V, 4, 4)
    eyes = np.einsum("vji,vj->vi", T[:, :3, :3], -T[:, :3, 3])
    azimuths = np.sort(np.degrees(np.arctan2(eyes[:, 1] - centre[1], eyes[:, 0] - centre[0])) % 360)
    gaps = np.diff(np.concatenate([azimuths, azimuths[:1] + 360]))
    assert (np.abs(gaps - 360 / V) <= 2 * 10 + 1e-6).all(), "evenly spread around the scene"
    elevation = np.degrees(
        np.arcsin((eyes[:, 2] - centre[2]) / np.linalg.norm(eyes - centre, axis=1))
    )
    assert ((elevation >= 40 - 1e-6) & (elevation <= 70 + 1e-6)).all()
    assert len({K[v].tobytes() for v in range(V)}) == V, "independently calibrated cameras"
    for v in range(V):
        uv, _ = _project(K[v], T[v], centre[None])
        np.testing.assert_allclose(uv[0], K[v, :2, 2], atol=1e-3)
        uv, z = _project(K[v], T[v], packed_scene)
        assert (z > 0).all() and _inside(uv, width, height).all()
        # Upright cameras: world z points up in the image (camera -y), small roll only.
        assert T[v, 1, 2] < 0
    Ks, _ = C.ring_rig(
        np.random.default_rng(6), V, width, height, centre, radius, shared_intrinsics=True
    )
    assert all(np.array_equal(Ks[0], Ks[v]) for v in range(V))


def test_samplers_are_deterministic():
    a = C.ring_rig(np.random.default_rng(9), 4, 640, 480, (0, 0, 0), 100.0)
    b = C.ring_rig(np.random.default_rng(9), 4, 640, 480, (0, 0, 0), 100.0)
    c = C.ring_rig(np.random.default_rng(10), 4, 640, 480, (0, 0, 0), 100.0)
    assert a[0].tobytes() == b[0].tobytes() and a[1].tobytes() == b[1].tobytes()
    assert a[1].tobytes() != c[1].tobytes()
    with pytest.raises(ValueError, match="num_views"):
        C.ring_rig(np.random.default_rng(0), 0, 640, 480, (0, 0, 0), 100.0)
    with pytest.raises(ValueError, match="distance_scale"):
        C.sample_view(
            np.random.default_rng(0), np.eye(3), 640, 480, (0, 0, 0), 1.0, distance_scale=(0.5, 1.0)
        )
