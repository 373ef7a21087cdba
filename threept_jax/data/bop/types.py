"""BOP records: cameras, ground truth, models, estimates, detections and targets."""

from __future__ import annotations

import pathlib
from dataclasses import dataclass

import numpy as np

from threept_jax.data.ply import load_ply_vertices
from threept_jax.geometry.symmetry import Symmetries
from threept_jax.geometry.validate import validate_intrinsics, validate_rigid

POSE_CSV_HEADER = "scene_id,im_id,obj_id,score,R,t,time"
IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".tif", ".tiff")


def make_pose(R, t) -> np.ndarray:
    """R [3, 3], t [3] (mm) -> T [4, 4] float64."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, np.float64).reshape(3, 3)
    T[:3, 3] = np.asarray(t, np.float64).reshape(3)
    return T


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=np.float64)
    a.setflags(write=False)
    return a


# ----------------------------------------------------------------------------- records
@dataclass(frozen=True, eq=False)
class Camera:
    """Per-image camera: K [3, 3] (pixels), depth_scale (depth png * scale = mm), optional
    T_cam_world [4, 4] (world -> camera, mm) from ``cam_R_w2c``/``cam_t_w2c``, and optional
    calibration_hw (H, W): the image size K was calibrated at, when the images are a resized
    version of it (inference rescales K to each image; BOP files have no such field)."""

    K: np.ndarray
    depth_scale: float | None = None
    T_cam_world: np.ndarray | None = None
    calibration_hw: tuple[int, int] | None = None

    def __post_init__(self):
        object.__setattr__(self, "K", _readonly(validate_intrinsics(self.K, "Camera K")))
        if self.T_cam_world is not None:
            T = validate_rigid(self.T_cam_world, "Camera T_cam_world (world -> camera, mm)")
            object.__setattr__(self, "T_cam_world", _readonly(T))
        if self.calibration_hw is not None:
            hw = tuple(np.ravel(self.calibration_hw).tolist())
            if len(hw) != 2 or not all(float(v).is_integer() and v > 0 for v in hw):
                raise ValueError(f"Camera calibration_hw must be two positive integers "
                                 f"(height, width), got {self.calibration_hw}")
            object.__setattr__(self, "calibration_hw", (int(hw[0]), int(hw[1])))

    def to_json(self) -> dict:
        out = {"cam_K": self.K.reshape(-1).tolist()}
        if self.depth_scale is not None:
            out["depth_scale"] = float(self.depth_scale)
        if self.T_cam_world is not None:
            out["cam_R_w2c"] = self.T_cam_world[:3, :3].reshape(-1).tolist()
            out["cam_t_w2c"] = self.T_cam_world[:3, 3].tolist()
        return out


@dataclass(frozen=True, eq=False)
class GtInstance:
    """A ground-truth object instance: obj_id and T_cam_obj [4, 4] (mm)."""

    obj_id: int
    T_cam_obj: np.ndarray

    def __post_init__(self):
        object.__setattr__(self, "obj_id", int(self.obj_id))
        object.__setattr__(self, "T_cam_obj", _readonly(self.T_cam_obj))

    @property
    def R(self) -> np.ndarray:
        return self.T_cam_obj[:3, :3]

    @property
    def t(self) -> np.ndarray:
        return self.T_cam_obj[:3, 3]

    def to_json(self) -> dict:
        return {
            "cam_R_m2c": self.R.reshape(-1).tolist(),
            "cam_t_m2c": self.t.tolist(),
            "obj_id": self.obj_id,
        }


@dataclass(frozen=True)
class GtInfo:
    """Meta information of a GT instance (``scene_gt_info.json``); boxes are [x, y, w, h]."""

    bbox_obj: tuple[int, int, int, int]
    bbox_visib: tuple[int, int, int, int]
    px_count_all: int
    px_count_valid: int
    px_count_visib: int
    visib_fract: float

    def to_json(self) -> dict:
        return {
            "bbox_obj": [int(v) for v in self.bbox_obj],
            "bbox_visib": [int(v) for v in self.bbox_visib],
            "px_count_all": int(self.px_count_all),
            "px_count_valid": int(self.px_count_valid),
            "px_count_visib": int(self.px_count_visib),
            "visib_fract": float(self.visib_fract),
        }


@dataclass(frozen=True, eq=False)
class ObjectModel:
    """An object model entry: id, diameter (mm), 3D box (min corner and size, mm),
    symmetries, and the PLY path (None when the folder lacks the mesh)."""

    obj_id: int
    diameter: float
    bbox_min: np.ndarray
    bbox_size: np.ndarray
    symmetries: Symmetries
    path: pathlib.Path | None = None

    def __post_init__(self):
        object.__setattr__(self, "bbox_min", _readonly(np.reshape(self.bbox_min, 3)))
        object.__setattr__(self, "bbox_size", _readonly(np.reshape(self.bbox_size, 3)))

    @property
    def texture_path(self) -> pathlib.Path | None:
        if self.path is None:
            return None
        for ext in (".png", ".jpg"):
            p = self.path.with_suffix(ext)
            if p.is_file():
                return p
        return None

    def vertices(self) -> np.ndarray:
        """All mesh vertices [N, 3] float64 in mm (read from the PLY on every call)."""
        if self.path is None or not self.path.is_file():
            name = f"obj_{self.obj_id:06d}.ply" if self.path is None else self.path
            raise FileNotFoundError(
                f"object {self.obj_id}: mesh file {name} is missing; models_info.json lists "
                "the object but its models folder has no mesh for it"
            )
        return load_ply_vertices(self.path)

    def to_json(self) -> dict:
        out = {
            "diameter": float(self.diameter),
            "min_x": float(self.bbox_min[0]),
            "min_y": float(self.bbox_min[1]),
            "min_z": float(self.bbox_min[2]),
            "size_x": float(self.bbox_size[0]),
            "size_y": float(self.bbox_size[1]),
            "size_z": float(self.bbox_size[2]),
        }
        out.update(self.symmetries.to_json())
        return out


@dataclass(frozen=True, eq=False)
class PoseEstimate:
    """One row of a BOP 6D results CSV: R [3, 3], t [3] in mm, time in seconds per image."""

    scene_id: int
    im_id: int
    obj_id: int
    score: float
    R: np.ndarray
    t: np.ndarray
    time: float = -1.0

    def __post_init__(self):
        object.__setattr__(self, "R", _readonly(np.reshape(self.R, (3, 3))))
        object.__setattr__(self, "t", _readonly(np.reshape(self.t, 3)))

    @property
    def T_cam_obj(self) -> np.ndarray:
        return make_pose(self.R, self.t)


@dataclass(frozen=True, eq=False)
class Detection2D:
    """One entry of a BOP 2D results JSON: amodal bbox [x, y, w, h] (pixel edges), optional
    visible-mask COCO RLE ``{"counts", "size": [h, w]}``."""

    scene_id: int
    im_id: int
    obj_id: int
    score: float
    bbox: tuple[float, float, float, float] | None = None
    segmentation: dict | None = None
    time: float = -1.0


@dataclass(frozen=True)
class Target:
    """A test target: an image, and for BOP19 localisation targets an object and count."""

    scene_id: int
    im_id: int
    obj_id: int | None = None
    inst_count: int | None = None


@dataclass(frozen=True)
class MultiviewTarget:
    """A multi-view test target: a scene and its views as (sensor or None, im_id) pairs."""

    scene_id: int
    views: tuple[tuple[str | None, int], ...]
