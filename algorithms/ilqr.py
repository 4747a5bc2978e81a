"""Iterative LQR (iLQR / DDP without second-order dynamics terms) in JAX, and the receding-horizon controller.

Solver (``ilqr_solve``, one copy; ``jax.jit``- and ``jax.vmap``-able, every loop a ``lax`` loop):

    minimise  sum_{k=0}^{H-1} [ 1/2 (x_k - r_k)^T Q (x_k - r_k) + 1/2 (u_k - v_k)^T R (u_k - v_k) ]
              + 1/2 (x_H - r_H)^T Q_T (x_H - r_H)
    subject to x_{k+1} = f(x_k, u_k),  x_0 given,  u_low <= u_k <= u_high,

with ``r = x_ref``, ``v = u_ref`` and ``f`` a discrete step function (the prior model). One iteration is:

1. **Backward pass** along the nominal ``(x_bar, u_bar)`` with ``A_k, B_k = jacfwd(f)`` (Gauss-Newton: the
   dynamics' second derivatives are dropped). The feedback law is

       u_k = u_bar_k + alpha d_k - K_k (x_k - x_bar_k)

   (the sign of ``scg_algorithms.lqr``: a positive gain pushes against a positive deviation). ``d_k, K_k`` minimise the
   local quadratic model with ``Quu + mu I`` (Levenberg-Marquardt regularisation ``mu``). With
   ``input_constraints="box"`` (default) they solve the box-constrained QP of box-DDP (Tassa, Mansard, Todorov,
   ICRA 2014): ``d_k`` by a projected Newton method within ``u_low - u_bar_k <= d_k <= u_high - u_bar_k`` and
   the rows of ``K_k`` of inputs clamped at a bound set to zero, so the model the line search trusts knows the
   limits. With ``"clip"`` the backward pass ignores the limits and only the forward pass clips.
   A backward pass fails when a regularised ``Quu`` is not positive definite (its Cholesky factor is not
   finite).
2. **Forward pass / line search**: the closed-loop rollouts for all step sizes ``alpha in {1, c, c^2, ...}``
   (``c = line_search_factor``) are computed in parallel (``vmap``), the inputs clipped to the limits; the first
   ``alpha`` whose actual cost decrease is at least ``line_search_min_ratio`` times the predicted decrease
   ``-(alpha d.Qu + alpha^2/2 d.(Quu + mu I).d)`` (and strictly positive) is accepted.
3. **Regularisation schedule**: on success ``mu <- mu / factor`` (and to 0 below ``regularization_min``), on a
   failed backward pass or a rejected line search ``mu <- max(mu * factor, regularization_min)``; the solver
   stops when ``mu > regularization_max``.

It stops after ``max_iterations`` iterations, when an accepted step lowered the cost by at most ``tolerance``
times the cost, when the predicted decrease of a full step with ``mu <= regularization_min`` is at most
``tolerance`` times the cost (a heavily regularised step is short wherever the plan is, so its prediction says
nothing about optimality), or when such a step is rejected although it promised less than ``sqrt(eps)`` of the
cost (``eps`` of the dtype; 3e-4 in float32): that is the rollout's rounding noise, so the plan is optimal to the
precision the cost can be evaluated in, and ``mu`` is left as it is rather than raised. A linear
system with quadratic cost is solved exactly by the first iteration (the backward pass is then the finite-horizon
Riccati recursion), which the tests check.

Controller (``make_ilqr``, registered as ``"ilqr"``): receding horizon. At control step ``k`` it solves from the
observed state over ``horizon`` steps along ``x_ref[k : k + horizon + 1]`` (indices clamped to the episode's
end), with the prior model's equilibrium input as ``u_ref``; the first input of the plan is applied. The plan
(inputs, states, gains) and ``mu`` are the controller's memory. Each solve starts from the previous plan shifted
by one step, used as a feedback policy (``warm_start="lqr"``) or open loop (``"open_loop"``); the stage appended
at its end, and the whole plan at reset, is the equilibrium input with the LQR gain about the reference
(``"lqr"``) or without feedback (``"open_loop"``).
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.scipy.linalg import cho_solve

from scg_algorithms import controller_setup as setup
from scg_algorithms.base import JaxController, option, parse_options, positive, state_from_obs
from scg_jax.tracing import batched_like

INPUT_CONSTRAINTS = ("box", "clip")


# --------------------------------------------------------------------------------------------- solver
@dataclasses.dataclass(frozen=True)
class ILQRSettings:
    """Static settings of ``ilqr_solve`` (hashable; they fix the compiled program, never traced).

    Attributes:
        max_iterations: iterations (backward pass + line search) at most; >= 1.
        tolerance: relative cost decrease (of an accepted step, or predicted for a full step) that counts as
            converged.
        regularization_init: ``mu`` at the start when ``ilqr_solve`` is not given one (0: the exact Newton step).
        regularization_min: smallest non-zero ``mu``; lowering below it sets ``mu = 0``.
        regularization_max: the solver gives up when ``mu`` would exceed it.
        regularization_factor: ``mu`` is multiplied (failure) or divided (success) by it; > 1.
        line_search_steps: number of step sizes tried (in parallel); >= 1.
        line_search_factor: ratio of successive step sizes ``alpha_i = factor^i``; in (0, 1).
        line_search_min_ratio: smallest accepted ratio of actual to predicted cost decrease; >= 0.
        input_constraints: ``"box"`` (box-DDP backward pass) or ``"clip"`` (clipping in the forward pass only).
        box_qp_iterations: projected-Newton iterations of the box QP per stage (``"box"`` only); >= 1.
    """

    max_iterations: int = 50
    tolerance: float = 1e-6
    regularization_init: float = 0.0
    regularization_min: float = 1e-6
    regularization_max: float = 1e10
    regularization_factor: float = 10.0
    line_search_steps: int = 8
    line_search_factor: float = 0.5
    line_search_min_ratio: float = 1e-4
    input_constraints: str = "box"
    box_qp_iterations: int = 4

    def __post_init__(self):
        _check_solver_settings(self, "ILQRSettings")


def _check_solver_settings(settings, path: str) -> None:
    """Raise ``ValueError`` naming ``<path>.<field>`` for an ``ILQRSettings`` field out of its range."""
    for name in ("max_iterations", "box_qp_iterations", "line_search_steps"):
        value = getattr(settings, name)
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"{path}.{name}: must be a positive integer, got {value!r}")
    for name in ("tolerance", "regularization_min", "regularization_max"):
        positive(f"{path}.{name}", getattr(settings, name))
    if not settings.regularization_init >= 0:
        raise ValueError(f"{path}.regularization_init: must be >= 0, got {settings.regularization_init!r}")
    if not settings.regularization_max > settings.regularization_min:
        raise ValueError(
            f"{path}.regularization_max: must exceed regularization_min ({settings.regularization_min}), "
            f"got {settings.regularization_max!r}"
        )
    if not settings.regularization_factor > 1:
        raise ValueError(f"{path}.regularization_factor: must be > 1, got {settings.regularization_factor!r}")
    if not 0 < settings.line_search_factor < 1:
        raise ValueError(f"{path}.line_search_factor: must be in (0, 1), got {settings.line_search_factor!r}")
    if not settings.line_search_min_ratio >= 0:
        raise ValueError(f"{path}.line_search_min_ratio: must be >= 0, got {settings.line_search_min_ratio!r}")
    if settings.input_constraints not in INPUT_CONSTRAINTS:
        raise ValueError(
            f"{path}.input_constraints: unknown value {settings.input_constraints!r}; allowed values are "
            f"{', '.join(INPUT_CONSTRAINTS)}"
        )


class ILQRSolution(NamedTuple):
    """What ``ilqr_solve`` returns (one copy; under ``vmap`` every leaf gets the batch axis first).

    Attributes:
        x: (H + 1, nx) nominal states, ``x[0] = x0``.
        u: (H, nu) nominal inputs, N, within the input limits.
        K: (H, nu, nx) feedback gains of the backward pass about ``(x, u)``: ``u_k = u[k] + alpha d[k] - K[k] (x_k -
            x[k])``; zero rows for inputs clamped at a limit (``"box"``).
        d: (H, nu) feed-forward corrections of that backward pass (near zero at convergence).
        cost: total cost of ``(x, u)`` (scalar).
        iterations: iterations run (int32), failed ones included.
        converged: a stopping test other than ``max_iterations`` or ``regularization_max`` was met (bool).
        regularization: the final ``mu``.
        cost_history: (max_iterations + 1,) cost of the nominal after each iteration (entry 0: the initial guess),
            the final cost repeated after the solver stopped.
    """

    x: Any
    u: Any
    K: Any
    d: Any
    cost: Any
    iterations: Any
    converged: Any
    regularization: Any
    cost_history: Any


class _Backward(NamedTuple):
    d: Any  # (H, nu)
    K: Any  # (H, nu, nx)
    dV1: Any  # sum_k d_k . Qu_k
    dV2: Any  # sum_k 1/2 d_k . (Quu_k + mu I) . d_k
    ok: Any  # every regularised Quu positive definite


def _symmetric(M):
    return 0.5 * (M + M.T)


def _masked_cholesky(H, free):
    """Cholesky factor of ``H`` restricted to the ``free`` entries, identity on the others."""
    both = free[:, None] & free[None, :]
    eye = jnp.eye(H.shape[0], dtype=H.dtype)
    return jnp.linalg.cholesky(jnp.where(both, H, eye))


def _box_qp(H, L, g, lower, upper, iterations: int, num_steps: int = 8):
    """Projected Newton (Bertsekas 1982; Tassa et al. 2014) for ``min 1/2 d^T H d + g^T d``, ``lower <= d <= upper``.

    Args:
        H: (n, n) positive definite. L: its Cholesky factor. g: (n,). lower, upper: (n,) with ``lower <= 0 <=
            upper`` (may be infinite). iterations: Newton iterations (unrolled; n is small).

    Returns:
        ``(d, free, L_free)``: the solution (n,), the inputs not clamped at a bound (bool, n) and the Cholesky factor
        of ``H`` restricted to them (identity elsewhere).
    """
    dtype = H.dtype
    if g.shape[0] == 1:
        # One input: clipping the unconstrained minimiser is the exact solution.
        d = jnp.clip(-g / H[0], lower, upper)
        grad = g + H[0] * d
        free = ~(((d <= lower) & (grad > 0)) | ((d >= upper) & (grad < 0)))
        return d, free, L
    steps = 0.5 ** jnp.arange(num_steps, dtype=dtype)
    objective = lambda v: g @ v + 0.5 * v @ H @ v  # noqa: E731
    d = jnp.clip(-cho_solve((L, True), g), lower, upper)
    free = jnp.ones(g.shape, bool)
    L_free = L
    for _ in range(iterations):
        grad = g + H @ d
        clamped = ((d <= lower) & (grad > 0)) | ((d >= upper) & (grad < 0))
        free = ~clamped
        L_free = _masked_cholesky(H, free)
        search = -cho_solve((L_free, True), jnp.where(free, grad, 0.0))
        candidates = jnp.clip(d[None, :] + steps[:, None] * search[None, :], lower, upper)
        values = jax.vmap(objective)(candidates)
        # Armijo condition on the projected arc.
        sufficient = values <= objective(d) + 0.1 * (candidates - d[None, :]) @ grad
        index = jnp.argmax(sufficient)
        d = jnp.where(jnp.any(sufficient), candidates[index], d)
    grad = g + H @ d
    free = ~(((d <= lower) & (grad > 0)) | ((d >= upper) & (grad < 0)))
    L_free = _masked_cholesky(H, free)
    return d, free, L_free


def _backward_pass(A, B, x, u, x_ref, u_ref, Q, R, Q_terminal, u_low, u_high, mu, settings: ILQRSettings):
    """Riccati-like recursion along the nominal ``(x, u)``; see the module docstring for the law and its sign."""
    nu = u.shape[-1]
    eye = jnp.eye(nu, dtype=u.dtype)
    Vx = Q_terminal @ (x[-1] - x_ref[-1])
    Vxx = Q_terminal

    def stage(carry, inputs):
        Vx, Vxx = carry
        A_k, B_k, x_k, u_k, xr_k, ur_k = inputs
        Qx = Q @ (x_k - xr_k) + A_k.T @ Vx
        Qu = R @ (u_k - ur_k) + B_k.T @ Vx
        Qxx = Q + A_k.T @ Vxx @ A_k
        Quu = _symmetric(R + B_k.T @ Vxx @ B_k)
        Qux = B_k.T @ Vxx @ A_k
        Quu_reg = Quu + mu * eye
        L = jnp.linalg.cholesky(Quu_reg)
        ok = jnp.all(jnp.isfinite(L))
        if settings.input_constraints == "box":
            d, free, L_free = _box_qp(Quu_reg, L, Qu, u_low - u_k, u_high - u_k, settings.box_qp_iterations)
            K = jnp.where(free[:, None], cho_solve((L_free, True), jnp.where(free[:, None], Qux, 0.0)), 0.0)
        else:
            d = -cho_solve((L, True), Qu)
            K = cho_solve((L, True), Qux)
        # Value function of the law du = d - K dx, valid for any (d, K) (not only the unconstrained optimum).
        Vx = Qx - K.T @ Qu - K.T @ Quu @ d + Qux.T @ d
        Vxx = _symmetric(Qxx + K.T @ Quu @ K - K.T @ Qux - Qux.T @ K)
        return (Vx, Vxx), (d, K, d @ Qu, 0.5 * d @ Quu_reg @ d, ok)

    _, (d, K, dV1, dV2, ok) = lax.scan(stage, (Vx, Vxx), (A, B, x[:-1], u, x_ref[:-1], u_ref), reverse=True)
    ok = jnp.all(ok) & jnp.all(jnp.isfinite(d)) & jnp.all(jnp.isfinite(K))
    return _Backward(d, K, jnp.sum(dV1), jnp.sum(dV2), ok)


def _rollout(step_fn, x0, x_bar, u_bar, d, K, alpha, x_ref, u_ref, Q, R, Q_terminal, u_low, u_high):
    """Closed-loop rollout of ``u_k = clip(u_bar_k + alpha d_k - K_k (x_k - x_bar_k))``; returns ``(x, u, cost)``."""

    def stage(x, inputs):
        xb, ub, dk, Kk, xr, ur = inputs
        u = jnp.clip(ub + alpha * dk - Kk @ (x - xb), u_low, u_high)
        dx, du = x - xr, u - ur
        cost = 0.5 * dx @ Q @ dx + 0.5 * du @ R @ du
        return step_fn(x, u), (x, u, cost)

    x_last, (xs, us, costs) = lax.scan(stage, x0, (x_bar[:-1], u_bar, d, K, x_ref[:-1], u_ref))
    dx = x_last - x_ref[-1]
    cost = jnp.sum(costs) + 0.5 * dx @ Q_terminal @ dx
    xs = jnp.concatenate([xs, x_last[None]], axis=0)
    # A diverged rollout must lose every comparison, not spread NaN into the accepted plan.
    finite = jnp.isfinite(cost) & jnp.all(jnp.isfinite(xs))
    return xs, us, jnp.where(finite, cost, jnp.inf)


def _next_regularization(mu, accepted, unresolved, settings: ILQRSettings):
    """Levenberg-Marquardt ``mu`` after an iteration: divided by the factor after an accepted step (0 once below the
    minimum), kept after a rejected step too small for the cost's resolution, else multiplied (at least the
    minimum)."""
    factor, mu_min = settings.regularization_factor, settings.regularization_min
    lowered = mu / factor
    return jnp.where(
        accepted,
        jnp.where(lowered < mu_min, 0.0, lowered),
        jnp.where(unresolved, mu, jnp.maximum(mu * factor, mu_min)),
    )


def ilqr_solve(
    step_fn,
    x0,
    u_init,
    x_ref,
    u_ref,
    Q,
    R,
    Q_terminal,
    u_low,
    u_high,
    settings: ILQRSettings | None = None,
    regularization=None,
    x_init=None,
    K_init=None,
) -> ILQRSolution:
    """Solve the finite-horizon tracking problem of the module docstring by iLQR from the initial guess ``u_init``.

    Args:
        step_fn: ``step_fn(x (nx,), u (nu,)) -> x_next (nx,)``, the discrete dynamics (JAX, differentiable).
        x0: (nx,) initial state. u_init: (H, nu) initial input guess, N (clipped to the limits).
        x_ref: (H + 1, nx) state reference. u_ref: (H, nu) input reference, N.
        Q: (nx, nx), R: (nu, nu), Q_terminal: (nx, nx) symmetric weights (R positive definite, or made so by
            the regularisation).
        u_low, u_high: (nu,) input limits, N (``-inf`` / ``inf`` for none).
        settings: ``ILQRSettings`` (static); default ``ILQRSettings()``.
        regularization: initial ``mu`` (scalar, may be traced, e.g. carried between control steps); default
            ``settings.regularization_init``.
        x_init, K_init: optional (H + 1, nx) states and (H, nu, nx) gains that make the initial guess a feedback
            policy: the first rollout applies ``u_k = clip(u_init[k] - K_init[k] (x_k - x_init[k]))``. On an
            unstable system an open-loop guess diverges over a long horizon and the solver can settle in a poor
            local minimum; a stabilising guess (the previous plan with its gains, or LQR about the reference)
            starts it in the right basin, and since the cost only decreases, the solution is never worse than it.
            Default: the open-loop guess ``u_init`` (``K_init = 0``).

    Returns:
        ``ILQRSolution``.
    """
    settings = ILQRSettings() if settings is None else settings
    x0 = jnp.asarray(x0)
    dtype = jnp.result_type(x0.dtype, jnp.asarray(u_init).dtype)
    cast = lambda a: jnp.asarray(a, dtype=dtype)  # noqa: E731
    x0, u_init, x_ref, u_ref, Q, R, Q_terminal = map(cast, (x0, u_init, x_ref, u_ref, Q, R, Q_terminal))
    u_low = jnp.broadcast_to(cast(u_low), u_init.shape[-1:])
    u_high = jnp.broadcast_to(cast(u_high), u_init.shape[-1:])
    horizon, nu = u_init.shape
    nx = x0.shape[0]
    mu0 = cast(settings.regularization_init if regularization is None else regularization)
    mu_min, mu_max = settings.regularization_min, settings.regularization_max
    tol = settings.tolerance
    alphas = settings.line_search_factor ** jnp.arange(settings.line_search_steps, dtype=dtype)

    def step(x, u):
        return jnp.asarray(step_fn(x, u), dtype=dtype)

    jacobians = jax.vmap(jax.jacfwd(step, argnums=(0, 1)))
    rollout = lambda x_bar, u_bar, d, K, alpha: _rollout(  # noqa: E731
        step, x0, x_bar, u_bar, d, K, alpha, x_ref, u_ref, Q, R, Q_terminal, u_low, u_high
    )
    backward = lambda A, B, x, u, mu: _backward_pass(  # noqa: E731
        A, B, x, u, x_ref, u_ref, Q, R, Q_terminal, u_low, u_high, mu, settings
    )

    # Cost differences below this fraction of the cost are rounding noise of the rollout (float32: 3e-4): the
    # state itself carries a relative error eps, so near the reference the error of ``x - x_ref`` is a large
    # fraction of it.
    resolution = float(np.sqrt(np.finfo(dtype).eps))

    def predicted_converged(bwd, cost, mu):
        # Only an (almost) unregularised step's prediction measures optimality: with a large mu the step, and so
        # its predicted decrease, is small however far the plan is from the optimum.
        predicted = -(bwd.dV1 + bwd.dV2)
        return bwd.ok & (mu <= mu_min) & (predicted <= tol * jnp.abs(cost))

    zeros_d = jnp.zeros((horizon, nu), dtype)
    zeros_K = jnp.zeros((horizon, nu, nx), dtype)
    x_init = jnp.zeros((horizon + 1, nx), dtype) if x_init is None else cast(x_init)
    K_init = zeros_K if K_init is None else cast(K_init)
    x, u, cost = rollout(x_init, u_init, zeros_d, K_init, cast(0.0))
    A, B = jacobians(x[:-1], u)
    bwd = backward(A, B, x, u, mu0)
    history = jnp.full((settings.max_iterations + 1,), cost)
    init = {
        "iteration": jnp.zeros((), jnp.int32),
        "x": x,
        "u": u,
        "cost": cost,
        "A": A,
        "B": B,
        "bwd": bwd,
        "mu": mu0,
        "converged": predicted_converged(bwd, cost, mu0),
        "failed": ~jnp.isfinite(cost),
        "history": history,
    }

    def cond(s):
        return (s["iteration"] < settings.max_iterations) & ~s["converged"] & ~s["failed"]

    def body(s):
        bwd = s["bwd"]
        xs, us, costs = jax.vmap(lambda alpha: rollout(s["x"], s["u"], bwd.d, bwd.K, alpha))(alphas)
        predicted = -(alphas * bwd.dV1 + alphas**2 * bwd.dV2)
        actual = s["cost"] - costs
        good = (actual > 0) & (actual >= settings.line_search_min_ratio * predicted)
        accepted = bwd.ok & jnp.any(good)
        best = jnp.argmax(good)
        x = jnp.where(accepted, xs[best], s["x"])
        u = jnp.where(accepted, us[best], s["u"])
        cost = jnp.where(accepted, costs[best], s["cost"])
        # A rejected (almost) Newton step that promised less than the cost's resolution is not a failure: the
        # plan is optimal to the precision the cost can be evaluated in, and raising mu would only make the
        # following steps (and, carried over, the next control steps) stale.
        unresolved = (
            bwd.ok & ~accepted & (s["mu"] <= mu_min) & (-(bwd.dV1 + bwd.dV2) <= resolution * jnp.abs(s["cost"]))
        )
        mu = _next_regularization(s["mu"], accepted, unresolved, settings)
        A, B = lax.cond(accepted, lambda: jacobians(x[:-1], u), lambda: (s["A"], s["B"]))
        new_bwd = backward(A, B, x, u, mu)
        small_step = accepted & (s["cost"] - cost <= tol * jnp.abs(s["cost"]))
        iteration = s["iteration"] + 1
        return {
            "iteration": iteration,
            "x": x,
            "u": u,
            "cost": cost,
            "A": A,
            "B": B,
            "bwd": new_bwd,
            "mu": mu,
            "converged": small_step | unresolved | predicted_converged(new_bwd, cost, mu),
            "failed": mu > mu_max,
            "history": s["history"].at[iteration].set(cost),
        }

    s = lax.while_loop(cond, body, batched_like(init, x))  # the mu, the counter: per copy under vmap
    history = jnp.where(jnp.arange(settings.max_iterations + 1) > s["iteration"], s["cost"], s["history"])
    bwd = s["bwd"]
    return ILQRSolution(
        x=s["x"],
        u=s["u"],
        K=jnp.where(bwd.ok, bwd.K, 0.0),
        d=jnp.where(bwd.ok, bwd.d, 0.0),
        cost=s["cost"],
        iterations=s["iteration"],
        converged=s["converged"],
        regularization=s["mu"],
        cost_history=history,
    )


# --------------------------------------------------------------------------------------------- controller
WARM_STARTS = ("lqr", "open_loop")


@dataclasses.dataclass(frozen=True)
class Options:
    """Options of the receding-horizon iLQR controller (a config file's ``controllers.ilqr`` section)."""

    horizon: int = option(25, "prediction horizon H, control steps")
    max_iterations: int = option(3, "iLQR iterations per control step (warm-started from the shifted plan)")
    q_diag: tuple | None = option(None, "diagonal state weight (nx,); default: the prior's Q")
    r_diag: tuple | None = option(None, "diagonal input weight (nu,); default: the prior's R")
    terminal_weight: str = setup.terminal_weight_option()
    terminal_scale: float = option(1.0, "factor on the terminal weight")
    discretization: str = setup.discretization_option("rk4")
    input_constraints: str = option(
        "box",
        "input limits in the backward pass (box-DDP) or only by clipping the forward pass",
        choices=INPUT_CONSTRAINTS,
    )
    warm_start: str = option(
        "lqr",
        "first guess of each solve: the previous plan as a feedback policy, started at reset from LQR about the "
        "reference (lqr), or the previous plan's inputs open loop, started from the equilibrium input (open_loop)",
        choices=WARM_STARTS,
    )
    box_qp_iterations: int = option(4, "projected-Newton iterations of the box QP per stage")
    tolerance: float = option(1e-6, "relative cost decrease counted as converged")
    regularization_init: float = option(0.0, "Levenberg-Marquardt mu at reset (mu is then carried between steps)")
    regularization_min: float = option(1e-6, "smallest non-zero mu")
    regularization_max: float = option(1e10, "mu at which an iteration gives up")
    regularization_factor: float = option(10.0, "mu is multiplied (failure) or divided (success) by this")
    line_search_steps: int = option(8, "step sizes tried in parallel: 1, c, c^2, ...")
    line_search_factor: float = option(0.5, "ratio c of successive step sizes")
    line_search_min_ratio: float = option(1e-4, "smallest accepted ratio of actual to predicted decrease")

    def _check(self, path: str) -> None:
        if self.horizon < 1:
            raise ValueError(f"{path}.horizon: must be a positive integer, got {self.horizon!r}")
        positive(f"{path}.terminal_scale", self.terminal_scale)
        _check_solver_settings(self, path)

    def settings(self) -> ILQRSettings:
        """The solver's ``ILQRSettings`` from these options."""
        names = [f.name for f in dataclasses.fields(ILQRSettings)]
        return ILQRSettings(**{name: getattr(self, name) for name in names})


class ILQRState(NamedTuple):
    """Controller memory of one copy: the previous plan, shifted by one step, as a feedback policy.

    Attributes:
        u_plan: (H, nu) inputs, N. x_plan: (H + 1, nx) states. K_plan: (H, nu, nx) gains; the next solve starts
            from the rollout of ``u = u_plan[k] - K_plan[k] (x - x_plan[k])`` from the observed state.
        regularization: the Levenberg-Marquardt ``mu`` (scalar).
    """

    u_plan: Any
    x_plan: Any
    K_plan: Any
    regularization: Any


def model_step_fn(env, prior_params, discretization: str = "rk4"):
    """The prior model's discrete step ``f(x, u) -> x_next`` over one control period (JAX); the shared helper
    ``scg_algorithms.controller_setup.prior_step_fn``, kept under this name for callers of this module."""
    return setup.prior_step_fn(env, prior_params, discretization)


def make_ilqr(env, prior_params, options=None) -> JaxController:
    """Receding-horizon iLQR on the prior model ``prior_params`` (see the module docstring).

    Defaults and why:

    - ``discretization="rk4"``: one RK4 step per control period is as accurate as the env's substepped integrator
      to well below the model mismatch a prior carries (the one-step difference is O(dt^5)), and makes the
      sequential rollouts and the Jacobians ``substeps`` (20 at 50/1000 Hz) times cheaper.
    - ``terminal_weight="dare"``: the terminal cost ``1/2 dx^T P dx`` with ``P`` the discrete Riccati solution of
      the prior's linearisation about ``(goal, u_eq)`` is the infinite-horizon LQR cost-to-go, so a short
      horizon acts like the infinite-horizon problem near the goal (with no active limits and a linear model it
      reproduces LQR exactly), instead of the myopic plan a bare ``Q`` gives.
    - ``max_iterations=3``: the warm start from the shifted plan is close to optimal after the first steps, so a
      few iterations per step keep the plan converged (real-time iteration) at a bounded cost.

    Args:
        env: the environment. prior_params: ``EnvParams`` of the controller's model; its ``Q``, ``R`` are the
            default weights, ``goal`` the linearisation point of the terminal weight, ``physics`` the model and
            the input limits (``env.input_bounds``). options: ``Options`` fields as a mapping.

    Returns:
        A ``JaxController`` named ``"ilqr"``; ``act`` returns the first input of the plan (N, within the limits).

    Raises:
        ValueError: naming ``controllers.ilqr.<field>`` for a bad option, or when the discrete Riccati equation
            for the terminal weight has no stabilising solution.
    """
    path = "controllers.ilqr"
    opts = parse_options(Options, options, path)
    settings = opts.settings()
    nx, nu = env.nx, env.nu
    Q, R = setup.cost_weights(env, prior_params, opts.q_diag, opts.r_diag, path)
    u_eq = setup.equilibrium_input(env, prior_params)
    K_lqr, P = np.zeros((nu, nx)), Q
    if opts.terminal_weight == "dare" or opts.warm_start == "lqr":
        field = "terminal_weight" if opts.terminal_weight == "dare" else "warm_start"
        model = setup.prior_model(env, prior_params, opts.discretization)
        hint = "use terminal_weight 'stage' and warm_start 'open_loop'"
        K_dare, P_dare = setup.goal_lqr(env, prior_params, model, Q, R, path, field, hint)
        if opts.terminal_weight == "dare":
            P = P_dare
        if opts.warm_start == "lqr":
            K_lqr = K_dare
    Q_terminal = opts.terminal_scale * P
    u_low, u_high = setup.input_limits(env, prior_params)
    step_fn = model_step_fn(env, prior_params, opts.discretization)
    horizon = opts.horizon

    def constants(dtype):
        return tuple(jnp.asarray(a, dtype=dtype) for a in (Q, R, Q_terminal, u_low, u_high, u_eq, K_lqr))

    def reference_window(reference, first, length, dtype):
        last = reference.x_ref.shape[0] - 1
        return reference.x_ref[jnp.clip(first + jnp.arange(length), 0, last)].astype(dtype)

    def reset(key, reference):
        dtype = jnp.asarray(reference.x_ref).dtype
        *_, u_eq_j, K_j = constants(dtype)
        # The first solve starts from LQR about the reference (warm_start "lqr") or from hovering open loop.
        return ILQRState(
            u_plan=jnp.broadcast_to(u_eq_j, (horizon, nu)),
            x_plan=reference_window(reference, 0, horizon + 1, dtype),
            K_plan=jnp.broadcast_to(K_j, (horizon, nu, nx)),
            regularization=jnp.asarray(settings.regularization_init, dtype=dtype),
        )

    def act(ctrl_state, obs, step, reference):
        x = state_from_obs(env, obs)
        dtype = x.dtype
        Q_j, R_j, Qt_j, low_j, high_j, u_eq_j, K_j = constants(dtype)
        x_ref = reference_window(reference, step, horizon + 1, dtype)
        u_ref = jnp.broadcast_to(u_eq_j, (horizon, nu))
        sol = ilqr_solve(
            step_fn,
            x,
            ctrl_state.u_plan,
            x_ref,
            u_ref,
            Q_j,
            R_j,
            Qt_j,
            low_j,
            high_j,
            settings,
            ctrl_state.regularization,
            x_init=ctrl_state.x_plan,
            K_init=ctrl_state.K_plan,
        )
        # A non-finite observation (a diverged copy) must not poison the plan carried to the next step.
        finite = (
            jnp.all(jnp.isfinite(sol.u))
            & jnp.all(jnp.isfinite(sol.x))
            & jnp.all(jnp.isfinite(sol.K))
            & jnp.isfinite(sol.regularization)
        )
        u_plan = jnp.where(finite, sol.u, u_ref)
        x_plan = jnp.where(finite, sol.x, x_ref)
        K_plan = jnp.where(finite, sol.K, jnp.broadcast_to(K_j, (horizon, nu, nx)))
        if opts.warm_start == "open_loop":
            K_plan = jnp.zeros_like(K_plan)
        # Shift by one step; the stage appended at the end is the warm start's (LQR about the reference there).
        x_next_end = reference_window(reference, step + horizon + 1, 1, dtype)
        state = ILQRState(
            u_plan=jnp.concatenate([u_plan[1:], u_eq_j[None]], axis=0),
            x_plan=jnp.concatenate([x_plan[1:], x_next_end], axis=0),
            K_plan=jnp.concatenate([K_plan[1:], K_j[None]], axis=0),
            # A solve that gave up (mu beyond its maximum) lets the next step start afresh rather than stuck.
            regularization=jnp.where(
                finite & (sol.regularization <= settings.regularization_max),
                sol.regularization,
                settings.regularization_init,
            ).astype(dtype),
        )
        return u_plan[0], state

    info = {
        "horizon": horizon,
        "max_iterations": opts.max_iterations,
        "discretization": opts.discretization,
        "input_constraints": opts.input_constraints,
        "Q": Q,
        "R": R,
        "Q_terminal": Q_terminal,
        "K_warm_start": K_lqr,
        "warm_start": opts.warm_start,
        "u_eq": u_eq,
        "u_bounds": (u_low, u_high),
    }
    return JaxController("ilqr", reset, act, info=info)
