"""The detector's input: a grain pipeline of 3PT-D examples, one tile queried with one object.

Built from picklable grain transforms (usable in multiprocess workers) and
:func:`detection_dataset`, which chains them over the ArrayRecord shards of a records folder
(``<records_dir>/<split>/*.array_record``, ``objects.json`` and the render banks, see
:mod:`threept_jax.data.records` and :mod:`threept_jax.data.banks`):

1. :class:`DecodeExample` - record bytes -> annotated image.
2. :class:`SampleTile` - picks the query object (an instance drawn with probability
   proportional to its ``visib_fract``; with probability ``negative_prob`` an object of the
   object table absent from the image, whose targets are all empty so presence learns "no"),
   and a square crop resized to the tile that puts the anchor instance at a size drawn
   log-uniformly from the scale prior (128-350 px on a 512 tile, scaled by ``tile / 512``;
   size = longer side of the amodal box). Targets are every instance of the query object in
   the tile: its *amodal* box, not clipped to the tile (a box may extend past the tile side,
   or below 0, as an object cut by the tile or image border does), since object generation
   reads a detection as the object's whole box (``threept_jax.pipeline.object_generation``);
   kept when the share of the object visible in the tile (``visib_fract`` x the share of its
   visible pixels inside the crop) is at least ``min_target_visib``; the others are flagged
   ``ignore`` (evaluation ignores them, as BOP ignores instances under 10 % visible).
3. :class:`AttachRenders` - the query object's 12 prior renders, its symmetries (padded) and,
   for training, ``num_templates`` templates sampled from its bank: the positive template of
   every target (nearest to the ground truth up to symmetry, in float64 against the whole
   bank) plus random negatives; ``template_index`` points at the positive within the sampled
   set, so the loss's one-hot target is exactly the bank-nearest template. Templates that are
   nearest to another symmetric equivalent of a target render like the positive and are kept
   out of the negatives.
4. :class:`PhotometricAugment` - brightness, contrast, saturation, hue, Gaussian noise and
   blur.

**Rotation convention.** Target ``rotations`` are *object-centred*:
``geometry.camera.object_centred_rotation(R_cam_obj, centre)``, the object's rotation in a virtual
camera turned to look at its bounding-sphere centre, which is how bank renders are made (see
:mod:`threept_jax.data.banks`). Cropping does not change them: a crop keeps the camera centre
and orientation, only K changes (returned as ``K``).

**Crops and pixels.** A crop of side ``c`` source pixels at (x0, y0), resized to the tile
side ``t``, maps pixel-edge coordinates by ``x' = (x - x0) * t / c`` (pixel-centre u' =
(u + 0.5 - x0) * t / c - 0.5, the map of ``geometry.camera.crop_intrinsics``); outside the
image the tile is 0 (as pan-and-scan pads). Downscaling is antialiased with a Gaussian of
sigma ``(c / t - 1) / 2`` source pixels.

Example fields (M = ``max_instances``, Nt = ``num_templates``, Ns = ``max_symmetries``):
``image`` uint8 [t, t, 3], ``K`` float32 [3, 3], ``obj_id`` int32, ``negative`` bool,
``boxes`` float32 [M, 4] (tile pixels, amodal xyxy), ``mask`` bool [M], ``ignore`` bool [M],
``rotations`` float32 [M, 3, 3], ``visib`` float32 [M], ``scene_id``, ``im_id`` int32,
``prior_rgb`` uint8 [12, h, w, 3], ``symmetries`` float32 [Ns, 4, 4], ``symmetry_mask`` bool
[Ns] and, when Nt > 0, ``template_rgb`` uint8 [Nt, h, w, 3], ``template_rotations`` float32
[Nt, 3, 3], ``template_index`` int32 [M] (0 where padded).
"""

from __future__ import annotations

import dataclasses
import pathlib
import threading
from collections.abc import Mapping

import cv2
import grain
import numpy as np

from threept_jax.data import records
from threept_jax.data.banks import BankFile, ObjectEntry, check_render_size, load_object_table
from threept_jax.geometry.camera import object_centred_rotation
from threept_jax.geometry.framing import SCALE_PRIOR, SCALE_REFERENCE_TILE
from threept_jax.geometry.symmetry import nearest_templates

__all__ = [
    "AttachRenders", "BankCache", "DecodeExample", "ExampleConfig", "PhotometricAugment",
    "PhotometricConfig", "SampleTile", "augment_image", "crop_transform", "decoded_records",
    "detection_dataset",
    "find_shards", "pad_symmetries", "warp_crop",
]


@dataclasses.dataclass(frozen=True)
class ExampleConfig:
    """How an example is cut from an annotated image (module docstring).

    Attributes:
      tile_size: side t of the square tile (the detector's ``image_size``).
      max_instances: M, targets per tile (the most visible are kept).
      num_templates: Nt templates sampled per example (0: none, as in evaluation).
      max_symmetries: Ns; objects with more symmetry transforms keep Ns evenly spaced ones
        (identity first). Positives are always computed with all of them.
      render_size: side of the bank renders, the detector's render size (``None``: as
        stored); banks of another size raise (``banks.check_render_size``): renders are never
        resized, so training sees the images inference onboarding makes.
      negative_prob: probability of querying an object absent from the image.
      scale_prior: anchor size range in pixels on a ``scale_reference`` tile.
      min_query_visib: an instance can be the query anchor when its visib_fract is at least
        this.
      min_target_visib: an instance is a target when at least this share of the object is
        visible inside the tile; smaller ones are flagged ``ignore``.
      min_box_size: instances whose box, clipped to the tile, is smaller than this (tile
        pixels) in width or height are dropped.
      split: negatives are drawn from objects of this split of the object table (all objects
        when the table has no split field).
    """

    tile_size: int = 512
    max_instances: int = 16
    num_templates: int = 64
    max_symmetries: int = 64
    render_size: int | None = None
    negative_prob: float = 0.2
    scale_prior: tuple[float, float] = SCALE_PRIOR
    scale_reference: int = SCALE_REFERENCE_TILE
    min_query_visib: float = 0.1
    min_target_visib: float = 0.1
    min_box_size: float = 2.0
    split: str | None = None

    def __post_init__(self):
        object.__setattr__(self, "scale_prior", tuple(float(v) for v in self.scale_prior))
        if self.tile_size < 8:
            raise ValueError(f"tile_size must be >= 8, got {self.tile_size}")
        for name in ("max_instances", "max_symmetries"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.num_templates < 0:
            raise ValueError(f"num_templates must be >= 0, got {self.num_templates}")
        if self.num_templates and self.num_templates < self.max_instances:
            raise ValueError(
                f"num_templates={self.num_templates} cannot hold the positive templates of "
                f"max_instances={self.max_instances} targets; raise num_templates")
        if not 0.0 <= self.negative_prob < 1.0:
            raise ValueError(f"negative_prob must be in [0, 1), got {self.negative_prob}")
        lo, hi = self.scale_prior
        if not 0 < lo <= hi:
            raise ValueError(f"scale_prior must be (lo, hi) with 0 < lo <= hi, got "
                             f"{self.scale_prior}")

    @property
    def size_range(self) -> tuple[float, float]:
        """Anchor size range on this tile, in tile pixels."""
        f = self.tile_size / self.scale_reference
        return self.scale_prior[0] * f, self.scale_prior[1] * f


@dataclasses.dataclass(frozen=True)
class PhotometricConfig:
    """Strengths of :class:`PhotometricAugment` (image values in [0, 1]).

    brightness: additive delta ~ U(-b, b); contrast and saturation: factors ~ U(1 - x, 1 + x)
    about the image mean and the grey level; hue: shift ~ U(-h, h) turns; noise_std: the
    Gaussian noise sigma ~ U(0, noise_std); blur: with probability blur_prob, a Gaussian blur
    of sigma ~ U(0.3, blur_sigma) pixels. Zeros everywhere leave the image unchanged.
    """

    brightness: float = 0.15
    contrast: float = 0.3
    saturation: float = 0.3
    hue: float = 0.03
    noise_std: float = 0.03
    blur_prob: float = 0.2
    blur_sigma: float = 1.2


# --------------------------------------------------------------------------- banks


class BankCache:
    """obj_id -> :class:`BankFile`, opened lazily and shared by the transforms of a worker.

    Picklable (handles are reopened in the process that uses them) and thread-safe.
    """

    def __init__(self, table: Mapping[int, ObjectEntry]):
        self.table = dict(table)
        self._files: dict[int, BankFile] = {}
        self._lock = threading.Lock()

    def __getstate__(self):
        return {"table": self.table}

    def __setstate__(self, state):
        self.__init__(state["table"])

    def entry(self, obj_id: int) -> ObjectEntry:
        try:
            return self.table[int(obj_id)]
        except KeyError:
            raise KeyError(
                f"object {int(obj_id)} is used by a record but missing from objects.json; "
                "re-run `python -m datagen.pack` so the object table lists every object of the "
                "shards") from None

    def get(self, obj_id: int) -> BankFile:
        obj_id = int(obj_id)
        bank = self._files.get(obj_id)
        if bank is None:
            bank = BankFile(self.entry(obj_id).bank_path)
            if bank.obj_id != obj_id:
                raise ValueError(f"{bank.path} holds object {bank.obj_id}, but objects.json "
                                 f"lists it for object {obj_id}; fix the table's bank path")
            with self._lock:
                self._files[obj_id] = bank
        return bank


# --------------------------------------------------------------------------- transforms


class DecodeExample(grain.transforms.Map):
    """Record bytes -> example dict (:func:`threept_jax.data.records.decode_example`)."""

    def map(self, element):
        return records.decode_example(element)


def _log_uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi)))) if hi > lo else float(lo)


def _interval_sample(rng, lo: float, hi: float, bound_lo: float, bound_hi: float) -> float:
    """U(lo, hi), restricted to [bound_lo, bound_hi] when the two intervals meet."""
    a, b = max(lo, bound_lo), min(hi, bound_hi)
    if a <= b:
        lo, hi = a, b
    return float(rng.uniform(lo, hi)) if hi > lo else float(lo)


def crop_transform(x0: float, y0: float, side: float, tile: int) -> np.ndarray:
    """[3, 3] float64 pixel-centre affine of a crop (x0, y0, side) resized to ``tile``."""
    z = tile / side
    return np.array([[z, 0.0, (0.5 - x0) * z - 0.5], [0.0, z, (0.5 - y0) * z - 0.5],
                     [0.0, 0.0, 1.0]])


def warp_crop(image: np.ndarray, x0: float, y0: float, side: float, tile: int) -> np.ndarray:
    """uint8 [H, W, 3] -> the crop (x0, y0, side) resized to uint8 [tile, tile, 3].

    Bilinear with a Gaussian prefilter of sigma (side / tile - 1) / 2 when shrinking; zeros
    outside the image.
    """
    h, w = image.shape[:2]
    shrink = side / tile
    sigma = max(0.0, (shrink - 1.0) / 2.0)
    pad = int(np.ceil(3 * sigma)) + 2
    # Work on the source window the crop touches (plus the filter's support) only.
    wx0 = int(np.clip(np.floor(x0) - pad, 0, w))
    wy0 = int(np.clip(np.floor(y0) - pad, 0, h))
    wx1 = int(np.clip(np.ceil(x0 + side) + pad, 0, w))
    wy1 = int(np.clip(np.ceil(y0 + side) + pad, 0, h))
    if wx1 <= wx0 or wy1 <= wy0:
        return np.zeros((tile, tile, 3), np.uint8)
    window = image[wy0:wy1, wx0:wx1]
    if sigma > 0.05:
        window = cv2.GaussianBlur(window, (0, 0), sigmaX=sigma, sigmaY=sigma,
                                  borderType=cv2.BORDER_REPLICATE)
    A = crop_transform(x0 - wx0, y0 - wy0, side, tile)[:2]
    return cv2.warpAffine(np.ascontiguousarray(window), A, (tile, tile), flags=cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0))


def _pixels_inside(instances: np.ndarray, x0: float, y0: float, side: float, m: int) -> np.ndarray:
    """[m] visible pixel count of each instance whose pixel centre lies inside the crop."""
    h, w = instances.shape
    # Column j has its centre at edge coordinate j + 0.5: inside when x0 <= j + 0.5 < x0 + side.
    c0 = int(np.clip(np.ceil(x0 - 0.5), 0, w))
    c1 = int(np.clip(np.ceil(x0 + side - 0.5), 0, w))
    r0 = int(np.clip(np.ceil(y0 - 0.5), 0, h))
    r1 = int(np.clip(np.ceil(y0 + side - 0.5), 0, h))
    counts = np.bincount(instances[r0:r1, c0:c1].ravel(), minlength=m + 1)
    return counts[1:m + 1]


class SampleTile(grain.transforms.RandomMap):
    """Query object, crop to the scale prior and tile targets (module docstring, step 2)."""

    def __init__(self, config: ExampleConfig, banks: BankCache):
        self.config = config
        self.banks = banks
        ids = [k for k, e in banks.table.items() if config.split is None or e.split in
               (None, config.split)]
        if not ids:
            raise ValueError(
                f"objects.json lists no object of split {config.split!r}; give the table's "
                "objects a 'split' field (`python -m datagen.pack --split-label`) or none at all")
        self.negative_pool = np.asarray(sorted(ids), np.int64)

    def _choose_query(self, ex, rng):
        cfg = self.config
        obj_ids = np.asarray(ex["obj_id"], np.int64)
        visib = np.asarray(ex["visib_fract"], np.float64)
        cand = np.flatnonzero(visib >= cfg.min_query_visib)
        negatives = np.setdiff1d(self.negative_pool, obj_ids)
        want_negative = rng.random() < cfg.negative_prob
        if (want_negative or cand.size == 0) and negatives.size:
            query = int(rng.choice(negatives))
            anchor = int(rng.choice(cand)) if cand.size else -1
            return query, anchor, True
        if cand.size == 0:
            # Nothing visible enough and every object of the split is in the image: query the
            # most visible instance anyway (its targets may all be ignored).
            anchor = int(np.argmax(visib))
            return int(obj_ids[anchor]), anchor, False
        anchor = int(rng.choice(cand, p=visib[cand] / visib[cand].sum()))
        return int(obj_ids[anchor]), anchor, False

    def _choose_crop(self, ex, anchor, rng):
        cfg = self.config
        h, w = ex["rgb"].shape[:2]
        t = cfg.tile_size
        if anchor < 0:
            side = min(h, w) * rng.uniform(0.5, 1.0)
            return rng.uniform(0, w - side), rng.uniform(0, h - side), side
        bx0, by0, bx1, by1 = (float(v) for v in ex["bbox_obj"][anchor])
        size = max(bx1 - bx0, by1 - by0, 1.0)
        target = _log_uniform(rng, *cfg.size_range)
        side = t * size / target
        # The anchor's amodal box lies in the crop (it fits: side / size = t / target > 1);
        # within that, the crop stays inside the image when the image allows it.
        x0 = _interval_sample(rng, bx1 - side, bx0, 0.0, w - side)
        y0 = _interval_sample(rng, by1 - side, by0, 0.0, h - side)
        return x0, y0, side

    def random_map(self, ex, rng: np.random.Generator):
        cfg = self.config
        t = cfg.tile_size
        obj_ids = np.asarray(ex["obj_id"], np.int64)
        for o in np.unique(obj_ids):
            self.banks.entry(o)
        query, anchor, negative = self._choose_query(ex, rng)
        x0, y0, side = self._choose_crop(ex, anchor, rng)
        z = t / side
        image = warp_crop(ex["rgb"], x0, y0, side, t)
        K = crop_transform(x0, y0, side, t) @ np.asarray(ex["K"], np.float64)

        m = len(obj_ids)
        inside = _pixels_inside(ex["instances"], x0, y0, side, m).astype(np.float64)
        total = np.bincount(ex["instances"].ravel(), minlength=m + 1)[1:m + 1].astype(np.float64)
        visib = np.asarray(ex["visib_fract"], np.float64) * np.where(
            total > 0, inside / np.maximum(total, 1.0), 0.0)
        # Amodal targets: the object's whole box, which may extend past the tile, as object
        # generation reads a detection (module docstring). Only the size test uses the part
        # inside the tile.
        boxes = (np.asarray(ex["bbox_obj"], np.float64) - [x0, y0, x0, y0]) * z
        inner = np.clip(boxes, 0.0, t)
        wh = inner[:, 2:] - inner[:, :2]
        present = (obj_ids == query) & (visib > 0) & np.all(wh >= cfg.min_box_size, axis=1)
        if negative:
            present[:] = False
        idx = np.flatnonzero(present)
        idx = idx[np.argsort(-visib[idx], kind="stable")][:cfg.max_instances]

        M = cfg.max_instances
        out_boxes = np.zeros((M, 4), np.float32)
        rotations = np.tile(np.eye(3, dtype=np.float32), (M, 1, 1))
        out_visib = np.zeros(M, np.float32)
        mask = np.zeros(M, bool)
        ignore = np.zeros(M, bool)
        n = len(idx)
        if n:
            bank = self.banks.get(query)
            T = np.asarray(ex["T_cam_obj"], np.float64)[idx]
            centre = T[:, :3, :3] @ bank.center.astype(np.float64) + T[:, :3, 3]
            rotations[:n] = object_centred_rotation(T[:, :3, :3], centre)
            out_boxes[:n] = boxes[idx]
            out_visib[:n] = visib[idx]
            mask[:n] = visib[idx] >= cfg.min_target_visib
            ignore[:n] = ~mask[:n]
        return {
            "image": image,
            "K": K.astype(np.float32),
            "obj_id": np.int32(query),
            "negative": np.bool_(negative),
            "boxes": out_boxes,
            "mask": mask,
            "ignore": ignore,
            "rotations": rotations,
            "visib": out_visib,
            "scene_id": np.int32(ex["scene_id"]),
            "im_id": np.int32(ex["im_id"]),
        }


def pad_symmetries(sym: np.ndarray, max_symmetries: int) -> tuple[np.ndarray, np.ndarray]:
    """[S, 4, 4] -> (float32 [Ns, 4, 4], bool [Ns]): all S symmetry transforms when S <= Ns,
    else Ns evenly spaced ones, padded with the identity; the mask marks the real ones."""
    Ns = max_symmetries
    keep = (np.arange(len(sym)) if len(sym) <= Ns
            else np.round(np.linspace(0, len(sym) - 1, Ns)).astype(np.int64))
    out = np.tile(np.eye(4, dtype=np.float32), (Ns, 1, 1))
    out[:len(keep)] = sym[keep]
    return out, np.arange(Ns) < len(keep)


class AttachRenders(grain.transforms.RandomMap):
    """Prior renders, padded symmetries and sampled templates of the query object (step 3)."""

    def __init__(self, config: ExampleConfig, banks: BankCache):
        self.config = config
        self.banks = banks

    def random_map(self, ex, rng: np.random.Generator):
        cfg = self.config
        bank = self.banks.get(int(ex["obj_id"]))
        out = dict(ex)
        out["prior_rgb"] = check_render_size(bank.priors(), cfg.render_size, str(bank.path))
        sym = bank.symmetries
        out["symmetries"], out["symmetry_mask"] = pad_symmetries(sym, cfg.max_symmetries)
        if not cfg.num_templates:
            return out

        num_t = bank.num_templates
        if num_t < cfg.num_templates:
            raise ValueError(
                f"render bank {bank.path} has {num_t} templates but the pipeline samples "
                f"num_templates={cfg.num_templates} per example; lower num_templates (config "
                "data.num_train_templates) or render a larger bank")
        valid = np.flatnonzero(ex["mask"])
        M = len(ex["mask"])
        index = np.zeros(M, np.int32)
        if valid.size:
            pos, equivalents = nearest_templates(ex["rotations"][valid],
                                                  bank.template_rotations, sym)
            positives = np.unique(pos)
            excluded = np.union1d(positives, np.concatenate(equivalents))
        else:
            pos = np.zeros(0, np.int64)
            positives = excluded = np.zeros(0, np.int64)
        need = cfg.num_templates - positives.size
        pool = np.setdiff1d(np.arange(num_t), excluded, assume_unique=True)
        if pool.size < need:
            # Tiny banks of very symmetric objects: fall back to equivalents of the positive.
            pool = np.setdiff1d(np.arange(num_t), positives, assume_unique=True)
        chosen = np.concatenate([positives, rng.choice(pool, need, replace=False)])
        chosen = chosen[rng.permutation(chosen.size)]
        where = {int(c): i for i, c in enumerate(chosen)}
        index[valid] = [where[int(p)] for p in pos]
        out["template_rgb"] = check_render_size(bank.templates(chosen), cfg.render_size,
                                                str(bank.path))
        out["template_rotations"] = bank.template_rotations[chosen].astype(np.float32)
        out["template_index"] = index
        return out


class PhotometricAugment(grain.transforms.RandomMap):
    """Colour and noise augmentation of ``image`` (module docstring, step 4)."""

    def __init__(self, config: PhotometricConfig):
        self.config = config

    def random_map(self, ex, rng: np.random.Generator):
        out = dict(ex)
        out["image"] = augment_image(ex["image"], self.config, rng)
        return out


def augment_image(image: np.ndarray, cfg: PhotometricConfig, rng: np.random.Generator
                  ) -> np.ndarray:
    """uint8 [H, W, 3] -> uint8 [H, W, 3] with the photometric changes of ``cfg``.

    Every random draw happens whatever the strengths, so the stream of draws (and so the
    rest of an example) does not depend on which augmentations are on.
    """
    x = image.astype(np.float32) / 255.0
    d_bright = rng.uniform(-1, 1) * cfg.brightness
    f_contrast = 1.0 + rng.uniform(-1, 1) * cfg.contrast
    f_sat = 1.0 + rng.uniform(-1, 1) * cfg.saturation
    d_hue = rng.uniform(-1, 1) * cfg.hue
    noise_sigma = rng.uniform(0, 1) * cfg.noise_std
    blur = rng.random() < cfg.blur_prob
    blur_sigma = rng.uniform(0.3, max(cfg.blur_sigma, 0.3))
    noise = rng.standard_normal(x.shape, dtype=np.float32)
    if d_hue:
        hsv = cv2.cvtColor(np.clip(x, 0, 1), cv2.COLOR_RGB2HSV)  # float32: H in [0, 360)
        hsv[..., 0] = np.mod(hsv[..., 0] + 360.0 * d_hue, 360.0)
        x = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)
    if f_sat != 1.0:
        grey = x @ np.array([0.299, 0.587, 0.114], np.float32)
        x = grey[..., None] + f_sat * (x - grey[..., None])
    if f_contrast != 1.0:
        x = x.mean() + f_contrast * (x - x.mean())
    x = x + d_bright
    if blur and cfg.blur_prob > 0:
        x = cv2.GaussianBlur(x, (0, 0), sigmaX=blur_sigma, sigmaY=blur_sigma)
    if noise_sigma:
        x = x + noise_sigma * noise
    return np.clip(np.round(x * 255.0), 0, 255).astype(np.uint8)


# --------------------------------------------------------------------------- datasets


def find_shards(records_dir, split: str) -> list[str]:
    """Sorted ArrayRecord shard paths of ``<records_dir>/<split>``; raises when there are none."""
    folder = pathlib.Path(records_dir) / split
    shards = sorted(str(p) for p in folder.glob("*.array_record"))
    if not shards:
        raise FileNotFoundError(
            f"no ArrayRecord shards (*.array_record) in {folder}; generate a records folder "
            "with `python -m datagen.generate` then `python -m datagen.pack`, and point "
            "data_dir at it (it needs train/, val/, objects.json and banks/)")
    return shards


def decoded_records(records_dir, split: str, *, seed: int, shuffle: bool, repeat: bool,
                    process_index: int, process_count: int, num_records: int | None
                    ) -> tuple[grain.MapDataset, int]:
    """This process's decoded records of a split (every ``process_count``-th from
    ``process_index``, the first ``num_records`` of them if given, shuffled, repeated) and the
    seed its random maps derive from (distinct per process: the per-index generators would
    otherwise repeat). Shared by the detector's and the refiner's pipelines."""
    source = grain.sources.ArrayRecordDataSource(find_shards(records_dir, split))
    if not 0 <= process_index < process_count:
        raise ValueError(f"process_index {process_index} not in [0, {process_count})")
    ds = grain.MapDataset.source(source)[process_index::process_count]
    if num_records is not None:
        ds = ds[:num_records]
    if len(ds) == 0:
        raise ValueError(f"{records_dir}/{split} has {len(source)} records, too few for "
                         f"{process_count} processes")
    seed = (int(seed) * 1_000_003 + process_index) % 2**31
    if shuffle:
        ds = ds.shuffle(seed=seed)
    if repeat:
        ds = ds.repeat(None)
    return ds.map(DecodeExample()), seed


def detection_dataset(
    records_dir,
    split: str,
    config: ExampleConfig,
    *,
    seed: int,
    batch_size: int | None,
    photometric: PhotometricConfig | None = None,
    shuffle: bool = True,
    repeat: bool = True,
    process_index: int = 0,
    process_count: int = 1,
    num_records: int | None = None,
    table: Mapping[int, ObjectEntry] | None = None,
) -> grain.MapDataset:
    """The 3PT-D input pipeline over ``<records_dir>/<split>`` as a grain ``MapDataset``.

    Records are sliced per process (``process_index::process_count``, disjoint), optionally
    limited to the first ``num_records`` of that slice, shuffled (a new permutation every
    epoch) and repeated; the random transforms draw from generators keyed by (seed, element
    index), so element i is the same whatever the worker layout and a restored iterator
    continues with the same examples. ``batch_size`` is per process (``None``: unbatched).
    """
    if config.split is None:
        config = dataclasses.replace(config, split=split)
    table = load_object_table(records_dir) if table is None else table
    banks = BankCache(table)
    ds, seed = decoded_records(records_dir, split, seed=seed, shuffle=shuffle, repeat=repeat,
                               process_index=process_index, process_count=process_count,
                               num_records=num_records)
    ds = ds.random_map(SampleTile(config, banks), seed=seed + 1)
    ds = ds.random_map(AttachRenders(config, banks), seed=seed + 2)
    if photometric is not None:
        ds = ds.random_map(PhotometricAugment(photometric), seed=seed + 3)
    if batch_size is not None:
        ds = ds.batch(batch_size, drop_remainder=repeat)
    return ds
