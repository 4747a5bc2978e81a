"""Linear model predictive safety certification (MPSC; Wabersich & Zeilinger 2018): the smallest change to the
proposed input that keeps a plan back into safety, on the linearised prior with a tightened constraint set.

Two filters share one ``Options`` (``safety_filters.linear_mpsc``; the CasADi variant reads the same fields):

- ``make_linear_mpsc`` (``"linear_mpsc"``): a JAX ``Filter``; ``certify`` is pure JAX of one copy, so the harness
  vmaps it over thousands of copies inside its jitted loop. Its QP is solved by the structured horizon-QP solver
  (``solver="structured"``, the default: ``scg_algorithms.mpc.structured``, prepared once by ``mpsc_structured``,
  warm-started from the shifted previous solution, polished), by a fixed-iteration ADMM with one factorisation
  shared by the batch (``solver="admm"``, ``mpsc_admm``) or by qpax's interior point (``solver="qpax"``).
- ``make_linear_mpsc_casadi``: the same QP for one copy on the host, formulated independently with
  ``casadi.Opti("conic")`` and qpOASES (or OSQP): the reference the tests hold the batched filter to.

Offline (host, numpy float64):

1. **Model**: ``env.symbolic_model(prior_params)`` (``scg_algorithms.controller_setup``) linearised about the goal and
   the prior's equilibrium input, ``x+ = Ad x + Bd u + c``.
2. **Ancillary feedback** ``K``: the discrete LQR of ``(Ad, Bd)`` with ``q_lqr``, ``r_lqr`` (``u = u_eq - K dx``).
3. **Model error**: ``n_samples`` transitions of the plant (``mpsc_tightening.sample_transitions``; the true
   ``env.default_params`` unless ``plant_params`` is given), ``w = x+ - (Ad x + Bd u + c)``.
4. **Tightening** (``tightening``): ``"reachable"`` (default), per-stage margins of the linearised error tube
   ``e+ = (Ad - Bd K) e + w`` from the per-dimension error bound; ``"rpi"``, the original's robust invariant
   ellipsoid of the same error dynamics from a semidefinite program (cvxpy + Clarabel or SCS) and each row's
   support-function margin at every stage; ``"none"``. Plus ``constraint_margin`` on every row that involves the
   state. Why ``reachable`` is the default: with
   ``x_0 = x`` the error starts at zero, so the tube's margin at stage ``j`` holds only ``j`` steps of error, while
   the invariant ellipsoid holds the error of every horizon at every stage; and the ellipsoid must contract by
   ``tau`` per step under a closed loop whose slowest mode is near 1 (cart-pole at 15 Hz: 0.947), so it stretches
   along that mode. The SDP also costs seconds of Clarabel per 40 samples (it has one LMI per sample).

Online, per copy (observation ``x``, proposed input ``u_L``), the condensed QP of ``scg_algorithms.mpc.qp``
(pre-stabilised inputs ``u_j = u_eq - K (x_j - x_goal) + v_j``, states eliminated, rows scaled to unit norm)::

    min_v  1/2 |u_0 - u_L|^2 + 1/2 regularization |v_{1:}|^2
    s.t.   x_0 = x,  x_{j+1} = Ad x_j + Bd u_j + c,  rows(x_{j+1}, u_j) <= b - margin_j   (j = 0..H-1)

The second term is in general ``1/2 sum_{j>=1} v_j^T W v_j``, ``W`` the ancillary LQR's ``R + B^T P B`` scaled to
the largest eigenvalue ``regularization`` (``mpsc_structured.plan_weight``; with one input, ``regularization``
itself). It makes the Hessian definite (the one-step cost alone is singular in ``v_1..``); it leaves ``v_0`` alone,
so it does not bias the certified input.
With ``x_0 = x`` the tube starts at zero error, so the constant RPI margin is conservative at early stages (the
design choice "(a)" of the research notes: the original's tube-initial-state freedom is dropped so the problem
stays a QP).

Certification: every solver's plan ``v`` is checked on every row of the horizon and the tail (``max(G v - h) <=
feasibility_tol``; qpax also by its status). Fallback (the original's Algorithm 1): the filter state keeps the last
certified plan ``v`` and the steps since (``kinf``). When no plan is certified, the input is ``u_eq - K (x - x_goal) +
v_prev[kinf]`` (the previous plan continued with the tube feedback; in this parametrisation the tube controller
``v_j - K (x - z_j)`` reduces to that), and after ``H`` such steps, with no certified plan left, the plain LQR (the
default), or with ``violation_penalty > 0`` (structured solver: the state rows soft at that exact-penalty price) the
first input of the least-violating plan. The input is finally clipped to the actuator box. ``info.feasible`` is
False on a fallback step, ``info.slack`` is 0 (a certified plan holds every row).

The structured solver's defaults (hard rows, 64 tail rows in the QP, at most 300 ADMM iterations, then the active-set
polish and at most 30 dual active-set steps where the ADMM stopped at its cap) were chosen against the exact
solution of the same QP (qpOASES on the host, qpax batched): on ``benchmarks/mpsc.py``'s states they certify every
state qpOASES certifies but one in 1,024, and in its closed loop they behave as the exact filter does.

Pass-through: where ``u_L`` is the first input of a feasible plan the QP's optimum is ``u_L`` itself (cost 0 up to
the regulariser), so the correction is the solver's error: below 1e-6 N with qpax in float64 and at the ADMM's
iteration tolerance otherwise (the tests measure both).

Units: SI (m, rad, N); the filter's arrays in the default float dtype, built in float64.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, ClassVar, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from scg_algorithms import controller_setup as setup
from scg_algorithms.base import option, parse_options, positive
from scg_algorithms.lqr import discrete_lqr_gain
from scg_algorithms.mpc import qp as qp_lib
from scg_algorithms.mpc import structured
from scg_algorithms.mpc.linear import _constraint_rows
from scg_algorithms.safety_filters import mpsc_admm, mpsc_structured
from scg_algorithms.safety_filters import mpsc_tightening as tight
from scg_algorithms.safety_filters.backup import backup_weights, diagonal_weight, failure_rows, validation_states
from scg_algorithms.safety_filters.base import (
    BACKUP_CONTROLLER,
    BACKUP_PLAN,
    CERTIFIED,
    Filter,
    FilterInfo,
    applied_correction,
)

PATH = "safety_filters.linear_mpsc"
CASADI_PATH = "safety_filters.linear_mpsc_casadi"
SOLVERS = ("structured", "admm", "qpax")
TIGHTENINGS = ("rpi", "reachable", "none")
CASADI_SOLVERS = ("qpoases", "osqp")
QPAX_OBJECTIVE_SCALE = 1e3  # the objective's factor in the qpax solve (see certify)


SOLVER_DOC = (
    "QP solver: scg_algorithms.mpc.structured (prepared once, warm-started, polished), the fixed-iteration "
    "shared-factorisation ADMM of mpsc_admm, or qpax's interior point"
)


@dataclasses.dataclass(frozen=True)
class Options:
    """Options of the linear MPSC (``safety_filters.linear_mpsc``)."""

    horizon: int = option(25, "prediction horizon H, control steps (the plan's free inputs)")
    terminal_horizon: float = option(
        2.0, "seconds the plan's tail follows the ancillary LQR inside the tightened rows (the terminal set); 0: none"
    )
    q_lqr: tuple | None = option(None, "diagonal state weight (nx,) of the ancillary LQR K; default: see backup")
    r_lqr: tuple | None = option(None, "diagonal input weight (nu,) of the ancillary LQR K; default: see backup")
    discretization: str = setup.discretization_option("env", "model")
    tightening: str = option(
        "reachable",
        "constraint tightening: robust invariant ellipsoid (SDP), per-stage reachable tube, or none",
        choices=TIGHTENINGS,
    )
    n_samples: int = option(600, "plant transitions sampled for the model-error bound")
    plant_draws: int = option(8, "plants drawn from the env's physics randomisation for the samples (1: nominal)")
    sample_seed: int = option(0, "PRNG seed of the samples")
    sample_half_width: tuple | None = option(
        None, "(nx,) half-widths of the box around the goal the sampled states fill; default: the env's reset draw"
    )
    tau: float = option(0.95, "S-procedure contraction of the invariant-ellipsoid program, in (0, 1)")
    sdp_solver: str = option("clarabel", "conic solver of the invariant-set program (cvxpy)", choices=tight.SDP_SOLVERS)
    error_quantile: float | None = option(
        None,
        "quantile of |w - mean| bounding the error per dimension (reachable); default: the largest of 1, 0.9, 0.75, "
        "0.5 whose tube leaves the goal inside the tightened rows",
    )
    constraint_margin: float = option(0.0, "extra margin on every row that involves the state (row units)")
    regularization: float = option(
        1e-2,
        "largest eigenvalue of the weight W of 1/2 v^T W v over v_1..v_H-1 (> 0): the plan's later inputs stay "
        "near the LQR's (W: mpsc_structured.plan_weight)",
    )
    solver: str = option("structured", SOLVER_DOC, choices=SOLVERS)
    structured_method: str = option(
        "admm",
        "structured: admm (the ADMM, its polish and dual active-set fallback; warm started) or dual_active_set "
        "(Goldfarb and Idnani's dual active-set method from the unconstrained minimiser; hard rows only, "
        "violation_penalty 0; structured_max_iter caps its steps)",
        choices=structured.METHODS,
    )
    structured_max_iter: int = option(
        300, "structured: ADMM iterations (dual_active_set: steps) at most per step (stops once converged)"
    )
    structured_tol: float = option(1e-5, "structured: absolute and relative residual tolerance of the scaled QP")
    structured_check_every: int = option(10, "structured: iterations between residual checks and step-size updates")
    structured_polish_rounds: int = option(3, "structured: active-set polish rounds after the ADMM (0: none)")
    structured_polish_soft_rows: bool = option(
        False,
        "structured: with soft state rows (violation_penalty > 0), the polish holds them too, so that a certified "
        "plan is the QP's exact solution (the ADMM's otherwise, to its tolerance; with it, 6 polish rounds and "
        "structured_dual_active_set_steps: 0: see docs/safety-filters.md)",
    )
    structured_dual_active_set_steps: int = option(
        30,
        "structured: where the ADMM stopped at its cap and no polish round was accepted, at most this many steps of "
        "the dual active-set method on the hard rows (0: none; with soft state rows it holds the input rows only)",
    )
    structured_adaptive_rho: bool = option(
        True,
        "structured: adapt the step size at the checks; false: keep the prepared one (times structured_rho_scale) "
        "throughout, for fixed iteration counts with structured_tol 0",
    )
    structured_rho_scale: float = option(
        1.0,
        "structured: factor on the prepared step size, the smallest generalised eigenvalue of the condensed QP "
        "(with structured_adaptive_rho false: the step size throughout)",
    )
    terminal_rows: int = option(
        64,
        "structured: tail rows imposed on the plan's last state in the QP (the nearest to the goal that the others "
        "do not imply); every tail row is checked after the solve",
    )
    violation_penalty: float = option(
        0.0,
        "structured: 0 (default): the state rows are hard; > 0: their price per unit of violation (exact penalty; "
        "1/2 N^2 per row unit, e.g. 1e4), and with no certified plan left the least-violating plan's first input is "
        "applied instead of the plain LQR",
    )
    admm_iterations: int = option(500, "ADMM iterations per solve (fixed)")
    admm_rho: float = option(0.1, "ADMM step size rho")
    admm_sigma: float = option(1e-6, "ADMM proximal weight sigma")
    admm_alpha: float = option(1.6, "ADMM relaxation alpha in (0, 2)")
    warm_start: bool = option(True, "start the ADMM from the previous step's iterate")
    qpax_iterations: int = option(40, "qpax interior-point iterations at most")
    feasibility_tol: float = option(1e-3, "largest row violation (m, rad, N) of a solution still used")
    casadi_solver: str = option("qpoases", "conic solver of the CasADi variant", choices=CASADI_SOLVERS)

    def _check(self, path: str) -> None:
        for name in (
            "horizon", "n_samples", "plant_draws", "admm_iterations", "qpax_iterations", "structured_max_iter",
            "structured_check_every",
        ):  # fmt: skip
            if getattr(self, name) < 1:
                raise ValueError(f"{path}.{name}: must be a positive integer, got {getattr(self, name)!r}")
        for name in ("admm_rho", "admm_sigma", "feasibility_tol", "structured_rho_scale"):
            positive(f"{path}.{name}", getattr(self, name))
        if not 0.0 < self.tau < 1.0:
            raise ValueError(f"{path}.tau: must be in (0, 1), got {self.tau!r}")
        if not 0.0 < self.admm_alpha < 2.0:
            raise ValueError(f"{path}.admm_alpha: must be in (0, 2), got {self.admm_alpha!r}")
        if self.error_quantile is not None and not 0.0 < self.error_quantile <= 1.0:
            raise ValueError(f"{path}.error_quantile: must be in (0, 1], got {self.error_quantile!r}")
        positive(f"{path}.regularization", self.regularization)
        nonnegative = (
            "constraint_margin", "terminal_horizon", "structured_tol", "structured_polish_rounds",
            "structured_dual_active_set_steps",
        )  # fmt: skip
        for name in (*nonnegative, "terminal_rows", "violation_penalty"):
            if getattr(self, name) < 0:
                raise ValueError(f"{path}.{name}: must be >= 0, got {getattr(self, name)!r}")
        if self.structured_method == "dual_active_set" and self.violation_penalty > 0:
            raise ValueError(
                f"{path}.structured_method: dual_active_set holds hard rows only, and violation_penalty > 0 makes the "
                "state rows soft; allowed with violation_penalty > 0: admm"
            )
        if self.structured_polish_soft_rows and self.structured_dual_active_set_steps:
            raise ValueError(
                f"{path}.structured_polish_soft_rows: not with structured_dual_active_set_steps > 0 (the dual "
                "active-set method holds the hard rows only, the polish every row); set "
                "structured_dual_active_set_steps: 0 with it"
            )


# --------------------------------------------------------------------------------------------- host set-up
@dataclasses.dataclass(frozen=True)
class Problem:
    """What both variants build on the host (numpy float64).

    Attributes:
        options: parsed ``Options``. system: the env's system name. nx, nu, horizon: sizes (``horizon`` H decisions).
        stages: H plus the terminal tail's steps (the rows are imposed at every stage).
        affine: ``qp_lib.AffineModel`` about the goal with the ancillary ``K``. K: (nu, nx). x_bar: (nx,) goal.
        u_bar: (nu,) equilibrium input, N. rows: ``qp_lib.ConstraintRows`` (actuator limits and the env's linear
        rows, merged). margins: (stages, m) tightening of each row at each stage. u_low, u_high: (nu,) clip box, N.
        errors: (n, nx) model-error samples (empty without tightening). P_rpi: (nx, nx) the invariant ellipsoid
        (``tightening="rpi"``) or ``None``. qp: the condensed ``qp_lib.CondensedQP`` (its objective unused).
        error_quantile: the quantile of the error bound the tube uses (``error_quantile``, or the one chosen).
        Q_lqr, R_lqr, P_lqr: (nx, nx), (nu, nu), (nx, nx) the ancillary LQR's weights and its Riccati solution.
    """

    options: Options
    system: str
    nx: int
    nu: int
    horizon: int
    stages: int
    affine: Any
    K: np.ndarray
    x_bar: np.ndarray
    u_bar: np.ndarray
    rows: Any
    margins: np.ndarray
    u_low: np.ndarray
    u_high: np.ndarray
    errors: np.ndarray
    P_rpi: np.ndarray | None
    qp: Any
    error_quantile: float = 1.0
    Q_lqr: np.ndarray | None = None
    R_lqr: np.ndarray | None = None
    P_lqr: np.ndarray | None = None


def build_problem(env, prior_params, options=None, plant_params=None, path: str = PATH) -> Problem:
    """Parse ``options`` (errors name ``<path>.<field>``) and build the offline data (see the module docstring).

    Args:
        env: the environment. prior_params: the filter's model (``EnvParams``). options: ``Options`` mapping.
        plant_params: the plant the model-error samples come from (default ``env.default_params``).
    """
    opts = parse_options(Options, options, path)
    nx, nu, H = env.nx, env.nu, opts.horizon
    if opts.sample_half_width is not None and len(opts.sample_half_width) != nx:
        raise ValueError(f"{path}.sample_half_width: expected {nx} values, got {len(opts.sample_half_width)}")
    model = setup.prior_model(env, prior_params, opts.discretization)
    x_bar = np.asarray(prior_params.goal, dtype=np.float64).reshape(nx)
    u_bar = setup.equilibrium_input(env, prior_params)
    Ad, Bd, c = setup.linearize_along(model, x_bar[None], u_bar)
    rows, u_low, u_high = mpsc_rows(env, prior_params, path)
    stages = H + terminal_steps(env, opts)
    errors = np.zeros((0, nx))
    if opts.tightening != "none":
        plant = env.default_params if plant_params is None else plant_params
        x, u, x_next = tight.sample_transitions(
            env, plant, opts.n_samples, opts.sample_seed, opts.sample_half_width, opts.plant_draws
        )
        errors = x_next - (x @ Ad[0].T + u @ Bd[0].T + c[0])

    weights = ancillary_weights(env, prior_params, rows, x_bar, opts, path)
    quantiles = tight.error_quantiles(opts.error_quantile) if opts.tightening == "reachable" else (1.0,)
    candidates, refusal = [], None
    for quantile in quantiles:  # the largest error bound whose tube leaves room; each gain's tube differs
        for q, r in weights:
            try:
                K, P_lqr = discrete_lqr_gain(Ad[0], Bd[0], np.diag(q), np.diag(r))
            except ValueError as error:
                raise ValueError(f"{path}.q_lqr: the ancillary LQR has no stabilising solution ({error})") from None
            A_cl = Ad[0] - Bd[0] @ K
            P_rpi = None
            margins = np.zeros((stages, rows.num_rows))
            if opts.tightening == "rpi":
                P_rpi = tight.rpi_ellipsoid(A_cl, errors, opts.tau, opts.sdp_solver, f"{path}.tau")
                margins = np.tile(tight.ellipsoid_tightening(rows.Ax, rows.Au, K, P_rpi), (stages, 1))
            elif opts.tightening == "reachable":
                _, w_bar = tight.error_box(errors, quantile)
                margins = tight.reachable_tightening(rows.Ax, rows.Au, K, A_cl, w_bar, stages)
            # The tail is the terminal set: it keeps the last free stage's tightening (the tube's margins keep
            # growing along a slow closed loop, and a tail 100 steps long would tighten the rows away).
            margins[H:] = margins[H - 1]
            margins = margins + opts.constraint_margin * rows.soft[None, :]
            try:
                _check_margins(rows, margins, u_low, u_high, path)
            except ValueError as error:
                refusal = error  # this gain's tube leaves no input; another candidate's may
                continue
            reason = tight.tube_room(rows, margins, x_bar, u_bar)
            if reason is not None:
                refusal = ValueError(
                    f"{path}.tightening: {reason}; lower the model error (sample_half_width, plant_draws, a better "
                    "prior), give a smaller error_quantile or make the ancillary LQR gentler (larger r_lqr)"
                )
                continue
            candidates.append((K, P_rpi, margins, quantile, (np.diag(q), np.diag(r), P_lqr)))
        if candidates:
            break
    if not candidates:
        raise refusal
    if len(candidates) > 1:  # keep the ancillary LQR whose terminal set holds the most sampled states
        states = validation_states(env, prior_params, 2000, jax.random.key(1))
        held = [
            terminal_set_fraction(states, Ad[0], Bd[0], c[0], K, x_bar, u_bar, rows, margins[H:])
            for K, _, margins, _, _ in candidates
        ]
        K, P_rpi, margins, quantile, lqr = candidates[int(np.argmax(held))]
    else:
        K, P_rpi, margins, quantile, lqr = candidates[0]
    affine = qp_lib.AffineModel(Ad=Ad, Bd=Bd, c=c, x_bar=x_bar[None], u_bar=u_bar, K=K[None], P=np.zeros((1, nx, nx)))
    qp = decision_prefix(qp_lib.build_qp(affine, stages, np.zeros((nx, nx)), np.zeros((nu, nu)), rows), H, nu)
    return Problem(
        opts, env.system.name, nx, nu, H, stages, affine, K, x_bar, u_bar, rows, margins, u_low, u_high, errors,
        P_rpi, qp, quantile, *lqr,
    )  # fmt: skip


def mpsc_rows(env, prior_params, path: str):
    """``(rows, u_low, u_high)``: the actuator limits and the env's linear constraints (``_constraint_rows``) with
    the system's failure bounds appended as state rows (a plan through them, which the linearised model may
    find, would lose the plant), and the clip box, N.

    Raises:
        ValueError: naming ``path`` when the env constrains no state (there is nothing to certify).
    """
    rows, _, _, u_low, u_high = _constraint_rows(env, prior_params, True)
    if not np.any(rows.soft):
        raise ValueError(
            f"{path}: the env has no linear constraint on the state, so there is nothing to certify; make the env "
            "with constraints (e.g. {'type': 'bounded', 'on': 'state', ...})"
        )
    A, b = failure_rows(env.system)
    rows = qp_lib.ConstraintRows(
        Ax=np.concatenate([rows.Ax, A]),
        Au=np.concatenate([rows.Au, np.zeros((A.shape[0], env.nu))]),
        b=np.concatenate([rows.b, b]),
        soft=np.concatenate([rows.soft, np.ones(A.shape[0], bool)]),
    )
    return rows, u_low, u_high


def terminal_steps(env, opts: Options) -> int:
    """Control steps of the plan's tail (``terminal_horizon`` seconds, rounded up; 0 without a terminal set)."""
    return max(0, math.ceil(opts.terminal_horizon / env.dt - 1e-9))


def ancillary_weights(env, prior_params, rows, x_bar, opts: Options, path: str) -> list[tuple[np.ndarray, ...]]:
    """Candidate ``(q (nx,), r (nu,))`` of the ancillary LQR: ``q_lqr``, ``r_lqr`` where given, else the backup
    controller's candidates (``scg_algorithms.safety_filters.backup.backup_weights``) from the state rows."""
    nx, nu = env.nx, env.nu
    state_rows = rows.soft & np.all(rows.Au == 0.0, axis=1)
    norms = np.linalg.norm(rows.Ax[state_rows], axis=1)
    defaults = backup_weights(
        env, prior_params, rows.Ax[state_rows] / norms[:, None], rows.b[state_rows] / norms, x_bar
    )
    candidates = []
    for default_q, default_r in defaults:
        q = diagonal_weight(opts.q_lqr, f"{path}.q_lqr", default_q, nx)
        r = diagonal_weight(opts.r_lqr, f"{path}.r_lqr", default_r, nu)
        if min(r) <= 0:
            raise ValueError(f"{path}.r_lqr: the LQR input weight must be positive, got {list(r)}")
        candidates.append((q, r))
        if opts.q_lqr is not None and opts.r_lqr is not None:
            break
    return candidates


def terminal_set_fraction(states, Ad, Bd, c, K, x_bar, u_bar, rows, margins) -> float:
    """The fraction of ``states`` (n, nx) from which the ancillary LQR ``u = u_bar - K (x - x_bar)`` on the
    linearised prior ``x+ = Ad x + Bd u + c`` keeps every row ``Ax x+ + Au u <= b - margin_j`` for the
    ``len(margins)`` steps of the terminal tail."""
    x = np.asarray(states, dtype=np.float64)
    held = np.ones(x.shape[0], bool)
    for margin in margins:
        u = u_bar - (x - x_bar) @ K.T
        x = x @ Ad.T + u @ Bd.T + c
        held &= np.all(x @ rows.Ax.T + u @ rows.Au.T <= rows.b - margin, axis=1)
    return float(held.mean())


def decision_prefix(qp, horizon: int, nu: int):
    """``qp`` (condensed over ``qp.horizon`` stages) with only the first ``horizon`` decisions ``v_0..v_{H-1}``:
    the later ones are 0, so those stages follow the ancillary LQR (the plan's tail, whose rows are the terminal
    set). The parameter layout ``theta`` keeps every stage."""
    nz_full, nz = qp.hess.shape[-1], horizon * nu
    if nz_full == nz:
        return qp
    return dataclasses.replace(
        qp,
        hess=qp.hess[:, :nz, :nz],
        G=qp.G[:, :, :nz],
        q_map=qp.q_map[:, :nz, :],
        u0_map=np.concatenate([qp.u0_map[:, :, :nz], qp.u0_map[:, :, nz_full:]], axis=2),
    )


def _check_margins(rows, margins, u_low, u_high, path: str) -> None:
    """Raise when the tightening leaves an input row with no room (its margin exceeds the box it bounds)."""
    for r in range(rows.num_rows):
        if np.any(rows.Ax[r] != 0.0):
            continue
        nonzero = np.flatnonzero(rows.Au[r])
        if nonzero.size != 1:
            continue
        i = nonzero[0]
        if margins[:, r].max() >= 0.5 * (u_high[i] - u_low[i]):
            raise ValueError(
                f"{path}.tightening: the input margin {margins[:, r].max():.3g} N leaves no admissible input "
                f"(limits [{u_low[i]:.3g}, {u_high[i]:.3g}] N); lower the model error (sample_half_width, a better "
                "prior) or make the ancillary LQR gentler (larger r_lqr)"
            )


# --------------------------------------------------------------------------------------------- JAX filter
class LinearMPSCParams(NamedTuple):
    """The filter's arrays (a pytree; the harness passes it as ``filter_params``).

    ``h = Hx @ x + h0`` (p,) and ``u_0 = U0z @ z + U0x @ x + u0c`` give the QP of state ``x``; ``hess`` (nz, nz),
    ``G`` (p, nz) and ``M_inv`` (the ADMM's shared inverse; ``None`` with the other solvers) are the same for every
    copy; with every solver ``G``, ``Hx``, ``h0`` check a plan's rows over the whole tail. ``K`` (nu, nx),
    ``x_bar`` (nx,), ``u_bar`` (nu,): the ancillary feedback about the goal; ``u_low``, ``u_high``: the clip box, N.
    ``structured``: with ``solver="structured"``, ``(prepared, c, q, r, bounds)`` of ``mpsc_structured``, else
    ``None``.
    """

    hess: Any
    G: Any
    Hx: Any
    h0: Any
    U0z: Any
    U0x: Any
    u0c: Any
    M_inv: Any
    K: Any
    x_bar: Any
    u_bar: Any
    u_low: Any
    u_high: Any
    structured: Any = None


class LinearMPSCState(NamedTuple):
    """Per copy: ``v_plan`` (H, nu) the last feasible plan's decisions, ``kinf`` (int32) steps since it was made
    (H or more: none left, plain LQR), ``warm`` the solver's warm start: a ``structured.Warm`` (``rho = 0``: none);
    with ``solver="admm"`` its ``values`` and ``multipliers`` hold the ADMM's last iterate ``z`` (nz,) and ``y``
    (p,)."""

    v_plan: Any
    kinf: Any
    warm: Any


def qp_data(problem: Problem) -> dict:
    """The QP of ``problem`` in the reduced form of ``LinearMPSCParams`` (numpy float64, before the ADMM inverse)."""
    qp, nx, nu, H = problem.qp, problem.nx, problem.nu, problem.stages
    m = problem.rows.num_rows
    norms = np.linalg.norm(np.concatenate([problem.rows.Ax, problem.rows.Au], axis=1), axis=1)
    h_map = qp.h_map[0].copy()
    # Stage j's copy of row r sits at j * m + r (scaled to unit norm by build_qp): lower its bound by the margin.
    h_map[:, -1] -= (problem.margins / norms[None, :]).reshape(H * m)
    theta_rest = np.concatenate([np.tile(qp.c_table[0], H), np.tile(qp.w_table[0], H), [1.0]])
    nz = qp.num_decisions
    u0_map = qp.u0_map[0]
    U0z, U0x, u0c = u0_map[:, :nz], u0_map[:, nz : nz + nx], u0_map[:, nz + nx :] @ theta_rest
    # The regulariser leaves v_0 alone, so a proposed input that starts a feasible plan is the exact optimum.
    _, W = mpsc_structured.plan_weight(problem)
    hess = U0z.T @ U0z + np.kron(np.diag(np.r_[0.0, np.ones(nz // nu - 1)]), W)
    return {
        "hess": hess,
        "G": qp.G[0],
        "Hx": h_map[:, :nx],
        "h0": h_map[:, nx:] @ theta_rest,
        "U0z": U0z,
        "U0x": U0x,
        "u0c": u0c,
    }


def qp_of(params: LinearMPSCParams, x, u_uncertified):
    """``(q (nz,), h (p,))`` of the QP ``min 1/2 z^T hess z + q^T z  s.t.  G z <= h`` for state ``x`` and the
    proposed input ``u_uncertified`` (pure JAX)."""
    q = params.U0z.T @ (params.U0x @ x + params.u0c - u_uncertified)
    h = params.Hx @ x + params.h0
    return q, h


def make_linear_mpsc(env, prior_params, options=None, plant_params=None) -> Filter:
    """Batched linear MPSC in JAX (see the module docstring).

    Args:
        env: the environment (with linear state constraints). prior_params: ``EnvParams`` of the filter's model
            (its ``constraints`` are the constraint values). options: ``Options`` mapping
            (``safety_filters.linear_mpsc``). plant_params: where the model-error samples come from (default
            ``env.default_params``).

    Returns:
        A JAX ``Filter`` named ``"linear_mpsc"``; ``certify(obs, u_uncertified, params, state)`` returns the certified
        input (nu,), N, ``LinearMPSCState`` and ``FilterInfo``. ``info`` holds the host ``problem`` (and with the
        structured solver ``structured``, the ``mpsc_structured.StructuredMPSC``).

    Raises:
        ValueError: naming ``safety_filters.linear_mpsc.<field>`` for a bad option or an infeasible tightening.
    """
    problem = build_problem(env, prior_params, options, plant_params)
    opts = problem.options
    dtype = jnp.zeros(()).dtype
    data = qp_data(problem)
    as_jax = lambda a: jnp.asarray(a, dtype)  # noqa: E731
    smpsc = mpsc_structured.build(problem) if opts.solver == "structured" else None
    params = LinearMPSCParams(
        **{k: as_jax(v) for k, v in data.items()},
        M_inv=None
        if opts.solver != "admm"
        else mpsc_admm.admm_inverse(data["hess"], data["G"], opts.admm_rho, opts.admm_sigma, dtype),
        K=as_jax(problem.K),
        x_bar=as_jax(problem.x_bar),
        u_bar=as_jax(problem.u_bar),
        u_low=as_jax(problem.u_low),
        u_high=as_jax(problem.u_high),
        structured=None
        if smpsc is None
        else (smpsc.prepared, as_jax(smpsc.c), as_jax(smpsc.q), as_jax(smpsc.r), tuple(map(as_jax, smpsc.bounds))),
    )
    nx, nu, H = problem.nx, problem.nu, problem.horizon
    nz, p = data["hess"].shape[0], data["G"].shape[0]
    rows_per_stage = p // problem.stages
    system = problem.system
    warm_size = (smpsc.layout.num_dense,) * 2 if smpsc is not None else (nz, p)

    def reset(key):
        warm = structured.Warm(jnp.zeros(warm_size[0], dtype), jnp.zeros(warm_size[1], dtype), jnp.zeros((), dtype))
        return LinearMPSCState(jnp.zeros((H, nu), dtype), jnp.asarray(H, jnp.int32), warm)

    def solve_structured(params, x, u_target, state):
        """``(v (nz,), warm, usable, u_least)`` of the structured solver (``usable``: not numerical; ``u_least``: the
        first input of the least-violating plan, the plain LQR's after a numerical failure)."""
        prepared, c, q, r, bounds = params.structured
        warm = state.warm if opts.warm_start else None  # the previous plan, one stage on (warm_steps=1)
        sol = structured.solve_prepared(
            smpsc.layout, prepared, x, c, q, r.at[0].add(-u_target), bounds, warm, smpsc.settings, warm_steps=1
        )
        # The plan's decisions in the ancillary parametrisation, where the tail's rows (G) are written.
        v = sol.u + (sol.x[:H] - params.x_bar) @ params.K.T - params.u_bar
        usable = (sol.status != structured.INFEASIBLE) & (sol.status != structured.NUMERICAL)
        u_lqr = params.u_bar - params.K @ (x - params.x_bar)
        return v.reshape(-1), sol.warm, usable, jnp.where(usable, sol.u[0], u_lqr)

    def solve_admm(params, x, q, h, state):
        # Warm start from the last solution shifted by one stage (its tail is the plan from here on).
        z0 = jnp.concatenate([state.warm.values[nu:], jnp.zeros(nu, dtype)]) if opts.warm_start else None
        y = state.warm.multipliers
        y0 = jnp.concatenate([y[rows_per_stage:], y[-rows_per_stage:]]) if opts.warm_start else None
        sol = mpsc_admm.admm_solve(
            params.M_inv, params.G, q, h, iterations=opts.admm_iterations, rho=opts.admm_rho,
            sigma=opts.admm_sigma, alpha=opts.admm_alpha, z0=z0, y0=y0,
        )  # fmt: skip
        u_lqr = params.u_bar - params.K @ (x - params.x_bar)
        return sol.z, structured.Warm(sol.z, sol.y, jnp.ones((), dtype)), jnp.ones((), bool), u_lqr

    def solve_qpax(params, x, q, h, state):
        # Scaled up: qpax floors its duals at sqrt(eps), which shifts z by about hess^-1 G^T sqrt(eps); with
        # the regulariser's 1e-4 eigenvalues that is 1e-4 N unscaled (scg_algorithms.mpc.qp explains the floor).
        sol = qp_lib.solve_qp(
            QPAX_OBJECTIVE_SCALE * params.hess, QPAX_OBJECTIVE_SCALE * q, params.G, h,
            max_iter=opts.qpax_iterations, solver_tol=1e-10, feasibility_tol=opts.feasibility_tol,
        )  # fmt: skip
        u_lqr = params.u_bar - params.K @ (x - params.x_bar)
        return sol.z, state.warm, sol.status != qp_lib.STATUS_FAILED, u_lqr

    def certify(obs, u_uncertified, params, state):
        obs = jnp.asarray(obs)
        u_uncertified = jnp.asarray(u_uncertified, dtype)
        if obs.ndim != 1 or obs.shape[0] < nx or u_uncertified.shape != (nu,):
            raise ValueError(
                f"linear_mpsc: built for {system} (state of {nx} entries, input of {nu}); got an observation of "
                f"shape {tuple(obs.shape)} and an input of shape {tuple(u_uncertified.shape)} (one copy)"
            )
        x = jnp.asarray(obs[:nx], dtype)
        u_target = jnp.clip(u_uncertified, params.u_low, params.u_high)
        q, h = qp_of(params, x, u_target)
        if opts.solver == "structured":
            z, warm, usable, u_last_resort = solve_structured(params, x, u_target, state)
        elif opts.solver == "admm":
            z, warm, usable, u_last_resort = solve_admm(params, x, q, h, state)
        else:
            z, warm, usable, u_last_resort = solve_qpax(params, x, q, h, state)
        # Every solver's plan is checked on every row of the horizon and the tail (the structured solver saw the
        # tail through its non-redundant rows only).
        excess = params.G @ z - h
        u_qp = params.U0z @ z + params.U0x @ x + params.u0c
        feasible = usable & (jnp.max(excess) <= opts.feasibility_tol) & jnp.all(jnp.isfinite(u_qp))
        # The proposal itself where the solved plan, started with it instead (v_0 enters u_0 with the identity),
        # still holds every row: the solver's error on a safe proposal is no correction.
        passes = feasible & (jnp.max(excess + params.G[:, :nu] @ (u_target - u_qp)) <= opts.feasibility_tol)
        u_qp = jnp.where(passes, u_target, u_qp)
        kinf = jnp.where(feasible, 0, jnp.minimum(state.kinf + 1, H))
        v_plan = jnp.where(feasible, z[: H * nu].reshape(H, nu), state.v_plan)
        u_plan = params.u_bar - params.K @ (x - params.x_bar) + v_plan[jnp.minimum(kinf, H - 1)]
        u_backup = jnp.where(kinf < H, u_plan, u_last_resort)
        u = jnp.clip(jnp.where(feasible, u_qp, u_backup), params.u_low, params.u_high)
        # A failed solve's iterate is a poor warm start: the next solve starts cold.
        warm = jax.tree.map(lambda a: jnp.where(feasible, a, jnp.zeros_like(a)), warm)
        applied = jnp.where(feasible, CERTIFIED, jnp.where(kinf < H, BACKUP_PLAN, BACKUP_CONTROLLER))
        info = FilterInfo(
            feasible=feasible,
            slack=jnp.zeros((), dtype),
            correction=applied_correction(u, u_uncertified, params.u_low, params.u_high),
            applied=applied,
        )
        return u, LinearMPSCState(v_plan, kinf.astype(jnp.int32), warm), info

    info = {
        "problem": problem, "options": opts, "horizon": H, "solver": opts.solver, "structured": smpsc,
        "error_quantile": problem.error_quantile, "tightening_max": problem.margins.max(axis=0).tolist(),
    }  # fmt: skip
    return Filter(name="linear_mpsc", system=system, params=params, reset_fn=reset, certify_fn=certify, info=info)


# --------------------------------------------------------------------------------------------- CasADi reference
@dataclasses.dataclass(frozen=True, eq=False)
class LinearMPSCCasadi:
    """The linear MPSC for one copy on the host (``is_jax = False``): ``casadi.Opti("conic")`` with qpOASES or OSQP.

    Formulated independently of the condensed QP: the inputs ``U`` (nu, H) are the variables, the states CasADi
    expressions of them, the rows and their margins imposed per stage, the cost ``1/2 |u_0 - u_L|^2 + 1/2 reg
    sum_{j>=1} |u_j - u_eq + K (x_j - x_goal)|^2`` (the JAX filter's ``v``). ``certify`` applies the same fallback.
    """

    name: str
    system: str
    problem: Problem
    opti: Any
    variables: dict
    parameters: dict
    params: Any = None
    is_jax: ClassVar[bool] = False

    def reset(self, key):
        return {"v_plan": np.zeros((self.problem.horizon, self.problem.nu)), "kinf": self.problem.horizon}

    def solve(self, x, u_uncertified) -> tuple[np.ndarray, np.ndarray, bool]:
        """``(u_0 (nu,), v (H, nu), success)`` of the QP for state ``x`` and proposed input ``u_uncertified``."""
        opti, p = self.opti, self.parameters
        opti.set_value(p["x0"], np.asarray(x, dtype=np.float64))
        opti.set_value(p["u_l"], np.asarray(u_uncertified, dtype=np.float64))
        try:
            opti.solve()
            success = bool(opti.stats()["success"])
        except RuntimeError:
            success = False
        u0 = np.asarray(opti.debug.value(self.variables["U"][:, 0]), dtype=np.float64).reshape(-1)
        V = np.asarray(opti.debug.value(self.variables["V"]), dtype=np.float64).reshape(self.problem.nu, -1).T
        return u0, V, success and bool(np.all(np.isfinite(u0)))

    def certify(self, x_or_obs, u_uncertified, filter_params, filter_state):
        problem = self.problem
        obs = np.asarray(x_or_obs, dtype=np.float64)
        u_l = np.asarray(u_uncertified, dtype=np.float64).reshape(-1)
        if obs.ndim != 1 or obs.shape[0] < problem.nx or u_l.shape != (problem.nu,):
            raise ValueError(
                f"linear_mpsc_casadi: built for {problem.system} (state of {problem.nx} entries, input of "
                f"{problem.nu}); got an observation of shape {obs.shape} and an input of shape {u_l.shape}"
            )
        x = obs[: problem.nx]
        u0, V, success = self.solve(x, u_l)
        H = problem.horizon
        if success:
            state = {"v_plan": V, "kinf": 0}
            u = u0
        else:
            kinf = min(filter_state["kinf"] + 1, H)
            v = filter_state["v_plan"][kinf] if kinf < H else np.zeros(problem.nu)
            state = {"v_plan": filter_state["v_plan"], "kinf": kinf}
            u = problem.u_bar - problem.K @ (x - problem.x_bar) + v
        u = np.clip(u, problem.u_low, problem.u_high)
        applied = CERTIFIED if success else (BACKUP_PLAN if state["kinf"] < H else BACKUP_CONTROLLER)
        correction = applied_correction(u, u_l, problem.u_low, problem.u_high, np)
        return u, state, FilterInfo(feasible=success, slack=0.0, correction=correction, applied=applied)


def make_linear_mpsc_casadi(env, prior_params, options=None, plant_params=None) -> LinearMPSCCasadi:
    """The linear MPSC for one copy on the host with CasADi (same ``Options`` and offline data as
    ``make_linear_mpsc``; see ``LinearMPSCCasadi``)."""
    import casadi as cs

    problem = build_problem(env, prior_params, options, plant_params, CASADI_PATH)
    opts = problem.options
    nx, nu, H = problem.nx, problem.nu, problem.horizon
    affine, rows = problem.affine, problem.rows
    A, B, c = cs.DM(affine.Ad[0]), cs.DM(affine.Bd[0]), cs.DM(affine.c[0])
    K, x_bar, u_bar = cs.DM(problem.K), cs.DM(problem.x_bar), cs.DM(problem.u_bar)

    opti = cs.Opti("conic")
    U = opti.variable(nu, H)
    x0 = opti.parameter(nx)
    u_l = opti.parameter(nu)
    X = [x0]
    V = []
    for j in range(H):
        V.append(U[:, j] - u_bar + K @ (X[j] - x_bar))
        X.append(A @ X[j] + B @ U[:, j] + c)
    V = cs.horzcat(*V)
    du = U[:, 0] - u_l
    W = cs.DM(mpsc_structured.plan_weight(problem)[1])
    opti.minimize(0.5 * cs.dot(du, du) + 0.5 * sum(cs.bilin(W, V[:, j], V[:, j]) for j in range(1, H)))
    Ax, Au = cs.DM(rows.Ax), cs.DM(rows.Au)
    for j in range(H):
        opti.subject_to(Ax @ X[j + 1] + Au @ U[:, j] <= cs.DM(rows.b - problem.margins[j]))
    x_tail = X[H]
    for j in range(H, problem.stages):  # the terminal set: the tail under the ancillary LQR keeps the rows
        u_tail = u_bar - K @ (x_tail - x_bar)
        x_tail = A @ x_tail + B @ u_tail + c
        opti.subject_to(Ax @ x_tail + Au @ u_tail <= cs.DM(rows.b - problem.margins[j]))
    opti.solver(opts.casadi_solver, {**qp_lib.casadi_qp_options(opts.casadi_solver, 1e-10), "expand": True})
    return LinearMPSCCasadi(
        name="linear_mpsc_casadi",
        system=problem.system,
        problem=problem,
        opti=opti,
        variables={"U": U, "V": V},
        parameters={"x0": x0, "u_l": u_l},
    )


__all__ = [
    "CASADI_SOLVERS",
    "LinearMPSCCasadi",
    "LinearMPSCParams",
    "LinearMPSCState",
    "Options",
    "PATH",
    "Problem",
    "SOLVERS",
    "TIGHTENINGS",
    "build_problem",
    "make_linear_mpsc",
    "make_linear_mpsc_casadi",
    "qp_data",
    "qp_of",
]
