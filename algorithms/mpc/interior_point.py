"""A primal-dual interior-point method with Riccati steps for the horizon QP of ``scg_algorithms.mpc.structured``.

The problem is ``structured``'s (its ``Layout`` and ``HorizonQP``; the env's convention: stage ``k`` constrains the
state it reaches and the input it commands), with hard rows only::

    min   sum_{k=0}^{N-1}  1/2 x_{k+1}^T Q_k x_{k+1} + q_k^T x_{k+1} + 1/2 u_k^T R_k u_k + r_k^T u_k
    s.t.  x_0 = x_init,      x_{k+1} = A_k x_k + B_k u_k + c_k
          u_low_k <= u_k <= u_high_k,     x_low_k <= x_{k+1}[x_rows] <= x_high_k,
          row_low_k <= C_k x_{k+1} + D_k u_k <= row_high_k

**Method** (Mehrotra's predictor-corrector with Riccati steps, as HPIPM runs it; Frison and Diehl 2020). Each row's
value ``v`` (an input, a state entry, a general row, divided by its half-width where both bounds are finite) gets a
slack and a multiplier per finite side: ``e v - b + s = 0``, ``s, lam >= 0`` (``e = +1``, ``b = high`` for the
upper side; ``e = -1``, ``b = -low`` for the lower). The iterate keeps the dynamics exactly (it starts from a rollout
and every step is one of the linear model), so the Newton step of the KKT conditions is the LQ problem

    min  1/2 dz^T (H + G^T W G) dz + (grad f + G^T y + G^T t)^T dz   s.t.   dx_{k+1} = A_k dx_k + B_k du_k,  dx_0 = 0
    W = sum_sides lam / s,    y = sum_sides e lam,    t = sum_sides e (lam r - rc) / s

(``r`` the primal residuals, ``rc`` the complementarity targets), which one backward Riccati recursion and one
forward rollout solve in ``O(N (nx + nu)^3)``. A general row couples ``u_k`` and ``x_{k+1}``: its weight enters the
recursion as the cross term ``C^T W D``. The factorisation (the matrix recursion; an unrolled ``nu x nu`` Cholesky
per stage) is computed once per iteration and serves the predictor and the corrector, each solved with
``IPMSettings.refinement_steps`` steps of iterative refinement (default 1); both take one step length,
``STEP_FRACTION`` of the largest that keeps every slack and multiplier positive. The objective is scaled so that the
unconstrained problem's smallest input curvature is 1.

**Active-set polish.** In float32 the barrier's weights on the rows that end active (``lam / s``, past 1e8 as the
complementarity falls) cost the recursion its digits, and on a few problems the iterate stops improving about 1e-3 N
from the solution. So after the iterations, as OSQP polishes its ADMM, from the last iterate and, failing that, from the
first whose complementarity products were all below ``SNAP_TOL``: the rows whose multiplier exceeds their slack
are held at their bounds by an augmented Lagrangian (weight ``POLISH_RHO`` on those rows only: one factorisation,
``POLISH_STEPS`` exact minimisations, each followed by a multiplier update), and the plan is accepted if no free row
is violated, every held row is at its bound and every held multiplier has its sign (within ``POLISH_TOL``). A round
that is not accepted holds the violated rows too and frees the wrong-signed ones for the next; one that held the
right rows, only not within ``POLISH_TOL`` of their bounds (float32 on an ill-conditioned stage: the cart-pole's
state 775 of the benchmark's 1,000 stalled at 4e-5 whatever the number of steps), is repeated at
``POLISH_RHO_GROWTH`` times the weight, up to ``POLISH_RHO_MAX``. At most
``IPMSettings.polish_rounds`` rounds from each start (one ``lax.while_loop``: under ``vmap`` it runs until every copy
has an accepted plan or has run all its rounds).

**Loops and tolerances.** At most ``IPMSettings.max_iterations`` iterations in a ``lax.while_loop``; under ``vmap``
it runs until its slowest copy stops, and a copy that stopped keeps its iterate. A copy stops when every
complementarity product ``s lam`` is below ``IPMSettings.tol`` and its primal residual and reduced gradient (relative
to the gradient's size) are below ``IPMSettings.residual_tol`` (default: the square root of the dtype's resolution),
when a multiplier passes ``LAMBDA_MAX`` (the rows admit no plan, or hardly any), or when a step gives a non-finite
iterate (the copy keeps the last finite one). The iteration count hardly depends on the active set (median 6 on the
2D quadrotor's position box, 99% within 16), which a batch that waits for its slowest copy wants; the linear MPC
caps it at 15.

**Status** (``structured``'s codes): ``CONVERGED`` (the stopping test or an accepted polish); ``MAX_ITERATIONS``;
``INFEASIBLE`` (a multiplier passed ``LAMBDA_MAX``: a heuristic certificate, not OSQP's); ``NUMERICAL`` (a step gave
a non-finite iterate; the last finite one is returned). The plan returned is the iterate's (or the accepted
polish's) inputs clipped to their box with their rollout, and ``violation`` is that plan's: an iterate stopped at the
cap can overshoot the box. Nothing returned is NaN; the caller decides what to apply.

Float32 by default (the dtype of ``x_init``), float64 when x64 is on.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from scg_algorithms.mpc.structured import CONVERGED, INFEASIBLE, MAX_ITERATIONS, NUMERICAL, HorizonQP, Layout
from scg_jax.tracing import batched_like

STEP_FRACTION = 0.995  # of the largest step that keeps every slack and multiplier positive
# Multipliers (scaled) beyond this mean the rows admit no plan: on the 2D quadrotor's position box 212 of the 213
# problems qpOASES calls infeasible pass it within 12 iterations, and of the 787 it solves only the one whose
# feasible set is a sliver (state 794 of the parity set), where the iterates diverge.
LAMBDA_MAX = 1e8
# The polish's second start: the first iterate whose complementarity products are all below this (scaled). Later
# steps can lose the active set in float32 before the stopping test holds (on the 2D quadrotor's position box, 1 of
# 787 states; from here the polish finds qpOASES's plan).
SNAP_TOL = 1e-3
POLISH_STEPS = 3  # augmented-Lagrangian minimisations per polish round
POLISH_RHO = 1e4  # the polish's weight on a held row (scaled units; 1e3-1e5 give the same plans)
# The weight of a round repeated because it held the right rows loosely, and its cap: at 1e6 the cart-pole's state
# 775 holds (1.4e-5 N from qpOASES); 1e6 from the start loses two 2D-quadrotor states that 1e4 keeps.
POLISH_RHO_GROWTH, POLISH_RHO_MAX = 100.0, 1e6
POLISH_TOL = 1e-5  # a polished plan's largest violation and wrong-signed multiplier (scaled units)


@dataclasses.dataclass(frozen=True)
class IPMSettings:
    """Interior-point settings (static).

    Attributes:
        max_iterations: cap on iterations (each: one Riccati factorisation and 2 (1 + refinement_steps) solves).
        tol: the largest complementarity product ``s lam`` (scaled) of a converged iterate.
        residual_tol: the largest primal residual and relative reduced gradient of a converged iterate; ``None``: the
            square root of the dtype's resolution (3.5e-4 in float32, 1.5e-8 in float64).
        polish_rounds: rounds of the active-set polish after the iterations (0: none).
        refinement_steps: steps of iterative refinement of each Newton step (each: one more Riccati solve). 0 suits
            a few iterations that stop before the barrier's weights grow large (SQP-RTI's QPs).
    """

    max_iterations: int = 30
    tol: float = 1e-6
    residual_tol: float | None = None
    polish_rounds: int = 3
    refinement_steps: int = 1

    def __post_init__(self):
        if self.max_iterations < 1:
            raise ValueError(f"IPMSettings.max_iterations: must be >= 1, got {self.max_iterations!r}")
        for name in ("polish_rounds", "refinement_steps"):
            if getattr(self, name) < 0:
                raise ValueError(f"IPMSettings.{name}: must be >= 0, got {getattr(self, name)!r}")
        for name in ("tol", "residual_tol"):
            if getattr(self, name) is not None and not getattr(self, name) > 0:
                raise ValueError(f"IPMSettings.{name}: must be positive, got {getattr(self, name)!r}")


class IPMSolution(NamedTuple):
    """The result of one solve.

    Attributes:
        u: (N, nu) inputs. x: (N + 1, nx) the plan's states, ``x[0] = x_init``.
        multipliers: (N, stage_rows) the last iterate's multipliers of the rows in the problem's units (> 0: the upper
            bound pushes, < 0: the lower one), in ``structured``'s order: inputs, state boxes, general rows.
        status: int32 (``structured``'s codes). iterations: int32 (the polish not counted). polished: bool, whether
            the plan is an accepted polish.
        mu: the last iterate's mean complementarity (scaled). primal_residual: its largest scaled primal residual.
        dual_residual: its reduced gradient's largest entry, relative to the gradient's size.
        violation: the largest violation of a row by the plan (row units).
    """

    u: Any
    x: Any
    multipliers: Any
    status: Any
    iterations: Any
    polished: Any
    mu: Any
    primal_residual: Any
    dual_residual: Any
    violation: Any


def check_layout(layout: Layout) -> None:
    """Raise unless every row of ``layout`` is hard (the interior point does not price violations)."""
    if any(layout.soft):
        raise ValueError(
            "interior_point: soft rows are not supported (Layout.soft_x, Layout.soft_rows); allowed: hard rows "
            "only (use the ADMM of scg_algorithms.mpc.structured for soft ones)"
        )


# --------------------------------------------------------------------------------------------- small products
# Products of the recursion as broadcast multiplies and sums, not dots: under vmap a dot of (batch, 6, 6) matrices runs
# per matrix, while these fuse into one loop over the batch (a stage's products 7x faster at 4,096 copies on CPU).
def _mm(a, b):
    """``a @ b`` over the last two axes."""
    return jnp.sum(a[..., :, :, None] * b[..., None, :, :], axis=-2)


def _mv(a, v):
    """``a @ v`` for matrices (..., i, j) and vectors (..., j)."""
    return jnp.sum(a * v[..., None, :], axis=-1)


def _T(a):
    return jnp.swapaxes(a, -1, -2)


# --------------------------------------------------------------------------------------------- rows
class _Rows(NamedTuple):
    """The rows of one copy in scaled units (``value = (row) / scale``)."""

    rows: tuple  # the state entries with a box (static)
    C: Any  # (N, m, nx) / scale
    D: Any  # (N, m, nu) / scale
    su: Any  # (N, nu) input scales
    sx: Any  # (N, nxr) state-box scales
    sr: Any  # (N, m) general rows' scales
    lo: Any  # (N, ms) scaled bounds (-inf/inf where absent)
    hi: Any
    has_lo: Any  # (N, ms) bool
    has_hi: Any


def _scale_of(lo, hi):
    finite = jnp.isfinite(lo) & jnp.isfinite(hi)
    half = jnp.where(finite, 0.5 * (hi - lo), 1.0)
    return jnp.where(finite & (half > 0), half, 1.0)


def _make_rows(layout: Layout, qp: HorizonQP) -> _Rows:
    su = _scale_of(qp.u_low, qp.u_high)
    sx = _scale_of(qp.x_low, qp.x_high)
    sr = _scale_of(qp.row_low, qp.row_high)
    C, D = qp.C / sr[..., None], qp.D / sr[..., None]
    lo = jnp.concatenate([qp.u_low / su, qp.x_low / sx, qp.row_low / sr], axis=-1)
    hi = jnp.concatenate([qp.u_high / su, qp.x_high / sx, qp.row_high / sr], axis=-1)
    return _Rows(tuple(layout.x_rows), C, D, su, sx, sr, lo, hi, jnp.isfinite(lo), jnp.isfinite(hi))


def _values(rows: _Rows, x, u):
    """(N, ms) scaled row values of the plan (``x``: (N, nx), the states ``x_1 .. x_N``; ``u``: (N, nu))."""
    parts = [u / rows.su]
    if rows.rows:
        parts.append(jnp.stack([x[:, i] for i in rows.rows], axis=-1) / rows.sx)
    if rows.C.shape[1]:
        parts.append(_mv(rows.C, x) + _mv(rows.D, u))
    return jnp.concatenate(parts, axis=-1)


def _transpose(rows: _Rows, y, nx: int):
    """``G^T y`` for row vectors ``y`` (N, ms): ``(on x: (N, nx), on u: (N, nu))``."""
    nu, nxr = rows.su.shape[1], rows.sx.shape[1]
    yu, yx, yr = y[:, :nu], y[:, nu : nu + nxr], y[:, nu + nxr :]
    on_u = yu / rows.su
    yx = yx / rows.sx
    zero = jnp.zeros_like(y[:, 0])
    on_x = jnp.stack([yx[:, rows.rows.index(i)] if i in rows.rows else zero for i in range(nx)], axis=-1)
    if rows.C.shape[1]:
        on_u = on_u + _mv(_T(rows.D), yr)
        on_x = on_x + _mv(_T(rows.C), yr)
    return on_x, on_u


# --------------------------------------------------------------------------------------------- Riccati
def _spd_inverse(M):
    """The inverse of a small symmetric positive definite matrix (nu, nu), by a Cholesky unrolled in Python.

    Elementwise operations only: under ``vmap`` they run over the batch as vectors, where a batched LAPACK call of
    (nu, nu) matrices pays its overhead per matrix (the recursion runs 3 solves per stage and iteration).
    """
    n = M.shape[-1]
    L = [[None] * n for _ in range(n)]
    for j in range(n):
        d = M[..., j, j] - sum(L[j][k] ** 2 for k in range(j))
        # Rounding can leave a pivot of a nearly singular stage at or below zero; the dtype's resolution of the
        # diagonal is the smallest pivot it can tell from zero.
        L[j][j] = jnp.sqrt(jnp.maximum(d, jnp.finfo(M.dtype).eps * M[..., j, j]))
        for i in range(j + 1, n):
            L[i][j] = (M[..., i, j] - sum(L[i][k] * L[j][k] for k in range(j))) / L[j][j]
    # inv(L) by forward substitution, column by column
    inv_L = [[None] * n for _ in range(n)]
    for j in range(n):
        inv_L[j][j] = 1.0 / L[j][j]
        for i in range(j + 1, n):
            inv_L[i][j] = -sum(L[i][k] * inv_L[k][j] for k in range(j, i)) / L[i][i]
    rows = [
        jnp.stack([sum(inv_L[k][i] * inv_L[k][j] for k in range(max(i, j), n)) for j in range(n)], axis=-1)
        for i in range(n)
    ]
    return jnp.stack(rows, axis=-2)


class _Factor(NamedTuple):
    Hinv: Any  # (N, nu, nu) inverse of the input Hessian of each stage
    K: Any  # (N, nu, nx) feedback
    Hux: Any  # (N, nu, nx)


def _factorize(qp: HorizonQP, rows: _Rows, w, scale):
    """The matrix recursion of the LQ step with row weights ``w`` (N, ms) (objective divided by ``scale``)."""
    N, nx = qp.A.shape[0], qp.A.shape[1]
    nu, nxr = rows.su.shape[1], rows.sx.shape[1]
    wu, wx, wr = w[:, :nu], w[:, nu : nu + nxr], w[:, nu + nxr :]
    # Diagonal additions as products with constant 0/1 matrices: a scatter would run element by element.
    R = qp.R / scale + (wu / rows.su**2)[..., None] * jnp.eye(nu, dtype=w.dtype)
    select = jnp.asarray(np.eye(nx)[list(rows.rows)], w.dtype)  # (nxr, nx)
    Q = qp.Q / scale + _mm(_T(select), (wx / rows.sx**2)[..., None] * select) if nxr else qp.Q / scale
    if rows.C.shape[1]:
        R = R + _mm(_T(rows.D), wr[..., None] * rows.D)
        Q = Q + _mm(_T(rows.C), wr[..., None] * rows.C)
        M = _mm(_T(rows.C), wr[..., None] * rows.D)
    else:
        M = jnp.zeros((N, nx, nu), Q.dtype)
    cross = rows.C.shape[1] > 0
    joseph = bool(rows.rows) or cross  # rows weigh on states: the cost-to-go in Joseph's form (below)

    def stage(P_next, inputs):
        A, B, Qk, Rk, Mk = inputs
        P = Qk + P_next
        PB = _mm(P, B) + Mk if cross else _mm(P, B)
        Huu = Rk + _mm(_T(B), PB) + _mm(_T(Mk), B) if cross else Rk + _mm(_T(B), PB)
        Hux = _mm(_T(PB), A)
        Hinv = _spd_inverse(0.5 * (Huu + _T(Huu)))
        K = -_mm(Hinv, Hux)
        if joseph:
            # The cost-to-go as a sum of quadratic forms of the closed loop (Joseph's form), not A^T P A - Hux^T
            # Huu^-1 Hux: with the barrier's weights on state rows at 1e8 the difference loses its definiteness in
            # float32 and the next stage's Cholesky breaks; the sum stays positive semidefinite.
            closed = A + _mm(B, K)
            P_prev = _mm(_T(closed), _mm(P, closed)) + _mm(_T(K), _mm(Rk, K))
            if cross:
                MK = _mm(Mk, K)
                P_prev = P_prev + _mm(_T(closed), MK) + _mm(_T(MK), closed)
        else:
            # Weights on inputs only: the difference form, about 0.6x the products of Joseph's.
            P_prev = _mm(_T(A), _mm(P, A)) + _mm(_T(Hux), K)
        return 0.5 * (P_prev + _T(P_prev)), _Factor(Hinv, K, Hux)

    _, factor = lax.scan(stage, batched_like(jnp.zeros((nx, nx), Q.dtype), w), (qp.A, qp.B, Q, R, M), reverse=True)
    return factor, (Q, R, M)


def _hessian_product(weights, dx, du):
    """The step's quadratic model times ``(dx, du)``: ``(on x_{k+1}, on u_k)``."""
    Q, R, M = weights
    return _mv(Q, dx) + _mv(M, du), _mv(R, du) + _mv(_T(M), dx)


def _step(qp: HorizonQP, factor: _Factor, gx, gu):
    """The LQ step ``(dx (N, nx), du (N, nu))`` for linear terms ``gx`` on ``x_{k+1}`` and ``gu`` on ``u_k``."""

    def backward(p_next, inputs):
        A, B, Hinv, Hux, g_x, g_u = inputs
        p = g_x + p_next
        h = g_u + _mv(_T(B), p)
        kff = -_mv(Hinv, h)
        return _mv(_T(A), p) + _mv(_T(Hux), kff), kff

    zero = batched_like(jnp.zeros_like(gx[0]), gx)  # zeros_like is the same for every copy under vmap
    _, kff = lax.scan(backward, zero, (qp.A, qp.B, factor.Hinv, factor.Hux, gx, gu), reverse=True)

    def forward(dx, inputs):
        A, B, K, k = inputs
        du = _mv(K, dx) + k
        dx_next = _mv(A, dx) + _mv(B, du)
        return dx_next, (dx_next, du)

    _, (dx, du) = lax.scan(forward, zero, (qp.A, qp.B, factor.K, kff))
    return dx, du


def _reduced_gradient(qp: HorizonQP, gx, gu):
    """The objective's gradient in the inputs along the dynamics (N, nu): the dual residual of the plan, whose
    states follow the model exactly; ``gx`` (N, nx) on ``x_{k+1}``, ``gu`` (N, nu) on ``u_k``."""
    A_next = jnp.concatenate([qp.A[1:], jnp.zeros_like(qp.A[:1])], axis=0)

    def stage(p_next, inputs):
        A, B, g_x, g_u = inputs
        p = g_x + _mv(_T(A), p_next)
        return p, g_u + _mv(_T(B), p)

    return lax.scan(stage, jnp.zeros_like(gx[0]), (A_next, qp.B, gx, gu), reverse=True)[1]


def _rollout(qp: HorizonQP, x_init, u):
    def stage(x, inputs):
        A, B, c, uk = inputs
        x_next = _mv(A, x) + _mv(B, uk) + c
        return x_next, x_next

    return lax.scan(stage, x_init, (qp.A, qp.B, qp.c, u))[1]


# --------------------------------------------------------------------------------------------- the method
SIDES = (1.0, -1.0)  # axis 1 of the slacks and multipliers: the upper side (e v <= hi), the lower (-v <= -lo)


class _Iterate(NamedTuple):
    x: Any  # (N, nx) x_1 .. x_N
    u: Any  # (N, nu)
    s: Any  # (N, 2, ms) slacks of the upper and lower sides (1 where the side has no bound)
    lam: Any  # (N, 2, ms) their multipliers (0 where the side has no bound)


class _Measures(NamedTuple):
    r: Any  # (N, 2, ms) primal residuals e v - b + s (0 where no bound)
    mu: Any  # mean complementarity
    gx: Any  # (N, nx) the Lagrangian's gradient on x_{k+1} (objective and rows)
    gu: Any  # (N, nu) on u_k
    r_primal: Any
    r_dual: Any  # the largest entry of the reduced gradient relative to the gradient's size


def _largest_step(x, dx):
    """The largest step in (0, 1] that keeps ``x + a dx >= 0`` for every entry (x > 0)."""
    ratio = jnp.where(dx < 0, -x / jnp.where(dx < 0, dx, -1.0), jnp.inf)
    return jnp.minimum(1.0, jnp.min(ratio))


def solve(layout: Layout, qp: HorizonQP, x_init, settings: IPMSettings = IPMSettings()) -> IPMSolution:
    """Solve one horizon QP (jit/vmap-able; matrices shared by every copy stay unbatched under ``vmap``).

    Args:
        layout: the static ``Layout`` (hard rows only; ``qp.K`` is not used). qp: this copy's ``HorizonQP``.
        x_init: (nx,) the initial state. settings: ``IPMSettings``.

    Returns:
        ``IPMSolution``.
    """
    check_layout(layout)
    x_init = jnp.asarray(x_init)
    dtype = x_init.dtype
    qp = HorizonQP(*(jnp.asarray(a, dtype) for a in qp))
    nx, nu = layout.nx, layout.nu
    rows = _make_rows(layout, qp)
    e = jnp.asarray(SIDES, dtype)[:, None]  # (2, 1)
    bound = jnp.stack([rows.hi, -rows.lo], axis=1)  # (N, 2, ms)
    has = jnp.isfinite(bound)
    mask = has.astype(dtype)
    bound = jnp.where(has, bound, 0.0)
    count = jnp.maximum(jnp.sum(mask), 1.0)
    residual_tol = float(np.sqrt(jnp.finfo(dtype).eps)) if settings.residual_tol is None else settings.residual_tol
    # The objective's scale: the smallest input curvature of the unconstrained problem is 1 (the multipliers then
    # are of the order of a row's half-width per unit curvature).
    free, _ = _factorize(qp, rows, jnp.zeros_like(rows.lo), jnp.asarray(1.0, dtype))
    scale = 1.0 / jnp.maximum(jnp.max(jax.vmap(jnp.diag)(free.Hinv)), jnp.finfo(dtype).tiny)

    def measure(it: _Iterate) -> _Measures:
        v = _values(rows, it.x, it.u)
        r = mask * (e * v[:, None, :] - bound + it.s)
        mu = jnp.sum(it.s * it.lam) / count
        tx, tu = _transpose(rows, jnp.sum(e * it.lam, axis=1), nx)
        gx = (_mv(qp.Q, it.x) + qp.q) / scale + tx
        gu = (_mv(qp.R, it.u) + qp.r) / scale + tu
        size = jnp.maximum(jnp.maximum(jnp.max(jnp.abs(gx)), jnp.max(jnp.abs(gu))), 1.0)
        r_dual = jnp.max(jnp.abs(_reduced_gradient(qp, gx, gu))) / size
        return _Measures(r, mu, gx, gu, jnp.max(jnp.abs(r)), r_dual)

    # Start: the unconstrained optimum (one LQ step from the rollout of zero inputs), slacks at least 1 (a
    # half-width), multipliers 1.
    u0 = jnp.zeros((layout.horizon, nu), dtype)
    x0 = _rollout(qp, x_init, u0)
    dx, du = _step(qp, free, _mv(qp.Q, x0) + qp.q, _mv(qp.R, u0) + qp.r)  # free: the unscaled objective's factor
    x0, u0 = x0 + dx, u0 + du
    v0 = _values(rows, x0, u0)
    start = _Iterate(x0, u0, jnp.where(has, jnp.maximum(bound - e * v0[:, None, :], 1.0), 1.0), mask)

    def iteration(carry):
        it, m, k, broke, converged, infeasible, snap, snapped = carry
        w = jnp.sum(it.lam / it.s, axis=1)
        factor, weights = _factorize(qp, rows, w, scale)

        def direction(rc):
            t = jnp.sum(e * (it.lam * m.r - rc) / it.s, axis=1)
            tx, tu = _transpose(rows, t, nx)
            gx, gu = m.gx + tx, m.gu + tu
            dx, du = _step(qp, factor, gx, gu)
            # Iterative refinement: in float32, with the barrier's weights past 1e6, the recursion solves the step
            # to a few digits; a solve of the model's residual recovers most of the rest.
            for _ in range(settings.refinement_steps):
                hx, hu = _hessian_product(weights, dx, du)
                ex, eu = _step(qp, factor, hx + gx, hu + gu)
                dx, du = dx + ex, du + eu
            ds = -m.r - mask * e * _values(rows, dx, du)[:, None, :]
            dlam = -(rc + it.lam * ds) / it.s
            return dx, du, ds, dlam

        def longest(ds, dlam):
            return jnp.minimum(_largest_step(it.s, ds), _largest_step(it.lam, dlam))

        _, _, ds, dlam = direction(it.s * it.lam)
        a = longest(ds, dlam)
        mu_aff = jnp.sum((it.s + a * ds) * (it.lam + a * dlam)) / count
        sigma = jnp.clip(mu_aff / jnp.maximum(m.mu, jnp.finfo(dtype).tiny), 0.0, 1.0) ** 3
        dx, du, ds, dlam = direction(it.s * it.lam + ds * dlam - mask * sigma * m.mu)
        alpha = STEP_FRACTION * longest(ds, dlam)
        new = _Iterate(it.x + alpha * dx, it.u + alpha * du, it.s + alpha * ds, it.lam + alpha * dlam)
        m_new = measure(new)
        finite = jnp.isfinite(m_new.mu) & jnp.isfinite(m_new.r_primal) & jnp.isfinite(m_new.r_dual)
        finite = finite & jnp.all(jnp.isfinite(new.u))
        blown = jnp.max(new.lam) > LAMBDA_MAX
        small = (m_new.r_primal <= residual_tol) & (m_new.r_dual <= residual_tol)
        stop = (jnp.max(new.s * new.lam) <= settings.tol) & small
        # A copy that stopped keeps its iterate, and so does one whose step broke (non-finite: in float32 that can
        # happen once the barrier's weights pass about 1e10, beyond the accuracy the dtype gives); the loop runs
        # until every copy of the batch has stopped.
        done = converged | broke | infeasible
        keep = done | ~finite
        it, m = jax.tree.map(lambda old, nw: jnp.where(keep, old, nw), (it, m), (new, m_new))
        # The first iterate near enough for its active set to be the solution's: a second start for the polish, in
        # case later steps lose digits (float32) before the stopping test holds.
        snap_now = ~done & finite & ~snapped & (jnp.max(new.s * new.lam) <= SNAP_TOL)
        snap = jax.tree.map(lambda old, nw: jnp.where(snap_now, nw, old), snap, new)
        return (
            it,
            m,
            k + jnp.where(done, 0, 1),
            broke | (~done & ~finite),
            converged | (~done & finite & stop),
            infeasible | (~done & finite & blown & ~stop),
            snap,
            snapped | snap_now,
        )

    def running(carry):
        return (carry[2] < settings.max_iterations) & ~(carry[3] | carry[4] | carry[5])

    no = jnp.asarray(False)
    it, m, iterations, broke, converged, infeasible, snap, snapped = lax.while_loop(
        running, iteration, batched_like((start, measure(start), jnp.int32(0), no, no, no, start, no), x_init)
    )
    status = jnp.where(infeasible, INFEASIBLE, MAX_ITERATIONS)
    status = jnp.where(converged, CONVERGED, jnp.where(broke, NUMERICAL, status)).astype(jnp.int32)
    if settings.polish_rounds:
        # Active-set polish from the last iterate, then from the first near one: the rows whose multiplier exceeds
        # their slack held at their bounds by an augmented Lagrangian (weight POLISH_RHO): a few exact minimisations
        # and multiplier updates on one factorisation. A round that leaves a free row violated or a held multiplier
        # of the wrong sign is not accepted; the next round holds the violated rows too and frees the wrong-signed
        # ones.
        # One lax loop over the rounds of both starts (rounds of the last iterate, then of the snapped one), not
        # unrolled: the polish traces to about an eighth of the equations (an SQP-RTI cart-pole step's program: 4,291
        # instead of 7,895), and the loop stops once every copy of the batch has a plan.
        rounds = settings.polish_rounds

        def polish_round(carry):
            j, active, rho, px, pu, ok = carry
            first = j < rounds
            origin = jax.tree.map(lambda last, near: jnp.where(first, last, near), it, snap)
            start_active = has & (origin.lam > origin.s)
            fresh = j % rounds == 0
            active = jnp.where(fresh, start_active, active)
            rho = jnp.where(fresh, POLISH_RHO, rho)
            y_start = jnp.sum(e * jnp.where(start_active, origin.lam, 0.0), axis=1)
            act = active.astype(dtype)
            on = jnp.sum(act, axis=1)  # (N, ms)
            target = jnp.sum(act * e * bound, axis=1)
            factor, _ = _factorize(qp, rows, rho * on, scale)

            def minimise(_, qxy):
                qx, qu, y = qxy
                v = _values(rows, qx, qu)
                pull = on * (y + rho * (v - target))
                tx, tu = _transpose(rows, pull, nx)
                gx = (_mv(qp.Q, qx) + qp.q) / scale + tx
                dx, du = _step(qp, factor, gx, (_mv(qp.R, qu) + qp.r) / scale + tu)
                qx, qu = qx + dx, qu + du
                v = _values(rows, qx, qu)
                return qx, qu, y + rho * on * (v - target)

            qx, qu, y = lax.fori_loop(
                0, POLISH_STEPS, minimise, batched_like((origin.x, origin.u, on * y_start), x_init)
            )
            v = _values(rows, qx, qu)
            slack_p = bound - e * v[:, None, :]  # >= 0 where feasible
            violated = has & ~active & (slack_p < -POLISH_TOL)
            wrong = active & (e * y[:, None, :] < -POLISH_TOL)
            held = jnp.max(jnp.abs(on * (v - target))) <= POLISH_TOL
            accept = ~ok & ~jnp.any(violated) & ~jnp.any(wrong) & held & jnp.all(jnp.isfinite(qu))
            px, pu = jnp.where(accept, qx, px), jnp.where(accept, qu, pu)
            # A round that held the right rows, only not closely enough, is repeated holding them harder.
            loose = ~jnp.any(violated) & ~jnp.any(wrong) & ~held
            rho = jnp.where(loose, jnp.minimum(rho * POLISH_RHO_GROWTH, POLISH_RHO_MAX), rho)
            return j + 1, (active & ~wrong) | violated, rho, px, pu, ok | accept

        _, _, _, px, pu, ok = lax.while_loop(
            lambda carry: (carry[0] < 2 * rounds) & ~carry[5],
            polish_round,
            batched_like(
                (jnp.int32(0), jnp.zeros_like(has), jnp.asarray(POLISH_RHO, dtype), it.x, it.u, jnp.asarray(False)),
                x_init,
            ),
        )
        it = it._replace(x=px, u=pu)
        status = jnp.where(ok, CONVERGED, status)
        polished = ok
    else:
        polished = jnp.asarray(False)
    # An iterate stopped at the cap may overshoot the input box (its slacks and residuals are not yet zero); the
    # inputs a caller applies are clipped, so the plan returned and judged is the clipped one. Judged unclipped, SQP-RTI
    # (4 iterations, no polish) on the paper cart-pole's 150% prior refused such plans, aged the one it kept and lost
    # the pole in 17 of 32 seeded episodes; clipped, none (tests/test_sqp_mpc.py counts the refusals).
    u = jnp.clip(it.u, qp.u_low, qp.u_high)
    x = _rollout(qp, x_init, u)
    violation = _violation(rows, x, u)
    scales = jnp.concatenate([rows.su, rows.sx, rows.sr], axis=-1)
    multipliers = jnp.sum(e * it.lam, axis=1) * scale / scales
    x = jnp.concatenate([x_init[None], x], axis=0)
    return IPMSolution(u, x, multipliers, status, iterations, polished, m.mu, m.r_primal, m.r_dual, violation)


def _violation(rows: _Rows, x, u):
    """The largest violation of a row by the plan, in row units."""
    v = _values(rows, x, u)
    scales = jnp.concatenate([rows.su, rows.sx, rows.sr], axis=-1)
    over = jnp.maximum(jnp.where(rows.has_hi, v - rows.hi, 0.0), jnp.where(rows.has_lo, rows.lo - v, 0.0))
    return jnp.max(jnp.maximum(over, 0.0) * scales)


def inputs_violation(layout: Layout, qp: HorizonQP, x_init, u):
    """The largest violation of a row of ``qp`` (row units, as ``IPMSolution.violation``) by the inputs ``u (N, nu)``
    applied from ``x_init`` through the QP's model: what keeping a plan's inputs would give (SQP's fallback)."""
    return _violation(_make_rows(layout, qp), _rollout(qp, x_init, u), u)


__all__ = ["IPMSettings", "IPMSolution", "check_layout", "inputs_violation", "solve"]
