"""Training-free detection by shape search: class-agnostic proposals, a pose search per
proposal, verification by the contour score.

Nothing here is learned; a part is found from its CAD model alone (issue 37's baseline, the one
every learned detector must beat). Four stages per image:

1. **Proposals** (:func:`proposals`): OpenCV's selective search (Uijlings et al., IJCV 2013;
   ``cv2.ximgproc``, the "fast" strategy on the image at half size): class-agnostic boxes of
   regions that hang together in colour, texture and size. On the held-out cell images its
   first 300 boxes hold a box within IoU 0.5 of 97 % of the visible parts.
2. **Pose search** (:func:`search`): each part's contour templates (:func:`shape_templates`,
   the contour model's stored views times in-plane turns, their outline points and normals in
   the image plane) are fitted to each proposal: the template's box fixes the distance (its
   area against the proposal's, or its extent along the image side that a proposal there
   touches: a part cut by the image's side; inside the depth range, the aspect within
   ``box_fit`` IoU: 4-12 % of the pairs on the demo cell, the only ones scored) and the
   centre, and the template scores by the LINE-2D orientation similarity of its outline with
   the image's gradients (:func:`orientation_response`: quantised orientations spread
   over a few pixels, Hinterstoisser et al., PAMI 2012). Each part keeps its best
   ``per_proposal`` templates per proposal, proposals thinned by NMS.
3. **Verification** (:func:`verify`): ``candidates`` poses of the image, an equal share per
   part (:func:`select_candidates`), are refined by the contour refiner
   (:func:`threept_jax.pipeline.contour.refine_poses`, its contour score: the posterior mass
   of the outline on the image's region boundary, in [0, 1]).
4. **Score** (:func:`calibrated_score`): the probability that a candidate is right, a logistic
   model of :func:`outline_features` (contour and template scores, the outline's LINE-2D
   similarity, thinness, elongation, size and the clutter around it) whose
   :data:`SCORE_WEIGHTS` were fitted on cells of other parts (``python -m
   train.templates_score``), or per part on scenes of a cell's own parts
   (:func:`fit_part_weights`, ``python -m train.templates_score --cell``), plus the learned
   verifier's correction to its log-odds when one is given
   (:class:`threept_jax.models.verifier.CandidateVerifier` on :func:`verifier_inputs`: the
   image around the candidate beside the part rendered at its pose); the refined poses'
   boxes are merged by NMS across parts (one part per place).

Shapes: O objects, R templates per object (views x in-plane turns), n outline points per
template, B proposals, k templates kept per proposal.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import dataclasses
import functools
import threading
from collections.abc import Sequence
from typing import NamedTuple

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from threept_jax.geometry.boxes import box_iou
from threept_jax.geometry.grids import viewpoint_rotation
from threept_jax.models.verifier import CROP
from threept_jax.pipeline.contour import ContourModel, ContourSettings, refine_poses
from threept_jax.render.crop import crop_and_resize
from threept_jax.render.mesh import RasterMesh
from threept_jax.render.raster import render

Array = jax.Array

#: The C library, whose ``rand()`` OpenCV's selective search ranks its regions with.
_LIBC = ctypes.CDLL(ctypes.util.find_library("c"))
_RAND_LOCK = threading.Lock()

#: Quantised gradient orientations (modulo 180 degrees: a part may be darker or lighter than
#: what is behind it).
NUM_BINS = 8


@dataclasses.dataclass(frozen=True)
class ShapeSearchSettings:
    """Options of the shape search (hashable).

    num_views: stored contour views used as templates (evenly spaced through the contour
      model's Fibonacci sphere); num_inplane: turns of each about the optical axis;
      num_points: outline points per template.
    max_proposals: selective-search boxes per image; proposal_scale: the image scale it runs at.
    box_fit: a template fits a proposal when their boxes, centred and the template scaled to
      the proposal's area, overlap by this IoU.
    box_scales, box_shift: a given box (a trained detector's, :func:`box_variants`) is fitted
      in copies of itself scaled by each of ``box_scales`` about its centre, each also shifted
      by ``box_shift`` of its width or height left, right, up and down: a network's box is off
      by a few pixels, and the fit is only as good as its box.
    per_proposal: templates kept per (proposal, part), the poses the verification chooses
      from: 3 rather than 8 spreads a part's share of it over more places (on three held-out
      sets of 48 images box AP50 +0.02-0.06; docs/benchmarks.md, "Three templates a
      proposal"); proposal_nms: IoU of the NMS that thins each part's proposals by their best
      template score.
    per_box: templates kept per copy of a given box (:func:`box_variants`).
    candidates: poses refined and scored per image, an equal share per part
      (:func:`select_candidates`).
    spread: half-width (px) of the orientation spreading; min_gradient: weakest gradient (Sobel
      magnitude of the strongest colour channel, 0-255 images) that counts as an edge.
    nms_iou: IoU of the final NMS across parts (one part per place: the scene's refinement
      and masks treat every detection as its own object).
    contour: the refinement and score of stage 3; lines: its correspondence lines per pose
      (every ``n``-th point of the contour model's outlines, evenly spread).
    """

    num_views: int = 200
    num_inplane: int = 36
    num_points: int = 48
    max_proposals: int = 300
    proposal_scale: float = 0.5
    box_fit: float = 0.6
    box_scales: tuple[float, ...] = (0.9, 1.0, 1.1)
    box_shift: float = 0.08
    per_proposal: int = 3
    per_box: int = 16
    proposal_nms: float = 0.5
    candidates: int = 200
    spread: int = 1
    min_gradient: float = 30.0
    nms_iou: float = 0.5
    contour: ContourSettings = ContourSettings(scales=(0.04, 0.02, 0.01), iterations=2)
    lines: int = 100

    def __post_init__(self):
        defaults = {f.name: f.default for f in dataclasses.fields(self)}
        for name in ("num_views", "num_inplane", "num_points", "max_proposals", "per_proposal",
                     "per_box", "candidates", "lines"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"ShapeSearchSettings.{name} must be an integer >= 1, got "
                                 f"{v!r} (the default is {defaults[name]})")
        if 2 * self.candidates < self.per_box:
            raise ValueError(f"ShapeSearchSettings: candidates ({self.candidates}) must be at "
                             f"least half of per_box ({self.per_box}), so that a given box's "
                             f"poses are verified: raise candidates or lower per_box")


class ShapeTemplates(NamedTuple):
    """Contour templates of O objects (stacked; numpy or jax arrays).

    xy [O, R, n, 2]: outline points in the camera's image plane at unit depth scale (mm, x
    right, y down, from the object's centre); bins [O, R, n] int32: quantised orientation of
    each point's normal; valid [O, R, n]; rotations [O, R, 3, 3] R_cam_obj of each template.
    """

    xy: Array
    bins: Array
    valid: Array
    rotations: Array


def orientation_bin(dx, dy):
    """Quantised orientation modulo 180 degrees of vectors (dx, dy), in [0, NUM_BINS): bin k
    is centred on k * 180 / NUM_BINS degrees, so the horizontal, vertical and diagonal edges
    of parts and images sit in the middle of a bin, not on a border between two."""
    xp = jnp if isinstance(dx, jax.Array) else np  # NumPy images, jitted outlines
    angle = xp.mod(xp.arctan2(dy, dx), np.pi)
    return (xp.floor(angle / np.pi * NUM_BINS + 0.5).astype(np.int32)) % NUM_BINS


def shape_templates(contours: dict[str, np.ndarray], settings: ShapeSearchSettings
                    ) -> dict[str, np.ndarray]:
    """The templates of one object from its contour model (``mesh_contours``' arrays):
    ``settings.num_views`` of its stored views (their outline points and normals, seen by a
    camera along the view's direction) times ``num_inplane`` turns about the optical axis."""
    dirs = np.asarray(contours["directions"], np.float64)
    views = np.linspace(0, len(dirs), settings.num_views, endpoint=False).astype(int)
    n_all = contours["points"].shape[1]
    sub = np.linspace(0, n_all, settings.num_points, endpoint=False).astype(int)
    turns = 2 * np.pi * np.arange(settings.num_inplane) / settings.num_inplane
    Rz = np.zeros((len(turns), 3, 3))
    Rz[:, 0, 0] = Rz[:, 1, 1] = np.cos(turns)
    Rz[:, 0, 1], Rz[:, 1, 0] = -np.sin(turns), np.sin(turns)
    Rz[:, 2, 2] = 1.0
    R = np.einsum("tij,vjk->vtik", Rz, np.stack([viewpoint_rotation(dirs[v]) for v in views]))
    P = np.asarray(contours["points"], np.float64)[views][:, sub] - contours["center"]
    N = np.asarray(contours["normals"], np.float64)[views][:, sub]
    q = np.einsum("vtij,vnj->vtni", R, P)
    nrm = np.einsum("vtij,vnj->vtni", R, N)
    valid = np.broadcast_to(np.asarray(contours["valid"])[views][:, sub][:, None], q.shape[:3])
    T = len(views) * len(turns)
    return {"xy": q[..., :2].reshape(T, -1, 2).astype(np.float32),
            "bins": orientation_bin(nrm[..., 0], nrm[..., 1]).reshape(T, -1),
            "valid": valid.reshape(T, -1).copy(), "rotations": R.reshape(T, 3, 3).astype(
                np.float32)}


def stack_templates(per_object) -> ShapeTemplates:
    return ShapeTemplates(*(np.stack([t[k] for t in per_object])
                            for k in ("xy", "bins", "valid", "rotations")))


def orientation_response(image: np.ndarray, spread: int = 1, min_gradient: float = 30.0
                         ) -> np.ndarray:
    """[NUM_BINS, H, W] float32 LINE-2D response maps of a uint8 RGB image: entry [k, y, x] is
    the best |cos| between orientation bin k and the quantised gradient orientations found
    within ``spread`` px of (x, y) (gradients of the strongest colour channel, Sobel magnitude
    above ``min_gradient``); 0 where there are none."""
    img = np.asarray(image, np.float32)
    gx = np.stack([cv2.Sobel(img[..., c], cv2.CV_32F, 1, 0, ksize=3) for c in range(3)])
    gy = np.stack([cv2.Sobel(img[..., c], cv2.CV_32F, 0, 1, ksize=3) for c in range(3)])
    mag = gx * gx + gy * gy
    ch = np.argmax(mag, 0)[None]
    gx, gy = np.take_along_axis(gx, ch, 0)[0], np.take_along_axis(gy, ch, 0)[0]
    strong = np.take_along_axis(mag, ch, 0)[0] > min_gradient ** 2
    b = orientation_bin(gx, gy)
    kernel = np.ones((2 * spread + 1, 2 * spread + 1), np.uint8)
    centres = np.arange(NUM_BINS) * np.pi / NUM_BINS
    out = np.zeros((NUM_BINS,) + b.shape, np.float32)
    for i in range(NUM_BINS):
        present = cv2.dilate(((b == i) & strong).astype(np.uint8), kernel).astype(bool)
        cos = np.abs(np.cos(centres - centres[i])).astype(np.float32)  # [asked]
        for k in range(NUM_BINS):
            np.maximum(out[k], np.where(present, cos[k], np.float32(0)), out=out[k])
    return out


def proposals(image: np.ndarray, settings: ShapeSearchSettings) -> np.ndarray:
    """[B, 4] float32 xywh class-agnostic boxes of a uint8 RGB image (selective search, fast
    strategy, at ``proposal_scale``), at most ``max_proposals``, in selective search's order."""
    s = settings.proposal_scale
    small = cv2.resize(cv2.cvtColor(np.asarray(image), cv2.COLOR_RGB2BGR), None, fx=s, fy=s,
                       interpolation=cv2.INTER_AREA)
    ss = cv2.ximgproc.segmentation.createSelectiveSearchSegmentation()
    ss.setBaseImage(small)
    ss.switchToSelectiveSearchFast()
    # OpenCV ranks the regions by their level times C's rand() (the paper's randomised
    # ranking), so which boxes came first depended on whatever had called rand() before: the
    # same image gave other detections from call to call. Seeded, it gives the same ones; the
    # lock keeps two threads from drawing from the one generator at once.
    with _RAND_LOCK:
        _LIBC.srand(0)
        boxes = ss.process()[:settings.max_proposals].astype(np.float32) / s
    return boxes.reshape(-1, 4)


#: A proposal within this many pixels of an image side touches it: the part in it may be cut
#: there (:func:`fit_templates`).
BORDER_PX = 3.0
#: Least share of a template's outline (and of its box) inside the image for it to fit a part
#: cut by the image's side; its similarity is over the outline inside, and over at least this
#: share of all of it.
MIN_VISIBLE = 0.5


def _visible_mean(values: Array, inside: Array, n_valid: Array) -> Array:
    """Mean of ``values`` [..., n] over the outline points ``inside`` the image [..., n], over
    at least :data:`MIN_VISIBLE` of the ``n_valid`` [...] points of the whole outline (and at
    least one)."""
    counted = jnp.maximum(jnp.maximum(jnp.sum(inside, -1), MIN_VISIBLE * n_valid), 1)
    return jnp.sum(jnp.where(inside, values, 0.0), -1) / counted


def fit_templates(response: Array, boxes: Array, xy: Array, bins: Array, valid: Array,
                  K: Array, depth_range: Array, box_fit: float, k: int):
    """The best ``k`` templates of one object in each proposal.

    response [NUM_BINS, H, W] (:func:`orientation_response`); boxes [B, 4] xywh; xy, bins, valid
    [R, n] (one object's :class:`ShapeTemplates`); K [3, 3]; depth_range [2] mm (object
    centres). Returns scores [B, k] (mean response over the outline; -1 where no template fits
    the box), template index [B, k], depth [B, k] (mm) and centre [B, k, 2] (px, the object
    centre's projection). Jitted programs (one compilation each per image size and template
    count), called from Python.

    A template's distance comes from the proposal's area, its centre from the proposal's. A
    proposal that touches one image side (within :data:`BORDER_PX`) may hold a part cut by it:
    its extent along that side is whole, so the distance comes from it, and the template's
    box is put against the proposal's far side, running out of the image. Either way a
    template fits when its box, clipped to the image, overlaps the proposal by ``box_fit`` IoU
    with at least :data:`MIN_VISIBLE` of it inside. It scores by the mean response over its
    outline points inside the image (at least :data:`MIN_VISIBLE` of them counted) times the
    square root of the share inside: part of an outline fits the image by chance more often
    than all of it, and at the full mean the fits of cut parts took the verification's places
    from whole parts (docs/benchmarks.md, "Parts cut by the image's side"). A proposal in a
    corner (one side and its neighbour) is taken to be cut less along one of them: the nearer
    of its two extents' distances, the template against its two far sides.

    Only the pairs that fit are scored (on the demo cell 4-12 % of them; the others' outline
    points were most of the fit's work): they are listed (:func:`_fitting_pairs`) and scored
    :data:`PAIR_WINDOW` at a time by one compiled program (:func:`_score_pairs`), and each
    proposal's best ``k`` taken."""
    cu, cv, Z, fits = _placements(response.shape[1:], boxes, xy, valid, K, depth_range,
                                  box_fit=box_fit)
    pair, count = _fitting_pairs(fits)
    scores = jnp.full(fits.size, -1.0)
    for start in range(0, int(count), PAIR_WINDOW):
        scores = _score_pairs(scores, pair, jnp.int32(start), response, xy, bins, valid, K,
                              cu, cv, Z)
    return _best(scores.reshape(fits.shape), cu, cv, Z, k=k)


#: Fitting (proposal, template) pairs :func:`fit_templates` scores a call (a proposal list's
#: pairs that fit number about 10 % of 300 x 7200 on the demo cell: 1-4 calls).
PAIR_WINDOW = 1 << 16
#: Pairs one step of a call scores at once.
PAIR_CHUNK = 1 << 12


@functools.partial(jax.jit, static_argnames=("hw", "box_fit"))
def _placements(hw: tuple[int, int], boxes: Array, xy: Array, valid: Array, K: Array,
                depth_range: Array, box_fit: float):
    """Where each template [R] would sit in each proposal [B] (:func:`fit_templates`): the
    projected centre of its outline box's corner cu, cv [B, R] (px), its depth Z [B, R] (mm)
    and whether it fits [B, R]."""
    H, W = hw
    fx, fy = K[0, 0], K[1, 1]
    big = jnp.float32(1e9)
    lo = jnp.min(jnp.where(valid[..., None], xy, big), 1)  # [R, 2]
    hi = jnp.max(jnp.where(valid[..., None], xy, -big), 1)
    size = jnp.maximum(hi - lo, 1e-3)
    x0, y0, bw, bh = (boxes[:, i:i + 1] for i in range(4))  # [B, 1]
    left, top = x0 <= BORDER_PX, y0 <= BORDER_PX
    right, bottom = x0 + bw >= W - BORDER_PX, y0 + bh >= H - BORDER_PX
    # Cut along x: it touches the left or the right side, not both (nor the top and bottom
    # both); its template is put against the far side. Likewise along y.
    ax = (left ^ right) & ~(top & bottom)
    ay = (top ^ bottom) & ~(left & right)
    z_h, z_w = fy * size[:, 1] / jnp.maximum(bh, 1.0), fx * size[:, 0] / jnp.maximum(bw, 1.0)
    Z = jnp.where(ax & ay, jnp.minimum(z_h, z_w), jnp.where(ax, z_h, jnp.where(
        ay, z_w, jnp.sqrt(fx * size[:, 0] * fy * size[:, 1] / jnp.maximum(bw * bh, 1.0)))))
    pw, ph = fx * size[:, 0] / Z, fy * size[:, 1] / Z  # [B, R]
    tx = jnp.where(ax & left, x0 + bw - pw, jnp.where(ax & right, x0, x0 + (bw - pw) / 2))
    ty = jnp.where(ay & top, y0 + bh - ph, jnp.where(ay & bottom, y0, y0 + (bh - ph) / 2))
    cw = jnp.clip(tx + pw, 0, W) - jnp.clip(tx, 0, W)  # the template's box inside the image
    ch = jnp.clip(ty + ph, 0, H) - jnp.clip(ty, 0, H)
    inter = (jnp.maximum(jnp.minimum(tx + pw, x0 + bw) - jnp.maximum(tx, x0), 0)
             * jnp.maximum(jnp.minimum(ty + ph, y0 + bh) - jnp.maximum(ty, y0), 0))
    fits = ((inter / jnp.maximum(cw * ch + bw * bh - inter, 1e-6) >= box_fit)
            & (cw * ch >= MIN_VISIBLE * pw * ph)
            & (Z >= depth_range[0]) & (Z <= depth_range[1]) & jnp.any(valid, -1))
    cu = tx - lo[:, 0] * fx / Z
    cv = ty - lo[:, 1] * fy / Z
    return cu, cv, Z, fits


@jax.jit
def _fitting_pairs(fits: Array) -> tuple[Array, Array]:
    """The flat indices [B * R] of the (proposal, template) pairs that fit [B, R], first, then
    B * R (out of range: never written) in the rest; and their count."""
    return jnp.nonzero(fits.reshape(-1), size=fits.size, fill_value=fits.size)[0], jnp.sum(fits)


@jax.jit
def _score_pairs(scores: Array, pair: Array, start: Array, response: Array, xy: Array,
                 bins: Array, valid: Array, K: Array, cu: Array, cv: Array, Z: Array) -> Array:
    """``scores`` [B * R] with the fit's scores written for the pairs ``pair[start:start +
    PAIR_WINDOW]`` (:func:`_fitting_pairs`; a window running past the list's end is moved back
    into it and scores some pairs again, the same)."""
    H, W = response.shape[1:]
    R = xy.shape[0]
    window = min(PAIR_WINDOW, pair.shape[0])
    chunk = PAIR_CHUNK if window == PAIR_WINDOW else window  # a short list: at once
    fx, fy = K[0, 0], K[1, 1]
    flat = response.reshape(-1)
    n_valid = jnp.sum(valid, -1)  # [R]
    some = jax.lax.dynamic_slice(pair, (start,), (window,))
    at = [a.reshape(-1)[some] for a in (cu, cv, Z)]  # gathers clamp the out of range index

    def score(args):
        t, cu_, cv_, Z_ = args  # [chunk]
        u = jnp.round(cu_[:, None] + xy[t, :, 0] * fx / Z_[:, None]).astype(jnp.int32)
        v = jnp.round(cv_[:, None] + xy[t, :, 1] * fy / Z_[:, None]).astype(jnp.int32)
        inside = valid[t] & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        # One flat index: XLA's CPU gather of it is 2-3x faster than of three.
        r = flat[(bins[t] * H + jnp.clip(v, 0, H - 1)) * W + jnp.clip(u, 0, W - 1)]
        return (_visible_mean(r, inside, n_valid[t])
                * jnp.sqrt(jnp.sum(inside, -1) / jnp.maximum(n_valid[t], 1)))

    got = jax.lax.map(score, tuple(x.reshape(-1, chunk) for x in (some % R, *at))).reshape(-1)
    return scores.at[some].set(got, mode="drop")


@functools.partial(jax.jit, static_argnames=("k",))
def _best(scores: Array, cu: Array, cv: Array, Z: Array, k: int):
    """Each proposal's best ``k`` of the fit's ``scores`` [B, R] (-1: no fit), as
    :func:`fit_templates` returns them."""
    top, idx = jax.lax.top_k(scores, k)
    Z, cu, cv = (jnp.take_along_axis(a, idx, 1) for a in (Z, cu, cv))
    return top, idx, Z, jnp.stack([cu, cv], -1)


def box_variants(boxes: np.ndarray, scales: Sequence[float], shift: float) -> np.ndarray:
    """[n, V, 4] xywh copies of boxes [n, 4] xywh: for each scale (about the box's centre), the
    scaled box, then it moved by ``shift`` of the given box's width right and left and of its
    height down and up (V = 5 * len(scales); only the scaled boxes when ``shift`` is 0)."""
    boxes = np.asarray(boxes, np.float32)
    moves = [(0.0, 0.0)] + ([(shift, 0.0), (-shift, 0.0), (0.0, shift), (0.0, -shift)]
                            if shift else [])
    centre = boxes[:, :2] + boxes[:, 2:] / 2
    out = []
    for s in scales:
        size = boxes[:, 2:] * s
        for dx, dy in moves:
            c = centre + np.array([dx, dy], np.float32) * boxes[:, 2:]
            out.append(np.concatenate([c - size / 2, size], -1))
    return np.stack(out, 1)


def select_candidates(scores: np.ndarray, parts: np.ndarray, n: int) -> np.ndarray:
    """Indices of the ``n`` candidates to verify, best template score first: each part's best
    ``n // P`` (P: the parts with candidates), then the best of the rest. A global top ``n``
    starved parts whose outlines fit the image less crisply (large or occluded parts) while
    few-line parts fitting the background filled the list (docs/benchmarks.md)."""
    scores, parts = np.asarray(scores), np.asarray(parts)
    order = np.argsort(-scores, kind="stable")
    present = np.unique(parts)
    if not len(present):
        return order[:0]
    each = n // len(present)
    rank = np.empty(len(order), np.int64)  # a candidate's rank within its part
    for p in present:
        mine = order[parts[order] == p]
        rank[mine] = np.arange(len(mine))
    share = order[rank[order] < each]
    rest = order[rank[order] >= each][:max(n - len(share), 0)]
    chosen = np.concatenate([share, rest])
    return chosen[np.argsort(-scores[chosen], kind="stable")]


def poses_from_fit(rotations: np.ndarray, center: np.ndarray, depth: np.ndarray,
                   uv: np.ndarray, K: np.ndarray) -> np.ndarray:
    """[P, 4, 4] T_cam_obj of templates ``rotations`` [P, 3, 3] whose object centre ``center``
    [P, 3] (object frame) projects to ``uv`` [P, 2] at depth ``depth`` [P] (mm)."""
    rays = np.concatenate([uv, np.ones((len(uv), 1))], -1) @ np.linalg.inv(K).T
    T = np.tile(np.eye(4), (len(uv), 1, 1))
    T[:, :3, :3] = rotations
    T[:, :3, 3] = rays * depth[:, None] - np.einsum("pij,pj->pi", rotations, center)
    return T


def _outline(model: ContourModel, T: Array, o: Array, K: Array):
    """The outline of object ``o`` at pose T [4, 4] T_cam_obj, from the stored view nearest the
    camera's direction: image points uv [N, 2] (px), normals in the camera frame [N, 3] and
    valid [N]."""
    R, t = T[:3, :3], T[:3, 3]
    d = -R.T @ t - model.center[o]
    v = jnp.argmax(model.directions[o] @ (d / jnp.maximum(jnp.linalg.norm(d), 1e-9)))
    X = model.points[o, v] @ R.T + t
    uv = X[:, :2] / jnp.maximum(X[:, 2:], 1e-6) * jnp.stack([K[0, 0], K[1, 1]]) + K[:2, 2]
    return uv, model.normals[o, v] @ R.T, model.valid[o, v]


def outline_boxes(model: ContourModel, poses: Array, obj: Array, K: Array) -> Array:
    """[P, 4] xyxy boxes of the outlines (the nearest stored view's contour points) of objects
    ``obj`` [P] at poses [P, 4, 4] T_cam_obj."""

    def one(T, o):
        uv, _, ok = _outline(model, T, o, K)
        return jnp.concatenate([jnp.min(jnp.where(ok[:, None], uv, 1e9), 0),
                                jnp.max(jnp.where(ok[:, None], uv, -1e9), 0)])

    return jax.vmap(one)(poses, obj)


#: Features of a verified detection (:func:`outline_features`), in this order.
FEATURES = ("contour", "template", "line2d", "lines", "thinness", "elongation", "size",
            "clutter")


@jax.jit
def outline_features(model: ContourModel, response: Array, K: Array, poses: Array, obj: Array,
                     contour: Array, template: Array, lines: Array) -> Array:
    """[P, len(FEATURES)] what a detection's score is calibrated from (:data:`FEATURES`):
    its contour score and template score (given), the LINE-2D similarity of its outline
    (the nearest stored view's points at poses [P, 4, 4]) with ``response`` (over the points
    inside the image, as :func:`fit_templates`), the share of its
    correspondence lines that were valid (``lines``, :func:`verify`'s), and the
    outline's shape in the image: thinness (the spread across its main axis, sqrt of the
    smaller eigenvalue of the points' covariance, over the projected radius of the part's
    bounding sphere), elongation (sqrt of the smaller over the larger eigenvalue) and size
    (log of the projected diameter in px), and the clutter inside its box: the mean response
    over the box and the orientation bins, the similarity any outline would reach there by
    chance (a contrario: a similarity counts for less where every orientation is
    everywhere). Few-line outlines (a plate seen edge-on, a pin) fit clutter; the share of
    good outlines among the candidates of each shape differs."""
    H, W = response.shape[1:]
    # Summed-area table of the mean response: a box's mean in four lookups.
    table = jnp.pad(jnp.cumsum(jnp.cumsum(jnp.mean(response, 0), 0), 1), ((1, 0), (1, 0)))

    def one(T, o):
        uv, N, ok = _outline(model, T, o, K)
        b = orientation_bin(N[:, 0], N[:, 1])
        ui, vi = jnp.round(uv[:, 0]).astype(jnp.int32), jnp.round(uv[:, 1]).astype(jnp.int32)
        inside = ok & (ui >= 0) & (ui < W) & (vi >= 0) & (vi < H)
        r = response[b, jnp.clip(vi, 0, H - 1), jnp.clip(ui, 0, W - 1)]
        n = jnp.maximum(jnp.sum(ok), 1)
        sim = _visible_mean(r, inside, n)
        w = ok.astype(jnp.float32) / n
        mean = jnp.sum(w[:, None] * uv, 0)
        c = uv - mean
        cov = jnp.einsum("n,ni,nj->ij", w, c, c)
        ev = jnp.linalg.eigvalsh(cov)
        r_px = model.radius[o] * jnp.sqrt(K[0, 0] * K[1, 1]) / jnp.maximum(T[2, 3], 1e-6)
        size = jnp.array([W, H])
        lo = jnp.clip(jnp.round(jnp.min(jnp.where(ok[:, None], uv, 1e9), 0)), 0, size)
        hi = jnp.clip(jnp.round(jnp.max(jnp.where(ok[:, None], uv, -1e9), 0)) + 1, 0, size)
        lo, hi = lo.astype(jnp.int32), hi.astype(jnp.int32)
        area = jnp.maximum((hi[0] - lo[0]) * (hi[1] - lo[1]), 1)
        clutter = (table[hi[1], hi[0]] - table[lo[1], hi[0]] - table[hi[1], lo[0]]
                   + table[lo[1], lo[0]]) / area
        return jnp.stack([sim, jnp.sqrt(jnp.maximum(ev[0], 0.0)) / r_px,
                          jnp.sqrt(jnp.maximum(ev[0], 0.0) / jnp.maximum(ev[1], 1e-9)),
                          jnp.log(2.0 * r_px), clutter])

    shape = jax.vmap(one)(poses, obj)
    return jnp.concatenate([contour[:, None], template[:, None], shape[:, :1], lines[:, None],
                            shape[:, 1:]], 1)


#: Logistic weights of :func:`calibrated_score` over :func:`score_inputs` (the last entry is
#: the bias), fitted by ``python -m train.templates_score`` on cell scenes of parts no
#: evaluation uses (docs/benchmarks.md, "Training-free detection").
SCORE_WEIGHTS = (0.3269, 0.1387, 0.5302, 2.092, 3.954, 0.513, 0.666, -1.508, -8.986)


def score_inputs(features: np.ndarray) -> np.ndarray:
    """[P, F] the inputs of the score's logistic model from :func:`outline_features` [P, F]:
    the three similarities as log-odds (clipped to [1e-3, 1 - 1e-3]), the rest as they are."""
    f = np.asarray(features, np.float64)
    p = np.clip(f[:, :3], 1e-3, 1 - 1e-3)
    return np.concatenate([np.log(p / (1 - p)), f[:, 3:]], 1)


def score_logit(features: np.ndarray, weights=SCORE_WEIGHTS) -> np.ndarray:
    """[P] the log-odds of the logistic model over :func:`score_inputs` of candidates'
    :func:`outline_features` [P, F] with ``weights`` [F + 1] (the last is the bias), or
    [P, F + 1]: each candidate its own (its part's, :func:`fit_part_weights`). What the
    learned verifier's correction is added to."""
    w = np.asarray(weights, np.float64)
    return np.sum(score_inputs(features) * w[..., :-1], -1) + w[..., -1]


def calibrated_score(features: np.ndarray, weights=SCORE_WEIGHTS, evidence=0.0) -> np.ndarray:
    """[P] the probability that each verified candidate (:func:`outline_features` [P, F]) is
    a right detection (its part, box IoU >= 0.5): the logistic model's :func:`score_logit`
    with ``weights``, plus ``evidence`` [P] (or a scalar), the learned verifier's correction
    of the log-odds (0: none)."""
    z = score_logit(features, weights) + np.asarray(evidence)
    return 1.0 / (1.0 + np.exp(-z))


def fit_score_weights(features: np.ndarray, right: np.ndarray, l2: float = 1e-2,
                      evidence=0.0) -> np.ndarray:
    """[F + 1] the weights of :func:`calibrated_score` that fit candidates' features [P, F] to
    whether each was right [P] (bool): L2-regularised logistic regression (``l2`` on the
    weights of the standardised inputs, not the bias) by SciPy's L-BFGS-B, with the verifier's
    ``evidence`` [P] as a fixed offset of the log-odds (what :func:`calibrated_score` adds)."""
    from scipy.optimize import minimize

    X = score_inputs(features)
    y = np.asarray(right, np.float64)
    offset = np.broadcast_to(np.asarray(evidence, np.float64), y.shape)
    mu, sd = X.mean(0), X.std(0) + 1e-9
    Z = np.concatenate([(X - mu) / sd, np.ones((len(X), 1))], 1)

    def loss(w):
        z = Z @ w + offset
        p = 1.0 / (1.0 + np.exp(-z))
        reg = np.concatenate([w[:-1], [0.0]])
        return (np.sum(np.logaddexp(0.0, z) - y * z) / len(y) + l2 * np.sum(reg ** 2),
                Z.T @ (p - y) / len(y) + 2.0 * l2 * reg)

    w = minimize(loss, np.zeros(Z.shape[1]), jac=True, method="L-BFGS-B").x
    return np.concatenate([w[:-1] / sd, [w[-1] - np.sum(w[:-1] * mu / sd)]])


def right_candidates(xyxy: np.ndarray, parts: np.ndarray, gt_boxes: np.ndarray,
                     gt_parts: np.ndarray, iou: float = 0.5) -> np.ndarray:
    """[P, G] bool: candidate p (box ``xyxy`` [P, 4], part ``parts`` [P]) is a right detection
    of ground-truth instance g (box ``gt_boxes`` [G, 4] xyxy, part ``gt_parts`` [G]): its part,
    box IoU >= ``iou``. What :func:`calibrated_score` estimates, and what fits it."""
    overlap = np.asarray(box_iou(np.asarray(xyxy, np.float64).reshape(-1, 4),
                                 np.asarray(gt_boxes, np.float64).reshape(-1, 4)))
    return (overlap >= iou) & (np.asarray(parts)[:, None] == np.asarray(gt_parts)[None])


#: Fewest right (and wrong) candidates of a part for :func:`fit_part_weights` to fit its own
#: weights.
MIN_PER_PART = 10


def fit_part_weights(features: np.ndarray, right: np.ndarray, parts: np.ndarray,
                     l2: float = 1e-2, min_count: int = MIN_PER_PART,
                     evidence=0.0) -> dict[int, np.ndarray]:
    """{part: [F + 1]} the weights of :func:`calibrated_score` fitted on each part's candidates
    alone (:func:`fit_score_weights` per part; ``parts`` [P] the candidates' parts): a cell's
    calibration on scenes of its own parts, where what a right candidate looks like differs
    from part to part (a plate's outline is as elongated as the tray's squares seen
    obliquely, a gear's is round). A part with fewer than ``min_count`` right or wrong
    candidates is left out: it keeps the shared weights. ``evidence`` [P]: the verifier's
    corrections, fixed offsets of the log-odds (:func:`fit_score_weights`)."""
    features, right, parts = np.asarray(features), np.asarray(right, bool), np.asarray(parts)
    evidence = np.broadcast_to(np.asarray(evidence, np.float64), parts.shape)
    out = {}
    for p in np.unique(parts):
        mine = parts == p
        if min(right[mine].sum(), (~right[mine]).sum()) >= min_count:
            out[int(p)] = fit_score_weights(features[mine], right[mine], l2, evidence[mine])
    return out


@functools.partial(jax.jit, static_argnames=("settings", "lines"))
def verify(model: ContourModel, image: Array, K: Array, poses: Array, obj: Array,
           settings: ContourSettings, lines: int) -> tuple[Array, Array, Array, Array]:
    """Refine candidate poses [P, 4, 4] T_cam_obj of objects ``obj`` [P] in one image (uint8
    [H, W, 3]) with the contour refiner on ``lines`` outline points, no occluders; returns the
    poses, their contour scores [P], outline boxes [P, 4] xyxy (of the full outlines) and the
    share of the ``lines`` that were valid [P]."""
    P = poses.shape[0]
    full, n = model, model.points.shape[2]
    if lines < n:  # a coarser outline: every (n / lines)-th point
        pick = jnp.asarray(np.linspace(0, n, lines, endpoint=False).astype(np.int32))
        model = model._replace(points=model.points[:, :, pick], normals=model.normals[:, :, pick],
                               valid=model.valid[:, :, pick])
    none = -jnp.ones((1, 8, 8), jnp.int32)
    res = refine_poses(model, image[None], K[None], jnp.eye(4)[None], poses, obj,
                       jnp.arange(P, dtype=jnp.int32), none, jnp.zeros((1, 8, 8)),
                       jnp.ones((P, 1), bool), settings)
    return (res.poses, res.scores, outline_boxes(full, res.poses, obj, K),
            res.lines / model.points.shape[2])


def verifier_boxes(xyxy: np.ndarray, margin: float = 1.3, min_side: float = 16.0) -> np.ndarray:
    """[P, 4] xyxy the square crop boxes the verifier reads: centred on each outline box
    ``xyxy`` [P, 4], ``margin`` times its longer side (at least ``min_side`` px), running out of
    the image where the outline does (the crop is zero there)."""
    xyxy = np.asarray(xyxy, np.float64).reshape(-1, 4)
    c = (xyxy[:, :2] + xyxy[:, 2:]) / 2
    side = np.maximum(margin * np.max(xyxy[:, 2:] - xyxy[:, :2], 1), min_side)
    return np.concatenate([c - side[:, None] / 2, c + side[:, None] / 2], 1).astype(np.float32)


def verifier_inputs(image: np.ndarray, K: np.ndarray, poses: np.ndarray, obj: np.ndarray,
                    xyxy: np.ndarray, meshes: Sequence[RasterMesh]) -> tuple[np.ndarray, np.ndarray]:
    """What :class:`~threept_jax.models.verifier.CandidateVerifier` reads of P candidates of an
    image [H, W, 3] uint8 with K [3, 3]: the image in each candidate's :func:`verifier_boxes`
    box (bilinear, [P, CROP, CROP, 3] uint8) and its part ``meshes[obj]`` rendered at its pose
    ``poses`` [P, 4, 4] T_cam_obj with that crop's intrinsics ([P, CROP, CROP, 3] uint8:
    silhouette, geometric edges, |normal z| inside the silhouette, 0-255). Each part's poses
    are rendered in one call padded to a power of two (a few compiled renders per mesh size)."""
    boxes = verifier_boxes(xyxy)
    n = len(boxes)
    renders = np.zeros((n, CROP, CROP, 3), np.uint8)
    if not n:
        return np.zeros((0, CROP, CROP, 3), np.uint8), renders
    crops, Kc = crop_and_resize(jnp.asarray(image), jnp.asarray(boxes), (CROP, CROP),
                                K=jnp.asarray(K, jnp.float32))
    crops = np.clip(np.asarray(crops), 0, 255).astype(np.uint8)
    Kc, poses, obj = np.asarray(Kc), np.asarray(poses, np.float32), np.asarray(obj)
    for o in np.unique(obj):
        rows = np.flatnonzero(obj == o)
        idx = np.concatenate([rows, np.full((1 << (len(rows) - 1).bit_length()) - len(rows),
                                            rows[0])])
        out = render(meshes[int(o)], poses[idx], Kc[idx], (CROP, CROP),
                     ("mask", "edge", "normal"))
        mask = np.asarray(out["mask"])[:len(rows)]
        renders[rows, ..., 0] = mask * 255
        renders[rows, ..., 1] = np.asarray(out["edge"])[:len(rows)] * 255
        shade = np.clip(np.abs(np.asarray(out["normal"])[:len(rows), ..., 2]) * 255, 0, 255)
        renders[rows, ..., 2] = shade * mask
    return crops, renders
