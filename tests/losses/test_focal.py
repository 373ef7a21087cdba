"""Sigmoid focal loss and matching cost against hand-computed values."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from threept_jax.losses.focal import focal_matching_cost, sigmoid_focal_loss


def focal_by_hand(x, t, alpha, gamma, w_neg=1.0):
    p = 1.0 / (1.0 + math.exp(-x))
    a_pos, a_neg = (1.0, 1.0) if alpha is None else (alpha, 1.0 - alpha)
    pos = a_pos * (1.0 - p) ** gamma * -math.log(p)
    neg = a_neg * p**gamma * -math.log(1.0 - p)
    return t * pos + (1.0 - t) * w_neg * neg, pos, neg


@jax.jit
def _focal(x, t, w):
    return (sigmoid_focal_loss(x, t, alpha=0.25, gamma=2.0, negative_weight=w),
            sigmoid_focal_loss(x, t, alpha=None, gamma=1.5),
            focal_matching_cost(x, alpha=0.25, gamma=2.0))


def test_focal_hand_values():
    # x = 0: p = 1/2, positive term 0.25 * 0.25 * ln 2, negative 0.75 * 0.25 * ln 2.
    assert focal_by_hand(0.0, 1.0, 0.25, 2.0)[0] == pytest.approx(0.0625 * math.log(2.0))
    assert focal_by_hand(0.0, 0.0, 0.25, 2.0)[0] == pytest.approx(0.1875 * math.log(2.0))
    xs = np.array([0.0, 2.0, -1.5, 0.3, 4.0], np.float32)
    ts = np.array([1.0, 0.0, 1.0, 0.0, 0.25], np.float32)
    ws = np.array([1.0, 0.5, 0.2, 1.0, 0.7], np.float32)
    got, got_noalpha, cost = _focal(xs, ts, ws)
    triples = list(zip(xs.tolist(), ts.tolist(), ws.tolist(), strict=True))
    ref = [focal_by_hand(x, t, 0.25, 2.0, w)[0] for x, t, w in triples]
    ref_noalpha = [focal_by_hand(x, t, None, 1.5)[0] for x, t, _ in triples]
    ref_cost = [focal_by_hand(float(x), 1.0, 0.25, 2.0)[1]
                - focal_by_hand(float(x), 0.0, 0.25, 2.0)[2] for x in xs]
    np.testing.assert_allclose(got, ref, rtol=1e-5)
    np.testing.assert_allclose(got_noalpha, ref_noalpha, rtol=1e-5)
    np.testing.assert_allclose(cost, ref_cost, rtol=1e-5, atol=1e-7)


def test_focal_finite_at_extreme_logits():
    x = jnp.asarray([-200.0, 200.0])
    loss, _, cost = _focal(x, jnp.asarray([1.0, 0.0]), jnp.ones(2))
    assert np.isfinite(np.asarray(loss)).all() and np.isfinite(np.asarray(cost)).all()
    # A confidently wrong prediction costs about alpha * |x| (softplus(200) ~ 200).
    np.testing.assert_allclose(loss, [0.25 * 200.0, 0.75 * 200.0], rtol=1e-5)


def test_bad_alpha():
    with pytest.raises(ValueError, match="alpha"):
        sigmoid_focal_loss(jnp.zeros(2), jnp.zeros(2), alpha=1.5)
