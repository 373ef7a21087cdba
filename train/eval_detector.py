"""Periodic evaluation of 3PT-D on held-out tiles (val split: meshes training never saw).

Each evaluation example is one tile of a val record queried with one object (the same
:class:`~threept_jax.data.detector_input.SampleTile` as training, with its own fixed seed, no
photometric augmentation, and negative queries at the training rate), so the set is the
same at every evaluation. For each val object the prior tokens and the template bank
(``eval.num_templates`` templates of its render bank, all by default) are embedded once per
evaluation. Per tile the detector's patches are scored with ``patch_scores`` (presence x best
template match), decoded with ``boxes_to_pixels`` and reduced by NMS to
``eval.max_detections``; each kept detection carries its top template.

Metrics (``eval/...``):

* ``ap``, ``ap50``, ``ap75``: COCO box AP with the BOP ignore rule
  (:func:`threept_jax.eval.coco.evaluate_coco`), every tile an image whose ground truth is the
  queried object's instances in it (those under ``data.min_target_visib`` visible are
  ignored), categories = object ids.
* ``orientation_acc``: among detections matched one-to-one to a ground truth at IoU >=
  ``eval.match_iou`` (greedy by score), the share whose top template is within
  ``eval.orientation_threshold_deg`` (15) degrees of the object-centred ground-truth rotation
  up to the object's symmetries: min_s angle(R_template, R_gt S_s).
* ``orientation_oracle``: the same share for the best template of the evaluated set (the
  ceiling the template grid allows), ``num_gt``, ``num_matched``.
"""

from __future__ import annotations

from collections.abc import Mapping

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
from flax import nnx

from threept_jax.data.banks import BankFile, ObjectEntry, resize_renders
from threept_jax.data.bop import Detection2D
from threept_jax.data.detector_input import BankCache, detection_dataset
from threept_jax.eval.coco import evaluate_coco
from threept_jax.geometry.boxes import box_iou, nms
from threept_jax.geometry.symmetry import symmetric_angle_deg
from threept_jax.models.detector import boxes_to_pixels, orientation_scores, patch_scores
from train import sharding
from train.run_config import example_config, model_config

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


class DetectorEvaluator:
    """``evaluator(params) -> metrics`` on a fixed set of val tiles (module docstring)."""

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
            scores = patch_scores(out["presence_logits"], out["detection_logits"])  # [B, P]
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
            p = resize_renders(bank.priors(), size)[None]
            t = resize_renders(bank.templates(self.template_ids[int(o)]), size)[None]
            priors.append(self._embed_object(params, p)[0])
            banks.append(self._embed_templates(params, t)[0])
        return jnp.stack(priors), jnp.stack(banks)

    # -- metrics -------------------------------------------------------------------------

    def __call__(self, params) -> dict[str, float]:
        e = self.config.eval
        return compute_metrics(
            self.detections(params), self.obj_ids,
            {int(o): self.banks.get(int(o)).template_rotations[t]
             for o, t in self.template_ids.items()},
            {int(o): self.banks.get(int(o)).symmetries for o in self.obj_ids}, self.tile,
            float(e.orientation_threshold_deg), float(e.match_iou))

    def detections(self, params) -> dict[str, np.ndarray]:
        """Kept detections and ground truth of every evaluated tile (``compute_metrics``'s
        ``res``), gathered on every process."""
        prior_all, bank_all = self._object_banks(params)
        outputs = []
        for local in self._local_batches():
            batch = sharding.global_batch(local, self.mesh)
            out = self._detect(params, batch, prior_all, bank_all)
            # Outputs are replicated: every process reads its own full copy.
            outputs.append(jax.tree.map(lambda x: np.asarray(x.addressable_data(0)), out))
        return {k: np.concatenate([o[k] for o in outputs]) for k in outputs[0]}


def compute_metrics(res: Mapping[str, np.ndarray], obj_ids: np.ndarray,
                    template_rotations: Mapping[int, np.ndarray],
                    symmetries: Mapping[int, np.ndarray], tile: int, threshold_deg: float,
                    match_iou: float) -> dict[str, float]:
    """Metrics of the module docstring from gathered per-tile results.

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
    return {
        "eval/ap": coco["ap"], "eval/ap50": coco["ap50"], "eval/ap75": coco["ap75"],
        "eval/orientation_acc": correct / matched if matched else 0.0,
        "eval/orientation_oracle": oracle / matched if matched else 0.0,
        "eval/num_gt": float(num_gt), "eval/num_matched": float(matched),
    }
