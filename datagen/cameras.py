"""Camera samplers for synthetic scenes: intrinsics, single views and multi-view rings.

Conventions (docs/design.md section 3): OpenCV cameras (x right, y down, z forward), K [3, 3] in
pixels mapping to pixel-centre coordinates (the image spans [-0.5, W - 0.5] in u), fx may differ
from fy, world frame z up with the support plane at z = 0, extrinsics ``T_cam_world`` [4, 4]
mapping world points (mm) into the camera. Multi-view rigs return one K and one T_cam_world
per view: ``K [V, 3, 3]``, ``T_cam_world [V, 4, 4]``, as in the calibrated multi-view setups
3PT handles (ITODD-MV, IPD: a ring of cameras above a bin, all looking at its centre).

Every sampler is a deterministic function of the ``np.random.Generator`` passed in. Distances
come from ``fit_distance``: the closest distance at which a sphere around the target projects
entirely inside the image, so chosen scenes are never cut by the image border.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from threept_jax.geometry import camera as cam


def sample_intrinsics(
    rng: np.random.Generator,
    width: int,
    height: int,
    fov_deg: tuple[float, float] = (40.0, 70.0),
    aspect: tuple[float, float] = (0.97, 1.03),
    principal_jitter: float = 0.02,
) -> np.ndarray:
    """K [3, 3] (float64) of a realistic pinhole camera for a ``width`` x ``height`` image.

    The field of view across the longer image side is uniform in ``fov_deg``; fy = fx * a with
    a uniform in ``aspect`` (non-square pixels, as calibrations report); the principal point is
    the image centre ((W - 1) / 2, (H - 1) / 2 in pixel-centre coordinates) moved by up to
    ``principal_jitter`` of the image size in each direction.
    """
    if width < 2 or height < 2:
        raise ValueError(f"image size must be at least 2x2 pixels, got {width}x{height}")
    lo, hi = fov_deg
    if not 0 < lo <= hi < 180:
        raise ValueError(f"fov_deg {fov_deg} must satisfy 0 < low <= high < 180 degrees")
    fov = math.radians(rng.uniform(lo, hi))
    f_long = (max(width, height) / 2) / math.tan(fov / 2)
    a = rng.uniform(*aspect)
    # The FOV is defined on the longer side; the other focal length follows from the aspect.
    if width >= height:
        fx, fy = f_long, f_long * a
    else:
        fx, fy = f_long / a, f_long
    cx = (width - 1) / 2 + rng.uniform(-principal_jitter, principal_jitter) * width
    cy = (height - 1) / 2 + rng.uniform(-principal_jitter, principal_jitter) * height
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def fov_deg(K: np.ndarray, width: int, height: int) -> tuple[float, float]:
    """(horizontal, vertical) field of view in degrees of K [3, 3] for the full image."""
    K = np.asarray(K, np.float64)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    h = math.atan((cx + 0.5) / fx) + math.atan((width - 0.5 - cx) / fx)
    v = math.atan((cy + 0.5) / fy) + math.atan((height - 0.5 - cy) / fy)
    return math.degrees(h), math.degrees(v)


def fit_distance(
    K: np.ndarray, width: int, height: int, radius: float, margin_px: float = 0.0
) -> float:
    """Smallest distance at which a sphere of ``radius`` centred on the optical axis fits the image.

    A sphere at distance d on the optical axis has the silhouette cone half-angle asin(r / d):
    in normalised coordinates a circle of radius rho = r / sqrt(d^2 - r^2), in pixels an
    ellipse of semi-axes fx rho, fy rho around the principal point. It fits when both stay
    ``margin_px`` inside the nearest image border, so d = r sqrt(1 + 1 / rho_max^2). Rolling the
    camera about its optical axis does not change this.
    """
    K = np.asarray(K, np.float64)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    room_u = min(cx + 0.5, width - 0.5 - cx) - margin_px
    room_v = min(cy + 0.5, height - 0.5 - cy) - margin_px
    if room_u <= 0 or room_v <= 0:
        raise ValueError(
            f"principal point ({cx:.1f}, {cy:.1f}) leaves no room inside the image with "
            f"margin {margin_px} px; check K and the image size {width}x{height}"
        )
    rho = min(room_u / fx, room_v / fy)
    return float(radius * math.sqrt(1.0 + 1.0 / rho**2))


def bounding_sphere(points: np.ndarray) -> tuple[np.ndarray, float]:
    """A sphere (centre [3], radius) containing ``points`` [N, 3]: AABB centre, farthest point."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    c = (p.min(0) + p.max(0)) / 2
    return c, float(np.linalg.norm(p - c, axis=1).max())


def _direction(azimuth: float, elevation: float) -> np.ndarray:
    """Unit vector from the target to the camera; elevation above the z = 0 plane (radians)."""
    ce = math.cos(elevation)
    return np.array([ce * math.cos(azimuth), ce * math.sin(azimuth), math.sin(elevation)])


def look_at_camera(
    eye: Sequence[float],
    target: Sequence[float],
    up: Sequence[float] = (0.0, 0.0, 1.0),
    roll_deg: float = 0.0,
) -> np.ndarray:
    """T_cam_world [4, 4] (float64) of an OpenCV camera at ``eye`` looking at ``target`` (mm).

    Built with ``threept_jax.geometry.camera.look_at`` in float64 NumPy (never XLA, whose bits
    depend on the backend and compile options: the same arguments give the same scene bytes);
    ``roll_deg`` then turns the camera about its optical axis (positive: the image content turns
    clockwise), which keeps the target on the axis. The rotation is re-orthonormalised.
    """
    T = cam.look_at(np.asarray(eye, np.float64), np.asarray(target, np.float64), up)
    R = T[:3, :3]
    u, _, vt = np.linalg.svd(R)
    R = u @ vt
    eye = np.asarray(eye, np.float64)
    if roll_deg:
        r = math.radians(roll_deg)
        Rz = np.array(
            [[math.cos(r), -math.sin(r), 0.0], [math.sin(r), math.cos(r), 0.0], [0.0, 0.0, 1.0]]
        )
        R = Rz @ R
    out = np.eye(4)
    out[:3, :3] = R
    out[:3, 3] = -R @ eye
    return out


def _orbit_camera(
    target: np.ndarray, distance: float, azimuth: float, elevation: float, roll_deg: float
) -> np.ndarray:
    direction = _direction(azimuth, elevation)
    # Image "up" is the world direction perpendicular to the view in the vertical plane through
    # the camera: world z for low cameras, the horizontal away-from-camera direction for a
    # camera looking straight down, never parallel to the view.
    se, ce = math.sin(elevation), math.cos(elevation)
    up = np.array([-se * math.cos(azimuth), -se * math.sin(azimuth), ce])
    return look_at_camera(target + distance * direction, target, up, roll_deg)


def sample_view(
    rng: np.random.Generator,
    K: np.ndarray,
    width: int,
    height: int,
    target: Sequence[float],
    radius: float,
    *,
    elevation_deg: tuple[float, float] = (25.0, 90.0),
    distance_scale: tuple[float, float] = (1.0, 1.6),
    roll_deg: tuple[float, float] = (-20.0, 20.0),
    target_jitter: float = 0.3,
    margin_px: float = 2.0,
) -> np.ndarray:
    """T_cam_world [4, 4] of one view of a scene bounded by the sphere (``target``, ``radius``).

    The camera looks at a point moved from ``target`` by up to ``target_jitter`` x radius (so
    scenes are not always centred); its distance is ``fit_distance`` of the enlarged sphere times
    a factor in ``distance_scale`` (>= 1 keeps the whole sphere in the image); azimuth is uniform,
    elevation uniform in ``elevation_deg`` above the ground plane, roll in ``roll_deg``.
    """
    if distance_scale[0] < 1.0:
        raise ValueError(
            f"distance_scale {distance_scale} must start at >= 1 to keep the scene in view"
        )
    target = np.asarray(target, np.float64)
    offset = rng.normal(size=3)
    offset *= rng.uniform(0, target_jitter) * radius / max(np.linalg.norm(offset), 1e-12)
    aim = target + offset
    r_eff = radius + float(np.linalg.norm(offset))
    distance = fit_distance(K, width, height, r_eff, margin_px) * rng.uniform(*distance_scale)
    azimuth = rng.uniform(0, 2 * math.pi)
    elevation = math.radians(rng.uniform(*elevation_deg))
    return _orbit_camera(aim, distance, azimuth, elevation, rng.uniform(*roll_deg))


def ring_rig(
    rng: np.random.Generator,
    num_views: int,
    width: int,
    height: int,
    target: Sequence[float],
    radius: float,
    *,
    elevation_deg: tuple[float, float] = (40.0, 70.0),
    distance_scale: tuple[float, float] = (1.0, 1.3),
    azimuth_jitter_deg: float = 10.0,
    roll_deg: tuple[float, float] = (-5.0, 5.0),
    shared_intrinsics: bool = False,
    margin_px: float = 2.0,
    **intrinsics_kwargs,
) -> tuple[np.ndarray, np.ndarray]:
    """A calibrated ring of V cameras above a scene, all looking at ``target``.

    Cameras sit at azimuths 2 pi k / V (+ a common random offset and +-``azimuth_jitter_deg``
    each), at elevations in ``elevation_deg``, each at its own ``fit_distance`` for the sphere
    (``target``, ``radius``) times a factor in ``distance_scale``, like the rigs of ITODD-MV and
    IPD above a bin. Each camera has its own intrinsics unless ``shared_intrinsics``.

    Returns:
      K [V, 3, 3] and T_cam_world [V, 4, 4] (float64, mm).
    """
    if num_views < 1:
        raise ValueError(f"num_views must be >= 1, got {num_views}")
    if distance_scale[0] < 1.0:
        raise ValueError(
            f"distance_scale {distance_scale} must start at >= 1 to keep the scene in view"
        )
    target = np.asarray(target, np.float64)
    K0 = sample_intrinsics(rng, width, height, **intrinsics_kwargs)
    base = rng.uniform(0, 2 * math.pi)
    Ks, Ts = [], []
    for k in range(num_views):
        K = (
            K0
            if shared_intrinsics
            else (K0 if k == 0 else sample_intrinsics(rng, width, height, **intrinsics_kwargs))
        )
        azimuth = (
            base
            + 2 * math.pi * k / num_views
            + math.radians(rng.uniform(-azimuth_jitter_deg, azimuth_jitter_deg))
        )
        elevation = math.radians(rng.uniform(*elevation_deg))
        distance = fit_distance(K, width, height, radius, margin_px) * rng.uniform(*distance_scale)
        Ks.append(K)
        Ts.append(_orbit_camera(target, distance, azimuth, elevation, rng.uniform(*roll_deg)))
    return np.stack(Ks), np.stack(Ts)
