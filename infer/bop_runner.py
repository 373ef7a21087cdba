"""``python -m infer bop``: a BOP split -> BOP 6D results CSV and 2D results JSON (RLE masks),
overlays, and optionally the BOP evaluator's scores."""

from __future__ import annotations

import json
import time

import cv2
import numpy as np
from tqdm import tqdm

from infer.cli import detector_options, load_models


def run_bop(args) -> dict:
    from infer.masks import PoseRenderer, detection_masks
    from infer.visualize import draw_detections
    from threept_jax.data import bop

    ds = bop.BopDataset(args.dataset_dir)
    models = ds.models(args.models_subdir)
    if args.obj_ids:
        missing = sorted(set(args.obj_ids) - set(models))
        if missing:
            raise SystemExit(f"error: objects {missing} are not in {ds.models_dir(args.models_subdir)}")
        models = {k: v for k, v in models.items() if k in args.obj_ids}
    split = ds.split(args.split)
    if args.targets == "all":
        images = [(s, i) for s in split.scene_ids for i in split.scene(s).image_ids]
    else:
        targets = ds.targets(args.targets)
        if targets is None:
            raise SystemExit(f"error: {args.dataset_dir}/test_targets_{args.targets}.json not found; "
                             "pass --targets all to run on every image of the split")
        images = sorted({(t.scene_id, t.im_id) for t in targets})
    if args.scene_ids:
        images = [x for x in images if x[0] in args.scene_ids]
    images = images[: args.max_images]
    if not images:
        raise SystemExit("error: no images selected")

    nets = load_models(args)
    objects = nets.onboard({k: m.path for k, m in models.items()})
    detector = nets.scene_detector(objects, **detector_options(args))
    renderer = PoseRenderer(objects)
    args.out.mkdir(parents=True, exist_ok=True)
    poses, dets2d = [], []
    for n, (scene_id, im_id) in enumerate(tqdm(images, desc="images", unit="img", dynamic_ncols=True)):
        scene = split.scene(scene_id)
        image, K = scene.image(im_id), scene.cameras[im_id].K
        if image.ndim == 2:
            image = np.repeat(image[..., None], 3, axis=2)
        start = time.perf_counter()
        dets = detector.detect(image, K)
        masks = detection_masks(dets, K, image.shape[:2], renderer)
        elapsed = time.perf_counter() - start
        for d, m in zip(dets, masks):
            poses.append(bop.PoseEstimate(scene_id, im_id, d.obj_id, d.score, d.pose[:3, :3],
                                          d.pose[:3, 3], elapsed))
            x0, y0, x1, y1 = (float(v) for v in d.box)
            dets2d.append(bop.Detection2D(scene_id, im_id, d.obj_id, d.score,
                                          (x0, y0, x1 - x0, y1 - y0), bop.mask_to_rle(m), elapsed))
        if n < args.overlays:
            (args.out / "overlays").mkdir(exist_ok=True)
            canvas = draw_detections(image, dets, masks)
            cv2.imwrite(str(args.out / "overlays" / f"{scene_id:06d}_{im_id:06d}.png"),
                        cv2.cvtColor(canvas, cv2.COLOR_RGB2BGR))
    stem = f"{args.method}_{ds.name}-{args.split}"
    csv_path, json_path = args.out / f"{stem}.csv", args.out / f"{stem}.json"
    bop.write_pose_results(csv_path, poses)
    bop.write_detection_results(json_path, dets2d)
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
