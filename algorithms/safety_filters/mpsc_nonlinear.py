"""Nonlinear model predictive safety certification: the MPSC problem on the nonlinear prior model, one copy on the
host with CasADi ``Opti`` and IPOPT (``is_jax = False``).

Problem per step (state ``x``, proposed input ``u_L``; ``fd`` the prior's discrete model,
``env.symbolic_model(prior_params)`` with the env's integrator or one RK4 step, plus the mean model error ``bias``
when ``model_bias``)::

    min_{X, U, S}  1/2 |U_0 - u_L|^2 + 1/2 regularization sum_{j>=1} |U_j - u_eq + K (X_j - x_goal)|^2
                   + violation_penalty sum(S)
    s.t.           X_0 = x,  X_{j+1} = fd(X_j, U_j) + bias,
                   Ax X_{j+1} + Au U_j <= b - margin_j + S_j,  S >= 0    (j = 0..H-1; S_j = 0 on input rows)
                   the terminal tail's rows from X_H, with one slack for the whole tail

- Terminal tail: the rows along the ancillary LQR on the linearised model are affine in ``X_H``; the NLP holds
  those the others do not imply (``mpsc_structured.nonredundant_rows``, a linear program per row at build; the set
  is the same), and a plan is checked against every tail row after the solve (``tail_all``, ``tail_imposed``:
  ``(F, high)``).
- Rows: the actuator limits and the env's linear constraints (``scg_algorithms.mpc.linear``'s rows; quadratic
  constraints are not imposed).
- Tightening per stage (``tightening="reachable"``): the linearised error tube under the ancillary LQR ``K`` about
  the goal, from the per-dimension bound of the model error ``w = x+ - fd(x, u) - bias`` over ``n_samples`` plant
  transitions (``mpsc_tightening``); the margin grows with the stage as the incremental-Lyapunov sequence
  ``s_j`` of the fork's ``nl_mpsc`` does, without its offline LMI.
- Soft state rows (``violation_penalty > 0``, as the linear MPSC's structured solver): every row on the state, at
  every stage and over the terminal tail, may be exceeded by a slack priced at ``violation_penalty`` per row unit
  (an exact penalty: where a plan holds every row, the solution is the hard problem's). The problem is then always
  feasible, and where no plan holds the rows IPOPT returns the least-violating one instead of failing. A plan is
  certified only when it meets the dynamics and every row without slack.
- Warm start: the last plan IPOPT returned (certified or least-violating) shifted by one step (the last input
  held); a cold start holds ``x``.
- Fallback (Algorithm 1) when no plan is certified: the last certified plan continued with the tube feedback,
  ``U_prev[kinf] - K (x - X_prev[kinf])``, and after ``H`` such steps the least-violating plan's first input (the LQR
  ``u_eq - K (x - x_goal)`` with hard rows or when IPOPT returned no plan that meets the dynamics); the input is
  clipped to the actuator limits.

``certify(x_or_obs, u_uncertified, filter_params, filter_state)`` takes numpy arrays of one copy and returns
``(u (nu,), filter_state, FilterInfo)``; ``filter_params`` is unused (the problem is built in). Units SI.
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np

from scg_algorithms import controller_setup as setup
from scg_algorithms.base import option, parse_options, positive
from scg_algorithms.lqr import discrete_lqr_gain
from scg_algorithms.mpc.nonlinear import deferred_interrupt
from scg_algorithms.safety_filters import mpsc_tightening as tight
from scg_algorithms.safety_filters.backup import validation_states
from scg_algorithms.safety_filters.base import (
    BACKUP_CONTROLLER,
    BACKUP_PLAN,
    CERTIFIED,
    FilterInfo,
    applied_correction,
)
from scg_algorithms.safety_filters.mpsc_structured import nonredundant_rows
from scg_algorithms.safety_filters.mpsc_structured import tail_rows as tail_rows_of

PATH = "safety_filters.nonlinear_mpsc"
TIGHTENINGS = ("reachable", "none")
FEASIBILITY_TOL = 1e-6  # largest dynamics residual and row violation (state units, m, N) of a solution still used
# Measured under the contract's 3D ceiling (docs/safety-filters.md, "Every system, every constraint"). The cost
# 1/2 |U_0 - u_L|^2 is in motor thrusts: with the reference above the ceiling, LQR asks for more thrust than the
# ceiling allows, and the nonlinear model lets a plan take it by tilting (the thrust then pushes sideways instead of
# up). Only the failure bounds (85 degrees) limit the tilt, so certified plans pitched the quadrotor to 1.44 rad at the
# ceiling and it flew 1.8 m off the circle. The linear MPSC's model has no such way out (tilt enters vertical thrust
# to second order), and in 2D the same filter holds (1.14x).
QUADROTOR_3D_REFUSAL = (
    f"{PATH}.allow_quadrotor_3d: the nonlinear MPSC is refused on quadrotor_3d: under a z <= 1.3 m ceiling its "
    "certified plans brake by tilting the quadrotor (pitch up to 1.44 rad at the ceiling, the plant 1.8 m off the "
    "reference): 0 violating steps but 2.7-3.2x LQR's RMSE where the filters' contract allows 1.5x; use "
    "safety_filters.linear_mpsc or cbf (both hold there), or set allow_quadrotor_3d: true to build it anyway"
)


@dataclasses.dataclass(frozen=True)
class Options:
    """Options of the nonlinear MPSC (``safety_filters.nonlinear_mpsc``)."""

    horizon: int = option(20, "prediction horizon H, control steps (the plan's free inputs)")
    terminal_horizon: float = option(
        2.0, "seconds the ancillary LQR on the linearised model continues from X_H inside the rows (terminal set)"
    )
    q_lqr: tuple | None = option(None, "diagonal state weight (nx,) of the ancillary LQR K; default: see backup")
    r_lqr: tuple | None = option(None, "diagonal input weight (nu,) of the ancillary LQR K; default: see backup")
    discretization: str = setup.discretization_option("rk4", "model")
    tightening: str = option("reachable", "per-stage tightening from the model error, or none", choices=TIGHTENINGS)
    n_samples: int = option(600, "plant transitions sampled for the model-error bound")
    plant_draws: int = option(8, "plants drawn from the env's physics randomisation for the samples (1: nominal)")
    sample_seed: int = option(0, "seed of the samples")
    sample_half_width: tuple | None = option(
        None, "(nx,) half-widths of the box around the goal the sampled states fill; default: the env's init box"
    )
    error_quantile: float | None = option(
        None,
        "quantile of |w - mean| bounding the error per dimension; default: the largest of 1, 0.9, 0.75, 0.5 whose "
        "tube leaves the goal inside the tightened rows",
    )
    model_bias: bool = option(True, "add the mean sampled model error to the prediction model")
    constraint_margin: float = option(
        0.003,
        "extra margin on every row that involves the state (row units; the default: 3 standard deviations of the "
        "configs' 1 mm position noise, which the tube from the observed state does not hold)",
    )
    regularization: float = option(1e-2, "weight of the deviation of U_j from the tube feedback (j >= 1)")
    violation_penalty: float = option(
        1e4,
        "price of a unit of violation of a state row (exact penalty; 1/2 N^2 per row unit; 0: hard rows): with no "
        "certified plan left, the least-violating plan's first input is applied instead of the plain LQR",
    )
    max_iter: int = option(100, "IPOPT iterations at most")
    tol: float = option(1e-8, "IPOPT tolerance")
    warm_start: bool = option(True, "start IPOPT from the previous plan shifted by one step")
    allow_quadrotor_3d: bool = option(
        False,
        "build on the 3D quadrotor, where the filter fails the contract (plans that tilt it to brake; the refusal "
        "message has the measurement)",
    )

    def _check(self, path: str) -> None:
        for name in ("horizon", "n_samples", "plant_draws", "max_iter"):
            if getattr(self, name) < 1:
                raise ValueError(f"{path}.{name}: must be a positive integer, got {getattr(self, name)!r}")
        positive(f"{path}.tol", self.tol)
        if self.error_quantile is not None and not 0.0 < self.error_quantile <= 1.0:
            raise ValueError(f"{path}.error_quantile: must be in (0, 1], got {self.error_quantile!r}")
        for name in ("constraint_margin", "regularization", "terminal_horizon", "violation_penalty"):
            if getattr(self, name) < 0:
                raise ValueError(f"{path}.{name}: must be >= 0, got {getattr(self, name)!r}")


class NonlinearMPSC:
    """Host filter (build it with ``make_nonlinear_mpsc``).

    Attributes:
        name, is_jax, system, params: the filter protocol (``params`` is ``None``). options: parsed ``Options``.
        K: (nu, nx) ancillary LQR. x_goal (nx,), u_eq (nu,): its linearisation point. u_low, u_high: clip box, N.
        margins: (H, m) per-stage tightening of the rows. bias: (nx,) model bias added to the prediction.
        errors: (n, nx) the model-error samples.
    """

    name = "nonlinear_mpsc"
    is_jax = False
    params = None

    def __init__(self, env, prior_params, opts: Options, plant_params=None):
        import casadi as cs

        from scg_algorithms.safety_filters.mpsc_linear import (
            ancillary_weights,
            mpsc_rows,
            terminal_set_fraction,
            terminal_steps,
        )

        self.options = opts
        self.system = env.system.name
        if self.system == "quadrotor_3d" and not opts.allow_quadrotor_3d:
            raise ValueError(QUADROTOR_3D_REFUSAL)
        nx, nu, H = self.nx, self.nu, self.horizon = env.nx, env.nu, opts.horizon
        if opts.sample_half_width is not None and len(opts.sample_half_width) != nx:
            raise ValueError(f"{PATH}.sample_half_width: expected {nx} values, got {len(opts.sample_half_width)}")
        model = setup.prior_model(env, prior_params, opts.discretization)
        self.x_goal = np.asarray(prior_params.goal, dtype=np.float64).reshape(nx)
        self.u_eq = setup.equilibrium_input(env, prior_params)
        Ad, Bd, c = (a[0] for a in setup.linearize_along(model, self.x_goal[None], self.u_eq))
        rows, self.u_low, self.u_high = mpsc_rows(env, prior_params, PATH)
        self.rows = rows
        stages = self.stages = H + terminal_steps(env, opts)

        self.bias = np.zeros(nx)
        self.errors = np.zeros((0, nx))
        mean = np.zeros(nx)
        if opts.tightening != "none" or opts.model_bias:
            plant = env.default_params if plant_params is None else plant_params
            x, u, x_next = tight.sample_transitions(
                env, plant, opts.n_samples, opts.sample_seed, opts.sample_half_width, opts.plant_draws
            )
            predicted = np.asarray(model.fd.map(x.shape[0])(x.T, u.T), dtype=np.float64).T
            self.errors = x_next - predicted
            mean = self.errors.mean(axis=0)
            if opts.model_bias:
                self.bias = mean
        weights = ancillary_weights(env, prior_params, rows, self.x_goal, opts, PATH)
        quantiles = tight.error_quantiles(opts.error_quantile) if opts.tightening == "reachable" else (1.0,)
        candidates, reason = [], None
        for quantile in quantiles:  # the largest error bound whose tube leaves room (as the linear MPSC's)
            for q, r in weights:
                try:
                    K, _ = discrete_lqr_gain(Ad, Bd, np.diag(q), np.diag(r))
                except ValueError as error:
                    raise ValueError(f"{PATH}.q_lqr: the ancillary LQR has no stabilising solution ({error})") from None
                margins = np.zeros((stages, rows.num_rows))
                if opts.tightening == "reachable":
                    _, w_bar = tight.error_box(self.errors, quantile)
                    if not opts.model_bias:  # without the bias in the model, the bound must cover the mean too
                        w_bar = w_bar + np.abs(mean)
                    margins = tight.reachable_tightening(rows.Ax, rows.Au, K, Ad - Bd @ K, w_bar, stages)
                    margins[H:] = margins[H - 1]  # the terminal tail keeps the last free stage's tightening
                margins = margins + opts.constraint_margin * rows.soft[None, :]
                reason = tight.tube_room(rows, margins, self.x_goal, self.u_eq)
                if reason is None:
                    candidates.append((K, margins))
            if candidates:
                self.error_quantile = quantile
                break
        if not candidates:
            raise ValueError(
                f"{PATH}.tightening: {reason}; lower the model error (sample_half_width, plant_draws, a better "
                "prior) or give a smaller error_quantile"
            )
        if len(candidates) > 1:  # keep the ancillary LQR whose terminal set holds the most sampled states
            states = validation_states(env, prior_params, 2000, jax.random.key(1))
            held = [
                terminal_set_fraction(states, Ad, Bd, c + self.bias, K, self.x_goal, self.u_eq, rows, m[H:])
                for K, m in candidates
            ]
            self.K, self.margins = candidates[int(np.argmax(held))]
        else:
            self.K, self.margins = candidates[0]
        self._tail = (Ad, Bd, c + self.bias)

        opti = cs.Opti()
        X = opti.variable(nx, H + 1)
        U = opti.variable(nu, H)
        x0 = opti.parameter(nx)
        u_l = opti.parameter(nu)
        K = cs.DM(self.K)
        goal, u_eq, bias = cs.DM(self.x_goal), cs.DM(self.u_eq), cs.DM(self.bias)
        opti.subject_to(X[:, 0] == x0)
        cost = 0.5 * cs.sumsqr(U[:, 0] - u_l)
        Ax, Au = cs.DM(rows.Ax), cs.DM(rows.Au)
        # The rows on the state are soft at the exact-penalty price violation_penalty (as the linear MPSC's): where
        # a plan holds every row the solution is the hard problem's (the price exceeds every multiplier), elsewhere
        # IPOPT returns the least-violating plan instead of failing. One slack per state row and stage, one for the
        # whole tail (its largest violation); a plan is certified only with every row held (``solve``).
        soft = opts.violation_penalty > 0
        state_rows = np.flatnonzero(np.any(rows.Ax != 0.0, axis=1)) if soft else np.zeros(0, int)
        select = cs.DM(np.eye(rows.num_rows)[:, state_rows])
        slack = opti.variable(state_rows.size, H) if state_rows.size else None
        tail_slack = opti.variable() if soft and self.stages > H else 0.0
        for j in range(H):
            opti.subject_to(X[:, j + 1] == model.fd(X[:, j], U[:, j]) + bias)
            bound = cs.DM(rows.b - self.margins[j]) + (select @ slack[:, j] if slack is not None else 0.0)
            opti.subject_to(Ax @ X[:, j + 1] + Au @ U[:, j] <= bound)
            if j >= 1:  # v_0 is left alone so that a safe proposal is the exact optimum
                cost += 0.5 * opts.regularization * cs.sumsqr(U[:, j] - u_eq + K @ (X[:, j] - goal))
        if slack is not None:
            opti.subject_to(cs.vec(slack) >= 0)
            cost += opts.violation_penalty * cs.sum1(cs.vec(slack))
        # The terminal set: from X_H the ancillary LQR on the linearised model keeps the rows over the tail. The NLP
        # holds only the tail rows that the others do not imply (mpsc_structured.nonredundant_rows, exact: the same
        # set; the 2D quadrotor's 1,800 tail rows made IPOPT's iterations about 4x dearer), and ``solve`` checks
        # every tail row after the solve. Both in the rows' own units (m, rad, N).
        self.tail_all = tail_rows_of(self._tail, self.K, self.x_goal, self.u_eq, rows, self.margins, H, PATH, False)
        self.tail_imposed = self.tail_all  # (F (k, nx), high (k,)): F X_H - high <= tail slack
        if self.stages > H:
            F, high = self.tail_all
            norms = np.linalg.norm(F, axis=1)
            free = (np.full(nx, -np.inf), np.full(nx, np.inf))
            kept = nonredundant_rows(F / norms[:, None], high / norms, self.x_goal, free, np.inf)
            F, high = self.tail_imposed = F[kept], high[kept]
            if F.shape[0]:
                opti.subject_to(cs.DM(F) @ X[:, H] - cs.DM(high) <= tail_slack)
            if soft:
                opti.subject_to(tail_slack >= 0)
                cost += opts.violation_penalty * tail_slack
        opti.minimize(cost)
        ipopt = {"print_level": 0, "sb": "yes", "max_iter": opts.max_iter, "tol": opts.tol}
        opti.solver("ipopt", {"print_time": False, "error_on_fail": False, "expand": True}, ipopt)
        # One Function built once: Opti.solve() rebuilds its solver on every call (about 1 s on a small CPU).
        self._solve = opti.to_function("nonlinear_mpsc", [x0, u_l, X, U], [X, U])
        self._residual = cs.Function(
            "residual",
            [x0, X, U],
            [
                cs.vertcat(
                    cs.vec(X[:, 0] - x0), *[cs.vec(X[:, j + 1] - model.fd(X[:, j], U[:, j]) - bias) for j in range(H)]
                )
            ],
        ).expand()

    def reset(self, key):
        """No plan yet: ``kinf = H`` (a failure at the first step falls back to the LQR)."""
        return {"x_plan": None, "u_plan": None, "kinf": self.horizon, "guess": None}

    def solve(self, x, u_uncertified, x_guess=None, u_guess=None):
        """``(X (H+1, nx), U (H, nu), success)`` of the NLP from ``x`` (nx,) for ``u_uncertified`` (nu,):
        ``success`` when the plan is certified (dynamics met, every row held)."""
        X, U, success, _ = self.solve_soft(x, u_uncertified, x_guess, u_guess)
        return X, U, success

    def solve_soft(self, x, u_uncertified, x_guess=None, u_guess=None):
        """``(X, U, success, usable)`` as ``solve``; ``usable``: the plan is finite and meets the dynamics (with soft
        rows, the least-violating plan where ``success`` is False)."""
        if x_guess is None:
            x_guess, u_guess = np.tile(x, (self.horizon + 1, 1)), np.tile(self.u_eq, (self.horizon, 1))
        with deferred_interrupt():  # a Ctrl-C here would be caught by CasADi and read as a failed solve
            X, U = self._solve(x, u_uncertified, x_guess.T, u_guess.T)
        X = np.asarray(X, dtype=np.float64).reshape(self.nx, -1).T
        U = np.asarray(U, dtype=np.float64).reshape(self.nu, -1).T
        # Success from the solution itself (the Function hides IPOPT's status): finite, dynamics met, rows held.
        if not (np.all(np.isfinite(X)) and np.all(np.isfinite(U))):
            return X, U, False, False
        dynamics = np.abs(np.asarray(self._residual(x, X.T, U.T))).max()
        rows = X[1:] @ self.rows.Ax.T + U @ self.rows.Au.T - (self.rows.b - self.margins[: self.horizon])
        F_tail, high_tail = self.tail_all
        tail = F_tail @ X[-1] - high_tail
        excess = max(rows.max(), tail.max(initial=-np.inf))
        usable = bool(dynamics <= FEASIBILITY_TOL)
        return X, U, usable and bool(excess <= FEASIBILITY_TOL), usable

    def certify(self, x_or_obs, u_uncertified, filter_params, filter_state):
        obs = np.asarray(x_or_obs, dtype=np.float64)
        u_unc = np.asarray(u_uncertified, dtype=np.float64).reshape(-1)
        if obs.ndim != 1 or obs.shape[0] < self.nx or u_unc.shape != (self.nu,):
            raise ValueError(
                f"nonlinear_mpsc: built for {self.system} (state of {self.nx} entries, input of {self.nu}); got an "
                f"observation of shape {obs.shape} and an input of shape {u_unc.shape} (one copy)"
            )
        u_l = np.clip(u_unc, self.u_low, self.u_high)
        x = obs[: self.nx]
        H = self.horizon
        x_guess = u_guess = None
        if self.options.warm_start and filter_state.get("guess") is not None:
            X_last, U_last = filter_state["guess"]  # the last usable plan (certified or least-violating), shifted
            x_guess = np.concatenate([X_last[1:], X_last[-1:]])
            x_guess[0] = x
            u_guess = np.concatenate([U_last[1:], U_last[-1:]])
        X, U, success, usable = self.solve_soft(x, u_l, x_guess, u_guess)
        applied = CERTIFIED
        if success:
            u = U[0]
            state = {"x_plan": X, "u_plan": U, "kinf": 0, "guess": (X, U)}
        else:
            kinf = min(filter_state["kinf"] + 1, H)
            if kinf < H and filter_state["x_plan"] is not None:
                u = filter_state["u_plan"][kinf] - self.K @ (x - filter_state["x_plan"][kinf])
                applied = BACKUP_PLAN
            else:  # no certified plan left: the least-violating plan's first input, or the LQR
                soft = usable and self.options.violation_penalty > 0
                u = U[0] if soft else self.u_eq - self.K @ (x - self.x_goal)
                applied = BACKUP_CONTROLLER
            state = {**filter_state, "kinf": kinf, "guess": (X, U) if usable else None}
        u = np.clip(u, self.u_low, self.u_high)
        correction = applied_correction(u, u_unc, self.u_low, self.u_high, np)
        return u, state, FilterInfo(feasible=success, slack=0.0, correction=correction, applied=applied)


def make_nonlinear_mpsc(env, prior_params, options=None, plant_params=None) -> NonlinearMPSC:
    """The nonlinear MPSC (see the module docstring).

    Args:
        env: the environment (with linear state constraints). prior_params: ``EnvParams`` of the filter's model.
        options: ``Options`` mapping (``safety_filters.nonlinear_mpsc``). plant_params: the plant the model-error
            samples come from (default ``env.default_params``).

    Raises:
        ValueError: naming ``safety_filters.nonlinear_mpsc.<field>`` for a bad option.
    """
    return NonlinearMPSC(env, prior_params, parse_options(Options, options, PATH), plant_params)


__all__ = ["Options", "NonlinearMPSC", "PATH", "QUADROTOR_3D_REFUSAL", "TIGHTENINGS", "make_nonlinear_mpsc"]
