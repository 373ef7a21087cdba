"""Evaluate BOP result files against a BOP dataset folder (6D CSV or 2D JSON).

Reads only what the evaluation needs: the target list, the scene JSON of the target scenes,
the meshes of the evaluated objects, and (for 2D) the masks of the target images. Protocol
details are in `threept_jax.eval.bop6d` and `threept_jax.eval.coco`.

Defaults, as in the toolkit: the image set is ``test_targets_bop24.json`` when present (else
``test_targets_bop19.json``, else every annotated image of the split); AR uses
``test_targets_bop19.json`` when present; models come from ``models_eval`` when present;
XYZ-IBD (a dataset folder named ``xyzibd``) keeps 200 estimates per image, others 100.
The image width that normalises MSPD comes from ``camera[_SENSOR].json`` or, without it, from
the header of the scene's first target image.
"""

from __future__ import annotations

import math
import pathlib
import warnings
from collections.abc import Sequence

import numpy as np

from threept_jax.data.bop import (
    BopDataset,
    BopSplit,
    Detection2D,
    PoseEstimate,
    Target,
    check_consistent_times,
    load_targets,
    read_detection_results,
    read_pose_results,
)
from threept_jax.eval.bop6d import ImageGt, PoseScores, evaluate_poses
from threept_jax.eval.coco import coco_gt_annotation, evaluate_coco
from threept_jax.eval.pose_error import PreparedModel, prepare_model

__all__ = [
    "resolve_targets",
    "load_image_gts",
    "evaluate_pose_results",
    "evaluate_detection_results",
    "evaluate_results_file",
    "default_max_estimates",
]


def check_positive_int(value, name: str, minimum: int = 1) -> int:
    """``value`` as int when it is an integer >= ``minimum``, else ValueError naming ``name``
    (the keyword argument, or the CLI flag when the CLI checks)."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def check_positive_float(value, name: str) -> float:
    """``value`` as float when it is a finite number > 0, else ValueError naming ``name``."""
    if (
        isinstance(value, bool)
        or not isinstance(value, (int, float, np.integer, np.floating))
        or not 0 < value < math.inf
    ):
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    return float(value)


def default_max_estimates(dataset: BopDataset) -> int:
    """100 estimates per image, 200 for XYZ-IBD (`scripts/eval_bop24_pose.py`)."""
    return 200 if dataset.name.lower().startswith("xyzibd") else 100


def resolve_targets(
    dataset: BopDataset, split: BopSplit, targets_path=None
) -> tuple[list[Target], list[Target] | None]:
    """(image targets for AP, bop19 localisation targets for AR or None)."""
    if targets_path is not None:
        targets = load_targets(targets_path)
        loc = (
            targets
            if all(t.obj_id is not None and t.inst_count is not None for t in targets) and targets
            else None
        )
        return targets, loc
    t24, t19 = dataset.targets("bop24"), dataset.targets("bop19")
    if t24 is not None:
        return t24, t19
    if t19 is not None:
        return t19, t19
    targets = []
    for sid in split.scene_ids:
        scene = split.scene(sid)
        if scene.has_gt:
            targets += [Target(sid, i) for i in scene.gt]
    if not targets:
        raise FileNotFoundError(
            f"{split.path} has no annotated scenes and {dataset.root} no "
            "test_targets_bop24.json / test_targets_bop19.json"
        )
    return targets, None


def _scene_width(
    dataset: BopDataset,
    split: BopSplit,
    scene_id: int,
    im_id: int,
    sensor: str | None,
    image_width: int | None,
) -> int:
    if image_width is not None:
        return check_positive_int(image_width, "image_width")
    cam = dataset.camera_info(sensor)
    if cam is not None and "width" in cam:
        try:
            return check_positive_int(cam["width"], "width")
        except ValueError as e:
            raise ValueError(f"{dataset.root}/camera{'_' + sensor if sensor else ''}.json: {e}; "
                             "fix the file or pass image_width (--image-width)") from None
    try:
        return split.scene(scene_id).image_size(im_id)[0]
    except FileNotFoundError:
        raise FileNotFoundError(
            f"cannot tell the image width of scene {scene_id} (MSPD is normalised by it): no "
            f"camera.json with 'width' in {dataset.root} and no image in the scene; pass "
            "image_width (--image-width)"
        ) from None


def load_image_gts(
    dataset: BopDataset,
    split: BopSplit,
    keys: Sequence[tuple[int, int]],
    sensor: str | None = None,
    image_width: int | None = None,
) -> dict[tuple[int, int], ImageGt]:
    """ImageGt for each (scene_id, im_id) in ``keys``."""
    out = {}
    widths: dict[int, int] = {}
    for sid, iid in keys:
        scene = split.scene(sid)
        if iid not in scene.gt:
            raise ValueError(f"target scene {sid} image {iid} is not in {scene._file('scene_gt')}")
        if sid not in widths:
            widths[sid] = _scene_width(dataset, split, sid, iid, sensor, image_width)
        infos = scene.gt_info.get(iid)
        if infos is None:
            raise ValueError(
                f"target scene {sid} image {iid} has no scene_gt_info entry "
                "(visib_fract is needed to ignore GT below 10% visibility)"
            )
        # Rotations as stored (possibly rounded), as the toolkit's error functions use them.
        out[(sid, iid)] = ImageGt(scene.cameras[iid].K, widths[sid], scene.gt_as_stored[iid], infos)
    return out


def evaluate_pose_results(
    dataset_dir,
    estimates: Sequence[PoseEstimate],
    *,
    split: str = "test",
    targets_path=None,
    models_subdir: str | None = None,
    sensor: str | None = None,
    image_width: int | None = None,
    max_estimates_per_image: int | None = None,
    compute_ar: bool = True,
) -> PoseScores:
    """6D AP (BOP 2024/25) and AR (BOP 2019, MSSD/MSPD) of ``estimates`` on a dataset.

    ``image_width`` (px, > 0) overrides the width that normalises MSPD;
    ``max_estimates_per_image`` (>= 1) the per-image cap. Warns when the translations look
    like metres (median |t| below the smallest model diameter)."""
    if image_width is not None:
        check_positive_int(image_width, "image_width")
    if max_estimates_per_image is not None:
        check_positive_int(max_estimates_per_image, "max_estimates_per_image")
    _check_finite_estimates(estimates)
    check_consistent_times(estimates)
    dataset = BopDataset(dataset_dir)
    sp = dataset.split(split, sensor)
    targets, loc = resolve_targets(dataset, sp, targets_path)
    keys = list(dict.fromkeys((t.scene_id, t.im_id) for t in targets))
    if loc is not None:
        keys += [k for k in dict.fromkeys((t.scene_id, t.im_id) for t in loc) if k not in keys]
    images = load_image_gts(dataset, sp, keys, sensor, image_width)
    gt_objs = {g.obj_id for im in images.values() for g in im.gts}
    needed = gt_objs & {e.obj_id for e in estimates}
    infos = dataset.models(models_subdir)
    _warn_if_metres(estimates, infos)
    missing = sorted(gt_objs - set(infos))
    if missing:
        raise ValueError(
            f"objects {missing} are in the GT but not in "
            f"{dataset.models_dir(models_subdir)}/models_info.json"
        )
    models: dict[int, PreparedModel] = {o: prepare_model(infos[o]) for o in sorted(needed)}
    for o in gt_objs - needed:  # no estimates: only the diameter is ever read
        models[o] = PreparedModel(
            o,
            np.zeros((1, 3)),
            np.zeros((1, 3)),
            np.zeros((1, 3)),
            np.eye(3)[None],
            np.zeros((1, 3)),
            infos[o].diameter,
        )
    if max_estimates_per_image is None:
        max_estimates_per_image = default_max_estimates(dataset)
    return evaluate_poses(
        estimates,
        images,
        models,
        targets,
        loc,
        max_estimates_per_image=max_estimates_per_image,
        compute_ar=compute_ar,
    )


def _check_finite_estimates(estimates: Sequence[PoseEstimate]) -> None:
    if not estimates:
        return
    vals = np.array([(e.score, e.time, *e.R.ravel(), *e.t.ravel()) for e in estimates])
    bad = np.flatnonzero(~np.isfinite(vals).all(1))
    if len(bad):
        e = estimates[int(bad[0])]
        raise ValueError(
            f"estimate {int(bad[0])} (scene {e.scene_id}, image {e.im_id}, object {e.obj_id}) "
            "has a non-finite score, time, R or t"
        )


def _warn_if_metres(estimates: Sequence[PoseEstimate], infos) -> None:
    """Warn when the median |t| is below the smallest model diameter: translations in metres
    would all score zero, and nothing else would say why."""
    if not estimates or not infos:
        return
    med = float(np.median([np.linalg.norm(e.t) for e in estimates]))
    d_min = min(m.diameter for m in infos.values())
    if med < d_min:
        warnings.warn(
            f"the median |t| of the estimates is {med:.4g} mm, below the smallest model "
            f"diameter ({d_min:.4g} mm): the translations look like metres; BOP results "
            "are in millimetres (multiply t by 1000)",
            stacklevel=3,
        )


def _coco_gt_for_image(
    dataset: BopDataset,
    split: BopSplit,
    sid: int,
    iid: int,
    need_masks: bool,
    sensor: str | None,
    coco_cache: dict,
):
    scene = split.scene(sid)
    if sid not in coco_cache:
        coco_cache[sid] = scene.scene_gt_coco()
    coco = coco_cache[sid]
    if coco is not None:
        anns = []
        for a in coco.get("annotations", []):
            if a["image_id"] == iid:
                a = dict(a)
                a["bop_ignore"] = int(a.pop("ignore", 0))
                anns.append(a)
        size = next(
            ((im["width"], im["height"]) for im in coco.get("images", []) if im["id"] == iid), None
        )
        if size is None:
            size = scene.image_size(iid)
        return anns, size
    gts, infos = scene.gt[iid], scene.gt_info[iid]
    anns = []
    if scene.has_masks(visib=True):
        size = None
        for j, info in enumerate(infos):
            mv = scene.mask_visib(iid, j)
            mf = scene.mask(iid, j) if scene.has_masks(visib=False) else None
            size = (mv.shape[1], mv.shape[0])
            a = coco_gt_annotation(
                mv, mf, info.visib_fract, None if mf is not None else _clip_box(info.bbox_obj, size)
            )
            if a is not None:
                a["category_id"] = gts[j].obj_id
                anns.append(a)
        if size is None:
            size = _image_size_or_camera(dataset, scene, iid, sensor)
        return anns, size
    if need_masks:
        raise FileNotFoundError(
            f"scene {sid} has no mask_visib/ folder and no "
            "scene_gt_coco.json; segmentation AP needs GT masks"
        )
    size = _image_size_or_camera(dataset, scene, iid, sensor)
    for j, info in enumerate(infos):
        if info.px_count_visib < 1:
            continue
        anns.append(
            {
                "category_id": gts[j].obj_id,
                "iscrowd": 0,
                "area": int(info.px_count_visib),
                "bbox": _clip_box(info.bbox_obj, size),
                "bop_ignore": int(info.visib_fract < 0.1),
            }
        )
    return anns, size


def _clip_box(b, size):
    """scene_gt_info ``bbox_obj`` (x, y, x_max - x, y_max - y, may leave the image) -> the COCO
    box of its in-image pixels, ``[x, y, w + 1, h + 1]`` as `bbox_from_binary_mask` gives."""
    x, y, w, h = b
    x0, y0 = max(x, 0), max(y, 0)
    x1, y1 = min(x + w, size[0] - 1), min(y + h, size[1] - 1)
    return [float(x0), float(y0), float(max(0, x1 - x0 + 1)), float(max(0, y1 - y0 + 1))]


def _image_size_or_camera(dataset, scene, iid, sensor):
    cam = dataset.camera_info(sensor)
    if cam is not None and "width" in cam and "height" in cam:
        return int(cam["width"]), int(cam["height"])
    return scene.image_size(iid)


def evaluate_detection_results(
    dataset_dir,
    detections: Sequence[Detection2D],
    *,
    split: str = "test",
    targets_path=None,
    models_subdir: str | None = None,
    sensor: str | None = None,
    any_part: bool = False,
) -> dict[str, dict[str, float]]:
    """2D AP (bbox and/or segm, whichever the detections carry) on a dataset;
    ``any_part``: the diagnostic of :func:`threept_jax.eval.coco.evaluate_coco`."""
    dataset = BopDataset(dataset_dir)
    sp = dataset.split(split, sensor)
    targets, _ = resolve_targets(dataset, sp, targets_path)
    order = list(dict.fromkeys((t.scene_id, t.im_id) for t in targets))
    need_masks = any(d.segmentation is not None for d in detections)
    gt, sizes, cache = {}, {}, {}
    for sid, iid in order:
        gt[(sid, iid)], sizes[(sid, iid)] = _coco_gt_for_image(
            dataset, sp, sid, iid, need_masks, sensor, cache
        )
    cats = set(dataset.models(models_subdir))
    for sid, iid in order:
        cats |= {g.obj_id for g in sp.scene(sid).gt_as_stored[iid]}
    return evaluate_coco(detections, gt, sizes, order, sorted(cats), any_part=any_part)


def evaluate_results_file(dataset_dir, results_path, *, rotation_atol: float = 1e-3, **kwargs):
    """Evaluate a ``.csv`` (6D, returns PoseScores) or ``.json`` (2D, returns a dict).

    ``rotation_atol`` (> 0) is the largest |R R^T - I| entry accepted in a 6D results file;
    other keywords go to `evaluate_pose_results` / `evaluate_detection_results`."""
    check_positive_float(rotation_atol, "rotation_atol")
    p = pathlib.Path(results_path)
    if p.suffix.lower() == ".csv":
        return evaluate_pose_results(dataset_dir, read_pose_results(p, rotation_atol), **kwargs)
    if p.suffix.lower() == ".json":
        kwargs.pop("image_width", None)
        kwargs.pop("max_estimates_per_image", None)
        kwargs.pop("compute_ar", None)
        return evaluate_detection_results(dataset_dir, read_detection_results(p), **kwargs)
    raise ValueError(f"{p}: results must be a 6D .csv or a 2D .json file")
