"""Kernel density estimation on SO(3) with an isotropic von Mises-Fisher kernel.

3PT's multi-view object generation (docs/design.md section 1.2) fuses the orientation
proposals of several views (the top 500 templates of each view, weighted by their scores) with
a kernel density estimate on SO(3), re-weights the proposals by that density and keeps the top
K rotations at a minimum angular separation. This module provides the two pieces:
:func:`vmf_kde` and :func:`top_k_separated`.

The kernel. With unit quaternions q1, q2 of two rotations and c = <q1, q2> (so that
c^2 = cos^2(theta / 2) = (1 + trace(R1^T R2)) / 4 for the angle theta between them), we use the
antipodally symmetric form

    k_kappa(R1, R2) = exp(kappa * (c^2 - 1)) / C(kappa),

which is the quaternion (Bingham) form of the isotropic matrix Fisher distribution
exp(tr(F^T R)) with F = (kappa / 4) I, and the natural von Mises-Fisher kernel on SO(3): q and
-q give the same value. For small angles c^2 - 1 ~ -theta^2 / 4, so the kernel is a Gaussian in
the rotation angle with standard deviation sqrt(2 / kappa) radians (:func:`kappa_from_std_deg`).

Normalisation. C(kappa) makes every kernel a probability density with respect to the
*normalised* Haar measure of SO(3) (total mass 1, so the uniform distribution has density 1).
With the Haar density of the angle, (1 - cos theta) / pi on [0, pi], the integral has the closed
form C(kappa) = exp(-kappa/2) (I0(kappa/2) - I1(kappa/2)) = i0e(kappa/2) - i1e(kappa/2), with
exponentially scaled Bessel functions, so it is evaluated without overflow. Densities are thus
comparable across kappa and across calls: a value of 50 means "50 times more likely than a
uniformly random rotation". float32 is accurate for kappa up to about 1e4 (a kernel width of
under a degree).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jax.scipy.special import i0e, i1e

from threept_jax.geometry.rotations import matrix_to_quaternion, quaternion_to_matrix

Array = jax.Array

_HIGHEST = jax.lax.Precision.HIGHEST


def kappa_from_std_deg(std_deg: float) -> float:
    """Concentration kappa whose kernel has angular standard deviation ``std_deg`` degrees.

    Small-angle approximation of the kernel (module docstring): exp(-kappa theta^2 / 4), a
    Gaussian in theta with sigma^2 = 2 / kappa. E.g. 10 degrees -> kappa ~ 65.7.
    """
    if std_deg <= 0:
        raise ValueError(f"std_deg must be positive (degrees), got {std_deg}")
    sigma = math.radians(std_deg)
    return 2.0 / (sigma * sigma)


def vmf_log_normalizer(kappa: Array) -> Array:
    """log C(kappa) of the kernel exp(kappa (c^2 - 1)) / C(kappa) (module docstring). [...]->[...]

    C(kappa) = i0e(kappa / 2) - i1e(kappa / 2) is the mean of exp(kappa (c^2 - 1)) over
    Haar-uniform rotations; C(0) = 1.
    """
    half = 0.5 * jnp.asarray(kappa, jnp.float32)
    return jnp.log(i0e(half) - i1e(half))


def vmf_kde(
    query: Array,
    samples: Array,
    weights: Array,
    kappa: float | Array,
    *,
    normalize_weights: bool = True,
    chunk_size: int = 1024,
) -> Array:
    """Weighted von Mises-Fisher kernel density on SO(3) at query rotations.

    query [Q, 3, 3], samples [S, 3, 3], weights [S] (>= 0; 0 marks padding), kappa scalar
    (concentration, see :func:`kappa_from_std_deg`) -> density [Q] float32.

    density(R) = sum_s w_s k_kappa(R, R_s), with w normalised to sum to 1 when
    ``normalize_weights`` (then the result is a probability density with respect to the
    normalised Haar measure: uniform = 1). With ``normalize_weights=False`` the raw weights are
    used, e.g. to let views with more or better proposals carry more mass. All-zero weights give
    a density of 0 everywhere.

    Memory is O(chunk_size * S): the Q queries are processed in chunks of ``chunk_size``
    sequentially, so Q and S of several thousand stay within a few tens of MB. Jit-able; kappa
    may be traced.
    """
    query = jnp.asarray(query, jnp.float32)
    samples = jnp.asarray(samples, jnp.float32)
    weights = jnp.asarray(weights, jnp.float32)
    if query.ndim != 3 or query.shape[-2:] != (3, 3):
        raise ValueError(f"query must be [Q, 3, 3] rotation matrices, got shape {query.shape}")
    if samples.ndim != 3 or samples.shape[-2:] != (3, 3):
        raise ValueError(f"samples must be [S, 3, 3] rotation matrices, got shape {samples.shape}")
    if weights.shape != samples.shape[:1]:
        raise ValueError(
            f"weights must be [S] = [{samples.shape[0]}] (one per sample), got {weights.shape}"
        )
    if chunk_size < 1:
        raise ValueError(f"chunk_size must be >= 1, got {chunk_size}")
    kappa = jnp.asarray(kappa, jnp.float32)

    q_query = matrix_to_quaternion(query)  # [Q, 4]
    q_samples = matrix_to_quaternion(samples)  # [S, 4]
    if normalize_weights:
        total = jnp.sum(weights)
        weights = weights / jnp.where(total > 0, total, 1.0)

    num_query = query.shape[0]
    chunk = min(chunk_size, max(num_query, 1))
    num_chunks = -(-num_query // chunk)
    padded = jnp.zeros((num_chunks * chunk, 4), jnp.float32).at[:num_query].set(q_query)

    def one_chunk(qc: Array) -> Array:  # [C, 4] -> [C]
        # HIGHEST keeps the dot product in full float32 on accelerators (TF32 would blur the
        # kernel for large kappa, where c is within 1e-4 of 1).
        c = jnp.matmul(qc, q_samples.T, precision=_HIGHEST)  # [C, S]
        # c^2 - 1 <= 0 so exp never overflows; far samples underflow harmlessly to 0.
        k = jnp.exp(kappa * (jnp.minimum(c * c, 1.0) - 1.0))
        return jnp.matmul(k, weights, precision=_HIGHEST)

    dens = jax.lax.map(one_chunk, padded.reshape(num_chunks, chunk, 4)).reshape(-1)[:num_query]
    return dens * jnp.exp(-vmf_log_normalizer(kappa))


def top_k_separated(
    rotations: Array,
    scores: Array,
    k: int,
    min_angle_deg: float,
    *,
    score_threshold: float = -jnp.inf,
) -> tuple[Array, Array]:
    """Greedy selection of the k best-scoring rotations that are pairwise far apart.

    rotations [N, 3, 3], scores [N] -> (indices [k] int32, valid [k] bool).

    Repeatedly keeps the highest remaining score (ties: lowest index) and removes every
    rotation closer than ``min_angle_deg`` (geodesic angle) to it, itself included; rotations
    at exactly ``min_angle_deg`` are kept. Candidates with score <= ``score_threshold`` (for
    padding, pass -inf scores or a threshold) are never selected. Slots after the last kept
    rotation have ``valid=False`` and index 0. Time O(k N), memory O(N); jit-able with static
    ``k``. This is the "top K hypotheses at least 45 degrees apart" step of 3PT's object
    generation (docs/design.md section 1.2).
    """
    rotations = jnp.asarray(rotations, jnp.float32)
    scores = jnp.asarray(scores, jnp.float32)
    if rotations.ndim != 3 or rotations.shape[-2:] != (3, 3):
        raise ValueError(f"rotations must be [N, 3, 3], got shape {rotations.shape}")
    if scores.shape != rotations.shape[:1]:
        raise ValueError(f"scores must be [N] = [{rotations.shape[0]}], got {scores.shape}")
    if not 0.0 <= min_angle_deg <= 180.0:
        raise ValueError(f"min_angle_deg must be in [0, 180] degrees, got {min_angle_deg}")
    n = rotations.shape[0]
    quats = matrix_to_quaternion(rotations)  # [N, 4]
    # angle(R1, R2) < m  <=>  |<q1, q2>| > cos(m / 2) for unit quaternions.
    cos_half = math.cos(math.radians(min_angle_deg) / 2.0)
    alive = scores > score_threshold

    def body(i, state):
        alive, idx, valid = state
        best = jnp.argmax(jnp.where(alive, scores, -jnp.inf))
        ok = alive[best]
        dots = jnp.abs(jnp.matmul(quats, quats[best], precision=_HIGHEST))  # [N]
        suppress = (dots > cos_half) | (jnp.arange(n) == best)
        alive = alive & ~(suppress & ok)
        return alive, idx.at[i].set(jnp.where(ok, best, 0)), valid.at[i].set(ok)

    idx = jnp.zeros((k,), jnp.int32)
    valid = jnp.zeros((k,), bool)
    if n == 0:
        return idx, valid
    _, idx, valid = jax.lax.fori_loop(0, k, body, (alive, idx, valid))
    return idx, valid


def kde_mean_shift(
    query: Array,
    samples: Array,
    weights: Array,
    kappa: float | Array,
    *,
    steps: int = 3,
) -> Array:
    """Move rotations [Q, 3, 3] uphill on the vMF kernel density of samples [S, 3, 3] -> [Q, 3, 3].

    Mean shift on SO(3), as Gaussian mean shift in Euclidean space: each step replaces a query
    by the kernel-weighted chordal mean of the sample quaternions (signs aligned with the
    query, since q and -q are one rotation), renormalised. With a kernel much wider than the
    samples' spread this is the weighted chordal mean of the samples; in general it climbs to
    the nearby mode. Object generation uses it to refine the densest proposals past the
    template grid's resolution. Jit-able.
    """
    q = matrix_to_quaternion(jnp.asarray(query, jnp.float32))  # [Q, 4]
    qs = matrix_to_quaternion(jnp.asarray(samples, jnp.float32))  # [S, 4]
    w = jnp.asarray(weights, jnp.float32)
    kappa = jnp.asarray(kappa, jnp.float32)

    def step(_, q):
        c = jnp.matmul(q, qs.T, precision=_HIGHEST)  # [Q, S]
        k = w * jnp.exp(kappa * (jnp.minimum(c * c, 1.0) - 1.0))
        mean = jnp.matmul(k * jnp.sign(c + (c == 0)), qs, precision=_HIGHEST)  # [Q, 4]
        norm = jnp.linalg.norm(mean, axis=-1, keepdims=True)
        return jnp.where(norm > 1e-12, mean / jnp.maximum(norm, 1e-12), q)

    return quaternion_to_matrix(jax.lax.fori_loop(0, steps, step, q))
