"""``threept_jax.pipeline.turns``: which near-symmetric turn of a pose the image shows.

Reference: the ground truth of hand-made scenes. A 12-tooth gear with one short tooth
(``tests/fixtures/gear.py``) rendered at a known pose over a noisy background, in one
view and in two views of a rig; a pose turned by whole teeth about the gear's axis (its
outline unchanged) comes back to the truth, the truth stays, and a grey image keeps the pose.
"""

import numpy as np
from fixtures.gear import gear
from scipy.spatial.transform import Rotation

from threept_jax.geometry.camera import look_at
from threept_jax.geometry.symmetry import axis_angle_rotation
from threept_jax.pipeline.turns import choose_turn, turn_scores
from threept_jax.render import Renderer
from threept_jax.render.mesh import Mesh

K = np.array([[600.0, 0, 320], [0, 610.0, 240], [0, 0, 1]])
HW = (480, 640)


def _turn(deg):
    T = np.eye(4)
    T[:3, :3] = axis_angle_rotation(np.radians(deg), [0, 0, 1])
    return T


def _scene(views):
    v, f = gear()
    mesh = Mesh(v, f, colors=np.tile((0.7, 0.7, 0.72), (len(v), 1)))
    renderer = Renderer(mesh)
    T_gt = np.eye(4)
    T_gt[:3, :3] = Rotation.from_euler("xyz", [25, -15, 40], degrees=True).as_matrix()
    eyes = np.array([[0, -40, 400], [200, 0, 350]], np.float64)[:views]
    T_cw = np.stack([np.asarray(look_at(e, np.zeros(3), (0, 1.0, 0)), np.float64) for e in eyes])
    rng = np.random.default_rng(0)
    images = []
    for T in T_cw:
        out = renderer.render((T @ T_gt).astype(np.float32), K.astype(np.float32), HW,
                              ("rgb", "mask"), ambient=0.3)
        bg = np.clip(0.3 + 0.05 * rng.standard_normal(HW + (3,)), 0, 1)
        img = np.where(np.asarray(out["mask"])[..., None], np.asarray(out["rgb"]), bg)
        images.append(np.round(img * 255).astype(np.uint8))
    corners = np.array([[x, y, z] for x in (v.min(0)[0], v.max(0)[0])
                        for y in (v.min(0)[1], v.max(0)[1]) for z in (v.min(0)[2], v.max(0)[2])])
    return renderer, corners, images, np.tile(K, (views, 1, 1)), T_cw, T_gt


def test_a_gear_turned_by_whole_teeth_comes_back_and_the_truth_stays():
    renderer, corners, images, Ks, T_cw, T_gt = _scene(2)
    turns = np.stack([_turn(30.0 * k) for k in range(1, 12)])
    for views in (1, 2):
        for k in (1, 4, 9):
            start = T_gt @ _turn(-30.0 * k)
            got = choose_turn(renderer, corners, start, turns, images[:views], Ks[:views],
                              T_cw[:views])
            np.testing.assert_allclose(got, T_gt, atol=1e-6)
        np.testing.assert_array_equal(
            choose_turn(renderer, corners, T_gt, turns, images[:views], Ks[:views],
                        T_cw[:views]), T_gt)
    # The truth's edges are found best: it outscores every turn in the scores themselves.
    cand = np.concatenate([T_gt[None], np.einsum("ij,mjk->mik", T_gt, turns)])
    scores = turn_scores(renderer, corners, cand, images, Ks, T_cw)
    assert scores.shape == (12,) and np.argmax(scores) == 0


def test_nothing_to_see_keeps_the_pose():
    renderer, corners, images, Ks, T_cw, T_gt = _scene(1)
    turns = np.stack([_turn(30.0 * k) for k in range(1, 12)])
    grey = [np.full(HW + (3,), 128, np.uint8)]
    start = T_gt @ _turn(60.0)
    np.testing.assert_array_equal(choose_turn(renderer, corners, start, turns, grey, Ks, T_cw),
                                  start)
    behind = start.copy()
    behind[:3, 3] = [0.0, 0.0, 900.0]  # behind the camera (at z = 400, looking down): no view
    assert turn_scores(renderer, corners, behind[None], images, Ks, T_cw) is None
    np.testing.assert_array_equal(choose_turn(renderer, corners, behind, turns, images, Ks, T_cw),
                                  behind)
