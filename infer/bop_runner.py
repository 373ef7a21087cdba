"""``python -m infer bop``: a BOP split -> BOP 6D results CSV and 2D results JSON (RLE masks),
overlays, and optionally the BOP evaluator's scores."""

from __future__ import annotations

import json
import time

import cv2
import numpy as np
from tqdm import tqdm

from infer.cli import detector_options, load_models

#: Images without detections named one by one on the console; the rest are counted.
MAX_EMPTY_LINES = 10


def select_images_and_objects(args, ds) -> tuple[list[tuple[int, int]], dict]:
    """The (scene_id, im_id) pairs and {obj_id: ObjectModel} a run covers, checked before any
    slow work.

    Objects: ``--obj-ids`` if given, else the objects the targets file names for the selected
    images (BOP19-style targets), else every object of ``models_info.json`` (BOP24-style
    targets and ``--targets all`` name images only). Objects outside that set are never
    onboarded, so ``models_info.json`` may list objects whose meshes are absent; a selected
    object without its mesh is an error naming it and the expected file.
    """
    models_dir = ds.models_dir(args.models_subdir)
    models = ds.models(args.models_subdir)
    if args.obj_ids:
        unknown = sorted(set(args.obj_ids) - set(models))
        if unknown:
            raise ValueError(f"--obj-ids {unknown} are not in {models_dir / 'models_info.json'} "
                             f"(it lists {sorted(models)})")
    split = ds.split(args.split)
    targets = None
    if args.targets == "all":
        images = [(s, i) for s in split.scene_ids for i in split.scene(s).image_ids]
    else:
        targets = ds.targets(args.targets)
        if targets is None:
            raise FileNotFoundError(
                f"{args.dataset_dir}/test_targets_{args.targets}.json not found; "
                "pass --targets all to run on every image of the split")
        if args.obj_ids:
            targets = [t for t in targets if t.obj_id is None or t.obj_id in args.obj_ids]
        if args.scene_ids:
            targets = [t for t in targets if t.scene_id in args.scene_ids]
        images = sorted({(t.scene_id, t.im_id) for t in targets})
    if args.scene_ids:
        images = [x for x in images if x[0] in args.scene_ids]
    images = images[: args.max_images]
    if not images:
        raise ValueError("no images selected (check --scene-ids, --obj-ids and --targets)")
    if args.obj_ids:
        wanted = set(args.obj_ids)
    elif targets is not None and any(t.obj_id is not None for t in targets):
        chosen = set(images)
        wanted = {t.obj_id for t in targets
                  if t.obj_id is not None and (t.scene_id, t.im_id) in chosen}
    else:
        wanted = set(models)
    unknown = sorted(wanted - set(models))
    if unknown:
        raise ValueError(f"test_targets_{args.targets}.json names objects {unknown} that "
                         f"{models_dir / 'models_info.json'} does not list")
    missing = [k for k in sorted(wanted) if models[k].path is None]
    if missing:
        paths = ", ".join(f"{k}: {models_dir / f'obj_{k:06d}.ply'}" for k in missing)
        raise FileNotFoundError(
            f"no mesh for target objects {missing} ({paths}); add the meshes, or pass --obj-ids "
            "with the objects to query")
    return images, {k: models[k] for k in sorted(wanted)}


def run_bop(args) -> dict:
    from infer.masks import PoseRenderer, detection_masks
    from infer.visualize import draw_detections, empty_caption
    from threept_jax.data import bop

    ds = bop.BopDataset(args.dataset_dir)
    images, models = select_images_and_objects(args, ds)
    split = ds.split(args.split)

    nets = load_models(args)
    objects = nets.onboard({k: m.path for k, m in models.items()})
    detector = nets.scene_detector(objects, **detector_options(args))
    renderer = PoseRenderer(objects)
    args.out.mkdir(parents=True, exist_ok=True)
    poses, dets2d, empty = [], [], []
    overlay_threshold = (args.score_threshold if args.overlay_threshold is None
                         else args.overlay_threshold)
    for n, (scene_id, im_id) in enumerate(tqdm(images, desc="images", unit="img", dynamic_ncols=True)):
        scene = split.scene(scene_id)
        image, K = scene.image(im_id), scene.cameras[im_id].K
        if image.ndim == 2:
            image = np.repeat(image[..., None], 3, axis=2)
        start = time.perf_counter()
        dets = detector.detect(image, K)
        masks = detection_masks(dets, K, image.shape[:2], renderer)
        elapsed = time.perf_counter() - start
        caption = None
        if not dets:
            caption = empty_caption(args.score_threshold, dets.best_score)
            empty.append(dets.best_score)
            if len(empty) <= MAX_EMPTY_LINES:
                tqdm.write(f"scene {scene_id} image {im_id}: {caption}")
        for d, m in zip(dets, masks):
            poses.append(bop.PoseEstimate(scene_id, im_id, d.obj_id, d.score, d.pose[:3, :3],
                                          d.pose[:3, 3], elapsed))
            # Detections are amodal; BOP's 2D ground truth lies inside the image.
            x0, y0, x1, y1 = np.clip(d.box, 0, [image.shape[1], image.shape[0]] * 2).tolist()
            dets2d.append(bop.Detection2D(scene_id, im_id, d.obj_id, d.score,
                                          (x0, y0, x1 - x0, y1 - y0), bop.mask_to_rle(m), elapsed))
        if n < args.overlays:
            (args.out / "overlays").mkdir(exist_ok=True)
            shown = [(d, m) for d, m in zip(dets, masks) if d.score >= overlay_threshold]
            if dets and not shown:
                caption = empty_caption(overlay_threshold, dets[0].score)
            canvas = draw_detections(image, [d for d, _ in shown], [m for _, m in shown],
                                     caption=caption)
            cv2.imwrite(str(args.out / "overlays" / f"{scene_id:06d}_{im_id:06d}.png"),
                        cv2.cvtColor(canvas, cv2.COLOR_RGB2BGR))
    stem = f"{args.method}_{ds.name}-{args.split}"
    csv_path, json_path = args.out / f"{stem}.csv", args.out / f"{stem}.json"
    bop.write_pose_results(csv_path, poses)
    bop.write_detection_results(json_path, dets2d)
    if empty:
        print(f"{len(empty)} of {len(images)} images had 0 detections above threshold "
              f"{args.score_threshold:g} (best score among them {max(empty):.3f})")
    print(f"wrote {len(poses)} estimates for {len(images)} images: {csv_path}, {json_path}")
    summary = {"csv": str(csv_path), "json": str(json_path), "num_estimates": len(poses)}
    if args.evaluate:
        from threept_jax.eval import evaluate_results_file

        targets = None if args.targets == "all" else (
            args.dataset_dir / f"test_targets_{args.targets}.json")
        pose = evaluate_results_file(args.dataset_dir, csv_path, split=args.split,
                                     targets_path=targets).to_json()
        det2d = evaluate_results_file(args.dataset_dir, json_path, split=args.split,
                                      targets_path=targets)
        summary.update(pose=pose, detection=det2d)
        print(json.dumps({"6d": {k: v for k, v in pose.items() if k != "per_object"},
                          "2d": det2d}, indent=1))
    return summary
