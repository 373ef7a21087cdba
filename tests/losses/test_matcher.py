"""Cost matrix and Hungarian matcher: SciPy optimum, brute force, padding, jit/vmap, no gradient."""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize

from threept_jax.losses.matcher import detection_cost, hungarian_match

_match = jax.jit(hungarian_match)


def brute_force_min(cost):
    """Minimum total cost of assigning every column (or every row if fewer) one-to-one."""
    p, m = cost.shape
    if p >= m:
        return min(sum(cost[r, c] for c, r in enumerate(rows))
                   for rows in itertools.permutations(range(p), m))
    return min(sum(cost[r, c] for r, c in enumerate(cols))
               for cols in itertools.permutations(range(m), p))


def total(cost, matched):
    cols = np.flatnonzero(matched >= 0)
    rows = matched[cols]
    assert len(set(rows.tolist())) == len(rows), "a hypothesis was matched twice"
    return cost[rows, cols].sum()


def test_square_matches_scipy_and_brute_force():
    cost = np.random.default_rng(0).uniform(size=(6, 6)).astype(np.float32)
    matched = np.asarray(_match(cost, np.ones(6, bool)))
    r, c = scipy.optimize.linear_sum_assignment(cost)
    assert np.all(matched >= 0)
    np.testing.assert_allclose(total(cost, matched), cost[r, c].sum(), rtol=1e-6)
    np.testing.assert_allclose(total(cost, matched), brute_force_min(cost), rtol=1e-6)


def test_rectangular_with_padding_in_a_batch():
    rng = np.random.default_rng(1)
    cost = rng.uniform(size=(3, 7, 5)).astype(np.float32)
    mask = np.array([[1, 1, 1, 0, 0], [1, 0, 1, 0, 1], [0, 0, 0, 0, 0]], bool)
    # Padded columns get costs that would attract the matching if they were not removed.
    cost[~np.broadcast_to(mask[:, None], cost.shape)] = -100.0
    matched = np.asarray(_match(cost, mask))
    assert matched.shape == (3, 5)
    np.testing.assert_array_equal(matched[~mask], -1)
    for b in range(3):
        valid = np.flatnonzero(mask[b])
        assert np.all(matched[b, valid] >= 0)
        if valid.size:
            sub = cost[b][:, valid]
            r, c = scipy.optimize.linear_sum_assignment(sub)
            np.testing.assert_allclose(total(cost[b], matched[b]), sub[r, c].sum(), rtol=1e-6)
            np.testing.assert_allclose(total(cost[b], matched[b]), brute_force_min(sub), rtol=1e-6)


def test_more_targets_than_hypotheses():
    cost = np.random.default_rng(2).uniform(size=(3, 5)).astype(np.float32)
    matched = np.asarray(_match(cost, np.ones(5, bool)))
    assert (matched >= 0).sum() == 3
    r, c = scipy.optimize.linear_sum_assignment(cost)
    np.testing.assert_allclose(total(cost, matched), cost[r, c].sum(), rtol=1e-6)


def test_non_finite_costs_and_vmap():
    cost = np.random.default_rng(3).uniform(size=(2, 4, 3)).astype(np.float32)
    cost[0, 0, 0] = np.nan
    cost[1, 2, 1] = np.inf
    mask = np.ones((2, 3), bool)
    matched = np.asarray(jax.jit(jax.vmap(hungarian_match))(cost, mask))
    for b in range(2):
        assert np.all(matched[b] >= 0) and len(set(matched[b].tolist())) == 3
    assert matched[0, 0] != 0 and matched[1, 1] != 2
    np.testing.assert_array_equal(matched, np.asarray(_match(cost, mask)))


def test_gradient_flows_only_through_the_matched_entries():
    cost = jnp.asarray(np.random.default_rng(4).uniform(size=(4, 3)), jnp.float32)

    def matched_cost(c):
        idx = hungarian_match(c, jnp.ones(3, bool))
        return jnp.sum(c[idx, jnp.arange(3)])

    g = np.asarray(jax.jit(jax.grad(matched_cost))(cost))
    r, c = scipy.optimize.linear_sum_assignment(np.asarray(cost))
    expected = np.zeros((4, 3))
    expected[r, c] = 1.0
    np.testing.assert_array_equal(g, expected)


def test_cost_matrix_hand_case():
    # pred (cx, cy, w, h) = (.5, .5, .2, .2) -> xyxy (.4, .4, .6, .6);
    # target (.55, .5, .2, .4) -> (.45, .3, .65, .7).
    # L1 = .05 + 0 + 0 + .2 = .25. Intersection .15 x .2 = .03, union .04 + .08 - .03 = .09,
    # IoU 1/3, hull .25 x .4 = .1, GIoU = 1/3 - (.1 - .09) / .1 = 0.2333.
    # Focal cost at logit 0: .25 * .25 * ln2 - .75 * .25 * ln2 = -.125 ln 2.
    pred = jnp.asarray([[[0.5, 0.5, 0.2, 0.2]]])
    tgt = jnp.asarray([[[0.55, 0.5, 0.2, 0.4]]])
    cost = jax.jit(lambda a, b, c: detection_cost(a, b, c, class_weight=2.0, l1_weight=5.0,
                                                  giou_weight=3.0))(pred, jnp.zeros((1, 1)), tgt)
    ref = 2.0 * (-0.125 * np.log(2.0)) + 5.0 * 0.25 - 3.0 * (1.0 / 3.0 - 0.1)
    assert cost.shape == (1, 1, 1)
    np.testing.assert_allclose(float(cost[0, 0, 0]), ref, rtol=1e-5)


def test_shape_error():
    with pytest.raises(ValueError, match="disagree"):
        hungarian_match(jnp.zeros((4, 3)), jnp.ones(2, bool))
