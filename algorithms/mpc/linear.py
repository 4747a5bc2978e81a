"""Linear MPC: the prior model linearised once on the host, a condensed QP per step, the first input applied.

Two controllers share one ``Options`` dataclass (a config file's ``controllers.linear_mpc`` and
``controllers.linear_mpc_casadi`` sections; the qpax fields are ignored by the CasADi one):

- ``make_linear_mpc`` (registered ``"linear_mpc"``): a ``JaxController`` whose ``act`` solves the QP with the
  structured horizon-QP solver (``scg_algorithms.mpc.structured``, prepared once on the host when the model is the
  same at every stage): Goldfarb and Idnani's dual active-set method from the unconstrained minimiser
  (``solver="active_set"``: hard rows and a prepared model only) or the ADMM, warm-started from the previous step's
  shifted plan (``solver="admm"``); the default ``"auto"`` takes the active set where it applies, else the ADMM.
  Or with the interior point on the same problem (``solver="ipm"``: ``scg_algorithms.mpc.interior_point``, hard
  rows only), or
  forms the right-hand side of the condensed QP of ``scg_algorithms.mpc.qp`` and solves it with ``qpax``
  (``solver="qpax"``, a primal-dual interior-point method in JAX); ``jax.vmap`` runs thousands of copies at once.
- ``make_linear_mpc_casadi`` (registered ``"linear_mpc_casadi"``): the same problem for one copy on the host in the
  form of ``casadi.Opti("conic")`` (inputs as the only variables, states as expressions of them; no
  pre-stabilisation) with qpOASES (default) or OSQP; the constraints are the symbolic model's own ``g`` functions.
  It is the reference the tests hold the JAX controller to.

Problem at control step ``k`` (observed state ``x_0``, reference ``r_j = x_ref[min(k + j, T)]``)::

    min  1/2 sum_{j=1}^{H-1} |x_j - r_j|_Q^2 + 1/2 |x_H - r_H|_P^2 + 1/2 sum_{j=0}^{H-1} |u_j - u_eq|_R^2
    s.t. x_{j+1} = Ad_j x_j + Bd_j u_j + c_j                     (prior model linearised, see below)
         u_low <= u_j <= u_high                                  (actuator limits of the prior physics, hard)
         g(x_{j+1}, u_j) <= 0  for the env's linear constraints  (input-only rows hard; rows on the state
                                                                  optionally softened, see ``soft_constraints``)

- **Model**: ``env.symbolic_model(prior_params)`` (the env's integrator and substeps, or one RK4 step with
  ``discretization="rk4"``) linearised with its ``dfd`` about ``(x_bar, u_eq)``: the goal (one model) or every
  reference point (``linearize_about="reference"``; stage ``j`` of step ``k`` uses point ``min(k + j, T)``), with
  the affine offset ``c = fd(x_bar, u_eq) - Ad x_bar - Bd u_eq``, so a moving reference is predicted exactly
  where the model is linear. ``u_eq`` is the prior's equilibrium input (hover thrust, zero force).
- **Terminal weight**: ``P`` of the discrete Riccati equation (``scg_algorithms.lqr.discrete_lqr_gain``) at the
  point of stage ``H``, so without active constraints the first input is the LQR input
  ``u_eq - K (x_0 - x_ref[k])`` for any horizon (the tests check this).
- **Constraints**: ``bounded``, ``abs_bound``, ``linear`` and ``default`` constraints (all stored as ``A z - b``)
  on the state, the input or both, with the values in ``prior_params.constraints``; rows identical to an actuator
  limit are dropped. ``quadratic`` constraints are not imposed (a linear MPC cannot hold them without a convex
  reformulation); their indices are listed in ``controller.info["skipped_constraints"]``. The env counts a row as
  violated when ``g > tolerance``; the MPC imposes ``g <= 0``.
- **Soft constraints** (``soft_constraints=True``): every row that involves the state gets a slack ``e >= 0``,
  one shared by all stages (default: the row's worst violation over the horizon) or one per stage
  (``slack_per_stage=True``; see ``scg_algorithms.mpc.qp`` for how the two behave), at the cost
  ``slack_l1 * e + 1/2 slack_l2 * e^2`` per slack, so the QP stays feasible when the plant is already outside
  or cannot avoid leaving the constraint set; input rows stay hard.
- **Failure handling** (JAX): every solve is checked (status in ``ctrl_state``; ``scg_algorithms.mpc.structured``
  or ``scg_algorithms.mpc.qp``). A finite iterate feasible within ``feasibility_tol`` is used even if the solver
  did not report convergence (float32 limits the
  residual it can reach, see ``scg_algorithms.mpc.qp``); a non-finite or infeasible one (an infeasible QP: hard
  state constraints that cannot be met, or input rows that contradict the actuator limits) is replaced by the
  LQR input ``u_eq - K (x_0 - x_ref[k])``. In every case the input is finally clipped to the box of the hard input
  rows (actuator limits and single-input constraint rows), so the output is never NaN and never commands outside
  the limits; general (non-box) input rows are only held by the QP. The CasADi controller does the same when
  its solver reports failure.

Controller memory (JAX): ``LinearMPCState(status, iterations, warm, plan_step)``: the last solve's status and
iterations, and with admm its warm start and the step it was made at.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, ClassVar, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from scg_algorithms import controller_setup as setup
from scg_algorithms.base import JaxController, option, parse_options, positive, state_from_obs
from scg_algorithms.lqr import discrete_lqr_gain
from scg_algorithms.mpc import interior_point, structured
from scg_algorithms.mpc import qp as qp_lib

LINEARIZE_ABOUT = setup.LINEARIZE_ABOUT
CASADI_SOLVERS = ("qpoases", "osqp")
SOLVERS = ("auto", "admm", "ipm", "qpax", "active_set")
PATH = "controllers.linear_mpc"
CASADI_PATH = "controllers.linear_mpc_casadi"


@dataclasses.dataclass(frozen=True)
class Options(setup.MPCOptions):
    """Options of the linear MPC (``controllers.linear_mpc``; ``controllers.linear_mpc_casadi`` has the same fields)."""

    terminal_weight: str = setup.terminal_weight_option()
    linearize_about: str = option(
        "auto",
        "linearise about the goal (one model) or every reference point (one per step); auto: goal for "
        "stabilization, reference for tracking",
        choices=LINEARIZE_ABOUT,
    )
    discretization: str = setup.discretization_option("env")
    env_constraints: bool = option(True, "impose the env's linear constraints (the actuator limits always hold)")
    soft_constraints: bool = option(False, "soften the constraint rows that involve the state with slacks >= 0")
    slack_per_stage: bool = option(
        False,
        "one slack per softened row and stage (the total violation costs); false: one per row shared by the "
        "horizon (its worst violation costs; H times fewer variables)",
    )
    slack_l1: float = option(1e3, "L1 weight of a slack in the objective J/2, cost per unit of violation")
    slack_l2: float = option(1e2, "L2 weight of a slack (1/2 slack_l2 e^2)")
    prestabilize: bool = option(
        True, "condense with the LQR-stabilised prediction (u = u_eq - K dx + v); off, float32 ADMM loses accuracy"
    )
    solver: str = option(
        "auto",
        "JAX QP solver: auto (active_set where the constraints are hard, the model is the same at every point and "
        "no admm_* or warm_start option is given, else admm), admm (scg_algorithms.mpc.structured: condensed "
        "OSQP-style ADMM, factorised once, warm started), ipm (scg_algorithms.mpc.interior_point: interior point "
        "with Riccati steps and an active-set polish; hard constraints only), qpax (dense interior point) or "
        "active_set (structured: Goldfarb and Idnani's dual active-set method on the condensed QP from its "
        "unconstrained minimiser; hard constraints and a model that is the same at every point only)",
        choices=SOLVERS,
    )
    active_set_max_steps: int = option(
        100, "active_set: steps at most per solve (a row joining or leaving the active set; most solves take 0-10)"
    )
    active_set_slots: int = option(
        8,
        "active_set: active rows held on the first try (a step's cost grows with their square); a solve whose set "
        "outgrows them is solved again with 4 times as many, up to every row it can hold",
    )
    admm_max_iter: int = option(1000, "admm: iterations at most per step (each copy stops when converged)")
    admm_tol: float = option(
        1e-5, "admm: absolute and relative residual tolerance on the scaled QP (0: always run admm_max_iter)"
    )
    admm_check_every: int = option(
        20,
        "admm: iterations between residual checks and step-size updates (a step size moved more often slows the "
        "ADMM: at 5, cold benchmark batches held by a slow copy ran up to 4x longer to the same plans)",
    )
    admm_polish_rounds: int = option(
        6,
        "admm: active-set polish rounds after the ADMM, at most (0: none; cheaper per step, less accurate at few "
        "iterations; a batch stops once every copy has an accepted round)",
    )
    admm_dual_active_set_steps: int = option(
        30,
        "admm: where the ADMM stopped at admm_max_iter and no polish round was accepted, at most this many steps "
        "of a dual active-set method (Goldfarb and Idnani), which cannot cycle where the rounds do (0: none)",
    )
    admm_adaptive_rho: bool = option(
        True,
        "admm: adapt the step size at the checks; false: keep the prepared one, whose products are folded once "
        "(one (rows x rows) product per iteration: the fastest iteration, for fixed iteration counts)",
    )
    admm_rho_scale: float = option(
        1.0,
        "admm: factor on the step size a cold solve starts from, the smallest generalised eigenvalue of the "
        "condensed Hessian and the rows' Gram matrix (with admm_adaptive_rho false: the step size throughout)",
    )
    admm_alpha: float = option(
        1.6,
        "admm: over-relaxation, in (0, 2) (OSQP's default 1.6; 1.9 with a fixed step size lets the cart-pole's cart "
        "box reach qpOASES's plans to 1e-3 N in 160 iterations, where 1.6 needs 200)",
    )
    warm_start: bool = option(True, "admm: start from the previous step's plan and multipliers, shifted")
    ipm_max_iter: int = option(
        15,
        "ipm: interior-point iterations at most per step (each copy stops when converged; a batch runs until its "
        "slowest copy stops, and one that has not converged by then seldom will in float32)",
    )
    ipm_tol: float = option(1e-6, "ipm: largest complementarity product (scaled) of a converged iterate")
    ipm_polish_rounds: int = option(3, "ipm: active-set polish rounds after the iterations (0: none)")
    max_iter: int = option(40, "qpax interior-point iterations at most (float32 solves rarely stop earlier)")
    solver_tol: float = option(
        1e-8, "qpax KKT residual tolerance (on the scaled QP; the default runs max_iter, see scg_algorithms.mpc.qp)"
    )
    feasibility_tol: float = option(
        1e-3, "largest constraint violation (row units: m, rad, N) of an unconverged iterate that is still used"
    )
    casadi_solver: str = option("qpoases", "conic solver of the CasADi variant", choices=CASADI_SOLVERS)

    def _check(self, path: str) -> None:
        counts = ("horizon", "max_iter", "admm_max_iter", "admm_check_every", "ipm_max_iter", "active_set_max_steps")
        for name in (*counts, "active_set_slots"):
            if getattr(self, name) < 1:
                raise ValueError(f"{path}.{name}: must be a positive integer, got {getattr(self, name)!r}")
        for name in ("solver_tol", "feasibility_tol", "admm_rho_scale", "ipm_tol"):
            positive(f"{path}.{name}", getattr(self, name))
        for name in (
            "slack_l1",
            "slack_l2",
            "admm_tol",
            "admm_polish_rounds",
            "admm_dual_active_set_steps",
            "ipm_polish_rounds",
        ):
            if getattr(self, name) < 0:
                raise ValueError(f"{path}.{name}: must be >= 0, got {getattr(self, name)!r}")
        if not 0.0 < self.admm_alpha < 2.0:
            raise ValueError(f"{path}.admm_alpha: must be in the open interval (0, 2), got {self.admm_alpha!r}")
        if self.solver in ("ipm", "active_set") and self.soft_constraints:
            raise ValueError(
                f"{path}.soft_constraints: the {self.solver} solver holds hard constraints only; allowed with soft "
                "constraints: solver admm or qpax"
            )
        if self.soft_constraints and self.slack_l1 == 0 and self.slack_l2 == 0:
            raise ValueError(f"{path}.slack_l1: slack_l1 and slack_l2 are both 0, so a slack would be free")


class LinearMPCState(NamedTuple):
    """The memory of one copy: the last solve's ``status`` (int32: ``scg_algorithms.mpc.structured``'s codes with
    ``solver="admm"`` and ``"ipm"``, ``scg_algorithms.mpc.qp.STATUS_*`` with qpax; ``info["status_names"]`` names
    them) and ``iterations`` (int32); with admm, the plan's ``warm`` start (``structured.Warm``; ``rho = 0``: none)
    and ``plan_step``, the control step it was made at."""

    status: Any
    iterations: Any
    warm: Any
    plan_step: Any


# --------------------------------------------------------------------------------------------- host set-up
@dataclasses.dataclass(frozen=True)
class Problem:
    """Everything both controllers build from ``(env, prior_params, options)`` on the host (numpy float64).

    Attributes:
        options: the parsed ``Options``. model: the ``env.symbolic_model`` it came from. Q, R: weights.
        affine: ``qp.AffineModel`` (its ``K`` is zero without pre-stabilisation). K_lqr: (n_points, nu, nx) LQR
            gains at the points (the fallback law). rows: ``qp.ConstraintRows``.
        row_of: for each env constraint, a tuple (one entry per row) of the index into ``rows`` (or -1 for a
            skipped constraint). skipped: indices of the env constraints that are not imposed.
        u_low, u_high: (nu,) clip box from the hard single-input rows (actuator limits included).
    """

    options: Options
    model: Any
    Q: np.ndarray
    R: np.ndarray
    affine: qp_lib.AffineModel
    K_lqr: np.ndarray
    rows: qp_lib.ConstraintRows
    row_of: tuple
    skipped: tuple
    u_low: np.ndarray
    u_high: np.ndarray


def _affine_model(env, prior_params, model, opts: Options, Q, R):
    """Linearisations, offsets, LQR gains and terminal weights at the chosen points."""
    mode = setup.linearization_mode(env, opts.linearize_about)
    u_bar = setup.equilibrium_input(env, prior_params)
    x_bar = setup.linearization_points(env, prior_params, model, mode)
    n = x_bar.shape[0]
    Ad, Bd, c = setup.linearize_along(model, x_bar, u_bar)

    # One Riccati solve when the linear part is the same everywhere (stabilization; level quadrotor references).
    same = qp_lib.same_along_axis0(Ad) and qp_lib.same_along_axis0(Bd)
    points = [0] if same else range(n)
    solves = [discrete_lqr_gain(Ad[i], Bd[i], Q, R) for i in points]
    K_lqr = np.stack([s[0] for s in solves])
    P_dare = np.stack([s[1] for s in solves])
    if same:
        K_lqr = np.repeat(K_lqr, n, axis=0)
        P_dare = np.repeat(P_dare, n, axis=0)
    K = K_lqr if opts.prestabilize else np.zeros_like(K_lqr)
    P = P_dare if opts.terminal_weight == "dare" else np.repeat(Q[None], n, axis=0)
    affine = qp_lib.AffineModel(Ad=Ad, Bd=Bd, c=c, x_bar=x_bar, u_bar=u_bar, K=K, P=P)
    return affine, K_lqr, mode


def _constraint_rows(env, prior_params, use_env: bool):
    """Actuator-limit rows, then the env's linear constraint rows as ``Ax x + Au u <= b`` (duplicates merged)."""
    nx, nu = env.nx, env.nu
    low, high = setup.input_limits(env, prior_params)
    Ax, Au, b = [], [], []
    for i in range(nu):
        for sign, bound in ((1.0, high[i]), (-1.0, -low[i])):
            if np.isfinite(bound):
                Ax.append(np.zeros(nx))
                Au.append(sign * np.eye(nu)[i])
                b.append(bound)
    row_of, skipped = [], []
    specs = env.constraint_specs if use_env else ()
    for index, (spec, values) in enumerate(zip(specs, prior_params.constraints[: len(specs)], strict=True)):
        if spec.form != "linear":
            skipped.append(index)
            row_of.append((-1,) * spec.num_rows)
            continue
        A = np.asarray(values.A, dtype=np.float64)
        rhs = np.asarray(values.b, dtype=np.float64)
        ax = np.zeros((A.shape[0], nx))
        au = np.zeros((A.shape[0], nu))
        for col, dim in enumerate(spec.active_dims):
            if spec.on == "state":
                ax[:, dim] = A[:, col]
            elif spec.on == "input":
                au[:, dim] = A[:, col]
            elif dim < nx:
                ax[:, dim] = A[:, col]
            else:
                au[:, dim - nx] = A[:, col]
        start = len(b)
        Ax.extend(ax)
        Au.extend(au)
        b.extend(rhs)
        row_of.append(tuple(range(start, start + A.shape[0])))
    if not use_env:
        skipped = []
        row_of = [(-1,) * spec.num_rows for spec in env.constraint_specs]
    Ax, Au, b = np.asarray(Ax).reshape(-1, nx), np.asarray(Au).reshape(-1, nu), np.asarray(b, dtype=np.float64)

    # Merge rows that are the same half-space (e.g. the "default" input constraint repeats the actuator limits).
    full = np.concatenate([Ax, Au, b[:, None]], axis=1)
    norms = np.linalg.norm(full[:, :-1], axis=1)
    keep = norms > 0
    if not np.all(keep):
        bad = [i for i, rows in enumerate(row_of) for r in rows if r >= 0 and not keep[r]]
        raise ValueError(f"constraints[{bad[0]}]: a row has all-zero coefficients; remove it")
    key = np.round(full / norms[:, None], 12)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    order = np.sort(first)
    new_index = {old: new for new, old in enumerate(order)}
    remap = np.array([new_index[first[inverse[r]]] for r in range(len(b))], dtype=int)
    row_of = tuple(tuple(int(remap[r]) if r >= 0 else -1 for r in rows) for rows in row_of)
    Ax, Au, b = Ax[order], Au[order], b[order]
    soft = np.any(Ax != 0.0, axis=1)
    rows = qp_lib.ConstraintRows(Ax=Ax, Au=Au, b=b, soft=soft)

    # The clip box: the tightest single-input hard rows (never looser than the actuator limits).
    u_low, u_high = low.copy(), high.copy()
    for ax, au, rhs in zip(Ax, Au, b, strict=True):
        nonzero = np.flatnonzero(au)
        if np.any(ax != 0.0) or nonzero.size != 1:
            continue
        i, a = nonzero[0], au[nonzero[0]]
        if a > 0:
            u_high[i] = min(u_high[i], rhs / a)
        else:
            u_low[i] = max(u_low[i], rhs / a)
    return rows, row_of, tuple(skipped), u_low, u_high


def build_problem(env, prior_params, options=None, path: str = PATH) -> Problem:
    """Parse ``options`` (error messages name ``<path>.<field>``) and build the host data both controllers share
    (see ``Problem``)."""
    opts = parse_options(Options, options, path)
    Q, R = setup.cost_weights(env, prior_params, opts.q_diag, opts.r_diag, path)
    model = setup.prior_model(env, prior_params, opts.discretization)
    affine, K_lqr, _ = _affine_model(env, prior_params, model, opts, Q, R)
    rows, row_of, skipped, u_low, u_high = _constraint_rows(env, prior_params, opts.env_constraints)
    if np.any(u_low > u_high):
        raise ValueError(
            f"constraints: the input constraints leave no admissible input (low {u_low.tolist()}, high "
            f"{u_high.tolist()})"
        )
    if opts.solver == "auto":  # the fastest solver that holds the problem (docs/controllers.md)
        hard = affine.time_invariant and not opts.soft_constraints
        # An ADMM option given asks for the ADMM (it would otherwise be ignored).
        admm_asked = isinstance(options, Mapping) and any(k.startswith("admm_") or k == "warm_start" for k in options)
        opts = dataclasses.replace(opts, solver="active_set" if hard and not admm_asked else "admm")
    return Problem(opts, model, Q, R, affine, K_lqr, rows, row_of, skipped, u_low, u_high)


def build_condensed_qp(problem: Problem) -> qp_lib.CondensedQP:
    """The condensed QP of ``problem`` (``scg_algorithms.mpc.qp.build_qp`` with its options)."""
    opts = problem.options
    return qp_lib.build_qp(
        problem.affine,
        opts.horizon,
        problem.Q,
        problem.R,
        problem.rows,
        soft_constraints=opts.soft_constraints,
        slack_per_stage=opts.slack_per_stage,
        slack_l1=opts.slack_l1,
        slack_l2=opts.slack_l2,
    )


# --------------------------------------------------------------------------------------------- structured QP
@dataclasses.dataclass(frozen=True)
class StructuredMPC:
    """The linear MPC as a ``structured.HorizonQP`` family (host data; see ``structured_mpc``).

    Attributes:
        layout: the ``structured.Layout``. settings: the ``structured.Settings`` of the options.
        stage_Q: (H, nx, nx) weights of ``x_1..x_H`` (the last: the terminal weight of the QP at step 0).
        bounds: ``(u_low, u_high, x_low, x_high, row_low, row_high)``, each with a leading stage axis (H, ...).
        C, D: (m, nx), (m, nu) the general rows (unit norm), the same at every stage.
        prepared: ``structured.Prepared`` when the model's matrices are the same at every point, else ``None``
            (the matrices then change with the step, and every copy condenses its own QP).
    """

    layout: structured.Layout
    settings: structured.Settings
    stage_Q: np.ndarray
    bounds: tuple
    C: np.ndarray
    D: np.ndarray
    prepared: Any


def _structured_rows(problem: Problem):
    """Split the constraint rows into the input box (the clip box), state boxes and general rows.

    Returns ``(x_rows, x_low, x_high, soft_x, C, D, row_high, soft_rows)``. A state-only row on one entry becomes a
    bound of that entry (the tightest with hard rows; with softened ones the first upper and the first lower one,
    and a further one stays a general row with its own slack, as in the CasADi controller); every other
    row that involves the state, and every input row on several inputs, is a general row ``C x + D u <= b``
    scaled to unit norm, so that its slack is in the row's units, as in ``scg_algorithms.mpc.qp``.
    """
    rows = problem.rows
    upper, lower, general = {}, {}, []
    for r, (ax, au, b) in enumerate(zip(rows.Ax, rows.Au, rows.b, strict=True)):
        state = np.flatnonzero(ax)
        if state.size == 0 and np.count_nonzero(au) == 1:
            continue  # a single-input row: part of the clip box (problem.u_low, problem.u_high)
        if state.size == 1 and not np.any(au):
            i, a = int(state[0]), ax[state[0]]
            side, tighter = (upper, min) if a > 0 else (lower, max)
            if i not in side:
                side[i] = (b / a, bool(rows.soft[r]))
                continue
            if not (side[i][1] or problem.options.soft_constraints):  # hard rows: only the tightest can bind
                side[i] = (tighter(side[i][0], b / a), False)
                continue
        general.append(r)
    x_rows = tuple(sorted(set(upper) | set(lower)))
    x_low = np.array([lower[i][0] if i in lower else -np.inf for i in x_rows])
    x_high = np.array([upper[i][0] if i in upper else np.inf for i in x_rows])
    soft_x = tuple(bool(upper.get(i, (0.0, False))[1] or lower.get(i, (0.0, False))[1]) for i in x_rows)
    Ax, Au, b = rows.Ax[general], rows.Au[general], rows.b[general]
    norms = np.linalg.norm(np.concatenate([Ax, Au], axis=1), axis=1)
    soft_rows = tuple(bool(rows.soft[r]) for r in general)
    return x_rows, x_low, x_high, soft_x, Ax / norms[:, None], Au / norms[:, None], b / norms, soft_rows


def structured_mpc(problem: Problem, prepare: bool = True) -> StructuredMPC:
    """The linear MPC of ``problem`` for ``scg_algorithms.mpc.structured`` (host, float64; with ``prepare``, prepared
    once for the ADMM when the model's matrices do not change along the reference)."""
    opts = problem.options
    affine = problem.affine
    H, nx, nu = opts.horizon, problem.Q.shape[0], problem.R.shape[0]
    x_rows, x_low, x_high, soft_x, C, D, row_high, soft_rows = _structured_rows(problem)
    soft = opts.soft_constraints
    layout = structured.Layout(
        horizon=H,
        nx=nx,
        nu=nu,
        x_rows=x_rows,
        num_rows=C.shape[0],
        soft_x=tuple(f and soft for f in soft_x),
        soft_rows=tuple(f and soft for f in soft_rows),
        slack="stage" if opts.slack_per_stage else "shared",
        l1=opts.slack_l1,
        l2=opts.slack_l2,
    )
    active_set = opts.solver == "active_set"
    settings = structured.Settings(
        method="dual_active_set" if active_set else "admm",
        active_set_slots=opts.active_set_slots,
        max_iterations=opts.active_set_max_steps if active_set else opts.admm_max_iter,
        check_every=opts.admm_check_every,
        eps_abs=opts.admm_tol,
        eps_rel=opts.admm_tol,
        polish_rounds=opts.admm_polish_rounds,
        dual_active_set_steps=opts.admm_dual_active_set_steps,
        adaptive_rho=opts.admm_adaptive_rho,
        rho_scale=opts.admm_rho_scale,
        alpha=opts.admm_alpha,
    )
    stage_Q = np.stack([problem.Q] * (H - 1) + [affine.P[0]])
    m = C.shape[0]
    bounds = tuple(
        np.tile(np.asarray(a, dtype=np.float64), (H, 1))
        for a in (problem.u_low, problem.u_high, x_low, x_high, np.full(m, -np.inf), row_high)
    )
    prepared = None
    if prepare and affine.time_invariant:
        template = structured.HorizonQP(
            A=np.repeat(affine.Ad[:1], H, axis=0),
            B=np.repeat(affine.Bd[:1], H, axis=0),
            c=np.zeros((H, nx)),
            K=np.repeat(affine.K[:1], H, axis=0),
            Q=stage_Q,
            q=np.zeros((H, nx)),
            R=np.repeat(problem.R[None], H, axis=0),
            r=np.zeros((H, nu)),
            u_low=bounds[0],
            u_high=bounds[1],
            x_low=bounds[2],
            x_high=bounds[3],
            C=np.repeat(C[None], H, axis=0),
            D=np.repeat(D[None], H, axis=0),
            row_low=bounds[4],
            row_high=bounds[5],
        )
        prepared = structured.prepare(layout, template, settings)
    return StructuredMPC(layout, settings, stage_Q, bounds, C, D, prepared)


def _no_warm(layout: structured.Layout, dtype) -> structured.Warm:
    """The ``Warm`` that means "none" (``rho = 0``): the next solve starts cold."""
    zeros = jnp.zeros(layout.num_dense, dtype)
    return structured.Warm(zeros, zeros, jnp.zeros((), dtype))


def _horizon_qp(problem: Problem, smpc: StructuredMPC, dtype):
    """``qp_at(step, x_ref) -> HorizonQP``: one copy's horizon QP at control step ``step`` (the model's points from
    ``step`` on, the reference's targets from ``step + 1``; along a reference, the terminal weight of the last
    point)."""
    opts, affine = problem.options, problem.affine
    H, n_points = opts.horizon, affine.num_points
    cast = lambda a: jnp.asarray(a, dtype)  # noqa: E731
    c_table, Ad, Bd, K, P = (cast(a) for a in (affine.c, affine.Ad, affine.Bd, affine.K, affine.P))
    stage_Q, R = cast(smpc.stage_Q), cast(problem.R)
    R_stages = jnp.broadcast_to(R, (H, *R.shape))
    r = jnp.tile(-(R @ cast(affine.u_bar)), (H, 1))
    bounds = tuple(cast(b) for b in smpc.bounds)
    C, D = (jnp.broadcast_to(cast(a), (H, *a.shape)) for a in (smpc.C, smpc.D))

    def qp_at(step, x_ref):
        stages = jnp.clip(step + jnp.arange(H), 0, n_points - 1)
        targets = jnp.clip(step + 1 + jnp.arange(H), 0, x_ref.shape[0] - 1)
        Q = stage_Q if affine.time_invariant else stage_Q.at[-1].set(P[jnp.minimum(step + H, n_points - 1)])
        q = -jnp.einsum("kxy,ky->kx", Q, jnp.asarray(x_ref, dtype)[targets])
        return structured.HorizonQP(
            Ad[stages], Bd[stages], c_table[stages], K[stages], Q, q, R_stages, r, *bounds[:4], C, D, *bounds[4:]
        )

    return qp_at


def _structured_solve(problem: Problem, smpc: StructuredMPC, dtype):
    """``solve(ctrl_state, x, step, x_ref) -> (u_0, ctrl_state, failed)`` with the admm or active_set solver (one
    copy; the active set method starts from the unconstrained minimiser every step, and ignores the warm start)."""
    opts, layout, H = problem.options, smpc.layout, problem.options.horizon
    qp_at = _horizon_qp(problem, smpc, dtype)
    cold = _no_warm(layout, dtype)

    def where(condition, a, b):
        return jax.tree.map(lambda u, v: jnp.where(condition, u, v), a, b)

    def solve(ctrl_state, x, step, x_ref):
        qp = qp_at(step, x_ref)
        moved = step - ctrl_state.plan_step
        usable = (ctrl_state.plan_step >= 0) & (moved >= 1) & (moved <= H)
        warm = where(usable, structured.shift(layout, ctrl_state.warm, jnp.maximum(moved, 0)), cold)
        warm = warm if opts.warm_start else cold
        if smpc.prepared is not None:  # the matrices are the prepared ones: only the vectors change
            bounds = tuple(getattr(qp, name) for name in structured.BOUND_FIELDS)
            sol = structured.solve_prepared(layout, smpc.prepared, x, qp.c, qp.q, qp.r, bounds, warm, smpc.settings)
        else:
            sol = structured.solve(layout, qp, x, warm, smpc.settings)
        u = sol.u[0]
        unusable = (sol.status == structured.INFEASIBLE) | (sol.status == structured.NUMERICAL)
        failed = unusable | (sol.violation > opts.feasibility_tol) | ~jnp.all(jnp.isfinite(u))
        state = LinearMPCState(sol.status, sol.iterations, where(failed, cold, sol.warm), jnp.asarray(step, jnp.int32))
        return u, state, failed

    return solve


def _ipm_solve(problem: Problem, smpc: StructuredMPC, dtype):
    """``solve(ctrl_state, x, step, x_ref) -> (u_0, ctrl_state, failed)`` with the ipm solver (one copy; no warm
    start: an interior point gains little from one)."""
    opts = problem.options
    qp_at = _horizon_qp(problem, smpc, dtype)
    settings = interior_point.IPMSettings(
        max_iterations=opts.ipm_max_iter, tol=opts.ipm_tol, polish_rounds=opts.ipm_polish_rounds
    )
    empty = _no_warm(smpc.layout, dtype)

    def solve(ctrl_state, x, step, x_ref):
        sol = interior_point.solve(smpc.layout, qp_at(step, x_ref), x, settings)
        u = sol.u[0]
        # An unconverged or broken-off iterate is used where it holds the rows (its violation), as the admm's is.
        failed = (sol.status == structured.INFEASIBLE) | (sol.violation > opts.feasibility_tol)
        failed = failed | ~jnp.all(jnp.isfinite(u))
        state = LinearMPCState(sol.status, sol.iterations, empty, jnp.asarray(step, jnp.int32))
        return u, state, failed

    return solve


# --------------------------------------------------------------------------------------------- JAX controller
def make_linear_mpc(env, prior_params, options=None) -> JaxController:
    """Batched linear MPC in JAX (see the module docstring).

    Args:
        env: the environment. prior_params: ``EnvParams`` of the controller's model; its ``Q``, ``R`` are the
            default weights and its ``constraints`` the constraint values. options: ``Options`` fields as a
            mapping (``controllers.linear_mpc``).

    Returns:
        A ``JaxController`` named ``"linear_mpc"``. ``act`` returns the input (nu,), N, and ``LinearMPCState``.
        ``info`` holds ``solver``, ``status_names``, ``qp`` (the ``CondensedQP`` of qpax), ``structured`` (the
        ``StructuredMPC`` of admm and ipm, unprepared with ipm; ``None`` with qpax), ``horizon``,
        ``linearize_about``, ``K_lqr``, ``u_low``/``u_high`` (the clip box) and ``skipped_constraints``.

    Raises:
        ValueError: naming ``controllers.linear_mpc.<field>`` for a bad option.
    """
    problem = build_problem(env, prior_params, options)
    opts = problem.options
    qp = build_condensed_qp(problem)
    dtype = jnp.zeros(()).dtype
    K_lqr = jnp.asarray(problem.K_lqr, dtype)
    u_bar = jnp.asarray(problem.affine.u_bar, dtype)
    u_low = jnp.asarray(problem.u_low, dtype)
    u_high = jnp.asarray(problem.u_high, dtype)
    last_point = problem.K_lqr.shape[0] - 1
    if opts.solver == "active_set" and not problem.affine.time_invariant:
        raise ValueError(
            f"{PATH}.solver: active_set needs a model that is the same at every point (linearize_about: goal, or a "
            "reference along which the linearisation does not change); allowed here: admm, ipm, qpax"
        )
    if opts.solver in ("admm", "ipm", "active_set"):
        smpc = structured_mpc(problem, prepare=opts.solver != "ipm")
        make_solve = _ipm_solve if opts.solver == "ipm" else _structured_solve
        solve_structured = make_solve(problem, smpc, dtype)
        empty = _no_warm(smpc.layout, dtype)
        status_names = structured.STATUS_NAMES
    else:
        smpc = None
        arrays = qp_lib.qp_arrays(qp, dtype)
        settings = {"max_iter": opts.max_iter, "solver_tol": opts.solver_tol, "feasibility_tol": opts.feasibility_tol}
        empty = structured.Warm(jnp.zeros(0, dtype), jnp.zeros(0, dtype), jnp.zeros((), dtype))
        status_names = ("solved", "inaccurate", "failed")

    def reset(key, reference):
        return LinearMPCState(jnp.zeros((), jnp.int32), jnp.zeros((), jnp.int32), empty, jnp.asarray(-1, jnp.int32))

    def act(ctrl_state, obs, step, reference):
        x = jnp.asarray(state_from_obs(env, obs), dtype)
        if smpc is not None:
            u_mpc, new_state, failed = solve_structured(ctrl_state, x, step, reference.x_ref)
        else:
            hess, q, G, h, theta, index = qp_lib.qp_vectors(qp, arrays, step, x, reference.x_ref)
            solution = qp_lib.solve_qp(hess, q, G, h, **settings)
            u_mpc = qp_lib.first_input(arrays, solution.z, theta, index)
            failed = (solution.status == qp_lib.STATUS_FAILED) | ~jnp.all(jnp.isfinite(u_mpc))
            new_state = LinearMPCState(solution.status, solution.iterations, empty, jnp.asarray(step, jnp.int32))
        k = jnp.clip(step, 0, reference.x_ref.shape[0] - 1)
        u_lqr = u_bar - K_lqr[jnp.minimum(k, last_point)] @ (x - reference.x_ref[k])
        u = jnp.clip(jnp.where(failed, u_lqr, u_mpc), u_low, u_high)
        return u, new_state

    info = {
        "solver": opts.solver,
        "status_names": status_names,
        "qp": qp,
        "structured": smpc,
        "horizon": opts.horizon,
        "linearize_about": "goal" if problem.affine.num_points == 1 else "reference",
        "K_lqr": problem.K_lqr,
        "u_low": problem.u_low,
        "u_high": problem.u_high,
        "skipped_constraints": problem.skipped,
        "options": opts,
    }
    return JaxController("linear_mpc", reset, act, info=info)


# --------------------------------------------------------------------------------------------- CasADi controller
@dataclasses.dataclass(frozen=True, eq=False)
class LinearMPCCasadi:
    """The linear MPC for one copy on the host (``is_jax = False``): ``casadi.Opti("conic")`` with qpOASES or OSQP.

    The problem is the JAX controller's, formulated independently (the inputs are the variables and the predicted
    states CasADi expressions of them, no pre-stabilisation, constraints through the symbolic model's ``g_i``
    functions), built once with parameters for the state, the reference window and the model offsets, and expanded
    to SX functions (``expand``) so that building the solver takes about a second and each call milliseconds.
    ``reset`` returns ``{"success": True}``; ``act(ctrl_state, obs, step, reference)`` returns ``(u (nu,) numpy,
    {"success": bool})`` (``ctrl_state`` is not used: every step is solved from scratch).
    """

    name: str
    problem: Problem
    opti: Any
    variables: dict
    parameters: dict
    is_jax: ClassVar[bool] = False

    def reset(self, key, reference):
        return {"success": True}

    def solve(self, x0, step: int, x_ref) -> tuple[np.ndarray, bool]:
        """First input (nu,) and solver success for state ``x0`` (nx,) at step ``step`` along ``x_ref`` (T+1, nx)."""
        problem, opti = self.problem, self.opti
        H = problem.options.horizon
        affine = problem.affine
        stages = np.minimum(step + np.arange(H + 1), affine.num_points - 1)
        targets = np.minimum(step + 1 + np.arange(H), x_ref.shape[0] - 1)
        p = self.parameters
        opti.set_value(p["x0"], x0)
        opti.set_value(p["r"], np.asarray(x_ref, dtype=np.float64)[targets].T)
        opti.set_value(p["c"], affine.c[stages[:H]].T)
        if "A" in p:
            for j in range(H):
                opti.set_value(p["A"][j], affine.Ad[stages[j]])
                opti.set_value(p["B"][j], affine.Bd[stages[j]])
            opti.set_value(p["P"], affine.P[stages[H]])
        try:
            opti.solve()
            success = bool(opti.stats()["success"])
        except RuntimeError:
            success = False
        u0 = np.asarray(opti.debug.value(self.variables["U"][:, 0]), dtype=np.float64).reshape(-1)
        return u0, success and bool(np.all(np.isfinite(u0)))

    def act(self, ctrl_state, obs, step, reference):
        problem = self.problem
        x = np.asarray(obs, dtype=np.float64)[: problem.model.nx]
        x_ref = np.asarray(reference.x_ref, dtype=np.float64)
        k = int(step)
        u, success = self.solve(x, k, x_ref)
        if not success:
            kk = min(max(k, 0), x_ref.shape[0] - 1)
            K = problem.K_lqr[min(kk, problem.K_lqr.shape[0] - 1)]
            u = problem.affine.u_bar - K @ (x - x_ref[kk])
        return np.clip(u, problem.u_low, problem.u_high), {"success": success}


def make_linear_mpc_casadi(env, prior_params, options=None) -> LinearMPCCasadi:
    """The linear MPC for one copy on the host with CasADi (same ``Options``; see ``LinearMPCCasadi``)."""
    import casadi as cs

    problem = build_problem(env, prior_params, options, CASADI_PATH)
    opts = problem.options
    affine, model = problem.affine, problem.model
    nx, nu, H = env.nx, env.nu, opts.horizon
    varying = not affine.time_invariant

    opti = cs.Opti("conic")
    U = opti.variable(nu, H)
    x0 = opti.parameter(nx)
    r = opti.parameter(nx, H)
    c = opti.parameter(nx, H)
    parameters = {"x0": x0, "r": r, "c": c}
    if varying:
        parameters["A"] = [opti.parameter(nx, nx) for _ in range(H)]
        parameters["B"] = [opti.parameter(nx, nu) for _ in range(H)]
        parameters["P"] = opti.parameter(nx, nx)
    A_of = (lambda j: parameters["A"][j]) if varying else (lambda j: cs.DM(affine.Ad[0]))
    B_of = (lambda j: parameters["B"][j]) if varying else (lambda j: cs.DM(affine.Bd[0]))
    P = parameters["P"] if varying else cs.DM(affine.P[0])

    # Condensed: the predicted states are expressions of the inputs (and the parameters), not variables. The
    # sparse form (states as variables, dynamics as equality rows) had 12 x 21 + 80 variables on the 3D quadrotor,
    # which the dense active-set solver qpOASES factorises at every cold start: 0.2-0.9 s per step, against a few
    # milliseconds for the 80 inputs alone (see the benchmarks).
    columns = [x0]
    for j in range(H):
        columns.append(A_of(j) @ columns[j] + B_of(j) @ U[:, j] + c[:, j])
    X = cs.horzcat(*columns)
    Q, R = cs.DM(problem.Q), cs.DM(problem.R)
    u_bar = cs.DM(affine.u_bar)
    cost = 0
    for j in range(H):
        dx = X[:, j + 1] - r[:, j]
        du = U[:, j] - u_bar
        weight = P if j == H - 1 else Q
        cost += 0.5 * cs.bilin(weight, dx, dx) + 0.5 * cs.bilin(R, du, du)

    # Slacks: per distinct row that involves the state (the same merge as the JAX controller), per stage or shared.
    rows = problem.rows
    soft_index = {}
    if opts.soft_constraints:
        for r_index in np.flatnonzero(rows.soft):
            soft_index[int(r_index)] = len(soft_index)
    E = opti.variable(len(soft_index), H if opts.slack_per_stage else 1) if soft_index else None
    if E is not None:
        opti.subject_to(cs.vec(E) >= 0)
        cost += opts.slack_l1 * cs.sum1(cs.vec(E)) + 0.5 * opts.slack_l2 * cs.sumsqr(E)

    low, high = setup.input_limits(env, prior_params)
    # Each distinct row once: the actuator limits are rows 0..n-1 of ``problem.rows``, and an env row that repeats
    # one of them (the "default" input constraint) or an earlier env row is skipped, since duplicated rows make the
    # active set degenerate for qpOASES.
    imposed = set(range(int(np.isfinite(low).sum() + np.isfinite(high).sum())))
    env_rows = []  # (constraint index, row within it, merged row index)
    for index, row_ids in enumerate(problem.row_of):
        for row, rid in enumerate(row_ids):
            if rid >= 0 and rid not in imposed:
                imposed.add(rid)
                env_rows.append((index, row, rid))
    for j in range(H):
        for i in range(nu):
            if np.isfinite(high[i]):
                opti.subject_to(U[i, j] <= high[i])
            if np.isfinite(low[i]):
                opti.subject_to(U[i, j] >= low[i])
        values = {index: model.constraints[index](X[:, j + 1], U[:, j]) for index in {e[0] for e in env_rows}}
        for index, row, rid in env_rows:
            if rid in soft_index:
                norm = float(np.linalg.norm(np.asarray(prior_params.constraints[index].A, dtype=np.float64)[row]))
                opti.subject_to(values[index][row] <= norm * E[soft_index[rid], j if opts.slack_per_stage else 0])
            else:
                opti.subject_to(values[index][row] <= 0)
    opti.minimize(cost)
    opti.solver(opts.casadi_solver, {**qp_lib.casadi_qp_options(opts.casadi_solver, 1e-9), "expand": True})
    return LinearMPCCasadi(
        name="linear_mpc_casadi",
        problem=problem,
        opti=opti,
        variables={"X": X, "U": U, "E": E},
        parameters=parameters,
    )
