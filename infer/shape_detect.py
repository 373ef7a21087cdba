"""The training-free detector: shape search from the CAD model alone (``--detector templates``).

:class:`ShapeSearchDetector` has the interface of :class:`infer.detect.SceneDetector`
(``objects``, ``detect(image, K)`` -> :class:`infer.detect.Detections`) and needs no network:
selective-search proposals, each part's contour templates fitted to each proposal, the best
poses refined by the contour refiner (:mod:`threept_jax.pipeline.shape_search`). Its
detections carry a refined pose, so the render-and-compare stage (the contour refiner by
default) starts where the search ended; its score is the probability that the detection is
right (its part, box IoU >= 0.5), a logistic model of the candidate's contour and template
scores and its outline's shape and surroundings
(:func:`~threept_jax.pipeline.shape_search.calibrated_score`, fitted by ``python -m
train.templates_score`` on cells of parts no evaluation uses).

A learned verifier corrects the score by default (``verifier="shipped"``,
``models/templates-verifier``, :class:`threept_jax.models.verifier.CandidateVerifier`: the
image around each candidate beside its part rendered at its pose, trained by ``python -m
train.templates_verifier`` on cells of other parts; ``verifier=None`` turns it off). On three
held-out sets of 48 images it raises box AP50 by 0.04-0.08 with the shared score, and by
0.03 with a cell's own calibration, and costs about 0.35 s an image (docs/benchmarks.md, "48
images a set").

A cell can calibrate the score on scenes of its own parts (``python -m train.templates_score
--cell DATA``: a logistic model per part, no network): :func:`load_score_weights` reads the
file it writes, ``ShapeSearchDetector(score_weights=...)`` scores each part's candidates with
its weights (``--templates-score FILE`` on the commands).

Building it renders each mesh's contour views once (the contour refiner's cache under
``cache_dir``, a few seconds per mesh on 2 CPU cores); the first image of a size compiles the
template fit and the verification (cold), later images reuse them (warm). Within
:func:`shared_searches`, detectors that differ only in their score weights search an image once.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import pathlib
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from typing import NamedTuple

import cv2
import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from infer.contour_refine import _cached_contours, hash_mesh
from infer.detect import Detection, Detections
from threept_jax.data.pretrained import VERIFIER_DIR, load_verifier
from threept_jax.geometry.validate import validate_intrinsics
from threept_jax.models.verifier import CandidateVerifier
from threept_jax.pipeline.contour import stack_contours
from threept_jax.pipeline.shape_search import (
    FEATURES,
    SCORE_WEIGHTS,
    ShapeSearchSettings,
    box_variants,
    calibrated_score,
    fit_templates,
    orientation_response,
    outline_features,
    poses_from_fit,
    proposals,
    score_inputs,
    select_candidates,
    shape_templates,
    stack_templates,
    verifier_inputs,
    verify,
)
from threept_jax.render.mesh import bucket_size, prepare_mesh, to_raster_mesh

#: Without a depth range, objects are searched from this projected diameter (px) to the image's
#: longer side.
MIN_DIAMETER_PX = 32.0
#: Default score (a probability) a detection must exceed. A dark or grey image with sensor noise
#: (sigma 3-8 grey levels) or uniform noise gives candidates scoring 0.08-0.35; on the held-out
#: cells 65 % of the verified candidates above 0.4 are right (docs/benchmarks.md); evaluations
#: pass 0 (AP ranks every detection).
SCORE_THRESHOLD = 0.4
#: How many images' verified candidates :func:`shared_searches` keeps (about 30 kB each).
SHARED_IMAGES = 64


def load_score_weights(path: str | os.PathLike) -> dict[int, tuple[float, ...]]:
    """``{obj_id: weights}`` of a cell's score calibration (the JSON ``python -m
    train.templates_score --cell`` writes), checked: its features must be this version's
    :data:`~threept_jax.pipeline.shape_search.FEATURES` and every weight finite."""
    path = pathlib.Path(path)
    refit = f"refit it: python -m train.templates_score --cell DATA --out {path}"
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise FileNotFoundError(f"templates score file {path} not found: {refit}") from None
    except (OSError, ValueError) as e:
        raise ValueError(f"templates score file {path} is not readable JSON ({e}): {refit}"
                         ) from None
    if not isinstance(data, dict) or not isinstance(data.get("parts"), dict):
        raise ValueError(f"{path} has no 'parts' (obj_id -> weights): it is not a cell "
                         f"calibration; {refit}")
    if data.get("features") != [*FEATURES, "bias"]:
        raise ValueError(f"{path} was fitted on the features {data.get('features')}, this "
                         f"version scores {[*FEATURES, 'bias']}: {refit}")
    out = {}
    for k, w in data["parts"].items():
        if not str(k).isdigit():
            raise ValueError(f"{path}: part id {k!r} is not an obj_id (an integer): {refit}")
        try:
            w = np.asarray(w, np.float64)
        except (TypeError, ValueError):
            w = np.zeros(0)
        if w.shape != (len(FEATURES) + 1,) or not np.isfinite(w).all():
            raise ValueError(f"{path}: the weights of part {k} must be {len(FEATURES) + 1} "
                             f"finite numbers, got {data['parts'][k]}: {refit}")
        out[int(k)] = tuple(float(v) for v in w)
    return out


class Candidates(NamedTuple):
    """Verified candidates of one image, before scoring and NMS: refined poses [n, 4, 4]
    T_cam_obj, ``obj`` [n] (rows of the detector's ``objects``), outline boxes ``xyxy`` [n, 4]
    (clipped to the image), :data:`~threept_jax.pipeline.shape_search.FEATURES` [n, F] and
    the verifier's ``evidence`` [n] (its correction to the score's log-odds; zeros without
    one). Read them, do not write to them: inside :func:`shared_searches` they are shared and
    read-only."""

    poses: np.ndarray
    obj: np.ndarray
    xyxy: np.ndarray
    features: np.ndarray
    evidence: np.ndarray


#: The shipped verifier, loaded once per process (:func:`shipped_verifier`).
_SHIPPED_VERIFIER: list[CandidateVerifier] = []


def shipped_verifier() -> CandidateVerifier:
    """The verifier of ``models/templates-verifier`` (checked against its ``SOURCE.json``),
    loaded on first use."""
    if not _SHIPPED_VERIFIER:
        _SHIPPED_VERIFIER.append(load_verifier(VERIFIER_DIR))
    return _SHIPPED_VERIFIER[0]


#: Faces of the meshes the verifier's 64 px renders draw: T-LESS and ITODD parts decimated from
#: 4096 to 1024 faces render 2.5x faster with the same box AP50 (docs/benchmarks.md).
VERIFIER_FACES = 1024


def raster_meshes(objects: Sequence) -> list:
    """The parts' meshes as the verifier's renders draw them (decimated to
    :data:`VERIFIER_FACES`, one face bucket for every part under it: one compiled render for
    all)."""
    prepared = [prepare_mesh(o.mesh, max_faces=VERIFIER_FACES, texture_size=None)
                for o in objects]
    bucket = bucket_size(max(VERIFIER_FACES, *(p.num_faces for p in prepared)))
    return [to_raster_mesh(p, face_bucket=bucket) for p in prepared]


@nnx.jit
def _evidence(verifier: CandidateVerifier, crops, renders, inputs):
    return verifier(crops, renders, inputs)


class _Searched(NamedTuple):
    """An image's search inside :func:`shared_searches`: its verified candidates (None: none)
    and the evidence of each verifier that scored them, ``{id(verifier): (verifier,
    evidence [n])}`` (the verifier held, so its id stays its own); None outside it."""

    candidates: Candidates | None
    evidence: dict | None


#: Inside :func:`shared_searches`: the searches of the images searched last, oldest first,
#: keyed by the search (parts' meshes, depth range, settings), the image and its K; None
#: outside.
_SHARED: OrderedDict[str, _Searched] | None = None


@contextlib.contextmanager
def shared_searches():
    """Within it, an image that a detector of the same parts, depth range and settings searched
    is not searched again: the verified candidates do not depend on the score weights, so the
    shared score, a cell's calibration and the cell detector's own templates search (``make
    demo``'s settings on the same images) share one search, and one verifier's evidence on
    it (the last :data:`SHARED_IMAGES` images' candidates are kept). Outside it every call
    searches, a repeated image too (what a timing of the warm path must see)."""
    global _SHARED
    outer = _SHARED
    if outer is None:  # nested: the outer context's searches stay shared
        _SHARED = OrderedDict()
    try:
        yield
    finally:
        _SHARED = outer


class ShapeSearchDetector:
    """Detects objects (anything with ``obj_id`` and ``mesh``, mm) by shape search (module
    docstring). ``depth_range``: (zmin, zmax) mm of the objects' centres from the camera (a
    cell's ``cell.json``); None: any distance at which an object appears 32 px to the image's
    size. ``score_threshold``: score a detection must exceed (:data:`SCORE_THRESHOLD`);
    ``max_detections`` per image. ``score_weights``: ``{obj_id: weights}`` of a cell's own
    calibration (:func:`load_score_weights`); parts it lacks (and without it, all) are scored
    with the shared :data:`~threept_jax.pipeline.shape_search.SCORE_WEIGHTS`. ``verifier``: a
    :class:`~threept_jax.models.verifier.CandidateVerifier` whose correction is added to the
    score's log-odds, ``"shipped"`` (the default, ``models/templates-verifier``) or None."""

    def __init__(self, objects: Sequence, *, depth_range: tuple[float, float] | None = None,
                 score_threshold: float = SCORE_THRESHOLD, max_detections: int = 100,
                 settings: ShapeSearchSettings | None = None,
                 cache_dir: str | os.PathLike | None = None,
                 score_weights: Mapping[int, Sequence[float]] | None = None,
                 verifier: CandidateVerifier | str | None = "shipped"):
        if not objects:
            raise ValueError("no objects to detect: give at least one mesh")
        if depth_range is not None:
            lo, hi = (float(z) for z in depth_range)
            if not 0 < lo < hi:
                raise ValueError(f"depth_range must be 0 < zmin < zmax in mm, got {depth_range}")
        self.objects = sorted(objects, key=lambda o: o.obj_id)
        self.depth_range = None if depth_range is None else (lo, hi)
        self.score_threshold = float(score_threshold)
        self.max_detections = int(max_detections)
        self.settings = settings or ShapeSearchSettings()
        weights = [np.ravel(np.asarray((score_weights or {}).get(o.obj_id, SCORE_WEIGHTS),
                                       np.float64)) for o in self.objects]
        for o, w in zip(self.objects, weights):
            if len(w) != len(FEATURES) + 1 or not np.isfinite(w).all():
                raise ValueError(f"the score weights of part {o.obj_id} must be "
                                 f"{len(FEATURES) + 1} finite numbers ({', '.join(FEATURES)}, "
                                 f"bias), got {w.tolist()}")
        self.score_weights = np.stack(weights)  # [O, F + 1]
        cache = None if cache_dir is None else pathlib.Path(cache_dir)
        contours = [_cached_contours(o.mesh, cache) for o in self.objects]
        self.model = stack_contours(contours)
        templates = stack_templates([shape_templates(c, self.settings) for c in contours])
        self._empty = ~templates.valid.any((1, 2))  # objects whose renders have no outline
        self._rotations = templates.rotations.astype(np.float64)
        # On the device once, not at every image.
        self.templates = jax.tree.map(jnp.asarray, templates)
        self.centers = np.stack([c["center"] for c in contours])
        self.diameters = np.array([2.0 * float(c["radius"]) for c in contours])
        if isinstance(verifier, str):
            if verifier != "shipped":
                raise ValueError(f"verifier must be a CandidateVerifier, 'shipped' or None, "
                                 f"got {verifier!r}")
            verifier = shipped_verifier()
        self.verifier = verifier
        self.rasters = [] if verifier is None else raster_meshes(self.objects)
        # What the search's candidates depend on, with the image and K (not the score weights
        # nor the verifier, whose evidence is added after the search).
        search = hashlib.sha256(repr((self.depth_range, self.settings)).encode())
        for o in self.objects:
            search.update(f"|{o.obj_id}|{len(o.mesh.vertices)}|".encode())
            hash_mesh(search, o.mesh)
        self._search = search

    def _depths(self, o: int, K: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
        if self.depth_range is not None:
            return np.asarray(self.depth_range, np.float32)
        f = float(np.sqrt(K[0, 0] * K[1, 1]))
        d = self.diameters[o]
        return np.array([f * d / max(hw), f * d / MIN_DIAMETER_PX], np.float32)

    def _verify(self, image: np.ndarray, response, K: np.ndarray, poses: np.ndarray,
                obj: np.ndarray, template: np.ndarray):
        """Stage 3 of m <= ``candidates`` poses [m, 4, 4] of parts ``obj`` [m] (rows of
        ``objects``) fitted with template scores ``template`` [m]: refined poses [m, 4, 4],
        outline boxes xyxy [m, 4] (clipped to the image) and :data:`FEATURES` [m, F] (NumPy).
        Padded to ``candidates`` (one compiled verification per image size)."""
        s = self.settings
        m = len(poses)
        pad = np.concatenate([np.arange(m), np.zeros(s.candidates - m, np.int64)])
        K32 = jnp.asarray(K, jnp.float32)
        o = jnp.asarray(np.asarray(obj)[pad], jnp.int32)
        refined, contour, xyxy, lines = verify(
            self.model, jnp.asarray(image), K32, jnp.asarray(np.asarray(poses)[pad], jnp.float32),
            o, settings=s.contour, lines=s.lines)
        features = outline_features(self.model, response, K32, refined, o, contour,
                                    jnp.asarray(np.asarray(template)[pad], jnp.float32), lines)
        refined, xyxy, features = (np.asarray(a)[:m] for a in (refined, xyxy, features))
        # Boxes of what the image shows: a part cut by the image's side is boxed to it.
        hw = image.shape[:2]
        xyxy = np.clip(xyxy, 0, np.array([hw[1], hw[0], hw[1], hw[0]], np.float32))
        return refined, xyxy, features

    def _evidence(self, image: np.ndarray, K: np.ndarray, c: Candidates,
                  known: dict | None = None) -> np.ndarray:
        """The verifier's correction [m] to the log-odds of the searched candidates ``c`` of
        an image (zeros without a verifier): their crops and renders through the verifier,
        padded to ``candidates`` (one compiled verifier). ``known``: a shared search's
        evidence (:class:`_Searched`), read when this verifier scored it, else added to."""
        m = len(c.obj)
        if self.verifier is None:
            return np.zeros(m, np.float32)
        if known is not None and id(self.verifier) in known:
            return known[id(self.verifier)][1]
        pad = np.concatenate([np.arange(m), np.zeros(self.settings.candidates - m, np.int64)])
        crops, renders = verifier_inputs(image, K, c.poses, c.obj, c.xyxy, self.rasters)
        inputs = score_inputs(c.features).astype(np.float32)
        evidence = np.asarray(_evidence(self.verifier, crops[pad], renders[pad],
                                        inputs[pad]))[:m]
        if known is not None:
            evidence.flags.writeable = False
            known[id(self.verifier)] = (self.verifier, evidence)
        return evidence

    def candidates(self, image: np.ndarray, K: np.ndarray) -> Candidates | None:
        """The verified candidates of one RGB image [H, W, 3] (uint8) with intrinsics K [3, 3]
        (pixels of this image), before scoring and NMS, with the verifier's evidence when the
        detector has one; None when there are none (no proposal, no outline). Within
        :func:`shared_searches`, an image searched there by a detector of the same search is
        not searched again (its candidates' arrays are read-only there)."""
        image = np.ascontiguousarray(image)
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise ValueError(f"image must be uint8 RGB [H, W, 3], got {image.dtype} "
                             f"{image.shape}")
        K = validate_intrinsics(K, "K", image_hw=image.shape[:2]).astype(np.float64)
        found, known = self._searched(image, K)
        if found is None or self.verifier is None:
            return found
        return found._replace(evidence=self._evidence(image, K, found, known))

    def _searched(self, image: np.ndarray, K: np.ndarray) -> _Searched:
        """:meth:`candidates` of a checked image and K without the verifier's evidence (zero):
        searched, or read from :func:`shared_searches`."""
        shared = _SHARED
        if shared is None:
            return _Searched(self._candidates(image, K), None)
        key = self._search.copy()
        key.update(f"|{image.shape}|".encode())
        key.update(image.tobytes())
        key.update(K.tobytes())
        key = key.hexdigest()
        if key in shared:
            shared.move_to_end(key)
            return shared[key]
        found = self._candidates(image, K)
        if found is not None:
            for a in found:
                a.flags.writeable = False
        shared[key] = _Searched(found, {})
        while len(shared) > SHARED_IMAGES:
            shared.popitem(last=False)
        return shared[key]

    def _candidates(self, image: np.ndarray, K: np.ndarray) -> Candidates | None:
        """:meth:`candidates` of a checked image and K (float64), searched."""
        hw = image.shape[:2]
        s = self.settings
        boxes = proposals(image, s)
        if not len(boxes) or self._empty.all():
            return None
        # A fixed proposal count: one compiled fit per image size.
        padded = np.zeros((s.max_proposals, 4), np.float32)
        padded[:, 2:] = 1.0
        padded[:len(boxes)] = boxes
        response = jnp.asarray(orientation_response(image, s.spread, s.min_gradient))
        found = []  # (template score, object, pose)
        for o in np.flatnonzero(~self._empty):
            t = self.templates
            score, idx, depth, uv = jax.device_get(fit_templates(
                response, padded, t.xy[o], t.bins[o], t.valid[o], K.astype(np.float32),
                self._depths(o, K, hw), box_fit=s.box_fit, k=s.per_proposal))
            score, idx, depth, uv = (a[:len(boxes)] for a in (score, idx, depth, uv))
            keep = np.asarray(cv2.dnn.NMSBoxes(boxes.tolist(), score[:, 0].tolist(), 1e-6,
                                               s.proposal_nms), int).ravel()
            if not len(keep):
                continue
            sc, ix, z, c = (a[keep].reshape(-1, *a.shape[2:]) for a in (score, idx, depth, uv))
            ok = sc > 0
            poses = poses_from_fit(self._rotations[o][ix[ok]],
                                   np.broadcast_to(self.centers[o], (ok.sum(), 3)),
                                   z[ok].astype(np.float64), c[ok].astype(np.float64), K)
            found += [(float(a), int(o), p) for a, p in zip(sc[ok], poses)]
        if not found:
            return None
        template, obj, poses = (np.array(a) for a in zip(*found))
        chosen = select_candidates(template, obj, s.candidates)
        refined, xyxy, features = self._verify(image, response, K, poses[chosen], obj[chosen],
                                               template[chosen])
        return Candidates(refined, obj[chosen].astype(np.int32), xyxy, features,
                          np.zeros(len(chosen), np.float32))

    def detect(self, image: np.ndarray, K: np.ndarray) -> Detections:
        """Detections in one RGB image [H, W, 3] (uint8) with intrinsics K [3, 3] (pixels of
        this image), best first; ``best_score`` is the best score of any candidate."""
        c = self.candidates(image, K)
        if c is None:
            return Detections()
        s = self.settings
        scores = np.asarray(calibrated_score(c.features, self.score_weights[c.obj], c.evidence))
        refined, obj, xyxy = c.poses, c.obj, c.xyxy
        finite = np.isfinite(scores) & np.isfinite(xyxy).all(1)
        order = [i for i in np.argsort(-np.where(finite, scores, -np.inf)) if finite[i]]
        xywh = [[float(b[0]), float(b[1]), float(b[2] - b[0]), float(b[3] - b[1])]
                for b in xyxy]
        keep = np.asarray(cv2.dnn.NMSBoxes([xywh[i] for i in order],
                                           [float(scores[i]) for i in order],
                                           self.score_threshold, s.nms_iou), int).ravel()
        keep = [order[j] for j in keep]
        dets = Detections(best_score=float(np.max(scores[finite])) if finite.any() else -np.inf)
        for i in keep[:self.max_detections]:
            o = self.objects[obj[i]]
            dets.append(Detection(o.obj_id, xyxy[i].astype(np.float32), float(scores[i]),
                                  refined[i][None].astype(np.float32),
                                  np.array([scores[i]], np.float32), np.zeros(0, np.float32)))
        return dets

    @property
    def max_boxes(self) -> int:
        """How many boxes :meth:`poses_in_boxes` takes a call: each verifies at least half its
        ``per_box`` best-fitted poses."""
        return 2 * self.settings.candidates // self.settings.per_box

    def poses_in_boxes(self, image: np.ndarray, K: np.ndarray, boxes: np.ndarray,
                       obj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The pose of each given box of a known part: the part's templates fitted inside the
        box and inside its shifted and rescaled copies (stage 2, ``box_scales`` and
        ``box_shift`` of the settings), the best of them (``per_box`` per copy, at most
        ``candidates // n`` per box) refined by the contour refiner (stage 3), the one with the
        best calibrated score kept (the detector's score weights of the part: a right outline,
        not only a well-fitted one). image uint8 [H, W, 3], K [3, 3], boxes [n, 4] xyxy, obj
        [n] (rows of ``objects``); returns poses [n, 4, 4] T_cam_obj and those scores [n], the
        probability that the pose's outline is right (-inf and a NaN pose where no template of
        the part fits the box: outside the depth range, or a part whose renders have no
        outline). At most :attr:`max_boxes` boxes a call."""
        s = self.settings
        n = len(boxes)
        most = self.max_boxes
        if n > most:
            raise ValueError(f"{n} boxes, at most {most} per call (2 * candidates // per_box)")
        poses = np.full((n, 4, 4), np.nan)
        scores = np.full(n, -np.inf)
        if not n:
            return poses, scores
        hw = image.shape[:2]
        K = validate_intrinsics(K, "K", image_hw=hw).astype(np.float64)
        response = jnp.asarray(orientation_response(image, s.spread, s.min_gradient))
        xywh = np.concatenate([boxes[:, :2], boxes[:, 2:] - boxes[:, :2]], -1)
        variants = box_variants(xywh, s.box_scales, s.box_shift)  # [n, V, 4]
        v = variants.shape[1]
        k = min(s.per_box, s.num_views * s.num_inplane)
        found = []  # (template score, box, pose)
        for o in np.unique(obj):
            if self._empty[o]:
                continue
            rows = np.flatnonzero(obj == o)
            # A part's boxes padded to a power of two (at most ``most``): a few compiled fits
            # per image size, not one of ``most`` boxes for every call (151 against 28 ms a
            # part for 3 boxes' 15 copies each, 2 cores).
            slots = min(most, 1 << (len(rows) - 1).bit_length())
            padded = np.zeros((slots * v, 4), np.float32)
            padded[:, 2:] = 1.0
            padded[:len(rows) * v] = variants[rows].reshape(-1, 4)
            t = self.templates
            score, idx, depth, uv = (a[:len(rows) * v] for a in jax.device_get(fit_templates(
                response, padded, t.xy[o], t.bins[o], t.valid[o], K.astype(np.float32),
                self._depths(o, K, hw), box_fit=s.box_fit, k=k)))
            ok = score > 0
            pose = poses_from_fit(self._rotations[o][idx[ok]],
                                  np.broadcast_to(self.centers[o], (ok.sum(), 3)),
                                  depth[ok].astype(np.float64), uv[ok].astype(np.float64), K)
            box = np.broadcast_to(np.repeat(rows, v)[:, None], ok.shape)[ok]
            found += list(zip(score[ok], box, pose))
        if not found:
            return poses, scores
        # The best-fitted candidates of each box, as many as the verification takes.
        found.sort(key=lambda c: -c[0])
        taken, per_box = [], np.zeros(n, int)
        for c in found:
            if per_box[c[1]] < s.candidates // n:
                taken.append(c)
                per_box[c[1]] += 1
        template, cand_box, cand_pose = (np.array(a) for a in zip(*taken))
        refined, xyxy, features = self._verify(image, response, K, cand_pose, obj[cand_box],
                                               template)
        c = Candidates(refined, obj[cand_box].astype(np.int32), xyxy, features,
                       np.zeros(len(taken), np.float32))
        calibrated = np.asarray(calibrated_score(c.features, self.score_weights[c.obj],
                                                 self._evidence(image, K, c)))
        for i in range(len(taken)):
            b = cand_box[i]
            if np.isfinite(calibrated[i]) and calibrated[i] > scores[b]:
                scores[b], poses[b] = calibrated[i], refined[i]
        return poses, scores
