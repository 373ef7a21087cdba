"""Full-image examples for the dense cell detector (:mod:`threept_jax.models.dense`).

A cell's training images are few (tens to thousands) and reused for thousands of steps, so
they are decoded once, scaled to the network's resolution and kept in memory
(:class:`CellImages`). Each training example is a mosaic (YOLOv4, Bochkovskiy et al. 2020): four
images, each scaled by a random factor, fill the four quadrants around a random centre of the
network's canvas, so one example shows a dozen parts at new scales and cut at new places; a
share of the examples is one image at a random scale and place instead. Then a horizontal
flip, and the photometric changes of 3PT-D's pipeline
(:func:`threept_jax.data.detector_input.augment_image`). Boxes are the amodal boxes
(``bbox_obj``) clipped to the image, as the evaluation scores them; instances under 10 %
visible are left out (BOP ignores them), and so is a box cut to under a third of its area or
under 4 px by the mosaic.

Images are uint8 [H, W, 3]; boxes xyxy pixel-edge coordinates; M instances per example padded
to ``max_instances`` with ``valid`` masks.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Sequence

import cv2
import numpy as np

from threept_jax.data.detector_input import PhotometricConfig, augment_image

#: Instances less visible than this are not trained on (BOP ignores them in evaluation).
MIN_VISIBLE = 0.1
#: The padding grey of letterboxed images (YOLO's).
PAD_VALUE = 114


@dataclasses.dataclass(frozen=True)
class DenseAugment:
    """The training augmentation (module docstring). ``scale``: (lo, hi) of the random factor
    on each image, relative to the factor that fits it to the canvas: narrower than a standard
    detector's (YOLO's 0.5-1.5) because a cell's camera is fixed and a part's size in the
    image tells parts apart (two L-profiles of the demo differ mostly in length; 0.75-1.33
    raised held-out box AP50 on all three of the demo's held-out sets, docs/training.md);
    ``mosaic_prob``: share of examples that are mosaics; ``flip_prob``: horizontal flips."""

    scale: tuple[float, float] = (0.75, 1.33)
    mosaic_prob: float = 0.8
    flip_prob: float = 0.5
    photometric: PhotometricConfig = PhotometricConfig(
        brightness=0.2, contrast=0.3, saturation=0.5, hue=0.015, noise_std=0.02,
        blur_prob=0.1, blur_sigma=1.0)


def fit_scale(image_hw: tuple[int, int], canvas_hw: tuple[int, int]) -> float:
    """The factor that fits an image inside the canvas without changing its aspect."""
    return min(canvas_hw[0] / image_hw[0], canvas_hw[1] / image_hw[1])


def letterbox(image: np.ndarray, canvas_hw: tuple[int, int]) -> tuple[np.ndarray, float]:
    """uint8 [H, W, 3] -> (the image scaled to fit the canvas, top-left, padded grey, and the
    factor): a box in the canvas divided by the factor is a box in the image."""
    s = fit_scale(image.shape[:2], canvas_hw)
    h, w = (max(1, round(v * s)) for v in image.shape[:2])
    out = np.full((*canvas_hw, 3), PAD_VALUE, np.uint8)
    out[:h, :w] = cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA)
    return out, s


class CellImages:
    """A cell's training images, decoded once and kept at the canvas's scale (module
    docstring): ``images`` (uint8), ``boxes`` [Mi, 4] and ``classes`` [Mi] per image.

    ``examples``: decoded records (:func:`threept_jax.data.records.decode_example` dicts);
    ``class_ids``: obj_id of each class index, the detector's output order.
    """

    def __init__(self, examples: Sequence[dict], class_ids: Sequence[int],
                 canvas_hw: tuple[int, int]):
        self.class_ids = [int(c) for c in class_ids]
        self.canvas_hw = tuple(canvas_hw)
        index = {c: i for i, c in enumerate(self.class_ids)}
        self.images, self.boxes, self.classes = [], [], []
        for ex in examples:
            image, s = letterbox(np.asarray(ex["rgb"]), self.canvas_hw)
            h, w = np.asarray(ex["rgb"]).shape[:2]
            keep = np.asarray(ex["visib_fract"]) >= MIN_VISIBLE
            unknown = sorted({int(o) for o in np.asarray(ex["obj_id"])[keep]} - set(index))
            if unknown:
                raise ValueError(f"image (scene {int(ex['scene_id'])}, {int(ex['im_id'])}) "
                                 f"holds parts {unknown} that are not among the classes "
                                 f"{self.class_ids}: train on the cell's whole part list")
            b = np.asarray(ex["bbox_obj"], np.float32)[keep]
            b = np.clip(b, 0, [w, h, w, h]) * s
            ok = (b[:, 2] > b[:, 0]) & (b[:, 3] > b[:, 1])
            self.images.append(image[:round(h * s), :round(w * s)])
            self.boxes.append(b[ok])
            self.classes.append(np.array([index[int(o)] for o in
                                          np.asarray(ex["obj_id"])[keep][ok]], np.int32))
        if not self.images:
            raise ValueError("no training images: the records folder's split is empty")

    def __len__(self) -> int:
        return len(self.images)


def _place(canvas, boxes_out, classes_out, image, boxes, classes, s, x0, y0, clip):
    """Scale ``image`` by ``s`` and paste it with its top-left at (x0, y0) of the canvas,
    keeping the part inside ``clip`` = (cx0, cy0, cx1, cy1); boxes go along."""
    h, w = image.shape[:2]
    sw, sh = max(1, round(w * s)), max(1, round(h * s))
    cx0, cy0, cx1, cy1 = clip
    # The pasted image's region, cut to the clip rectangle.
    px0, py0 = max(cx0, x0), max(cy0, y0)
    px1, py1 = min(cx1, x0 + sw), min(cy1, y0 + sh)
    if px1 <= px0 or py1 <= py0:
        return
    m = np.array([[s, 0, x0 - px0], [0, s, y0 - py0]], np.float32)
    interp = cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR
    canvas[py0:py1, px0:px1] = cv2.warpAffine(image, m, (px1 - px0, py1 - py0), flags=interp,
                                              borderValue=(PAD_VALUE,) * 3)
    b = boxes * s + np.array([x0, y0, x0, y0], np.float32)
    area = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    c = np.clip(b, [px0, py0, px0, py0], [px1, py1, px1, py1])
    wc, hc = c[:, 2] - c[:, 0], c[:, 3] - c[:, 1]
    ok = (wc >= 4) & (hc >= 4) & (wc * hc >= area / 3)
    boxes_out.append(c[ok])
    classes_out.append(classes[ok])


def training_example(cell: CellImages, rng: np.random.Generator, aug: DenseAugment,
                     max_instances: int) -> dict[str, np.ndarray]:
    """One augmented example: ``image`` uint8 [H, W, 3], ``boxes`` [M, 4], ``classes`` [M],
    ``valid`` [M] (M = ``max_instances``; extra instances are dropped, the largest kept)."""
    H, W = cell.canvas_hw
    canvas = np.full((H, W, 3), PAD_VALUE, np.uint8)
    boxes, classes = [], []
    lo, hi = aug.scale
    if rng.random() < aug.mosaic_prob:
        xc, yc = int(rng.uniform(0.25, 0.75) * W), int(rng.uniform(0.25, 0.75) * H)
        for q, i in enumerate(rng.integers(len(cell), size=4)):
            img = cell.images[i]
            s = rng.uniform(lo, hi)
            h, w = (round(v * s) for v in img.shape[:2])
            # Each image keeps the corner that faces the centre, shifted at random.
            right, below = q % 2, q // 2
            x0 = xc - (0 if right else w) + int(rng.uniform(-0.25, 0.25) * w)
            y0 = yc - (0 if below else h) + int(rng.uniform(-0.25, 0.25) * h)
            clip = (xc if right else 0, yc if below else 0, W if right else xc, H if below else yc)
            _place(canvas, boxes, classes, img, cell.boxes[i], cell.classes[i], s, x0, y0, clip)
    else:
        i = rng.integers(len(cell))
        img = cell.images[i]
        s = rng.uniform(lo, hi)
        h, w = (round(v * s) for v in img.shape[:2])
        x0 = int(rng.uniform(min(0, W - w), max(0, W - w)))
        y0 = int(rng.uniform(min(0, H - h), max(0, H - h)))
        _place(canvas, boxes, classes, img, cell.boxes[i], cell.classes[i], s, x0, y0,
               (0, 0, W, H))
    boxes = np.concatenate(boxes) if boxes else np.zeros((0, 4), np.float32)
    classes = np.concatenate(classes) if classes else np.zeros(0, np.int32)
    if rng.random() < aug.flip_prob:
        canvas = canvas[:, ::-1]
        boxes = np.stack([W - boxes[:, 2], boxes[:, 1], W - boxes[:, 0], boxes[:, 3]], -1)
    canvas = augment_image(np.ascontiguousarray(canvas), aug.photometric, rng)
    order = np.argsort(-(boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1]))
    order = order[:max_instances]
    out_boxes = np.zeros((max_instances, 4), np.float32)
    out_classes = np.zeros(max_instances, np.int32)
    valid = np.zeros(max_instances, bool)
    out_boxes[:len(order)] = boxes[order]
    out_classes[:len(order)] = classes[order]
    valid[:len(order)] = True
    return {"image": canvas, "boxes": out_boxes, "classes": out_classes, "valid": valid}


def training_batches(cell: CellImages, batch_size: int, seed: int, aug: DenseAugment,
                     max_instances: int, start: int = 0) -> Iterator[dict[str, np.ndarray]]:
    """Endless stacked batches; batch n is drawn from a generator keyed by (seed, n), so a run
    resumed at step ``start`` sees the batches it would have seen."""
    n = start
    while True:
        rng = np.random.default_rng([seed, n])
        items = [training_example(cell, rng, aug, max_instances) for _ in range(batch_size)]
        yield {k: np.stack([x[k] for x in items]) for k in items[0]}
        n += 1
