"""Small synthetic BOP datasets with chosen poses, for tests, benchmarks and demos.

Instances are given as (obj_id, T_cam_obj, visible fraction). Masks are not rendered: the
amodal mask of an instance is the axis-aligned rectangle spanned by its projected model
vertices (clipped to the image) and the visible mask is its top rows, so many rows that the
visible fraction is as close as possible to the requested one. This is enough to exercise the
readers, writers and evaluators, whose GT boxes and visibilities come from those masks.
"""

from __future__ import annotations

import pathlib
import shutil
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from threept_jax.data.bop import (
    BopSceneWriter,
    Camera,
    GtInfo,
    GtInstance,
    ObjectModel,
    Target,
    write_camera_info,
    write_json_atomic,
    write_models_info,
    write_targets,
)

__all__ = ["SyntheticInstance", "instance_masks", "write_synthetic_dataset"]


@dataclass(frozen=True, eq=False)
class SyntheticInstance:
    """An instance to place: object id, pose T_cam_obj [4, 4] (mm), visible fraction."""

    obj_id: int
    T_cam_obj: np.ndarray
    visib: float = 1.0


def _rectangle(
    vertices: np.ndarray,
    T_cam_obj: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    visib: float,
) -> tuple[int, int, int, int, int]:
    """Pixel rectangle (x0, y0, x1, y1, inclusive, clipped) of the projected vertices and the
    number of its top rows that are visible."""
    X = vertices @ T_cam_obj[:3, :3].T + T_cam_obj[:3, 3]
    uv = X @ K.T
    uv = uv[:, :2] / uv[:, 2:3]
    x0, y0 = np.floor(uv.min(0) + 0.5).astype(int)
    x1, y1 = np.floor(uv.max(0) + 0.5).astype(int)
    x0, x1 = (int(v) for v in np.clip([x0, x1], 0, width - 1))
    y0, y1 = (int(v) for v in np.clip([y0, y1], 0, height - 1))
    return x0, y0, x1, y1, int(round(visib * (y1 - y0 + 1)))


def instance_masks(
    vertices: np.ndarray,
    T_cam_obj: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    visib: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Amodal and visible masks [H, W] bool of a rectangle-shaped stand-in silhouette."""
    x0, y0, x1, y1, n_vis = _rectangle(vertices, T_cam_obj, K, width, height, visib)
    full = np.zeros((height, width), bool)
    full[y0 : y1 + 1, x0 : x1 + 1] = True
    vis = np.zeros_like(full)
    vis[y0 : y0 + n_vis, x0 : x1 + 1] = True
    return full, vis


def _rect_info(x0, y0, x1, y1, n_vis) -> GtInfo:
    """GtInfo of `instance_masks` without building the masks (same numbers)."""
    w = x1 - x0 + 1
    n_all, n_v = w * (y1 - y0 + 1), w * n_vis
    return GtInfo(
        (x0, y0, x1 - x0, y1 - y0) if n_v else (-1,) * 4,
        (x0, y0, x1 - x0, n_vis - 1) if n_v else (-1,) * 4,
        n_all,
        n_all,
        n_v,
        n_v / n_all,
    )


def write_synthetic_dataset(
    root,
    models: Mapping[int, ObjectModel],
    scenes: Mapping[int, Mapping[int, Sequence[SyntheticInstance]]],
    K: np.ndarray,
    width: int = 640,
    height: int = 480,
    *,
    split: str = "test",
    write_images: bool = True,
    targets: Sequence[Target] | None = None,
    bop19_targets: bool = True,
) -> pathlib.Path:
    """Write a BOP dataset: ``models/`` (PLYs copied from the given models), ``camera.json``,
    ``{split}/{scene:06d}/`` scene files and ``test_targets_bop24.json`` (+ bop19 targets of
    the instances with visib_fract >= 0.1). With ``write_images`` False only the JSON files are
    written (masks are still used to compute scene_gt_info)."""
    root = pathlib.Path(root)
    mdir = root / "models"
    mdir.mkdir(parents=True, exist_ok=True)
    for m in models.values():
        if m.path is not None:
            dst = mdir / f"obj_{m.obj_id:06d}.ply"
            if not dst.exists():
                shutil.copyfile(m.path, dst)
    write_models_info(mdir / "models_info.json", models)
    write_camera_info(root / "camera.json", K, width, height, depth_scale=1.0)
    verts = {o: _hull(m.vertices()) for o, m in models.items()}
    all_targets, t19 = [], []
    for scene_id, ims in scenes.items():
        sdir = root / split / f"{int(scene_id):06d}"
        cams, gts, infos = {}, {}, {}
        writer = BopSceneWriter(sdir) if write_images else None
        for im_id, insts in ims.items():
            cam = Camera(K, 1.0)
            rects = [
                _rectangle(verts[i.obj_id], i.T_cam_obj, cam.K, width, height, i.visib)
                for i in insts
            ]
            im_infos = [_rect_info(*r) for r in rects]
            gt = [GtInstance(i.obj_id, i.T_cam_obj) for i in insts]
            if writer is not None:
                masks = [
                    instance_masks(verts[i.obj_id], i.T_cam_obj, cam.K, width, height, i.visib)
                    for i in insts
                ]
                full = np.array([m[0] for m in masks]).reshape(-1, height, width)
                vis = np.array([m[1] for m in masks]).reshape(-1, height, width)
                rgb = np.full((height, width, 3), 90, np.uint8)
                writer.add_image(im_id, cam, rgb, gt, full, vis)
            else:
                cams[im_id] = cam.to_json()
                gts[im_id] = [g.to_json() for g in gt]
                infos[im_id] = [info.to_json() for info in im_infos]
            all_targets.append(Target(int(scene_id), int(im_id)))
            counts: dict[int, int] = {}
            for i, info in zip(insts, im_infos):
                if info.visib_fract >= 0.1:
                    counts[i.obj_id] = counts.get(i.obj_id, 0) + 1
            t19 += [Target(int(scene_id), int(im_id), o, c) for o, c in counts.items()]
        if writer is not None:
            writer.close()
        else:
            write_json_atomic(sdir / "scene_camera.json", cams)
            write_json_atomic(sdir / "scene_gt.json", gts)
            write_json_atomic(sdir / "scene_gt_info.json", infos)
    write_targets(root / "test_targets_bop24.json", targets if targets is not None else all_targets)
    if bop19_targets:
        write_targets(root / "test_targets_bop19.json", t19)
    return root


def _hull(vertices: np.ndarray) -> np.ndarray:
    """Convex-hull vertices: the projected extremes of a point set lie on them."""
    from scipy.spatial import ConvexHull, QhullError

    try:
        return vertices[ConvexHull(vertices).vertices]
    except (QhullError, ValueError):
        return vertices
