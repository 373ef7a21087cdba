"""Writing BOP scenes (``BopSceneWriter``) and ``camera.json``."""

from __future__ import annotations

import json
import pathlib
from collections.abc import Sequence

import numpy as np

from threept_jax.data.bop.json_format import _int_keys, _load_json, write_json_atomic
from threept_jax.data.bop.reader import _suffix
from threept_jax.data.bop.types import Camera, GtInfo, GtInstance
from threept_jax.data.files import atomic_write_bytes
from threept_jax.geometry.validate import validate_intrinsics


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
