"""The lazy BOP dataset reader: datasets, splits, scenes, images, targets."""

from __future__ import annotations

import functools
import pathlib
import re
import warnings
from collections.abc import Mapping

import numpy as np
from scipy.spatial.transform import Rotation

from threept_jax.data.bop.json_format import _int_keys, _json_int, _load_json, entry_errors
from threept_jax.data.bop.models import (
    MULTIVIEW_TARGETS_FILE,
    load_models,
    load_multiview_targets,
    load_targets,
)
from threept_jax.data.bop.types import (
    IMAGE_EXTS,
    Camera,
    GtInfo,
    GtInstance,
    MultiviewTarget,
    ObjectModel,
    Target,
    make_pose,
)
from threept_jax.geometry.validate import validate_intrinsics, validate_rotation


def _find_image(folder: pathlib.Path, stem: str) -> pathlib.Path:
    for ext in IMAGE_EXTS:
        p = folder / f"{stem}{ext}"
        if p.is_file():
            return p
    raise FileNotFoundError(f"no image {stem}.(png|jpg|tif) in {folder}")


def _read_image(path: pathlib.Path) -> np.ndarray:
    import cv2

    im = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if im is None:
        raise ValueError(f"could not decode image {path}")
    if im.ndim == 3 and im.shape[2] == 3:
        im = im[..., ::-1]
    elif im.ndim == 3 and im.shape[2] == 4:
        im = im[..., [2, 1, 0, 3]]
    return np.ascontiguousarray(im)


def _image_size(path: pathlib.Path) -> tuple[int, int]:
    from PIL import Image

    with Image.open(path) as im:
        return im.size


# ----------------------------------------------------------------------------- reader
def _suffix(sensor: str | None) -> str:
    return f"_{sensor}" if sensor else ""


CAMERA_FORM = "{cam_K: [9 numbers], depth_scale: number[, cam_R_w2c, cam_t_w2c]}"
GT_FORM = "a list of {cam_R_m2c: [9 numbers], cam_t_m2c: [3 numbers] (mm), obj_id: int}"
GT_INFO_FORM = ("a list of {bbox_obj, bbox_visib: [x, y, w, h], px_count_all, px_count_valid, "
                "px_count_visib: int, visib_fract: number}")


def _entry_list(v) -> list:
    if not isinstance(v, list):
        raise TypeError(f"a list of instances, got {type(v).__name__}")
    return v


def _parse_camera(entry: Mapping, where: str) -> Camera:
    model = entry.get("cam_model")
    if "cam_K" in entry:
        K = entry["cam_K"]
    elif isinstance(model, Mapping) and "Pinhole" in str(model.get("projection_model_type", "")):
        fx, fy, cx, cy = model["projection_params"][:4]
        K = [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0]
    else:
        raise ValueError(
            f"{where}: no cam_K; only pinhole cameras are supported (BOP-H3 fisheye "
            "'cam_model' entries need the hand_tracking_toolkit and are out of scope)"
        )
    T = None
    if "cam_R_w2c" in entry and "cam_t_w2c" in entry:
        R = validate_rotation(entry["cam_R_w2c"], f"{where} cam_R_w2c")
        T = make_pose(R, entry["cam_t_w2c"])
    ds = entry.get("depth_scale")
    return Camera(validate_intrinsics(K, f"{where} cam_K"), None if ds is None else float(ds), T)


# Ground-truth rotations: BOP datasets store them rounded (LM-O's rows reach |R R^T - I| ~
# 1e-2), and the toolkit evaluates them as stored. Up to GT_ROTATION_MAX_DEVIATION they are
# accepted; above GT_ROTATION_WARN_DEVIATION a file gets one warning.
GT_ROTATION_WARN_DEVIATION = 1e-6
GT_ROTATION_MAX_DEVIATION = 0.1


def _parse_gt(entry, where: str) -> tuple[GtInstance, float]:
    """A GT instance with its rotation as stored, and the rotation's |R R^T - I| (largest
    entry). Refuses what is not a rotation at all: non-finite, reflecting (det < 0) or
    further than GT_ROTATION_MAX_DEVIATION from orthonormal."""
    R = validate_rotation(entry["cam_R_m2c"], f"{where} cam_R_m2c", GT_ROTATION_MAX_DEVIATION)
    t = np.asarray(entry["cam_t_m2c"], np.float64).reshape(-1)
    if t.shape != (3,):
        raise ValueError(f"{where}: cam_t_m2c must have 3 values (mm)")
    if not np.all(np.isfinite(t)):
        raise ValueError(f"{where}: cam_t_m2c has non-finite values: {t.tolist()}")
    dev = float(np.abs(R @ R.T - np.eye(3)).max())
    return GtInstance(_json_int(entry["obj_id"]), make_pose(R, t)), dev


def _nearest_rotation(T: np.ndarray) -> np.ndarray:
    """T [4, 4] with its rotation block replaced by the nearest rotation (Frobenius norm)."""
    T = T.copy()
    T[:3, :3] = Rotation.from_matrix(T[:3, :3]).as_matrix()
    return T


def _parse_gt_info(e) -> GtInfo:
    return GtInfo(
        tuple(e.get("bbox_obj", (-1,) * 4)),
        tuple(e.get("bbox_visib", (-1,) * 4)),
        int(e.get("px_count_all", 0)),
        int(e.get("px_count_valid", 0)),
        int(e.get("px_count_visib", 0)),
        float(e["visib_fract"]),
    )


class BopScene:
    """One scene folder; JSON files are read on first access and cached, images on request."""

    def __init__(self, path, sensor: str | None = None):
        self.path = pathlib.Path(path)
        self.sensor = sensor
        self.scene_id = int(self.path.name)
        if not self.path.is_dir():
            raise FileNotFoundError(f"scene folder {self.path} does not exist")

    def _file(self, stem: str) -> pathlib.Path:
        return self.path / f"{stem}{_suffix(self.sensor)}.json"

    def _dir(self, stem: str) -> pathlib.Path:
        return self.path / f"{stem}{_suffix(self.sensor)}"

    @functools.cached_property
    def cameras(self) -> dict[int, Camera]:
        """{im_id: Camera} from ``scene_camera[_SENSOR].json``."""
        p = self._file("scene_camera")
        raw = _int_keys(_load_json(p), p)
        out = {}
        for k, v in sorted(raw.items()):
            with entry_errors(f"{p} image {k}", CAMERA_FORM):
                out[k] = _parse_camera(v, f"{p} image {k}")
        return out

    @functools.cached_property
    def gt_as_stored(self) -> dict[int, list[GtInstance]]:
        """{im_id: [GtInstance]} from ``scene_gt[_SENSOR].json`` (index = gt_id), rotations
        exactly as stored: what the BOP toolkit's error functions use, so the evaluator reads
        this. They may be slightly non-orthonormal (rounded in the file, warned once per
        file above GT_ROTATION_WARN_DEVIATION); use `gt` wherever a rotation must be one."""
        p = self._file("scene_gt")
        raw = _int_keys(_load_json(p), p)
        out, worst, n_off = {}, 0.0, 0
        for k, v in sorted(raw.items()):
            out[k] = []
            with entry_errors(f"{p} image {k}", GT_FORM):
                for i, e in enumerate(_entry_list(v)):
                    g, dev = _parse_gt(e, f"{p} image {k} gt {i}")
                    out[k].append(g)
                    worst = max(worst, dev)
                    n_off += dev > GT_ROTATION_WARN_DEVIATION
        if n_off:
            warnings.warn(
                f"{p}: {n_off} ground-truth rotations are not orthonormal to "
                f"{GT_ROTATION_WARN_DEVIATION:g} (worst |R R^T - I| = {worst:.2e}), as in "
                "rounded official BOP files; evaluation uses them as stored (as the BOP "
                "toolkit does), BopScene.gt gives their nearest rotations",
                stacklevel=2,
            )
        return out

    @functools.cached_property
    def gt(self) -> dict[int, list[GtInstance]]:
        """{im_id: [GtInstance]} from ``scene_gt[_SENSOR].json`` (index = gt_id), each
        rotation a rotation: one stored further than GT_ROTATION_WARN_DEVIATION from
        orthonormal is replaced by its nearest rotation (see `gt_as_stored`)."""
        out = {}
        for k, gts in self.gt_as_stored.items():
            out[k] = []
            for g in gts:
                R = g.R
                if np.abs(R @ R.T - np.eye(3)).max() > GT_ROTATION_WARN_DEVIATION:
                    g = GtInstance(g.obj_id, _nearest_rotation(g.T_cam_obj))
                out[k].append(g)
        return out

    @functools.cached_property
    def gt_info(self) -> dict[int, list[GtInfo]]:
        """{im_id: [GtInfo]} from ``scene_gt_info[_SENSOR].json``."""
        p = self._file("scene_gt_info")
        raw = _int_keys(_load_json(p), p)
        out = {}
        for k, v in sorted(raw.items()):
            with entry_errors(f"{p} image {k}", GT_INFO_FORM):
                out[k] = [_parse_gt_info(e) for e in _entry_list(v)]
        gt_path = self._file("scene_gt")
        if gt_path.is_file():
            for k, v in self.gt_as_stored.items():
                if k in out and len(out[k]) != len(v):
                    raise ValueError(
                        f"{p}: image {k} has {len(out[k])} entries but scene_gt "
                        f"has {len(v)}; regenerate scene_gt_info"
                    )
        return out

    @property
    def has_gt(self) -> bool:
        return self._file("scene_gt").is_file()

    @property
    def image_ids(self) -> list[int]:
        return sorted(self.cameras)

    def _image_dir(self) -> pathlib.Path:
        for stem in ("rgb", "gray"):
            d = self._dir(stem)
            if d.is_dir():
                return d
        raise FileNotFoundError(
            f"{self.path} has no rgb{_suffix(self.sensor)}/ or "
            f"gray{_suffix(self.sensor)}/ image folder"
        )

    def image_path(self, im_id: int) -> pathlib.Path:
        return _find_image(self._image_dir(), f"{im_id:06d}")

    def image(self, im_id: int) -> np.ndarray:
        """The colour image [H, W, 3] uint8 RGB (gray images are [H, W])."""
        return _read_image(self.image_path(im_id))

    def image_size(self, im_id: int) -> tuple[int, int]:
        """(width, height) of an image, from its file header only."""
        return _image_size(self.image_path(im_id))

    def depth(self, im_id: int) -> np.ndarray:
        """Depth [H, W] float32 in mm (stored value times depth_scale)."""
        raw = _read_image(_find_image(self._dir("depth"), f"{im_id:06d}")).astype(np.float32)
        scale = self.cameras[im_id].depth_scale
        return raw * np.float32(1.0 if scale is None else scale)

    def mask(self, im_id: int, gt_id: int) -> np.ndarray:
        """Amodal (full silhouette, in image) mask [H, W] bool of GT ``gt_id``."""
        return _read_image(_find_image(self._dir("mask"), f"{im_id:06d}_{gt_id:06d}")) > 0

    def mask_visib(self, im_id: int, gt_id: int) -> np.ndarray:
        """Visible mask [H, W] bool of GT ``gt_id``."""
        return _read_image(_find_image(self._dir("mask_visib"), f"{im_id:06d}_{gt_id:06d}")) > 0

    def has_masks(self, visib: bool = True) -> bool:
        return self._dir("mask_visib" if visib else "mask").is_dir()

    def scene_gt_coco(self) -> dict | None:
        """Contents of ``scene_gt_coco[_SENSOR].json`` when present, else None."""
        p = self._file("scene_gt_coco")
        return _load_json(p) if p.is_file() else None


class BopSplit:
    """A split folder (``test``, ``val``, ``train_pbr``, ...) of a dataset."""

    def __init__(self, path, sensor: str | None = None):
        self.path = pathlib.Path(path)
        self.sensor = sensor
        if not self.path.is_dir():
            raise FileNotFoundError(f"split folder {self.path} does not exist")
        self._scenes: dict[int, BopScene] = {}

    @functools.cached_property
    def scene_ids(self) -> list[int]:
        return sorted(
            int(p.name) for p in self.path.iterdir() if p.is_dir() and re.fullmatch(r"\d+", p.name)
        )

    def scene(self, scene_id: int) -> BopScene:
        if scene_id not in self._scenes:
            p = self.path / f"{int(scene_id):06d}"
            if not p.is_dir():
                raise FileNotFoundError(f"scene {scene_id} not found: {p} does not exist")
            sc = BopScene(p, self.sensor)
            if not sc._file("scene_camera").is_file():
                sensors = sorted(
                    m.group(1)
                    for f in p.glob("scene_camera_*.json")
                    if (m := re.fullmatch(r"scene_camera_(.+)\.json", f.name))
                )
                hint = (
                    f"; this is a multi-sensor scene, pass sensor= one of {sensors}"
                    if sensors and not self.sensor
                    else ""
                )
                raise FileNotFoundError(f"{sc._file('scene_camera')} does not exist{hint}")
            self._scenes[scene_id] = sc
        return self._scenes[scene_id]

    def sensors(self) -> list[str]:
        """Sensor names found as ``scene_camera_{sensor}.json`` in the first scene."""
        if not self.scene_ids:
            return []
        first = self.path / f"{self.scene_ids[0]:06d}"
        return sorted(
            m.group(1)
            for f in first.glob("scene_camera_*.json")
            if (m := re.fullmatch(r"scene_camera_(.+)\.json", f.name))
        )


class BopDataset:
    """A BOP dataset folder. Nothing is read until asked for."""

    def __init__(self, root):
        self.root = pathlib.Path(root)
        if not self.root.is_dir():
            raise FileNotFoundError(f"BOP dataset folder {self.root} does not exist")

    @property
    def name(self) -> str:
        return self.root.name

    def models_dir(self, subdir: str | None = None) -> pathlib.Path:
        """The models folder: ``subdir`` if given, else ``models_eval`` when present (BOP
        evaluates on it), else ``models``."""
        if subdir is not None:
            d = self.root / subdir
            if not d.is_dir():
                raise FileNotFoundError(f"models folder {d} does not exist")
            return d
        for name in ("models_eval", "models"):
            if (self.root / name).is_dir():
                return self.root / name
        raise FileNotFoundError(f"{self.root} has neither models_eval/ nor models/")

    def models(self, subdir: str | None = None) -> dict[int, ObjectModel]:
        return load_models(self.models_dir(subdir))

    def split(self, name: str = "test", sensor: str | None = None) -> BopSplit:
        return BopSplit(self.root / name, sensor)

    def targets(self, name: str) -> list[Target] | None:
        """``test_targets_{name}.json`` (name: 'bop19' or 'bop24') or None when absent."""
        p = self.root / f"test_targets_{name}.json"
        return load_targets(p) if p.is_file() else None

    def multiview_targets(self) -> list[MultiviewTarget] | None:
        p = self.root / MULTIVIEW_TARGETS_FILE
        return load_multiview_targets(p) if p.is_file() else None

    def camera_info(self, sensor: str | None = None) -> dict | None:
        """Contents of ``camera[_SENSOR].json`` (width, height, fx, ...) or None."""
        p = self.root / f"camera{_suffix(sensor)}.json"
        return _load_json(p) if p.is_file() else None
