"""The contour refiner on held-out path-traced scenes (issue 36): does the image alone improve poses?

Scenes are made by the data generator (Mitsuba path tracing, random materials and lights, the
parts never seen by any model: the refiner has no training). Two datasets, generated on first
use when ``--data`` does not exist:

* ``cell``: the robot-cell layout, one 640 x 480 camera, T-LESS and ITODD meshes;
* ``rig``: bins and piles seen by a ring of 3 cameras (the multi-view groups datagen writes).

Every ground-truth instance at least ``--min-visib`` visible in the first view starts from the
truth moved by a rung of the noise ladder (rotation about the object's centre by exactly A
degrees about a random axis, translation by exactly T mm in a random direction), all
instances of an image refined together through ``infer.contour_refine.ContourRefiner`` (the
``--refiner contour`` of the commands) in 1 view and, for the rig, in its 3 views. Printed per
rung: median rotation (degrees, symmetry-aware: the BOP toolkit's MSSD is used for recall) and
translation (mm) error before and after, BOP MSSD average recall, the share of instances made
worse (MSSD grew by more than 1 % of the diameter), and the ratio of each median to the start's
(the reference, same starts, same process). Then the score test: 5 starts per instance at the
10 degree / 30 mm rung, each refined; does the highest contour score pick the refined pose of
lowest MSSD (chance 20 %)? Times: the first call (compilation) apart from the warm calls, and
warm milliseconds per object per view per Gauss-Newton iteration. ``--refiner RUN`` adds the
rows of a trained 3PT-R (render-and-compare, its best checkpoint) on the same starts;
``--opencv`` those of OpenCV's ``cv2.rapid`` trackers; ``--verifier`` the verifier test
(:func:`verifier_test`: does the score tell good detections from ones elsewhere or of the wrong
part?).

    python bench/contour_refine.py [--data runs/contour] [--rungs 5:10 10:30 20:60]
        [--evidence region edges both] [--prior 0 0.1] [--opencv] [--refiner RUN]
        [--out contour.json]
"""

from __future__ import annotations

import argparse
import json
import pathlib
import shutil
import sys
import tempfile
import time
import warnings

import numpy as np
from scipy.spatial.transform import Rotation
from tqdm import tqdm

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from infer.contour_refine import ContourRefiner  # noqa: E402
from infer.refine import refine_objects  # noqa: E402
from threept_jax.data import bop  # noqa: E402
from threept_jax.eval.bop6d import MSSD_THRESHOLDS  # noqa: E402
from threept_jax.eval.pose_error import mssd  # noqa: E402
from threept_jax.pipeline.contour import ContourSettings  # noqa: E402

SHARED = ROOT.parent / "shared" / "meshes" / "bop"


def generate(data: pathlib.Path) -> None:
    from datagen import generate as G

    meshes = [str(SHARED / "tless" / "models"), str(SHARED / "itodd" / "models")]
    common = ["--meshes", *meshes, "--resolution", "640", "480", "--spp", "8", "--split", "val",
              "--val-fraction", "0", "--quiet"]
    G.main(["--out", str(data / "cell"), "--num-scenes", "8", "--layout", "cell", "--seed",
            "11", "--instances", "8", "--distinct", "5", "8", *common])
    G.main(["--out", str(data / "rig"), "--num-scenes", "6", "--views", "3", "--layout",
            "mixed", "--seed", "12", "--instances", "6", "--distinct", "3", "6", *common])


def jitter(T: np.ndarray, center: np.ndarray, deg: float, mm: float,
           rng: np.random.Generator) -> np.ndarray:
    """T_world_obj [4, 4] turned by exactly ``deg`` about a random axis through the object's
    centre and moved by exactly ``mm`` in a random direction."""
    axis = rng.standard_normal(3)
    dR = Rotation.from_rotvec(np.radians(deg) * axis / np.linalg.norm(axis)).as_matrix()
    step = rng.standard_normal(3)
    out = T.copy()
    c = T[:3, :3] @ center + T[:3, 3]
    out[:3, :3] = dR @ T[:3, :3]
    out[:3, 3] = c + mm * step / np.linalg.norm(step) - out[:3, :3] @ center
    return out


def load_groups(root: pathlib.Path, min_visib: float):
    """[(images, Ks, T_cam_world [V, 4, 4], [(obj_id, T_world_obj)])] of a generated dataset:
    multi-view groups when it has them, else single images."""
    ds = bop.BopDataset(root)
    split = ds.split("val_pbr")
    multiview = ds.multiview_targets()
    out = []
    if multiview:
        groups = [(g.scene_id, [v for _, v in g.views]) for g in multiview]
    else:
        groups = [(s, [i]) for s in split.scene_ids for i in split.scene(s).image_ids]
    for scene_id, im_ids in groups:
        scene = split.scene(scene_id)
        cams = [scene.cameras[i] for i in im_ids]
        T_cw = np.stack([c.T_cam_world if c.T_cam_world is not None else np.eye(4)
                         for c in cams]).astype(np.float64)
        info = scene.gt_info[im_ids[0]]
        insts = []
        for g, inf in zip(scene.gt[im_ids[0]], info):
            if inf.visib_fract >= min_visib:
                insts.append((g.obj_id, np.linalg.inv(T_cw[0]) @ g.T_cam_obj))
        if insts:
            out.append(([scene.image(i) for i in im_ids], np.stack([c.K for c in cams]),
                        T_cw, insts))
    return ds, out


def errors(T, T_gt, model):
    """(rotation deg, translation mm, mssd mm) of T against T_gt (object models, symmetries)."""
    dR = T[:3, :3].T @ T_gt[:3, :3]
    rot = np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))
    trans = np.linalg.norm(T[:3, 3] - T_gt[:3, 3])
    e = mssd(T[:3, :3], T[:3, 3:4], T_gt[:3, :3], T_gt[:3, 3:4], model["pts"], model["sym"])
    return rot, trans, e


def recall(e_mssd, diam):
    return float(np.mean([np.mean(np.asarray(e_mssd) < t * np.asarray(diam))
                          for t in MSSD_THRESHOLDS]))


def build(ds, settings, cache):
    """(the dataset's objects, their ContourRefiner, seconds per object to build it). The
    contour models are kept in ``cache`` (a fresh directory per run): the first settings
    build them, the others read them back."""
    objects = refine_objects({k: m.path for k, m in ds.models().items()})
    t = time.perf_counter()
    print(f"contour models of {len(objects)} objects ...", flush=True)
    refiner = ContourRefiner(objects, settings, cache_dir=cache)
    return objects, refiner, (time.perf_counter() - t) / len(objects)


def run(name, groups, views, rungs, settings, built, rng_seed=0):
    objects, refiner, onboard_s = built
    eval_models = {}
    for o in objects:
        v = np.asarray(o.mesh.vertices, np.float64)
        pts = v[np.random.default_rng(0).choice(len(v), min(len(v), 1000), replace=False)]
        sym = np.asarray(o.symmetries, np.float64)
        eval_models[o.obj_id] = {"pts": pts, "sym": (sym[:, :3, :3], sym[:, :3, 3]),
                                 "diam": float(o.mesh.diameter),
                                 "center": np.asarray(o.mesh.center, np.float64)}
    rows, cold, warm, n_obj_views = [], None, [], 0
    iters = len(settings.scales) * settings.iterations + 2  # + the two scores
    for deg, mm in rungs:
        rng = np.random.default_rng(rng_seed)
        before, after = [], []
        for images, Ks, T_cw, insts in tqdm(groups, desc=f"{name} {views}v {deg}deg/{mm}mm",
                                            leave=False):
            images, Ks, T_cw = images[:views], Ks[:views], T_cw[:views]
            starts = [jitter(T, eval_models[o]["center"], deg, mm, rng) for o, T in insts]
            t = time.perf_counter()
            out = refiner(images, Ks, T_cw if views > 1 else None if np.allclose(T_cw[0], np.eye(4))
                          else T_cw, [o for o, _ in insts], starts)
            dt = time.perf_counter() - t
            if cold is None:
                cold = dt
            else:
                warm.append(dt)
                n_obj_views += len(insts) * views
            for (o, T_gt), s, r in zip(insts, starts, out):
                m = eval_models[o]
                before.append((*errors(s, T_gt, m), m["diam"]))
                after.append((*errors(r.T_world_obj, T_gt, m), m["diam"]))
        b, a = np.array(before), np.array(after)
        rows.append({
            "data": name, "views": views, "rung": f"{deg:g} deg / {mm:g} mm", "instances": len(b),
            "rot_start": float(np.median(b[:, 0])), "rot_after": float(np.median(a[:, 0])),
            "trans_start": float(np.median(b[:, 1])), "trans_after": float(np.median(a[:, 1])),
            "ar_start": recall(b[:, 2], b[:, 3]), "ar_after": recall(a[:, 2], a[:, 3]),
            "worse": float(np.mean(a[:, 2] > b[:, 2] + 0.01 * b[:, 3]))})
    ms = 1000 * np.sum(warm) / max(n_obj_views, 1) / iters
    return rows, {"data": name, "views": views, "cold_s": cold, "warm_ms_per_object_view_iter": ms,
                  "contour_model_s_per_object": onboard_s}


RAPID_KINDS = ("rapid", "ols", "gos")


def opencv_refine(kind: str, image: np.ndarray, mesh, K: np.ndarray, T_cam_obj: np.ndarray,
                  iterations: int = 1) -> np.ndarray:
    """OpenCV contrib's contour trackers (``cv2.rapid``: RAPID, OLS, GOS) run ``iterations``
    times on one image from T_cam_obj, as a tracker runs on a still frame (100 control points,
    20 px search lines); the pose it ends at (its input where it fails). One iteration is their
    best of 1, 3 and 10 from 10 degree / 30 mm starts on the cell scenes (more drift further)."""
    import cv2

    pts = np.ascontiguousarray(mesh.vertices, np.float32)
    tris = np.ascontiguousarray(mesh.faces, np.int32)
    bgr = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    rvec, _ = cv2.Rodrigues(T_cam_obj[:3, :3])
    tvec = T_cam_obj[:3, 3:4].astype(np.float64).copy()
    Kd = np.asarray(K, np.float64)
    tracker = {"rapid": lambda: cv2.rapid.Rapid.create(pts, tris),
               "ols": lambda: cv2.rapid.OLSTracker.create(pts, tris),
               "gos": lambda: cv2.rapid.GOSTracker.create(pts, tris)}[kind]()
    for _ in range(iterations):
        try:
            _, rvec, tvec = tracker.compute(bgr, 100, 20, Kd, rvec, tvec)
        except cv2.error:
            break
    out = np.eye(4)
    out[:3, :3] = cv2.Rodrigues(np.asarray(rvec, np.float64))[0]
    out[:3, 3] = np.asarray(tvec, np.float64).ravel()
    return out if np.all(np.isfinite(out)) else T_cam_obj


def run_opencv(name, ds, groups, rungs, rng_seed=0):
    """The 1-view rows of :func:`run` for each ``cv2.rapid`` tracker on the same starts."""
    from threept_jax.render.mesh import prepare_mesh

    objects = {o.obj_id: o for o in refine_objects({k: m.path for k, m in ds.models().items()})}
    small = {k: prepare_mesh(o.mesh, max_faces=2048, texture_size=None)
             for k, o in objects.items()}
    rows = []
    for kind in RAPID_KINDS:
        for deg, mm in rungs:
            rng = np.random.default_rng(rng_seed)
            before, after = [], []
            t = time.perf_counter()
            for images, Ks, T_cw, insts in tqdm(groups, desc=f"cv2.rapid {kind} {deg}/{mm}",
                                                leave=False):
                for o, T_gt in insts:
                    m = objects[o]
                    sym = np.asarray(m.symmetries, np.float64)
                    em = {"pts": np.asarray(m.mesh.vertices, np.float64)[::max(
                        1, m.mesh.num_vertices // 1000)], "sym": (sym[:, :3, :3], sym[:, :3, 3])}
                    s = jitter(T_gt, np.asarray(m.mesh.center, np.float64), deg, mm, rng)
                    # The world frame is the first camera's when the views carry T_cam_world.
                    T0 = T_cw[0]
                    r = np.linalg.inv(T0) @ opencv_refine(kind, images[0], small[o], Ks[0],
                                                          T0 @ s)
                    before.append((*errors(s, T_gt, em), float(m.mesh.diameter)))
                    after.append((*errors(r, T_gt, em), float(m.mesh.diameter)))
            b, a = np.array(before), np.array(after)
            rows.append({
                "data": name, "views": 1, "rung": f"{deg:g} deg / {mm:g} mm",
                "instances": len(b), "evidence": f"cv2.rapid {kind}",
                "rot_start": float(np.median(b[:, 0])), "rot_after": float(np.median(a[:, 0])),
                "trans_start": float(np.median(b[:, 1])),
                "trans_after": float(np.median(a[:, 1])),
                "ar_start": recall(b[:, 2], b[:, 3]), "ar_after": recall(a[:, 2], a[:, 3]),
                "worse": float(np.mean(a[:, 2] > b[:, 2] + 0.01 * b[:, 3])),
                "seconds_per_instance": (time.perf_counter() - t) / max(len(b), 1)})
    return rows


def score_test(groups, views, built, num=5, seed=1):
    objects, refiner, _ = built
    models = {o.obj_id: o for o in objects}
    rng = np.random.default_rng(seed)
    picked, total = 0, 0
    for images, Ks, T_cw, insts in groups:
        images, Ks, T_cw = images[:views], Ks[:views], T_cw[:views]
        for o, T_gt in insts:
            m = models[o]
            pts = np.asarray(m.mesh.vertices, np.float64)[::max(1, m.mesh.num_vertices // 1000)]
            res = []
            for _ in range(num):
                s = jitter(T_gt, np.asarray(m.mesh.center, np.float64), 10.0, 30.0, rng)
                r = refiner(images, Ks, T_cw if views > 1 else None, [o], [s])[0]
                sym = np.asarray(m.symmetries, np.float64)
                e = mssd(r.T_world_obj[:3, :3], r.T_world_obj[:3, 3:4], T_gt[:3, :3],
                         T_gt[:3, 3:4], pts, (sym[:, :3, :3], sym[:, :3, 3]))
                res.append((r.score, e))
            res = np.array(res)
            total += 1
            picked += res[np.argmax(res[:, 0]), 1] <= res[:, 1].min() + 1e-6
    return picked / max(total, 1), total


def verifier_test(groups, views, built, seed=2):
    """Is the refined contour score a detection verifier? Positives: every instance from its
    truth moved by 5 deg / 10 mm (a good detection). Negatives, refined the same way: the same
    part moved 1.5-3 diameters sideways in the first camera's image plane with a random
    rotation (a detection on clutter or on another part), and another part of the dataset at
    the instance's true pose (the right place, the wrong part). Each set of an image is refined
    in one call (its instances hide each other, as in a scene). Returns the ROC AUC of the
    score against each kind of negative (SciPy's Mann-Whitney U / (n_pos n_neg); 0.5: chance)
    and the median scores."""
    from scipy.stats import mannwhitneyu

    objects, refiner, _ = built
    models = {o.obj_id: o for o in objects}
    ids = sorted(models)
    rng = np.random.default_rng(seed)
    scores = {"true": [], "elsewhere": [], "other part": []}
    for images, Ks, T_cw, insts in tqdm(groups, desc=f"verifier {views}v", leave=False):
        images, Ks, T_cw = images[:views], Ks[:views], T_cw[:views]
        cams = T_cw if views > 1 or not np.allclose(T_cw[0], np.eye(4)) else None
        obj = [o for o, _ in insts]
        true = [jitter(T, np.asarray(models[o].mesh.center, np.float64), 5.0, 10.0, rng)
                for o, T in insts]
        away = []
        for o, T in insts:
            d = float(models[o].mesh.diameter)
            angle = rng.uniform(0, 2 * np.pi)
            shift_cam = rng.uniform(1.5, 3.0) * d * np.array([np.cos(angle), np.sin(angle), 0])
            moved = jitter(T, np.asarray(models[o].mesh.center, np.float64), 180.0 *
                           rng.random(), 0.0, rng)
            moved[:3, 3] += T_cw[0][:3, :3].T @ shift_cam
            away.append(moved)
        other = [int(rng.choice([i for i in ids if i != o])) for o in obj]
        for key, o_ids, hyps in (("true", obj, true), ("elsewhere", obj, away),
                                 ("other part", other, [T for _, T in insts])):
            scores[key] += [r.score for r in refiner(images, Ks, cams, o_ids, hyps)]
    pos = np.asarray(scores["true"])
    out = {"median_true": float(np.median(pos))}
    for key in ("elsewhere", "other part"):
        neg = np.asarray(scores[key])
        u = mannwhitneyu(pos, neg, alternative="greater").statistic
        out[f"auc_vs_{key.replace(' ', '_')}"] = float(u / (len(pos) * len(neg)))
        out[f"median_{key.replace(' ', '_')}"] = float(np.median(neg))
    out["instances"] = len(pos)
    return out


def run_3ptr(run_dir: pathlib.Path, data: pathlib.Path, min_visib: float, rungs) -> list[dict]:
    """The rows of :func:`run` for a trained 3PT-R on the same starts (same seeds)."""
    import infer

    models = infer.load(None, refiner=run_dir, cache_dir=None)
    rows = []
    for name, views_list in (("cell", (1,)), ("rig", (1, 3))):
        ds, groups = load_groups(data / name, min_visib)
        objects = refine_objects({k: m.path for k, m in ds.models().items()})
        built = (objects, models.scene_refiner(objects), 0.0)
        for views in views_list:
            out, _ = run(name, groups, views, rungs, ContourSettings(), built)
            rows += [dict(r, evidence=f"3PT-R {run_dir}") for r in out]
    return rows


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=pathlib.Path, default=ROOT / "runs" / "contour")
    p.add_argument("--rungs", nargs="+", default=["5:10", "10:30", "20:60"])
    p.add_argument("--evidence", nargs="+", default=["both"], choices=["region", "edges", "both"])
    p.add_argument("--prior", nargs="+", type=float, default=[ContourSettings().prior],
                   help="ContourSettings.prior values to compare (the pull back to the start)")
    p.add_argument("--min-visib", type=float, default=0.5)
    p.add_argument("--no-score-test", action="store_true")
    p.add_argument("--verifier", action="store_true",
                   help="the verifier test (verifier_test): does the contour score separate "
                        "good detections from detections elsewhere and of the wrong part?")
    p.add_argument("--opencv", action="store_true",
                   help="also run OpenCV contrib's cv2.rapid trackers (RAPID, OLS, GOS) on the "
                        "same 1-view starts")
    p.add_argument("--refiner", type=pathlib.Path, default=None, metavar="RUN",
                   help="also refine the same starts with this 3PT-R run (its best checkpoint, "
                        "infer.refine.SceneRefiner: the --refiner RUN of the commands)")
    p.add_argument("--out", type=pathlib.Path, default=None)
    args = p.parse_args(argv)
    warnings.simplefilter("ignore")
    if not (args.data / "cell").exists():
        generate(args.data)
    rungs = [tuple(float(x) for x in r.split(":")) for r in args.rungs]
    table, times, scores, verifiers = [], [], [], []
    combos = [(e, q) for e in args.evidence for q in args.prior]
    cache = pathlib.Path(tempfile.mkdtemp(prefix="contour-bench-"))
    onboard = {}
    for evidence, prior in combos:
        first = (evidence, prior) == combos[0]
        settings = ContourSettings(evidence=evidence, prior=prior)
        if len(args.prior) > 1:
            evidence = f"{evidence}, prior {prior:g}"
        for name, views_list in (("cell", (1,)), ("rig", (1, 3))):
            ds, groups = load_groups(args.data / name, args.min_visib)
            built = build(ds, settings, cache / name)
            built = (*built[:2], onboard.setdefault(name, built[2]))  # the cold build's time
            for views in views_list:
                rows, t = run(name, groups, views, rungs, settings, built)
                for r in rows:
                    r["evidence"] = evidence
                t["evidence"] = evidence
                table += rows
                times.append(t)
                if args.opencv and views == 1 and first:
                    table += run_opencv(name, ds, groups, rungs)
                if args.verifier:
                    v = verifier_test(groups, views, built)
                    verifiers.append({"data": name, "views": views, "evidence": evidence, **v})
                if not args.no_score_test and views == views_list[-1]:
                    acc, n = score_test(groups, views, built)
                    scores.append({"data": name, "views": views, "evidence": evidence,
                                   "best_of_5_picked": acc, "instances": n})
    if args.refiner is not None:
        table += run_3ptr(args.refiner, args.data, args.min_visib, rungs)
    print("\n| evidence | data | views | rung | n | rotation deg start -> after (ratio) | "
          "translation mm start -> after (ratio) | MSSD AR start -> after | worse |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in table:
        print(f"| {r['evidence']} | {r['data']} | {r['views']} | {r['rung']} | {r['instances']} | "
              f"{r['rot_start']:.2f} -> {r['rot_after']:.2f} "
              f"({r['rot_after'] / r['rot_start']:.2f}) | {r['trans_start']:.1f} -> "
              f"{r['trans_after']:.1f} ({r['trans_after'] / r['trans_start']:.2f}) | "
              f"{r['ar_start']:.3f} -> {r['ar_after']:.3f} | {r['worse']:.2f} |")
    print()
    for t in times:
        print(f"{t['evidence']} {t['data']} {t['views']} view(s): first call (compile) "
              f"{t['cold_s']:.1f} s, warm {t['warm_ms_per_object_view_iter']:.2f} ms per object "
              f"per view per iteration; contour model {t['contour_model_s_per_object']:.1f} s "
              f"per object")
    for s in scores:
        print(f"score test {s['evidence']} {s['data']} {s['views']} view(s): the top score "
              f"picks the best of 5 refined poses {100 * s['best_of_5_picked']:.0f} % of "
              f"{s['instances']} instances (chance 20 %)")
    for v in verifiers:
        print(f"verifier {v['evidence']} {v['data']} {v['views']} view(s), {v['instances']} "
              f"instances: ROC AUC of the refined score, good detections against detections "
              f"elsewhere {v['auc_vs_elsewhere']:.2f}, against the wrong part at the right "
              f"place {v['auc_vs_other_part']:.2f} (0.5: chance); median scores "
              f"{v['median_true']:.3f} / {v['median_elsewhere']:.3f} / "
              f"{v['median_other_part']:.3f}")
    shutil.rmtree(cache, ignore_errors=True)
    if args.out:
        args.out.write_text(json.dumps({"table": table, "times": times, "scores": scores,
                                        "verifiers": verifiers}, indent=1))


if __name__ == "__main__":
    main()
