"""Nonlinear MPC in JAX: SQP and SQP-RTI on the structured horizon-QP solver (``scg_algorithms.mpc.structured``).

The problem is the CasADi controller's (``scg_algorithms.mpc.nonlinear``, the reference), scaled by 1/2::

    min   1/2 sum_{i=1}^{H-1} |x_i - r_i|_Q^2 + 1/2 |x_H - r_H|_P^2 + 1/2 sum_{i=0}^{H-1} |u_i - u_eq|_R^2
          [+ 1/2 soft_penalty sum (s + s^2)]
    s.t.  x_0 = x_hat,  x_{i+1} = f_d(x_i, u_i),  u_low <= u_i <= u_high,
          g(x_{i+1}, u_i) + margin <= 0   (hard)   or   <= s_i, s_i >= 0   (soft)

(the stage term of ``x_0`` is a constant and dropped). ``f_d`` is ``controller_setup.prior_step_fn`` (one RK4 step
or the env's integrator and substeps: the ``discretization`` option, as in the CasADi controller) and ``g`` the
env's constraints through ``scg_jax.constraints`` with the prior's values. Input-only rows on one input (the
"default" input constraint, ``abs_bound`` on the input) tighten the input box; the other rows are general rows of
the QP, linearised at every iteration.

**One iteration** linearises the dynamics and the constraints about the current plan ``(x_bar, u_bar)`` with
``jax.jacfwd`` (stage by stage, ``vmap``-ed), ``x_{i+1} = A_i x_i + B_i u_i + c_i`` with
``c_i = f_d(x_bar_i, u_bar_i) - A_i x_bar_i - B_i u_bar_i``, solves the QP (in the absolute inputs, pre-stabilised
with the goal's LQR gain for float32's sake) with ``structured.solve``, warm-started from the previous QP's rows
and multipliers (or, with ``qp_solver="ipm"``, with ``interior_point.solve`` from a cold start: Riccati steps on the
stage-wise problem, no condensing, at most ``ipm_max_iter`` iterations; hard rows only), and moves the plan toward
the QP's by the largest step ``a`` in ``1, 1/2, ..., 2^-7`` that lowers the l1 merit
``J + mu (sum |x_{i+1} - f_d(x_i, u_i)|_1 + sum max(g + margin, 0))`` (hard rows; ``mu = merit_weight``), or by the
smallest when none does.

- ``solver="sqp"``: iterates until the largest input change of an iteration is below ``sqp_tol`` (N) or
  ``sqp_max_iter`` iterations (a ``lax.while_loop``; under ``vmap`` the batch runs until its slowest copy stops).
- ``solver="sqp_rti"``: one iteration per control step about the previous plan shifted by one step (its last
  input held, the last state propagated through ``f_d``), the real-time iteration of Diehl et al. (2005), with the
  full step (no line search: a partial step is a weaker input, and the next step corrects the plan anyway). That
  step runs before the loop, without the merit, on the model Jacobians the margins were computed with. Without a
  plan (the first step) it iterates as ``sqp`` does in the loop, from the measured state held and the equilibrium
  input; under ``vmap`` the loop runs no iteration once every copy has a plan.

**A learned model** (GP-MPC, ``scg_algorithms.gp_mpc``): ``Prediction`` adds a model error's mean to ``f_d`` and
tightens every env constraint row at every stage by a margin from its variance, propagated along the plan about to be
linearised (the CasADi GP-MPC's ``tightening``, in JAX). ``sqp_mpc_builder`` does the host-side set-up once, so the
controller can be built inside ``jax.jit`` from a traced model (one compile per GP size).

**Failure**: a QP that is infeasible or non-finite moves nothing, and so does one whose plan violates a hard row by
more than ``fallback_tol`` unless the plan it would leave in place violates the same rows by more (its inputs
applied from the measured state through the QP's model; that plan only ages, shifted with its last input held, and
on a 2D quadrotor tracking its circle under a ceiling it held full thrust and flew off). With ``qp_solver="ipm"``
the plan judged and taken is the interior point's inputs clipped to the QP's input box, with their rollout (an
iterate stopped at its cap can overshoot the box, and the plan applied is clipped anyway). When the very first
iteration fails, the input is the shifted previous plan's (or the equilibrium input without one), clipped to the
box. ``SQPState.num_failures`` counts those steps. Nothing returned is NaN.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import custom_batching, lax

from scg_algorithms import controller_setup as setup
from scg_algorithms.base import JaxController, state_from_obs
from scg_algorithms.mpc import interior_point, structured
from scg_jax import constraints as constraints_lib
from scg_jax.backends import jax_backend
from scg_jax.tracing import batched_like

LINE_SEARCH_STEPS = 8  # a = 1, 1/2, ..., 2^-7
JACOBIAN_CHUNK = 1024  # stages per chunk of a batch's model Jacobians (_jacobians)


class Prediction(NamedTuple):
    """A learned correction of the prior's step and the constraint tightening its uncertainty brings (GP-MPC).

    Attributes:
        mean: ``mean(x (nx,), u (nu,)) -> (nx,)``, the mean of the prior's one-step error, added to ``f_d``.
        variance: ``variance(x, u) -> (nx,)``, its variance per state entry. Both may close over traced arrays (a
            GP's data), so one compiled program serves every GP of the same shape.
        K: (nu, nx) the ancillary gain of the covariance propagation (``δu = -K δx``).
        z_q: the chance-constraint quantile (``scg_algorithms.gp_mpc.tightening.quantile``).
        sigma0: (nx, nx) covariance of the initial state.
    """

    mean: Any
    variance: Any
    K: Any
    z_q: Any
    sigma0: Any


class SQPState(NamedTuple):
    """The memory of one copy.

    Attributes:
        x_plan: (H + 1, nx) the last plan's states. u_plan: (H, nu) its inputs, N. warm: the last QP's
            ``structured.Warm``. plan_step: the control step it was made at (-1: none).
        status: the last QP's ``structured`` status. iterations: SQP iterations of the last step.
        qp_iterations: ADMM iterations of the last step, all QPs together. num_failures: steps whose first QP failed.
    """

    x_plan: Any
    u_plan: Any
    warm: Any
    plan_step: Any
    status: Any
    iterations: Any
    qp_iterations: Any
    num_failures: Any


def _input_rows(env, prior_params, u_low, u_high, margin):
    """Split the env's constraint rows: those on one input only tighten ``(u_low, u_high)``; the others are kept.

    Returns ``(u_low, u_high, keep, box_rows)`` with ``keep`` the indices of the general rows and ``box_rows`` a
    ``(row, input, a, value0)`` tuple per box row (``a u_input + value0 <= 0``). A row counts as a box row when its
    Jacobian has no state part and one input entry, the same at two random points (a linear row)."""
    specs, values = env.constraint_specs, prior_params.constraints
    if not specs:
        return u_low, u_high, np.zeros(0, int), []
    g = lambda x, u: constraints_lib.evaluate_all(specs, values, x, u, jax_backend)  # noqa: E731
    rng = np.random.default_rng(0)
    with jax.enable_x64(True):
        points = [(rng.normal(size=env.nx), rng.normal(size=env.nu)) for _ in range(2)]
        jac = [
            [np.asarray(a) for a in jax.jacfwd(g, argnums=(0, 1))(jnp.asarray(x), jnp.asarray(u))] for x, u in points
        ]
        value0 = np.asarray(g(jnp.zeros(env.nx), jnp.zeros(env.nu)))
    (Jx, Ju), (Jx2, Ju2) = jac
    u_low, u_high, keep, box_rows = u_low.copy(), u_high.copy(), [], []
    for row in range(value0.shape[0]):
        inputs = np.flatnonzero(Ju[row])
        linear = np.allclose(Jx[row], Jx2[row]) and np.allclose(Ju[row], Ju2[row])
        if linear and not np.any(Jx[row]) and inputs.size == 1:
            i, a = int(inputs[0]), Ju[row, inputs[0]]
            bound = (-margin - value0[row]) / a  # a u_i + value0 + margin <= 0
            if a > 0:
                u_high[i] = min(u_high[i], bound)
            else:
                u_low[i] = max(u_low[i], bound)
            box_rows.append((row, i, float(a), float(value0[row])))
        else:
            keep.append(row)
    return u_low, u_high, np.asarray(keep, int), box_rows


def make_sqp_mpc(
    env, prior_params, opts, prediction: Prediction | None = None, name: str = "nonlinear_mpc"
) -> JaxController:
    """Nonlinear MPC by SQP (``opts.solver == "sqp"``) or SQP-RTI (``"sqp_rti"``) in JAX (see the module doc):
    ``sqp_mpc_builder(env, prior_params, opts, name)(prediction)``."""
    return sqp_mpc_builder(env, prior_params, opts, name)(prediction)


class _Setup(NamedTuple):
    """What ``sqp_mpc_builder`` computes once on the host: sizes, the QP's fixed parts (float arrays of the default
    dtype), the constraint rows and the solver's layout and settings."""

    env: Any
    opts: Any
    layout: Any
    settings: Any
    ipm: Any  # interior_point.IPMSettings when qp_solver is ipm, else None (the ADMM's settings)
    horizon: int
    m: int  # general constraint rows kept in the QP
    soft: bool
    margin: float
    keep: Any  # (m,) indices of the general rows among the env's
    box_rows: list  # (row, input, a, value0) per input-box row
    num_env_rows: int
    Qs: Any  # (H, nx, nx): Q at every stage but the last, P there
    Rs: Any  # (H, nu, nu)
    r_vec: Any  # (H, nu): -R u_eq
    Ks: Any  # (H, nu, nx) pre-stabilising gain
    box: tuple  # (H, nu) input bounds, low and high
    u_eq: Any
    u_low: Any
    u_high: Any
    prior_step: Any  # prior_step(x, u) -> x+, the prior's discrete model
    g_all: Any  # g_all(x, u) -> (num_env_rows,) every env constraint row
    g_rows: Any  # g_rows(x, u) -> (m,) the kept rows plus the margin


class _Model(NamedTuple):
    """A ``_Setup`` with the prediction model of one controller (``None``: the prior alone)."""

    setup: _Setup
    prediction: Prediction | None

    def step(self, x, u):
        s = self.setup
        return s.prior_step(x, u) if self.prediction is None else s.prior_step(x, u) + self.prediction.mean(x, u)


def sqp_mpc_builder(env, prior_params, opts, name: str = "nonlinear_mpc", adaptive_rho: bool = False):
    """The host-side set-up of ``make_sqp_mpc`` (weights, terminal weight, constraint rows, ADMM step size), done
    once; the ``build`` it returns makes the controller from a ``prediction`` without host work, so it may run inside
    ``jax.jit`` with a traced ``prediction`` (``scg_algorithms.evaluation.make_evaluator``: one compile per shape).

    Args:
        env: the environment. prior_params: unbatched ``EnvParams`` of the model. opts: the parsed
            ``scg_algorithms.mpc.nonlinear.Options``.
        name: the controller's name. adaptive_rho: adapt the ADMM step size (``structured.Settings``) instead of
            keeping the template's: GP-MPC needs it, its margins change the QP from step to step.
        ``build``'s ``prediction``: ``None`` (the prior's ``f_d``), or a ``Prediction``: the model is then
            ``f_d + error mean`` and every env constraint row is tightened at each stage by the margin of
            ``Prediction``'s variance propagated along the plan being linearised (``plan_margins``, computed once
            per control step, as the CasADi GP-MPC computes its margins along its warm start). A box row's margin
            tightens that stage's input
            box (a stage whose box the margins would empty keeps the midpoint of its tightened bounds).

    Returns:
        ``build(prediction) -> JaxController``; ``act`` returns ``(u (nu,) N, SQPState)``. ``info``: ``solver``,
        ``horizon``, ``P``, ``K`` (the pre-stabilising gain), ``u_low``/``u_high`` (the input box), ``status_names``,
        and ``plan_margins(x_plan (H + 1, nx), u_plan (H, nu)) -> (H, ng)``, each env constraint row's margin per stage
        (zero without a ``Prediction``).
    """
    path = f"controllers.{name}"
    H, nx, nu = opts.horizon, env.nx, env.nu
    model = setup.prior_model(env, prior_params, opts.discretization)
    Q, R = setup.cost_weights(env, prior_params, opts.q_diag, opts.r_diag, path, positive_definite_r=False)
    P = setup.terminal_weight(opts.terminal_weight, env, prior_params, model, Q, R, path)
    K = setup.goal_lqr(env, prior_params, model, Q, R, path)[0]
    u_eq = setup.equilibrium_input(env, prior_params)
    u_low, u_high = setup.input_limits(env, prior_params)
    margin = float(opts.constraint_margin)
    u_low, u_high, keep, box_rows = _input_rows(env, prior_params, u_low, u_high, margin)
    m = int(keep.size)
    soft = bool(opts.soft_constraints) and m > 0
    layout = structured.Layout(
        horizon=H,
        nx=nx,
        nu=nu,
        num_rows=m,
        soft_rows=(soft,) * m,
        slack="stage",
        # IPOPT's objective is twice this one: soft_penalty (s + s^2) becomes l1 s + 1/2 l2 s^2 with these.
        l1=0.5 * opts.soft_penalty if soft else 0.0,
        l2=opts.soft_penalty if soft else 0.0,
    )
    specs, values = env.constraint_specs, prior_params.constraints

    def g_all(x, u):
        return constraints_lib.evaluate_all(specs, values, x, u, jax_backend)

    def g_rows(x, u):
        return g_all(x, u)[keep] + margin

    cast = lambda a: jnp.asarray(a, jnp.zeros(()).dtype)  # noqa: E731
    goal = np.asarray(prior_params.goal, dtype=np.float64).reshape(nx)
    template = _template(layout, model, goal, u_eq, K, Q, R, P, u_low, u_high, g_rows if m else None)
    settings = structured.Settings(
        max_iterations=opts.qp_max_iter,
        # The checks' products cost as much as several iterations (a batch runs until its slowest copy stops):
        # every 20 iterations instead of 10, an SQP-RTI step of 1,024 2D quadrotors took 0.91x the time.
        check_every=20,
        eps_abs=opts.qp_tol,
        eps_rel=opts.qp_tol,
        polish_rounds=opts.qp_polish_rounds,
        rho=structured.suggested_rho(layout, template),
        # A step size that adapts costs a Cholesky per check and copy under vmap whenever one copy of the batch needs
        # it, which at 1,024 copies is every check: fixed at the template's, an SQP-RTI step of 1,024 2D quadrotors
        # took 0.59 ms per copy instead of 1.16 (before the condensing was made cheaper).
        # GP-MPC's margins close most of the cart-pole's input box late in the horizon: with the template's step size
        # float32 ADMM then ran into its cap at most steps and rejected a third of them (RMSE 0.276 against 0.164).
        adaptive_rho=adaptive_rho,
    )
    fixed = _Setup(
        env=env,
        opts=opts,
        layout=layout,
        settings=settings,
        ipm=interior_point.IPMSettings(
            max_iterations=opts.ipm_max_iter,
            polish_rounds=opts.ipm_polish_rounds,
            refinement_steps=opts.ipm_refinement_steps,
        )
        if opts.qp_solver == "ipm"
        else None,
        horizon=H,
        m=m,
        soft=soft,
        margin=margin,
        keep=keep,
        box_rows=box_rows,
        num_env_rows=m + len(box_rows),
        Qs=cast(np.stack([Q] * (H - 1) + [P])),
        Rs=cast(np.repeat(R[None], H, axis=0)),
        r_vec=cast(np.tile(-(R @ u_eq), (H, 1))),
        Ks=cast(np.repeat(K[None], H, axis=0)),
        box=(cast(np.tile(u_low, (H, 1))), cast(np.tile(u_high, (H, 1)))),
        u_eq=cast(u_eq),
        u_low=cast(u_low),
        u_high=cast(u_high),
        prior_step=setup.prior_step_fn(env, prior_params, opts.discretization),
        g_all=g_all,
        g_rows=g_rows,
    )
    info = {
        "solver": opts.solver,
        "horizon": H,
        "P": P,
        "K": K,
        "u_low": u_low,
        "u_high": u_high,
        "status_names": structured.STATUS_NAMES,
        "layout": layout,
    }

    def build(prediction: Prediction | None) -> JaxController:
        model = _Model(fixed, prediction)
        return JaxController(
            name=name,
            reset_fn=lambda key, reference: _reset(fixed),
            act_fn=lambda ctrl_state, obs, step, reference: _act(model, ctrl_state, obs, step, reference),
            info={**info, "plan_margins": lambda x_plan, u_plan: _plan_margins(model, x_plan, u_plan)},
        )

    return build


def _jacobians(model: _Model, x, u):
    """``(A (H, nx, nx), B (H, nx, nu), f (H, nx))``: the model's Jacobians and values at the stages ``(x_i, u_i)``
    (forward mode gives the values with the Jacobians).

    Under ``vmap`` (copies) the prior's Jacobians are taken ``JACOBIAN_CHUNK`` stages at a time (``lax.map``): forward
    mode carries ``nx + nu`` tangents through every intermediate of the model, and at 1,024 copies of the 3D quadrotor
    those are arrays of 20,480 x 16 x 12 that leave the cache; in chunks the same Jacobians took 0.47x the time.
    A learned model's (GP-MPC's, which closes over the GP's data) are taken at once."""

    def step(x_i, u_i):
        value = model.step(x_i, u_i)
        return value, value

    jacobian = jax.jacfwd(step, argnums=(0, 1), has_aux=True)

    def at_once(x, u):
        (A, B), f = jax.vmap(jacobian)(x, u)
        return A, B, f

    if model.prediction is not None:
        return at_once(x, u)
    chunked = custom_batching.custom_vmap(at_once)

    @chunked.def_vmap
    def _(axis_size, in_batched, x, u):
        x, u = (a if b else jnp.broadcast_to(a, (axis_size, *a.shape)) for a, b in zip((x, u), in_batched, strict=True))
        stages = x.shape[1]
        (A, B), f = lax.map(
            lambda xu: jacobian(*xu),
            (x.reshape(-1, x.shape[-1]), u.reshape(-1, u.shape[-1])),
            batch_size=JACOBIAN_CHUNK,
        )
        return tuple(a.reshape(axis_size, stages, *a.shape[1:]) for a in (A, B, f)), (True, True, True)

    return chunked(x, u)


def _needs_margins(model: _Model) -> bool:
    return model.prediction is not None and model.setup.num_env_rows > 0


def _plan_margins(model: _Model, x_plan, u_plan, lin=None):
    """(H, ng) margins of the env's constraint rows at ``(x_{i+1}, u_i)`` along the plan (``tightening``); ``lin``:
    the ``_jacobians`` at ``(x_plan[:-1], u_plan)`` when the caller has them."""
    s, prediction = model.setup, model.prediction
    dtype = s.u_eq.dtype
    if not _needs_margins(model):
        return jnp.zeros((s.horizon, s.num_env_rows), dtype)
    from scg_algorithms.gp_mpc import tightening

    A, B, _ = _jacobians(model, x_plan[:-1], u_plan) if lin is None else lin
    var = jnp.maximum(jax.vmap(prediction.variance)(x_plan[:-1], u_plan), 0.0)
    sigmas = tightening.propagate_covariance_scan(A, B, prediction.K, var, prediction.sigma0)
    rows_x, rows_u = jax.vmap(jax.jacfwd(s.g_all, argnums=(0, 1)))(x_plan[1:], u_plan)
    return tightening.margins(rows_x, rows_u, sigmas, prediction.K, prediction.z_q, xp=jnp).astype(dtype)


def _tightened_box(s: _Setup, margins):
    """The stages' input boxes (H, nu) with each box row's margin taken off (module doc)."""
    low, high = s.box
    for row, i, a, value0 in s.box_rows:
        bound = (-s.margin - margins[:, row] - value0) / a
        low, high = (low, high.at[:, i].min(bound)) if a > 0 else (low.at[:, i].max(bound), high)
    empty = low > high
    middle = 0.5 * (low + high)
    return jnp.where(empty, middle, low), jnp.where(empty, middle, high)


def _linearize(model: _Model, x_bar, u_bar, row_margins, stage_box, lin=None):
    """The QP of the plan ``(x_bar (H + 1, nx), u_bar (H, nu))``, the general rows tightened by ``row_margins``
    (H, m), the inputs in ``stage_box``; ``lin``: the ``_jacobians`` at ``(x_bar[:-1], u_bar)`` when known."""
    s = model.setup
    H, nx, nu, dtype = s.horizon, s.env.nx, s.env.nu, s.u_eq.dtype
    A, B, f = _jacobians(model, x_bar[:-1], u_bar) if lin is None else lin
    c = f - jnp.einsum("kxy,ky->kx", A, x_bar[:-1]) - jnp.einsum("kxu,ku->kx", B, u_bar)
    if s.m:
        C, D = jax.vmap(jax.jacfwd(s.g_rows, argnums=(0, 1)))(x_bar[1:], u_bar)
        g0 = jax.vmap(s.g_rows)(x_bar[1:], u_bar)
        high = -g0 - row_margins + jnp.einsum("kmx,kx->km", C, x_bar[1:]) + jnp.einsum("kmu,ku->km", D, u_bar)
    else:
        C, D, high = jnp.zeros((H, 0, nx), dtype), jnp.zeros((H, 0, nu), dtype), jnp.zeros((H, 0), dtype)
    empty = jnp.zeros((H, 0), dtype)
    return structured.HorizonQP(
        A, B, c, s.Ks, s.Qs, None, s.Rs, s.r_vec, *stage_box, empty, empty, C, D, -jnp.inf * jnp.ones_like(high), high
    )


def _merit(model: _Model, x, u, x0, window, row_margins):
    """The line search's merit: the plan's cost plus ``merit_weight`` times its defects and (hard rows) violation."""
    s = model.setup
    dx = x[1:] - window[1:]
    du = u - s.u_eq
    J = 0.5 * jnp.einsum("kx,kxy,ky->", dx, s.Qs, dx) + 0.5 * jnp.einsum("ku,kuv,kv->", du, s.Rs, du)
    defects = jnp.sum(jnp.abs(x[1:] - jax.vmap(model.step)(x[:-1], u))) + jnp.sum(jnp.abs(x[0] - x0))
    violation = jnp.sum(jnp.maximum(jax.vmap(s.g_rows)(x[1:], u) + row_margins, 0.0)) if (s.m and not s.soft) else 0.0
    return J + s.opts.merit_weight * (defects + violation)


def _solve_qp(s: _Setup, qp, x0, warm) -> structured.Solution:
    """The QP by the ADMM (warm-started) or, with ``qp_solver: ipm``, by the interior point (cold; ``warm`` is
    passed through for the next step; its plan's inputs come clipped to the QP's box)."""
    if s.ipm is None:
        return structured.solve(s.layout, qp, x0, warm, s.settings)
    sol = interior_point.solve(s.layout, qp, x0, s.ipm)
    return structured.Solution(
        u=sol.u, x=sol.x, slack=jnp.zeros_like(sol.multipliers), multipliers=sol.multipliers, warm=warm,
        status=sol.status, iterations=sol.iterations, primal_residual=sol.primal_residual,
        dual_residual=sol.dual_residual, violation=sol.violation,
    )  # fmt: skip


def _iteration(model: _Model, x0, window, x_bar, u_bar, warm, margins, lin=None, full_step: bool = False):
    """One SQP iteration: the QP about ``(x_bar, u_bar)`` (``lin``: the model's ``_jacobians`` there, when known),
    then a step along it chosen by the merit, or (``full_step``, static: SQP-RTI) the full step, the merit not
    evaluated."""
    s = model.setup
    dtype = s.u_eq.dtype
    row_margins, stage_box = margins[:, s.keep], _tightened_box(s, margins)
    qp = _linearize(model, x_bar, u_bar, row_margins, stage_box, lin)
    qp = qp._replace(q=-jnp.einsum("kxy,ky->kx", s.Qs, window[1:]))
    sol = _solve_qp(s, qp, x0, warm)
    ok = (sol.status == structured.CONVERGED) | (sol.status == structured.MAX_ITERATIONS)
    # A plan that misses a hard row by more than fallback_tol is still taken where the plan it would leave in place
    # misses the same rows by more: 8 episodes of the 2D quadrotor's circle under a ceiling at 1.3 m, where the ADMM
    # stops at its cap, went from one flight to 30.6 m and RMSE 0.529 to every episode that starts below the ceiling
    # within 1e-4 m of it and RMSE 0.235 (tests/test_sqp_mpc.py).
    kept = interior_point.inputs_violation(s.layout, qp, x0, u_bar) if (s.m and not s.soft) else jnp.zeros((), dtype)
    tolerated = jnp.maximum(s.opts.fallback_tol, kept)
    ok = ok & (sol.violation <= tolerated) & jnp.all(jnp.isfinite(sol.u)) & jnp.all(jnp.isfinite(sol.x))
    if not full_step:
        base = _merit(model, x_bar, u_bar, x0, window, row_margins)
        fractions = 0.5 ** jnp.arange(LINE_SEARCH_STEPS, dtype=dtype)

        def trial(a):
            return _merit(model, x_bar + a * (sol.x - x_bar), u_bar + a * (sol.u - u_bar), x0, window, row_margins)

        merits = jax.vmap(trial)(fractions)
        # Round-off of the merit (float32: defects of 1e-7 m weighed by merit_weight) must not reject a step.
        better = merits <= base + 8 * jnp.finfo(dtype).eps * jnp.abs(base)
        a = jnp.where(jnp.any(better), fractions[jnp.argmax(better)], fractions[-1])
        a = jnp.where(ok, a, 0.0)
    else:
        a = jnp.where(ok, 1.0, 0.0).astype(dtype)
    x_new = x_bar + a * (sol.x - x_bar)
    u_new = jnp.clip(u_bar + a * (sol.u - u_bar), s.u_low, s.u_high)
    change = jnp.max(jnp.abs(u_new - u_bar))
    return x_new, u_new, jnp.where(ok, 1, 0), sol, change


def _shifted(model: _Model, state: SQPState, x0, moved):
    """The last plan advanced by ``moved`` steps from ``x0``, its tail extended by the model under its last inputs."""
    H = model.setup.horizon
    index = jnp.minimum(jnp.arange(H) + moved, H - 1)
    u = state.u_plan[index]
    x = state.x_plan[jnp.minimum(jnp.arange(H + 1) + moved, H)].at[0].set(x0)

    # The last `moved` states, one model step each: a loop of `moved` steps (under vmap, of the batch's largest
    # `moved`, one in a closed loop) rather than a scan over the horizon that evaluates the model at every stage.
    def extend(carry):
        j, x = carry
        k = H - moved + j
        return j + 1, x.at[k + 1].set(model.step(x[k], u[k]))

    _, x = lax.while_loop(lambda carry: carry[0] < moved, extend, (jnp.zeros_like(moved), x))
    return x, u


def _reset(s: _Setup) -> SQPState:
    dtype = s.u_eq.dtype
    zeros = jnp.zeros(s.layout.num_dense, dtype)
    return SQPState(
        x_plan=jnp.zeros((s.horizon + 1, s.env.nx), dtype),
        u_plan=jnp.tile(s.u_eq, (s.horizon, 1)),
        warm=structured.Warm(zeros, zeros, jnp.zeros((), dtype)),
        plan_step=jnp.asarray(-1, jnp.int32),
        status=jnp.zeros((), jnp.int32),
        iterations=jnp.zeros((), jnp.int32),
        qp_iterations=jnp.zeros((), jnp.int32),
        num_failures=jnp.zeros((), jnp.int32),
    )


def _act(model: _Model, ctrl_state: SQPState, obs, step, reference):
    s = model.setup
    H, dtype, opts = s.horizon, s.u_eq.dtype, s.opts
    rti = opts.solver == "sqp_rti"
    x0 = jnp.asarray(state_from_obs(s.env, obs), dtype)
    x_ref = jnp.asarray(reference.x_ref, dtype)
    window = x_ref[jnp.minimum(step + jnp.arange(H + 1), x_ref.shape[0] - 1)]
    moved = step - ctrl_state.plan_step
    have_plan = (ctrl_state.plan_step >= 0) & (moved >= 1) & (moved <= H)
    x_shift, u_shift = _shifted(model, ctrl_state, x0, jnp.clip(moved, 1, H))
    x_bar = jnp.where(have_plan, x_shift, jnp.tile(x0, (H + 1, 1)))
    u_bar = jnp.where(have_plan, u_shift, jnp.tile(s.u_eq, (H, 1)))
    warm = jax.tree.map(
        lambda a, b: jnp.where(have_plan, a, b),
        structured.shift(s.layout, ctrl_state.warm, jnp.clip(moved, 1, H)),
        _reset(s).warm,
    )
    # The model's Jacobians along the shifted plan: the margins' (once per step) and SQP-RTI's linearisation.
    lin = _jacobians(model, x_bar[:-1], u_bar) if (rti or _needs_margins(model)) else None
    margins = _plan_margins(model, x_bar, u_bar, lin)
    # SQP-RTI: one full step about the shifted plan for the copies that have one, taken before the loop and without
    # the line search's merits, which it would discard (under vmap they would be computed for every copy); the loop
    # then runs only for copies without a plan (an episode's first step), none once every copy has one.
    cap = jnp.where(have_plan, 0, opts.sqp_max_iter) if rti else opts.sqp_max_iter
    if rti:
        x_r, u_r, ok_r, sol_r, _ = _iteration(model, x0, window, x_bar, u_bar, warm, margins, lin, full_step=True)
        warm_r = jax.tree.map(lambda a, b: jnp.where(ok_r == 1, a, b), sol_r.warm, warm)
        rti_out = (x_r, u_r, warm_r, sol_r.status, sol_r.iterations, ok_r == 1, jnp.ones((), jnp.int32))

    def cond(carry):
        *_, it, change, ok = carry
        return (it < cap) & (change > opts.sqp_tol) & ok

    def body(carry):
        x, u, warm, status, qp_it, first_ok, it, _, _ = carry
        x, u, ok, sol, change = _iteration(model, x0, window, x, u, warm, margins)
        first_ok = jnp.where(it == 0, ok == 1, first_ok)
        warm = jax.tree.map(lambda a, b: jnp.where(ok == 1, a, b), sol.warm, warm)
        return x, u, warm, sol.status, qp_it + sol.iterations, first_ok, it + 1, change, ok == 1

    init = (x_bar, u_bar, warm, jnp.zeros((), jnp.int32), jnp.zeros((), jnp.int32), jnp.ones((), bool))
    init = (*init, jnp.zeros((), jnp.int32), jnp.asarray(jnp.inf, dtype), jnp.ones((), bool))
    x, u, warm, status, qp_it, first_ok, it, _, _ = lax.while_loop(cond, body, batched_like(init, x0))
    if rti:
        x, u, warm, status, qp_it, first_ok, it = jax.tree.map(
            lambda a, b: jnp.where(have_plan, a, b), rti_out, (x, u, warm, status, qp_it, first_ok, it)
        )
    u_apply = jnp.clip(jnp.where(jnp.all(jnp.isfinite(u[0])), u[0], s.u_eq), s.u_low, s.u_high)
    x = jnp.where(jnp.isfinite(x), x, 0.0)
    new_state = SQPState(
        x_plan=x.at[0].set(x0),
        u_plan=u,
        warm=warm,
        plan_step=jnp.asarray(step, jnp.int32),
        status=status.astype(jnp.int32),
        iterations=it,
        qp_iterations=qp_it,
        num_failures=ctrl_state.num_failures + (~first_ok).astype(jnp.int32),
    )
    return u_apply, new_state


def _template(layout, model, goal, u_eq, K, Q, R, P, u_low, u_high, g_rows):
    """A QP like those of the controller (the model linearised at the goal), for the initial ADMM step size."""
    H, nx, nu, m = layout.horizon, layout.nx, layout.nu, layout.num_rows
    lin = model.linearize(goal, u_eq)
    if m:
        with jax.enable_x64(True):
            C, D = (np.asarray(a) for a in jax.jacfwd(g_rows, argnums=(0, 1))(jnp.asarray(goal), jnp.asarray(u_eq)))
    else:
        C, D = np.zeros((0, nx)), np.zeros((0, nu))
    rep = lambda a: np.repeat(np.asarray(a, dtype=np.float64)[None], H, axis=0)  # noqa: E731
    return structured.HorizonQP(
        A=rep(lin.Ad),
        B=rep(lin.Bd),
        c=np.zeros((H, nx)),
        K=rep(K),
        Q=np.stack([Q] * (H - 1) + [P]),
        q=np.zeros((H, nx)),
        R=rep(R),
        r=np.zeros((H, nu)),
        u_low=rep(u_low),
        u_high=rep(u_high),
        x_low=np.zeros((H, 0)),
        x_high=np.zeros((H, 0)),
        C=rep(C),
        D=rep(D),
        row_low=np.full((H, m), -np.inf),
        row_high=np.ones((H, m)),
    )
