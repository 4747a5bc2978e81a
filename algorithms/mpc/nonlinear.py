"""Nonlinear MPC with CasADi ``Opti`` and IPOPT: the host-side baseline of the original suite.

At every control step ``k`` the controller solves, from the observed state ``x_hat``,

    min   sum_{i=0}^{H-1} [ (x_i - r_i)^T Q (x_i - r_i) + (u_i - u_eq)^T R (u_i - u_eq) ]
          + (x_H - r_H)^T P (x_H - r_H)  [+ soft_penalty * sum (s + s^2)]
    s.t.  x_0 = x_hat,   x_{i+1} = f_d(x_i, u_i),   u_low <= u_i <= u_high,
          g(x_{i+1}, u_i) + margin <= 0            (hard)   or   <= s_i, s_i >= 0   (soft)

with ``r_i = x_ref[min(k + i, num_steps)]`` (the task reference passed to ``act``, clamped past its end), ``u_eq``
the prior model's equilibrium input (hover thrust, zero force; never the true plant's ``reference.u_ref``), ``f_d``
one RK4 step of the prior model over the control period (``discretization="rk4"``, the default) or the env's own
integrator and substeps (``"env"``: exact to the plant's discretisation but a larger expression, slower), and
``g`` the env's constraints with the prior's values (``SymbolicModel.g``). The constraints are imposed on
``(x_{i+1}, u_i)``, the pairs the env itself evaluates after step ``i`` (the state reached and the input
commanded), so a plan the solver finds feasible is one the env counts as feasible; the measured ``x_0`` carries no
constraint (nothing can change it, and imposing one would make the problem infeasible whenever noise puts the
measurement just outside). The first input of the plan is applied (clipped to the actuator limits, which the
solver already enforces, against round-off).

Terminal weight ``P`` (``terminal_weight="dare"``, default): the solution of the discrete algebraic Riccati
equation of the prior model linearised about ``(goal, u_eq)`` with the stage weights, i.e. the infinite-horizon
cost-to-go of the unconstrained linearisation. Near the goal the finite-horizon problem then equals the
infinite-horizon one (the classical argument for nominal stability of MPC), and short horizons do not shorten the
controller's foresight as much as ``P = Q`` (``"stage"``, the original suite's choice) does. The quadrotor's
linearisation about hover is the same at every position, so the same ``P`` serves the whole circle.

The ``Opti`` problem is built once (parameters: the initial state and the reference window); its NLP
(``opti.x``, ``opti.p``, ``opti.f``, ``opti.g``) is handed to ``nlpsol("ipopt")`` with ``expand=True`` (SX
evaluation, several times faster than MX), so every step is one solver call with the warm start passed as
arguments, its statistics available and no exception on failure.

Warm start (``warm_start="primal_dual"``, default): the previous plan shifted by one step (the last state
propagated through ``f_d`` with the last input repeated, the first state replaced by the measurement) and the
constraint multipliers shifted the same way, with IPOPT's ``warm_start_init_point`` and a small initial barrier
parameter (``warm_mu_init``). ``"primal"`` passes the shifted plan only (IPOPT starts from its default barrier
parameter); ``"none"`` solves every step cold. On the 2D quadrotor tracking a 0.5 m circle in 3 s (horizon 15,
40 steps) they take 5.8, 7.3 and 8.3 IPOPT iterations per step, with the same inputs to 1e-5 N. At
``reset`` there is no plan: the first step starts from the equilibrium input and the measured state held
constant over the horizon, with the default barrier parameter.

Failure (IPOPT reports anything but success, e.g. an infeasible hard constraint or ``max_iter``): the input comes
from, in order, (1) the last iterate when it is finite and its constraint violation is at most ``fallback_tol``
(as ``opti.debug.value`` would give); (2) the shifted previous plan when one exists; (3) the last iterate when it
is finite (IPOPT's restoration phase ends at a least-infeasible point); (4) the equilibrium input. The choice is
counted in the controller state (``num_failures``, ``fallbacks``), and the input is always finite.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import signal
import threading
import time
from collections.abc import Iterator
from typing import NamedTuple

import casadi as cs
import numpy as np

from scg_algorithms import controller_setup as setup
from scg_algorithms.base import option, parse_options, positive, state_from_obs

PATH = "controllers.nonlinear_mpc"
SOURCES = ("solution", "last_iterate", "shifted_plan", "equilibrium")
SOLVERS = ("ipopt", "sqp", "sqp_rti")
QP_SOLVERS = ("admm", "ipm")


def _vector(dm) -> np.ndarray:
    """A dense CasADi column as a flat float64 array (``nonzeros`` is the quickest way out of a DM)."""
    return np.array(dm.nonzeros(), dtype=np.float64)


def _numpy(dm) -> np.ndarray:
    """A CasADi matrix (possibly sparse) as a dense float64 array."""
    return np.asarray(cs.DM(dm).full(), dtype=np.float64)


@dataclasses.dataclass(frozen=True)
class Options(setup.MPCOptions):
    """Options of the nonlinear MPC (a config file's ``controllers.nonlinear_mpc`` section)."""

    terminal_weight: str = setup.terminal_weight_option()
    discretization: str = setup.discretization_option("rk4")
    soft_constraints: bool = option(False, "soften the env's constraints with slack variables >= 0")
    soft_penalty: float = option(1e3, "weight of the slack penalty sum(s + s^2) (soft_constraints)")
    constraint_margin: float = option(
        1e-6, "the env's constraints are imposed as g <= -margin, so solver round-off never counts as a violation"
    )
    warm_start: str = option(
        "primal_dual",
        "warm start from the shifted previous solution: primal_dual, primal (plan only), none (cold every step)",
        choices=("primal_dual", "primal", "none"),
    )
    warm_mu_init: float = option(1e-4, "IPOPT's initial barrier parameter when warm starting primal and dual")
    max_iter: int = option(100, "IPOPT iteration limit per step")
    tol: float = option(1e-6, "IPOPT convergence tolerance")
    fallback_tol: float = option(
        1e-4,
        "largest constraint violation of IPOPT's last iterate accepted after a failed solve (sqp, sqp_rti: of a QP's "
        "plan, or more where the plan kept instead violates more)",
    )
    solver: str = option(
        "ipopt",
        "ipopt (CasADi, host, one copy: the reference), sqp (JAX, iterated to convergence) or sqp_rti (JAX, one "
        "QP per step about the shifted plan); see scg_algorithms.mpc.sqp",
        choices=SOLVERS,
    )
    sqp_max_iter: int = option(20, "sqp: SQP iterations at most per step (sqp_rti: at its first step)")
    sqp_tol: float = option(1e-6, "sqp: stop when no input of the plan moves by more than this, N")
    qp_max_iter: int = option(200, "sqp, sqp_rti: ADMM iterations at most per QP")
    qp_tol: float = option(1e-5, "sqp, sqp_rti: the QP's residual tolerance (scg_algorithms.mpc.structured)")
    # 3 rounds left the 3D quadrotor's SQP-RTI at 1.18x IPOPT's RMSE (the benchmark's 2 episodes), 6 at 1.0000, for
    # 1.13x the time per step; the rounds stop once every copy of a batch has an accepted polish.
    qp_polish_rounds: int = option(
        6, "sqp, sqp_rti: rounds of the QP's active-set polish after its ADMM, at most (0: none)"
    )
    merit_weight: float = option(1e4, "sqp, sqp_rti: weight of the l1 constraint violation in the line search's merit")
    # admm: scg_algorithms.mpc.structured, warm-started; ipm: scg_algorithms.mpc.interior_point, hard rows only.
    qp_solver: str = option("admm", "sqp, sqp_rti: the QP solver, admm or ipm (Riccati steps)", choices=QP_SOLVERS)
    ipm_max_iter: int = option(15, "qp_solver ipm: interior-point iterations at most per QP")
    ipm_polish_rounds: int = option(3, "qp_solver ipm: rounds of its active-set polish (0: none)")
    ipm_refinement_steps: int = option(1, "qp_solver ipm: steps of iterative refinement of each Newton step")

    def _check(self, path: str) -> None:
        positive(f"{path}.horizon", self.horizon)
        positive(f"{path}.max_iter", self.max_iter)
        positive(f"{path}.tol", self.tol)
        positive(f"{path}.warm_mu_init", self.warm_mu_init)
        positive(f"{path}.soft_penalty", self.soft_penalty)
        positive(f"{path}.fallback_tol", self.fallback_tol)
        for name in ("sqp_max_iter", "qp_max_iter", "sqp_tol", "merit_weight", "ipm_max_iter"):
            positive(f"{path}.{name}", getattr(self, name))
        for name in ("qp_tol", "qp_polish_rounds", "ipm_polish_rounds", "ipm_refinement_steps"):
            if getattr(self, name) < 0:
                raise ValueError(f"{path}.{name}: must be >= 0, got {getattr(self, name)!r}")
        if self.constraint_margin < 0:
            raise ValueError(f"{path}.constraint_margin: must be >= 0, got {self.constraint_margin!r}")
        if self.qp_solver == "ipm" and self.soft_constraints:
            raise ValueError(
                f"{path}.soft_constraints: qp_solver ipm takes hard rows only; use qp_solver admm for soft constraints"
            )


@contextlib.contextmanager
def deferred_interrupt() -> Iterator[None]:
    """Hold a Ctrl-C that arrives during the block (a CasADi solve) and raise it as ``KeyboardInterrupt`` after.

    CasADi checks for Ctrl-C between IPOPT's iterations and function evaluations; it catches the
    ``KeyboardInterrupt``, logs a warning on stderr and stops the solver as if the solve had failed, and a host-side
    evaluation would take its fallback and go on. In the main thread, with Python's default handler in place, the
    block runs with a handler that only records the signal, so the solve finishes (milliseconds) and the interrupt
    is raised once it returns; elsewhere the block runs as it is (``raise_if_interrupted`` then catches IPOPT's stop).
    """
    if threading.current_thread() is not threading.main_thread() or (
        signal.getsignal(signal.SIGINT) is not signal.default_int_handler
    ):
        yield
        return
    received = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: received.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if received:
        raise KeyboardInterrupt


def raise_if_interrupted(stats: dict) -> None:
    """Raise the ``KeyboardInterrupt`` of a Ctrl-C that CasADi caught during an IPOPT solve (outside
    ``deferred_interrupt``'s reach): CasADi logs a warning and stops IPOPT with ``User_Requested_Stop``, which reads
    like any failed solve.

    Args:
        stats: the solver's ``stats()`` after the call.

    Raises:
        KeyboardInterrupt: the solve was stopped by Ctrl-C.
    """
    if stats.get("return_status") == "User_Requested_Stop":
        raise KeyboardInterrupt


class NMPCState(NamedTuple):
    """The memory of one copy (numpy; a new tuple every step).

    Attributes:
        x_plan: (H + 1, nx) the plan of the last step (``x_plan[0]`` the state it started from), or ``None``.
        u_plan: (H, nu) its inputs, N, or ``None``.
        lam_g: (ng,) the constraint multipliers of the last successful solve, or ``None``.
        plan_step: the control step the plan was made at (-1: none).
        solve_time_s: per ``act`` call, the wall time of the IPOPT call (s).
        iterations: per ``act`` call, IPOPT's iteration count.
        sources: per ``act`` call, where the input came from (``SOURCES``).
        statuses: per ``act`` call, IPOPT's return status.
        num_failures: steps at which IPOPT did not report success.
        fallbacks: ``{source: count}`` of the fallbacks taken (all sources but ``"solution"``).
    """

    x_plan: np.ndarray | None
    u_plan: np.ndarray | None
    lam_g: np.ndarray | None
    plan_step: int
    solve_time_s: tuple
    iterations: tuple
    sources: tuple
    statuses: tuple
    num_failures: int
    fallbacks: dict


class Solution(NamedTuple):
    """One solver call: the plan, the slacks, the multipliers and IPOPT's report."""

    x: np.ndarray  # (H + 1, nx)
    u: np.ndarray  # (H, nu)
    slack: np.ndarray  # (H, ng_env) with soft constraints, (H, 0) without
    lam_g: np.ndarray  # (ng,)
    success: bool
    status: str
    iterations: int
    max_violation: float  # largest violation of the NLP's constraints at the returned point
    wall_time_s: float


class NonlinearMPC:
    """Host controller (``is_jax = False``); build it with ``make_nonlinear_mpc``.

    Attributes:
        name, is_jax: the controller protocol. options: the parsed ``Options``.
        model: the prediction ``SymbolicModel`` (``fd`` is the model used in the NLP, ``g`` the constraints).
        Q, R, P: (nx, nx), (nu, nu), (nx, nx) stage and terminal weights.
        u_eq: (nu,) equilibrium input of the prior, N. u_low, u_high: (nu,) actuator limits of the prior, N.
        horizon: H.
    """

    name = "nonlinear_mpc"
    is_jax = False

    def __init__(self, env, prior_params, opts: Options, prediction_model=None, tightened: bool = False):
        """See ``make_nonlinear_mpc``. Variants (GP-MPC) pass ``prediction_model``, a CasADi ``Function``
        ``(x, u) -> x_next`` used instead of the prior's ``fd``, and ``tightened=True``, which adds a margin per
        constraint row and stage (``solve``'s ``margins``) to the env's constraints."""
        self.env = env
        self.options = opts
        self.horizon = H = opts.horizon
        self.model = model = setup.prior_model(env, prior_params, opts.discretization)
        self.fd = model.fd if prediction_model is None else prediction_model
        nx, nu = self.nx, self.nu = model.nx, model.nu
        # The full prior Q and R (or the options' diagonals), as every model-based controller here uses them.
        self.Q, self.R = Q, R = setup.cost_weights(
            env, prior_params, opts.q_diag, opts.r_diag, PATH, positive_definite_r=False
        )
        self.u_eq = setup.equilibrium_input(env, prior_params)
        self.u_low, self.u_high = setup.input_limits(env, prior_params)
        self.P = setup.terminal_weight(opts.terminal_weight, env, prior_params, model, Q, R, PATH)
        self.ng_env = ng_env = int(model.g.size1_out(0))

        # ---- the problem, built once
        opti = cs.Opti()
        X = opti.variable(nx, H + 1)
        U = opti.variable(nu, H)
        S = opti.variable(ng_env, H) if (opts.soft_constraints and ng_env) else None
        x_init = opti.parameter(nx)
        x_ref = opti.parameter(nx, H + 1)
        margin = opti.parameter(ng_env, H) if (tightened and ng_env) else None
        self.tightened = margin is not None
        cost = 0
        # Constraint order defines the multiplier layout used to shift the dual warm start: the initial-state rows,
        # then H blocks of identical size (dynamics, input bounds, env constraints, slack signs).
        opti.subject_to(X[:, 0] == x_init)
        for i in range(H):
            dx = X[:, i] - x_ref[:, i]
            du = U[:, i] - self.u_eq
            cost += cs.bilin(Q, dx, dx) + cs.bilin(R, du, du)
            opti.subject_to(X[:, i + 1] == self.fd(X[:, i], U[:, i]))
            opti.subject_to(opti.bounded(self.u_low, U[:, i], self.u_high))
            if ng_env:
                rows = model.g(X[:, i + 1], U[:, i]) + opts.constraint_margin
                if margin is not None:
                    rows = rows + margin[:, i]
                if S is None:
                    opti.subject_to(rows <= 0)
                else:
                    opti.subject_to(rows - S[:, i] <= 0)
                    opti.subject_to(S[:, i] >= 0)
                    cost += opts.soft_penalty * (cs.sum1(S[:, i]) + cs.sumsqr(S[:, i]))
        dx = X[:, H] - x_ref[:, H]
        cost += cs.bilin(self.P, dx, dx)
        opti.minimize(cost)
        self.opti = opti
        self.ng = int(opti.ng)
        self.block = (self.ng - nx) // H
        if nx + H * self.block != self.ng:  # the layout assumption above, checked once
            raise RuntimeError(f"nonlinear_mpc: unexpected constraint layout ({self.ng} rows)")

        # Where each entry of X, U, S and of the parameters sits in the NLP's vectors, found once by pushing
        # position codes through the (linear) packing, so each step packs and unpacks with numpy indexing.
        slack = S if S is not None else cs.MX(ng_env, H)
        unpack = cs.Function("unpack", [opti.x], [X, U, slack])
        index_x, index_u, index_s = (np.asarray(a, dtype=float) for a in unpack(np.arange(opti.nx)))
        self._index_x = index_x.T.round().astype(int)  # (H + 1, nx)
        self._index_u = index_u.T.round().astype(int)  # (H, nu)
        self._index_s = index_s.T.round().astype(int) if S is not None else None  # (H, ng_env)
        self._nz = int(opti.nx)
        codes_x0 = np.arange(nx, dtype=float)
        codes_ref = nx + np.arange(nx * (H + 1), dtype=float).reshape(H + 1, nx)
        if margin is None:
            codes = np.asarray(cs.Function("pack_p", [x_init, x_ref], [opti.p])(codes_x0, codes_ref.T))
        else:
            codes_margin = nx * (H + 2) + np.arange(ng_env * H, dtype=float).reshape(H, ng_env)
            pack_p = cs.Function("pack_p", [x_init, x_ref, margin], [opti.p])
            codes = np.asarray(pack_p(codes_x0, codes_ref.T, codes_margin.T))
        self._param_order = codes.ravel().round().astype(int)  # p = concatenate([x0, window, margins])[order]
        # Opti keeps the parameters that enter a constraint additively in its bounds (x_0 = x_init puts x_init
        # there), so the bounds are affine in p: stored as value at p = 0 plus a Jacobian, evaluated with numpy.
        bounds = cs.Function(
            "bounds", [opti.p], [opti.lbg, opti.ubg, cs.jacobian(opti.lbg, opti.p), cs.jacobian(opti.ubg, opti.p)]
        )
        self._lbg0, self._ubg0, self._lbg_p, self._ubg_p = (_numpy(a) for a in bounds(np.zeros(opti.np)))
        self._lbg0, self._ubg0 = self._lbg0.ravel(), self._ubg0.ravel()
        # Expanded to SX once and shared by both solvers (``expand=True`` on each would expand twice).
        nlp_fn = cs.Function("nlp", [opti.x, opti.p], [opti.f, opti.g]).expand()
        z_sym, p_sym = cs.SX.sym("z", opti.nx), cs.SX.sym("p", opti.np)
        f_sym, g_sym = nlp_fn(z_sym, p_sym)
        nlp = {"x": z_sym, "p": p_sym, "f": f_sym, "g": g_sym}
        ipopt = {
            "print_level": 0,
            "sb": "yes",
            "max_iter": opts.max_iter,
            "tol": opts.tol,
            "acceptable_tol": max(opts.tol, 1e-4),
        }
        base = {"print_time": False, "error_on_fail": False}
        self._solver_cold = cs.nlpsol("nmpc_cold", "ipopt", nlp, {**base, "ipopt": ipopt})
        if opts.warm_start == "primal_dual":
            warm = {
                **ipopt,
                "warm_start_init_point": "yes",
                "mu_init": opts.warm_mu_init,
                "warm_start_bound_push": 1e-6,
                "warm_start_slack_bound_push": 1e-6,
                "warm_start_mult_bound_push": 1e-6,
            }
            self._solver_warm = cs.nlpsol("nmpc_warm", "ipopt", nlp, {**base, "ipopt": warm})
        else:
            self._solver_warm = None

    # ------------------------------------------------------------------------------------------ pieces
    def reference_window(self, reference, step: int) -> np.ndarray:
        """``reference.x_ref[step : step + H + 1]`` (H + 1, nx), the last point repeated past the end."""
        x_ref = np.asarray(reference.x_ref, dtype=np.float64)
        index = np.minimum(np.arange(step, step + self.horizon + 1), x_ref.shape[0] - 1)
        return x_ref[index]

    def cold_guess(self, x0) -> tuple[np.ndarray, np.ndarray]:
        """The guess without a plan: ``x0`` held over the horizon and the equilibrium input."""
        x0 = np.asarray(x0, dtype=np.float64)
        return np.tile(x0, (self.horizon + 1, 1)), np.tile(self.u_eq, (self.horizon, 1))

    def shift(self, x_plan, u_plan, lam_g, shift: int, x0):
        """A plan moved ``shift`` >= 1 steps ahead: states and inputs past the end are continued with the last
        input held (states through ``fd``), multiplier blocks repeat the last one, and the first state is ``x0``."""
        H = self.horizon
        x = np.concatenate([x_plan[shift:], np.zeros((shift, self.nx))])
        u = np.concatenate([u_plan[shift:], np.repeat(u_plan[-1:], shift, axis=0)])
        for i in range(H + 1 - shift, H + 1):
            x[i] = _vector(self.fd(x[i - 1], u[i - 1]))
        x[0] = x0
        lam = None
        if lam_g is not None:
            blocks = lam_g[self.nx :].reshape(H, self.block)
            blocks = np.concatenate([blocks[shift:], np.repeat(blocks[-1:], shift, axis=0)])
            lam = np.concatenate([lam_g[: self.nx], blocks.ravel()])
        return x, u, lam

    def solve(self, x0, x_ref_window, x_guess, u_guess, lam_g=None, margins=None) -> Solution:
        """One NLP solve from ``x0`` (nx,) along ``x_ref_window`` (H + 1, nx), started from the guess
        ``x_guess`` (H + 1, nx), ``u_guess`` (H, nu) and, when given and ``warm_start="primal_dual"``, the
        multipliers ``lam_g`` (ng,) (then IPOPT warm-starts with a small barrier parameter). ``margins``
        (H, ng_env), for a ``tightened`` controller: added to each constraint row at each stage (default 0)."""
        x0 = np.asarray(x0, dtype=np.float64)
        parts = [x0, np.asarray(x_ref_window, dtype=np.float64).ravel()]
        if self.tightened:
            parts.append(np.zeros(self.horizon * self.ng_env) if margins is None else np.asarray(margins).ravel())
        p = np.concatenate(parts)[self._param_order]
        lbg = self._lbg0 + self._lbg_p @ p
        ubg = self._ubg0 + self._ubg_p @ p
        z0 = np.zeros(self._nz)
        z0[self._index_x] = x_guess
        z0[self._index_u] = u_guess
        if lam_g is not None and self._solver_warm is not None:
            solver, args = self._solver_warm, {"lam_g0": lam_g}
        else:
            solver, args = self._solver_cold, {}
        tick = time.perf_counter()
        with deferred_interrupt():
            out = solver(x0=z0, p=p, lbg=lbg, ubg=ubg, **args)
        wall = time.perf_counter() - tick
        stats = solver.stats()
        raise_if_interrupted(stats)
        z = _vector(out["x"])
        g = _vector(out["g"])
        violation = np.concatenate([lbg - g, g - ubg, [0.0]])
        max_violation = float(np.max(violation)) if np.all(np.isfinite(g)) else math.inf
        return Solution(
            x=z[self._index_x],
            u=z[self._index_u],
            slack=z[self._index_s] if self._index_s is not None else np.zeros((self.horizon, 0)),
            lam_g=_vector(out["lam_g"]),
            success=bool(stats.get("success", False)),
            status=str(stats.get("return_status", "unknown")),
            iterations=int(stats.get("iter_count", -1)),
            max_violation=max_violation,
            wall_time_s=wall,
        )

    def stage_margins(self, x_guess, u_guess):
        """Margins (H, ng_env) of a ``tightened`` variant for the plan about to be solved (here: none)."""
        return None

    # ------------------------------------------------------------------------------------------ protocol
    def reset(self, key, reference) -> NMPCState:
        """No plan yet; ``key`` and ``reference`` are unused (the controller is deterministic)."""
        return NMPCState(
            x_plan=None,
            u_plan=None,
            lam_g=None,
            plan_step=-1,
            solve_time_s=(),
            iterations=(),
            sources=(),
            statuses=(),
            num_failures=0,
            fallbacks={source: 0 for source in SOURCES[1:]},
        )

    def act(self, ctrl_state: NMPCState, obs, step, reference):
        """Solve from the observed state at control step ``step``; returns ``(u (nu,) N, new ctrl_state)``."""
        step = int(step)
        x0 = np.asarray(state_from_obs(self.env, np.asarray(obs, dtype=np.float64)), dtype=np.float64)
        window = self.reference_window(reference, step)
        shift = step - ctrl_state.plan_step
        have_plan = ctrl_state.x_plan is not None and 1 <= shift <= self.horizon
        lam = None
        if have_plan and self.options.warm_start != "none":
            x_guess, u_guess, lam = self.shift(ctrl_state.x_plan, ctrl_state.u_plan, ctrl_state.lam_g, shift, x0)
        else:
            x_guess, u_guess = self.cold_guess(x0)
        lam = lam if self.options.warm_start == "primal_dual" else None
        sol = self.solve(x0, window, x_guess, u_guess, lam, self.stage_margins(x_guess, u_guess))

        finite = bool(np.all(np.isfinite(sol.x)) and np.all(np.isfinite(sol.u)))
        lam_next = None
        if sol.success and finite:
            source, x_plan, u_plan = "solution", sol.x, sol.u
            lam_next = sol.lam_g if np.all(np.isfinite(sol.lam_g)) else None
        elif finite and sol.max_violation <= self.options.fallback_tol:
            source, x_plan, u_plan = "last_iterate", sol.x, sol.u
        elif have_plan:
            x_plan, u_plan, _ = self.shift(ctrl_state.x_plan, ctrl_state.u_plan, None, shift, x0)
            source = "shifted_plan"
        elif finite:
            source, x_plan, u_plan = "last_iterate", sol.x, sol.u
        else:
            source = "equilibrium"
            x_plan, u_plan = self.cold_guess(x0)
        u = np.clip(u_plan[0], self.u_low, self.u_high)
        if not np.all(np.isfinite(u)):  # a non-finite shifted plan (it can only come from an earlier last iterate)
            source, u = "equilibrium", np.clip(self.u_eq, self.u_low, self.u_high)
            x_plan, u_plan = self.cold_guess(x0)
        fallbacks = dict(ctrl_state.fallbacks)
        if source != "solution":
            fallbacks[source] += 1
        new_state = NMPCState(
            x_plan=x_plan,
            u_plan=u_plan,
            lam_g=lam_next,
            plan_step=step,
            solve_time_s=ctrl_state.solve_time_s + (sol.wall_time_s,),
            iterations=ctrl_state.iterations + (sol.iterations,),
            sources=ctrl_state.sources + (source,),
            statuses=ctrl_state.statuses + (sol.status,),
            num_failures=ctrl_state.num_failures + (not sol.success),
            fallbacks=fallbacks,
        )
        return u, new_state

    @property
    def info(self) -> dict:
        """Static facts for reports."""
        return {
            "horizon": self.horizon,
            "discretization": self.options.discretization,
            "terminal_weight": self.options.terminal_weight,
            "soft_constraints": self.options.soft_constraints,
            "num_constraint_rows": self.ng,
            "P": self.P,
        }


def make_nonlinear_mpc(env, prior_params, options=None) -> NonlinearMPC:
    """Nonlinear MPC on the prior model ``env.symbolic_model(prior_params)`` solved by IPOPT (see the module doc).

    Args:
        env: the environment. prior_params: unbatched ``EnvParams`` of the controller's model (e.g.
            ``prior_params(env, params, 1.5)``): its physics, its ``Q``/``R`` (default weights), its ``goal`` (the
            terminal weight's linearisation point) and its constraint values. options: ``Options`` fields as a
            mapping (a config file's ``controllers.nonlinear_mpc``).

    Returns:
        With ``solver="ipopt"`` (default), a ``NonlinearMPC`` host controller; its state (``NMPCState``) records the
        IPOPT wall time, iterations and status of every step, and the fallbacks taken. With ``"sqp"`` or
        ``"sqp_rti"``, a ``JaxController`` (``scg_algorithms.mpc.sqp.make_sqp_mpc``) for the jitted, batched loop.

    Raises:
        ValueError: naming ``controllers.nonlinear_mpc.<field>`` for a bad option.
    """
    opts = parse_options(Options, options, PATH)
    if opts.solver != "ipopt":
        from scg_algorithms.mpc.sqp import make_sqp_mpc

        return make_sqp_mpc(env, prior_params, opts)
    return NonlinearMPC(env, prior_params, opts)
