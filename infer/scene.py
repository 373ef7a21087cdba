"""``find_instances``: detected instances with poses from one or several calibrated views.

Single view: every detection is an instance; its pose is the best of its hypotheses (top
template turned by the box ray, translation fitted to the box).

Multi-view (docs/design.md section 1.2): detections of each view are matched across views
along the epipolar rays through their box centres (same object id), triangulated, and kept when
seen in at least ``min_views`` views. The orientation proposals of every member view (its top
``proposals_per_view`` templates, turned by the view's box ray and brought to the world frame)
are fused with a von Mises-Fisher kernel density on SO(3); the top ``num_hypotheses`` rotations
at least ``min_angle_deg`` apart, each refined by mean shift on that density (finer than the
template grid), become the instance's hypotheses, the translation puts the
object's bounding-sphere centre at the triangulated point.

Detectors whose detections carry poses rather than an orientation distribution (the templates
and cell detectors) are fused by :func:`fuse_posed_views`: the same matching, of the poses'
projected centres; the members' own poses as the hypotheses, moved to their centres' fusion
(one view sees a part's place in the image well and its depth only through its outline's size;
views far enough apart see the depth by parallax).

Masks are the silhouettes of the best pose rendered in each view, each pixel going to the
highest-scoring instance that covers it (:func:`render_masks`); with a refiner
(``infer.run_scene``) the same rule at the refined poses.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np

from infer.detect import Detection, SceneDetector
from infer.masks import PoseRenderer, detection_masks
from threept_jax.geometry.camera import box_center_ray, camera_rotation, invert
from threept_jax.geometry.so3_kde import (
    kappa_from_std_deg,
    kde_mean_shift,
    top_k_separated,
    vmf_kde,
)
from threept_jax.geometry.triangulation import fuse_ray_estimates, match_across_views
from threept_jax.geometry.validate import validate_rigid


@dataclasses.dataclass(frozen=True)
class Instance:
    """One object instance found in a scene.

    Attributes:
      obj_id: object id.
      score: in [0, 1], the mean detection score of its views.
      T_world_obj: [4, 4] best pose in the world frame (the camera frame for one view), mm.
      hypotheses: [K, 4, 4] pose hypotheses (world frame), best first.
      hypothesis_scores: [K].
      boxes: {view index: [4] xyxy box}; views where the instance was detected.
      masks: {view index: bool [H, W]} in every view (when requested): rendered silhouettes of
        the pose, or the refiner's visible masks after refinement.
      T_world_obj_initial: the pose before refinement (None when not refined).
      refine_score: the refiner's score of the refined pose (None when not refined): the
        contour refiner's contour score in [0, 1], or a 3PT-R's logit.
      pose_score: the detection's ``pose_score`` (one view): the probability that the pose
        is right, which ranks the 6D results where the detector gives it; None: ``score``.
    """

    obj_id: int
    score: float
    T_world_obj: np.ndarray
    hypotheses: np.ndarray
    hypothesis_scores: np.ndarray
    boxes: dict
    masks: dict
    T_world_obj_initial: np.ndarray | None = None
    refine_score: float | None = None
    pose_score: float | None = None


def assign_pixels(instances: Sequence[Instance]) -> None:
    """Each pixel of each view to the first (best) instance whose mask claims it (in place)."""
    taken: dict = {}
    for x in instances:
        for v, m in x.masks.items():
            prev = taken.get(v)
            m = m if prev is None else (m & ~prev)
            x.masks[v] = m
            taken[v] = m if prev is None else (prev | m)


class Instances(list):
    """The instances of a scene (a list of :class:`Instance`, best first) and ``best_score``:
    the highest detection-candidate score in any view, kept or not (-inf when none), so an
    empty list can say whether the threshold or the cross-view matching left it empty."""

    def __init__(self, instances=(), best_score: float = -np.inf):
        super().__init__(instances)
        self.best_score = float(best_score)


def _check_views(images, Ks, T_cam_world):
    V = len(images)
    if V == 0:
        raise ValueError("a scene needs at least one image")
    if len(Ks) != V:
        raise ValueError(f"{V} images but {len(Ks)} intrinsics: give one K per view")
    if T_cam_world is None:
        if V > 1:
            raise ValueError("several views need T_cam_world [V, 4, 4] (world -> camera) per view")
        return np.eye(4, dtype=np.float32)[None]
    T = np.asarray(T_cam_world, np.float32)
    if T.shape != (V, 4, 4):
        raise ValueError(f"T_cam_world must be [V={V}, 4, 4], got {T.shape}")
    validate_rigid(T, "T_cam_world (world -> camera, OpenCV axes, mm)")
    return T


def fuse_views(detections: Sequence[Sequence[Detection]], Ks: np.ndarray, T_cam_world: np.ndarray,
               objects: dict, *, min_views: int = 3, max_epipolar_px: float = 10.0,
               proposals_per_view: int = 500, kernel_std_deg: float = 10.0,
               logit_scale: float = 10.0, num_hypotheses: int = 8,
               min_angle_deg: float = 45.0) -> list[Instance]:
    """Multi-view object generation (module docstring) from per-view detections.

    ``objects`` maps obj_id to its ``OnboardedObject`` (template rotations and sphere centre).
    Each proposal weighs ``softmax(logit_scale * cosine)`` over its view's proposals (the
    detector's own orientation logits: pass its learned ``logit_scale``), so every view carries
    the same mass.
    """
    V = len(detections)
    centres = [np.array([(d.box[:2] + d.box[2:]) / 2 - 0.5 for d in dets]).reshape(-1, 2)
               for dets in detections]
    labels = [np.array([d.obj_id for d in dets], np.int64) for dets in detections]
    tracks = match_across_views(centres, Ks, T_cam_world, labels=labels,
                                max_epipolar_px=max_epipolar_px, min_views=min(min_views, V))
    T_world_cam = np.asarray(invert(jnp.asarray(T_cam_world)))
    kappa = kappa_from_std_deg(kernel_std_deg)
    out = []
    for m in range(len(tracks.points)):
        members = [(v, detections[v][int(i)]) for v, i in enumerate(tracks.detections[m]) if i >= 0]
        obj = objects[members[0][1].obj_id]
        props, weights = [], []
        for v, det in members:
            top = np.argsort(-det.template_scores)[:proposals_per_view]
            ray = box_center_ray(np.asarray(det.box, np.float64), Ks[v].astype(np.float64))
            R_cam = camera_rotation(obj.template_rotations[top], ray)
            props.append(T_world_cam[v, :3, :3].astype(np.float64) @ R_cam)
            logits = logit_scale * det.template_scores[top].astype(np.float64)
            w = np.exp(logits - logits.max())
            weights.append(w / w.sum())
        props = np.concatenate(props).astype(np.float32)
        weights = np.concatenate(weights).astype(np.float32)
        density = vmf_kde(props, props, weights, kappa)
        idx, valid = top_k_separated(props, density, num_hypotheses, min_angle_deg)
        idx, valid = np.asarray(idx), np.asarray(valid)
        R = np.asarray(kde_mean_shift(props[idx], props, weights, kappa), np.float64)
        t = tracks.points[m][None] - R @ obj.center.astype(np.float64)
        hyp = np.tile(np.eye(4), (len(R), 1, 1))
        hyp[:, :3, :3], hyp[:, :3, 3] = R, t
        scores = np.where(valid, np.asarray(density)[idx], -np.inf)
        out.append(Instance(obj.obj_id, float(np.mean([d.score for _, d in members])),
                            hyp[0].astype(np.float32), hyp.astype(np.float32),
                            scores.astype(np.float32), {v: d.box for v, d in members}, {}))
    out.sort(key=lambda x: -x.score)
    return out


def find_instances(detector: SceneDetector, images: Sequence[np.ndarray],
                   Ks: Sequence[np.ndarray], T_cam_world: np.ndarray | None = None, *,
                   with_masks: bool = True, min_views: int = 3,
                   renderer: PoseRenderer | None = None) -> Instances:
    """Instances in a scene seen by one or several calibrated RGB views.

    Args:
      detector: a ``SceneDetector`` holding the onboarded objects.
      images: V uint8 RGB images [H, W, 3] (sizes may differ).
      Ks: V intrinsics [3, 3] (pixels, of each image as given).
      T_cam_world: [V, 4, 4] world -> camera extrinsics (mm); required when V > 1.
      with_masks: render each instance's silhouette in every view.
      min_views: 3PT-D's multi-view instances must be seen in at least this many views (3PT:
        3; capped at V). The templates and cell detectors keep every detection
        (:func:`fuse_posed_views`: those two views or more match are fused).

    Returns :class:`Instances`, best first.
    """
    T_cam_world = _check_views(images, Ks, T_cam_world)
    Ks = np.stack([np.asarray(k, np.float32) for k in Ks])
    detections = [detector.detect(img, k) for img, k in zip(images, Ks)]
    if len(images) == 1:
        instances = [Instance(d.obj_id, d.score, d.pose, d.poses, d.pose_scores, {0: d.box}, {},
                              pose_score=d.pose_score) for d in detections[0]]
        # The world frame of a single view is its camera frame unless T_cam_world says otherwise.
        T_wc = np.asarray(invert(jnp.asarray(T_cam_world[0])))
        instances = [dataclasses.replace(x, T_world_obj=T_wc @ x.T_world_obj,
                                         hypotheses=T_wc[None] @ x.hypotheses) for x in instances]
    elif not isinstance(detector, SceneDetector):  # the templates and cell detectors: poses
        instances = fuse_posed_views(detections, Ks, T_cam_world, detector.objects)
    else:
        objects = {o.obj_id: o for o in detector.objects}
        instances = fuse_views(detections, Ks, T_cam_world, objects, min_views=min_views,
                               logit_scale=detector.logit_scale,
                               num_hypotheses=detector.num_hypotheses,
                               min_angle_deg=detector.min_angle_deg)
    instances = Instances(instances, max(d.best_score for d in detections))
    if with_masks and instances:
        masks = render_masks(instances, [x.T_world_obj for x in instances], images, Ks,
                             T_cam_world, renderer or PoseRenderer(detector.objects))
        for x, m in zip(instances, masks):
            x.masks.update(m)
    return instances


#: How far off a single view's pose is, for :func:`fuse_posed_views`: its centre's depth (a
#: share: the outline's size) and its centre's place in the image (px). On the adapted parts'
#: 48 held-out images, the best-scored verified pose of each fully visible part: median
#: depth error 1.9-3.4 % by part, median image error of its origin 0.8-8 px, about 3.
DEPTH_SHARE, CENTRE_PX = 0.03, 3.0


def fuse_posed_views(detections: Sequence[Sequence[Detection]], Ks: np.ndarray,
                     T_cam_world: np.ndarray, objects: Sequence, *,
                     max_epipolar_px: float = 10.0, num_hypotheses: int = 8,
                     max_depth_change: float = 0.15) -> list[Instance]:
    """Multi-view instances from detections that carry poses (module docstring).

    Matched across views by :func:`~threept_jax.geometry.triangulation.match_across_views`:
    the projected centres of their poses (``objects``' ``center``; a box's centre is not the
    part's where the image's side cuts it) on each other's epipolar lines, one part, in two
    views or more. A track's centre is its members' centres fused
    by :func:`~threept_jax.geometry.triangulation.fuse_ray_estimates` (each sure across its
    ray, :data:`CENTRE_PX`, unsure along it, :data:`DEPTH_SHARE`: views far apart triangulate
    the depth, nearly parallel ones average it); the track is kept where that centre's depth
    in each member's view is within ``max_depth_change`` (a share) of the member's own (else
    its members are two parts on one epipolar line). Its hypotheses: every member's poses,
    its best-scored view first, at most ``num_hypotheses``, in the world frame, each moved to
    put its centre there; its score is the members' mean. A detection in no kept track is an
    instance of its own view, at its own pose: a rig keeps what one view sees."""
    Ks = np.asarray(Ks, np.float64)
    T_cw = np.asarray(T_cam_world, np.float64)
    middle = {o.obj_id: np.asarray(o.center, np.float64) for o in objects}
    T_world_cam = np.asarray(invert(jnp.asarray(T_cam_world)), np.float64)

    # The centre of each detection's best pose, in its view's camera frame, and its pixel.
    centres = [np.array([np.asarray(d.poses[0], np.float64)[:3, :3] @ middle[d.obj_id]
                         + np.asarray(d.poses[0], np.float64)[:3, 3] for d in dets]
                        ).reshape(-1, 3) for dets in detections]
    seen = [(c @ K.T)[:, :2] / c[:, 2:] for c, K in zip(centres, Ks)]
    labels = [np.array([d.obj_id for d in dets], np.int64) for dets in detections]
    tracks = match_across_views(seen, Ks, T_cam_world, labels=labels,
                                max_epipolar_px=max_epipolar_px,
                                min_views=2)
    groups, points = [], []
    for row in tracks.detections:
        group = [(v, int(i)) for v, i in enumerate(row) if i >= 0]
        views = [v for v, _ in group]
        own = np.array([centres[v][i] for v, i in group])  # [n, 3] camera frames
        X = fuse_ray_estimates(
            np.einsum("nij,nj->ni", T_world_cam[views, :3, :3], own) + T_world_cam[views, :3, 3],
            T_world_cam[views, :3, 3], DEPTH_SHARE * own[:, 2],
            CENTRE_PX * own[:, 2] / np.sqrt(Ks[views, 0, 0] * Ks[views, 1, 1]))
        depth = (np.einsum("nij,j->ni", T_cw[views, :3, :3], X) + T_cw[views, :3, 3])[:, 2]
        if np.all(np.abs(depth / own[:, 2] - 1.0) <= max_depth_change):
            groups.append(group)
            points.append(X)
    tracked = {m for g in groups for m in g}
    for v, dets in enumerate(detections):
        for i in range(len(dets)):
            if (v, i) not in tracked:
                groups.append([(v, i)])
                points.append(None)
    out = []
    for group, X in zip(groups, points):
        members = sorted(((v, detections[v][i]) for v, i in group), key=lambda vd: -vd[1].score)
        c = middle[members[0][1].obj_id]
        hyps, scores = [], []
        for v, det in members:
            for T, s in zip(np.asarray(det.poses, np.float64), det.pose_scores):
                W = T_world_cam[v] @ T
                if X is not None:
                    W[:3, 3] += X - (W[:3, :3] @ c + W[:3, 3])
                hyps.append(W)
                scores.append(s)
        hyps = np.stack(hyps[:num_hypotheses]).astype(np.float32)
        out.append(Instance(members[0][1].obj_id, float(np.mean([d.score for _, d in members])),
                            hyps[0], hyps, np.asarray(scores[:num_hypotheses], np.float32),
                            {v: d.box for v, d in members}, {}))
    out.sort(key=lambda x: -x.score)
    return out


def render_masks(instances: Sequence[Instance], poses: Sequence[np.ndarray],
                 images: Sequence[np.ndarray], Ks: Sequence[np.ndarray],
                 T_cam_world: np.ndarray, renderer: PoseRenderer) -> list[dict]:
    """{view: bool [H, W]} per instance: the silhouette of its CAD model at ``poses``
    (world, one per instance) in every view, each pixel to the first (best) instance covering
    it."""
    out = [{} for _ in instances]
    for v, (img, K) in enumerate(zip(images, Ks)):
        posed = [Detection(x.obj_id, np.zeros(4, np.float32), x.score,
                           (T_cam_world[v] @ T).astype(np.float32)[None],
                           x.hypothesis_scores[:1], np.zeros(0, np.float32))
                 for x, T in zip(instances, poses)]
        for m, mask in zip(out, detection_masks(posed, np.asarray(K, np.float32),
                                                img.shape[:2], renderer)):
            m[v] = mask
    return out
