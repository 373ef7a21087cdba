"""The refiner evaluation's metrics against brute-force loops and OpenCV."""

import cv2
import jax.numpy as jnp
import numpy as np
from scipy.spatial.transform import Rotation

from threept_jax.pipeline.refinement import Matches
from train.eval_refiner import average_recall, match_accuracy, summarize


def test_average_recall_is_the_bop_threshold_loop():
    rng = np.random.default_rng(0)
    err = rng.uniform(0, 60, 40)
    err[3] = np.inf
    err[5] = np.nan
    diam = rng.uniform(50, 120, 40)
    want = np.mean([[e < t * d for e, d in zip(err, diam)]
                    for t in (0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4, 0.45, 0.5)])
    assert average_recall(err, diam) == want
    assert average_recall(np.zeros(0), np.zeros(0)) == 0.0


def test_match_accuracy_counts_matches_within_2_crop_pixels_of_the_opencv_projection():
    """Both counts against OpenCV's projection: the matched real pixel's, and the render pixel's
    own centre (the position-only baseline; map 32 x 32 over a 64 px crop, so map pixel
    (i, j) is crop point (2 j + 0.5, 2 i + 0.5))."""
    rng = np.random.default_rng(1)
    B, J, V, N = 2, 3, 2, 20
    K = np.array([[[60.0, 0, 31.5], [0, 62.0, 30.0], [0, 0, 1]]] * V)
    crop_K = np.stack([K, K * [[1.1], [1.0], [1]]])
    T = np.tile(np.eye(4), (B, V, 1, 1))
    T[..., :3, :3] = Rotation.random(B * V, random_state=2).as_matrix().reshape(B, V, 3, 3)
    T[..., :3, 3] = [5.0, -3.0, 400.0]
    X = rng.normal(0, 30, (B, J, V, N, 3))
    uv = np.empty((B, J, V, N, 2))
    for b in range(B):
        for j in range(J):
            for v in range(V):
                rvec = cv2.Rodrigues(T[b, v, :3, :3])[0]
                p, _ = cv2.projectPoints(X[b, j, v], rvec, T[b, v, :3, 3], crop_K[b, v], None)
                uv[b, j, v] = p[:, 0]
    shift = rng.uniform(0, 4, (B, J, V, N))
    angle = rng.uniform(0, 2 * np.pi, (B, J, V, N))
    uv_noisy = uv + shift[..., None] * np.stack([np.cos(angle), np.sin(angle)], -1)
    w = (rng.uniform(size=(B, J, V, N)) < 0.8).astype(np.float32)
    # Render pixels at the projection's nearest map pixel, or one to three map pixels off.
    col = np.clip(np.round((uv[..., 0] - 0.5) / 2) + rng.integers(-3, 4, w.shape), 0, 31)
    row = np.clip(np.round((uv[..., 1] - 0.5) / 2), 0, 31)
    centre = np.stack([2 * col + 0.5, 2 * row + 0.5], -1)
    m = Matches(points_3d=jnp.asarray(X, jnp.float32), points_2d=jnp.asarray(uv_noisy, jnp.float32),
                weights=jnp.asarray(w), similarity=jnp.zeros(w.shape),
                render_pixel=jnp.asarray(row * 32 + col, jnp.int32),
                real_pixel=jnp.zeros(w.shape, jnp.int32))
    within, same_place, total = match_accuracy(m, jnp.asarray(crop_K, jnp.float32),
                                               jnp.asarray(T, jnp.float32), crop_size=64,
                                               map_size=32)
    np.testing.assert_allclose(np.asarray(total), w.sum(axis=(1, 2, 3)))
    np.testing.assert_allclose(np.asarray(within), ((shift <= 2.0) * w).sum(axis=(1, 2, 3)))
    near = np.linalg.norm(centre - uv, axis=-1) <= 2.0
    assert 0 < (near * w).sum() < w.sum()
    np.testing.assert_allclose(np.asarray(same_place), (near * w).sum(axis=(1, 2, 3)))


def test_summary_medians_recall_and_score_accuracy_by_hand():
    # Two valid instances and a padded invalid one; J = 2; poses before, after 1, after 3.
    def pose(angle_deg, t):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("z", angle_deg, degrees=True).as_matrix()
        T[:3, 3] = t
        return T

    gt = np.stack([pose(0, [0, 0, 500])] * 3)
    poses = np.stack([
        [[pose(10, [0, 0, 510]), pose(20, [0, 0, 520])], [pose(2, [0, 0, 502]),
         pose(8, [0, 0, 504])], [pose(1, [0, 0, 501]), pose(4, [0, 0, 502])]],
    ] * 3)  # [3, 3, 2, 4, 4]
    mssd = np.array([[[30.0, 60.0], [4.0, 9.0], [2.0, 5.0]]] * 3)
    sym = np.tile(np.eye(4), (3, 2, 1, 1))
    r = {"poses": poses, "mssd": mssd, "T_world_obj_gt": gt, "diameter": np.full(3, 100.0),
         "symmetries": sym, "symmetry_mask": np.array([[True, False]] * 3),
         "valid": np.array([True, True, False]), "obj_id": np.array([1, 2, 1]),
         "scores": np.array([[2.0, 1.0], [0.0, 1.0], [0.0, 9.0]]),
         "within": np.array([3.0, 1.0, 9.0]), "same_place": np.array([2.0, 4.0, 9.0]),
         "total": np.array([4.0, 4.0, 9.0]),
         "num_pairs": np.full(3, 2.0)}
    for k in ("matching/loss", "matching/within_2px", "matching/within_2px_same_place",
              "classification/loss", "segmentation/iou"):
        r[k] = np.array([0.5, 0.5, 7.0])
    out = summarize(r, num_steps=3, unseen={1: True, 2: False})
    assert out["eval/num_instances"] == 2
    assert np.isclose(out["eval/rot_deg_before"], 15.0)  # median of 10, 20, 10, 20
    assert np.isclose(out["eval/trans_mm_after_1"], 3.0)  # median of 2, 4, 2, 4
    assert np.isclose(out["eval/rot_deg_after_3"], 2.5)
    # MSSD 30 and 60 against thresholds 5..50 mm: 30 passes 35..50 (4 of 10), 60 none.
    assert np.isclose(out["eval/ar_mssd_before"], (4 + 0) / 20)
    # After 3: 2 passes all 10, 5 passes 10..50 (9 of 10).
    assert np.isclose(out["eval/ar_mssd_after"], 19 / 20)
    # Top scores: instance 0 picks hypothesis 0 (the best: correct), instance 1 picks 1 (not).
    assert out["eval/score_acc"] == 0.5
    assert np.isclose(out["eval/ar_mssd_top_after"], (10 + 9) / 20)
    # Before refinement the picks are MSSD 30 (4 of 10) and 60 (0 of 10).
    assert np.isclose(out["eval/ar_mssd_top_before"], 4 / 20)
    assert out["eval/match_within_2px"] == 0.5
    assert out["eval/match_within_2px_same_place"] == 0.75
    assert out["eval/matches_per_pair"] == 2.0
    assert out["eval/unseen_share"] == 0.5
    assert out["eval/mask_iou"] == 0.5


def test_kept_errors_keep_the_start_where_the_step_made_it_worse():
    from train.refiner_objective import kept_errors

    before = np.array([[10.0, 20.0, 30.0]])
    after = np.array([[12.0, 5.0, np.nan]])  # worse, better, a failed step
    np.testing.assert_array_equal(np.asarray(kept_errors(before, after)), [[10.0, 5.0, 30.0]])
