"""``python -m infer bop``: a BOP split -> BOP 6D results CSV and 2D results JSON (RLE masks),
overlays, and optionally the BOP evaluator's scores.

Every image (``--targets bop19|bop24|all``) or multi-view group (``--targets multiview``) is
one :func:`infer.run_scene` call, queried with every selected object, or with BOP19 targets
(no ``--obj-ids``) with the objects its targets name, as the BOP 6D localisation task gives
them: detection, object generation, and refinement when a refiner
is given (``--refiner``). An image's BOP ``time`` is the wall time of that call (a group's time
on every view's rows). With a refiner, ``{method}_*`` holds the refined poses and the refiner's
masks and ``{method}-initial_*`` the object-generation poses of the same instances with their
rendered silhouettes: the files a run without the refiner writes, so one run gives before and
after. ``--refine-only RESULTS.csv`` refines another method's 6D results instead
(:func:`run_refine_only`).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import pathlib
import time

import cv2
import numpy as np
from tqdm import tqdm

from infer.api import Camera, refine, run_scene
from infer.options import detector_options, load_models
from infer.scene import render_masks

#: Images without detections named one by one on the console; the rest are counted.
MAX_EMPTY_LINES = 10


@dataclasses.dataclass(frozen=True)
class View:
    """One image of a run: scene, image id and sensor (None: the scene's only camera)."""

    scene_id: int
    im_id: int
    sensor: str | None = None


def select_groups_and_objects(args, ds) -> tuple[list[tuple[View, ...]], dict, dict | None]:
    """The groups of views a run covers (one view each, except ``--targets multiview``),
    {obj_id: ObjectModel}, and the objects queried in each image: {(scene_id, im_id): obj_ids},
    or None when every image is queried with every object. Checked before any slow work.

    Objects: ``--obj-ids`` if given (queried in every image), else the objects the targets file
    names for the selected images (BOP19-style targets: the BOP 6D localisation task, where
    which objects an image shows is given; each image is queried with its own), else every
    object of ``models_info.json`` (BOP24-style and multi-view targets and ``--targets all``
    name images only). Objects outside that set are never onboarded, so ``models_info.json``
    may list objects whose meshes are absent; a selected object without its mesh is an error
    naming it and the expected file.
    """
    from threept_jax.data.bop import MULTIVIEW_TARGETS_FILE

    models_dir = ds.models_dir(args.models_subdir)
    models = ds.models(args.models_subdir)
    if args.obj_ids:
        unknown = sorted(set(args.obj_ids) - set(models))
        if unknown:
            raise ValueError(f"--obj-ids {unknown} are not in {models_dir / 'models_info.json'} "
                             f"(it lists {sorted(models)})")
    targets = None
    if args.targets == "multiview":
        mv = ds.multiview_targets()
        if mv is None:
            raise FileNotFoundError(
                f"{args.dataset_dir / MULTIVIEW_TARGETS_FILE} not found; multi-view runs "
                "read their groups of views from it (datagen --views V writes one)")
        groups = [tuple(View(g.scene_id, im, sensor) for sensor, im in g.views) for g in mv
                  if not args.scene_ids or g.scene_id in args.scene_ids]
    elif args.targets == "all":
        split = ds.split(args.split)
        groups = [(View(s, i),) for s in split.scene_ids for i in split.scene(s).image_ids
                  if not args.scene_ids or s in args.scene_ids]
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
        groups = [(View(s, i),) for s, i in sorted({(t.scene_id, t.im_id) for t in targets})]
    groups = groups[: args.max_images]
    if not groups:
        raise ValueError("no images selected (check --scene-ids, --obj-ids and --targets)")
    queries = None
    if args.obj_ids:
        wanted = set(args.obj_ids)
    elif targets is not None and any(t.obj_id is not None for t in targets):
        chosen = {(g[0].scene_id, g[0].im_id) for g in groups}
        queries = {}
        for t in targets:
            if t.obj_id is not None and (t.scene_id, t.im_id) in chosen:
                queries.setdefault((t.scene_id, t.im_id), set()).add(t.obj_id)
        queries = {k: tuple(sorted(v)) for k, v in queries.items()}
        wanted = {k for ids in queries.values() for k in ids}
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
    return groups, {k: models[k] for k in sorted(wanted)}, queries


def group_cameras(splits, group: tuple[View, ...], multiview: bool) -> list[Camera]:
    """The run_scene cameras of a group: K alone for one view (the world frame is the camera
    frame), K and T_cam_world (``cam_R_w2c``/``cam_t_w2c``) for a multi-view group.
    ``splits``: sensor -> BopSplit."""
    cams = []
    for view in group:
        scene = splits(view.sensor).scene(view.scene_id)
        where = f"scene {view.scene_id} image {view.im_id} ({scene.path})"
        if view.im_id not in scene.cameras:
            raise FileNotFoundError(f"{where} has no camera entry (the targets name it)")
        cam = scene.cameras[view.im_id]
        if multiview and cam.T_cam_world is None:
            raise ValueError(f"{where} has no cam_R_w2c/cam_t_w2c: a multi-view group needs "
                             "each view's world -> camera pose")
        cams.append(Camera(cam.K, T_cam_world=cam.T_cam_world if multiview else None))
    return cams


def _rgb(image: np.ndarray) -> np.ndarray:
    return np.repeat(image[..., None], 3, axis=2) if image.ndim == 2 else image[..., :3]


def _clip_box(box, hw) -> tuple[float, float, float, float]:
    """xyxy clipped to the image; BOP's 2D ground truth lies inside it."""
    x0, y0, x1, y1 = np.clip(np.asarray(box, np.float64), 0, [hw[1], hw[0]] * 2).tolist()
    return x0, y0, x1, y1


def mask_box(mask: np.ndarray) -> tuple[float, float, float, float] | None:
    """Tight xyxy box (pixel edges) of a mask, None when it is empty."""
    ys, xs = np.nonzero(mask)
    if not len(xs):
        return None
    return float(xs.min()), float(ys.min()), float(xs.max() + 1), float(ys.max() + 1)


def model_box(points: np.ndarray, T_cam_obj: np.ndarray, K: np.ndarray) -> np.ndarray:
    """xyxy box (pixel edges) of the model points projected at a pose
    (``object_generation.projected_box``, whose boxes the detector's poses are fitted to)."""
    from threept_jax.pipeline.object_generation import projected_box

    T = np.asarray(T_cam_obj, np.float32)
    return np.asarray(projected_box(np.asarray(points, np.float32), T[:3, :3], T[:3, 3],
                                    np.asarray(K, np.float32)), np.float64)


def in_view(center_cam: np.ndarray, K: np.ndarray, hw: tuple[int, int]) -> bool:
    """Whether a point [3] of the camera frame (mm) lies in front of the camera and projects
    inside the image (pixel centres at integers)."""
    if center_cam[2] <= 0:
        return False
    u, v = (K @ center_cam)[:2] / center_cam[2]
    return bool(-0.5 <= u < hw[1] - 0.5 and -0.5 <= v < hw[0] - 0.5)


@dataclasses.dataclass
class Results:
    """The rows of one pair of result files (6D CSV, 2D JSON) as they accumulate."""

    poses: list = dataclasses.field(default_factory=list)
    dets2d: list = dataclasses.field(default_factory=list)

    def add(self, scene_id: int, im_id: int, obj_id: int, score: float, T_cam_obj: np.ndarray,
            mask: np.ndarray, box, seconds: float, pose_score: float | None = None) -> np.ndarray:
        """Append one estimate: its 6D row (scored ``pose_score`` when given, else ``score``)
        and its 2D row (``box`` xyxy clipped to the image, the RLE of ``mask``, scored
        ``score``); returns the clipped box."""
        from threept_jax.data import bop

        x0, y0, x1, y1 = _clip_box(box, mask.shape)
        self.poses.append(bop.PoseEstimate(scene_id, im_id, obj_id,
                                           score if pose_score is None else pose_score,
                                           T_cam_obj[:3, :3],
                                           T_cam_obj[:3, 3], seconds))
        self.dets2d.append(bop.Detection2D(scene_id, im_id, obj_id, score,
                                           (x0, y0, x1 - x0, y1 - y0), bop.mask_to_rle(mask),
                                           seconds))
        return np.array([x0, y0, x1, y1])

    def write(self, out: pathlib.Path, stem: str) -> tuple[pathlib.Path, pathlib.Path]:
        from threept_jax.data import bop

        csv_path, json_path = out / f"{stem}.csv", out / f"{stem}.json"
        bop.write_pose_results(csv_path, self.poses)
        bop.write_detection_results(json_path, self.dets2d)
        return csv_path, json_path


def add_group_rows(results: Results, group, images, Ks, T_cam_world, instances, poses, masks,
                   elapsed: float, objects: dict, *, refined: bool) -> list[list[tuple]]:
    """Append the rows of a group's instances (world poses ``poses``, per-view ``masks``) to
    ``results``, per view in that view's camera frame; returns, per view, the (instance index,
    T_cam_obj, 2D xyxy box, mask) of the rows written (for overlays).

    One view: every instance. Several: those whose bounding-sphere centre projects inside the
    view in front of its camera. Score: the detection score (AP ranks by it; the refiner's
    score is a logit not calibrated across objects); the 6D row's is the instance's
    ``pose_score`` where the detector gives one (the cell detector: its network's score ranks
    boxes, the outline's calibrated score ranks poses). 2D box: amodal, as the evaluation's
    ground truth (the box of the full silhouette): for refined instances the projected model
    at the refined pose (the refiner's mask is the visible part: its box shrank occluded
    parts' boxes), else the detection box (the projected model when the view did not detect
    it), clipped to the image.
    """
    drawn = []
    for v, (view, image, K) in enumerate(zip(group, images, Ks)):
        hw = image.shape[:2]
        rows = []
        for i, (x, T_wo, m) in enumerate(zip(instances, poses, masks)):
            T = np.asarray(T_cam_world[v], np.float64) @ np.asarray(T_wo, np.float64)
            obj = objects[x.obj_id]
            if len(group) > 1 and not in_view(T[:3, :3] @ obj.center + T[:3, 3], K, hw):
                continue
            if refined or v not in x.boxes:
                box = model_box(obj.mesh.vertices, T, K)
            else:
                box = x.boxes[v]
            box = results.add(view.scene_id, view.im_id, x.obj_id, x.score, T, m[v], box, elapsed,
                              pose_score=x.pose_score)
            rows.append((i, T, box, m[v]))
        drawn.append(rows)
    return drawn


def _draw(path: pathlib.Path, image, rows, instances, threshold: float, caption,
          rows_before=()) -> None:
    """One overlay: the rows above ``threshold`` (boxes, labels, contours of the written poses)
    and, when refining, the contours of the same instances before refinement
    (``rows_before``, white)."""
    from infer.detect import Detection
    from infer.visualize import draw_detections, empty_caption

    shown = [r for r in rows if instances[r[0]].score >= threshold]
    if rows and not shown:
        caption = empty_caption(threshold, max(instances[r[0]].score for r in rows))
    dets = [Detection(instances[i].obj_id, box, instances[i].score, T[None], np.ones(1),
                      np.zeros(0)) for i, T, box, _ in shown]
    kept = {r[0] for r in shown}
    before = [m for i, *_, m in rows_before if i in kept]
    if before and caption is None:
        caption = "white: contours before refinement; colour: after"
    canvas = draw_detections(image, dets, [m for *_, m in shown], caption=caption,
                             before_masks=before)
    path.parent.mkdir(exist_ok=True)
    cv2.imwrite(str(path), cv2.cvtColor(canvas, cv2.COLOR_RGB2BGR))


def run_bop(args) -> dict:
    """The ``bop`` command (module docstring); returns the summary (file paths, counts and,
    with ``--evaluate``, the scores)."""
    from threept_jax.data import bop

    if args.refine_only is not None:
        return run_refine_only(args)
    ds = bop.BopDataset(args.dataset_dir)
    cell = bop.load_cell(args.dataset_dir)
    if args.depth_range is None and cell is not None:
        args.depth_range = tuple(cell["depth_range_mm"])
        print(f"depth range {args.depth_range[0]:.0f}-{args.depth_range[1]:.0f} mm from "
              f"{args.dataset_dir / bop.CELL_FILE} (--depth-range overrides it)", flush=True)
    groups, models, queries = select_groups_and_objects(args, ds)
    multiview = args.targets == "multiview"
    splits = functools.cache(lambda sensor: ds.split(args.split, sensor))  # scenes read once
    cameras = [group_cameras(splits, g, multiview) for g in groups]

    nets = load_models(args)
    objects = nets.onboard({k: m.path for k, m in models.items()})
    by_id = {o.obj_id: o for o in objects}
    refining = nets.refiner is not None
    args.out.mkdir(parents=True, exist_ok=True)
    final, initial = Results(), Results()
    empty = []
    overlay_threshold = (args.score_threshold if args.overlay_threshold is None
                         else args.overlay_threshold)
    what = "groups" if multiview else "images"
    shown = 0
    for group, cams in zip(tqdm(groups, desc=what, unit=what[:-1], dynamic_ncols=True),
                           cameras):
        images = [_rgb(splits(v.sensor).scene(v.scene_id).image(v.im_id)) for v in group]
        start = time.perf_counter()
        queried = (objects if queries is None else
                   [o for o in objects
                    if o.obj_id in queries.get((group[0].scene_id, group[0].im_id), ())])
        instances = run_scene(images, cams, queried, nets, with_masks=True,
                              **detector_options(args))
        elapsed = time.perf_counter() - start
        Ks = [c.K for c in cams]
        T_cw = np.stack([c.T_cam_world for c in cams]) if multiview else np.eye(4)[None]
        drawn = add_group_rows(final, group, images, Ks, T_cw, instances,
                               [x.T_world_obj for x in instances],
                               [x.masks for x in instances], elapsed, by_id, refined=refining)
        drawn_before = [[] for _ in group]
        if refining:  # outside the timed part: the before-refinement files
            before = [x.T_world_obj_initial for x in instances]
            drawn_before = add_group_rows(
                initial, group, images, Ks, T_cw, instances, before,
                render_masks(instances, before, images, Ks, T_cw, nets.pose_renderer(objects)),
                elapsed, by_id, refined=False)
        caption = None
        if not instances:
            caption = empty_caption_of(instances, args.score_threshold, multiview)
            empty.append(instances.best_score)
            if len(empty) <= MAX_EMPTY_LINES:
                names = ", ".join(str(v.im_id) for v in group)
                tqdm.write(f"scene {group[0].scene_id} image{'s' * multiview} {names}: {caption}")
        for view, image, rows, rows_before in zip(group, images, drawn, drawn_before):
            if shown >= args.overlays:
                break
            shown += 1
            _draw(args.out / "overlays" / f"{view.scene_id:06d}_{view.im_id:06d}.png", image,
                  rows, instances, overlay_threshold, caption, rows_before)

    stem = f"{args.method}_{ds.name}-{args.split}"
    csv_path, json_path = final.write(args.out, stem)
    if empty:
        print(f"{len(empty)} of {len(groups)} {what} had 0 detections above threshold "
              f"{args.score_threshold:g} (best score among them {max(empty):.3f})")
    print(f"wrote {len(final.poses)} estimates for {len(groups)} {what}: {csv_path}, {json_path}")
    summary = {"csv": str(csv_path), "json": str(json_path), "num_estimates": len(final.poses)}
    initial_paths = None
    if refining:
        initial_paths = initial.write(args.out, f"{args.method}-initial_{ds.name}-{args.split}")
        print(f"before refinement: {initial_paths[0]}, {initial_paths[1]}")
        summary.update(csv_initial=str(initial_paths[0]), json_initial=str(initial_paths[1]))
    if args.evaluate:
        targets = evaluation_targets(args, ds, groups)
        summary.update(evaluate(args, csv_path, json_path, targets))
        if initial_paths is not None:
            summary.update({f"{k}_initial": v for k, v in
                            evaluate(args, *initial_paths, targets).items()})
        _print_scores(summary, args.out, stem)
    return summary


def empty_caption_of(instances, threshold: float, multiview: bool) -> str:
    """What an empty scene's overlay and console line say."""
    from infer.visualize import empty_caption

    if multiview and instances.best_score > threshold:
        return (f"0 instances: no detection above threshold {threshold:g} was matched across "
                "enough views")
    return empty_caption(threshold, instances.best_score)


def evaluation_targets(args, ds, groups) -> pathlib.Path | None:
    """The targets file the evaluation uses: the run's ``--targets`` file (when it exists:
    ``--refine-only`` does not need one); for a multi-view run ``test_targets_bop24.json`` when
    the dataset has one, else a file listing every image of the groups that were run (written
    to ``--out``); None (the evaluator's default: the BOP24, BOP19 or ground-truth images) for
    ``--targets all``."""
    from threept_jax.data import bop

    if args.targets == "all":
        return None
    if args.targets != "multiview":
        path = args.dataset_dir / f"test_targets_{args.targets}.json"
        return path if path.is_file() else None
    bop24 = args.dataset_dir / "test_targets_bop24.json"
    if bop24.is_file():
        return bop24
    path = args.out / f"test_targets_multiview-views_{ds.name}-{args.split}.json"
    bop.write_targets(path, [bop.Target(v.scene_id, v.im_id) for g in groups for v in g])
    return path


def evaluate(args, csv_path, json_path, targets) -> dict:
    """{"pose": 6D scores (``PoseScores.to_json()``), "detection": 2D {"bbox", "segm"}}."""
    from threept_jax.eval import evaluate_results_file

    pose = evaluate_results_file(args.dataset_dir, csv_path, split=args.split,
                                 targets_path=targets).to_json()
    out = {"pose": pose}
    if json_path is not None:
        out["detection"] = evaluate_results_file(args.dataset_dir, json_path, split=args.split,
                                                 targets_path=targets)
    return out


def score_lines(summary: dict) -> list[str]:
    """The evaluated scores of a run (:func:`evaluate`'s ``pose``, ``detection`` and their
    ``_initial`` twins) as a table: a row per result file, the BOP 6D AP with its MSSD and MSPD
    parts and AP-mm, COCO box and mask AP / AP50."""
    rows = [(suffix, name) for suffix, name in (("", "refined" if "pose_initial" in summary
                                                 else "results"),
                                                ("_initial", "before refinement"))
            if f"pose{suffix}" in summary]
    pose = summary[f"pose{rows[0][0]}"]
    columns = ("6D AP", "MSSD", "MSPD", "AP-mm", "box AP", "AP50", "mask AP", "AP50")
    lines = [f"BOP scores ({pose['num_gt']} ground-truth instances):",
             f"  {'':18s}" + "".join(f" {c:>7s}" for c in columns)]
    for suffix, name in rows:
        p = summary[f"pose{suffix}"]
        d = summary.get(f"detection{suffix}") or {}
        values = [p["ap"], p["ap_mssd"], p["ap_mspd"], p["ap_mm"],
                  *(d[t][k] if t in d else None for t in ("bbox", "segm") for k in ("ap", "ap50"))]
        lines.append(f"  {name:18s}" + "".join(f" {'-' if v is None else f'{v:.3f}':>7s}"
                                               for v in values))
    box = (summary.get("detection") or {}).get("bbox")
    if box and "f1" in box:
        lines.append(f"  box: best F1 {box['f1']:.3f} at score {box['f1_threshold']:.3f}")
    return lines


def _print_scores(summary: dict, out: pathlib.Path, stem: str) -> None:
    """Prints :func:`score_lines` and writes every score (per object too) to
    ``out/{stem}_scores.json``."""
    path = out / f"{stem}_scores.json"
    scores = {k: v for k, v in summary.items() if k.startswith(("pose", "detection"))}
    path.write_text(json.dumps(scores, indent=1))
    print("\n".join([*score_lines(summary), f"  every score, per object too: {path}"]))


# --------------------------------------------------------------------------- --refine-only


def refine_only_inputs(args, ds) -> tuple[dict, dict]:
    """({(scene_id, im_id): [PoseEstimate]} in file order, {obj_id: ObjectModel}) of
    ``--refine-only``, checked before any model loads: a CSV that does not read, objects
    without a mesh and images the split lacks are errors naming the CSV."""
    from threept_jax.data import bop

    path = args.refine_only
    estimates = bop.read_pose_results(path)
    if args.scene_ids:
        estimates = [e for e in estimates if e.scene_id in args.scene_ids]
    if args.obj_ids:
        estimates = [e for e in estimates if e.obj_id in args.obj_ids]
    per_image: dict = {}
    for e in estimates:
        per_image.setdefault((e.scene_id, e.im_id), []).append(e)
    per_image = dict(list(per_image.items())[: args.max_images])
    if not per_image:
        raise ValueError(f"{path} holds no estimates to refine (check --scene-ids, --obj-ids)")
    models_dir = ds.models_dir(args.models_subdir)
    models = ds.models(args.models_subdir)
    wanted = sorted({e.obj_id for rows in per_image.values() for e in rows})
    unknown = [k for k in wanted if k not in models]
    if unknown:
        raise ValueError(f"{path} has estimates of objects {unknown} that "
                         f"{models_dir / 'models_info.json'} does not list")
    missing = [k for k in wanted if models[k].path is None]
    if missing:
        paths = ", ".join(f"{k}: {models_dir / f'obj_{k:06d}.ply'}" for k in missing)
        raise FileNotFoundError(f"{path} has estimates of objects {missing} without a mesh "
                                f"({paths})")
    split = ds.split(args.split)
    for scene_id, im_id in per_image:
        try:
            scene = split.scene(scene_id)
            if im_id not in scene.cameras:
                raise FileNotFoundError(f"its cameras list no image {im_id}")
            scene.image_path(im_id)
        except FileNotFoundError as e:
            raise FileNotFoundError(f"{path} has estimates for scene {scene_id} image {im_id}, "
                                    f"which {split.path} lacks: {e}") from None
    return per_image, {k: models[k] for k in wanted}


def method_of(path: pathlib.Path) -> str:
    """The method name of a BOP results file ``METHOD_DATASET-SPLIT.csv``."""
    return path.stem.split("_")[0]


def run_refine_only(args) -> dict:
    """``--refine-only RESULTS.csv``: every estimate of an image refined together by 3PT-R
    (one view, camera frame) from its pose; writes ``{method}-3ptr_{ds}-{split}.csv`` and
    ``.json`` (the refiner's masks, each pixel to the best-scored estimate claiming it). Scores
    are kept; an image's time is its time in the input plus our refinement of it (-1 stays
    unknown)."""
    from infer.refine import refine_objects
    from infer.scene import assign_pixels
    from threept_jax.data import bop

    ds = bop.BopDataset(args.dataset_dir)
    per_image, models = refine_only_inputs(args, ds)
    nets = load_models(args, detector=False)
    objects = refine_objects({k: m.path for k, m in models.items()})
    by_id = {o.obj_id: o for o in objects}
    split = ds.split(args.split)
    args.out.mkdir(parents=True, exist_ok=True)
    results = Results()
    for n, ((scene_id, im_id), rows) in enumerate(
            tqdm(per_image.items(), desc="images", unit="img", dynamic_ncols=True)):
        scene = split.scene(scene_id)
        image, K = _rgb(scene.image(im_id)), scene.cameras[im_id].K
        rows = sorted(rows, key=lambda e: -e.score)  # masks: pixels to the best-scored first
        start = time.perf_counter()
        refined = refine([image], [Camera(K)], objects,
                         [(e.obj_id, e.T_cam_obj) for e in rows], nets)
        elapsed = time.perf_counter() - start
        assign_pixels(refined)
        taken = rows[0].time
        total = taken + elapsed if taken >= 0 else -1.0
        drawn = []
        for e, r in zip(rows, refined):
            T = r.T_world_obj
            box = model_box(by_id[e.obj_id].mesh.vertices, T, K)  # amodal, as the GT's
            box = results.add(scene_id, im_id, e.obj_id, e.score, T, r.masks[0], box, total)
            drawn.append((len(drawn), T, box, r.masks[0]))
        if n < args.overlays:
            _draw(args.out / "overlays" / f"{scene_id:06d}_{im_id:06d}.png", image, drawn,
                  rows, args.overlay_threshold or 0.0, None)
    from threept_jax.pipeline.contour import ContourSettings

    by = "contour" if isinstance(nets.refiner, ContourSettings) else "3ptr"
    stem = f"{method_of(args.refine_only)}-{by}_{ds.name}-{args.split}"
    csv_path, json_path = results.write(args.out, stem)
    print(f"refined {len(results.poses)} estimates of {len(per_image)} images: {csv_path}, "
          f"{json_path}")
    summary = {"csv": str(csv_path), "json": str(json_path), "num_estimates": len(results.poses)}
    if args.evaluate:
        targets = evaluation_targets(args, ds, [])
        summary.update(evaluate(args, csv_path, json_path, targets))
        summary["pose_initial"] = evaluate(args, args.refine_only, None, targets)["pose"]
        _print_scores(summary, args.out, stem)
    return summary
