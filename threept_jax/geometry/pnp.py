"""Multi-view Perspective-n-Point: robust Levenberg-Marquardt on SE(3) over all views at once.

3PT's refiner (docs/design.md section 1.3) turns 2D-3D correspondences from every view (render
pixels with known object coordinates matched to real pixels) into one pose update of the object
in the world frame. :func:`solve_pnp` does that: it minimises the robust reprojection error of
all correspondences in all calibrated views jointly,

    sum_v sum_n w_vn rho(|| pi(K_v, T_cam_world_v T_world_obj X_vn) - x_vn ||),

with rho a Huber loss (scale ``huber_px`` pixels) followed by a few Tukey-biweight iterations
(scale ``tukey_px``) that remove the remaining influence of gross outliers, the way RANSAC's
final inlier refit does.

Design choices (all branch-free, so the solver is jit-able and vmap-able over problems):

* Parameterisation: **right perturbation in the object frame**, about the weighted centroid c of
  the 3D points: T_world_obj' = T_world_obj [I, c] [Exp(omega), rho] [I, -c]. Centring decouples
  rotation from translation and keeps the 6x6 normal equations well conditioned in float32. The
  update is the first-order SE(3) retraction (R Exp(omega), t + R rho), which has the same
  derivative at 0 as the exponential map.
* Jacobians are analytic; the 6x6 normal equations are accumulated in one fused reduction and
  solved by an unrolled Jacobi-scaled Cholesky. Damping is Marquardt's (lambda times the
  diagonal); accept/reject and the lambda update are ``jnp.where`` selects. Each iteration
  costs one evaluation (the candidate's cost, Jacobian and normal equations are computed
  together and kept if the step is accepted).
* Robust weights are IRLS weights rho'(s)/s recomputed at every evaluation; the accept test
  uses the true robust cost.
* Depth is clamped to ``min_depth`` (mm) before the perspective division, so points behind a
  camera give large but finite residuals, which the robust loss caps.
* Without an initial pose, a linear initialisation runs on every view: a DLT (11 unknowns, the
  last entry of P fixed to 1, valid because the centroid lies in front of the camera) and a
  plane homography (8 unknowns, for flat point sets where the DLT is singular), each refined by
  a few iteratively reweighted (Cauchy) solves; the candidate with the lowest robust
  multi-view cost is lifted to the world frame and refined by LM.

Conventions: millimetres, OpenCV cameras (docs/design.md section 3), ``K`` with pixel-centre
coordinates (``threept_jax.geometry.camera``). Shapes: V views, N correspondences per view
(pad with weight 0).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

Array = jax.Array


def _spd_solve_entries(a: list[list[Array]], b: list[Array], jitter: float = 1e-6,
                       jacobi: bool = True) -> list[Array]:
    """Solve A x = b for symmetric positive semi-definite A given entry by entry.

    ``a[i][j]`` and ``b[i]`` are same-shape arrays (any batch shape), so every step of the
    Cholesky factorisation, unrolled at trace time, is an elementwise operation on contiguous
    batch vectors that XLA fuses: much faster than one LAPACK call (or strided slicing of a
    [..., n, n] array) per tiny matrix. Regularised so that singular systems give a finite
    answer instead of NaN: with ``jacobi`` the system is scaled to a unit diagonal and
    ``jitter`` is added to it (scale-free, for well-posed systems such as LM's normal
    equations); without, ``jitter`` times the mean diagonal is added (a ridge that drives
    directions without data to zero, which the DLT relies on for flat point sets).
    """
    n = len(b)
    dtype = b[0].dtype
    tiny = jnp.finfo(dtype).tiny
    if jacobi:
        inv_d = [jax.lax.rsqrt(jnp.maximum(a[i][i], tiny)) for i in range(n)]
        a = [[a[i][j] * inv_d[i] * inv_d[j] for j in range(n)] for i in range(n)]
        b = [b[i] * inv_d[i] for i in range(n)]
        ridge = jnp.asarray(jitter, dtype)
    else:
        ridge = jitter * jnp.maximum(sum(a[i][i] for i in range(n)) / n, tiny)
    floor = ridge * 1e-3
    L: list[list[Array | None]] = [[None] * n for _ in range(n)]
    inv_diag: list[Array] = []
    for j in range(n):
        acc = a[j][j] + ridge
        for k in range(j):
            acc = acc - L[j][k] * L[j][k]
        inv = jax.lax.rsqrt(jnp.maximum(acc, floor))
        inv_diag.append(inv)
        for i in range(j + 1, n):
            acc = a[i][j]
            for k in range(j):
                acc = acc - L[i][k] * L[j][k]
            L[i][j] = acc * inv
    y: list[Array] = []
    for i in range(n):
        acc = b[i]
        for k in range(i):
            acc = acc - L[i][k] * y[k]
        y.append(acc * inv_diag[i])
    x: list[Array | None] = [None] * n
    for i in reversed(range(n)):
        acc = y[i]
        for k in range(i + 1, n):
            acc = acc - L[k][i] * x[k]
        x[i] = acc * inv_diag[i]
    if jacobi:
        x = [x[i] * inv_d[i] for i in range(n)]
    return x


def _spd_solve(A: Array, b: Array, jitter: float = 1e-6, jacobi: bool = True) -> Array:
    """Array form of :func:`_spd_solve_entries`: A [..., n, n], b [..., n] -> x [..., n]."""
    n = A.shape[-1]
    a = [[A[..., i, j] for j in range(n)] for i in range(n)]
    x = _spd_solve_entries(a, [b[..., i] for i in range(n)], jitter, jacobi)
    return jnp.stack(x, axis=-1)


def _cross3(a: list[Array], b: list[Array]) -> list[Array]:
    """Cross product of 3-vectors given as lists of 3 arrays."""
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def _dot3(a: list[Array], b: list[Array]) -> Array:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _polar_entries(m: list[list[Array]], iterations: int = 6) -> list[list[Array]]:
    """Nearest rotation to the 3x3 matrix ``m[row][col]`` (orthogonal polar factor).

    Scaled Newton iteration X <- (z X + X^-T / z) / 2 with z = |det X|^(-1/3) (Higham 1986),
    which converges quadratically; X^-T is the cofactor matrix over the determinant. A negative
    determinant (a reflection, e.g. from a failed DLT) is flipped first, since -M is the closer
    proper-rotation candidate for a 3x3 matrix; a singular M returns a finite matrix.
    Branch-free and elementwise over any batch shape.
    """
    cols = [[m[r][c] for r in range(3)] for c in range(3)]
    det = _dot3(cols[0], _cross3(cols[1], cols[2]))
    sign = jnp.where(det < 0, -1.0, 1.0).astype(det.dtype)
    cols = [[sign * v for v in col] for col in cols]
    tiny = jnp.finfo(det.dtype).tiny ** 0.25

    def newton(_, flat):
        c0, c1, c2 = flat[0:3], flat[3:6], flat[6:9]
        cof = _cross3(c1, c2) + _cross3(c2, c0) + _cross3(c0, c1)  # columns of the cofactors
        det = _dot3(c0, cof[0:3])
        det = jnp.where(jnp.abs(det) < tiny, tiny, det)
        z = jnp.abs(det) ** (-1.0 / 3.0)
        inv = 1.0 / (z * det)
        return tuple(0.5 * (z * a + b * inv) for a, b in zip(flat, cof))

    # A rolled loop: the body is compiled once (unrolled, it dominated compile time).
    flat = jax.lax.fori_loop(0, iterations, newton, tuple(v for col in cols for v in col))
    cols = [list(flat[0:3]), list(flat[3:6]), list(flat[6:9])]
    return [[cols[c][r] for c in range(3)] for r in range(3)]


def _polar_rotation(M: Array, iterations: int = 6) -> Array:
    """Array form of :func:`_polar_entries`: M [..., 3, 3] -> rotation [..., 3, 3]."""
    m = [[M[..., r, c] for c in range(3)] for r in range(3)]
    out = _polar_entries(m, iterations)
    return jnp.stack([jnp.stack(row, -1) for row in out], -2)


def _cross_cols(a: Array, b: Array) -> Array:
    """Row-wise cross product of [..., 3] vectors (explicit, so it fuses)."""
    return jnp.stack(
        [
            a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
            a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
            a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0],
        ],
        axis=-1,
    )


def _exp_so3(w: Array) -> Array:
    """Rodrigues exp map [..., 3] -> [..., 3, 3], with Taylor terms near 0 (elementwise)."""
    th2 = jnp.sum(w * w, axis=-1)
    small = th2 < 1e-8
    safe = jnp.where(small, 1.0, th2)
    th = jnp.sqrt(safe)
    a = jnp.where(small, 1.0 - th2 / 6.0, jnp.sin(th) / th)
    b = jnp.where(small, 0.5 - th2 / 24.0, (1.0 - jnp.cos(th)) / safe)
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    one = jnp.ones_like(x)
    rows = [
        [one - b * (y * y + z * z), -a * z + b * x * y, a * y + b * x * z],
        [a * z + b * x * y, one - b * (x * x + z * z), -a * x + b * y * z],
        [-a * y + b * x * z, a * x + b * y * z, one - b * (x * x + y * y)],
    ]
    return jnp.stack([jnp.stack(r, -1) for r in rows], -2)


def _matvec3(M: Array, v: Array) -> Array:
    """M [..., 3, 3] @ v [..., 3] -> [..., 3] without a dot op (keeps fusion on CPU)."""
    return jnp.sum(M * v[..., None, :], axis=-1)


def _matmul3(A: Array, B: Array) -> Array:
    """A [..., 3, 3] @ B [..., 3, 3] elementwise (tiny matrices, fusable)."""
    return jnp.sum(A[..., :, :, None] * B[..., None, :, :], axis=-2)


class _Problem:
    """Preprocessed arrays of one PnP problem (all [V, ...] or [V, N])."""

    def __init__(self, X, uv, K, T_cam_world, w, min_depth):
        self.X0, self.X1, self.X2 = X[..., 0], X[..., 1], X[..., 2]  # [V, N] centred
        self.fx = K[:, 0, 0][:, None]
        self.sk = K[:, 0, 1][:, None]
        self.fy = K[:, 1, 1][:, None]
        # Observations relative to the principal point: halves the magnitude of the numbers
        # whose difference is the residual, which matters at float32 precision.
        self.uo = uv[..., 0] - K[:, 0, 2][:, None]
        self.vo = uv[..., 1] - K[:, 1, 2][:, None]
        self.Rcw = T_cam_world[:, :3, :3]
        self.tcw = T_cam_world[:, :3, 3]
        self.w = w
        self.min_depth = min_depth

    def camera_points(self, R: Array, t: Array):
        """Object rotation R [3, 3], translation t [3] of the centred frame -> per-view M, p."""
        M = _matmul3(self.Rcw, R[None])  # [V, 3, 3] R_cam_obj
        tc = _matvec3(self.Rcw, t[None]) + self.tcw  # [V, 3]
        p = [
            M[:, i, 0, None] * self.X0 + M[:, i, 1, None] * self.X1 + M[:, i, 2, None] * self.X2
            + tc[:, i, None]
            for i in range(3)
        ]
        return M, p

    def residuals(self, R: Array, t: Array):
        M, (px, py, pz) = self.camera_points(R, t)
        iz = 1.0 / jnp.maximum(pz, self.min_depth)
        a = px * iz
        b = py * iz
        u = self.fx * a + self.sk * b
        v = self.fy * b
        return M, iz, u, v, u - self.uo, v - self.vo


def _robust(s2: Array, kind: str, scale: float):
    """Per-point robust cost rho and IRLS weight rho'(s)/s from squared residual norms s2."""
    if kind == "huber":
        # One rsqrt instead of a sqrt and a division: this runs once per point per iteration.
        inside = s2 <= scale * scale
        inv_s = jax.lax.rsqrt(jnp.maximum(s2, scale * scale))
        rho = jnp.where(inside, 0.5 * s2, scale * (s2 * inv_s - 0.5 * scale))
        wr = jnp.where(inside, 1.0, scale * inv_s)
        return rho, wr
    if kind == "tukey":
        c2 = scale * scale
        t2 = jnp.minimum(s2 / c2, 1.0)
        one_minus = 1.0 - t2
        rho = c2 / 6.0 * (1.0 - one_minus * one_minus * one_minus)
        return rho, one_minus * one_minus
    if kind == "cauchy":
        c2 = scale * scale
        return 0.5 * c2 * jnp.log1p(s2 / c2), 1.0 / (1.0 + s2 / c2)
    raise ValueError(f"unknown robust loss {kind!r}; use 'huber', 'tukey' or 'cauchy'")


def _sum_all(arrays: list[Array], axes: tuple[int, ...] | None = None) -> list[Array]:
    """Sums of many same-shape arrays over ``axes`` (default all) in one variadic reduction.

    XLA fuses a variadic reduction with the elementwise code producing its operands into a
    single pass over the data; separate ``jnp.sum`` calls (or a batched ``dot_general`` over
    tiny matrices) are several times slower on CPU.
    """
    ndim = arrays[0].ndim
    axes = tuple(range(ndim)) if axes is None else tuple(a % ndim for a in axes)
    zeros = tuple(jnp.zeros((), a.dtype) for a in arrays)
    out = jax.lax.reduce(
        tuple(arrays), zeros, lambda x, y: tuple(a + b for a, b in zip(x, y)), axes)
    return list(out)


def _robust_phase(s2: Array, tukey_phase: Array, huber_px: float, tukey_px: float | None):
    """Huber, or Tukey where the (traced) ``tukey_phase`` flag is set: rho and IRLS weights."""
    rho, wr = _robust(s2, "huber", huber_px)
    if tukey_px is None:
        return rho, wr
    rho_t, wr_t = _robust(s2, "tukey", tukey_px)
    return jnp.where(tukey_phase, rho_t, rho), jnp.where(tukey_phase, wr_t, wr)


def _cost(prob: _Problem, R: Array, t: Array, kind: str, scale: float) -> Array:
    _, _, _, _, ru, rv = prob.residuals(R, t)
    rho, _ = _robust(ru * ru + rv * rv, kind, scale)
    return jnp.sum(prob.w * rho)


def _evaluate(prob: _Problem, R: Array, t: Array, tukey_phase: Array, huber_px: float,
              tukey_px: float | None):
    """Robust cost, 6x6 normal matrix H and gradient g at (R, t): right perturbation."""
    M, iz, u, v, ru, rv = prob.residuals(R, t)
    rho, wr = _robust_phase(ru * ru + rv * rv, tukey_phase, huber_px, tukey_px)
    W = prob.w * wr
    X = (prob.X0, prob.X1, prob.X2)
    # d(u, v)/d(p_cam) = [[fx, s, -u], [0, fy, -v]] / z;  d p_cam / d rho = M,
    # d p_cam / d omega = -M [X]_x, so a row a of d(u,v)/d rho gives X x a for omega.
    cu = prob.fx * M[:, 0, :] + prob.sk * M[:, 1, :]  # [V, 3] per-view constants
    cv = prob.fy * M[:, 1, :]
    Au = [(cu[:, k, None] - u * M[:, 2, k, None]) * iz for k in range(3)]
    Av = [(cv[:, k, None] - v * M[:, 2, k, None]) * iz for k in range(3)]

    def with_omega(A):
        return [X[1] * A[2] - X[2] * A[1], X[2] * A[0] - X[0] * A[2], X[0] * A[1] - X[1] * A[0]] + A

    Ju = with_omega(Au)  # 6 x [V, N]
    Jv = with_omega(Av)
    # The 21 distinct entries of J^T W J, the 6 of J^T W r and the cost in one variadic
    # reduction over (V, N): a single pass over the points.
    WJu = [W * j for j in Ju]
    WJv = [W * j for j in Jv]
    pairs = [(k, l) for k in range(6) for l in range(k, 6)]
    terms = [WJu[k] * Ju[l] + WJv[k] * Jv[l] for k, l in pairs]
    terms += [WJu[k] * ru + WJv[k] * rv for k in range(6)]
    terms.append(prob.w * rho)
    sums = _sum_all(terms)
    entries = dict(zip(pairs, sums[:21]))
    H = jnp.stack([jnp.stack([entries[min(k, l), max(k, l)] for l in range(6)]) for k in range(6)])
    g = jnp.stack(sums[21:27])
    cost = sums[27]
    return cost, H, g


def _levenberg_marquardt(prob: _Problem, R: Array, t: Array, *, huber_px: float,
                         tukey_px: float | None, huber_iterations: int, tukey_iterations: int,
                         rtol_huber: float, rtol: float, atol: Array):
    """Robust LM from (R, t): a Huber phase, then (optionally) a Tukey phase.

    One ``lax.while_loop`` runs both phases, so the normal equations are traced once. An
    iteration evaluates a candidate (the pose after the pending damped step, or at the start of
    a phase the current pose under the phase's loss), accepts it if the robust cost drops
    (lambda x0.2, else x10), then solves for the next step. A phase ends when that step's
    predicted decrease is below rtol * cost + atol with lambda <= 1 (converged, without
    spending an evaluation on the negligible step), when lambda saturates (stalled), or after
    its step cap. Everything is ``jnp.where``-selected, so it vmaps.
    Returns (R, t, steps taken, converged in the final phase).
    """
    dtype = t.dtype
    lam0, lam_min, lam_max = 1e-4, 1e-9, 1e7
    two_phase = tukey_px is not None and tukey_iterations > 0
    max_loops = huber_iterations + (tukey_iterations + 1 if two_phase else 0) + 1

    def cond(state):
        return ~state["done"] & (state["loops"] < max_loops)

    def next_step(H, g, lam):
        """Damped step from (H, g) and the decrease the quadratic model predicts for it."""
        d2 = jnp.maximum(jnp.diagonal(H), jnp.finfo(dtype).tiny)
        delta = _spd_solve(H + jnp.diag(lam * d2), -g)
        return delta, -jnp.dot(g, delta) - 0.5 * jnp.dot(delta, H @ delta)

    def body(st):
        fresh, tukey = st["fresh"], st["tukey"]
        delta = jnp.where(fresh, 0.0, st["delta"])
        R_new = _matmul3(st["R"], _exp_so3(delta[:3]))
        t_new = st["t"] + _matvec3(st["R"], delta[3:])
        cost_new, H_new, g_new = _evaluate(prob, R_new, t_new, tukey, huber_px, tukey_px)
        accept = fresh | ((cost_new < st["cost"]) & jnp.isfinite(cost_new))
        cost = jnp.where(accept, cost_new, st["cost"])
        H = jnp.where(accept, H_new, st["H"])
        g = jnp.where(accept, g_new, st["g"])
        lam = jnp.where(fresh, lam0, jnp.clip(jnp.where(accept, st["lam"] * 0.2,
                                                        st["lam"] * 10.0), lam_min, lam_max))
        stepped = ~fresh
        k = jnp.where(fresh, 0, st["k"] + 1)
        # The next step is computed now, so that a phase whose next step would be negligible
        # ends without spending an evaluation on it.
        delta_next, predicted = next_step(H, g, lam)
        cap = jnp.where(tukey, tukey_iterations, huber_iterations)
        converged = (predicted <= jnp.where(tukey, rtol, rtol_huber) * cost + atol) & (lam <= 1.0)
        phase_end = (k >= cap) | converged | (lam >= lam_max)
        if two_phase:
            switch = phase_end & ~tukey
            done = phase_end & tukey
        else:
            switch = jnp.bool_(False)
            done = phase_end
        return {
            "loops": st["loops"] + 1,
            "steps": st["steps"] + stepped.astype(jnp.int32),
            "k": k,
            "fresh": switch,
            "tukey": tukey | switch,
            "done": done,
            "converged": jnp.where(done, converged, st["converged"]),
            "R": jnp.where(accept, R_new, st["R"]),
            "t": jnp.where(accept, t_new, st["t"]),
            "cost": cost,
            "H": H,
            "g": g,
            "lam": lam,
            "delta": delta_next,
        }

    state = {
        "loops": jnp.int32(0), "steps": jnp.int32(0), "k": jnp.int32(0),
        "fresh": jnp.bool_(True), "tukey": jnp.bool_(False), "done": jnp.bool_(False),
        "converged": jnp.bool_(False), "R": R, "t": t, "cost": jnp.asarray(jnp.inf, dtype),
        "H": jnp.eye(6, dtype=dtype), "g": jnp.zeros(6, dtype), "lam": jnp.asarray(lam0, dtype),
        "delta": jnp.zeros(6, dtype),
    }
    out = jax.lax.while_loop(cond, body, state)
    return out["R"], out["t"], out["steps"], out["converged"]


def _fit_dlt(X: list[Array], x: Array, y: Array, w: Array, scale: Array, ridge: float = 1e-6,
             unrolled: bool = True):
    """Weighted DLT with P[2, 3] = 1 in principal-axes coordinates.

    X: 3 arrays [..., m], the centred 3D points in the principal axes of the point set, scaled
    to unit RMS radius ``scale`` (mm); x, y [..., m] normalised image coordinates; w [..., m]
    weights.
    Returns (RE [..., 3, 3], t [..., 3]) with p_cam ~ s RE X + t, i.e. RE = R_cam_obj E for the
    principal axes E and RMS radius s.

    Flat point sets: the coordinate along the smallest axis is ~0, its columns of the normal
    matrix vanish and the ridge sets the matching entries of P to 0, so the remaining 8
    unknowns are exactly the plane homography; the missing third column of the rotation is
    completed from the first two. One solver thus covers planar and non-planar objects.
    """
    one = jnp.ones_like(x)
    Xt = [X[0], X[1], X[2], one]
    r2 = x * x + y * y
    wx, wy, wr = w * x, w * y, w * r2
    pairs4 = [(i, j) for i in range(4) for j in range(i, 4)]
    pairs3 = [(i, j) for i in range(3) for j in range(i, 3)]
    terms = [w * Xt[i] * Xt[j] for i, j in pairs4]
    terms += [wx * Xt[i] * X[j] for i in range(4) for j in range(3)]
    terms += [wy * Xt[i] * X[j] for i in range(4) for j in range(3)]
    terms += [wr * X[i] * X[j] for i, j in pairs3]
    terms += [wx * Xt[i] for i in range(4)] + [wy * Xt[i] for i in range(4)]
    terms += [wr * X[j] for j in range(3)]
    sums = iter(_sum_all(terms, axes=(-1,)))
    A = {pq: next(sums) for pq in pairs4}
    Bx = {(i, j): next(sums) for i in range(4) for j in range(3)}
    By = {(i, j): next(sums) for i in range(4) for j in range(3)}
    C = {pq: next(sums) for pq in pairs3}
    rx = [next(sums) for _ in range(4)]
    ry = [next(sums) for _ in range(4)]
    rc = [next(sums) for _ in range(3)]
    zero = jnp.zeros_like(rx[0])

    def entry(r, c):  # the normal matrix of unknowns [P_row0 (4), P_row1 (4), P_row2[:3] (3)]
        if r > c:
            r, c = c, r
        if c < 4:
            return A[r, c]
        if r < 4 and c < 8:
            return zero
        if r < 4:
            return -Bx[r, c - 8]
        if c < 8:
            return A[r - 4, c - 4]
        if r < 8:
            return -By[r - 4, c - 8]
        return C[r - 8, c - 8]

    a = [[entry(r, c) for c in range(11)] for r in range(11)]
    b = rx + ry + [-v for v in rc]
    if unrolled:
        p = _spd_solve_entries(a, b, jitter=ridge, jacobi=False)
    else:
        # LAPACK: slower per tiny system but far quicker to compile; used where the batch of
        # systems is small (one per view).
        A = jnp.stack([jnp.stack(row, -1) for row in a], -2)
        A = A + (ridge * jnp.mean(jnp.diagonal(A, axis1=-2, axis2=-1), -1))[..., None, None] \
            * jnp.eye(11, dtype=A.dtype)
        L = jnp.linalg.cholesky(A)
        sol = jax.scipy.linalg.cho_solve((L, True), jnp.stack(b, -1)[..., None])[..., 0]
        p = [sol[..., i] for i in range(11)]
    m = [p[0:3], p[4:7], p[8:11]]  # rows of P[:, :3]
    tp = [p[3], p[7], jnp.ones_like(p[0])]
    m1 = [m[r][0] for r in range(3)]
    m2 = [m[r][1] for r in range(3)]
    n1 = jnp.sqrt(_dot3(m1, m1))
    n2 = jnp.sqrt(_dot3(m2, m2))
    normal = _cross3(m1, m2)
    inv_n = 1.0 / jnp.maximum(jnp.sqrt(_dot3(normal, normal)), 1e-30)
    # m ~ mu s [r1 r2 r3] (mu = 1 / t_z > 0 because P[2, 3] = 1 and the centroid is in front).
    # Adding mu s r3 (estimated from the first two columns) to the third column leaves the
    # polar factor unchanged for 3D points (giving [1 1 2] scaling) and completes it for flat
    # ones (third column ~ 0).
    col_norm = 0.5 * (n1 + n2) * inv_n
    aug = [[m[r][0], m[r][1], m[r][2] + col_norm * normal[r]] for r in range(3)]
    RE = _polar_entries(aug)
    mu_s = 0.5 * (_dot3([RE[r][0] for r in range(3)], m1) + _dot3([RE[r][1] for r in range(3)], m2))
    mu_s = jnp.where(jnp.abs(mu_s) < 1e-30, 1e-30, mu_s)
    f = scale / mu_s
    RE = jnp.stack([jnp.stack(row, -1) for row in RE], -2)
    return RE, jnp.stack([v * f for v in tp], -1)


def _linear_init(prob: _Problem, E: Array, scale_X: Array, *, num_views: int,
                 num_hypotheses: int, num_score_points: int, key: Array, threshold_px: float,
                 irls_scales_px: tuple[float, ...], cost_kind: str, cost_scale: float):
    """Initial (R, t) of the centred object frame in the world, from single-view DLTs.

    Runs on the ``num_views`` views with the largest total weight. Per view:
    ``num_hypotheses`` DLTs on random 6-point subsets of the valid points are scored by MSAC
    (sum of w min(err^2, threshold^2)) on ``num_score_points`` random valid points of the view;
    from the best, the least-squares DLT on all points and then Cauchy-reweighted DLTs (scales
    ``irls_scales_px``) are tried in turn, each kept only if it lowers the MSAC score on all
    points. The per-view results are lifted to the world frame and the one with the lowest
    robust multi-view cost is returned.
    """
    N = prob.w.shape[1]
    V = min(num_views, prob.w.shape[0])
    _, views = jax.lax.top_k(jnp.sum(prob.w, -1), V)  # [V] the best-supported views
    w_v = prob.w[views]
    y = prob.vo[views] / prob.fy[views]  # normalised image coordinates [V, N]
    x = (prob.uo[views] - prob.sk[views] * y) / prob.fx[views]
    inv_s = 1.0 / scale_X
    # Principal-axes coordinates at unit scale: X'' = E^T Xc / s.
    Xp = [(E[0, k] * prob.X0[views] + E[1, k] * prob.X1[views] + E[2, k] * prob.X2[views])
          * inv_s for k in range(3)]
    focal = 0.5 * (prob.fx[views] + prob.fy[views])  # [V, 1] pixels per normalised unit

    def reproj_s2(RE, t, Xq, xq, yq, f):
        """Squared pixel errors of per-view poses RE [..., V, 3, 3], t [..., V, 3] at points
        Xq (3 x [..., V, m]), xq, yq [..., V, m] -> [..., V, m]."""
        p = [scale_X * (RE[..., i, 0, None] * Xq[0] + RE[..., i, 1, None] * Xq[1]
                        + RE[..., i, 2, None] * Xq[2]) + t[..., i, None] for i in range(3)]
        iz = 1.0 / jnp.maximum(p[2], prob.min_depth)
        du = (p[0] * iz - xq) * f
        dv = (p[1] * iz - yq) * f
        s2 = du * du + dv * dv
        # Points behind the camera are outliers whatever their projection.
        return jnp.where((p[2] > prob.min_depth) & jnp.isfinite(s2), s2, jnp.inf)

    def msac(s2):
        return jnp.sum(w_v * jnp.minimum(s2, threshold_px**2), -1)  # [V]

    # Start: the best random-subset hypothesis, or nothing (score inf) without hypotheses.
    RE = jnp.broadcast_to(jnp.eye(3, dtype=x.dtype), (V, 3, 3))
    t = jnp.zeros((V, 3), x.dtype).at[:, 2].set(1.0)
    if num_hypotheses > 0:
        # Random points among the valid points of each view: the r-th valid point is found by
        # a binary search of r in the running count of valid points, so padding is never drawn.
        count = jnp.cumsum((w_v > 0).astype(jnp.int32), -1)  # [V, N]
        n_valid = jnp.maximum(count[:, -1:], 1)  # [V, 1]
        key_h, key_s = jax.random.split(key)

        def sample(k, shape):  # -> indices [*shape[:-2], V, m] of valid points
            r = jnp.minimum((jax.random.uniform(k, shape) * n_valid).astype(jnp.int32),
                            n_valid - 1)
            flat = r.reshape(-1, V, shape[-1])
            idx = jax.vmap(lambda rr: jax.vmap(
                lambda c, q: jnp.searchsorted(c, q, side="right"))(count, rr))(flat)
            return jnp.minimum(idx, N - 1).reshape(shape)

        def gather(arr, idx):  # [V, N] -> [..., V, m]
            return jnp.take_along_axis(jnp.broadcast_to(arr, idx.shape[:-1] + (N,)), idx, -1)

        idx_h = sample(key_h, (num_hypotheses, V, 6))
        REh, th = _fit_dlt([gather(c, idx_h) for c in Xp], gather(x, idx_h), gather(y, idx_h),
                           jnp.ones(idx_h.shape, x.dtype), scale_X, unrolled=False)
        idx_s = sample(key_s, (V, min(num_score_points, N)))
        s2 = reproj_s2(REh, th, [gather(c, idx_s) for c in Xp], gather(x, idx_s),
                       gather(y, idx_s), focal)  # [H, V, m]
        score = jnp.sum(gather(w_v, idx_s) * jnp.minimum(s2, threshold_px**2), -1)
        best = jnp.argmin(jnp.where(jnp.isfinite(score), score, jnp.inf), axis=0)  # [V]
        RE = jnp.take_along_axis(REh, best[None, :, None, None], 0)[0]
        t = jnp.take_along_axis(th, best[None, :, None], 0)[0]
    s2 = reproj_s2(RE, t, Xp, x, y, focal)
    score = msac(s2) if num_hypotheses > 0 else jnp.full((V,), jnp.inf, x.dtype)

    # Refits on all points: first unweighted (the plain least-squares DLT), then with Cauchy
    # weights of decreasing scale. Each refit is kept only if it lowers the MSAC score on all
    # points: a refit from a poor pose with few inliers can otherwise jump anywhere, even
    # behind the camera. A scan keeps one copy of the solver in the compiled program.
    def refit(carry, c):
        RE, t, s2, score = carry
        _, wr = _robust(s2, "cauchy", c)
        wr = jnp.where(jnp.isfinite(wr), wr, 0.0)
        RE_new, t_new = _fit_dlt(Xp, x, y, w_v * wr, scale_X, unrolled=False)
        s2_new = reproj_s2(RE_new, t_new, Xp, x, y, focal)
        score_new = msac(s2_new)
        better = score_new < score  # [V]; NaN compares False
        return (jnp.where(better[:, None, None], RE_new, RE), jnp.where(better[:, None], t_new, t),
                jnp.where(better[:, None], s2_new, s2), jnp.where(better, score_new, score)), None

    # 1e15 px: weights of exactly 1, without inf * 0 in the Cauchy formula.
    scales = jnp.asarray((1e15,) + tuple(irls_scales_px), x.dtype)
    (RE, t, _, _), _ = jax.lax.scan(refit, (RE, t, s2, score), scales)
    # Camera-frame pose of the centred object in view v -> world frame.
    R_cam = jnp.einsum("vij,kj->vik", RE, E)  # R_cam_obj = RE E^T
    R_w = _matmul3(jnp.swapaxes(prob.Rcw[views], -1, -2), R_cam)
    t_w = _matvec3(jnp.swapaxes(prob.Rcw[views], -1, -2), t - prob.tcw[views])
    costs = jax.vmap(lambda R_, t_: _cost(prob, R_, t_, cost_kind, cost_scale))(R_w, t_w)
    best = jnp.argmin(jnp.where(jnp.isfinite(costs), costs, jnp.inf))
    return R_w[best], t_w[best]


def solve_pnp(
    points_3d: Array,
    points_2d: Array,
    K: Array,
    T_cam_world: Array,
    weights: Array,
    T_world_obj_init: Array | None = None,
    *,
    huber_px: float = 2.0,
    tukey_px: float | None = 8.0,
    max_iterations: int = 10,
    tukey_iterations: int = 5,
    init_views: int = 1,
    init_hypotheses: int = 32,
    init_score_points: int = 64,
    init_threshold_px: float = 8.0,
    init_irls_px: tuple[float, ...] = (8.0, 4.0),
    seed: int = 0,
    min_depth: float = 1.0,
    rtol: float = 1e-6,
    degenerate_ratio: float = 1e-6,
) -> tuple[Array, dict[str, Array]]:
    """Robust multi-view PnP: object pose in the world from 2D-3D matches in V calibrated views.

    Args:
      points_3d: [V, N, 3] object-frame points (mm) of each correspondence.
      points_2d: [V, N, 2] observed pixels (pixel-centre convention) in view v.
      K: [V, 3, 3] intrinsics (upper triangular, skew allowed).
      T_cam_world: [V, 4, 4] extrinsics; single view is V = 1 with the identity.
      weights: [V, N] >= 0 per-correspondence confidence; 0 marks padding.
      T_world_obj_init: optional [4, 4] initial pose. ``None`` runs the linear initialisation
        of the module docstring (per-view DLT / homography with IRLS, best robust cost).
      huber_px: Huber scale (pixels) of the main LM phase.
      tukey_px: Tukey biweight scale (pixels) of the final phase, or ``None`` to skip it.
        Residuals above it get zero weight, so set it well above the inlier noise.
      max_iterations, tukey_iterations: caps of the two LM phases (``lax.while_loop``; each
        stops early once the predicted decrease is below ``rtol`` times the cost).
      init_irls_px: Cauchy scales (pixels) of the reweighted linear solves of the
        initialisation, one solve per entry (coarse to fine).
      min_depth: depth (mm) at which points are clamped before the perspective division.
      degenerate_ratio: point sets whose second principal variance is below this fraction of
        the first (collinear, or a single point) are reported as degenerate.

    Returns:
      T_world_obj [4, 4] and ``info``, a dict of scalars: ``rms_px`` (weighted RMS reprojection
      error over all points with weight > 0), ``inlier_rms_px`` and ``num_inliers`` (points
      within ``tukey_px``, or 3 ``huber_px`` without Tukey), ``iterations`` (LM steps taken
      over both phases), ``num_valid`` (points with weight > 0), ``degenerate`` and
      ``converged`` (at least 4 valid points and 4 inliers, a non-degenerate point set, finite
      output and the LM stopping criterion of the last phase met). With fewer than 4 valid
      points or a degenerate point set (collinear, a single point, all weights 0) the initial
      pose is returned unchanged (the identity without one), with ``converged=False``; no
      output is ever NaN.

    Pure and jit-able (the keyword arguments are static); vmap over a leading problem axis of
    every array argument to solve a batch.
    """
    points_3d = jnp.asarray(points_3d)
    dtype = jnp.promote_types(points_3d.dtype, jnp.float32)
    X = points_3d.astype(dtype)
    uv = jnp.asarray(points_2d, dtype)
    K = jnp.asarray(K, dtype)
    T_cam_world = jnp.asarray(T_cam_world, dtype)
    w = jnp.asarray(weights, dtype)
    if X.ndim != 3 or X.shape[-1] != 3:
        raise ValueError(f"points_3d must be [V, N, 3], got {X.shape} (single view: add V=1)")
    V, N = X.shape[:2]
    if uv.shape != (V, N, 2):
        raise ValueError(f"points_2d must be [V, N, 2] = {(V, N, 2)}, got {uv.shape}")
    if K.shape != (V, 3, 3):
        raise ValueError(f"K must be [V, 3, 3] = {(V, 3, 3)}, got {K.shape}")
    if T_cam_world.shape != (V, 4, 4):
        raise ValueError(
            f"T_cam_world must be [V, 4, 4] = {(V, 4, 4)}, got {T_cam_world.shape} "
            "(single view: pass the identity with V=1)"
        )
    if w.shape != (V, N):
        raise ValueError(f"weights must be [V, N] = {(V, N)}, got {w.shape}")
    if T_world_obj_init is not None:
        T_world_obj_init = jnp.asarray(T_world_obj_init, dtype)
        if T_world_obj_init.shape != (4, 4):
            raise ValueError(f"T_world_obj_init must be [4, 4], got {T_world_obj_init.shape}")
    if huber_px <= 0 or (tukey_px is not None and tukey_px <= 0):
        raise ValueError(f"robust scales must be positive pixels, got {huber_px=}, {tukey_px=}")

    # Non-finite inputs (e.g. NaN padding) count as padding.
    finite = jnp.all(jnp.isfinite(X), -1) & jnp.all(jnp.isfinite(uv), -1)
    w = jnp.where(finite & (w > 0), w, 0.0)
    X = jnp.where(finite[..., None], X, 0.0)
    uv = jnp.where(finite[..., None], uv, 0.0)
    valid = w > 0
    num_valid = jnp.sum(valid)
    w_sum = jnp.sum(w)
    w_safe = jnp.where(w_sum > 0, w_sum, 1.0)

    # Centre (and measure the spread of) the 3D points: conditioning and degeneracy test.
    Xs = [X[..., k] for k in range(3)]
    c = jnp.stack(_sum_all([w * Xk for Xk in Xs])) / w_safe
    Xc = X - c
    Xs = [Xk - c[k] for k, Xk in enumerate(Xs)]
    pairs = [(k, l) for k in range(3) for l in range(k, 3)]
    mom = dict(zip(pairs, _sum_all([w * Xs[k] * Xs[l] for k, l in pairs])))
    cov = jnp.stack([jnp.stack([mom[min(k, l), max(k, l)] for l in range(3)]) for k in range(3)])
    evals, evecs = jnp.linalg.eigh(cov / w_safe)  # ascending
    degenerate = (evals[1] <= degenerate_ratio * evals[2]) | (evals[2] <= 0)
    scale_X = jnp.sqrt(jnp.maximum(evals[2] + evals[1] + evals[0], 1e-12))
    # Principal axes, largest first, as a proper rotation.
    E = jnp.stack([evecs[:, 2], evecs[:, 1], _cross_cols(evecs[:, 2], evecs[:, 1])], -1)

    prob = _Problem(Xc, uv, K, T_cam_world, w, min_depth)

    if T_world_obj_init is None:
        R0, t0 = _linear_init(
            prob, E, scale_X, num_views=init_views, num_hypotheses=init_hypotheses,
            num_score_points=init_score_points, key=jax.random.key(seed),
            threshold_px=init_threshold_px, irls_scales_px=tuple(init_irls_px),
            cost_kind="huber", cost_scale=huber_px)
        fallback = jnp.eye(4, dtype=dtype)
    else:
        R0 = T_world_obj_init[:3, :3]
        t0 = T_world_obj_init[:3, 3] + R0 @ c  # pose of the centred frame
        fallback = T_world_obj_init
    ok0 = jnp.all(jnp.isfinite(R0)) & jnp.all(jnp.isfinite(t0))
    R0 = jnp.where(ok0, R0, jnp.eye(3, dtype=dtype))
    t0 = jnp.where(ok0, t0, jnp.zeros(3, dtype))

    # A predicted decrease below (1e-4 px)^2 per unit weight is at float32's resolution of
    # pixel coordinates: nothing left to gain.
    atol = 1e-8 * w_sum
    tukey = tukey_px is not None and tukey_iterations > 0
    # When a Tukey phase follows, the Huber phase only has to bring the pose into its basin.
    R, t, iterations, done = _levenberg_marquardt(
        prob, R0, t0, huber_px=huber_px, tukey_px=tukey_px, huber_iterations=max_iterations,
        tukey_iterations=tukey_iterations, rtol_huber=max(rtol, 1e-3) if tukey else rtol,
        rtol=rtol, atol=atol)
    R = _polar_rotation(R, iterations=2)  # remove float32 drift of the products of updates

    T = jnp.eye(4, dtype=dtype).at[:3, :3].set(R).at[:3, 3].set(t - R @ c)
    finite_out = jnp.all(jnp.isfinite(T))
    T = jnp.where(finite_out & (num_valid >= 4) & ~degenerate, T, fallback)

    _, _, _, _, ru, rv = prob.residuals(T[:3, :3], T[:3, :3] @ c + T[:3, 3])
    s2 = ru * ru + rv * rv
    big = jnp.asarray(jnp.finfo(dtype).max / 4, dtype)
    s2 = jnp.minimum(jnp.where(jnp.isfinite(s2), s2, big), big)
    rms = jnp.sqrt(jnp.sum(w * s2) / w_safe)
    gate = tukey_px if tukey_px is not None else 3.0 * huber_px
    inl = valid & (s2 <= gate * gate)
    inl_w = jnp.sum(jnp.where(inl, w, 0.0))
    inlier_rms = jnp.sqrt(jnp.sum(jnp.where(inl, w * s2, 0.0)) / jnp.where(inl_w > 0, inl_w, 1.0))
    num_inliers = jnp.sum(inl)
    converged = (num_valid >= 4) & (num_inliers >= 4) & ~degenerate & finite_out & done
    info = {
        "rms_px": jnp.minimum(rms, big),
        "inlier_rms_px": inlier_rms,
        "num_inliers": num_inliers.astype(jnp.int32),
        "iterations": iterations.astype(jnp.int32),
        "num_valid": num_valid.astype(jnp.int32),
        "degenerate": degenerate,
        "converged": converged,
    }
    return T, info
