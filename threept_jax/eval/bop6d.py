"""BOP 6D pose evaluation: detection AP (BOP 2024/2025) and localisation AR (BOP 2019).

What is reproduced from the BOP toolkit (github.com/thodan/bop_toolkit), and where:

Detection AP (`scripts/eval_bop24_pose.py`, `scripts/eval_calc_errors.py`,
`scripts/eval_calc_scores.py`, `bop_toolkit_lib/pose_matching.py`, `bop_toolkit_lib/score.py`):

* Estimates: the top ``max_estimates_per_image`` (100; 200 for XYZ-IBD) by score in each image,
  grouped in order of first appearance and stably sorted (`inout.load_bop_results`).
* Only target images count (``test_targets_bop24.json``; only its image set is used). In each
  target image the objects considered are those present in the GT, at any visibility
  (`inout.get_im_targets(eval_mode="detection")`); estimates of objects absent from an image's
  GT get no error and are dropped, as in `eval_calc_errors.py` (they are not false positives).
* Errors per estimate against every GT of the same object in the image: MSSD (inf when
  ``||t_e - t_g|| >= diameter``, the toolkit's sphere-overlap shortcut) and MSPD.
  MSSD is divided by the diameter (thresholds 0.05:0.05:0.50, `np.arange(0.05, 0.51, 0.05)`),
  MSPD multiplied by ``640 / image width`` (thresholds 5:5:50 px), AP-mm uses raw MSSD with
  thresholds 2:2:20 mm (`normalized_by_diameter=[]`).
* Greedy matching per image and object (`pose_matching.match_poses`): estimates in
  decreasing score (stable), each to the not-yet-matched GT with the lowest error strictly
  below the threshold (first GT on ties). All GT are matchable in detection mode.
* Scoring per object (`score.calc_pose_detection_scores`): GT with ``visib_fract < 0.1`` are
  not counted and estimates matched to them are removed; the rest are sorted by score
  (stable, in scene/image/object order of the errors) into TP/FP; recall = TP / #GT,
  precision = TP / (TP + FP); AP = mean over 101 recall points r of the maximum precision at
  recall >= r, on the curve with (0, 0) and (1, 0) appended (`score.calc_ap`).
* AP per error type = mean over objects with at least one counted GT of the mean over
  thresholds; ``ap = (ap_mssd + ap_mspd) / 2`` (``bop24_mAP``), ``ap_mm`` = AP_MSSD with the mm
  thresholds (``bop25_mAP_mm``).

Localisation AR (`scripts/eval_bop19_pose.py` with ``visib_gt_min = -1``): targets are
``test_targets_bop19.json`` (scene, image, object, inst_count); per target the top
``inst_count`` estimates by score are evaluated (no per-image cap); the valid GT of an object
are its ``inst_count`` most visible instances; matching as above but only to valid GT; recall
= matched valid GT / valid GT over the whole dataset (`score.calc_localization_scores`),
averaged over the same thresholds. Without a bop19 file, targets are derived from the GT: each
object with ``k >= 1`` instances of ``visib_fract >= 0.1`` in a target image is a target with
``inst_count = k``. VSD is not computed (it needs depth rendering; see the README).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from threept_jax.data.bop import GtInfo, GtInstance, PoseEstimate, Target
from threept_jax.eval.pose_error import PreparedModel, mspd_pairs, mssd_pairs

__all__ = [
    "ImageGt",
    "PoseScores",
    "evaluate_poses",
    "average_precision_101",
    "MSSD_THRESHOLDS",
    "MSPD_THRESHOLDS",
    "MSSD_MM_THRESHOLDS",
    "VISIB_GT_MIN",
    "gt_coverage",
    "gt_targets",
    "visible_counts",
]

MSSD_THRESHOLDS = np.arange(0.05, 0.51, 0.05)  # x diameter
MSPD_THRESHOLDS = np.arange(5, 51, 5)  # px at 640 px image width
MSSD_MM_THRESHOLDS = np.array(list(range(2, 21, 2)))  # mm
VISIB_GT_MIN = 0.1
MSPD_REFERENCE_WIDTH = 640.0


def visible_counts(gts: Sequence[GtInstance], infos: Sequence[GtInfo]) -> dict[int, int]:
    """{obj_id: its instances with ``visib_fract >= VISIB_GT_MIN``} of one image: the
    localisation targets the ground truth gives (module docstring)."""
    counts: dict[int, int] = {}
    for g, info in zip(gts, infos):
        if info.visib_fract >= VISIB_GT_MIN:
            counts[g.obj_id] = counts.get(g.obj_id, 0) + 1
    return counts


def gt_targets(split) -> list[Target]:
    """BOP19-style targets of a split (``threept_jax.data.bop.BopSplit``) derived from its
    ground truth by :func:`visible_counts`, for a dataset without ``test_targets_bop19.json``
    (write them with ``threept_jax.data.bop.write_targets``)."""
    out = []
    for sid in split.scene_ids:
        scene = split.scene(sid)
        for im_id in scene.image_ids:
            counts = visible_counts(scene.gt_as_stored.get(im_id, []), scene.gt_info.get(im_id, []))
            out += [Target(sid, im_id, o, c) for o, c in sorted(counts.items())]
    return out


def gt_coverage(split, results: Sequence[Mapping]) -> tuple[int, int, int]:
    """A detection diagnostic, not a BOP metric: (ground-truth instances at least
    ``VISIB_GT_MIN`` visible that some detection covers at box IoU >= 0.5 whatever its object,
    those that a detection of their own object covers, such instances) over a split
    (``threept_jax.data.bop.BopSplit``) and BOP 2D results (``scene_id``, ``image_id``,
    ``category_id``, ``bbox`` [x, y, w, h])."""
    from threept_jax.geometry.boxes import box_iou

    def xyxy(b):
        return [b[0], b[1], b[0] + b[2], b[1] + b[3]]

    dets: dict = {}
    for d in results:
        dets.setdefault((d["scene_id"], d["image_id"]), []).append(d)
    hit_any = hit_own = total = 0
    for sid in split.scene_ids:
        scene = split.scene(sid)
        for im_id in scene.image_ids:
            found = dets.get((sid, im_id), [])
            boxes = np.array([xyxy(d["bbox"]) for d in found], np.float32).reshape(-1, 4)
            for g, info in zip(scene.gt_as_stored[im_id], scene.gt_info[im_id]):
                if info.visib_fract < VISIB_GT_MIN:
                    continue
                total += 1
                if not found:
                    continue
                iou = np.asarray(box_iou(np.array([xyxy(info.bbox_obj)], np.float32), boxes))[0]
                hit_any += bool((iou >= 0.5).any())
                hit_own += any(iou[i] >= 0.5 and d["category_id"] == g.obj_id
                               for i, d in enumerate(found))
    return hit_any, hit_own, total


@dataclass(frozen=True, eq=False)
class ImageGt:
    """GT of one image: intrinsics K [3, 3], image width (px), instances and their info."""

    K: np.ndarray
    width: int
    gts: Sequence[GtInstance]
    infos: Sequence[GtInfo]


@dataclass
class PoseScores:
    """Scores in [0, 1]; ``per_object`` maps obj_id to the same keys."""

    ap: float
    ap_mssd: float
    ap_mspd: float
    ap_mm: float
    ar_mssd: float | None
    ar_mspd: float | None
    per_object: dict[int, dict[str, float]] = field(default_factory=dict)
    num_estimates: int = 0
    num_gt: int = 0

    def to_json(self) -> dict:
        return {
            "ap": self.ap,
            "ap_mssd": self.ap_mssd,
            "ap_mspd": self.ap_mspd,
            "ap_mm": self.ap_mm,
            "ar_mssd": self.ar_mssd,
            "ar_mspd": self.ar_mspd,
            "per_object": {str(k): v for k, v in sorted(self.per_object.items())},
            "num_estimates": self.num_estimates,
            "num_gt": self.num_gt,
        }


def average_precision_101(recall: np.ndarray, precision: np.ndarray) -> float:
    """COCO-style AP at 101 recall points exactly as `bop_toolkit_lib/score.py::calc_ap`."""
    i = np.argsort(recall)
    mrec = np.concatenate(([0], np.asarray(recall)[i], [1]))
    mpre = np.concatenate(([0], np.asarray(precision)[i], [0]))
    rts = np.linspace(0.0, 1.00, 101, endpoint=True)
    # max precision over points with recall >= rt, via a suffix maximum over sorted recall.
    order = np.argsort(mrec, kind="stable")
    srec, spre = mrec[order], mpre[order]
    suffix_max = np.maximum.accumulate(spre[::-1])[::-1]
    first = np.searchsorted(srec, rts, side="left")
    vals = np.where(first < len(srec), suffix_max[np.minimum(first, len(srec) - 1)], 0.0)
    return float(np.mean(vals))


def _greedy_match(err: np.ndarray, ths: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """`pose_matching.match_poses` for all thresholds at once.

    err [E, G] (estimates in decreasing score), ths [T] -> matched GT index [T, E] (-1: none)."""
    E, G = err.shape
    T = len(ths)
    out = np.full((T, E), -1, dtype=np.int64)
    if E == 0 or G == 0:
        return out
    if G == 1 and (valid is None or valid[0]):
        # One GT: at each threshold it goes to the first estimate below the threshold.
        ok = err[:, 0][None, :] < ths[:, None]
        has = ok.any(1)
        out[has, np.argmax(ok, axis=1)[has]] = 0
        return out
    taken = np.zeros((T, G), bool)
    if valid is not None:
        taken |= ~valid[None, :]
    rows = np.arange(T)
    for e in range(E):
        cand = (err[e][None, :] < ths[:, None]) & ~taken
        has = cand.any(1)
        if not has.any():
            continue
        best = np.argmin(np.where(cand, err[e][None, :], np.inf), axis=1)
        r = rows[has]
        out[r, e] = best[has]
        taken[r, best[has]] = True
    return out


@dataclass
class _Group:
    """Estimates (global indices, decreasing score) and GT ids of one (image, object)."""

    key: tuple[int, int]
    obj_id: int
    est: list[int]
    gt_ids: list[int]


def _ordered_images(targets: Sequence[Target]) -> list[tuple[int, int]]:
    """Target images organised like the toolkit's ``targets_org``: scenes in order of first
    appearance, then images in order of first appearance within the scene."""
    scenes: dict[int, dict[int, None]] = {}
    for t in targets:
        scenes.setdefault(t.scene_id, {})[t.im_id] = None
    return [(s, i) for s, ims in scenes.items() for i in ims]


def evaluate_poses(
    estimates: Sequence[PoseEstimate],
    images: Mapping[tuple[int, int], ImageGt],
    models: Mapping[int, PreparedModel],
    targets: Sequence[Target],
    localization_targets: Sequence[Target] | None = None,
    *,
    max_estimates_per_image: int = 100,
    compute_ar: bool = True,
) -> PoseScores:
    """Evaluate 6D estimates against GT with the BOP protocol (see the module docstring).

    ``images`` maps (scene_id, im_id) to ImageGt for at least every target image; ``models``
    maps obj_id to a PreparedModel; ``targets`` gives the image set for AP;
    ``localization_targets`` the bop19 targets for AR (derived from the GT when None)."""
    if (
        isinstance(max_estimates_per_image, bool)
        or not isinstance(max_estimates_per_image, (int, np.integer))
        or max_estimates_per_image < 1
    ):
        raise ValueError(
            f"max_estimates_per_image must be an integer >= 1, got {max_estimates_per_image!r}"
        )
    est_list = list(estimates)
    det_images = _ordered_images(targets)
    for key in det_images:
        if key not in images:
            raise ValueError(f"target image scene {key[0]} im {key[1]} has no GT in the dataset")
    for key, im in images.items():
        if not im.width > 0:
            raise ValueError(
                f"image scene {key[0]} im {key[1]}: width {im.width} px must be > 0 (it "
                "normalises MSPD to 640 px)"
            )

    # ---- estimate selection (detection): top-k per image, then per (image, object).
    by_image: dict[tuple[int, int], list[int]] = {}
    for i, e in enumerate(est_list):
        by_image.setdefault((e.scene_id, e.im_id), []).append(i)
    det_by_iobj: dict[tuple[int, int, int], list[int]] = {}
    for key, idx in by_image.items():
        kept = sorted(idx, key=lambda i: est_list[i].score, reverse=True)[:max_estimates_per_image]
        for i in kept:
            det_by_iobj.setdefault((key[0], key[1], est_list[i].obj_id), []).append(i)
    det_groups: list[_Group] = []
    for key in det_images:
        gts = images[key].gts
        for obj_id in dict.fromkeys(g.obj_id for g in gts):
            ests = det_by_iobj.get((key[0], key[1], obj_id), [])
            ests = sorted(ests, key=lambda i: est_list[i].score, reverse=True)
            det_groups.append(
                _Group(key, obj_id, ests, [j for j, g in enumerate(gts) if g.obj_id == obj_id])
            )

    # ---- estimate selection (localisation): top inst_count per (image, object) target.
    loc_groups: list[tuple[_Group, np.ndarray]] = []
    if compute_ar:
        if localization_targets is None:
            localization_targets = []
            for key in det_images:
                counts = visible_counts(images[key].gts, images[key].infos)
                localization_targets += [Target(key[0], key[1], o, c) for o, c in counts.items()]
        all_by_iobj: dict[tuple[int, int, int], list[int]] = {}
        for i, e in enumerate(est_list):
            all_by_iobj.setdefault((e.scene_id, e.im_id, e.obj_id), []).append(i)
        loc_org: dict[int, dict[int, dict[int, int]]] = {}
        for t in localization_targets:
            if t.obj_id is None or t.inst_count is None:
                raise ValueError(
                    "localisation targets need obj_id and inst_count "
                    "(test_targets_bop19.json format)"
                )
            loc_org.setdefault(t.scene_id, {}).setdefault(t.im_id, {})[t.obj_id] = t.inst_count
        for scene_id, ims in loc_org.items():
            for im_id, objs in ims.items():
                key = (scene_id, im_id)
                if key not in images:
                    raise ValueError(f"bop19 target scene {scene_id} im {im_id} has no GT")
                gts, infos = images[key].gts, images[key].infos
                by_visib = sorted(range(len(gts)), key=lambda j: infos[j].visib_fract, reverse=True)
                to_add = dict(objs)
                valid = np.zeros(len(gts), bool)
                for j in by_visib:
                    o = gts[j].obj_id
                    if to_add.get(o, 0) > 0:
                        valid[j] = True
                        to_add[o] -= 1
                for obj_id, n in objs.items():
                    ests = sorted(
                        all_by_iobj.get((scene_id, im_id, obj_id), []),
                        key=lambda i: est_list[i].score,
                        reverse=True,
                    )[:n]
                    gt_ids = [j for j, g in enumerate(gts) if g.obj_id == obj_id]
                    loc_groups.append((_Group(key, obj_id, ests, gt_ids), valid[gt_ids]))

    # ---- errors for the union of (estimate, GT) pairs, batched per object.
    pairs: dict[tuple[int, int], int] = {}
    for g in det_groups + [g for g, _ in loc_groups]:
        for i in g.est:
            for j in g.gt_ids:
                pairs.setdefault((i, j), len(pairs))
    pair_list = list(pairs)
    mssd = np.full(len(pair_list), np.inf)
    mspd = np.full(len(pair_list), np.inf)
    by_obj: dict[int, list[int]] = {}
    for n, (i, _) in enumerate(pair_list):
        by_obj.setdefault(est_list[i].obj_id, []).append(n)
    for obj_id, idx in by_obj.items():
        if obj_id not in models:
            raise ValueError(
                f"object {obj_id} has GT and estimates but no model; add "
                f"obj_{obj_id:06d}.ply and its models_info entry"
            )
        model = models[obj_id]
        idx = np.array(idx)
        R_e = np.stack([est_list[pair_list[n][0]].R for n in idx])
        t_e = np.stack([est_list[pair_list[n][0]].t for n in idx])
        gts = [
            images[(est_list[pair_list[n][0]].scene_id, est_list[pair_list[n][0]].im_id)]
            for n in idx
        ]
        R_g = np.stack([im.gts[pair_list[n][1]].R for im, n in zip(gts, idx)])
        t_g = np.stack([im.gts[pair_list[n][1]].t for im, n in zip(gts, idx)])
        K = np.stack([im.K for im in gts])
        overlap = np.linalg.norm(t_e - t_g, axis=1) < model.diameter
        if overlap.any():
            mssd[idx[overlap]] = mssd_pairs(
                R_e[overlap], t_e[overlap], R_g[overlap], t_g[overlap], model
            )
        mspd[idx] = mspd_pairs(R_e, t_e, R_g, t_g, K, model)

    def err_matrix(g: _Group, kind: str) -> np.ndarray:
        if not g.est or not g.gt_ids:
            return np.zeros((len(g.est), len(g.gt_ids)))
        n = np.array([[pairs[(i, j)] for j in g.gt_ids] for i in g.est])
        if kind == "mspd":
            return (MSPD_REFERENCE_WIDTH / images[g.key].width) * mspd[n]
        if kind == "mssd":
            return mssd[n] / models[g.obj_id].diameter
        return mssd[n]

    kinds = {"mssd": MSSD_THRESHOLDS, "mspd": MSPD_THRESHOLDS, "mm": MSSD_MM_THRESHOLDS}

    # ---- detection AP.
    obj_ids = sorted({g.obj_id for g in det_groups})
    num_gt = {o: 0 for o in obj_ids}
    for g in det_groups:
        infos = images[g.key].infos
        num_gt[g.obj_id] += sum(infos[j].visib_fract >= VISIB_GT_MIN for j in g.gt_ids)
    ap: dict[str, dict[int, float]] = {}
    num_est_counted = 0
    for kind, ths in kinds.items():
        # per object: per threshold lists of (score, is_tp) in the toolkit's order.
        rec: dict[int, list[list[tuple[float, bool]]]] = {o: [[] for _ in ths] for o in obj_ids}
        for g in det_groups:
            if not g.est:
                continue
            infos = images[g.key].infos
            visible = np.array([infos[j].visib_fract >= VISIB_GT_MIN for j in g.gt_ids], bool)
            match = _greedy_match(err_matrix(g, kind), ths)
            for t in range(len(ths)):
                for e, i in enumerate(g.est):
                    m = match[t, e]
                    if m >= 0 and not visible[m]:
                        continue
                    rec[g.obj_id][t].append((est_list[i].score, m >= 0))
        ap[kind] = {}
        for o in obj_ids:
            if num_gt[o] == 0:
                continue
            aps = []
            for t in range(len(ths)):
                items = rec[o][t]
                order = sorted(range(len(items)), key=lambda k: items[k][0], reverse=True)
                tp = np.array([items[k][1] for k in order], bool)
                tp_c = np.cumsum(tp)
                fp_c = np.cumsum(~tp)
                recall = tp_c / float(num_gt[o])
                with np.errstate(invalid="ignore", divide="ignore"):
                    precision = tp_c / (tp_c + fp_c)
                precision[~np.isfinite(precision)] = 0.0
                aps.append(average_precision_101(recall, precision))
            ap[kind][o] = float(np.mean(aps))
    for g in det_groups:
        num_est_counted += len(g.est)

    # ---- localisation AR.
    ar: dict[str, float] = {}
    ar_obj: dict[str, dict[int, float]] = {}
    if compute_ar:
        for kind in ("mssd", "mspd"):
            ths = kinds[kind]
            tps = np.zeros(len(ths))
            tars = 0
            obj_tps: dict[int, np.ndarray] = {}
            obj_tars: dict[int, int] = {}
            for g, valid in loc_groups:
                n_valid = int(valid.sum())
                tars += n_valid
                obj_tars[g.obj_id] = obj_tars.get(g.obj_id, 0) + n_valid
                obj_tps.setdefault(g.obj_id, np.zeros(len(ths)))
                if not g.est or not g.gt_ids:
                    continue
                match = _greedy_match(err_matrix(g, kind), ths, valid)
                hits = (match >= 0).sum(1)
                tps += hits
                obj_tps[g.obj_id] += hits
            ar[kind] = float(np.mean(tps / tars)) if tars else 0.0
            ar_obj[kind] = {
                o: float(np.mean(obj_tps[o] / obj_tars[o])) for o in obj_tars if obj_tars[o] > 0
            }

    def mean(d: dict[int, float]) -> float:
        return float(np.mean(list(d.values()))) if d else 0.0

    per_object = {}
    for o in obj_ids:
        if num_gt[o] == 0:
            continue
        per_object[o] = {
            "ap": 0.5 * (ap["mssd"][o] + ap["mspd"][o]),
            "ap_mssd": ap["mssd"][o],
            "ap_mspd": ap["mspd"][o],
            "ap_mm": ap["mm"][o],
            "ar_mssd": ar_obj.get("mssd", {}).get(o),
            "ar_mspd": ar_obj.get("mspd", {}).get(o),
        }
    ap_mssd, ap_mspd = mean(ap["mssd"]), mean(ap["mspd"])
    return PoseScores(
        ap=0.5 * (ap_mssd + ap_mspd),
        ap_mssd=ap_mssd,
        ap_mspd=ap_mspd,
        ap_mm=mean(ap["mm"]),
        ar_mssd=ar.get("mssd"),
        ar_mspd=ar.get("mspd"),
        per_object=per_object,
        num_estimates=num_est_counted,
        num_gt=int(sum(num_gt.values())),
    )
