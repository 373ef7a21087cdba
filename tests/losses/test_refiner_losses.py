"""3PT-R losses against hand-derived values and float64 NumPy references."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from threept_jax.eval.pose_error import mssd
from threept_jax.losses.refiner import (
    MATCHING_TEMPERATURE,
    RefinerLossConfig,
    classification_loss,
    matching_loss,
    mssd_errors,
    segmentation_loss,
)

EYE4 = np.eye(4, dtype=np.float32)
EYE3 = np.eye(3, dtype=np.float32)


@jax.jit
def _matching_tau1(*args):
    return matching_loss(*args, temperature=1.0)


def test_matching_2x2_by_hand():
    # K = I, T = I: a point (x, y, z) lands at (u, v) = (x / z, y / z), i.e. map pixel
    # (row v, column u). Real descriptors F_0..F_3 = (1,0), (0,1), (-1,0), (0,-1).
    real = np.array([[[1, 0], [0, 1]], [[-1, 0], [0, -1]]], np.float32)
    # Render pixel 0 -> real (0, 1); pixel 1 -> real (1, 0); pixel 2 projects outside the
    # map (u = 5); pixel 3 lands on real (1, 1), which is not visible.
    xyz = np.array([[[1, 0, 1], [0, 1, 1]], [[5, 0, 1], [1, 1, 1]]], np.float32)
    render = np.array([[[0, 1], [1, 0]], [[0, -1], [0, 1]]], np.float32)
    rmask = np.ones((2, 2), bool)
    vis = np.array([[True, True], [True, False]])
    loss, m = _matching_tau1(real, render, xyz, rmask, EYE4, EYE3, vis)
    # Pixel 0: Z = (0, 1), logits (0, 1, 0, -1), target 1: log(2 + e + 1/e) - 1.
    # Pixel 1: Z = (1, 0), logits (1, 0, -1, 0), target 2: log(2 + e + 1/e) + 1.
    z = 2.0 + math.e + 1.0 / math.e
    assert float(loss) == pytest.approx(math.log(z), rel=1e-6)
    assert float(m["loss"]) == float(loss)
    assert float(m["num_valid"]) == 2.0
    # Pixel 0's argmax is its target; pixel 1's argmax (0, 0) is 1 px from (1, 0).
    assert float(m["top1"]) == 0.5
    assert float(m["within_2px"]) == 1.0


def test_matching_excludes_off_mask_and_behind_camera():
    real = np.array([[[1, 0], [0, 1]], [[-1, 0], [0, -1]]], np.float32)
    render = np.array([[[0, 1], [1, 0]], [[0, -1], [0, 1]]], np.float32)
    # Pixel 2 would land on (0, 0) but is off the render mask; pixel 3 lands on (1, 1)
    # through z < 0 (x / z = 1, y / z = 1), behind the camera.
    xyz = np.array([[[1, 0, 1], [0, 1, 1]], [[0, 0, 1], [-1, -1, -1]]], np.float32)
    rmask = np.array([[True, True], [False, True]])
    vis = np.ones((2, 2), bool)
    loss, m = _matching_tau1(real, render, xyz, rmask, EYE4, EYE3, vis)
    z = 2.0 + math.e + 1.0 / math.e
    assert float(m["num_valid"]) == 2.0
    assert float(loss) == pytest.approx(math.log(z), rel=1e-6)


@pytest.mark.parametrize(("u", "v", "expected"), [
    (0.5, 0.0, 1),        # a tie at half a pixel goes to the higher index
    (-0.5, 0.0, 0),       # the map's left edge is inside
    (0.0, 1.49, 3),       # nearest pixel: row 1
    (2.0, 2.4999, 8),     # bottom-right pixel, inside
    (2.5, 0.0, None),     # right edge of a 3-wide map: outside
    (0.0, -0.51, None),   # above the top edge: outside
])
def test_matching_nearest_pixel_rule(u, v, expected):
    # 3 x 3 map, one-hot real descriptors (C = 9), every render descriptor = e_0 except the
    # probed pixel, whose descriptor is e_expected: it is a top-1 hit iff its target is
    # pixel `expected`. Only render pixel (0, 0) is in the render mask.
    real = np.eye(9, dtype=np.float32).reshape(3, 3, 9)
    render = np.zeros((3, 3, 9), np.float32)
    render[0, 0, 0 if expected is None else expected] = 1.0
    xyz = np.zeros((3, 3, 3), np.float32)
    xyz[..., 2] = 2.0
    xyz[0, 0] = (2 * u, 2 * v, 2.0)
    rmask = np.zeros((3, 3), bool)
    rmask[0, 0] = True
    loss, m = jax.jit(matching_loss)(real, render, xyz, rmask, EYE4, EYE3, np.ones((3, 3), bool))
    if expected is None:
        assert float(m["num_valid"]) == 0.0 and float(loss) == 0.0
    else:
        assert float(m["num_valid"]) == 1.0
        assert float(m["top1"]) == 1.0
        tau = MATCHING_TEMPERATURE
        assert float(loss) == pytest.approx(math.log(math.exp(1 / tau) + 8) - 1 / tau, abs=1e-6)


def test_matching_within_2px_radius():
    # 3 x 3 map; render pixel (0, 0) targets real (0, 0) but its argmax is (0, 2) (2 px: in)
    # or (2, 2) (2.83 px: out).
    real = np.eye(9, dtype=np.float32).reshape(3, 3, 9)
    xyz = np.zeros((3, 3, 3), np.float32)
    xyz[..., 2] = 1.0
    rmask = np.zeros((3, 3), bool)
    rmask[0, 0] = True
    vis = np.ones((3, 3), bool)
    for argmax, within in ((2, 1.0), (8, 0.0)):
        render = np.zeros((3, 3, 9), np.float32)
        render[0, 0, argmax] = 1.0
        _, m = jax.jit(matching_loss)(real, render, xyz, rmask, EYE4, EYE3, vis)
        assert float(m["top1"]) == 0.0
        assert float(m["within_2px"]) == within


def test_matching_same_place_baseline_by_hand():
    # Every render point is (0, 0, 1), which identity K and T put at real pixel (0, 0). Render
    # pixel (0, 0) is at its target, (0, 2) 2 px from it (in), (2, 2) 2.83 px (out); the
    # descriptors play no part.
    real = np.eye(9, dtype=np.float32).reshape(3, 3, 9)
    xyz = np.zeros((3, 3, 3), np.float32)
    xyz[..., 2] = 1.0
    vis = np.ones((3, 3), bool)
    for pixel, same_place in (((0, 0), 1.0), ((0, 2), 1.0), ((2, 2), 0.0)):
        rmask = np.zeros((3, 3), bool)
        rmask[pixel] = True
        _, m = jax.jit(matching_loss)(real, real, xyz, rmask, EYE4, EYE3, vis)
        assert float(m["within_2px_same_place"]) == same_place


def _rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q * np.linalg.det(q)


def test_matching_identity_correspondence_at_gt_pose():
    # The object points seen by each map pixel at the GT pose project back onto that pixel:
    # the target of render pixel p is real pixel p, so identical one-hot descriptors give
    # top-1 = 1 and each pixel's loss log(e^(1/tau) + (h w - 1)) - 1/tau.
    rng = np.random.default_rng(0)
    h = w = 4
    K = np.array([[5.2, 0.0, 1.6], [0.0, 4.7, 1.4], [0.0, 0.0, 1.0]])
    R = _rotation(rng)
    t = np.array([3.0, -2.0, 40.0])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    ii, jj = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    depth = rng.uniform(30.0, 50.0, (h, w))
    uv1 = np.stack([jj, ii, np.ones_like(ii)], -1).astype(np.float64)
    cam = (uv1 @ np.linalg.inv(K).T) * depth[..., None]
    obj = (cam - t) @ R  # R^T (p - t), row vectors
    desc = np.eye(h * w, dtype=np.float32).reshape(h, w, h * w)
    rmask = np.ones((h, w), bool)
    rmask[3, 0] = False
    loss, m = jax.jit(matching_loss)(desc, desc, obj.astype(np.float32), rmask,
                                     T.astype(np.float32), K.astype(np.float32),
                                     np.ones((h, w), bool))
    tau = MATCHING_TEMPERATURE
    assert float(m["num_valid"]) == h * w - 1
    assert float(m["top1"]) == 1.0
    assert float(loss) == pytest.approx(math.log(math.exp(1 / tau) + h * w - 1) - 1 / tau,
                                        abs=1e-6)


def _unit(rng, shape):
    x = rng.normal(size=shape)
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def _random_case(rng, lead, h, w, c):
    """Random pairs whose render points land inside, outside and behind the map."""
    real = _unit(rng, (*lead, h, w, c))
    render = _unit(rng, (*lead, h, w, c))
    K = np.array([[3.0, 0.0, (w - 1) / 2], [0.0, 2.5, (h - 1) / 2], [0.0, 0.0, 1.0]])
    T = np.tile(np.eye(4), (*lead, 1, 1))
    T[..., :3, 3] = rng.normal(0.0, 0.1, (*lead, 3)) + (0.0, 0.0, 5.0)
    T[..., :3, :3] = np.stack([_rotation(rng) for _ in range(int(np.prod(lead)))]).reshape(
        *lead, 3, 3)
    xyz = rng.uniform(-5.0, 5.0, (*lead, h, w, 3))
    xyz[..., 2] = rng.uniform(-6.0, 3.0, (*lead, h, w))
    rmask = rng.random((*lead, h, w)) < 0.8
    vis = rng.random((*lead, h, w)) < 0.7
    return real, render, xyz, rmask, T, K, vis


def _matching_reference(real, render, xyz, rmask, T, K, vis, tau):
    """Float64 brute force over pairs and pixels; also d loss / d(real, render, tau)."""
    lead = real.shape[:-3]
    h, w, c = real.shape[-3:]
    real = real.reshape(-1, h * w, c)
    render = render.reshape(-1, h * w, c)
    xyz = xyz.reshape(-1, h * w, 3)
    rmask = rmask.reshape(-1, h * w)
    vis = vis.reshape(-1, h * w)
    T = np.broadcast_to(T, (*lead, 4, 4)).reshape(-1, 4, 4)
    total = count = top1 = near = 0.0
    g_real, g_render, g_tau = np.zeros_like(real), np.zeros_like(render), 0.0
    for n in range(real.shape[0]):
        for p in range(h * w):
            if not rmask[n, p]:
                continue
            cam = T[n, :3, :3] @ xyz[n, p] + T[n, :3, 3]
            if cam[2] <= 0:
                continue
            u, v = (K @ cam)[:2] / cam[2]
            col, row = math.floor(u + 0.5), math.floor(v + 0.5)
            if not (0 <= col < w and 0 <= row < h) or not vis[n, row * w + col]:
                continue
            gt = row * w + col
            s = real[n] @ render[n, p]
            logits = s / tau
            prob = np.exp(logits - logits.max())
            prob /= prob.sum()
            total += np.log(np.exp(logits - logits.max()).sum()) + logits.max() - logits[gt]
            count += 1
            best = int(np.argmax(logits))
            top1 += best == gt
            near += math.hypot(best // w - row, best % w - col) <= 2.0
            onehot = np.eye(h * w)[gt]
            g_render[n, p] += (prob - onehot) @ real[n] / tau
            g_real[n] += np.outer(prob - onehot, render[n, p]) / tau
            g_tau += (s[gt] - prob @ s) / tau**2
    d = max(count, 1.0)
    grads = (g_real.reshape(*lead, h, w, c) / d, g_render.reshape(*lead, h, w, c) / d, g_tau / d)
    return total / d, count, top1 / d, near / d, grads


def test_matching_float64_brute_force_and_gradients():
    rng = np.random.default_rng(1)
    lead, h, w, c = (2, 3), 3, 4, 5
    real, render, xyz, rmask, T, K, vis = _random_case(rng, lead, h, w, c)
    T = T[:, :1]  # one GT pose per instance, broadcast over the 3 hypotheses
    tau = 0.3
    ref_loss, ref_count, ref_top1, ref_near, ref_grads = _matching_reference(
        real, render, xyz, rmask, T, K, vis, tau)
    assert ref_count > 5 and ref_count < rmask.sum()  # both kinds of pixel occur
    f32 = [np.asarray(a, np.float32) for a in (real, render, xyz)]

    def f(real_, render_, tau_):
        return matching_loss(real_, render_, f32[2], rmask, T.astype(np.float32),
                             K.astype(np.float32), vis, temperature=tau_)

    (loss, m), grads = jax.jit(jax.value_and_grad(f, argnums=(0, 1, 2), has_aux=True))(
        f32[0], f32[1], jnp.float32(tau))
    assert float(loss) == pytest.approx(ref_loss, rel=1e-5)
    assert float(m["num_valid"]) == ref_count
    assert float(m["top1"]) == pytest.approx(ref_top1)
    assert float(m["within_2px"]) == pytest.approx(ref_near)
    for got, want in zip(grads, ref_grads, strict=True):
        np.testing.assert_allclose(np.asarray(got), want, rtol=1e-4, atol=1e-6)


def test_matching_vmap_is_per_example():
    rng = np.random.default_rng(2)
    real, render, xyz, rmask, T, K, vis = _random_case(rng, (3, 2), 3, 3, 4)
    f32 = lambda a: np.asarray(a, np.float32)  # noqa: E731
    got, m = jax.jit(jax.vmap(matching_loss, in_axes=(0, 0, 0, 0, 0, None, 0)))(
        f32(real), f32(render), f32(xyz), rmask, f32(T), f32(K), vis)
    for b in range(3):
        ref = _matching_reference(real[b], render[b], xyz[b], rmask[b], T[b], K, vis[b],
                                  MATCHING_TEMPERATURE)
        assert float(got[b]) == pytest.approx(ref[0], rel=1e-5)
        assert float(m["num_valid"][b]) == ref[1]


def test_matching_no_valid_pixel_gives_zero_and_finite_gradients():
    rng = np.random.default_rng(3)
    real, render, xyz, _, T, K, vis = _random_case(rng, (2,), 3, 3, 4)
    xyz[0, 0, 0] = np.nan  # garbage off the render mask must not leak
    rmask = np.zeros((2, 3, 3), bool)
    rmask[1, 2, 2] = True
    # In the mask but behind the camera: camera point (0, 0, -1) in the object frame.
    xyz[1, 2, 2] = T[1, :3, :3].T @ (np.array([0.0, 0.0, -1.0]) - T[1, :3, 3])

    def f(real_, render_):
        return matching_loss(real_, render_, xyz.astype(np.float32), rmask,
                             T.astype(np.float32), K.astype(np.float32), vis)

    (loss, m), grads = jax.jit(jax.value_and_grad(f, argnums=(0, 1), has_aux=True))(
        real.astype(np.float32), render.astype(np.float32))
    assert float(loss) == 0.0
    assert {k: float(v) for k, v in m.items()} == {"loss": 0.0, "num_valid": 0.0, "top1": 0.0,
                                                   "within_2px": 0.0, "within_2px_same_place": 0.0}
    for g in grads:
        assert np.all(np.asarray(g) == 0.0)


def test_matching_holds_one_pair_matrix_at_a_time():
    # Compiled, not run: 8 pairs of 64 x 64 maps, loss and gradients. Each pair's logits are
    # [4096, 4096] float32 = 64 MiB; all 8 at once would need >= 512 MiB of temporaries.
    n, h, c = 8, 64, 16
    S = jax.ShapeDtypeStruct
    args = (S((n, h, h, c), jnp.float32), S((n, h, h, c), jnp.float32),
            S((n, h, h, 3), jnp.float32), S((n, h, h), bool), S((n, 4, 4), jnp.float32),
            S((n, 3, 3), jnp.float32), S((n, h, h), bool))
    grad = jax.grad(lambda a, b, *r: matching_loss(a, b, *r)[0], argnums=(0, 1))
    temp = jax.jit(grad).lower(*args).compile().memory_analysis().temp_size_in_bytes
    assert temp < 3 * (h * h) ** 2 * 4


def test_matching_refuses_bad_temperature_and_shapes():
    d = np.zeros((2, 2, 3), np.float32)
    xyz = np.zeros((2, 2, 3), np.float32)
    m = np.ones((2, 2), bool)
    with pytest.raises(ValueError, match="temperature must be a finite number > 0"):
        matching_loss(d, d, xyz, m, EYE4, EYE3, m, temperature=0.0)
    with pytest.raises(ValueError, match="render_desc must end in"):
        matching_loss(d, d[..., :2], xyz, m, EYE4, EYE3, m)
    with pytest.raises(ValueError, match="K_map must end in"):
        matching_loss(d, d, xyz, m, EYE4, EYE4, m)


def test_classification_by_hand():
    scores = np.array([[1.0, 2.0, 0.5], [0.0, 0.0, 0.0], [3.0, 1.0, 2.0], [0.0, 1.0, 2.0]],
                      np.float32)
    errors = np.array([[5.0, 1.0, 3.0], [2.0, 2.0, 1.0], [np.nan, 4.0, 1.0],
                       [np.nan, np.inf, np.nan]], np.float32)
    valid = np.array([True, True, True, True])
    loss, m = jax.jit(classification_loss)(scores, errors, valid)
    # Row 0: target 1 (argmax 1, right). Row 1: target 2 (argmax 0, wrong). Row 2: the NaN
    # error counts as +inf, target 2 (argmax 0, wrong). Row 3: no finite error, dropped.
    ce = [math.log(math.e + math.e**2 + math.e**0.5) - 2.0, math.log(3.0),
          math.log(math.e**3 + math.e + math.e**2) - 2.0]
    assert float(loss) == pytest.approx(sum(ce) / 3, rel=1e-6)
    assert float(m["accuracy"]) == pytest.approx(1 / 3)
    # Invalid instances are left out; a tie in errors targets the first.
    loss, m = jax.jit(classification_loss)(scores, np.array(
        [[1.0, 1.0, 2.0]] * 4, np.float32), np.array([False, True, False, False]))
    assert float(loss) == pytest.approx(math.log(3.0), rel=1e-6)
    assert float(m["accuracy"]) == 1.0


def test_classification_none_valid_is_zero_with_finite_gradients():
    scores = jnp.array([[1.0, 2.0], [0.0, 3.0]])
    errors = jnp.array([[1.0, 2.0], [3.0, 0.5]])
    f = lambda s: classification_loss(s, errors, jnp.zeros(2, bool))  # noqa: E731
    (loss, m), g = jax.value_and_grad(f, has_aux=True)(scores)
    assert float(loss) == 0.0 and float(m["accuracy"]) == 0.0
    assert np.all(np.asarray(g) == 0.0)
    with pytest.raises(ValueError, match=r"scores and errors must both be \[B, J\]"):
        classification_loss(scores, errors[:, :1], jnp.ones(2, bool))


def test_segmentation_float64_formula():
    rng = np.random.default_rng(4)
    logits = rng.normal(0.0, 3.0, (2, 3, 2, 4, 4))
    logits[0, 0, 0, 0, :2] = (100.0, -100.0)  # saturated logits stay finite
    vis = rng.random((2, 1, 2, 4, 4)) < 0.4
    vis[0, 0, 0, 0, :2] = (False, True)
    valid = rng.random((2, 3, 2)) < 0.7
    valid[0, 0, 0] = True
    loss, m = jax.jit(segmentation_loss)(logits.astype(np.float32), vis, valid)
    t = np.broadcast_to(vis, logits.shape).astype(np.float64)
    log_p, log_q = -np.logaddexp(0.0, -logits), -np.logaddexp(0.0, logits)
    bce = -(t * log_p + (1 - t) * log_q)
    ref = bce[valid].mean()
    pred = logits > 0
    inter = (pred & (t > 0)).sum((-2, -1))
    union = (pred | (t > 0)).sum((-2, -1))
    iou = np.where(union > 0, inter / np.maximum(union, 1), 1.0)
    assert float(loss) == pytest.approx(ref, rel=1e-5)
    assert float(m["iou"]) == pytest.approx(iou[valid].mean(), rel=1e-6)


def test_segmentation_by_hand_and_empty():
    # One 1 x 2 map: logits (0, ln 3), mask (1, 0): BCE = ln 2 and ln 4; prediction (0, 1) vs
    # mask (1, 0): IoU 0. A second map, both empty: IoU 1.
    logits = np.array([[[0.0, math.log(3.0)]], [[-5.0, -5.0]]], np.float32)
    vis = np.array([[[True, False]], [[False, False]]])
    loss, m = jax.jit(segmentation_loss)(logits, vis, np.array([True, False]))
    assert float(loss) == pytest.approx((math.log(2.0) + math.log(4.0)) / 2, rel=1e-6)
    assert float(m["iou"]) == 0.0
    _, m = jax.jit(segmentation_loss)(logits, vis, np.array([False, True]))
    assert float(m["iou"]) == 1.0
    f = lambda x: segmentation_loss(x, vis, np.zeros(2, bool))  # noqa: E731
    (loss, m), g = jax.value_and_grad(f, has_aux=True)(jnp.asarray(logits))
    assert float(loss) == 0.0 and float(m["iou"]) == 0.0
    assert np.all(np.asarray(g) == 0.0)


def _rigid(rng):
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    T[:3, 3] = rng.normal(0, 30, 3) + [0, 0, 500]
    return T


def test_mssd_errors_match_the_bop_float64_reference_with_symmetries_and_padding():
    rng = np.random.default_rng(3)
    pts = rng.normal(0, 20, (50, 3))
    # A 4-fold symmetry about z (with a non-zero offset on one transform) and 2 padded rows.
    sym = np.tile(np.eye(4), (6, 1, 1))
    for i, a in enumerate((90, 180, 270)):
        c, s_ = np.cos(np.radians(a)), np.sin(np.radians(a))
        sym[i + 1, :2, :2] = [[c, -s_], [s_, c]]
    sym[2, :3, 3] = [1.0, -2.0, 0.5]
    sym_mask = np.array([True, True, True, True, False, False])
    sym[4:] = np.diag([5.0, 5.0, 5.0, 1.0])  # padding: must be ignored
    T_gt = _rigid(rng)
    T_est = np.stack([_rigid(rng) for _ in range(3)] + [T_gt @ sym[2]])
    pmask = np.ones(56, bool)
    pmask[50:] = False
    pts_pad = np.concatenate([pts, np.full((6, 3), 1e4)])
    got = np.asarray(mssd_errors(T_est, T_gt, pts_pad, pmask, sym, sym_mask))
    want = [mssd(T[:3, :3], T[:3, 3], T_gt[:3, :3], T_gt[:3, 3], pts,
                 (sym[:4, :3, :3], sym[:4, :3, 3])) for T in T_est]
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-2)
    assert got[-1] < 1e-2  # a symmetric copy of the ground truth has no error


def test_refiner_loss_config_refuses_negative_weights_and_bad_temperature():
    with pytest.raises(ValueError, match="classification_weight"):
        RefinerLossConfig(classification_weight=-1.0)
    with pytest.raises(ValueError, match="temperature"):
        RefinerLossConfig(temperature=0.0)
