"""Periodic evaluation of 3PT-D on held-out data (val split: meshes training never saw).

**Full images (the headline and the best-checkpoint metric).** The first ``eval.num_images``
val records are detected the way inference detects them
(:class:`threept_jax.pipeline.detection.FullImageDetector`: pan-and-scan at
``eval.num_scales`` scales (``pan_and_scan.plan_layout``), or, for records of a robot cell
(``cell.json``, ``datagen --layout cell``), the scales of its depth range, every val object queried in every
tile, one NMS across tiles, scales and objects, ``eval.max_detections`` per image, no score threshold), with each
val object's prior tokens and template bank (``eval.num_templates`` templates of its render
bank, all by default) embedded once per evaluation. Metrics:

* ``eval/ap``, ``eval/ap50``, ``eval/ap75``: COCO box AP with the BOP ignore rule
  (:func:`threept_jax.eval.coco.evaluate_coco`) of the inference score
  (``detection.DEFAULT_SCORE_MODE``); ground truth: every instance with a visible pixel, its
  amodal box, ignored under 10 % visible; categories: the val objects.
* ``eval/ap50_<mode>`` for each score mode of ``detection.SCORE_MODES`` (``product``:
  presence x best template match, ``presence``, ``template``: the best template match alone),
  from the same forward pass.
* ``eval/bop6d_ap``, ``eval/bop6d_ap_mssd``, ``eval/bop6d_ap_mspd``: BOP 6D detection AP
  (:func:`threept_jax.eval.bop6d.evaluate_poses`) of the best single-view hypothesis of each
  detection (object generation alone, no refinement), when ``objects.json`` gives every val
  object's mesh (``datagen.pack`` writes it); otherwise they are left out with a warning.
* ``eval/num_images``, ``eval/num_gt`` (GT counted, not ignored).

**Tiles (a diagnostic, never the headline).** ``eval/tile_diagnostic/...``: ``eval.num_examples``
val tiles cut as for training (:class:`~threept_jax.data.detector_input.SampleTile`, each crop
anchored on a ground-truth instance at the training scale, each tile queried with one
object, a fixed seed, no photometric augmentation), so they say how the model does where
training puts objects, not how it finds them. Per tile the patches are scored with
``detection_scores`` (the default mode), decoded with ``boxes_to_pixels`` and reduced by NMS to
``eval.max_detections``; each kept detection carries its top template.

* ``ap``, ``ap50``, ``ap75``: COCO box AP with the BOP ignore rule, every tile an image whose
  ground truth is the queried object's instances in it (those under ``data.min_target_visib``
  visible are ignored), categories = object ids.
* ``orientation_acc``: among detections matched one-to-one to a ground truth at IoU >=
  ``eval.match_iou`` (greedy by score), the share whose top template is within
  ``eval.orientation_threshold_deg`` (15) degrees of the object-centred ground-truth rotation
  up to the object's symmetries: min_s angle(R_template, R_gt S_s).
* ``orientation_oracle``: the same share for the best template of the evaluated set (the
  ceiling the template grid allows), ``num_gt``, ``num_matched``.
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
import warnings
from collections.abc import Mapping, Sequence

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
from flax import nnx

from threept_jax.data import records
from threept_jax.data.banks import BankFile, ObjectEntry, check_render_size
from threept_jax.data.bop import Detection2D, GtInfo, GtInstance, PoseEstimate, Target, load_cell
from threept_jax.data.detector_input import BankCache, detection_dataset, find_shards
from threept_jax.eval.bop6d import ImageGt, evaluate_poses
from threept_jax.eval.coco import evaluate_coco
from threept_jax.eval.pose_error import PreparedModel, prepare_model
from threept_jax.geometry.boxes import box_iou, nms
from threept_jax.geometry.symmetry import symmetric_angle_deg
from threept_jax.models.detector import boxes_to_pixels, detection_scores, orientation_scores
from threept_jax.pipeline.detection import (
    DEFAULT_SCORE_MODE,
    SCORE_MODES,
    DetectionSettings,
    FullImageDetector,
    ObjectQueries,
    model_points,
)
from threept_jax.pipeline.pan_and_scan import projected_size_range
from threept_jax.render.mesh import read_trimesh
from train import sharding
from train.run_config import example_config, model_config

#: Prefix of the tile metrics (a diagnostic: crops anchored on an instance at training scale).
TILE_PREFIX = "eval/tile_diagnostic/"

#: Eval batch fields sent to the device (and returned, so hosts see them in global order).
EVAL_FIELDS = ("image", "obj_index", "boxes", "mask", "ignore", "rotations", "valid")


def greedy_match(det_boxes: np.ndarray, det_scores: np.ndarray, gt_boxes: np.ndarray,
                 iou_threshold: float) -> np.ndarray:
    """[D] index of the ground truth each detection is matched to (-1: none), one-to-one,
    detections in decreasing score order taking the free ground truth of highest IoU."""
    match = np.full(len(det_boxes), -1, np.int64)
    if not len(det_boxes) or not len(gt_boxes):
        return match
    iou = np.asarray(box_iou(det_boxes, gt_boxes))
    free = np.ones(len(gt_boxes), bool)
    for d in np.argsort(-det_scores, kind="stable"):
        cand = np.where(free, iou[d], -1.0)
        g = int(np.argmax(cand))
        if cand[g] >= iou_threshold:
            match[d] = g
            free[g] = False
    return match


@dataclasses.dataclass(frozen=True, eq=False)
class HeldOutImage:
    """One full val image and its ground truth, keyed (0, record index) in the evaluators.

    ``coco_gt``: annotations of :func:`threept_jax.eval.coco.evaluate_coco` (instances with a
    visible pixel: amodal box, visible area, ``bop_ignore`` under 10 % visible); ``pose_gt``:
    :class:`~threept_jax.eval.bop6d.ImageGt` (every instance)."""

    key: tuple[int, int]
    rgb: np.ndarray
    K: np.ndarray
    coco_gt: list[dict]
    pose_gt: ImageGt

    @property
    def size(self) -> tuple[int, int]:
        """(width, height)."""
        return int(self.rgb.shape[1]), int(self.rgb.shape[0])


def held_out_image(example: Mapping[str, np.ndarray], index: int) -> HeldOutImage:
    """A :class:`HeldOutImage` from a decoded record (``threept_jax.data.records``)."""
    obj_ids = np.asarray(example["obj_id"]).reshape(-1)
    m = len(obj_ids)
    px_visib = np.bincount(np.asarray(example["instances"]).ravel(), minlength=m + 1)[1:m + 1]
    coco_gt, gts, infos = [], [], []
    for i in range(m):
        x0, y0, x1, y1 = (float(v) for v in example["bbox_obj"][i])
        v0, v1, v2, v3 = (float(v) for v in example["bbox_visib"][i])
        visib = float(example["visib_fract"][i])
        if px_visib[i] >= 1:
            coco_gt.append({"category_id": int(obj_ids[i]), "iscrowd": 0,
                            "area": float(px_visib[i]), "bbox": [x0, y0, x1 - x0, y1 - y0],
                            "bop_ignore": int(visib < 0.1)})
        gts.append(GtInstance(int(obj_ids[i]), np.asarray(example["T_cam_obj"][i], np.float64)))
        infos.append(GtInfo((round(x0), round(y0), round(x1 - x0), round(y1 - y0)),
                            (round(v0), round(v1), round(v2 - v0), round(v3 - v1)),
                            0, 0, int(px_visib[i]), visib))
    rgb = np.asarray(example["rgb"])
    K = np.asarray(example["K"], np.float64)
    return HeldOutImage((0, int(index)), rgb, K, coco_gt,
                        ImageGt(K, int(rgb.shape[1]), gts, infos))


def read_held_out_images(records_dir, num_images: int) -> list[HeldOutImage]:
    """The first ``num_images`` records of ``<records_dir>/val`` (all when fewer)."""
    from array_record.python.array_record_data_source import ArrayRecordDataSource

    source = ArrayRecordDataSource(find_shards(records_dir, "val"))
    return [held_out_image(records.decode_example(source[i]), i)
            for i in range(min(int(num_images), len(source)))]


def object_meshes(records_dir, obj_ids: Sequence[int]) -> dict[int, pathlib.Path] | None:
    """obj_id -> mesh file of each of ``obj_ids`` from ``objects.json``'s ``mesh`` entries
    (``datagen.pack`` writes them, relative to the records folder, in mm as BOP models are),
    or None when one lacks it."""
    path = pathlib.Path(records_dir) / "objects.json"
    raw = json.loads(path.read_text())
    out = {}
    for o in obj_ids:
        mesh = raw.get(str(int(o)), {}).get("mesh")
        if not mesh or not (path.parent / mesh).is_file():
            return None
        out[int(o)] = path.parent / mesh
    return out


def full_image_metrics(outputs: Sequence[Mapping[str, Mapping[str, np.ndarray]]],
                       images: Sequence[HeldOutImage], obj_ids: Sequence[int],
                       models: Mapping[int, PreparedModel] | None = None) -> dict[str, float]:
    """Full-image metrics of the module docstring.

    ``outputs[i][mode]``: the detections of ``images[i]`` for each score mode, as
    :func:`threept_jax.pipeline.detection.detection_function` returns them (``boxes`` [D, 4]
    xyxy, ``scores`` [D], ``valid`` [D], ``object`` [D] index into ``obj_ids`` and, for the
    6D AP, ``poses`` [D, K, 4, 4]). ``models``: obj_id -> prepared model, None skips 6D AP.
    """
    obj_ids = [int(o) for o in obj_ids]
    order = [im.key for im in images]
    gt = {im.key: im.coco_gt for im in images}
    sizes = {im.key: im.size for im in images}
    metrics: dict[str, float] = {}
    modes = list(outputs[0]) if outputs else [DEFAULT_SCORE_MODE]
    for mode in modes:
        dets = []
        for im, out in zip(images, outputs, strict=True):
            o = out[mode]
            for i in np.flatnonzero(o["valid"]):
                x0, y0, x1, y1 = (float(v) for v in o["boxes"][i])
                dets.append(Detection2D(*im.key, obj_ids[int(o["object"][i])],
                                        float(o["scores"][i]), bbox=(x0, y0, x1 - x0, y1 - y0)))
        coco = evaluate_coco(dets, gt, sizes, order, obj_ids, iou_types=("bbox",)).get(
            "bbox", {"ap": 0.0, "ap50": 0.0, "ap75": 0.0})
        metrics[f"eval/ap50_{mode}"] = coco["ap50"]
        if mode == DEFAULT_SCORE_MODE:
            metrics.update({"eval/ap": coco["ap"], "eval/ap50": coco["ap50"],
                            "eval/ap75": coco["ap75"]})
    metrics["eval/num_images"] = float(len(images))
    metrics["eval/num_gt"] = float(sum(1 for im in images for a in im.coco_gt
                                       if not a["bop_ignore"] and a["category_id"] in obj_ids))
    if models is not None:
        estimates, targets = [], []
        for im, out in zip(images, outputs, strict=True):
            o = out[DEFAULT_SCORE_MODE]
            for i in np.flatnonzero(o["valid"]):
                T = np.asarray(o["poses"][i][0], np.float64)
                estimates.append(PoseEstimate(*im.key, obj_ids[int(o["object"][i])],
                                              float(o["scores"][i]), T[:3, :3], T[:3, 3]))
            targets += [Target(*im.key, obj, sum(g.obj_id == obj for g in im.pose_gt.gts))
                        for obj in dict.fromkeys(g.obj_id for g in im.pose_gt.gts)]
        scores = evaluate_poses(estimates, {im.key: im.pose_gt for im in images}, models,
                                targets, compute_ar=False)
        metrics.update({"eval/bop6d_ap": scores.ap, "eval/bop6d_ap_mssd": scores.ap_mssd,
                        "eval/bop6d_ap_mspd": scores.ap_mspd})
    return metrics


class DetectorEvaluator:
    """``evaluator(params) -> metrics`` on fixed val images and tiles (module docstring)."""

    def __init__(self, config: ml_collections.ConfigDict, graphdef: nnx.GraphDef,
                 mesh: jax.sharding.Mesh, table: Mapping[int, ObjectEntry]):
        self.config = config
        self.graphdef = graphdef
        self.mesh = mesh
        e = config.eval
        self.batch = int(e.batch_size)
        self.local_batch = sharding.check_batch_size(self.batch, mesh, "eval.batch_size")
        self.num_examples = int(e.num_examples)
        if self.num_examples < 1:
            raise ValueError(f"eval.num_examples must be >= 1, got {self.num_examples}")
        # Every process evaluates the same number of batches (the device calls are
        # collective); rows past its share of num_examples are marked invalid.
        self.local_examples = -(-self.num_examples // jax.process_count())
        self.num_batches = -(-self.local_examples // self.local_batch)
        model_cfg = model_config(config)
        self.tile = int(model_cfg.image_size)
        self.render_size = int(model_cfg.render_size)
        ids = [k for k, v in table.items() if v.split in (None, "val")]
        self.obj_ids = np.asarray(sorted(ids), np.int64)
        self.obj_index = {int(o): i for i, o in enumerate(self.obj_ids)}
        self.banks = BankCache(table)
        self.dataset = detection_dataset(
            config.data_dir, "val", example_config(config, split="val", num_templates=0),
            seed=e.seed, batch_size=None, photometric=None, shuffle=False, repeat=True,
            process_index=jax.process_index(), process_count=jax.process_count(), table=table)
        self.template_ids = self._template_subset()
        self._build_functions()
        self.images = read_held_out_images(config.data_dir, int(e.num_images))
        cell = load_cell(config.data_dir)
        self.depth_range = None if cell is None else tuple(cell["depth_range_mm"])
        meshes = object_meshes(config.data_dir, self.obj_ids)
        if meshes is None:
            warnings.warn(
                f"{config.data_dir}/objects.json gives no mesh for some val objects (datagen.pack "
                "writes them); the evaluation reports no 6D AP", stacklevel=2)
        self.models = None if meshes is None else {
            o: prepare_model(points=np.asarray(read_trimesh(path).vertices),
                             symmetries=self.banks.entry(o).symmetries,
                             diameter=self.banks.entry(o).diameter)
            for o, path in meshes.items()}
        self._points = None if meshes is None else jnp.stack(
            [model_points(m.points) for m in self.models.values()])
        self.image_detector = FullImageDetector(
            graphdef, self.tile, DetectionSettings(
                score_threshold=0.0, nms_iou=float(e.nms_iou),
                max_detections=int(e.max_detections),
                candidates_per_object=int(e.candidates_per_object), num_hypotheses=1,
                score_modes=SCORE_MODES, generate_objects=meshes is not None),
            # A cell's records know the depth range: the scales it implies, as inference uses.
            num_scales=None if self.depth_range else int(e.num_scales),
            jit_kwargs={"out_shardings": sharding.replicated(mesh)})

    def _template_subset(self) -> dict[int, np.ndarray]:
        """Template indices evaluated per object: all, or a fixed random subset."""
        n = int(self.config.eval.num_templates)
        out = {}
        for o in self.obj_ids:
            total = self.banks.get(o).num_templates
            if n < 0 or n >= total:
                out[int(o)] = np.arange(total)
            else:
                rng = np.random.default_rng(int(self.config.eval.seed) * 7919 + int(o))
                out[int(o)] = np.sort(rng.choice(total, n, replace=False))
        sizes = {len(v) for v in out.values()}
        if len(sizes) > 1:
            raise ValueError(
                f"val banks hold different template counts {sorted(sizes)}; set "
                f"--config.eval.num_templates to at most {min(sizes)} so every object is "
                "evaluated against the same number of templates")
        return out

    def _build_functions(self) -> None:
        graphdef = self.graphdef
        e = self.config.eval
        chunk = int(e.template_chunk)
        max_det, iou_thr = int(e.max_detections), float(e.nms_iou)
        tile = self.tile
        rep = sharding.replicated(self.mesh)

        def embed_object(params, priors):  # [1, 12, h, w, 3] -> [1, Np, D]
            return nnx.merge(graphdef, params).embed_object(priors)

        def embed_templates(params, renders):  # [1, T, h, w, 3] -> [1, T, E]
            model = nnx.merge(graphdef, params)
            return model.embed_templates(renders, chunk_size=chunk)

        def detect(params, batch, prior_all, bank_all):
            model = nnx.merge(graphdef, params)
            prior = prior_all[batch["obj_index"]]
            bank = bank_all[batch["obj_index"]]
            out = model(batch["image"], prior, bank)
            scores = detection_scores(out["presence_logits"], out["detection_logits"],
                                      DEFAULT_SCORE_MODE)  # [B, P]
            boxes = boxes_to_pixels(out["boxes"], (tile, tile))  # [B, P, 4]
            keep, ok = jax.vmap(lambda b, s: nms(b, s, iou_thr, max_det))(boxes, scores)

            def take(x):  # [B, P, ...] -> [B, K, ...] at the kept patches
                return jnp.take_along_axis(x, keep.reshape(*keep.shape, *[1] * (x.ndim - 2)),
                                           axis=1)

            emb = take(out["embeddings"])  # [B, K, E]
            top = jnp.argmax(orientation_scores(emb, bank), axis=-1)  # [B, K]
            result = {"det_boxes": take(boxes), "det_scores": take(scores[..., None])[..., 0],
                      "det_valid": ok, "det_template": top.astype(jnp.int32)}
            result.update({f"gt_{k}": v for k, v in batch.items()})
            return result

        self._embed_object = jax.jit(embed_object, out_shardings=rep)
        self._embed_templates = jax.jit(embed_templates, out_shardings=rep)
        self._detect = jax.jit(detect, out_shardings=rep)

    # -- data ----------------------------------------------------------------------------

    def _local_batches(self):
        """Fixed number of per-process batches; rows past the example count are invalid."""
        for b in range(self.num_batches):
            rows = []
            for i in range(b * self.local_batch, (b + 1) * self.local_batch):
                ex = self.dataset[i]
                rows.append({
                    "image": ex["image"], "boxes": ex["boxes"], "mask": ex["mask"],
                    "ignore": ex["ignore"], "rotations": ex["rotations"],
                    "obj_index": np.int32(self.obj_index[int(ex["obj_id"])]),
                    "valid": np.bool_(i < self.local_examples),
                })
            yield {k: np.stack([r[k] for r in rows]) for k in EVAL_FIELDS}

    def _object_banks(self, params):
        priors, banks = [], []
        size = self.render_size
        for o in self.obj_ids:
            bank: BankFile = self.banks.get(int(o))
            p = check_render_size(bank.priors(), size, str(bank.path))[None]
            t = check_render_size(bank.templates(self.template_ids[int(o)]), size,
                                  str(bank.path))[None]
            priors.append(self._embed_object(params, p)[0])
            banks.append(self._embed_templates(params, t)[0])
        return jnp.stack(priors), jnp.stack(banks)

    # -- metrics -------------------------------------------------------------------------

    def __call__(self, params) -> dict[str, float]:
        e = self.config.eval
        banks = self._object_banks(params)
        metrics = full_image_metrics(self.image_detections(params, banks), self.images,
                                     self.obj_ids, self.models)
        return metrics | compute_metrics(
            self.detections(params, banks), self.obj_ids,
            {int(o): self.banks.get(int(o)).template_rotations[t]
             for o, t in self.template_ids.items()},
            {int(o): self.banks.get(int(o)).symmetries for o in self.obj_ids}, self.tile,
            float(e.orientation_threshold_deg), float(e.match_iou))

    def image_detections(self, params, banks=None) -> list[dict[str, dict[str, np.ndarray]]]:
        """Per held-out image, the detections of each score mode (``full_image_metrics``'s
        ``outputs``), on every process. ``banks``: ``_object_banks(params)`` when known."""
        prior_all, bank_all = self._object_banks(params) if banks is None else banks
        rep = sharding.replicated(self.mesh)
        rotations = np.stack([self.banks.get(int(o)).template_rotations[self.template_ids[int(o)]]
                              for o in self.obj_ids])
        queries = ObjectQueries(prior_all, bank_all, _replicate(rotations, rep),
                                None if self._points is None else _replicate(self._points, rep))
        diameters = [self.banks.entry(int(o)).diameter for o in self.obj_ids]
        out = []
        for im in self.images:
            sizes = None if self.depth_range is None else projected_size_range(
                diameters, self.depth_range, im.K)
            res = self.image_detector(params, _replicate(im.rgb, rep),
                                      _replicate(im.K.astype(np.float32), rep), queries, sizes)
            out.append(jax.tree.map(lambda x: np.asarray(x.addressable_data(0)), res))
        return out

    def detections(self, params, banks=None) -> dict[str, np.ndarray]:
        """Kept detections and ground truth of every evaluated tile (``compute_metrics``'s
        ``res``), gathered on every process. ``banks``: ``_object_banks(params)`` when known."""
        prior_all, bank_all = self._object_banks(params) if banks is None else banks
        outputs = []
        for local in self._local_batches():
            batch = sharding.global_batch(local, self.mesh)
            out = self._detect(params, batch, prior_all, bank_all)
            # Outputs are replicated: every process reads its own full copy.
            outputs.append(jax.tree.map(lambda x: np.asarray(x.addressable_data(0)), out))
        return {k: np.concatenate([o[k] for o in outputs]) for k in outputs[0]}


def _replicate(x, rep: jax.sharding.NamedSharding) -> jax.Array:
    """A host array (the same on every process) as a global array replicated over the mesh."""
    return jax.make_array_from_process_local_data(rep, np.asarray(x))


def compute_metrics(res: Mapping[str, np.ndarray], obj_ids: np.ndarray,
                    template_rotations: Mapping[int, np.ndarray],
                    symmetries: Mapping[int, np.ndarray], tile: int, threshold_deg: float,
                    match_iou: float) -> dict[str, float]:
    """Tile metrics of the module docstring (``eval/tile_diagnostic/...``) from gathered
    per-tile results.

    ``res`` holds, for N tiles with K kept detections and M padded targets:
    ``det_boxes`` [N, K, 4] (xyxy tile pixels), ``det_scores`` [N, K], ``det_valid`` [N, K],
    ``det_template`` [N, K] (row of the object's evaluated templates), ``gt_boxes`` [N, M, 4],
    ``gt_mask`` / ``gt_ignore`` [N, M], ``gt_rotations`` [N, M, 3, 3] (object-centred),
    ``gt_obj_index`` [N] (into ``obj_ids``) and ``gt_valid`` [N]. ``template_rotations`` and
    ``symmetries`` map object ids to the evaluated templates' rotations [T, 3, 3] and the
    symmetry transforms [S, 4, 4].
    """
    detections, gt, sizes, order = [], {}, {}, []
    matched = correct = oracle = num_gt = 0
    for n in np.flatnonzero(res["gt_valid"]):
        obj = int(obj_ids[res["gt_obj_index"][n]])
        key = (int(n), 0)
        order.append(key)
        sizes[key] = (tile, tile)
        present = res["gt_mask"][n] | res["gt_ignore"][n]
        gt[key] = []
        for box, ign in zip(res["gt_boxes"][n][present], res["gt_ignore"][n][present],
                            strict=True):
            x0, y0, x1, y1 = (float(v) for v in box)
            gt[key].append({"category_id": obj, "iscrowd": 0, "area": (x1 - x0) * (y1 - y0),
                            "bbox": [x0, y0, x1 - x0, y1 - y0], "bop_ignore": int(ign)})
        ok = res["det_valid"][n]
        boxes, scores = res["det_boxes"][n][ok], res["det_scores"][n][ok]
        for box, score in zip(boxes, scores, strict=True):
            x0, y0, x1, y1 = (float(v) for v in box)
            detections.append(Detection2D(int(n), 0, obj, float(score),
                                          bbox=(x0, y0, x1 - x0, y1 - y0)))
        # Orientation of matched detections (targets only, not ignored instances).
        tgt = res["gt_mask"][n]
        num_gt += int(tgt.sum())
        match = greedy_match(boxes, scores, res["gt_boxes"][n][tgt], match_iou)
        if not (match >= 0).any():
            continue
        tmpl_R, sym = template_rotations[obj], symmetries[obj]
        gt_R = res["gt_rotations"][n][tgt][match[match >= 0]]
        top = res["det_template"][n][ok][match >= 0]
        ang = symmetric_angle_deg(tmpl_R[top], gt_R, sym)
        matched += len(ang)
        correct += int((ang <= threshold_deg).sum())
        best = np.stack([symmetric_angle_deg(tmpl_R, np.broadcast_to(r, tmpl_R.shape), sym).min()
                         for r in gt_R])
        oracle += int((best <= threshold_deg).sum())
    coco = evaluate_coco(detections, gt, sizes, order, [int(o) for o in obj_ids],
                         iou_types=("bbox",)).get("bbox", {"ap": 0.0, "ap50": 0.0,
                                                           "ap75": 0.0})
    metrics = {
        "ap": coco["ap"], "ap50": coco["ap50"], "ap75": coco["ap75"],
        "orientation_acc": correct / matched if matched else 0.0,
        "orientation_oracle": oracle / matched if matched else 0.0,
        "num_gt": float(num_gt), "num_matched": float(matched),
    }
    return {TILE_PREFIX + k: v for k, v in metrics.items()}
