"""Input checks for cameras and rigid transforms: the one home for "is this K / R / T valid?".

Every entry point that takes intrinsics or poses from a user or a file (BOP reading, the
renderers, detection, ``run_scene``) calls these, so the same mistake gets the same message
wherever it is made. They work on NumPy values (batched, ``[..., 3, 3]`` / ``[..., 4, 4]``) and
return float64 copies; JAX code calls them on concrete values before tracing.
"""

from __future__ import annotations

import numpy as np

__all__ = ["validate_intrinsics", "validate_rotation", "validate_rigid"]


def _matrices(x, shape: tuple[int, int], where: str, what: str) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    n = shape[0] * shape[1]
    if x.ndim < 2 or x.shape[-2:] != shape:
        if x.size != n:
            raise ValueError(
                f"{where}: {what} must be {shape[0]}x{shape[1]} ({n} values, row-major), got "
                f"shape {x.shape}")
        x = x.reshape(shape)
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{where}: {what} has non-finite entries: {x.tolist()}")
    return x


def validate_intrinsics(K, where: str = "K", image_hw: tuple[int, int] | None = None
                        ) -> np.ndarray:
    """Check and return pinhole intrinsics K [..., 3, 3] as float64.

    K must be upper triangular, row-major ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``, with
    fx, fy > 0. With ``image_hw`` (H, W) the values are also checked against the image: focal
    lengths in pixels (not normalised by the image size) and a principal point near the image
    (a K for another image size is the classic silent error).
    """
    K = _matrices(K, (3, 3), where, "K")
    if np.abs(K[..., 1, 0]).max(initial=0) > 1e-9 or np.abs(K[..., 2, :2]).max(initial=0) > 1e-9:
        raise ValueError(
            f"{where}: K {K.tolist()} is not upper-triangular; K is row-major "
            "[fx, s, cx, 0, fy, cy, 0, 0, 1] (was it written column-major or transposed?)")
    if np.abs(K[..., 2, 2] - 1.0).max(initial=0) > 1e-9:
        raise ValueError(f"{where}: K[2][2] is {K[..., 2, 2].tolist()}, expected 1 "
                         "(divide K by it)")
    if np.any(K[..., 0, 0] <= 0) or np.any(K[..., 1, 1] <= 0):
        raise ValueError(
            f"{where}: focal lengths must be positive (fx > 0, fy > 0), got "
            f"fx={K[..., 0, 0].tolist()}, "
            f"fy={K[..., 1, 1].tolist()} (an image flip belongs in the pose, not in K)")
    if image_hw is not None:
        h, w = image_hw
        if np.minimum(K[..., 0, 0], K[..., 1, 1]).min() < 0.05 * max(h, w):
            raise ValueError(
                f"{where}: focal lengths ({K[..., 0, 0].tolist()}, {K[..., 1, 1].tolist()}) px "
                f"are implausibly small for a {w}x{h} image: K must be in pixels, not "
                "normalised by the image size")
        cx, cy = K[..., 0, 2], K[..., 1, 2]
        if not (np.all((-0.5 * w <= cx) & (cx <= 1.5 * w))
                and np.all((-0.5 * h <= cy) & (cy <= 1.5 * h))):
            raise ValueError(
                f"{where}: principal point ({cx.tolist()}, {cy.tolist()}) is far outside the "
                f"{w}x{h} image: is K for this image size (after any resizing or cropping)?")
    return K


def _orthonormality(R: np.ndarray) -> tuple[float, float]:
    """Largest |R R^T - I| entry and smallest determinant over R [..., 3, 3]."""
    dev = np.abs(R @ np.swapaxes(R, -1, -2) - np.eye(3)).max(initial=0)
    det = float(np.min(np.linalg.det(R))) if R.size else 1.0
    return float(dev), det


def validate_rotation(R, where: str = "R", atol: float = 1e-3) -> np.ndarray:
    """Check and return rotations R [..., 3, 3] as float64: orthonormal within ``atol`` and
    det = +1 (a reflection is refused)."""
    R = _matrices(R, (3, 3), where, "rotation")
    dev, det = _orthonormality(R)
    if dev > atol or det < 0:
        raise ValueError(
            f"{where}: rotation {R.tolist()} is not orthonormal (|R R^T - I| = {dev:.2e}, "
            f"det = {det:.4f}); write R row-major and project it onto SO(3) "
            "(threept_jax.geometry.rotations.project_to_so3) before saving")
    return R


def validate_rigid(T, where: str = "T_cam_obj", atol: float = 1e-3) -> np.ndarray:
    """Check and return rigid transforms T [..., 4, 4] as float64: last row [0, 0, 0, 1] and
    an orthonormal, non-reflecting rotation block (millimetres, OpenCV axes)."""
    T = _matrices(T, (4, 4), where, "transform")
    if np.abs(T[..., 3, :] - [0, 0, 0, 1]).max(initial=0) > 1e-6:
        raise ValueError(f"{where}: last row must be [0, 0, 0, 1] (a rigid transform), got "
                         f"{T[..., 3, :].tolist()}")
    dev, det = _orthonormality(T[..., :3, :3])
    if dev > atol or det <= 0:
        raise ValueError(
            f"{where} is not a rigid transform (R R^T deviates from I by {dev:.3g}, min det "
            f"{det:.3g}): it is scaled, reflecting or not a rotation; project the rotation with "
            "threept_jax.geometry.rotations.project_to_so3")
    return T
