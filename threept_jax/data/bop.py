"""BOP datasets in and out: lazy reader, typed records, result files and a scene writer.

The layout and field names follow the BOP toolkit's `docs/bop_datasets_format.md`
(BOP-scenewise format) and its `bop_toolkit_lib/inout.py`:

```
DATASET/
  camera[_SENSOR].json            optional: width, height, fx, fy, cx, cy, depth_scale
  test_targets_bop19.json         [{scene_id, im_id, obj_id, inst_count}]  (6D localisation)
  test_targets_bop24.json         [{scene_id, im_id}]                      (6D/2D detection)
  test_targets_multiview_bop25.json  multi-view groups (see `load_multiview_targets`)
  models[_eval]/models_info.json, obj_{obj_id:06d}.ply (+ texture png)
  {split}/{scene_id:06d}/
    scene_camera[_SENSOR].json    per image: cam_K (row-major), depth_scale, cam_R_w2c, cam_t_w2c
    scene_gt[_SENSOR].json        per image: [{obj_id, cam_R_m2c, cam_t_m2c}]  (mm)
    scene_gt_info[_SENSOR].json   per image: [{bbox_obj, bbox_visib, px_count_*, visib_fract}]
    rgb|gray[_SENSOR]/{im_id:06d}.png|jpg|tif, depth[_SENSOR]/, mask[_SENSOR]/, mask_visib[_SENSOR]/
```

Conventions: poses are ``T_cam_obj`` (4x4 float64, translation in mm) built from
``cam_R_m2c``/``cam_t_m2c``; world extrinsics, when present, are ``T_cam_world`` from
``cam_R_w2c``/``cam_t_w2c``. Opening a dataset reads no image and no per-scene JSON: scenes
load their JSON on first use and images are read one at a time on request.

Writers produce files the official toolkit reads: the 6D results CSV
(`inout.save_bop_results`: ``scene_id,im_id,obj_id,score,R,t,time``, R row-major, t in mm,
one time per image), the 2D results JSON (`inout.save_coco_results`: amodal ``bbox`` [x, y,
w, h], visible-mask COCO RLE, integer ids) and whole scenes (`BopSceneWriter`), whose
``scene_gt_info`` fields are computed as in `scripts/calc_gt_info.py` (``bbox_obj`` from the
full silhouette, ``[x, y, x_max - x_min, y_max - y_min]``, [-1]*4 when nothing is visible).
JSON is formatted like `inout.save_json` (one top-level entry per line, integer keys in
numeric order) and written atomically (temporary file + rename).
"""

from __future__ import annotations

import functools
import io
import json
import os
import pathlib
import re
import tempfile
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from threept_jax.data.files import atomic_write_bytes
from threept_jax.geometry.diameter import MIN_DIAMETER_MM, mesh_diameter
from threept_jax.geometry.symmetry import Symmetries
from threept_jax.geometry.validate import validate_intrinsics, validate_rotation

from threept_jax.data.ply import load_ply_vertices

__all__ = [
    "Camera",
    "GtInstance",
    "GtInfo",
    "ObjectModel",
    "PoseEstimate",
    "Detection2D",
    "Target",
    "MultiviewTarget",
    "BopDataset",
    "BopSplit",
    "BopScene",
    "BopSceneWriter",
    "load_models_info",
    "load_models",
    "write_models_info",
    "compute_model_info",
    "load_targets",
    "load_multiview_targets",
    "write_targets",
    "read_pose_results",
    "write_pose_results",
    "top_estimates_per_image",
    "check_consistent_times",
    "read_detection_results",
    "write_detection_results",
    "mask_to_rle",
    "rle_to_mask",
    "write_json_atomic",
    "make_pose",
]

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
    T_cam_world [4, 4] (mm) from ``cam_R_w2c``/``cam_t_w2c``."""

    K: np.ndarray
    depth_scale: float | None = None
    T_cam_world: np.ndarray | None = None

    def __post_init__(self):
        object.__setattr__(self, "K", _readonly(validate_intrinsics(self.K)))
        if self.T_cam_world is not None:
            object.__setattr__(self, "T_cam_world", _readonly(self.T_cam_world))

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
            raise FileNotFoundError(
                f"object {self.obj_id}: mesh file {self.path} is missing; models_info.json lists "
                "the object but the models folder has no obj_{obj_id:06d}.ply for it"
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


# ----------------------------------------------------------------------------- JSON helpers
def _json_dumps_bop(content) -> str:
    """Format like `bop_toolkit_lib.inout.save_json`: one top-level entry per line."""
    buf = io.StringIO()
    if isinstance(content, Mapping):
        items = sorted(content.items(), key=lambda kv: kv[0])
        buf.write("{\n")
        for i, (k, v) in enumerate(items):
            buf.write(f'  "{k}": {json.dumps(v, sort_keys=True)}')
            buf.write(",\n" if i != len(items) - 1 else "\n")
        buf.write("}")
    elif isinstance(content, list):
        buf.write("[\n")
        for i, v in enumerate(content):
            buf.write(f"  {json.dumps(v, sort_keys=True)}")
            buf.write(",\n" if i != len(content) - 1 else "\n")
        buf.write("]")
    else:
        buf.write(json.dumps(content, sort_keys=True))
    return buf.getvalue()


def write_json_atomic(path, content) -> None:
    """Write ``content`` as BOP-formatted JSON to ``path`` via a temporary file and rename."""
    atomic_write_bytes(pathlib.Path(path), _json_dumps_bop(content).encode())


def _load_json(path: pathlib.Path):
    if not path.is_file():
        raise FileNotFoundError(f"missing BOP file {path}")
    try:
        with open(path) as f:
            return json.load(f)
    except json.JSONDecodeError as e:
        raise ValueError(f"{path} is not valid JSON ({e}); the file is probably truncated") from e


def _int_keys(d: Mapping, path) -> dict:
    out = {}
    for k, v in d.items():
        try:
            out[int(k)] = v
        except ValueError:
            raise ValueError(f"{path}: key {k!r} is not an integer image id") from None
    return out


# ----------------------------------------------------------------------------- models
def compute_model_info(
    vertices: np.ndarray, symmetries: Symmetries | None = None, obj_id: int = 0, path=None
) -> ObjectModel:
    """Model info from vertices [N, 3] (mm): exact diameter (max pairwise vertex distance,
    `misc.calc_pts_diameter`) and 3D box, as `scripts/calc_model_info.py` computes them."""
    v = np.asarray(vertices, np.float64)
    lo, hi = v.min(0), v.max(0)
    diameter = mesh_diameter(v)
    return ObjectModel(
        int(obj_id),
        diameter,
        lo,
        hi - lo,
        symmetries or Symmetries(),
        None if path is None else pathlib.Path(path),
    )


def _parse_model_info(obj_id: int, info: Mapping, path: pathlib.Path, folder: pathlib.Path):
    where = f"{path} object {obj_id}"
    if "diameter" not in info:
        raise ValueError(
            f"{where}: no 'diameter'; recompute models_info.json "
            "(bop_toolkit scripts/calc_model_info.py)"
        )
    diameter = float(info["diameter"])
    if not diameter >= MIN_DIAMETER_MM:
        raise ValueError(
            f"{where}: diameter {diameter} looks like metres; BOP models and poses are in mm "
            "(scale the PLY and models_info.json by 1000)"
        )
    lo = [float(info.get(k, 0.0)) for k in ("min_x", "min_y", "min_z")]
    size = [float(info.get(k, 0.0)) for k in ("size_x", "size_y", "size_z")]
    mesh = folder / f"obj_{obj_id:06d}.ply"
    return ObjectModel(
        obj_id,
        diameter,
        lo,
        size,
        Symmetries.from_json(info, where),
        mesh if mesh.is_file() else None,
    )


def load_models_info(path) -> dict[int, ObjectModel]:
    """Parse a ``models_info.json`` into {obj_id: ObjectModel} (mesh paths beside it)."""
    path = pathlib.Path(path)
    raw = _int_keys(_load_json(path), path)
    return {k: _parse_model_info(k, v, path, path.parent) for k, v in sorted(raw.items())}


def load_models(models_dir) -> dict[int, ObjectModel]:
    """Load a BOP models folder (``models_info.json`` + ``obj_*.ply``) lazily (no mesh read)."""
    models_dir = pathlib.Path(models_dir)
    info = models_dir / "models_info.json"
    if not info.is_file():
        raise FileNotFoundError(
            f"{models_dir} has no models_info.json; a BOP models folder needs one "
            "(compute it with threept_jax.data.bop.compute_model_info and write_models_info)"
        )
    return load_models_info(info)


def write_models_info(path, models: Mapping[int, ObjectModel] | Iterable[ObjectModel]) -> None:
    """Write ``models_info.json`` for the given models (atomic)."""
    if isinstance(models, Mapping):
        models = models.values()
    write_json_atomic(path, {int(m.obj_id): m.to_json() for m in models})


# ----------------------------------------------------------------------------- targets
def load_targets(path) -> list[Target]:
    """Load ``test_targets_bop19.json`` (with obj_id, inst_count) or ``_bop24.json`` (images)."""
    path = pathlib.Path(path)
    raw = _load_json(path)
    if not isinstance(raw, list):
        raise ValueError(
            f"{path}: a targets file must hold a JSON list of "
            "{scene_id, im_id[, obj_id, inst_count]} entries"
        )
    out = []
    for i, t in enumerate(raw):
        if "scene_id" not in t or "im_id" not in t:
            raise ValueError(f"{path}: entry {i} lacks scene_id or im_id: {t}")
        if isinstance(t["im_id"], list):
            raise ValueError(
                f"{path}: entry {i} lists several images; this is a multi-view "
                "targets file (read it with load_multiview_targets); per-image "
                "evaluation needs test_targets_bop24.json or _bop19.json"
            )
        out.append(
            Target(
                int(t["scene_id"]),
                int(t["im_id"]),
                None if t.get("obj_id") is None else int(t["obj_id"]),
                None if t.get("inst_count") is None else int(t["inst_count"]),
            )
        )
    return out


def write_targets(path, targets: Iterable[Target]) -> None:
    """Write a targets file (bop19 style when obj_id is set, else bop24 style)."""
    rows = []
    for t in targets:
        row = {"im_id": int(t.im_id), "scene_id": int(t.scene_id)}
        if t.obj_id is not None:
            row["obj_id"] = int(t.obj_id)
            row["inst_count"] = int(t.inst_count or 1)
        rows.append(row)
    write_json_atomic(path, rows)


def load_multiview_targets(path) -> list[MultiviewTarget]:
    """Load ``test_targets_multiview_bop25.json``: a list of groups with ``scene_id`` and the
    group's views under ``im_id`` (or ``im_ids``): an int, a list of ints, or a list of
    ``[sensor, im_id]`` pairs. Returns one MultiviewTarget per group."""
    path = pathlib.Path(path)
    raw = _load_json(path)
    if not isinstance(raw, list):
        raise ValueError(f"{path}: expected a JSON list of multi-view groups")
    out = []
    for i, g in enumerate(raw):
        views = g.get("im_ids", g.get("im_id"))
        if "scene_id" not in g or views is None:
            raise ValueError(f"{path}: group {i} needs scene_id and im_id/im_ids: {g}")
        if not isinstance(views, list):
            views = [views]
        parsed = []
        for v in views:
            if isinstance(v, (list, tuple)) and len(v) == 2:
                parsed.append((str(v[0]), int(v[1])))
            elif isinstance(v, Mapping):
                parsed.append((v.get("sensor"), int(v["im_id"])))
            else:
                parsed.append((None, int(v)))
        out.append(MultiviewTarget(int(g["scene_id"]), tuple(parsed)))
    return out


# ----------------------------------------------------------------------------- images
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


def _parse_gt(entry, where: str) -> GtInstance:
    R = validate_rotation(entry["cam_R_m2c"], f"{where} cam_R_m2c")
    t = np.asarray(entry["cam_t_m2c"], np.float64).reshape(-1)
    if t.shape != (3,):
        raise ValueError(f"{where}: cam_t_m2c must have 3 values (mm)")
    return GtInstance(int(entry["obj_id"]), make_pose(R, t))


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
        return {k: _parse_camera(v, f"{p} image {k}") for k, v in sorted(raw.items())}

    @functools.cached_property
    def gt(self) -> dict[int, list[GtInstance]]:
        """{im_id: [GtInstance]} from ``scene_gt[_SENSOR].json`` (index = gt_id)."""
        p = self._file("scene_gt")
        raw = _int_keys(_load_json(p), p)
        return {
            k: [_parse_gt(e, f"{p} image {k} gt {i}") for i, e in enumerate(v)]
            for k, v in sorted(raw.items())
        }

    @functools.cached_property
    def gt_info(self) -> dict[int, list[GtInfo]]:
        """{im_id: [GtInfo]} from ``scene_gt_info[_SENSOR].json``."""
        p = self._file("scene_gt_info")
        raw = _int_keys(_load_json(p), p)
        out = {k: [_parse_gt_info(e) for e in v] for k, v in sorted(raw.items())}
        gt_path = self._file("scene_gt")
        if gt_path.is_file():
            for k, v in self.gt.items():
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
        p = self.root / "test_targets_multiview_bop25.json"
        return load_multiview_targets(p) if p.is_file() else None

    def camera_info(self, sensor: str | None = None) -> dict | None:
        """Contents of ``camera[_SENSOR].json`` (width, height, fx, ...) or None."""
        p = self.root / f"camera{_suffix(sensor)}.json"
        return _load_json(p) if p.is_file() else None


# ----------------------------------------------------------------------------- 6D results
def write_pose_results(path, estimates: Iterable[PoseEstimate], time_tol: float = 1e-3) -> None:
    """Write a BOP 6D results CSV (atomic). Every image must carry one time (s) for all its
    estimates (-1 when unknown), as the toolkit requires."""
    lines = [POSE_CSV_HEADER]
    times: dict[tuple[int, int], float] = {}
    for e in estimates:
        key = (int(e.scene_id), int(e.im_id))
        t = float(e.time)
        if key in times and abs(times[key] - t) > time_tol:
            raise ValueError(
                f"scene {key[0]} image {key[1]}: estimates carry different times "
                f"({times[key]} and {t}); BOP wants one time per image (the whole image's "
                "processing time) on every row of that image"
            )
        times.setdefault(key, t)
        R = validate_rotation(e.R, f"estimate scene {key[0]} im {key[1]} obj {e.obj_id}")
        lines.append(
            ",".join(
                [
                    str(key[0]),
                    str(key[1]),
                    str(int(e.obj_id)),
                    repr(float(e.score)),
                    " ".join(repr(float(v)) for v in R.reshape(-1)),
                    " ".join(repr(float(v)) for v in np.reshape(e.t, 3)),
                    repr(times[key]),
                ]
            )
        )
    atomic_write_bytes(pathlib.Path(path), ("\n".join(lines) + "\n").encode())


def read_pose_results(path, rotation_atol: float = 1e-3) -> list[PoseEstimate]:
    """Read a BOP 6D results CSV (`inout.load_bop_results`, version bop19), validating it."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"results file {path} does not exist")
    out = []
    with open(path) as f:
        for line_no, line in enumerate(f, start=1):
            if line_no == 1 and POSE_CSV_HEADER in line:
                continue
            if not line.strip():
                continue
            elems = line.rstrip("\r\n").split(",")
            where = f"{path}:{line_no}"
            if len(elems) != 7:
                raise ValueError(
                    f"{where}: expected 7 comma-separated columns ({POSE_CSV_HEADER}), got "
                    f"{len(elems)}; R and t must be space-separated inside their column"
                )
            try:
                sid, iid, oid = int(elems[0]), int(elems[1]), int(elems[2])
                score = float(elems[3])
                R = np.array([float(v) for v in elems[4].split()], np.float64)
                t = np.array([float(v) for v in elems[5].split()], np.float64)
                tm = float(elems[6])
            except ValueError as e:
                raise ValueError(f"{where}: could not parse the row ({e})") from None
            if t.shape != (3,):
                raise ValueError(f"{where}: t must have 3 values (mm), got {t.size}")
            R = validate_rotation(R, where, rotation_atol)
            out.append(PoseEstimate(sid, iid, oid, score, R, t, tm))
    return out


def check_consistent_times(estimates: Iterable[PoseEstimate], tol: float = 1e-3) -> None:
    """Raise if one image's estimates carry different times (`inout.check_consistent_timings`)."""
    times: dict[tuple[int, int], float] = {}
    for e in estimates:
        key = (e.scene_id, e.im_id)
        if key in times and abs(times[key] - e.time) > tol:
            raise ValueError(
                f"the running time for scene {key[0]} and image {key[1]} is not the same for all "
                f"estimates ({times[key]} and {e.time}); write one time per image"
            )
        times.setdefault(key, e.time)


def top_estimates_per_image(
    estimates: Sequence[PoseEstimate], max_per_image: int | None
) -> list[PoseEstimate]:
    """Keep the ``max_per_image`` highest-scoring estimates of each image, grouped by image in
    order of first appearance (stable sort), exactly as `inout.load_bop_results` does."""
    if max_per_image is None:
        return list(estimates)
    groups: dict[tuple[int, int], list[PoseEstimate]] = {}
    for e in estimates:
        groups.setdefault((e.scene_id, e.im_id), []).append(e)
    out = []
    for g in groups.values():
        out.extend(sorted(g, key=lambda e: e.score, reverse=True)[:max_per_image])
    return out


# ----------------------------------------------------------------------------- 2D results
def mask_to_rle(mask: np.ndarray) -> dict:
    """COCO RLE of a binary mask [H, W]: {"counts": compressed str, "size": [H, W]}."""
    from pycocotools import mask as mask_utils

    m = np.asfortranarray(np.asarray(mask, dtype=np.uint8))
    rle = mask_utils.encode(m)
    return {"counts": rle["counts"].decode("ascii"), "size": [int(m.shape[0]), int(m.shape[1])]}


def rle_to_mask(rle: Mapping) -> np.ndarray:
    """Decode a COCO RLE (compressed string or uncompressed list counts) to [H, W] bool."""
    from pycocotools import mask as mask_utils

    h, w = (int(v) for v in rle["size"])
    counts = rle["counts"]
    if isinstance(counts, list):
        obj = mask_utils.frPyObjects({"counts": counts, "size": [h, w]}, h, w)
    else:
        obj = {
            "counts": counts.encode("ascii") if isinstance(counts, str) else counts,
            "size": [h, w],
        }
    return mask_utils.decode(obj).astype(bool)


def write_detection_results(path, detections: Iterable[Detection2D]) -> None:
    """Write a BOP 2D results JSON (list of COCO results with scene_id, atomic)."""
    rows = []
    for d in detections:
        row = {
            "scene_id": int(d.scene_id),
            "image_id": int(d.im_id),
            "category_id": int(d.obj_id),
            "score": float(d.score),
            "time": float(d.time),
        }
        if d.bbox is not None:
            x, y, w, h = (float(v) for v in d.bbox)
            if w < 0 or h < 0:
                raise ValueError(
                    f"detection scene {d.scene_id} im {d.im_id}: bbox {d.bbox} "
                    "has negative size; BOP boxes are [x, y, width, height]"
                )
            row["bbox"] = [x, y, w, h]
        if d.segmentation is not None:
            seg = dict(d.segmentation)
            if isinstance(seg.get("counts"), bytes):
                seg["counts"] = seg["counts"].decode("ascii")
            row["segmentation"] = seg
        rows.append(row)
    write_json_atomic(path, rows)


def read_detection_results(path) -> list[Detection2D]:
    """Read a BOP 2D results JSON (`inout.check_coco_results` keys), validating it."""
    path = pathlib.Path(path)
    raw = _load_json(path)
    if not isinstance(raw, list):
        raise ValueError(f"{path}: a 2D results file must be a JSON list of detections")
    out = []
    for i, r in enumerate(raw):
        where = f"{path} entry {i}"
        for key in ("scene_id", "image_id", "category_id", "score"):
            if key not in r:
                raise ValueError(
                    f"{where}: missing {key!r} (BOP 2D results need scene_id, "
                    "image_id, category_id, score, bbox and/or segmentation)"
                )
        for key in ("scene_id", "image_id", "category_id"):
            if not isinstance(r[key], int) or isinstance(r[key], bool):
                raise ValueError(f"{where}: {key} must be an integer, got {r[key]!r}")
        bbox = r.get("bbox") or None
        if bbox is not None and len(bbox) != 4:
            raise ValueError(f"{where}: bbox must be [x, y, w, h], got {bbox}")
        seg = r.get("segmentation") or None
        if seg is not None and (
            not isinstance(seg, Mapping) or "counts" not in seg or "size" not in seg
        ):
            raise ValueError(
                f"{where}: segmentation must be a COCO RLE dict with counts and "
                "size (polygons are not accepted by BOP)"
            )
        out.append(
            Detection2D(
                r["scene_id"],
                r["image_id"],
                r["category_id"],
                float(r["score"]),
                None if bbox is None else tuple(float(v) for v in bbox),
                seg,
                float(r.get("time", -1.0)),
            )
        )
    return out


# ----------------------------------------------------------------------------- scene writer
def _bbox_xywh(mask: np.ndarray, offset=(0, 0)) -> list[int]:
    """`misc.calc_2d_bbox` of the nonzero pixels: [x_min, y_min, x_max - x_min, y_max - y_min]."""
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return [-1, -1, -1, -1]
    x0, y0 = int(xs.min()) - offset[0], int(ys.min()) - offset[1]
    return [x0, y0, int(xs.max()) - offset[0] - x0, int(ys.max()) - offset[1] - y0]


def _write_image(path: pathlib.Path, im: np.ndarray, jpg_quality: int = 95) -> None:
    import cv2

    im = np.asarray(im)
    if im.ndim == 3 and im.shape[2] == 3:
        im = im[..., ::-1]
    ext = path.suffix.lower()
    params = (
        [cv2.IMWRITE_JPEG_QUALITY, int(jpg_quality)]
        if ext in (".jpg", ".jpeg")
        else [cv2.IMWRITE_PNG_COMPRESSION, 3]
    )
    ok, buf = cv2.imencode(ext, np.ascontiguousarray(im), params)
    if not ok:
        raise ValueError(f"could not encode image {path}")
    atomic_write_bytes(path, buf.tobytes())


class BopSceneWriter:
    """Writes one BOP scene folder image by image (used by the data generator).

    `add_image` writes the image, depth and masks at once and records the scene JSON entries;
    `flush` (also called by `close` and on leaving a ``with`` block) rewrites
    ``scene_camera.json``, ``scene_gt.json`` and ``scene_gt_info.json`` atomically. Opening an
    existing scene folder continues it (its JSON entries are kept), so generation can resume.
    """

    def __init__(
        self,
        scene_dir,
        *,
        image_ext: str = "png",
        sensor: str | None = None,
        image_dir: str = "rgb",
        jpg_quality: int = 95,
    ):
        self.path = pathlib.Path(scene_dir)
        self.image_ext = "." + image_ext.lower().lstrip(".")
        if self.image_ext not in (".png", ".jpg", ".jpeg"):
            raise ValueError(f"image_ext must be png or jpg, got {image_ext!r}")
        self.sensor = sensor
        self.image_dir = image_dir
        self.jpg_quality = jpg_quality
        self.path.mkdir(parents=True, exist_ok=True)
        sfx = _suffix(sensor)
        self._files = {
            k: self.path / f"{k}{sfx}.json" for k in ("scene_camera", "scene_gt", "scene_gt_info")
        }
        self._data: dict[str, dict[int, object]] = {}
        for k, p in self._files.items():
            self._data[k] = _int_keys(_load_json(p), p) if p.is_file() else {}

    def _dir(self, stem: str) -> pathlib.Path:
        d = self.path / f"{stem}{_suffix(self.sensor)}"
        d.mkdir(parents=True, exist_ok=True)
        return d

    def add_image(
        self,
        im_id: int,
        camera: Camera,
        image: np.ndarray | None,
        instances: Sequence[GtInstance],
        masks: np.ndarray,
        masks_visib: np.ndarray,
        depth_mm: np.ndarray | None = None,
        masks_full: np.ndarray | None = None,
        full_offset: tuple[int, int] = (0, 0),
    ) -> list[GtInfo]:
        """Write one image and its annotations; returns the computed GtInfo per instance.

        image [H, W, 3] uint8 RGB (or [H, W] gray, stored under ``gray``), depth_mm [H, W] in
        mm (stored as uint16 png ``round(depth / camera.depth_scale)``), masks and masks_visib
        [O, H, W] bool (amodal silhouette inside the image, visible part). ``masks_full``
        [O, H2, W2] is the amodal silhouette on a larger canvas where image pixel (0, 0) sits at
        ``full_offset`` (x, y); BOP counts ``px_count_all`` and ``bbox_obj`` on it so that
        truncated objects keep their full size. Without it the in-image masks are used.
        """
        im_id = int(im_id)
        masks = np.asarray(masks, bool)
        masks_visib = np.asarray(masks_visib, bool)
        n = len(instances)
        if masks.shape[0] != n or masks_visib.shape != masks.shape:
            raise ValueError(
                f"image {im_id}: {n} instances but masks {masks.shape} and "
                f"masks_visib {masks_visib.shape}; pass one [H, W] mask per instance"
            )
        if np.any(masks_visib & ~masks):
            raise ValueError(f"image {im_id}: a visible mask has pixels outside its amodal mask")
        if masks_full is not None:
            masks_full = np.asarray(masks_full, bool)
            if masks_full.shape[0] != n:
                raise ValueError(f"image {im_id}: masks_full needs one mask per instance")
        stem = f"{im_id:06d}"
        if image is not None:
            image = np.asarray(image)
            if image.dtype != np.uint8:
                raise ValueError(f"image {im_id}: image must be uint8, got {image.dtype}")
            folder = self._dir(self.image_dir if image.ndim == 3 else "gray")
            _write_image(folder / f"{stem}{self.image_ext}", image, self.jpg_quality)
        valid = None
        if depth_mm is not None:
            if camera.depth_scale is None or camera.depth_scale <= 0:
                raise ValueError(f"image {im_id}: writing depth needs camera.depth_scale > 0")
            d = np.round(np.asarray(depth_mm, np.float64) / camera.depth_scale)
            if d.max(initial=0) > 65535 or d.min(initial=0) < 0:
                raise ValueError(
                    f"image {im_id}: depth {float(np.max(depth_mm))} mm overflows uint16 at "
                    f"depth_scale {camera.depth_scale}; raise depth_scale (e.g. 1.0 for 65 m)"
                )
            _write_image(self._dir("depth") / f"{stem}.png", d.astype(np.uint16))
            valid = d > 0
        infos = []
        for i in range(n):
            _write_image(self._dir("mask") / f"{stem}_{i:06d}.png", masks[i].astype(np.uint8) * 255)
            _write_image(
                self._dir("mask_visib") / f"{stem}_{i:06d}.png",
                masks_visib[i].astype(np.uint8) * 255,
            )
            full = masks[i] if masks_full is None else masks_full[i]
            off = (0, 0) if masks_full is None else full_offset
            px_all = int(full.sum())
            px_visib = int(masks_visib[i].sum())
            px_valid = int(masks[i].sum() if valid is None else (masks[i] & valid).sum())
            infos.append(
                GtInfo(
                    tuple(_bbox_xywh(full, off)) if px_visib > 0 else (-1, -1, -1, -1),
                    tuple(_bbox_xywh(masks_visib[i])),
                    px_all,
                    px_valid,
                    px_visib,
                    px_visib / float(px_all) if px_all > 0 else 0.0,
                )
            )
        self._data["scene_camera"][im_id] = camera.to_json()
        self._data["scene_gt"][im_id] = [g.to_json() for g in instances]
        self._data["scene_gt_info"][im_id] = [g.to_json() for g in infos]
        return infos

    def flush(self) -> None:
        for k, p in self._files.items():
            write_json_atomic(p, self._data[k])

    def close(self) -> None:
        self.flush()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def write_camera_info(path, K, width: int, height: int, depth_scale: float | None = None) -> None:
    """Write a dataset-level ``camera.json`` (width, height, fx, fy, cx, cy, depth_scale)."""
    K = validate_intrinsics(K)
    out = {
        "cx": float(K[0, 2]),
        "cy": float(K[1, 2]),
        "fx": float(K[0, 0]),
        "fy": float(K[1, 1]),
        "height": int(height),
        "width": int(width),
    }
    if depth_scale is not None:
        out["depth_scale"] = float(depth_scale)
    atomic_write_bytes(pathlib.Path(path), json.dumps(out, indent=2, sort_keys=True).encode())


__all__ += ["write_camera_info", "POSE_CSV_HEADER"]
