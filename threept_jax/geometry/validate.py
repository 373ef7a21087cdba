"""Input checks for cameras and rigid transforms: the one home for "is this K / R / T valid?".

Every entry point that takes intrinsics or poses from a user or a file (BOP reading, the
renderers, detection, ``run_scene``) calls these, so the same mistake gets the same message
wherever it is made. They work on NumPy values (batched, ``[..., 3, 3]`` / ``[..., 4, 4]``) and
return float64 copies; JAX code calls them on concrete values before tracing.
"""

from __future__ import annotations

import warnings

import numpy as np

__all__ = ["scale_intrinsics", "validate_intrinsics", "validate_rotation", "validate_rigid"]


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


def scale_intrinsics(K, calibration_hw: tuple[int, int], image_hw: tuple[int, int]
                     ) -> np.ndarray:
    """K [..., 3, 3] calibrated on images of size ``calibration_hw`` (H, W) -> K of the same
    camera on images resized to ``image_hw`` (H, W), float64.

    Pixel centres sit at integer coordinates (BOP, OpenCV), so the image spans
    [-0.5, W - 0.5] and a resize by sx = W' / W maps u to (u + 0.5) * sx - 0.5:
    fx' = fx * sx, s' = s * sx, cx' = (cx + 0.5) * sx - 0.5, and likewise fy, cy with
    sy = H' / H.
    """
    K = np.array(K, dtype=np.float64)
    (ch, cw), (h, w) = calibration_hw, image_hw
    sx, sy = w / cw, h / ch
    K[..., 0, :] = K[..., 0, :] * sx
    K[..., 1, :] = K[..., 1, :] * sy
    K[..., 0, 2] += 0.5 * sx - 0.5
    K[..., 1, 2] += 0.5 * sy - 0.5
    return K


def _size(hw, where: str, what: str) -> tuple[int, int]:
    hw = tuple(np.ravel(hw).tolist())
    if len(hw) != 2 or not all(float(v).is_integer() and v > 0 for v in hw):
        raise ValueError(f"{where}: {what} must be two positive integers (height, width), "
                         f"got {hw}")
    return int(hw[0]), int(hw[1])


def validate_intrinsics(K, where: str = "K", image_hw: tuple[int, int] | None = None,
                        calibration_hw: tuple[int, int] | None = None) -> np.ndarray:
    """Check and return pinhole intrinsics K [..., 3, 3] as float64.

    K must be upper triangular, row-major ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``, with
    fx, fy > 0. With ``image_hw`` (H, W) the values are also checked against the image: focal
    lengths in pixels (not normalised by the image size) and a principal point inside the image
    (a K for another image size is the classic silent error): outside [-0.5, W - 0.5] x
    [-0.5, H - 0.5] it is refused, outside the central 20-80% of the size it is warned about.

    ``calibration_hw`` (H, W): the image size K was calibrated at. When it differs from
    ``image_hw``, the returned K is rescaled to the image (:func:`scale_intrinsics`) before
    the checks; a resize that changes the aspect ratio by more than 1% is warned about (a crop
    also moves the principal point, which no rescaling can know).
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
    if calibration_hw is not None:
        if image_hw is None:
            raise ValueError(f"{where}: a calibration size needs the image size to rescale K to")
        (ch, cw), (h, w) = _size(calibration_hw, where, "calibration size"), image_hw
        if abs((w / cw) / (h / ch) - 1) > 0.01:
            warnings.warn(
                f"{where}: the image ({w}x{h}) and the calibration size ({cw}x{ch}) have "
                "different aspect ratios; K is rescaled per axis, which is right for a resize "
                "but wrong for a crop (a crop shifts cx, cy: subtract the crop's corner instead)",
                stacklevel=2)
        K = scale_intrinsics(K, (ch, cw), (h, w))
    if image_hw is not None:
        h, w = image_hw
        if np.minimum(K[..., 0, 0], K[..., 1, 1]).min() < 0.05 * max(h, w):
            raise ValueError(
                f"{where}: focal lengths ({K[..., 0, 0].tolist()}, {K[..., 1, 1].tolist()}) px "
                f"are implausibly small for a {w}x{h} image: K must be in pixels, not "
                "normalised by the image size")
        # Principal point as a fraction of the image extent [-0.5, size - 0.5].
        u, v = (K[..., 0, 2] + 0.5) / w, (K[..., 1, 2] + 0.5) / h
        point = f"principal point ({K[..., 0, 2].tolist()}, {K[..., 1, 2].tolist()})"
        fix = ("is K for this image size? If K was calibrated at another resolution, give "
               "that size (Camera calibration_hw, --calibration-size W H, or "
               '"calibration_size": [W, H] in a cameras JSON) and K is rescaled')
        if np.any((u < 0) | (u > 1) | (v < 0) | (v > 1)):
            raise ValueError(f"{where}: {point} is outside the {w}x{h} image: {fix}")
        if np.any((u < 0.2) | (u > 0.8) | (v < 0.2) | (v > 0.8)):
            warnings.warn(f"{where}: {point} is outside the central 20-80% of the {w}x{h} "
                          f"image: {fix}", stacklevel=2)
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


def validate_vertices(vertices: np.ndarray, where) -> None:
    """Raise ValueError naming ``where`` when there are no vertices or some are NaN/inf."""
    if len(vertices) == 0:
        raise ValueError(f"{where}: no vertices: the file is empty or truncated")
    bad = ~np.isfinite(vertices).all(1)
    if bad.any():
        raise ValueError(
            f"{where}: {int(bad.sum())} vertices have NaN or infinite coordinates "
            f"(first: vertex {int(np.argmax(bad))}); repair or re-export the mesh"
        )


def validate_mesh_arrays(vertices: np.ndarray, faces: np.ndarray | None, where) -> None:
    """Raise ValueError naming ``where`` unless vertices [N, 3] and faces [F, 3] hold a usable
    triangle mesh: some triangles, finite vertices, every face index in [0, N). Runs before
    any processing that indexes vertices by faces (duplicate removal, normals)."""
    validate_vertices(vertices, where)
    if faces is None or len(faces) == 0:
        raise ValueError(
            f"{where}: no triangles ({len(vertices)} vertices, 0 faces): the file is truncated "
            "or holds a point cloud; a mesh needs faces")
    out = (faces < 0) | (faces >= len(vertices))
    if out.any():
        f = int(np.argmax(out.any(1)))
        raise ValueError(
            f"{where}: face indices out of range: face {f} has {np.asarray(faces[f]).tolist()} "
            f"outside [0, {len(vertices)}) ({int(out.any(1).sum())} such faces); the mesh is "
            "corrupt")
