"""The training-free detector (issue 37): box AP and seconds per image against 3PT-D.

On a BOP split with ground truth (default: the demo cell's held-out test images,
``runs/demo/zero_shot/data/test``, written by ``make demo``; or the held-out cell scenes of
``bench/contour_refine.py``, ``runs/contour/cell``), every image queried with all of the
dataset's parts, the cell's depth range from its ``cell.json``:

* the templates detector (:class:`infer.shape_detect.ShapeSearchDetector`, no network; with
  ``--per-image`` each image queried with the parts it shows, as a cell that knows its tray's
  parts):
  onboarding seconds per part (contour views rendered, or read from the cache, and templates),
  the first image (cold: compilation) and the median of the others (warm), and the time of each
  stage on the last image;
* the shipped 3PT-D (:class:`infer.detect.SceneDetector`) on the same images in the same
  process, the reference of the time ratio;
* box AP50 / AP of each (COCO, the dataset's amodal boxes clipped to the image as the BOP
  evaluation does).

``--no-depth-range`` drops the cell's depth range: what a user without a cell gets.

``--ceiling`` (a diagnostic, not a result) asks what limits the AP, the search or the score:
the share of ground-truth instances with a verified candidate of their part within IoU 0.5, and
the box AP50 a perfect score would give (every right candidate ranked above every wrong one,
the NMS across parts as the detector's) beside the calibrated score's, on the same candidates.

This is the detector alone; the BOP 6D AP after refinement comes from ``python -m infer bop
--detector templates --evaluate`` (docs/benchmarks.md).

    python bench/shape_search.py [--data DIR] [--images 8] [--per-image] [--no-depth-range]
        [--by-parts] [--ceiling] [--templates-score FILE] [--candidates 300] [--per-proposal 1]
        [--contour-iterations 1] [--[no-]verifier] [--out F.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import pathlib
import sys
import time

import cv2
import numpy as np
from tqdm import tqdm

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import infer  # noqa: E402
from infer.api import DEFAULT_CACHE  # noqa: E402
from infer.refine import refine_objects  # noqa: E402
from infer.shape_detect import ShapeSearchDetector, load_score_weights  # noqa: E402
from threept_jax.data import bop  # noqa: E402
from threept_jax.eval.bop_eval import evaluate_detection_results  # noqa: E402
from threept_jax.pipeline import shape_search as ss  # noqa: E402


def box_ap(data, split, dets):
    """(AP50, AP) of 2D detections, every part of the dataset a category."""
    ap = evaluate_detection_results(data, dets, split=split)["bbox"]
    return ap["ap50"], ap["ap"]


def run(detect, split, keys, per_image=None):
    """Detections2D and seconds per image of ``detect(image, K)``; with ``per_image(parts)``
    (a detector of those parts), each image is queried with the parts it shows and timed on
    a second call (warm: a new part count compiles)."""
    out, seconds = [], []
    for s, im in tqdm(keys, desc="images", leave=False):
        scene = split.scene(s)
        image, K = scene.image(im), scene.cameras[im].K
        if per_image is not None:
            detect = per_image(tuple(sorted({g.obj_id for g in scene.gt[im]}))).detect
            detect(image, K)
        t = time.perf_counter()
        found = detect(image, K)
        seconds.append(time.perf_counter() - t)
        for d in found:
            x0, y0, x1, y1 = (float(v) for v in d.box)
            out.append(bop.Detection2D(s, im, d.obj_id, d.score, (x0, y0, x1 - x0, y1 - y0)))
    return out, seconds


def stage_seconds(detector, image, K):
    """Seconds of each stage of one (warm) detection."""
    st = detector.settings
    t = time.perf_counter()
    boxes = ss.proposals(image, st)
    t1 = time.perf_counter()
    ss.orientation_response(image, st.spread, st.min_gradient)
    t2 = time.perf_counter()
    detector.detect(image, K)
    t3 = time.perf_counter()
    return {"proposals": t1 - t, "response": t2 - t1, "total": t3 - t2, "num_proposals": len(boxes)}


def ceiling(detector, data, split_name, split, keys, per_image=None):
    """(share of instances with a right verified candidate, box AP50 of the calibrated score,
    box AP50 of a perfect score) on the detector's candidates (module docstring); with
    ``per_image(parts)``, each image's candidates are those of a detector of its own parts, as
    :func:`run` queries it."""
    found, total, dets = 0, 0, {"score": [], "perfect": []}
    for s, im in tqdm(keys, desc="ceiling", leave=False):
        scene = split.scene(s)
        if per_image is not None:
            detector = per_image(tuple(sorted({g.obj_id for g in scene.gt[im]})))
        ids = np.array([o.obj_id for o in detector.objects])
        image = scene.image(im)
        c = detector.candidates(image, scene.cameras[im].K)
        gt_ids = np.array([g.obj_id for g in scene.gt[im]])
        h, w = image.shape[:2]
        gt_box = np.array([[max(b[0], 0), max(b[1], 0), min(b[0] + b[2], w), min(b[1] + b[3], h)]
                           for b in (i.bbox_obj for i in scene.gt_info[im])], np.float64)
        total += len(gt_ids)
        if c is None:
            continue
        hit = ss.right_candidates(c.xyxy, ids[c.obj], gt_box, gt_ids)  # [candidates, instances]
        found += int(hit.any(0).sum())
        score = np.asarray(ss.calibrated_score(c.features, detector.score_weights[c.obj],
                                               c.evidence))
        for name, rank in (("score", score), ("perfect", hit.any(1) + 0.5 * score)):
            order = np.argsort(-rank)
            xywh = [[float(b[0]), float(b[1]), float(b[2] - b[0]), float(b[3] - b[1])]
                    for b in c.xyxy[order]]
            keep = np.asarray(cv2.dnn.NMSBoxes(xywh, rank[order].tolist(), 0.0,
                                               detector.settings.nms_iou), int).ravel()
            dets[name] += [bop.Detection2D(s, im, int(ids[c.obj[order[k]]]),
                                           float(rank[order[k]]), tuple(xywh[k]))
                           for k in keep[:detector.max_detections]]
    ap = {k: box_ap(data, split_name, v)[0] for k, v in dets.items()}
    return found / max(total, 1), ap["score"], ap["perfect"]


def seconds_by_parts(objects, split, keys, depth, settings, cache, counts=(1, 5, 10, 20)):
    """Warm seconds per image (median over ``keys``, after one call that compiles) with the
    first N parts of the dataset queried, for each N in ``counts`` (as many as there are)."""
    out = {}
    for n in counts:
        if n > len(objects):
            break
        detector = ShapeSearchDetector(objects[:n], depth_range=depth, score_threshold=0.0,
                                       max_detections=30, settings=settings, cache_dir=cache)
        scene = split.scene(keys[0][0])
        detector.detect(scene.image(keys[0][1]), scene.cameras[keys[0][1]].K)
        _, seconds = run(detector.detect, split, keys)
        out[n] = float(np.median(seconds))
        print(f"  {n} parts queried: {out[n]:.2f} s per image (warm)")
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", type=pathlib.Path, default=ROOT / "runs/demo/zero_shot/data/test")
    p.add_argument("--split", default="val_pbr")
    p.add_argument("--images", type=int, default=8)
    p.add_argument("--candidates", type=int, default=None, help="poses verified per image")
    p.add_argument("--proposals", type=int, default=None, help="selective-search boxes")
    p.add_argument("--per-proposal", type=int, default=None,
                   help="templates kept per proposal and part")
    p.add_argument("--contour-iterations", type=int, default=None,
                   help="iterations of the verification's contour refinement at each scale")
    p.add_argument("--no-3pt", action="store_true", help="skip the 3PT-D reference")
    p.add_argument("--per-image", action="store_true",
                   help="query each image with the parts it shows (a cell that knows its "
                        "tray's parts) instead of every part of the dataset; templates only")
    p.add_argument("--no-depth-range", action="store_true",
                   help="ignore the cell's depth range (a user without a cell: templates from "
                        "32 px to the image size, 3PT-D's pan-and-scan over three scales)")
    p.add_argument("--cache-dir", type=pathlib.Path, default=DEFAULT_CACHE)
    p.add_argument("--by-parts", action="store_true",
                   help="also time 1, 5, 10 and 20 parts queried (the first N of the dataset)")
    p.add_argument("--templates-score", type=pathlib.Path, default=None, metavar="FILE",
                   help="the cell's own score calibration (python -m train.templates_score "
                        "--cell DATA --out FILE; never fitted on the images evaluated here)")
    p.add_argument("--verifier", action=argparse.BooleanOptionalAction,
                   help="the shipped learned verifier's correction to the score "
                        "(models/templates-verifier). Default: on, as in the detector")
    p.add_argument("--ceiling", action="store_true",
                   help="diagnostic: instances with a right verified candidate, and the box "
                        "AP50 a perfect score would give on the same candidates")
    p.add_argument("--out", type=pathlib.Path, default=None)
    args = p.parse_args(argv)
    if not args.data.exists():
        sys.exit(f"{args.data} not found: run `make demo` (or bench/contour_refine.py for "
                 "runs/contour/cell) first, or pass --data")
    ds = bop.BopDataset(args.data)
    split = ds.split(args.split)
    cell = bop.load_cell(args.data)
    depth = None if cell is None or args.no_depth_range else tuple(cell["depth_range_mm"])
    keys = [(s, im) for s in split.scene_ids for im in split.scene(s).image_ids][:args.images]
    meshes = {k: m.path for k, m in ds.models().items()}
    settings = ss.ShapeSearchSettings()
    over = {k: v for k, v in (("candidates", args.candidates),
                              ("max_proposals", args.proposals),
                              ("per_proposal", args.per_proposal)) if v is not None}
    if args.contour_iterations is not None:
        over["contour"] = dataclasses.replace(settings.contour,
                                              iterations=args.contour_iterations)
    settings = dataclasses.replace(settings, **over)

    weights = None if args.templates_score is None else load_score_weights(args.templates_score)
    verifier = None if args.verifier is False else "shipped"
    t = time.perf_counter()
    objects = refine_objects(meshes)
    detector = ShapeSearchDetector(objects, depth_range=depth, score_threshold=0.0,
                                   max_detections=30, settings=settings,
                                   cache_dir=args.cache_dir / "contours", score_weights=weights,
                                   verifier=verifier)
    onboard = (time.perf_counter() - t) / len(objects)
    per_image = None
    if args.per_image:
        by_id = {o.obj_id: o for o in objects}

        @functools.lru_cache(maxsize=None)  # run() and ceiling() ask for the same part sets
        def per_image(ids):
            return ShapeSearchDetector([by_id[i] for i in ids], depth_range=depth,
                                       score_threshold=0.0, max_detections=30,
                                       settings=settings, cache_dir=args.cache_dir / "contours",
                                       score_weights=weights, verifier=verifier)
    dets, seconds = run(detector.detect, split, keys, per_image)
    scene = split.scene(keys[-1][0])
    stages = stage_seconds(detector, scene.image(keys[-1][1]), scene.cameras[keys[-1][1]].K)
    ap50, ap = box_ap(args.data, args.split, dets)
    result = {"data": str(args.data), "images": len(keys), "parts": len(objects),
              "templates_score": None if weights is None else str(args.templates_score),
              "verifier": detector.verifier is not None,
              "per_image": args.per_image,
              "depth_range": depth,
              "settings": {k: v for k, v in dataclasses.asdict(settings).items()
                           if k != "contour"},
              "templates": {"onboard_s_per_part": onboard, "cold_s": seconds[0],
                            "warm_s": float(np.median(seconds[1:])) if len(seconds) > 1 else None,
                            "stages_s": stages, "box_ap50": ap50, "box_ap": ap}}
    print(f"templates: onboarding {onboard:.1f} s/part, cold {seconds[0]:.1f} s, warm "
          f"{result['templates']['warm_s']:.2f} s/image ({len(objects)} parts), box AP50 "
          f"{ap50:.3f}, AP {ap:.3f}; stages {json.dumps({k: round(v, 2) for k, v in stages.items()})}")
    if args.by_parts:
        result["templates"]["warm_s_by_parts"] = seconds_by_parts(
            objects, split, keys[:3], depth, settings, args.cache_dir / "contours")
    if args.ceiling:
        found, ap_score, ap_perfect = ceiling(detector, args.data, args.split, split, keys,
                                              per_image)
        result["templates"]["ceiling"] = {"instances_verified": found,
                                          "box_ap50_score": ap_score,
                                          "box_ap50_perfect_score": ap_perfect}
        print(f"diagnostic: {found:.0%} of the instances have a right verified candidate; box "
              f"AP50 {ap_score:.3f} with the score, {ap_perfect:.3f} with a perfect score")
    if not (args.no_3pt or args.per_image):
        models = infer.load(cache_dir=args.cache_dir, detector="3pt")
        onboarded = models.onboard(meshes)
        d3 = models.scene_detector(onboarded, depth_range=depth, score_threshold=0.0,
                                   max_detections=30)
        dets3, sec3 = run(d3.detect, split, keys)
        a50, a = box_ap(args.data, args.split, dets3)
        warm3 = float(np.median(sec3[1:])) if len(sec3) > 1 else sec3[0]
        result["3pt"] = {"cold_s": sec3[0], "warm_s": warm3, "box_ap50": a50, "box_ap": a}
        print(f"3PT-D (shipped): cold {sec3[0]:.1f} s, warm {warm3:.2f} s/image, box AP50 "
              f"{a50:.3f}, AP {a:.3f}; templates / 3PT-D warm time: "
              f"{result['templates']['warm_s'] / warm3:.2f}x")
    if args.out:
        args.out.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
