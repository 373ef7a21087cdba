"""The templates detector's candidates on a cell's scenes, and a cell's own score fitted on them.

What ``python -m train.templates_score`` (the shared weights, and ``--cell``) and
``python -m train.adapt`` (the cell detector's calibration, ``WORKDIR/templates_score.json``)
both need: :func:`collect` gathers every verified candidate of a BOP dataset's images with its
features and whether it is right (IoU >= 0.5 with a ground-truth box of its part), and
:func:`calibrate_cell` fits a logistic model per part on them (``train/templates_score.py``'s
docstring says what and why, with the figures). It imports inference and ``threept_jax``,
never the commands that use it.
"""

from __future__ import annotations

import pathlib
import sys

import numpy as np
from tqdm import tqdm


class TooFewCandidates(ValueError):
    """A dataset whose images give too few candidates to fit a score on (the message says
    what and how to fix it): ``train.adapt`` keeps the shared score, the command exits."""


def cell_parts(data: pathlib.Path, split_name: str):
    """A BOP dataset's split, its cell's depth range (None without a ``cell.json``) and its
    parts ``{obj_id: RefineObject}``: what a search of its images needs."""
    from infer.refine import refine_objects
    from threept_jax.data import bop

    cell = bop.load_cell(data)
    depth = None if cell is None else tuple(cell["depth_range_mm"])
    dataset = bop.BopDataset(data)
    objects = refine_objects({k: m.path for k, m in dataset.models().items()})
    return dataset.split(split_name), depth, {o.obj_id: o for o in objects}


def searched_images(data: pathlib.Path, split_name: str, per_image: bool, cache: pathlib.Path,
                    name: str, max_images: int | None = None, verifier: str | None = None):
    """Each image of the dataset's ``split_name`` (the first ``max_images``) searched by the
    templates detector of its cell's parts (``per_image``: of the parts it shows), one detector
    per set of parts: ``(detector, image, K, candidates, parts, right)`` with the candidates'
    parts (obj_id) [n] and whether each is right [n] (IoU >= 0.5 with a ground-truth box of its
    part). Images without a candidate are skipped. ``verifier``: the detector's argument."""
    from infer.shape_detect import ShapeSearchDetector
    from threept_jax.pipeline.shape_search import right_candidates

    split, depth, by_id = cell_parts(data, split_name)
    detectors = {}
    keys = [(s, im) for s in split.scene_ids for im in split.scene(s).image_ids][:max_images]
    for s, im in tqdm(keys, desc=name, leave=False):
        scene = split.scene(s)
        gt_ids = np.array([g.obj_id for g in scene.gt[im]])
        gt_box = np.array([[b[0], b[1], b[0] + b[2], b[1] + b[3]]
                           for b in (i.bbox_obj for i in scene.gt_info[im])], np.float64)
        ids = tuple(sorted(set(gt_ids.tolist())) if per_image else sorted(by_id))
        if ids not in detectors:
            detectors[ids] = ShapeSearchDetector([by_id[i] for i in ids], depth_range=depth,
                                                 cache_dir=cache, verifier=verifier)
        det = detectors[ids]
        image, K = scene.image(im), scene.cameras[im].K
        c = det.candidates(image, K)
        if c is None:
            continue
        parts = np.array([o.obj_id for o in det.objects])[c.obj]
        yield det, image, K, c, parts, right_candidates(c.xyxy, parts, gt_box, gt_ids).any(1)


def collect(data: pathlib.Path, per_image: bool, cache: pathlib.Path, name: str,
            split_name: str = "val_pbr", max_images: int | None = None,
            verifier: str | None = None):
    """Features [P, F], rightness [P], parts (obj_id) [P] and the verifier's evidence [P]
    (zeros without one) of every verified candidate of the images :func:`searched_images`
    searches."""
    rows = [(c.features, right, parts, c.evidence) for _, _, _, c, parts, right in
            searched_images(data, split_name, per_image, cache, name, max_images, verifier)]
    if not rows:
        raise TooFewCandidates(f"{data}: no image gave a candidate (no proposal or no part "
                               f"outline): check its images and meshes, or delete the folder "
                               f"to make it again")
    return tuple(np.concatenate(a) for a in zip(*rows))


#: Images a cell's calibration reads by default: on the demo's cell its first 30 training
#: images gave the held-out AP50 of all 60 (0.368 / 0.286 / 0.334 against 0.369 / 0.284 /
#: 0.343) in half the time.
CELL_IMAGES = 30


def calibrate_cell(data: pathlib.Path, split_name: str | None, cache: pathlib.Path,
                   max_images: int = CELL_IMAGES) -> dict:
    """The per-part weights of one cell's dataset (module docstring), fitted on its first
    ``max_images`` images, and its figures. A dataset that is not one exits naming the fix;
    one with too few candidates raises :class:`TooFewCandidates`."""
    from threept_jax.data import bop
    from threept_jax.pipeline.shape_search import FEATURES, MIN_PER_PART, fit_part_weights

    if not (data / "models").is_dir():
        sys.exit(f"{data} is not a BOP dataset (no models/): pass the folder that holds "
                 f"models/ and the split, e.g. a train.adapt run's WORKDIR/data/train")
    splits = [p.name for p in sorted(data.iterdir()) if p.is_dir() and p.name != "models"]
    if split_name is None:
        if len(splits) != 1:
            sys.exit(f"{data} holds the splits {splits}: name one with --split")
        split_name = splits[0]
    elif split_name not in splits:
        sys.exit(f"{data} has no split {split_name!r} (it has {splits})")
    if not bop.BopDataset(data).split(split_name).scene_ids:
        sys.exit(f"{data}/{split_name} has no scenes")
    f, r, parts, evidence = collect(data, False, cache, str(data.name), split_name, max_images)
    weights = fit_part_weights(f, r, parts, evidence=evidence)
    counts = {int(p): {"candidates": int((parts == p).sum()), "right": int(r[parts == p].sum())}
              for p in np.unique(parts)}
    for p, n in counts.items():
        kept = "its own weights" if p in weights else (
            f"the shared weights (fewer than {MIN_PER_PART} right or wrong)")
        print(f"part {p}: {n['candidates']} candidates, {n['right']} right -> {kept}")
    if not weights:
        raise TooFewCandidates(f"{data}: no part had {MIN_PER_PART} right and {MIN_PER_PART} "
                               f"wrong candidates to fit: give more images of the cell "
                               f"(train.adapt --train-scenes)")
    return {"features": [*FEATURES, "bias"], "data": str(data), "split": split_name,
            "parts": {str(p): w.tolist() for p, w in weights.items()}, "counts": counts}
