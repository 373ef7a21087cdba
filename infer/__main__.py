"""Command line: ``python -m infer bop ...`` (a BOP split -> BOP result files) and
``python -m infer images ...`` (your images + meshes -> JSON and overlays).

Run ``python -m infer bop --help`` / ``python -m infer images --help``.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import sys
import time
from collections.abc import Sequence

import cv2
import numpy as np
from tqdm import tqdm

DEFAULT_CACHE = pathlib.Path(os.environ.get("THREEPT_CACHE", "~/.cache/threept_jax")).expanduser()


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--workdir", required=True, help="a detector training run (train/launch.py --workdir)")
    p.add_argument("--step", default="best", help="checkpoint: best, latest or a step number")
    p.add_argument("--num-templates", type=int, default=5140,
                   help="templates per object (the paper's 5140; fewer onboard faster)")
    p.add_argument("--num-scales", type=int, default=3,
                   help="pan-and-scan scales (3 for an unknown depth range)")
    p.add_argument("--score-threshold", type=float, default=0.1)
    p.add_argument("--max-detections", type=int, default=100, help="per image")
    p.add_argument("--cache-dir", type=pathlib.Path, default=DEFAULT_CACHE,
                   help="onboarding and compilation cache (env THREEPT_CACHE)")
    p.add_argument("--out", type=pathlib.Path, required=True, help="output folder")
    p.add_argument("--overlays", type=int, default=10, help="overlay PNGs written (0: none)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m infer", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    b = sub.add_parser("bop", help="run on a BOP split, write BOP 6D CSV + 2D JSON",
                       formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    _common(b)
    b.add_argument("--dataset-dir", type=pathlib.Path, required=True)
    b.add_argument("--split", default="test")
    b.add_argument("--targets", default="bop24", choices=("bop24", "bop19", "all"),
                   help="which images: a test_targets file, or every image of the split")
    b.add_argument("--obj-ids", type=int, nargs="*", help="query only these objects (default all)")
    b.add_argument("--scene-ids", type=int, nargs="*", help="only these scenes")
    b.add_argument("--max-images", type=int, default=None)
    b.add_argument("--models-subdir", default="models", help="meshes to onboard")
    b.add_argument("--method", default="threept", help="method name in the result file names")
    b.add_argument("--evaluate", action="store_true", help="also run the BOP evaluator")
    i = sub.add_parser("images", help="run on images with given meshes and cameras",
                       formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    _common(i)
    i.add_argument("--mesh", action="append", required=True, metavar="ID=PATH",
                   help="an object to find (repeat): integer id and mesh file (PLY/OBJ/GLB/STL)")
    i.add_argument("--units", default="mm", choices=("mm", "cm", "m", "in"),
                   help="length unit of the mesh files")
    i.add_argument("--image", action="append", required=True, help="an RGB image (repeat for views)")
    i.add_argument("--K", action="append", metavar="fx,fy,cx,cy",
                   help="intrinsics in pixels, one per image (or use --cameras)")
    i.add_argument("--cameras", type=pathlib.Path,
                   help='JSON list, one per image: {"K": 3x3, "T_cam_world": 4x4 (mm, multi-view)}')
    return parser


def _load_detector(args):
    import jax

    from infer.checkpoint import load_detector
    from infer.onboarding import Onboarder

    jax.config.update("jax_compilation_cache_dir", str(args.cache_dir / "jax"))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
    model, cfg, step = load_detector(args.workdir, args.step)
    model_id = f"{pathlib.Path(args.workdir).resolve()}@{step}"
    onboarder = Onboarder(model, cfg, model_id, cache_dir=args.cache_dir / "onboarding",
                          num_templates=args.num_templates)
    return model, cfg, onboarder


def _detector(args, model, cfg, objects):
    from infer.detect import SceneDetector

    return SceneDetector(model, cfg, objects, num_scales=args.num_scales,
                         score_threshold=args.score_threshold, max_detections=args.max_detections)


def _read_rgb(path) -> np.ndarray:
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise FileNotFoundError(f"cannot read image {path}")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def run_bop(args) -> dict:
    from threept_jax.data import bop

    from infer.masks import PoseRenderer, detection_masks
    from infer.visualize import draw_detections

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

    model, cfg, onboarder = _load_detector(args)
    objects = onboarder.onboard_all({k: m.path for k, m in models.items()})
    detector = _detector(args, model, cfg, objects)
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


def _cameras(args, n: int) -> tuple[list[np.ndarray], np.ndarray | None]:
    if args.cameras is not None:
        cams = json.loads(args.cameras.read_text())
        if len(cams) != n:
            raise SystemExit(f"error: {args.cameras} has {len(cams)} cameras for {n} images")
        Ks = [np.asarray(c["K"], np.float64) for c in cams]
        T = [c.get("T_cam_world") for c in cams]
        T = None if all(t is None for t in T) else np.asarray(T, np.float32)
        return Ks, T
    if not args.K or len(args.K) != n:
        raise SystemExit(f"error: give one --K fx,fy,cx,cy per image ({n}) or --cameras FILE")
    Ks = []
    for k in args.K:
        try:
            fx, fy, cx, cy = (float(v) for v in k.split(","))
        except ValueError:
            raise SystemExit(f"error: --K {k!r} must be four numbers fx,fy,cx,cy (pixels)") from None
        Ks.append(np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]]))
    return Ks, None


def run_images(args) -> list:
    from infer.scene import run_scene
    from infer.visualize import draw_detections
    from infer.detect import Detection

    meshes = {}
    for item in args.mesh:
        key, _, path = item.partition("=")
        if not key.isdigit() or not path:
            raise SystemExit(f"error: --mesh {item!r} must be ID=PATH with an integer id")
        meshes[int(key)] = path
    images = [_read_rgb(p) for p in args.image]
    Ks, T_cam_world = _cameras(args, len(images))
    model, cfg, onboarder = _load_detector(args)
    objects = onboarder.onboard_all(meshes, units=args.units)
    detector = _detector(args, model, cfg, objects)
    start = time.perf_counter()
    instances = run_scene(detector, images, Ks, T_cam_world)
    elapsed = time.perf_counter() - start
    args.out.mkdir(parents=True, exist_ok=True)
    rows = [{"obj_id": x.obj_id, "score": x.score, "T_world_obj": x.T_world_obj.tolist(),
             "boxes_xyxy": {str(v): b.tolist() for v, b in x.boxes.items()},
             "hypotheses": x.hypotheses.tolist(), "hypothesis_scores": x.hypothesis_scores.tolist()}
            for x in instances]
    (args.out / "instances.json").write_text(json.dumps({"time_s": elapsed, "instances": rows}, indent=1))
    for v, (img, path) in enumerate(zip(images, args.image)):
        if v >= args.overlays:
            break
        T_cw = np.eye(4) if T_cam_world is None else T_cam_world[v]
        drawn = [Detection(x.obj_id, x.boxes.get(v, np.zeros(4)), x.score, (T_cw @ x.T_world_obj)[None],
                           x.hypothesis_scores[:1], np.zeros(0)) for x in instances]
        canvas = draw_detections(img, drawn, [x.masks[v] for x in instances])
        cv2.imwrite(str(args.out / f"overlay_{v}_{pathlib.Path(path).stem}.png"),
                    cv2.cvtColor(canvas, cv2.COLOR_RGB2BGR))
    print(f"{len(instances)} instances in {elapsed:.2f} s -> {args.out / 'instances.json'}")
    return instances


def main(argv: Sequence[str] | None = None):
    args = build_parser().parse_args(argv)
    try:
        return run_bop(args) if args.command == "bop" else run_images(args)
    except (FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        raise SystemExit(2) from e


if __name__ == "__main__":
    main()
