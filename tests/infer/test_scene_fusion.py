"""Multi-view object generation against ground-truth poses (synthetic detections, cv2 boxes)."""

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from infer.detect import Detection
from infer.onboarding import OnboardedObject
from infer.scene import fuse_views
from threept_jax.geometry import camera
from threept_jax.geometry.grids import super_fibonacci_rotations
from threept_jax.geometry.rotations import geodesic_angle


def _object(obj_id, rng, templates):
    pts = rng.uniform([-40, -25, -10], [40, 25, 10], (300, 3)).astype(np.float32)
    centre = ((pts.min(0) + pts.max(0)) / 2).astype(np.float32)
    return OnboardedObject(obj_id, f"obj{obj_id}", None, 100.0, pts, None, None, templates,
                           np.eye(4, dtype=np.float32)[None], centre)


def test_fuse_views_recovers_poses_of_a_ring_rig():
    rng = np.random.default_rng(0)
    templates = super_fibonacci_rotations(2000)
    V = 4
    K = np.array([[800.0, 0, 320], [0, 790.0, 240], [0, 0, 1]], np.float32)
    Ks = np.stack([K] * V)
    eyes = [(600 * np.cos(a), 600 * np.sin(a), 500.0) for a in np.linspace(0, 2 * np.pi, V, endpoint=False)]
    T_cw = np.stack([np.asarray(camera.look_at(e, (0, 0, 0))) for e in eyes]).astype(np.float64)
    objects = {i: _object(i, rng, templates) for i in (3, 7)}
    gt = []  # (obj_id, T_world_obj)
    for obj_id, pos in ((3, (-80, 20, 0)), (7, (60, -40, 10)), (3, (20, 90, 0))):
        T = np.eye(4)
        T[:3, :3] = Rotation.random(random_state=len(gt)).as_matrix()
        T[:3, 3] = pos
        gt.append((obj_id, T))
    detections = []
    for v in range(V):
        dets = []
        for obj_id, T in gt:
            obj = objects[obj_id]
            T_co = T_cw[v] @ T
            uv, _ = cv2.projectPoints(obj.points.astype(np.float64), cv2.Rodrigues(T_co[:3, :3])[0],
                                      T_co[:3, 3], K.astype(np.float64), None)
            box = np.concatenate([uv[:, 0].min(0), uv[:, 0].max(0)]) + 0.5
            # The orientation distribution a perfect detector would give: peaked at the
            # object-centred rotation (the template that looks like the object in this view).
            c_cam = T_co[:3, :3] @ obj.center + T_co[:3, 3]
            R_oc = camera.ray_rotation(c_cam).T @ T_co[:3, :3]
            ang = np.asarray(geodesic_angle(templates, R_oc[None].astype(np.float32)))
            scores = (np.cos(ang) + 0.01 * rng.standard_normal(len(ang))).astype(np.float32)
            dets.append(Detection(obj_id, box.astype(np.float32), 0.9, np.eye(4)[None], np.ones(1),
                                  scores))
        dets.append(Detection(7, np.array([10, 10, 40, 40], np.float32), 0.3, np.eye(4)[None],
                              np.ones(1), np.zeros(len(templates), np.float32)))  # spurious
        detections.append(dets)
    instances = fuse_views(detections, Ks, T_cw.astype(np.float32), objects, min_views=3,
                           logit_scale=20.0)
    assert len(instances) == len(gt)
    for obj_id, T in gt:
        match = [x for x in instances if x.obj_id == obj_id
                 and np.linalg.norm(x.T_world_obj[:3, 3] - T[:3, 3]) < 10.0]
        assert len(match) == 1, (obj_id, T[:3, 3], [x.T_world_obj[:3, 3] for x in instances])
        x = match[0]
        assert len(x.boxes) == V
        # Measured 3.5-6.6 degrees with 2000 templates (nearest template ~8 degrees away on
        # average; picking the densest template alone gave 8-15): mean shift on the fused
        # density refines below the grid. The box-centre ray is not the sphere centre's.
        err = np.degrees(float(geodesic_angle(x.T_world_obj[:3, :3], T[:3, :3].astype(np.float32))))
        assert err < 7.5
        np.testing.assert_allclose(x.T_world_obj[:3, 3], T[:3, 3], atol=3.0)
