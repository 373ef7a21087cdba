"""vMF kernel density on SO(3) and separated top-k, against float64 NumPy/SciPy references."""

import math

import jax
import numpy as np
import pytest
from scipy import integrate
from scipy.spatial.transform import Rotation

from threept_jax.geometry.grids import super_fibonacci_rotations
from threept_jax.geometry.so3_kde import (
    kappa_from_std_deg,
    top_k_separated,
    vmf_kde,
    vmf_log_normalizer,
)

kde = jax.jit(vmf_kde, static_argnames=("normalize_weights", "chunk_size"))


def _angle64(R1, R2):
    """Geodesic angle in radians, float64, via SciPy (independent of the code under test)."""
    rel = Rotation.from_matrix(np.asarray(R1, np.float64)).inv() * Rotation.from_matrix(
        np.asarray(R2, np.float64)
    )
    return rel.magnitude()


def _perturbed(rng, R0, std_deg, n):
    rotvec = rng.normal(scale=math.radians(std_deg), size=(n, 3))
    return (Rotation.from_matrix(R0) * Rotation.from_rotvec(rotvec)).as_matrix()


@pytest.mark.parametrize("kappa", [0.0, 0.7, 8.0, 65.0, 900.0])
def test_normalizer_matches_numerical_integral(kappa):
    # C(kappa) = E_uniform[exp(kappa (cos^2(theta/2) - 1))], the angle having density
    # (1 - cos t) / pi on [0, pi] under the Haar measure.
    def integrand(t):
        return math.exp(kappa * (math.cos(t / 2) ** 2 - 1.0)) * (1.0 - math.cos(t)) / math.pi

    ref, _ = integrate.quad(integrand, 0.0, math.pi, epsabs=0, epsrel=1e-12, limit=200)
    got = float(np.exp(vmf_log_normalizer(kappa)))
    np.testing.assert_allclose(got, ref, rtol=2e-4)


def test_density_integrates_to_one_over_haar_measure():
    # Monte Carlo over Haar-uniform queries: the mean density must be ~1 (uniform = 1).
    rng = np.random.default_rng(1)
    samples = Rotation.random(7, random_state=rng).as_matrix()
    weights = rng.uniform(0.1, 1.0, 7)
    query = Rotation.random(20000, random_state=rng).as_matrix()
    dens = np.asarray(kde(query, samples, weights, 4.0))
    stderr = dens.std() / math.sqrt(dens.size)
    assert abs(dens.mean() - 1.0) < 4 * stderr + 1e-3


@pytest.mark.parametrize("kappa", [3.0, 60.0, 2000.0])
def test_kernel_matches_float64_brute_force(kappa):
    rng = np.random.default_rng(2)
    R0 = Rotation.random(random_state=rng).as_matrix()
    samples = np.concatenate(
        [_perturbed(rng, R0, 5.0, 40), Rotation.random(40, random_state=rng).as_matrix()]
    )
    weights = rng.uniform(0.0, 2.0, len(samples))
    weights[::7] = 0.0  # padding entries
    query = np.concatenate(
        [_perturbed(rng, R0, 3.0, 30), Rotation.random(20, random_state=rng).as_matrix()]
    )

    # Reference: float64 loop using the trace form c^2 = (1 + tr(R1^T R2)) / 4 and a
    # numerically integrated normaliser; shares no code with the quaternion implementation.
    norm, _ = integrate.quad(
        lambda t: math.exp(kappa * (math.cos(t / 2) ** 2 - 1)) * (1 - math.cos(t)) / math.pi,
        0,
        math.pi,
        epsabs=0,
        epsrel=1e-12,
        limit=400,
    )
    w = weights / weights.sum()
    ref = np.zeros(len(query))
    for qi, Rq in enumerate(query):
        for Rs, ws in zip(samples, w):
            c2 = (1.0 + np.trace(Rq.T @ Rs)) / 4.0
            ref[qi] += ws * math.exp(kappa * (c2 - 1.0)) / norm

    got = np.asarray(kde(query, samples, weights, kappa, chunk_size=16))
    np.testing.assert_allclose(got, ref, rtol=3e-3, atol=1e-5 * ref.max())
    raw = np.asarray(kde(query, samples, weights, kappa, normalize_weights=False))
    np.testing.assert_allclose(raw, ref * weights.sum(), rtol=3e-3, atol=1e-5 * raw.max())


def test_mode_recovers_known_rotation():
    rng = np.random.default_rng(3)
    R0 = Rotation.random(random_state=rng).as_matrix()
    # 500 proposals around R0 (10 degree spread) plus 300 uniform distractors, as in one view's
    # top-500 orientation list with clutter.
    samples = np.concatenate(
        [_perturbed(rng, R0, 10.0, 500), Rotation.random(300, random_state=rng).as_matrix()]
    )
    weights = np.ones(len(samples))
    grid = super_fibonacci_rotations(5140)
    kappa = kappa_from_std_deg(10.0)
    coarse = np.asarray(kde(grid, samples, weights, kappa))
    best = grid[int(np.argmax(coarse))]
    # Local refinement: a dense set of rotations within ~15 degrees of the coarse mode.
    local = _perturbed(rng, best, 6.0, 4000)
    fine = np.asarray(kde(local, samples, weights, kappa))
    mode = local[int(np.argmax(fine))]
    assert math.degrees(_angle64(mode, R0)) < 3.0
    # The density at the true rotation far exceeds that of a uniform rotation (= 1).
    assert float(kde(R0[None], samples, weights, kappa)[0]) > 20.0


def test_kappa_from_std_matches_kernel_width():
    # exp(kappa (cos^2(t/2) - 1)) ~ exp(-t^2 / (2 sigma^2)) for small t.
    kappa = kappa_from_std_deg(5.0)
    t = math.radians(2.0)
    sigma = math.radians(5.0)
    np.testing.assert_allclose(
        math.exp(kappa * (math.cos(t / 2) ** 2 - 1)), math.exp(-(t**2) / (2 * sigma**2)), rtol=1e-3
    )


def _greedy_reference(rotations, scores, k, min_angle_deg, score_threshold=-np.inf):
    """Brute-force float64 greedy loop with SciPy angles."""
    order = sorted(range(len(scores)), key=lambda i: (-scores[i], i))
    kept = []
    for i in order:
        if len(kept) == k:
            break
        if scores[i] <= score_threshold:
            continue
        if all(math.degrees(_angle64(rotations[i], rotations[j])) >= min_angle_deg for j in kept):
            kept.append(i)
    return kept


@pytest.mark.parametrize("min_angle,k", [(45.0, 8), (20.0, 16), (90.0, 30)])
def test_top_k_separated_matches_brute_force(min_angle, k):
    rng = np.random.default_rng(int(min_angle))
    # Clusters of nearby rotations make the suppression matter.
    centres = Rotation.random(12, random_state=rng).as_matrix()
    rotations = np.concatenate([_perturbed(rng, c, 15.0, 25) for c in centres])
    scores = rng.uniform(0, 1, len(rotations))
    scores[rng.choice(len(scores), 20, replace=False)] = -np.inf  # padding
    idx, valid = jax.jit(top_k_separated, static_argnums=(2, 3))(rotations, scores, k, min_angle)
    idx, valid = np.asarray(idx), np.asarray(valid)
    got = idx[valid].tolist()
    ref = _greedy_reference(rotations, scores, k, min_angle)
    assert got == ref
    assert np.all(idx[~valid] == 0)
    # Pairwise separation of what was kept.
    for a in range(len(got)):
        for b in range(a + 1, len(got)):
            assert math.degrees(_angle64(rotations[got[a]], rotations[got[b]])) >= min_angle - 1e-4


def test_top_k_separated_threshold_and_exhaustion():
    rng = np.random.default_rng(5)
    R0 = Rotation.random(random_state=rng).as_matrix()
    rotations = _perturbed(rng, R0, 2.0, 10)  # all within a few degrees of each other
    scores = np.linspace(0.0, 1.0, 10)
    idx, valid = top_k_separated(rotations, scores, 4, 45.0, score_threshold=0.5)
    assert np.asarray(valid).tolist() == [True, False, False, False]
    assert int(idx[0]) == 9


def test_bad_shapes_raise_clear_errors():
    R = np.eye(3)[None]
    with pytest.raises(ValueError, match="weights must be"):
        vmf_kde(R, R, np.ones(2), 1.0)
    with pytest.raises(ValueError, match="query must be"):
        vmf_kde(np.eye(3), R, np.ones(1), 1.0)
    with pytest.raises(ValueError, match="scores must be"):
        top_k_separated(R, np.ones(3), 2, 45.0)


def test_kde_mean_shift_reaches_the_chordal_mean():
    from scipy.spatial.transform import Rotation

    from threept_jax.geometry.so3_kde import kde_mean_shift

    centre = Rotation.random(random_state=3)
    noise = Rotation.from_rotvec(np.random.default_rng(3).normal(0, np.radians(4), (200, 3)))
    samples = centre * noise
    w = np.random.default_rng(4).uniform(0.5, 1.5, 200)
    start = (centre * Rotation.from_rotvec([0.2, -0.1, 0.15])).as_matrix()[None]  # ~15 deg off
    # A kernel far wider than the spread: the fixed point is the weighted chordal mean (SciPy).
    got = kde_mean_shift(start.astype(np.float32), samples.as_matrix().astype(np.float32),
                         w.astype(np.float32), 2.0, steps=20)
    ref = samples.mean(weights=w).as_matrix()
    err = Rotation.from_matrix(np.asarray(got[0], np.float64)).inv() * Rotation.from_matrix(ref)
    assert np.degrees(err.magnitude()) < 0.05
    # A narrow kernel climbs to the nearest mode: two clusters, start near the second.
    other = Rotation.from_rotvec([np.pi / 2, 0, 0]) * centre
    both = Rotation.concatenate([samples, other * noise])
    start2 = (other * Rotation.from_rotvec([0.1, 0.1, 0.0])).as_matrix()[None]
    got2 = kde_mean_shift(start2.astype(np.float32), both.as_matrix().astype(np.float32),
                          np.ones(400, np.float32), 400.0, steps=20)
    err2 = Rotation.from_matrix(np.asarray(got2[0], np.float64)).inv() * other
    assert np.degrees(err2.magnitude()) < 1.5
