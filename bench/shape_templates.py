"""Shape templates without training (issue 37): what OpenCV's LINE-2D (``cv2.linemod``) gives.

Two measurements on the held-out path-traced cell scenes of ``bench/contour_refine.py``
(``runs/contour/cell``: T-LESS and ITODD meshes, the cell's camera and depth range, generated
there on first use):

1. **Tolerance**: for ground-truth instances, a template rendered at the true pose (the
   project's rasterizer, the mesh's colours or grey, headlight shading) and templates of the
   pose turned by 3-16 degrees in the image plane (about the optical axis) and out of it: the
   best LINE-2D similarity near the instance against the best anywhere else in the image
   (clutter and other parts). This sets how densely templates must sample rotations.
2. **Detection**: templates over a Fibonacci view sphere (``--views``), ``--inplane`` turns of
   each (the rendered view rotated about the principal point, exact for a turn about the
   optical axis) at ``--distances`` distances spread over the cell's depth range; every image
   matched with the templates of the parts it holds (5-8 parts queried), boxes of the matches
   merged by NMS (IoU 0.5) across templates and parts, the best 30 kept, scored by the
   project's COCO evaluator (box AP50 with each part, and with parts ignored: is anything
   found at all). Onboarding seconds per part and matching seconds per image are printed.

    python bench/shape_templates.py [--views 200] [--inplane 12] [--distances 3] [--scenes 2]
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

import cv2
import numpy as np
from scipy.spatial.transform import Rotation
from tqdm import tqdm

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from infer.refine import refine_objects  # noqa: E402
from threept_jax.data import bop  # noqa: E402
from threept_jax.eval.coco import evaluate_coco  # noqa: E402
from threept_jax.geometry.grids import viewpoint_rotation  # noqa: E402
from threept_jax.pipeline.contour import fibonacci_directions  # noqa: E402
from threept_jax.render.mesh import prepare_mesh, to_raster_mesh  # noqa: E402
from threept_jax.render.raster import render  # noqa: E402

DATA = ROOT / "runs" / "contour" / "cell"
MIN_SIDE = 16  # template images are squares of a multiple of this (LINE-2D's pyramid)


def render_bgr(rm, T, K, hw):
    out = render(rm, np.asarray(T, np.float32), np.asarray(K, np.float32), hw, ("rgb", "mask"),
                 ambient=0.5)
    rgb = np.round(np.asarray(out["rgb"]) * 255).astype(np.uint8)
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), np.asarray(out["mask"]).astype(np.uint8) * 255


def turned(T, center, deg, axis):
    """T_cam_obj turned by ``deg`` about a camera-frame ``axis`` through the object's centre."""
    dR = Rotation.from_rotvec(np.radians(deg) * np.asarray(axis, np.float64)).as_matrix()
    out = T.copy()
    c = T[:3, :3] @ center + T[:3, 3]
    out[:3, :3] = dR @ T[:3, :3]
    out[:3, 3] = c - out[:3, :3] @ center
    return out


def tolerance(split, objects, scenes, degrees=(0, 3, 5, 8, 12, 16)):
    """Per turn: median best similarity near the instance (in-plane, out-of-plane) and the
    median best similarity elsewhere, over the fully visible instances of ``scenes``."""
    rows = {d: {"inplane": [], "outofplane": [], "elsewhere": []} for d in degrees}
    for s in tqdm(scenes, desc="tolerance", leave=False):
        scene = split.scene(s)
        im = scene.image_ids[0]
        bgr = cv2.cvtColor(scene.image(im), cv2.COLOR_RGB2BGR)
        K = scene.cameras[im].K
        for g, info in zip(scene.gt[im], scene.gt_info[im]):
            if info.visib_fract < 0.95:
                continue
            o = objects[g.obj_id]
            center = np.asarray(o["mesh"].center, np.float64)
            for d in degrees:
                for kind, axis in (("inplane", (0, 0, 1)), ("outofplane", (1, 0, 0))):
                    tbgr, m = render_bgr(o["raster"], turned(g.T_cam_obj, center, d, axis), K,
                                         bgr.shape[:2])
                    det = cv2.linemod.getDefaultLINE()
                    tid, rect = det.addTemplate([tbgr], "x", m)
                    if tid < 0:
                        continue
                    matches, _ = det.match([bgr], 50.0)
                    near = [x.similarity for x in matches
                            if abs(x.x - rect[0]) < 12 and abs(x.y - rect[1]) < 12]
                    far = [x.similarity for x in matches
                           if abs(x.x - rect[0]) >= 40 or abs(x.y - rect[1]) >= 40]
                    rows[d][kind].append(max(near, default=0.0))
                    rows[d]["elsewhere"].append(max(far, default=0.0))
    return {d: {k: float(np.median(v)) if v else float("nan") for k, v in r.items()}
            for d, r in rows.items()}


def onboard(o, f, distances, views, inplane):
    """LINE-2D templates of one part: (detector, {template id: (x, y, w, h)})."""
    det = cv2.linemod.getDefaultLINE()
    rects = {}
    center = np.asarray(o["mesh"].center, np.float64)
    diameter = float(o["mesh"].diameter)
    for z in distances:
        S = int(np.ceil(f * diameter / z * 1.05 / MIN_SIDE) * MIN_SIDE)
        K = np.array([[f, 0, S / 2 - 0.5], [0, f, S / 2 - 0.5], [0, 0, 1]])
        for d in fibonacci_directions(views):
            T = np.eye(4)
            T[:3, :3] = viewpoint_rotation(d)
            T[:3, 3] = np.array([0, 0, z]) - T[:3, :3] @ center
            img, m = render_bgr(o["raster"], T, K, (S, S))
            for k in range(inplane):
                M = cv2.getRotationMatrix2D((S / 2 - 0.5, S / 2 - 0.5), 360.0 * k / inplane, 1.0)
                tid, rect = det.addTemplate(
                    [cv2.warpAffine(img, M, (S, S))], "x",
                    cv2.warpAffine(m, M, (S, S), flags=cv2.INTER_NEAREST))
                if tid >= 0:
                    rects[tid] = rect
    return det, rects


def detection(split, objects, scenes, depth_range, views, inplane, num_distances):
    keys = [(s, split.scene(s).image_ids[0]) for s in scenes]
    f = float(np.sqrt(np.prod(np.diag(split.scene(scenes[0]).cameras[keys[0][1]].K)[:2])))
    distances = np.geomspace(depth_range[0] * 1.05, depth_range[1] * 0.95, num_distances)
    wanted = sorted({g.obj_id for s, im in keys for g in split.scene(s).gt[im]})
    t = time.perf_counter()
    built = {i: onboard(objects[i], f, distances, views, inplane)
             for i in tqdm(wanted, desc="templates", leave=False)}
    onboard_s = (time.perf_counter() - t) / len(wanted)
    dets, gt, sizes, match_s = [], {}, {}, []
    for s, im in tqdm(keys, desc="images", leave=False):
        scene = split.scene(s)
        bgr = cv2.cvtColor(scene.image(im), cv2.COLOR_RGB2BGR)
        queried = sorted({g.obj_id for g in scene.gt[im]})
        t = time.perf_counter()
        boxes, scores, parts = [], [], []
        for obj_id in queried:
            det, rects = built[obj_id]
            for m in det.match([bgr], 75.0)[0]:
                r = rects[m.template_id]
                boxes.append([m.x, m.y, r[2], r[3]])
                scores.append(float(m.similarity))
                parts.append(obj_id)
        keep = np.asarray(cv2.dnn.NMSBoxes(boxes, scores, 0.0, 0.5), int).ravel()[:30] \
            if boxes else []
        match_s.append(time.perf_counter() - t)
        for k in keep:
            dets.append(bop.Detection2D(s, im, parts[k], scores[k] / 100, tuple(boxes[k])))
        gt[(s, im)] = [{"bbox": list(map(float, info.bbox_obj)), "area": float(info.px_count_visib),
                        "iscrowd": 0, "bop_ignore": int(info.visib_fract < 0.1),
                        "category_id": g.obj_id}
                       for g, info in zip(scene.gt[im], scene.gt_info[im])]
        sizes[(s, im)] = bgr.shape[1::-1]
    ap = evaluate_coco(dets, gt, sizes, keys, wanted, ("bbox",))["bbox"]
    agnostic = evaluate_coco(dets, gt, sizes, keys, wanted, ("bbox",), any_part=True)["bbox"]
    return {"parts": len(wanted), "templates_per_part": float(np.mean(
        [len(r) for _, r in built.values()])), "onboard_s_per_part": onboard_s,
        "match_s_per_image": float(np.median(match_s)), "box_ap50": ap["ap50"],
        "box_ap50_any_part": agnostic["ap50"]}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--views", type=int, default=200)
    p.add_argument("--inplane", type=int, default=12)
    p.add_argument("--distances", type=int, default=3)
    p.add_argument("--scenes", type=int, default=2, help="held-out images scored")
    p.add_argument("--out", type=pathlib.Path, default=None)
    args = p.parse_args(argv)
    if not DATA.exists():
        sys.exit(f"{DATA} not found: run `python bench/contour_refine.py` once (it generates "
                 "the held-out cell scenes)")
    ds = bop.BopDataset(DATA)
    split = ds.split("val_pbr")
    objects = {o.obj_id: {"mesh": o.mesh, "raster": to_raster_mesh(
        prepare_mesh(o.mesh, max_faces=4096, texture_size=None))}
        for o in refine_objects({k: m.path for k, m in ds.models().items()})}
    scenes = list(split.scene_ids)[:args.scenes]
    tol = tolerance(split, objects, scenes)
    print("LINE-2D similarity of a template at the true pose turned by A degrees (median over "
          "fully visible instances):\n| A | in-plane, at the instance | out-of-plane, at the "
          "instance | best elsewhere |\n|---|---|---|---|")
    for d, r in tol.items():
        print(f"| {d} | {r['inplane']:.1f} | {r['outofplane']:.1f} | {r['elsewhere']:.1f} |")
    cell = json.loads((DATA / "cell.json").read_text())
    out = detection(split, objects, scenes, cell["depth_range_mm"], args.views, args.inplane,
                    args.distances)
    print(f"\n{args.views} views x {args.inplane} in-plane x {args.distances} distances: "
          f"{out['templates_per_part']:.0f} templates per part, onboarding "
          f"{out['onboard_s_per_part']:.1f} s per part, matching {out['match_s_per_image']:.2f} s "
          f"per image ({out['parts']} parts); box AP50 {out['box_ap50']:.3f} (any part "
          f"{out['box_ap50_any_part']:.3f})")
    if args.out:
        args.out.write_text(json.dumps({"tolerance": tol, "detection": out}, indent=1))


if __name__ == "__main__":
    main()
