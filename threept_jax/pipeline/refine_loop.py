"""The render-and-compare inference loop of 3PT-R over every object of a scene (issue 15, part 1).

For N object instances, each with K pose hypotheses (object generation, best first), seen in V
calibrated views, :func:`refine_instances` runs ``LoopSettings.iterations`` times::

    crop every view around the instance's current best hypothesis (crop_boxes, anti-aliased)
    render every hypothesis into every crop, run the network on all instances at once
    score = the mean of the network's per-view scores over the instance's views
    reciprocal matches on render edges -> multi-view PnP per hypothesis, each update kept only
        when the matches back it (update_hypotheses' safety test)
    drop duplicates up to symmetry, keep the refined best ceil(K * keep): K = 8 -> 4 -> 2 -> 1,
        and the start beside them, unrefined (pools of 8, 5, 3, 2)

where the start is the input the first look scored best (what selection alone would keep). It
then looks once more, at the final pool (the refined best and the start), and keeps the one the
network scores higher. Refinement that moves a pose somewhere the image does not support is
thus refused twice: step by step by the geometry of the matches, and at the end by the score of
what it produced against where it started. It returns one pose per instance, the
score of that pose itself, its visible-mask logits per view and the last crops' boxes
(:class:`LoopResult`). The refinement itself is :mod:`threept_jax.pipeline.refinement`
(``render_hypotheses``, ``update_hypotheses``), the one step training runs too.

Static shapes: N, K, V and the sizes fix the compiled program; K after each iteration is known
at trace time. Pad N to a bin (:func:`pad_to_bin`) with ``instance_mask`` False on the padding
so that a scene with another instance count reuses the compilation. Instances are batched on a
leading axis (``vmap`` for crops, renders and PnP; one network call with batch N), never a
Python loop over objects.

Crops: ``crop_and_resize`` (bilinear) at ``antialias`` x the crop size, box-averaged down, which
stands in for the Gaussian prefilter of the training crops (``data.detector_input.warp_crop``).
The crop intrinsics are ``crop_intrinsics`` of the box at the final size (box-averaging keeps
the pixel-centre rule: a final pixel's centre is the mean of its sub-pixels' centres).

Duplicates: hypotheses i and j are duplicates when, for some symmetry S of the object,
``angle(R_i, R_j R_S) < duplicate_deg`` and ``|t_i - (R_j t_S + t_j)| < duplicate_frac *
diameter``. In score order, a hypothesis that duplicates a better kept one goes behind every
non-duplicate; duplicates are kept only when too few distinct hypotheses remain.

Padding: a padded instance (``instance_mask`` False) is computed on a copy of the first real
instance's inputs (so garbage padding cannot cost time or produce NaNs) and its outputs are
replaced by fixed values: identity poses, ``-inf`` scores and mask logits, zero boxes.

Jit it with the network, the sizes and both settings static, e.g. ``jax.jit(refine_instances,
static_argnames=("network", "crop_size", "output_size", "settings", "loop"))`` for a pure
function network; for an ``nnx.Module`` wrap it in ``nnx.jit`` with the model as an argument
(a static module would bake its weights into the program as constants).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from threept_jax.geometry.camera import crop_intrinsics
from threept_jax.geometry.framing import crop_boxes
from threept_jax.pipeline.refinement import (
    Network,
    RefineSettings,
    render_hypotheses,
    update_hypotheses,
)
from threept_jax.render.crop import crop_and_resize
from threept_jax.render.mesh import RasterMesh

Array = jax.Array
BINS = (1, 2, 4, 8, 16, 32, 64)


@dataclasses.dataclass(frozen=True)
class LoopSettings:
    """Options of the inference loop (hashable: static under ``jit``).

    Attributes:
      iterations: render-and-compare iterations.
      keep: share of the hypotheses kept after each iteration, ``ceil(K * keep)`` (at least 1):
        0.5 halves K = 8 -> 4 -> 2 -> 1.
      crop_margin: ``crop_boxes``' margin (as training, ``RefinerExampleConfig.crop_margin``).
      antialias: crops are sampled at ``antialias`` x the crop size and box-averaged down.
      duplicate_deg, duplicate_frac: two hypotheses closer than ``duplicate_deg`` in rotation
        and ``duplicate_frac`` x the diameter in translation, up to symmetry, are duplicates
        (module docstring).
    """

    iterations: int = 3
    keep: float = 0.5
    crop_margin: float = 1.2
    antialias: int = 4
    duplicate_deg: float = 2.0
    duplicate_frac: float = 0.02

    def __post_init__(self):
        for name in ("iterations", "antialias"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < 1:
                raise ValueError(f"LoopSettings.{name} must be an integer >= 1, got {value!r}")
        if not 0.0 < self.keep <= 1.0:
            raise ValueError(f"LoopSettings.keep must be in (0, 1] (share of hypotheses kept "
                             f"after each iteration), got {self.keep}")
        if not self.crop_margin >= 1.0:
            raise ValueError(f"LoopSettings.crop_margin must be >= 1 (the crop must hold the "
                             f"object's bounding sphere), got {self.crop_margin}")
        if not 0.0 <= self.duplicate_deg < 180.0:
            raise ValueError(f"LoopSettings.duplicate_deg must be in [0, 180), got "
                             f"{self.duplicate_deg}")
        if not 0.0 <= self.duplicate_frac:
            raise ValueError(f"LoopSettings.duplicate_frac must be >= 0, got "
                             f"{self.duplicate_frac}")

    def schedule(self, num_hypotheses: int) -> tuple[int, ...]:
        """Refined hypotheses carried out of each iteration, after the K given: K = 8 -> (8, 4,
        2, 1). Each iteration after the first also sees the start unrefined, so the pools are
        (8, 5, 3) and the last look scores 2."""
        ks = [int(num_hypotheses)]
        for _ in range(self.iterations):
            ks.append(max(1, math.ceil(ks[-1] * self.keep)))
        return tuple(ks)


class LoopResult(NamedTuple):
    """Output of :func:`refine_instances` (padded instances: see the module docstring).

    poses: [N, 4, 4] refined best T_world_obj per instance (mm).
    scores: [N] score logit of that pose, rendered and seen by the network in the last look
      (the mean of its per-view scores over the instance's views).
    mask_logits: [N, V, h, w] the network's visible-mask logits of that pose in each view's
      last crop (:func:`paste_masks` puts them into the images).
    boxes: [N, V, 4] the last crops' boxes (pixel-edge xyxy in each view's image).
    hypotheses: [N, k + 1, 4, 4] the last pool in score order: the k refined hypotheses
      carried out of the last iteration (``LoopSettings.schedule``, 1 by default) and the
      start (module docstring), unrefined; hypothesis_scores [N, k + 1] their scores.
    history: [N, iterations + 2, 4, 4] the input's first hypothesis, the refined best after
      each iteration, and last the pose returned (``poses``).
    """

    poses: Array
    scores: Array
    mask_logits: Array
    boxes: Array
    hypotheses: Array
    hypothesis_scores: Array
    history: Array


DEFAULT_SETTINGS = RefineSettings()
DEFAULT_LOOP = LoopSettings()


def pad_to_bin(n: int, bins: tuple[int, ...] = BINS) -> int:
    """The padded instance count of n instances: the smallest bin >= n; past the last bin, the
    next multiple of the last bin (n = 100 with the default bins -> 128)."""
    if not bins or any(int(b) < 1 for b in bins) or list(bins) != sorted(set(bins)):
        raise ValueError(f"bins must be increasing positive integers, got {bins}")
    if int(n) < 0:
        raise ValueError(f"instance count must be >= 0, got {n}")
    for b in bins:
        if n <= b:
            return int(b)
    return int(-(-int(n) // bins[-1]) * bins[-1])


def paste_masks(mask_logits, boxes, image_hw: tuple[int, int]) -> np.ndarray:
    """Masks of crops in their images: mask_logits [V, h, w], boxes [V, 4] -> bool [V, H, W].

    Image pixel (r, c) is True when its centre (c + 0.5, r + 0.5) (pixel-edge coordinates) lies
    in the box (x0 <= x < x1, y0 <= y < y1) and the map pixel it falls in has a logit > 0
    (nearest); the map's h x w pixels tile the box evenly. Host-side NumPy (float64).
    """
    logits = np.asarray(mask_logits)
    boxes = np.asarray(boxes, np.float64)
    if logits.ndim != 3 or boxes.shape != (logits.shape[0], 4):
        raise ValueError(f"mask_logits must be [V, h, w] and boxes [V, 4], got {logits.shape} "
                         f"and {boxes.shape}")
    H, W = int(image_hw[0]), int(image_hw[1])
    V, h, w = logits.shape
    out = np.zeros((V, H, W), bool)
    for v in range(V):
        x0, y0, x1, y1 = boxes[v]
        if not (x1 > x0 and y1 > y0):
            continue
        cols = np.floor((np.arange(W) + 0.5 - x0) * (w / (x1 - x0))).astype(np.int64)
        rows = np.floor((np.arange(H) + 0.5 - y0) * (h / (y1 - y0))).astype(np.int64)
        ok_c = (cols >= 0) & (cols < w)
        ok_r = (rows >= 0) & (rows < h)
        fg = logits[v] > 0
        out[v][np.ix_(ok_r, ok_c)] = fg[np.ix_(rows[ok_r], cols[ok_c])]
    return out


def duplicate_pairs(poses: Array, symmetries: Array, symmetry_mask: Array, diameter: Array, *,
               max_deg: float, max_frac: float) -> Array:
    """[K, K] bool: hypotheses i and j are equal up to a symmetry (module docstring).

    poses [K, 4, 4], symmetries [Ns, 4, 4] (object frame, identity included) with
    symmetry_mask [Ns], diameter [] mm. Symmetric in i, j; the diagonal is True.
    """
    T = jnp.asarray(poses, jnp.float32)
    S = jnp.asarray(symmetries, jnp.float32)
    R, t = T[:, :3, :3], T[:, :3, 3]
    RS = jnp.einsum("jab,sbc->jsac", R, S[:, :3, :3])  # [K, Ns, 3, 3]
    tS = jnp.einsum("jab,sb->jsa", R, S[:, :3, 3]) + t[:, None]  # [K, Ns, 3]
    cos = (jnp.einsum("iab,jsab->ijs", R, RS) - 1.0) / 2.0  # trace(R_i^T R_j R_S)
    dist = jnp.linalg.norm(t[:, None, None] - tS[None], axis=-1)  # [K, K, Ns]
    close = (cos >= np.cos(np.radians(max_deg))) & (dist <= max_frac * diameter)
    dup = jnp.any(close & jnp.asarray(symmetry_mask, bool)[None, None], axis=-1)
    return dup | dup.T | jnp.eye(T.shape[0], dtype=bool)


def select_hypotheses(poses: Array, scores: Array, symmetries: Array, symmetry_mask: Array,
                      diameter: Array, num_keep: int, *, max_deg: float, max_frac: float
                      ) -> Array:
    """Indices [num_keep] of the hypotheses to keep, best first.

    Greedy in score order (ties: lower index first; NaN scores last): a hypothesis that is a
    :func:`duplicate_pairs` of a better one not itself dropped is dropped; dropped ones follow the
    kept ones, in score order, to fill ``num_keep`` when too few distinct hypotheses remain.
    """
    scores = jnp.where(jnp.isnan(scores), -jnp.inf, scores)
    K = scores.shape[0]
    order = jnp.argsort(-scores, stable=True)
    dup = duplicate_pairs(poses, symmetries, symmetry_mask, diameter, max_deg=max_deg,
                     max_frac=max_frac)[order][:, order]  # in rank order
    rank = jnp.arange(K)
    dropped = jnp.zeros((K,), bool)
    for a in range(K):  # K is small and static
        dropped = dropped | (dup[a] & ~dropped[a] & (rank > a))
    final = jnp.argsort(jnp.where(dropped, K, 0) + rank, stable=True)
    return order[final[:num_keep]]


def antialiased_crops(images: Array, Ks: Array, boxes: Array, crop_size: int, antialias: int):
    """Crops [V, c, c, 3] float in [0, 1] of uint8 images [V, H, W, 3] in boxes [V, 4] and their
    intrinsics [V, 3, 3]: bilinear at ``antialias`` x c, box-averaged (module docstring)."""
    a, c = antialias, crop_size
    fine = crop_and_resize(images, boxes, (a * c, a * c))  # [V, a c, a c, 3] float 0..255
    V = fine.shape[0]
    crops = fine.reshape(V, c, a, c, a, 3).mean(axis=(2, 4)) / 255.0
    return crops, crop_intrinsics(Ks, boxes, (c, c))


def _check_shapes(meshes, mesh_index, images, Ks, T_cam_world, hypotheses, symmetries,
                  symmetry_mask, instance_mask, view_mask, crop_size, output_size):
    V = images.shape[0] if images.ndim == 4 else -1
    if images.ndim != 4 or images.shape[-1] != 3 or images.dtype != jnp.uint8:
        raise ValueError(f"images must be uint8 [V, H, W, 3] (one image per view, RGB), got "
                         f"{images.dtype} {images.shape}")
    N = hypotheses.shape[0] if hypotheses.ndim == 4 else -1
    want = {
        "Ks": (Ks.shape, (V, 3, 3)),
        "T_cam_world": (T_cam_world.shape, (V, 4, 4)),
        "hypotheses": (hypotheses.shape, (N, hypotheses.shape[1] if N >= 0 else -1, 4, 4)),
        "mesh_index": (mesh_index.shape, (N,)),
        "instance_mask": (instance_mask.shape, (N,)),
        "view_mask": (view_mask.shape, (N, V)),
        "symmetries": (symmetries.shape, (N, symmetries.shape[1] if symmetries.ndim == 4
                                          else -1, 4, 4)),
        "symmetry_mask": (symmetry_mask.shape, (N,) + symmetries.shape[1:2]),
    }
    for name, (got, shape) in want.items():
        if tuple(got) != shape:
            raise ValueError(f"{name} must have shape {shape} (N={N} instances from hypotheses "
                             f"[N, K, 4, 4], V={V} views from images), got {tuple(got)}")
    if hypotheses.shape[1] < 1:
        raise ValueError("hypotheses must hold at least one hypothesis per instance (K >= 1)")
    if meshes.face_geom.ndim != 3:
        raise ValueError("meshes must be stacked on a leading object axis "
                         "(RefinerMeshes.stacked), got face_geom of shape "
                         f"{meshes.face_geom.shape}")
    if crop_size % output_size:
        raise ValueError(f"crop_size {crop_size} must be a multiple of output_size "
                         f"{output_size} (the network's map)")


def refine_instances(network: Network, meshes: RasterMesh, mesh_index: Array, images: Array,
                     Ks: Array, T_cam_world: Array, hypotheses: Array, symmetries: Array,
                     symmetry_mask: Array, instance_mask: Array, view_mask: Array, *,
                     crop_size: int, output_size: int,
                     settings: RefineSettings = DEFAULT_SETTINGS,
                     loop: LoopSettings = DEFAULT_LOOP) -> LoopResult:
    """Refine every instance's hypotheses by render-and-compare (module docstring).

    Args:
      network: ``network(real [B, V, c, c, 3], renders [B, K, V, c, c, 3]) -> dict``, the
        refiner contract (``refine_step``), called once per iteration with B = N.
      meshes: the prepared meshes stacked on a leading object axis O
        (``RefinerMeshes.stacked``); mesh_index [N] int, each instance's row.
      images: [V, H, W, 3] uint8, one image per view; Ks [V, 3, 3] their intrinsics;
        T_cam_world [V, 4, 4] extrinsics (mm; single view: the identity).
      hypotheses: [N, K, 4, 4] T_world_obj (mm), best first.
      symmetries: [N, Ns, 4, 4] object-frame symmetry transforms (identity included) with
        symmetry_mask [N, Ns] (padding False).
      instance_mask: [N] bool, False on padding (:func:`pad_to_bin`).
      view_mask: [N, V] bool, the views each instance is refined in: a False view gets zero
        weight in PnP and is left out of the score mean (its crop is still rendered).
      crop_size, output_size: the network's crop and map sizes (``RefinerConfig``).
      settings: the refinement step's options (the refiner config's ``refine`` section).
      loop: :class:`LoopSettings`.

    Returns :class:`LoopResult`. Pure and jit-able (module docstring).
    """
    images = jnp.asarray(images)
    Ks = jnp.asarray(Ks, jnp.float32)
    T_cam_world = jnp.asarray(T_cam_world, jnp.float32)
    hypotheses = jnp.asarray(hypotheses, jnp.float32)
    mesh_index = jnp.asarray(mesh_index, jnp.int32)
    symmetries = jnp.asarray(symmetries, jnp.float32)
    symmetry_mask = jnp.asarray(symmetry_mask, bool)
    instance_mask = jnp.asarray(instance_mask, bool)
    view_mask = jnp.asarray(view_mask, bool)
    _check_shapes(meshes, mesh_index, images, Ks, T_cam_world, hypotheses, symmetries,
                  symmetry_mask, instance_mask, view_mask, crop_size, output_size)
    N = hypotheses.shape[0]
    schedule = loop.schedule(hypotheses.shape[1])

    # Padding computes on a copy of the first real instance (module docstring).
    first = jnp.argmax(instance_mask)

    def real(x):
        m = instance_mask.reshape((N,) + (1,) * (x.ndim - 1))
        return jnp.where(m, x, x[first])

    mesh_index = jnp.clip(real(mesh_index), 0, meshes.face_geom.shape[0] - 1)
    hyps = real(hypotheses)
    symmetries, symmetry_mask, view_mask = real(symmetries), real(symmetry_mask), real(view_mask)
    mesh_of = lambda i: jax.tree.map(lambda x: x[i], meshes)  # noqa: E731
    diameter = meshes.diameter[mesh_index]
    views = jnp.maximum(jnp.sum(view_mask, -1), 1)

    def look(hyps):
        """Crop every view around each instance's first hypothesis, render all of them, run
        the network: (boxes, crops, crop_K, renders, outputs, score [N, K])."""
        def crop_one(index, best):
            box = crop_boxes(mesh_of(index), best, T_cam_world, Ks, margin=loop.crop_margin)
            return (box,) + antialiased_crops(images, Ks, box, crop_size, loop.antialias)

        boxes, crops, crop_K = jax.vmap(crop_one)(mesh_index, hyps[:, 0])

        def render_one(index, cK, h):
            return render_hypotheses(mesh_of(index), cK, T_cam_world, h, crop_size=crop_size,
                                     output_size=output_size, ambient=settings.ambient)

        rend = jax.vmap(render_one)(mesh_index, crop_K, hyps)
        out = dict(network(crops, rend.rgb))
        score = jnp.sum(jnp.where(view_mask[:, None], out["view_scores"], 0.0), -1)
        return boxes, crops, crop_K, rend, out, score / views[:, None]

    def take(x, index):  # x [N, K, ...], index [N, k] -> [N, k, ...]
        return jnp.take_along_axis(x, index.reshape(index.shape + (1,) * (x.ndim - 2)), axis=1)

    history, start = [hyps[:, 0]], None
    for k_next in schedule[1:]:
        boxes, crops, crop_K, rend, out, score = look(hyps)

        def update_one(o, r, index, c, cK, h, vm):
            return update_hypotheses(o, r, mesh_of(index), c, cK, T_cam_world, h, settings, vm)

        res = jax.vmap(update_one)(out, rend, mesh_index, crops, crop_K, hyps, view_mask)
        select = functools.partial(select_hypotheses, num_keep=k_next,
                                   max_deg=loop.duplicate_deg, max_frac=loop.duplicate_frac)
        keep = jax.vmap(select)(res.hypotheses, score, symmetries, symmetry_mask,
                                diameter)  # [N, k_next]
        if start is None:  # the first look's best-scored input: what selection alone keeps
            start = take(hyps, keep[:, :1])
        # The start goes on unrefined beside the refined ones: every later look scores it
        # against what refinement made of the poses, so refinement the image does not support
        # is not kept.
        hyps = jnp.concatenate([take(res.hypotheses, keep), start], axis=1)
        history.append(hyps[:, 0])

    # The last look: score the final pool (the refined best and the start) and keep the
    # higher; its score, mask and crop are the result's.
    boxes, _, _, _, out, score = look(hyps)
    order = jnp.argsort(-jnp.where(jnp.isnan(score), -jnp.inf, score), axis=1, stable=True)
    hyps, scores = take(hyps, order), take(score, order)
    mask_logits = take(out["mask_logits"], order[:, :1])[:, 0]
    history.append(hyps[:, 0])

    def pad(x, fill):
        m = instance_mask.reshape((N,) + (1,) * (x.ndim - 1))
        return jnp.where(m, x, jnp.asarray(fill, x.dtype))

    eye = jnp.eye(4, dtype=jnp.float32)
    return LoopResult(
        poses=pad(hyps[:, 0], eye),
        scores=pad(scores[:, 0], -jnp.inf),
        mask_logits=pad(mask_logits.astype(jnp.float32), -jnp.inf),
        boxes=pad(boxes, 0.0),
        hypotheses=pad(hyps, eye),
        hypothesis_scores=pad(scores, -jnp.inf),
        history=pad(jnp.stack(history, 1), eye),
    )
