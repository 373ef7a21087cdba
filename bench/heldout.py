"""Held-out accuracy of render-and-compare refinement (issue 15, section 3): BOP 6D AP, AP-mm
and 2D segmentation AP before and after 3PT-R, from one view and from three, with the oracle
network as the upper bound.

The scenes: a BOP dataset of multi-view captures (``python -m datagen.generate --views 3``, whose
``test_targets_multiview_bop25.json`` groups the views of each capture) of parts the detector and
the refiner never saw in training. Every part of the dataset is queried in every image.

Rows, each evaluated on every view image of the groups run (BOP toolkit rules, MSSD/MSPD AP and
AP-mm, COCO segmentation AP of the visible masks):

* ``1 view``: every view alone through the real inference path: detection and object generation
  (``infer.run_scene(refine=False)``: the initial poses, their rendered silhouettes as masks),
  then 3PT-R (``SceneRefiner`` on the same instances: the refined poses, the refiner's masks).
* ``3 views``: each capture's views together (multi-view fusion, multi-view refinement); an
  instance is written to a view when its centre projects into that image.
* ``oracle``: the same initial instances refined by the oracle network
  (``threept_jax.testing.refiner_oracle``: descriptors from ground-truth object coordinates,
  read off the images re-rendered with every ground-truth object painted with its coordinates),
  so the loop's ceiling from these initial poses: what a perfect network would reach.
* ``diagnostic (GT init)``, labelled as such: the detector replaced by ground-truth poses
  perturbed as in refiner training (``perturb_poses``: 15 deg half-normal, 2 % of the diameter
  in x, y, 5 % of the depth in z), K = 8 per visible instance, score 1. It shows what the refiner
  does from a start close to the truth; it is not what a user sees.

    python bench/heldout.py --dataset DIR --detector RUN --refiner RUN [--split val_pbr]
        [--max-groups N] [--views 1 3] [--no-oracle] [--no-diagnostic] [--out report.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import sys
import tempfile
import time
import warnings

import numpy as np
from tqdm import tqdm

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import infer  # noqa: E402
from infer.bop_runner import Results, in_view, mask_box  # noqa: E402
from infer.refine import NUM_HYPOTHESES, RefineObject, SceneRefiner  # noqa: E402
from infer.scene import Instance, assign_pixels  # noqa: E402
from threept_jax.data import bop  # noqa: E402
from threept_jax.data.refiner_input import RefinerExampleConfig, perturb_poses  # noqa: E402
from threept_jax.eval import evaluate_detection_results, evaluate_pose_results  # noqa: E402
from threept_jax.pipeline.refine_loop import LoopSettings  # noqa: E402
from threept_jax.render.mesh import prepare_mesh, to_raster_mesh  # noqa: E402
from threept_jax.render.raster import render  # noqa: E402
from threept_jax.testing.refiner_oracle import make_oracle, xyz_colored  # noqa: E402


def visible(T_cam_obj: np.ndarray, center: np.ndarray, K: np.ndarray, hw) -> bool:
    """The rule of ``python -m infer bop``: the object's centre is in front of the camera and
    projects into the image."""
    return in_view(T_cam_obj[:3, :3] @ center + T_cam_obj[:3, 3], K, hw)


def oracle_image(gt, meshes: dict, K: np.ndarray, hw) -> np.ndarray:
    """uint8 [H, W, 3]: every ground-truth instance painted with its object coordinates
    (``xyz_colored``), unshaded, the nearest surface winning."""
    rgb, depth = np.zeros(tuple(hw) + (3,), np.float32), np.full(hw, np.inf)
    for g in gt:
        out = render(meshes[g.obj_id], np.asarray(g.T_cam_obj, np.float32),
                     np.asarray(K, np.float32), hw, ("rgb", "depth", "mask"), ambient=1.0)
        d = np.where(np.asarray(out["mask"]), np.asarray(out["depth"]), np.inf)
        near = d < depth
        rgb[near], depth = np.asarray(out["rgb"])[near], np.minimum(depth, d)
    return np.round(rgb * 255).astype(np.uint8)


def refined_instances(found, refined) -> list[Instance]:
    """The instances with the refined poses and the refiner's masks, one owner per pixel."""
    out = [dataclasses.replace(x, T_world_obj=r.T_world_obj, masks=dict(r.masks))
           for x, r in zip(found, refined)]
    assign_pixels(out)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dataset", type=pathlib.Path, required=True)
    ap.add_argument("--split", default="val_pbr")
    ap.add_argument("--detector", required=True, help="3PT-D training run")
    ap.add_argument("--refiner", required=True, help="3PT-R training run")
    ap.add_argument("--max-groups", type=int, default=None)
    ap.add_argument("--views", type=int, nargs="+", default=[1, 3], choices=[1, 3])
    ap.add_argument("--no-oracle", action="store_true")
    ap.add_argument("--no-diagnostic", action="store_true")
    ap.add_argument("--score-threshold", type=float, default=0.0,
                    help="detections kept (AP ranks them; 0 keeps the max-detections best)")
    ap.add_argument("--max-detections", type=int, default=10, help="per image")
    ap.add_argument("--seed", type=int, default=0, help="diagnostic perturbations")
    ap.add_argument("--out", type=pathlib.Path, default=None, help="report JSON")
    args = ap.parse_args()

    ds = bop.BopDataset(args.dataset)
    groups = ds.multiview_targets()
    if groups is None:
        raise SystemExit(f"error: {args.dataset} has no {bop.MULTIVIEW_TARGETS_FILE}; "
                         "generate the dataset with python -m datagen.generate --views 3")
    groups = groups[: args.max_groups]
    split = ds.split(args.split)
    info = ds.models()
    models = infer.load(args.detector, refiner=args.refiner)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        objects = models.onboard({k: m.path for k, m in info.items()})
    refiner = models.scene_refiner(objects)
    settings, rcfg = models.refine_settings, models.refiner_config
    centers = {o.obj_id: np.asarray(o.mesh.center, np.float64) for o in objects}
    oracle = oracle_meshes = None
    if not args.no_oracle:
        colored = {o.obj_id: xyz_colored(prepare_mesh(o.mesh, max_faces=settings.max_faces))
                   for o in objects}
        oracle_meshes = {k: to_raster_mesh(m) for k, m in colored.items()}
        oracle = SceneRefiner(
            make_oracle(rcfg.output_size), rcfg, dataclasses.replace(settings, ambient=1.0),
            [RefineObject(o.obj_id, colored[o.obj_id], o.symmetries) for o in objects],
            loop=LoopSettings(antialias=1))
    example = RefinerExampleConfig()
    rng = np.random.default_rng(args.seed)
    table: dict[str, Results] = {}
    images_run = []
    detector_options = dict(score_threshold=args.score_threshold,
                            max_detections=args.max_detections)

    def rows(name: str) -> Results:
        return table.setdefault(name, Results())

    def add(name: str, scene_id: int, im_id: int, obj_id: int, score: float, T, mask,
            seconds: float) -> None:
        box = mask_box(mask) or (0, 0, 0, 0)  # the table scores masks, not boxes
        rows(name).add(scene_id, im_id, obj_id, score, T, mask, box, seconds)

    for group in tqdm(groups, desc="captures", unit="capture", dynamic_ncols=True):
        scene = split.scene(group.scene_id)
        ids = [im_id for _, im_id in group.views]
        images = [scene.image(i) for i in ids]
        images = [np.repeat(im[..., None], 3, 2) if im.ndim == 2 else im for im in images]
        cams = [scene.cameras[i] for i in ids]
        hw = images[0].shape[:2]
        images_run += [(group.scene_id, i) for i in ids]
        oracle_images = (None if oracle is None else
                         [oracle_image(scene.gt[i], oracle_meshes, c.K, hw)
                          for i, c in zip(ids, cams)])
        for V in args.views:
            # One call per view (V = 1, camera frame) or one for the capture (V = 3, world).
            calls = ([[v] for v in range(len(ids))] if V == 1 else [list(range(len(ids)))])
            for views in calls:
                if V == 1:
                    cameras = [bop.Camera(cams[views[0]].K)]
                    T_cw = np.eye(4)[None]
                else:
                    cameras = [cams[v] for v in views]
                    T_cw = np.stack([cams[v].T_cam_world for v in views])
                Ks = np.stack([cams[v].K for v in views])
                ims = [images[v] for v in views]
                start = time.perf_counter()
                found = infer.run_scene(ims, cameras, objects, models, refine=False,
                                        **detector_options)
                t_find = time.perf_counter() - start
                hyps = [x.hypotheses for x in found]
                obj_ids = [x.obj_id for x in found]
                T_arg = None if V == 1 else T_cw
                start = time.perf_counter()
                refined = refined_instances(found, refiner(ims, Ks, T_arg, obj_ids, hyps))
                t_ref = time.perf_counter() - start
                sets = {f"{V} view{'s' * (V > 1)}: initial": (found, t_find),
                        f"{V} view{'s' * (V > 1)}: 3PT-R": (refined, t_find + t_ref)}
                if oracle is not None:
                    o_ims = [oracle_images[v] for v in views]
                    sets[f"{V} view{'s' * (V > 1)}: oracle"] = (
                        refined_instances(found, oracle(o_ims, Ks, T_arg, obj_ids, hyps)),
                        float("nan"))
                for name, (instances, seconds) in sets.items():
                    rows(name)  # a row without instances still gets its (zero) line
                    for x in instances:
                        for j, v in enumerate(views):
                            T = T_cw[j] @ x.T_world_obj
                            if V == 1 or visible(T, centers[x.obj_id], Ks[j], hw):
                                add(name, group.scene_id, ids[v], x.obj_id, x.score, T,
                                    x.masks[j], seconds)
                if args.no_diagnostic:
                    continue
                # Diagnostic: ground-truth poses perturbed, K = 8, for instances visible in the
                # first view of the call.
                v0 = views[0]
                gts = [(g, info[g.obj_id]) for g in scene.gt[ids[v0]]
                       if visible(g.T_cam_obj, centers[g.obj_id], Ks[0], hw)]
                if not gts:
                    continue
                T_wc0 = np.linalg.inv(T_cw[0])
                d_hyps = [T_wc0 @ perturb_poses(g.T_cam_obj, centers[g.obj_id], m.diameter,
                                                NUM_HYPOTHESES, example, rng) for g, m in gts]
                d_ids = [g.obj_id for g, _ in gts]
                start = [Instance(o, 1.0, h[0], h, np.ones(len(h)), {}, {})
                         for o, h in zip(d_ids, d_hyps)]
                diag = {"initial": start,
                        "3PT-R": refined_instances(start, refiner(ims, Ks, T_arg, d_ids,
                                                                  d_hyps))}
                if oracle is not None:
                    diag["oracle"] = refined_instances(
                        start, oracle([oracle_images[v] for v in views], Ks, T_arg, d_ids,
                                      d_hyps))
                for name, instances in diag.items():
                    for x in instances:
                        for j, v in enumerate(views):
                            T = T_cw[j] @ x.T_world_obj
                            mask = x.masks.get(j)
                            if mask is None:  # the initial diagnostic has no masks
                                mask = np.zeros(hw, bool)
                            if V == 1 or visible(T, centers[x.obj_id], Ks[j], hw):
                                add(f"diagnostic, GT init, {V} view{'s' * (V > 1)}: {name}",
                                    group.scene_id, ids[v], x.obj_id, 1.0, T, mask, 0.0)

    report = evaluate(args, table, images_run)
    print(f"\n{len(groups)} captures x {len(groups[0].views)} views, {len(images_run)} images, "
          f"{len(info)} parts queried; detector {args.detector}, refiner {args.refiner}")
    print(f"{'row':<44} {'6D AP':>6} {'AP-mm':>6} {'AR':>6} {'segm AP':>7} {'rows':>5}")
    for name, r in report.items():
        print(f"{name:<44} {r['ap']:>6.3f} {r['ap_mm']:>6.3f} {r['ar']:>6.3f} "
              f"{r['segm_ap']:>7.3f} {r['rows']:>5}")
    if args.out is not None:
        args.out.write_text(json.dumps(report, indent=1))


def evaluate(args, table: dict, images_run) -> dict:
    """Every row's 6D AP, AP-mm, AR (MSSD/MSPD mean) and segmentation AP on the images run."""
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        targets = pathlib.Path(tmp) / "targets.json"
        bop.write_targets(targets, [bop.Target(s, i) for s, i in sorted(set(images_run))])
        for name, rows in table.items():
            # Times: BOP wants one per image; rows of one image share their call's time, and
            # the diagnostic and oracle rows carry none that matters.
            poses = [dataclasses.replace(p, time=-1.0) for p in rows.poses]
            pose = evaluate_pose_results(args.dataset, poses, split=args.split,
                                         targets_path=targets)
            segm = evaluate_detection_results(args.dataset, rows.dets2d, split=args.split,
                                              targets_path=targets)
            out[name] = {"ap": pose.ap, "ap_mm": pose.ap_mm,
                         "ar": (pose.ar_mssd + pose.ar_mspd) / 2,
                         "segm_ap": segm["segm"]["ap"], "rows": len(rows.poses)}
    return out


if __name__ == "__main__":
    main()
