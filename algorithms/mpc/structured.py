"""The structured horizon-QP solver every MPC-based method uses in JAX: condensing, an OSQP-style ADMM and a dual
active-set method.

Problem (one copy; ``N`` stages, ``nx`` states, ``nu`` inputs; the env's convention: stage ``k`` constrains the
state it reaches and the input it commands)::

    min   sum_{k=0}^{N-1}  1/2 x_{k+1}^T Q_k x_{k+1} + q_k^T x_{k+1} + 1/2 u_k^T R_k u_k + r_k^T u_k  [+ penalties]
    s.t.  x_0 = x_init,      x_{k+1} = A_k x_k + B_k u_k + c_k
          u_low_k   <= u_k                      <= u_high_k       (always hard)
          x_low_k   <= x_{k+1}[i]               <= x_high_k       (the state entries i of ``Layout.x_rows``)
          row_low_k <= C_k x_{k+1} + D_k u_k    <= row_high_k     (``Layout.num_rows`` general rows)

``Q_{N-1}`` is the terminal weight. Every matrix may change along the horizon (the linearisations of SQP-RTI) and
between copies; bounds may be infinite. A soft row (``Layout.soft_x``, ``Layout.soft_rows``) may be violated by
``e >= 0`` (in the row's units: m, rad, N) at the price ``l1 e + 1/2 l2 e^2`` per side, either per stage
(``slack="stage"``: every stage's violation is priced) or with one slack per row and side for the whole horizon
(``slack="shared"``: the worst violation over the horizon is priced, as safe-control-gym's MPC does). Both are
priced inside the ADMM's prox (below), so soft rows add no variables.

**Condensing.** The states are eliminated with a pre-stabilising change of variables ``u_k = -K_k x_k + v_k``
(``HorizonQP.K``, e.g. the LQR gain; zeros give the plain inputs): ``x_{k+1} = Ex_k v + ex_k`` and
``u_k = Eu_k v + eu_k``. The solution does not depend on ``K``; its conditioning does. On the upright cart-pole at
15 Hz (horizon 20) the plain inputs' Hessian has a condition number of 2e5, and float32 ADMM on it stalls 4e-2 N
from the optimum however many iterations it runs (float64: 1e-10 N in 50), because the plain linear term is large
and mostly cancels; with ``K`` the LQR gain, float32 reaches 1e-6 N in 25 iterations. The QP is then
``min 1/2 v^T H v + g^T v  s.t.  low <= G v <= high`` where every row (the inputs, the state boxes, the general
rows) is a dense row of ``G``, stage by stage, in units between its interval's half-width and its norm
(``_row_scales``), and the objective is scaled so that its largest input diagonal is 1.

**ADMM** (OSQP, Stellato et al. 2020, with relaxation ``alpha``, one step size ``t`` per copy and no proximal term,
since ``G`` has full column rank: every input has its row)::

    v~ = (H + t G^T G)^-1 (G^T (t s - y) - g),     s~ = G v~
    s^ = alpha s~ + (1 - alpha) s
    s  = prox(s^ + y / t)    (the projection onto [low, high]; for soft rows, the prox of their penalty)
    y  = y + t (s^ - s)

Without a proximal term OSQP's relaxed primal iterate enters no update, so it is not carried; the residuals use
the latest ``v~``. Two ways to apply the inverse:

- ``prepare`` + ``solve_prepared`` (matrices shared by every copy and call, e.g. linear MPC about the goal):
  everything that does not depend on the copy is computed once on the host in float64, including the generalised
  eigenvectors ``T`` of ``(H, G^T G)`` (``T^T H T = diag(lam)``, ``T^T G^T G T = I``), so that
  ``(H + t G^T G)^-1 = T diag(1 / (lam + t)) T^T`` for *every* ``t``. In ``xi = T^-1 v`` an iteration is
  ``xi~ = ((G T)^T (t s - y) - T^T g) / (lam + t)``, ``s~ = (G T) xi~``: two products with one matrix shared by
  the batch (a GEMM under ``vmap``), and ``t`` adapts per copy at no cost. With ``adaptive_rho=False`` the two
  products fold into one ``(p, p)`` matrix for the initial ``t`` where that is cheaper (``p <= 2 n``: ``p^2``
  multiplications against ``2 p n``). Rows that are zero for the whole family (a general row imposed at one stage
  only, with zero ``C``, ``D`` at the others, as the MPSC's terminal rows) are left out of the ADMM: their value
  is 0 whatever ``v``, so it runs on the ``k`` other rows (the MPSC's 275 rows, 83 of them not zero); a hard one
  whose bounds exclude 0 makes the QP ``INFEASIBLE``.
- ``solve`` (matrices per copy, e.g. the QPs of SQP and SQP-RTI): condenses and factorises per copy (Cholesky of
  ``H + t G^T G``, kept as ``(H + t G^T G)^-1 [G^T, g]``), refactorised when ``t`` has moved by more than
  ``Settings.refactor_ratio``. With ``adaptive_rho=False`` and ``p <= 2 n`` it also keeps ``G`` times that matrix,
  and an iteration is one ``(p, p)`` product (``v~`` is formed at the checks).

**Loops and tolerances.** At most ``Settings.max_iterations`` iterations (rounded up to a multiple of
``check_every``), in segments of ``check_every`` (a ``lax.fori_loop`` inside a ``lax.while_loop``). After each
segment, on the scaled problem: OSQP's stopping test (``|G v~ - s|_inf <= eps_abs + eps_rel max(|G v~|_inf,
|s|_inf)`` and ``|H v~ + g + G^T y|_inf <= eps_abs + eps_rel max(|H v~|_inf, |G^T y|_inf, |g|_inf)``; on the shared
path the dual residual is measured in the coordinates ``xi``), OSQP's certificate of primal infeasibility on the
hard rows (``|G^T dy|_inf <= eps_infeasible |dy|_inf`` and ``high^T dy+ + low^T dy- <= -eps_infeasible
|dy|_inf``), and OSQP's step-size rule ``t <- t sqrt(relative primal residual / relative dual residual)``. Under
``vmap`` a plain while loop would run every copy until the slowest stops; on a CPU (``_chunk``), once at most half
of the batch still runs, each pass (a segment) runs on at most ``ADMM_CHUNK`` copies still running, gathered from
the batch (``scg_jax.tracing.compacted_while_loop``), so a batch pays for the segments its copies need.
``eps_abs = eps_rel = 0`` runs every solve to the cap in a plain loop (no copy waits for another, the fastest
batched setting for a fixed count). Then at most ``polish_rounds`` rounds of the active-set polish (``_polish``,
with its acceptance tolerances; more than one round: compacted as the ADMM's segments), and, for a copy whose ADMM
stopped at the cap and whose rounds found no acceptable plan, at most ``dual_active_set_steps`` steps of a dual
active-set method (``_dual_active_set``, run only for the copies that need it, ``DUAL_ACTIVE_SET_CHUNK`` at a
time: ``scg_jax.tracing.where_needed``).

**Dual active-set method** (``Settings.method = "dual_active_set"``; ``prepare`` + ``solve_prepared`` with hard rows
only). Goldfarb and Idnani's method in the coordinates ``xi`` (``H = diag(lam)`` there) from the minimiser without
rows, ``xi = -T^T g / lam``: each step raises the force on the most violated row until it reaches its bound or a held
multiplier reaches zero; the set's rows and the inverse of its Schur matrix are kept in ``active_set_slots`` slots
and updated per step (``_active_set_solve``). ``max_iterations`` caps the steps. Where few rows are active at the
solution (linear MPC: a mean of 0.7-7 steps on the check problems) it is several times as fast as the ADMM, and
exact to float32's rounding. Under ``vmap`` on a CPU the copies still running after ``ACTIVE_SET_WHOLE_STEPS`` steps
are gathered, ``ACTIVE_SET_CHUNK`` at a time. It takes no warm start; its ``Solution.warm`` has ``rho = 0``.

**Solution.** The inputs are taken from the projected ``s`` (inside their box whatever the iteration count), the
states from ``v~`` through the model. ``status``: ``CONVERGED`` (0); ``MAX_ITERATIONS`` (1: the last iterate, with
its residuals and ``violation``, the largest violation of a hard row by the plan); ``INFEASIBLE`` (2: the hard rows
admit no solution; the iterate is returned); ``NUMERICAL`` (3: a non-finite iterate; the plan is the pre-stabilised
trajectory, inputs clipped to their box). Nothing returned is NaN; the caller decides what to apply on 1, 2 or 3.

Float32 by default (the dtype of ``x_init``), float64 when x64 is on; ``prepare`` computes in float64 and casts.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from scg_jax.tracing import batched_like, compacted_while_loop, where_needed

CONVERGED = 0
MAX_ITERATIONS = 1
INFEASIBLE = 2
NUMERICAL = 3
STATUS_NAMES = ("converged", "max_iterations", "infeasible", "numerical")
SLACK_MODES = ("stage", "shared")
DEFAULT_RHO = 1e-3  # the initial step size of ``solve`` when neither the settings nor a warm start give one
# The polish's acceptance in float32 of a free row's violation and a multiplier's wrong sign (a row held at its bound
# may still sit the square root of the resolution from it, the rounding of the solve). At that root (3.5e-4) the
# polish let through a plan that held a row with a multiplier of the wrong sign (2.4e-4, scaled), which put the 2D
# quadrotor's first input 2.4e-3 N from qpOASES's, and one whose free row crossed the 1D quadrotor's ceiling by
# 1.35e-4 half-widths (1.1e-3 N off).
POLISH_TOL = 1e-5
POLISH_DUAL_TOL = 2e-6
# Solves that drop the wrong-signed rows from the ADMM's set before the dual active-set method starts there.
RESTORE_ROUNDS = 3
# Under vmap on a CPU (see _chunk): copies per chunk of the dual active-set method, which runs only for the copies that
# need it (``scg_jax.tracing.where_needed``); copies per pass of the ADMM's loop with a convergence tolerance and of
# the polish's rounds (more than one), which run only on the copies still running (``compacted_while_loop``).
# Passes of 64-512 copies did about as well on the 2-core machine (linear MPC's defaults, 4,096 copies), 1,024 worse.
DUAL_ACTIVE_SET_CHUNK = 256
ADMM_CHUNK = 256
POLISH_CHUNK = 256
# The dual active-set solver (``Settings.method``): steps every copy of a batch takes together before the copies that
# still run are gathered, ACTIVE_SET_CHUNK at a time (on a CPU; see _chunk). Most copies stop within two steps (on the
# 2D quadrotor's position box 43% of the copies need none, 87% of the feasible ones at most two, 97% at most five), so
# later passes over the whole batch would mostly wait; chunks of 32-64 did best on the 2-core machine at 4,096 copies
# (256: 47k QPs/s there against 57-64k).
ACTIVE_SET_WHOLE_STEPS = 2
ACTIVE_SET_CHUNK = 64
# A copy whose set outgrows its slots is solved again with this many times as many (at most every row it can hold).
ACTIVE_SET_GROWTH = 4
METHODS = ("admm", "dual_active_set")


def _chunk(size: int) -> int | None:
    """``size`` on a CPU, where a pass over fewer copies costs about proportionally less; ``None`` (the plain loops)
    on an accelerator, where a pass over a few hundred copies may cost about as much as over thousands (not measured:
    no device was at hand)."""
    return size if jax.default_backend() == "cpu" else None


# --------------------------------------------------------------------------------------------- problem
@dataclasses.dataclass(frozen=True)
class Layout:
    """The static structure of a horizon QP (hashable; decided in Python when a controller is made).

    Attributes:
        horizon: N >= 1 stages. nx, nu: state and input sizes.
        x_rows: the state entries that carry a box row (the columns of ``x_low``/``x_high``, in this order).
        num_rows: general rows per stage (``C``, ``D``).
        soft_x: per entry of ``x_rows``, whether its row is soft. soft_rows: per general row, whether it is soft.
        slack: ``"stage"`` or ``"shared"`` (see the module docstring).
        l1, l2: the price of a violation ``e``: ``l1 e + 1/2 l2 e^2`` (objective units per row unit).
    """

    horizon: int
    nx: int
    nu: int
    x_rows: tuple = ()
    num_rows: int = 0
    soft_x: tuple | None = None
    soft_rows: tuple | None = None
    slack: str = "stage"
    l1: float = 0.0
    l2: float = 0.0

    def __post_init__(self):
        if self.horizon < 1 or self.nx < 1 or self.nu < 1:
            raise ValueError(f"Layout: horizon, nx and nu must be >= 1, got {self.horizon}, {self.nx}, {self.nu}")
        rows = tuple(int(i) for i in self.x_rows)
        if any(not 0 <= i < self.nx for i in rows) or len(set(rows)) != len(rows):
            raise ValueError(f"Layout.x_rows: expected distinct state indices in [0, {self.nx}), got {self.x_rows}")
        if self.num_rows < 0:
            raise ValueError(f"Layout.num_rows: must be >= 0, got {self.num_rows}")
        if self.slack not in SLACK_MODES:
            raise ValueError(f"Layout.slack: unknown value {self.slack!r}; allowed values are stage, shared")
        soft_x = (False,) * len(rows) if self.soft_x is None else tuple(bool(s) for s in self.soft_x)
        soft_rows = (False,) * self.num_rows if self.soft_rows is None else tuple(bool(s) for s in self.soft_rows)
        if len(soft_x) != len(rows) or len(soft_rows) != self.num_rows:
            raise ValueError("Layout: soft_x needs one flag per x_rows entry and soft_rows one per general row")
        if any(soft_x + soft_rows) and (self.l1 < 0 or self.l2 < 0 or self.l1 + self.l2 == 0):
            raise ValueError(f"Layout: soft rows need l1, l2 >= 0, not both 0; got {self.l1}, {self.l2}")
        object.__setattr__(self, "x_rows", rows)
        object.__setattr__(self, "soft_x", soft_x)
        object.__setattr__(self, "soft_rows", soft_rows)

    @property
    def stage_rows(self) -> int:
        """Rows of one stage: the inputs, the state boxes, the general rows."""
        return self.nu + len(self.x_rows) + self.num_rows

    @property
    def soft(self) -> tuple:
        """Per row of a stage, whether it is soft (input rows never are)."""
        return (False,) * self.nu + self.soft_x + self.soft_rows

    @property
    def num_decisions(self) -> int:
        """Entries of ``v``: one per stage and input."""
        return self.horizon * self.nu

    @property
    def num_dense(self) -> int:
        """Rows of ``G`` (stage-major)."""
        return self.horizon * self.stage_rows


class HorizonQP(NamedTuple):
    """The data of one horizon QP (a pytree: ``vmap`` over any leaf). Infinite bounds are allowed.

    Attributes:
        A: (N, nx, nx). B: (N, nx, nu). c: (N, nx): ``x_{k+1} = A_k x_k + B_k u_k + c_k``.
        K: (N, nu, nx) pre-stabilising gains (``u_k = -K_k x_k + v_k``; only the conditioning depends on them).
        Q: (N, nx, nx) weight of ``x_{k+1}`` (``Q[N-1]`` the terminal weight). q: (N, nx).
        R: (N, nu, nu) positive definite. r: (N, nu).
        u_low, u_high: (N, nu). x_low, x_high: (N, len(x_rows)) bounds of ``x_{k+1}[x_rows]``.
        C: (N, m, nx). D: (N, m, nu). row_low, row_high: (N, m).
    """

    A: Any
    B: Any
    c: Any
    K: Any
    Q: Any
    q: Any
    R: Any
    r: Any
    u_low: Any
    u_high: Any
    x_low: Any
    x_high: Any
    C: Any
    D: Any
    row_low: Any
    row_high: Any


MATRIX_FIELDS = ("A", "B", "K", "Q", "R", "C", "D")
BOUND_FIELDS = ("u_low", "u_high", "x_low", "x_high", "row_low", "row_high")


@dataclasses.dataclass(frozen=True)
class Settings:
    """Solver settings (static; see the module docstring for the tests they enter).

    Attributes:
        method: ``"admm"`` (the ADMM, its polish and fallback below) or ``"dual_active_set"`` (``solve_prepared``
            only, hard rows only: Goldfarb and Idnani's dual active-set method from the minimiser without rows,
            ``_active_set_solve``; ``max_iterations`` caps its steps, ``active_set_slots`` sizes its set; every other
            field but ``polish_tol`` is the ADMM's).
        active_set_slots: rows the dual active-set method's set holds on its first try (its cost per step grows with
            the square of the count); a copy whose set would outgrow them is solved again with ``ACTIVE_SET_GROWTH``
            times as many, up to every row it can hold (``min(n, rows)``).
        max_iterations: cap on iterations (rounded up to a multiple of ``check_every``). check_every: iterations
            between residual checks, infeasibility tests and step-size updates.
        eps_abs, eps_rel: stopping test on the scaled problem (both 0: run to the cap). eps_infeasible: the
            certificate's tolerance.
        rho: the initial step size ``t`` (a warm start brings its own); ``None``: the smallest generalised
            eigenvalue of ``(H, G^T G)`` for ``solve_prepared`` (``suggested_rho``: on the 2D quadrotor's QP it
            reached 5e-4 N in 25 iterations where ``sqrt(lam_min lam_max)`` needed 50), ``DEFAULT_RHO`` for
            ``solve`` (pass the ``suggested_rho`` of a typical problem). rho_scale: a factor on that initial step
            size (a fixed-step solve's step size, tuned against a reference). adaptive_rho: update ``t`` at the checks
            (``False``: ``prepare`` folds the products for the initial ``t``). rho_min, rho_max: bounds of ``t``.
        alpha: relaxation in (0, 2). refactor_ratio: ``solve`` refactorises when ``t`` has moved by this factor.
        polish_rounds: rounds of the active-set polish after the ADMM (0: none; see ``_polish``).
        polish_tol: the largest violation of a hard row (in half-widths of its interval) and of complementarity a
            polished plan may have to be accepted (``None``: the square root of the dtype's resolution for a row held
            at its bound, 3.5e-4 in float32 and 1.5e-8 in float64; at most ``POLISH_TOL`` for the violation of a
            free row and ``POLISH_DUAL_TOL`` for a multiplier of the wrong sign, 1e-5 and 2e-6 in float32).
        polish_soft_rows: the polish also holds the soft rows at their bounds where it finds them there, and is
            accepted only if their multipliers stay within the violation's price (per-stage slack, ``l2 = 0``: an
            exact penalty): the soft problem's exact solution wherever no soft row is violated at it (a plan exists),
            the ADMM's where one is. ``False``: the soft rows keep the ADMM's multipliers (and its accuracy).
        dual_active_set_steps: where the ADMM stopped at its cap and no polish round was accepted, at most this
            many steps of Goldfarb and Idnani's dual active-set method on the hard rows (``_dual_active_set``; 0:
            none). The rounds can go round between active sets when the ADMM stopped far from the solution (a
            degenerate state bound); this method cannot cycle, and a step costs about one round. Must be 0 with
            ``polish_soft_rows``.
    """

    method: str = "admm"
    active_set_slots: int = 8
    max_iterations: int = 200
    check_every: int = 10
    eps_abs: float = 1e-5
    eps_rel: float = 1e-5
    eps_infeasible: float = 1e-5
    rho: float | None = None
    rho_scale: float = 1.0
    adaptive_rho: bool = True
    rho_min: float = 1e-9
    rho_max: float = 1e6
    alpha: float = 1.6
    refactor_ratio: float = 5.0
    polish_rounds: int = 3
    polish_tol: float | None = None
    polish_soft_rows: bool = False
    dual_active_set_steps: int = 0

    def __post_init__(self):
        if self.method not in METHODS:
            raise ValueError(f"Settings.method: unknown value {self.method!r}; allowed: {', '.join(METHODS)}")
        if self.active_set_slots < 1:
            raise ValueError(f"Settings.active_set_slots: must be >= 1, got {self.active_set_slots!r}")
        if self.max_iterations < 1 or self.check_every < 1:
            raise ValueError(
                f"Settings: max_iterations and check_every must be >= 1, got {self.max_iterations}, {self.check_every}"
            )
        if not 0.0 < self.alpha < 2.0:
            raise ValueError(f"Settings.alpha: must be in (0, 2), got {self.alpha!r}")
        for name in ("rho", "rho_scale", "rho_min", "rho_max", "refactor_ratio"):
            value = getattr(self, name)
            if value is not None and not value > 0:
                raise ValueError(f"Settings.{name}: must be positive, got {value!r}")
        if self.polish_rounds < 0:
            raise ValueError(f"Settings.polish_rounds: must be >= 0, got {self.polish_rounds!r}")
        if self.dual_active_set_steps < 0:
            raise ValueError(f"Settings.dual_active_set_steps: must be >= 0, got {self.dual_active_set_steps!r}")
        if self.dual_active_set_steps and self.polish_soft_rows:
            raise ValueError(
                "Settings.dual_active_set_steps: must be 0 with polish_soft_rows (it holds the hard rows only)"
            )
        if self.polish_tol is not None and self.polish_tol < 0:
            raise ValueError(f"Settings.polish_tol: must be >= 0, got {self.polish_tol!r}")
        for name in ("eps_abs", "eps_rel", "eps_infeasible"):
            if getattr(self, name) < 0:
                raise ValueError(f"Settings.{name}: must be >= 0, got {getattr(self, name)!r}")

    @property
    def segment(self) -> int:
        """Iterations between checks."""
        return min(self.check_every, self.max_iterations)

    @property
    def cap(self) -> int:
        """The iteration cap actually run: ``max_iterations`` rounded up to a multiple of ``segment``."""
        return -(-self.max_iterations // self.segment) * self.segment


class Warm(NamedTuple):
    """A warm start in the problem's units, so that it survives a change of offsets and scaling.

    Attributes:
        values: (p,) the rows' values ``s`` (m, rad, N, ...). multipliers: (p,) their multipliers.
        rho: scalar step size; ``0`` (or anything non-finite) means "no warm start".
    """

    values: Any
    multipliers: Any
    rho: Any


class Solution(NamedTuple):
    """The result of one solve (see the module docstring for ``status``).

    Attributes:
        u: (N, nu) inputs (within their box). x: (N + 1, nx) the states of the plan, ``x[0] = x_init``.
        slack: (N, stage_rows) the soft rows' violations ``e >= 0`` (row units; 0 for the others; with
            ``slack="shared"`` each row's worst over the horizon, the same at every stage).
        multipliers: (N, stage_rows) of the rows in the problem's units (> 0: the upper bound pushes, < 0: the lower
            one), in the order inputs, state boxes, general rows.
        warm: the ``Warm`` of this solution (``shift`` it for the next step).
        status: int32. iterations: int32. primal_residual, dual_residual: the scaled residuals at the last check.
        violation: the largest violation of a hard row by the plan (row units; ``inf`` after NUMERICAL), which
            tells an unconverged but usable plan from an unusable one.
    """

    u: Any
    x: Any
    slack: Any
    multipliers: Any
    warm: Warm
    status: Any
    iterations: Any
    primal_residual: Any
    dual_residual: Any
    violation: Any


# --------------------------------------------------------------------------------------------- condensing
def _maps(layout: Layout, A, B, K):
    """``(Ex (N, nx, n), Eu (N, nu, n))``: ``x_{k+1}`` and ``u_k`` as linear maps of ``v`` (offsets apart)."""
    N, nu, n = layout.horizon, layout.nu, layout.num_decisions
    select = np.zeros((N, nu, n))
    for k in range(N):
        select[k, :, k * nu : (k + 1) * nu] = np.eye(nu)

    E0 = batched_like(jnp.zeros((layout.nx, n), A.dtype), A)
    return lax.scan(_maps_step, E0, (A, B, K, jnp.asarray(select, A.dtype)))[1]


# The scans' bodies live at module level: run eagerly (on the host, at set-up), a scan is compiled per body function,
# so a closure made per call would be traced and compiled again by every ``prepare``.
def _maps_step(E, inputs):
    A_k, B_k, K_k, S_k = inputs
    Eu = S_k - small_matmul(K_k, E)
    E = small_matmul(A_k, E) + small_matmul(B_k, Eu)
    return E, (E, Eu)


def small_matmul(M, E):
    """``M @ E`` over the last two axes, as one multiply-and-sum: for the stage matrices' short contractions (nx, nu)
    under ``vmap`` XLA:CPU's batched dot ran the 2D quadrotor's condensing maps (1,024 copies) 3-4x slower."""
    return jnp.sum(M[..., :, :, None] * E[..., None, :, :], axis=-2)


def _offsets_step(x, inputs):
    A_k, B_k, K_k, c_k = inputs
    u = -K_k @ x
    x = A_k @ x + B_k @ u + c_k
    return x, (x, u)


def _offsets(A, B, K, c, x_init):
    """``(ex (N, nx), eu (N, nu))``: the states and inputs of ``v = 0`` (the pre-stabilised trajectory)."""
    return lax.scan(_offsets_step, x_init, (A, B, K, c))[1]


def _stage_values(layout: Layout, x, u, C, D):
    """The rows of every stage, ``[u_k; x_{k+1}[x_rows]; C_k x_{k+1} + D_k u_k]``, from stacked ``x`` (N, nx, ...)
    and ``u`` (N, nu, ...) (maps or vectors alike)."""
    parts = [u, x[:, np.asarray(layout.x_rows, dtype=int)]]
    if layout.num_rows:
        parts.append(jnp.einsum("kmx,kx...->km...", C, x) + jnp.einsum("kmu,ku...->km...", D, u))
    return jnp.concatenate(parts, axis=1)


def _rows(layout: Layout, Ex, Eu, C, D):
    """The unscaled rows ``G`` (p, n), stage-major."""
    return _stage_values(layout, Ex, Eu, C, D).reshape(layout.num_dense, layout.num_decisions)


def _row_offsets(layout: Layout, ex, eu, C, D):
    """The rows' values at ``v = 0`` (p,)."""
    return _stage_values(layout, ex, eu, C, D).reshape(-1)


def _row_bounds(layout: Layout, u_low, u_high, x_low, x_high, row_low, row_high):
    """``(low, high)`` (p,) of the rows."""
    N = layout.horizon
    extra = layout.num_rows > 0
    lo = jnp.concatenate([jnp.reshape(a, (N, -1)) for a in (u_low, x_low) + ((row_low,) if extra else ())], axis=1)
    hi = jnp.concatenate([jnp.reshape(a, (N, -1)) for a in (u_high, x_high) + ((row_high,) if extra else ())], axis=1)
    return lo.reshape(-1), hi.reshape(-1)


def _row_scales(layout: Layout, bounds, G, scale):
    """(p,) each row's unit: the geometric mean of half the width of its interval (1 where a bound is infinite) and
    the row's Euclidean norm in the scaled objective's units (``|G_i| / sqrt(scale)``, OSQP's equilibration).

    Either alone fails somewhere: in half-widths a state row with one far bound (1D quadrotor, z in [-10, 1.5] m)
    weighs 20x less than an input row, and the ADMM needed 20,000 iterations where OSQP needs 175; with unit rows
    the 3D quadrotor's QP with its position boxes left 5% of 200 random states 1e-3 N or more from qpOASES after
    1,000 iterations. The mean met 1e-3 N on all four systems' parity sets (200 states each, float32).
    """
    lo, hi = _row_bounds(layout, *bounds)
    width = 0.5 * (hi - lo)
    width = jnp.where(jnp.isfinite(width) & (width > 0), width, 1.0)
    row_norm = jnp.linalg.norm(G, axis=1) / jnp.sqrt(scale)
    row_norm = jnp.where(row_norm > 0, row_norm, 1.0)
    return jnp.sqrt(width * row_norm)


def _hessian(A, B, K, Q, R, Ex):
    """The unscaled condensed Hessian (n, n), from the stages' closed-loop cost-to-go.

    With ``Acl_k = A_k - B_k K_k``, ``V_N = 0``, ``P_k = Q_k + V_{k+1}`` and ``V_k = Acl_k^T P_k Acl_k + K_k^T R_k K_k``
    (the Hessian of the cost from stage ``k`` on in ``x_k``, the later ``v`` held), block ``(i, j)`` of ``H`` is
    ``B_i^T P_i B_i + R_i`` for ``i = j`` and ``M_i Ex_{i-1}[:, j]`` for ``j < i``, with ``M_i = B_i^T P_i Acl_i -
    R_i K_i`` (``v_i`` against the state ``x_i`` it meets). That is ``N`` stage-sized products where ``Ex^T Q Ex``
    takes a product over the whole ``(N nx, n)`` map: on the 2D quadrotor's SQP-RTI (1,024 copies, 10 ADMM
    iterations) the step's fixed part fell from 100 to 74 µs per copy, most of the difference that map's copies in
    memory.
    """
    N, nx, n = Ex.shape
    nu = n // N
    Acl = A - small_matmul(B, K)

    def back(V, stage):
        Acl_k, B_k, K_k, Q_k, R_k = stage
        P = Q_k + V
        PA, PB = small_matmul(P, Acl_k), small_matmul(P, B_k)
        M = small_matmul(B_k.T, PA) - small_matmul(R_k, K_k)
        D = small_matmul(B_k.T, PB) + R_k
        V = small_matmul(Acl_k.T, PA) + small_matmul(K_k.T, small_matmul(R_k, K_k))
        return 0.5 * (V + V.T), (M, 0.5 * (D + D.T))

    zero = batched_like(jnp.zeros((nx, nx), Ex.dtype), Acl)
    Q, R, K = (jnp.broadcast_to(a, (N, *a.shape[-2:])) for a in (Q, R, K))
    _, (M, D) = lax.scan(back, zero, (Acl, B, K, Q, R), reverse=True)
    lower = jnp.concatenate([jnp.zeros((nu, n), Ex.dtype), small_matmul(M[1:], Ex[:-1]).reshape(-1, n)])
    diagonal = jnp.einsum("kuv,kl->kulv", D, jnp.eye(N, dtype=Ex.dtype)).reshape(n, n)
    return lower + lower.T + diagonal


def _gradient(Q, R, q, r, Ex, Eu, ex, eu):
    """The unscaled condensed linear term (n,)."""
    g = jnp.einsum("kxn,kx->n", Ex, jnp.einsum("kxy,ky->kx", Q, ex) + q)
    return g + jnp.einsum("kun,ku->n", Eu, jnp.einsum("kuv,kv->ku", R, eu) + r)


def _input_scale(layout: Layout, H):
    """The objective scale: the largest diagonal entry of ``H`` (the inputs')."""
    return jnp.max(jnp.diagonal(H))


class _Scaled(NamedTuple):
    """One copy's scaled row data, as the ADMM sees it."""

    lo: Any  # (p,) (low - offset) / norm
    hi: Any
    off: Any  # (p,) the rows' values at v = 0 (problem units)
    norms: Any  # (p,) row units
    scale: Any  # objective scale


def _scaled(layout: Layout, off, bounds, norms, scale) -> _Scaled:
    lo, hi = _row_bounds(layout, *bounds)
    return _Scaled(lo=(lo - off) / norms, hi=(hi - off) / norms, off=off, norms=norms, scale=scale)


# --------------------------------------------------------------------------------------------- prox
def _stage_prox(v, lo, hi, l1, l2, t):
    """Per row: ``argmin_s l1 e + 1/2 l2 e^2 + t/2 (s - v)^2`` with ``e`` the distance of ``s`` to ``[lo, hi]``
    (scaled units)."""
    above = hi + jnp.maximum(0.0, (t * (v - hi) - l1) / (t + l2))
    below = lo - jnp.maximum(0.0, (t * (lo - v) - l1) / (t + l2))
    return jnp.where(v > hi, above, jnp.where(v < lo, below, v))


def _shared_level(excess, weight, l1, l2, t):
    """The slack ``e >= 0`` (problem units) of one side of one row shared by the stages:
    ``argmin_e l1 e + 1/2 l2 e^2 + t/2 sum_k weight_k^2 (excess_k - e)_+^2``, exactly: the derivative is piecewise
    linear and increasing, with kinks at the stages' excesses (sorted; ``-inf`` for an infinite bound).

    Args:
        excess: (N,) ``(v_k - high_k) * norm_k``, the stage's violation in problem units. weight: (N,) ``1 / norm``.
    """
    order = jnp.argsort(-excess)
    b, w2 = excess[order], weight[order] ** 2
    finite = jnp.isfinite(b)
    s1 = jnp.cumsum(jnp.where(finite, w2 * b, 0.0))
    s0 = jnp.cumsum(jnp.where(finite, w2, 0.0))
    level = (t * s1 - l1) / (l2 + t * s0)
    below_next = jnp.concatenate([b[1:], jnp.full((1,), -jnp.inf, b.dtype)])
    valid = finite & (level <= b) & (level >= below_next)
    return jnp.maximum(jnp.max(jnp.where(valid, level, 0.0)), 0.0)


def _shared_prox(layout: Layout, data: _Scaled, v, t, l1, l2):
    """The prox of the shared slacks' price on the soft rows, the projection on the others (scaled units)."""
    N, R = layout.horizon, layout.stage_rows
    soft = np.flatnonzero(layout.soft)
    projected = jnp.clip(v, data.lo, data.hi)
    V, lo, hi, norms = (a.reshape(N, R)[:, soft] for a in (v, data.lo, data.hi, data.norms))
    weight = 1.0 / norms
    per_row = jax.vmap(_shared_level, in_axes=(1, 1, None, None, None))
    e_up = per_row((V - hi) * norms, weight, l1, l2, t)
    e_low = per_row((lo - V) * norms, weight, l1, l2, t)
    S = jnp.clip(V, lo - weight * e_low, hi + weight * e_up)
    return projected.reshape(N, R).at[:, soft].set(S).reshape(-1)


def _soft_mask(layout: Layout, keep=None):
    """(p,) 1.0 for the soft rows, 0.0 for the hard ones, stage-major; with ``keep``, of those rows only."""
    mask = np.tile(np.asarray(layout.soft, float), layout.horizon)
    return mask if keep is None else jnp.asarray(mask)[keep]


def _projection(layout: Layout, data: _Scaled, keep=None):
    """``project(v, t)``: the ADMM's prox for this layout (static choice: a clip when no row is soft); ``keep``: the
    rows ``data`` holds, when not all of them (per-stage slack only)."""
    if not any(layout.soft):
        return lambda v, t: jnp.clip(v, data.lo, data.hi)
    l1 = layout.l1 / data.scale  # objective units per problem unit of violation
    l2 = layout.l2 / data.scale
    if layout.slack == "shared":
        if keep is not None:
            raise ValueError("_projection: shared slacks need every row of the horizon")
        return lambda v, t: _shared_prox(layout, data, v, t, l1, l2)
    mask = _soft_mask(layout, keep)
    l1_rows, l2_rows = l1 * mask * data.norms, l2 * mask * data.norms**2  # per scaled unit
    hard = mask == 0

    def project(v, t):
        return jnp.where(hard, jnp.clip(v, data.lo, data.hi), _stage_prox(v, data.lo, data.hi, l1_rows, l2_rows, t))

    return project


# --------------------------------------------------------------------------------------------- the ADMM
class _Operators(NamedTuple):
    """The linear algebra of one copy, as closures.

    - ``update(s, y, t, factor) -> (primal~, s~)``: the v-update from ``(s, y)`` (``primal~`` is ``v~``, or
      ``xi~ = T^-1 v~`` on the shared path, or what gives it there) and ``s~ = G v~``;
    - ``refactor(t, factor) -> (factor, t)``: the factor for step size ``t`` and the step size it is for;
    - ``dual(primal~, y) -> (residual, terms)``: the dual residual ``H v + g + G^T y`` (in the path's coordinates)
      and the three terms whose largest norm scales it;
    - ``GT(y)``: ``G^T y`` in the same coordinates; ``to_v(primal)``: the decisions; ``to_xi(primal)``: the
      polish's coordinates (``v`` itself on ``solve``'s path).
    """

    update: Any
    refactor: Any
    dual: Any
    GT: Any
    to_v: Any
    to_xi: Any


def _norm(a):
    return jnp.max(jnp.abs(a), initial=0.0)


def _support(dy, lo, hi):
    """``sum(hi max(dy, 0) + lo min(dy, 0))`` with ``0 * inf = 0``."""
    return jnp.sum(jnp.where(dy > 0, hi * dy, 0.0)) + jnp.sum(jnp.where(dy < 0, lo * dy, 0.0))


class _Result(NamedTuple):
    primal: Any  # the last v-update (v~, or its representation on the shared path)
    s: Any
    y: Any
    t: Any
    status: Any
    iterations: Any
    r_prim: Any
    r_dual: Any
    violation: Any  # the largest violation of a hard row by the last v-update (problem units)


def _solve_factorize(arrays, fold: bool, t):
    """``solve``'s factor for step size ``t``: ``(H + t G^T G)^-1 [G^T, g]`` (n, p + 1), and (``fold``) ``G`` times it
    (p, p + 1), each as (matrix, last column); ``arrays``: ``(Hs, Gs, gs, GTG)`` (scaled)."""
    Hs, Gs, gs, GTG = arrays
    L = jnp.linalg.cholesky(Hs + t * GTG)
    solved = jax.scipy.linalg.cho_solve((L, True), jnp.concatenate([Gs.T, gs[:, None]], axis=1))
    # Split here, not in the loop: a slice of a loop constant is copied at every iteration.
    pairs = (solved, Gs @ solved) if fold else (solved,)
    return tuple((a[:, :-1], a[:, -1]) for a in pairs)


def _solve_admm_ops(arrays, fold: bool, ratio: float) -> _Operators:
    """``solve``'s ADMM operators from its arrays ``(Hs, Gs, gs, GTG)``: the scaled Hessian (n, n), rows (p, n),
    gradient (n,) and ``Gs^T Gs`` (n, n). ``fold``: ``s~`` from one folded (p, p + 1) product (a fixed step size);
    ``ratio``: the step size's change that calls for a new factor."""
    Hs, Gs, gs, GTG = arrays

    def update(s, y, t, factor):
        # factor: (_solve_factorize(t), t).
        (M, m), *folded = factor[0]
        w = t * s - y
        v = M @ w - m
        s_tilde = folded[0][0] @ w - folded[0][1] if fold else Gs @ v
        return v, s_tilde

    def refactor(t, factor):
        matrices, t_old = factor
        stale = (t > ratio * t_old) | (t < t_old / ratio)
        # Without a refactorisation the step size stays the factorised one (the two must agree). A loop of at most
        # one pass, not lax.cond: under vmap a cond computes both branches for every copy, the loop's body runs only
        # when some copy is stale (and keeps the others' factors).
        _, matrices, t_new = lax.while_loop(
            lambda carry: carry[0],
            lambda carry: (False, _solve_factorize(arrays, fold, t), t),
            batched_like((stale, matrices, t_old), t),
        )
        return (matrices, t_new), t_new

    def dual(v, y):
        Hv, GTy = Hs @ v, Gs.T @ y
        return Hv + gs + GTy, (Hv, GTy, gs)

    return _Operators(update, refactor, dual, lambda y: Gs.T @ y, lambda v: v, lambda v: v)


def _prepared_admm_ops(arrays) -> _Operators:
    """``solve_prepared``'s ADMM operators in the coordinates ``xi`` (``T^T H T = diag(lam)``) from its arrays
    ``(GT, GT_t, lam, T, fixed, rho, h, shift_h)``: the prepared rows (p, n) and their transpose, ``lam`` (n,),
    ``T`` (n, n), the folded (p, p) product (or ``None``: an adaptive step size) and its step size, the copy's
    ``T^T g`` (n,) and, folded, its (p,) shift. Products keep the copy's vector on the left (``w @ GT`` for
    ``GT^T w``): under vmap the batch then stays the leading axis of the result, where ``GT @ xi`` gives (k, copies)
    and every use after it reads across the batch (in the ADMM's loop that transposed read cost about four times
    the product)."""
    GT, GT_t, lam, T, fixed, rho, h, shift_h = arrays
    if fixed is None:

        def update(s, y, t, factor):
            xi = ((t * s - y) @ GT - h) / (lam + t)
            return xi, xi @ GT_t

        def to_xi(primal):
            return primal

    else:

        def update(s, y, t, factor):
            # One (k, k) product per iteration (fixed is symmetric); xi~ = (GT^T (t s - y) - h) / (lam + rho) only
            # at the checks.
            return t * s - y, (t * s - y) @ fixed - shift_h

        def to_xi(primal):
            return (primal @ GT - h) / (lam + rho)

    def dual(primal, y):
        # T^T (H v + g + G^T y) with T^T H T = diag(lam): the dual residual in the coordinates xi.
        xi = to_xi(primal)
        GTy = y @ GT
        return lam * xi + h + GTy, (lam * xi, GTy, h)

    return _Operators(update, lambda t, factor: (factor, t), dual, lambda y: y @ GT, lambda p: to_xi(p) @ T.T, to_xi)


def _admm(
    layout: Layout, make_ops, ops_data, data: _Scaled, s0, y0, t0, factor, settings: Settings, keep=None, compact=True
) -> _Result:
    """Run the ADMM on one copy from ``(s0, y0, t0)`` (scaled rows; ``keep``: the rows they hold, when not all).

    ``make_ops(ops_data)`` gives the copy's ``_Operators``. With a convergence tolerance, under ``vmap`` on a CPU
    (``_chunk``), once at most half of the batch still runs, each pass (``check_every`` iterations) runs on at most
    ``ADMM_CHUNK`` copies still running (``scg_jax.tracing.compacted_while_loop``), so a batch pays its copies'
    iterations, not its slowest copy's times the batch; with tolerance 0 every copy runs to the cap (unless
    certified infeasible), and the plain loop runs, as it does with ``compact=False`` (``solve``'s path)."""
    dtype = s0.dtype
    alpha = settings.alpha
    tiny = float(jnp.finfo(dtype).tiny)

    def body(args, carry):
        # Every array the loop reads comes in args (the compacted loop's body may close over no traced value).
        ops_data, data, fixed, keep = args
        ops = make_ops(ops_data)
        project = _projection(layout, data, keep)
        hard = jnp.asarray(_soft_mask(layout, keep)) == 0

        def iterate(s, y, t, factor):
            primal, s_tilde = ops.update(s, y, t, factor)
            s_hat = alpha * s_tilde + (1.0 - alpha) * s
            s_new = project(s_hat + y / t, t)
            dy = t * (s_hat - s_new)
            return primal, s_tilde, s_new, y + dy, dy

        def check(primal, s_tilde, s, y, dy, t):
            r_prim = _norm(s_tilde - s)
            residual, terms = ops.dual(primal, y)
            r_dual = _norm(residual)
            scale_prim = jnp.maximum(_norm(s_tilde), _norm(s))
            scale_dual = jnp.maximum(jnp.maximum(_norm(terms[0]), _norm(terms[1])), _norm(terms[2]))
            converged = (r_prim <= settings.eps_abs + settings.eps_rel * scale_prim) & (
                r_dual <= settings.eps_abs + settings.eps_rel * scale_dual
            )
            dy = jnp.where(hard, dy, 0.0)  # a soft row can always be met: no certificate from it
            dy_norm = _norm(dy)
            eps = settings.eps_infeasible * dy_norm
            infeasible = (dy_norm > 0) & (_norm(ops.GT(dy)) <= eps) & (_support(dy, data.lo, data.hi) <= -eps)
            relative_prim = r_prim / jnp.maximum(scale_prim, tiny)
            relative_dual = jnp.maximum(r_dual / jnp.maximum(scale_dual, tiny), tiny)
            ratio = jnp.sqrt(relative_prim / relative_dual)
            ratio = jnp.where(jnp.isfinite(ratio) & (ratio > 0), ratio, 1.0)
            t_new = jnp.clip(t * ratio, settings.rho_min, settings.rho_max)
            excess = jnp.maximum(jnp.maximum(s_tilde - data.hi, data.lo - s_tilde), 0.0) * data.norms
            violation = _norm(jnp.where(hard, excess, 0.0))
            return converged, infeasible, r_prim, r_dual, t_new, violation

        _, s, y, t, carried, _, _, _, _, _, iterations, _ = carry
        factor = carried if settings.adaptive_rho else fixed

        def light(_, sy):
            return iterate(sy[0], sy[1], t, factor)[2:4]

        s, y = lax.fori_loop(0, settings.segment - 1, light, (s, y))
        primal, s_tilde, s, y, dy = iterate(s, y, t, factor)
        converged, infeasible, r_prim, r_dual, t_new, violation = check(primal, s_tilde, s, y, dy, t)
        done = converged | infeasible | ~(jnp.isfinite(r_prim) & jnp.isfinite(r_dual))
        if settings.adaptive_rho:
            carried, t = ops.refactor(jnp.where(done, t, t_new), factor)
        out = (primal, s, y, t, carried, converged, infeasible, r_prim, r_dual, violation)
        return *out, iterations + settings.segment, done

    def cond(args, carry):
        *_, iterations, done = carry
        return (~done) & (iterations < settings.cap)

    ops = make_ops(ops_data)
    factor, t0 = ops.refactor(t0, factor)
    # A fixed step size's factor is not carried: under vmap the loop would select every copy's factor per segment.
    fixed, carried = (None, factor) if settings.adaptive_rho else (factor, ())
    primal0, _ = ops.update(s0, y0, t0, factor)
    false, zero = jnp.zeros((), bool), jnp.zeros((), dtype)
    init = (primal0, s0, y0, t0, carried, false, false, zero, zero, zero, jnp.zeros((), jnp.int32), false)
    init = batched_like(init, data.off)  # s0 is zeros on a cold start
    args = (ops_data, data, fixed, keep)
    if compact and (settings.eps_abs > 0 or settings.eps_rel > 0):
        out = compacted_while_loop(cond, body, args, init, _chunk(ADMM_CHUNK))
    else:
        out = lax.while_loop(lambda carry: cond(args, carry), lambda carry: body(args, carry), init)
    primal, s, y, t, _, converged, infeasible, r_prim, r_dual, violation, iterations, _ = out
    status = jnp.where(converged, CONVERGED, jnp.where(infeasible, INFEASIBLE, MAX_ITERATIONS))
    finite = jnp.isfinite(r_prim) & jnp.isfinite(r_dual) & jnp.isfinite(t)
    for a in (primal, s, y):
        finite = finite & jnp.all(jnp.isfinite(a))
    status = jnp.where(finite, status, NUMERICAL).astype(jnp.int32)
    return _Result(primal, s, y, t, status, iterations, r_prim, r_dual, violation)


class _PolishOps(NamedTuple):
    """The linear algebra of the polish, as closures (one copy).

    - ``free(y) -> (primal, s)``: the minimiser of the objective plus ``y^T G v`` (no rows) and its rows;
    - ``schur(index) -> S``: ``G_I H^-1 G_I^T`` (k, k) of the rows ``index`` ((k,), or ``slice(None)``: every row);
    - ``correct(primal, index, lam) -> (primal, s)``: the minimiser with the extra force ``G_I^T lam``;
    - ``column(index, j) -> (S_Ij (k,), S_jj)``: one column of ``G H^-1 G^T`` on the rows ``index`` and its diagonal
      entry at row ``j``.
    """

    free: Any
    schur: Any
    correct: Any
    column: Any


def _solve_polish_ops(arrays) -> _PolishOps:
    """``solve``'s polish operators from its arrays ``(Gs, inv_G, inv_g)``: the scaled rows (p, n), ``H^-1 Gs^T`` (n, p)
    and ``H^-1 g`` (n,)."""
    Gs, inv_G, inv_g = arrays

    def free(y):
        v = -(inv_G @ y + inv_g)
        return v, Gs @ v

    def schur(index):
        return Gs[index] @ inv_G[:, index]

    def correct(v, index, lam):
        v = v - inv_G[:, index] @ lam
        return v, Gs @ v

    def column(index, j):
        return Gs[index] @ inv_G[:, j], Gs[j] @ inv_G[:, j]

    return _PolishOps(free, schur, correct, column)


def _prepared_polish_ops(arrays) -> _PolishOps:
    """``solve_prepared``'s polish operators in the coordinates ``xi`` (``T^T H T = diag(lam)``) from its arrays
    ``(GT, GT_t, lam, h)``: the rows (p, n) and their transpose (n, p), ``lam`` (n,) and the copy's ``T^T g`` (n,)."""
    GT, GT_t, lam_xi, h = arrays

    def free(y):
        xi = -(h + y @ GT) / lam_xi
        return xi, xi @ GT_t

    def schur(index):
        rows = GT[index]
        return (rows / lam_xi) @ rows.T

    def correct(xi, index, lam):
        xi = xi - (lam @ GT[index]) / lam_xi
        return xi, xi @ GT_t

    def column(index, j):
        row = GT[j] / lam_xi
        return GT[index] @ row, GT[j] @ row

    return _PolishOps(free, schur, correct, column)


def _rows_first(priority, k: int, levels: int = 2):
    """The indices of the rows ordered by ``priority`` ((p,) integers in ``[0, levels)``: 0 first, then 1, ...; ties
    by index), the first ``k``.

    Ranks by counting, not by a sort: under ``vmap`` on a CPU an ``argsort`` sorts each copy's rows on its own (38-49
    ms for 4,096 copies of 83 rows, about half of a polish round), while the counts of the rows before each one are a
    product with a constant triangular matrix over the whole batch, and the first ``k`` are picked by a product
    with a one-hot matrix (5-6 ms together). The products run at full float32 precision (an accelerator's default may
    round their inputs to bfloat16, which holds integers exactly only up to 256), so counts and indices are exact.
    """
    p = priority.shape[0]
    exact = functools.partial(jnp.matmul, precision=lax.Precision.HIGHEST)
    before = jnp.asarray(np.tril(np.ones((p, p)), -1), jnp.float32)  # before[i, j] = 1 for the rows j < i
    position, ahead = jnp.zeros(p, jnp.float32), jnp.zeros((), jnp.float32)
    for level in range(levels):
        at = (priority == level).astype(jnp.float32)
        position = position + at * (ahead + exact(before, at))
        ahead = ahead + jnp.sum(at)
    chosen = (position[None, :] == jnp.arange(k, dtype=jnp.float32)[:, None]).astype(jnp.float32)  # (k, p)
    return exact(chosen, jnp.arange(p, dtype=jnp.float32)).astype(jnp.int32)


def _first_extreme(values, largest: bool):
    """The index of the first largest (or smallest) entry of ``values`` (p,), as ``jnp.argmax``/``jnp.argmin`` give it
    for values without NaN (a NaN entry counts as neither; all NaN gives 0).

    Two plain reductions, not XLA's (value, index) pair reduction: under ``vmap`` on a CPU that one runs about one
    entry per clock over the batch (2.4 ms for the 4,096 copies' 240 rows of the 2D quadrotor's position box, once per
    dual active-set step: the largest single operation of a batch that runs 30), where a max and a min each
    vectorise.
    """
    extreme = jnp.max(values) if largest else jnp.min(values)
    p = values.shape[0]
    first = jnp.min(jnp.where(values == extreme, jnp.arange(p), p))
    return jnp.where(first < p, first, 0)


def _solve_held(S, held, rhs):
    """``x`` (k,) with ``S_HH x_H = rhs_H`` on the rows ``held`` ((k,), 1.0 or 0.0) of the Schur matrix ``S`` (k, k)
    and ``x = 0`` elsewhere (identity rows decouple the rows not held): one small Cholesky. ``rhs`` off the set is
    never read, so it may be infinite there (a free row's infinite bound)."""
    M = held[:, None] * S * held[None, :] + jnp.diag(1.0 - held)
    x = jax.scipy.linalg.cho_solve((jnp.linalg.cholesky(M), True), jnp.where(held > 0, rhs, 0.0))
    return jnp.where(held > 0, x, 0.0)


def _forces_at_bounds(ops: _PolishOps, side, lo, hi, s_free, k: int):
    """``(index, lam)``: the forces ``lam`` on the rows ``index`` that hold the rows of ``side`` (+1: at the upper
    bound, -1: at the lower, 0: free) at their bounds, the held rows first and at most ``k`` rows (every row, as
    ``slice(None)``, when they fit: no sort, no gathers); ``lam`` is 0 off the set."""
    held = side != 0
    index = slice(None) if k == side.shape[0] else _rows_first(jnp.where(held, 0, 1), k)
    target = jnp.where(side > 0, hi, jnp.where(side < 0, lo, 0.0))[index]
    lam = _solve_held(ops.schur(index), held[index].astype(s_free.dtype), s_free[index] - target)
    return index, lam


def _polish(
    layout: Layout, make_ops, ops_data, data: _Scaled, result: _Result, settings: Settings, keep=None, compact=True
) -> _Result:
    """Refine the ADMM's plan by a primal-dual active-set method on the hard rows (OSQP's polish, iterated).

    The soft rows keep the ADMM's multipliers as fixed forces (with ``Settings.polish_soft_rows``, they take part
    as hard rows, and the result is accepted only if their multipliers stay within the violation's price). Each
    round solves the equality-constrained QP of the current active set (the rows at a bound whose multiplier pushes
    outwards, at most ``n`` of them, gathered into an ``(n, n)`` Schur system: one small Cholesky per copy and
    round) and updates the set by the primal-dual rule ``y_i + (s_i - bound_i) > 0`` (Hintermueller et al. 2002).
    The result replaces the ADMM's, with status ``CONVERGED``, only if every hard row holds (a free row within
    ``POLISH_TOL`` of its half-width, a row held at its bound within the square root of the resolution) and no
    multiplier has the wrong sign by more than ``POLISH_DUAL_TOL`` (float32; float64: the square root for all
    three; ``Settings.polish_tol`` replaces them all); otherwise the ADMM's plan stands. Near the solution this
    converges in one or two rounds where the ADMM needs thousands of iterations (degenerate active sets along a
    state bound).
    """
    ops = make_ops(ops_data)
    n, p = layout.num_decisions, data.lo.shape[0]  # p: the rows data holds (keep: the kept rows)
    dtype = result.s.dtype
    soft = jnp.asarray(_soft_mask(layout, keep)) > 0
    # With polish_soft_rows (exact penalty per stage), the soft rows join the active set, their multipliers capped
    # by the price of a unit of violation (per scaled unit, as in _projection).
    price = jnp.where(soft, layout.l1 / data.scale * data.norms, jnp.inf)
    exact_soft = settings.polish_soft_rows and layout.slack == "stage" and layout.l2 == 0.0
    hard = jnp.ones(p, bool) if exact_soft else ~soft
    lo, hi = data.lo, data.hi
    y_soft = jnp.where(hard, 0.0, result.y)
    primal_free, s_free = ops.free(y_soft)
    # held_tol: how far a row held at its bound may sit from it (the solve's rounding); tol: how far a free row may
    # cross its bound; dual_tol: how far a multiplier may push the wrong way (see POLISH_TOL).
    if settings.polish_tol is None:
        held_tol = float(np.sqrt(np.finfo(dtype).eps))
        tol, dual_tol = min(held_tol, POLISH_TOL), min(held_tol, POLISH_DUAL_TOL)
    else:
        held_tol = tol = dual_tol = settings.polish_tol
    k = min(n, p)

    def checks(hard, lo, hi, price):
        def active_sets(s, y):
            upper = hard & jnp.isfinite(hi) & (y + (s - hi) > 0)
            lower = hard & jnp.isfinite(lo) & (y + (s - lo) < 0)
            return upper, lower & ~upper

        def acceptable(primal, s, y):
            violation = jnp.where(hard, jnp.maximum(jnp.maximum(s - hi, lo - s), 0.0), 0.0)
            held = y != 0  # the rows of the set (the others have no multiplier)
            at_high = jnp.isfinite(hi) & (s >= hi - held_tol)
            at_low = jnp.isfinite(lo) & (s <= lo + held_tol)
            # A multiplier pushes only at its own bound, with the right sign.
            complementary = ~jnp.any(hard & (((y > dual_tol) & ~at_high) | ((y < -dual_tol) & ~at_low)))
            finite = jnp.all(jnp.isfinite(s)) & jnp.all(jnp.isfinite(y)) & jnp.all(jnp.isfinite(primal))
            priced = jnp.all(jnp.abs(y) <= price * (1.0 + held_tol))  # a soft row's force within its price
            feasible = jnp.all(violation <= jnp.where(held, held_tol, tol))
            return feasible & complementary & finite & priced

        return active_sets, acceptable

    active_sets, acceptable = checks(hard, lo, hi, price)

    def round_(args, carry):
        # Every array a round reads comes in args (the compacted loop's body may close over no traced value).
        ops_data, hard, lo, hi, price, primal_free, s_free = args
        ops = make_ops(ops_data)
        active_sets, acceptable = checks(hard, lo, hi, price)
        rounds, (upper, lower, best, accepted) = carry
        active = upper | lower
        index, lam = _forces_at_bounds(ops, jnp.where(upper, 1, jnp.where(lower, -1, 0)), lo, hi, s_free, k)
        primal, s = ops.correct(primal_free, index, lam)
        y = jnp.zeros(p, dtype).at[index].set(lam)
        good = (jnp.sum(active) <= k) & acceptable(primal, s, y) & ~accepted
        best = jax.tree.map(lambda a, b: jnp.where(good, a, b), (primal, s, y), best)
        return rounds + 1, (*active_sets(s, y), best, accepted | good)

    def more(args, carry):
        return (carry[0] < settings.polish_rounds) & ~carry[1][3]

    upper, lower = active_sets(result.s, result.y)
    init = (upper, lower, (result.primal, result.s, jnp.zeros_like(result.y)), jnp.zeros((), bool))
    init = batched_like((jnp.zeros((), jnp.int32), init), result.s)
    args = (ops_data, hard, lo, hi, price, primal_free, s_free)
    # Rounds until one is accepted, at most polish_rounds; with more than one, under vmap only the copies that have
    # none yet run the next (compacted_while_loop, POLISH_CHUNK copies per round), where a plain loop would run every
    # copy's rounds until the batch's last is accepted.
    if compact and settings.polish_rounds > 1:
        _, (_, _, (primal, s, y), ok) = compacted_while_loop(more, round_, args, init, _chunk(POLISH_CHUNK))
    else:
        _, (_, _, (primal, s, y), ok) = lax.while_loop(lambda c: more(args, c), lambda c: round_(args, c), init)
    if settings.dual_active_set_steps:  # never with polish_soft_rows (Settings)
        # It starts from the ADMM's set, where the rounds started (their last set may be empty: see the method).
        upper, lower = active_sets(result.s, result.y)
        start_side = jnp.where(upper, 1, jnp.where(lower, -1, 0))
        fallback = _dual_active_set(
            make_ops, ops_data, hard, lo, hi, primal_free, s_free, start_side, k, settings.dual_active_set_steps, tol,
            skip=ok | (result.status != MAX_ITERATIONS),  # converged, or certified infeasible: nothing to find
        )  # fmt: skip
        good = ~ok & acceptable(*fallback)
        primal, s, y = jax.tree.map(lambda a, b: jnp.where(good, a, b), fallback, (primal, s, y))
        ok = ok | good
    ok = ok & (result.status != NUMERICAL)
    # The polished rows at their polished values (within tol of their bounds), the others at the ADMM's.
    s_final = jnp.where(hard, jnp.clip(s, lo, hi), result.s)
    y_final = jnp.where(hard, y, result.y)
    violation = _norm(jnp.where(~soft, jnp.maximum(jnp.maximum(s - hi, lo - s), 0.0) * data.norms, 0.0))
    pick = lambda a, b: jnp.where(ok, a, b)  # noqa: E731
    return result._replace(
        primal=pick(primal, result.primal),
        s=pick(s_final, result.s),
        y=pick(y_final, result.y),
        status=jnp.where(ok, CONVERGED, result.status).astype(jnp.int32),
        violation=pick(violation, result.violation),
    )


def _most_violated(held, s, lo, hi):
    """``(j, sigma, violation)``: the free row that crosses its bound the most (ties: the first) and which bound."""
    above, below = s - hi, lo - s
    violation = jnp.where(held, -jnp.inf, jnp.maximum(above, below))
    j = _first_extreme(violation, largest=True)
    return j, jnp.where(above[j] >= below[j], 1.0, -1.0).astype(s.dtype), violation[j]


class _Move(NamedTuple):
    """One step of Goldfarb and Idnani's method in slot form (``_dual_step``)."""

    w: Any  # (k,) W times the row's column: the held forces' change per unit of its force is -sigma w
    d: Any  # (k,) -sigma w
    c: Any  # the row's Schur complement on the set: how far it moves towards its bound per unit of force
    t: Any  # the step's force (inf: the row cannot be met and no held row can give way)
    joins: Any  # the row reaches its bound before any held multiplier reaches zero
    out: Any  # the slot whose multiplier reaches zero first (the row that leaves, where not joins)


def _dual_step(W, column, S_jj, valid, lam_slots, sigma, excess, dependent) -> _Move:
    """The step of Goldfarb and Idnani's method that raises the force on a violated row ``j`` (one copy).

    ``W`` (k, k): the inverse of the held rows' Schur matrix in the slots ``valid`` (identity on the others);
    ``column`` (k,), ``S_jj``: ``j``'s column of the Schur matrix on the slots and its diagonal entry; ``lam_slots``:
    the held multipliers (0 off the set); ``sigma``: +1 where ``j`` crosses its upper bound, -1 its lower;
    ``excess``: how far (>= 0). The force rises until ``j`` reaches its bound (``joins``) or a held multiplier
    reaches zero first (that row leaves). A row whose Schur complement is below ``dependent`` of its diagonal
    depends on the set (its force would be round-off): only a leaving row can make room.
    """
    column = jnp.where(valid, column, 0.0)
    w = W @ column
    d = -sigma * w
    c = S_jj - column @ w
    full = jnp.where(c > dependent * S_jj, jnp.maximum(excess, 0.0) / c, jnp.inf)
    releasing = valid & (lam_slots * d < 0)
    partial_at = jnp.where(releasing, -lam_slots / jnp.where(releasing, d, 1.0), jnp.inf)
    partial = jnp.min(partial_at)
    return _Move(w, d, c, jnp.minimum(full, partial), full <= partial, _first_extreme(partial_at, largest=False))


def _follow_set(W, move: _Move, valid, joins, leaves):
    """``(W, free_slot)``: the inverse of the held rows' Schur matrix after ``move`` (``joins``: its row joins at the
    first free slot, returned; ``leaves``: the slot ``move.out`` is freed; neither: ``W`` unchanged).

    ``O(k^2)``, where a new factor costs ``O(k^3)`` and forming the set's Schur matrix ``O(k^2 n)``: both cases are a
    rank-one change of the other slots' block and a new row and column at one slot ``g``, written in one pass over
    ``W``: joining, ``W + w w^T / c`` and the row's border ``(-w / c, 1 / c)`` at the free slot; leaving,
    ``W - W e_o e_o^T W / W_oo`` and the identity's row and column at the slot ``o`` (set exactly, not left to
    rounding, since a later join reads that slot as padding).
    """
    k = W.shape[0]
    slot = jnp.arange(k)
    w, c, out = move.w, move.c, move.out
    free_slot = _first_extreme(valid, largest=False)
    g = jnp.where(joins, free_slot, out)
    at_g = (slot == g) & (joins | leaves)
    c_safe = jnp.where(joins, c, 1.0)
    z = jnp.where(joins, w, W[:, out])
    alpha = jnp.where(joins, 1.0 / c_safe, jnp.where(leaves, -1.0 / W[out, out], 0.0))
    border = jnp.where(slot == g, 1.0, jnp.where(valid, -w, 0.0)) / c_safe
    edge = jnp.where(joins, border, (slot == g).astype(W.dtype))
    W = jnp.where(
        at_g[:, None],
        edge[None, :],
        jnp.where(at_g[None, :], edge[:, None], W + alpha * z[:, None] * z[None, :]),
    )
    return W, free_slot


def _dual_active_set(
    make_ops, ops_data, hard, lo, hi, primal_free, s_free, start_side, k: int, max_steps: int, tol, skip
):
    """Goldfarb and Idnani's dual active-set method on the rows ``hard`` (one copy): ``(primal, s, y)``.

    The polish's fallback where its rounds found no acceptable plan after an ADMM that stopped at its cap: far from
    the solution the rounds can go round (on a state box of the 2D quadrotor: 23 rows that depend on each other,
    whose solve gives no set, then 17 rows, then none again). This method keeps every multiplier of the right
    sign: each step takes the most violated row ``j`` and raises its force until ``j`` reaches its bound (it joins
    the set) or a held row's multiplier reaches zero first (that row leaves, and the next step takes ``j`` up
    again). The objective rises at every step, so it cannot cycle. The set's equations are the polish's Schur
    system, whose inverse is computed once (one ``(k, k)`` Cholesky) and then follows the set: a row that joins or
    leaves changes it by a rank-one update and one row and column (``O(k^2)`` per step, where a factor per step costs
    ``O(k^3)`` and forming the set's Schur matrix ``O(k^2 n)``). The found set's forces are then solved afresh, so the
    updates' round-off does not reach the plan.

    It starts from ``start_side`` (+1: the row held at its upper bound, -1: at its lower, 0: free), less the rows
    whose multipliers come out with the wrong sign (at most ``RESTORE_ROUNDS`` solves), or from the empty set when
    that does not settle or the set holds more than ``k`` rows. It stops when no free row is violated by more than
    half of ``tol``, after ``max_steps`` steps, or when ``j`` cannot be met (it depends on the set and no held
    multiplier can give way: the rows are infeasible); the caller checks the result as it checks a round's. The
    inverse and the steps run only for a batch where some copy's start is not yet the answer (most batches that need
    the method at all start at it: the ADMM's set, restored, is already optimal).
    ``skip``: the copy needs none; its result is the minimiser without rows (checked by the caller as any other).
    Under ``vmap`` on a CPU the method runs only for the copies that do not skip it, ``DUAL_ACTIVE_SET_CHUNK`` at a time
    (``scg_jax.tracing.where_needed``): a batch's loops wait for the slowest copy of a chunk, and the copies that
    skip it (their polish accepted, or the ADMM converged) cost nothing. ``make_ops(ops_data)`` gives the polish's
    operators (``_PolishOps``); the method is written on ``ops_data`` so that each chunk gathers its copies' arrays.

    Goldfarb, D., and Idnani, A. (1983). A numerically stable dual method for solving strictly convex quadratic
    programs. Mathematical Programming 27, 1-33.
    """
    p = s_free.shape[0]
    dtype = s_free.dtype

    def method(ops_data, hard, lo, hi, primal_free, s_free, start_side, needed):
        # needed: false for a copy that skips the method, whose loops then do not run (without gathering, under
        # vmap every copy of the batch comes here).
        ops = make_ops(ops_data)
        rows = jnp.arange(p)
        # A row whose Schur complement on the set is below this share of its diagonal depends on the set: in float32
        # its force would be round-off.
        dependent = float(np.sqrt(np.finfo(dtype).eps))

        slot = jnp.arange(k)

        def step(carry):
            side, lam, j, sigma, _, _, steps, (_, s), (slots, valid, W) = carry
            # W: the inverse of the held rows' Schur matrix, kept in the slots ``valid`` (identity on the others).
            # d: the held multipliers' change per unit of j's force, which keeps the held rows at their bounds.
            column, S_jj = ops.column(slots, j)
            excess = sigma * (s[j] - jnp.where(sigma > 0, hi[j], lo[j]))  # j's violation (its bound is finite)
            lam_slots = jnp.where(valid, lam[slots], 0.0)
            move = _dual_step(W, column, S_jj, valid, lam_slots, sigma, excess, dependent)
            t, d, out = move.t, move.d, move.out
            stuck = ~jnp.isfinite(t) | jnp.all(valid)  # j cannot be met
            t = jnp.where(stuck, 0.0, t)
            lam = lam.at[slots].add(jnp.where(valid, t * d, 0.0)).at[j].add(t * sigma)
            joins = ~stuck & move.joins
            leaves = ~stuck & ~move.joins
            leaving = slots[out]
            lam = jnp.where(leaves & (rows == leaving), 0.0, lam)
            side = jnp.where(leaves & (rows == leaving), 0, side)
            side = jnp.where(joins & (rows == j), sigma.astype(side.dtype), side)
            W, free_slot = _follow_set(W, move, valid, joins, leaves)
            slots = jnp.where(joins & (slot == free_slot), j, slots).astype(slots.dtype)
            valid = jnp.where(joins & (slot == free_slot), True, jnp.where(leaves & (slot == out), False, valid))
            # The rows with a force now: the set and j (whose force stays while a row left; after it joined, its force
            # is in the set's).
            index = jnp.concatenate([slots, j[None]])
            force = jnp.where(jnp.concatenate([valid, ~joins[None]]), lam[index], 0.0)
            plan = ops.correct(primal_free, index, force)
            return (*pick(side, lam, jnp.where(joins, -1, j), sigma, stuck, steps + 1, *plan), (slots, valid, W))

        def solution(side, lam):
            held = (side != 0) | (lam != 0)
            index = rows if k == p else _rows_first(jnp.where(held, 0, 1), k)
            return ops.correct(primal_free, index, lam[index])

        def pick(side, lam, j, sigma, stuck, steps, primal, s):
            worst, worst_sigma, violation = _most_violated(~hard | (side != 0), s, lo, hi)
            new_j = jnp.where(j >= 0, j, worst)
            new_sigma = jnp.where(j >= 0, sigma, worst_sigma)
            met = (j < 0) & (violation <= 0.5 * tol)
            return side, lam, new_j, new_sigma, met, stuck, steps, (primal, s)

        def restore(carry):
            side, _, rounds, _ = carry
            # The multipliers (p,) that hold the rows of side at their bounds (the polish's round).
            index, lam_index = _forces_at_bounds(ops, side, lo, hi, s_free, k)
            lam = jnp.zeros(p, dtype).at[index].set(lam_index)
            wrong = (side != 0) & (lam * side < 0)
            return jnp.where(wrong, 0, side), jnp.where(wrong, 0.0, lam), rounds + 1, jnp.any(wrong)

        # The start: the ADMM's set, less the rows whose multipliers have the wrong sign (a few solves); the empty
        # set (the minimiser without rows) if that does not settle.
        zero = jnp.zeros((), jnp.int32)
        side = jnp.where(jnp.sum(start_side != 0) <= k, start_side, 0).astype(jnp.int32)
        side, lam, _, unsettled = lax.while_loop(
            lambda c: needed & c[3] & (c[2] < RESTORE_ROUNDS),
            restore,
            batched_like((side, jnp.zeros(p, dtype), zero, jnp.any(side != 0)), s_free),
        )
        cold = unsettled | ~jnp.all(jnp.isfinite(lam))
        side, lam = jnp.where(cold, 0, side), jnp.where(cold, 0.0, lam)
        start = pick(side, lam, -1 + zero, jnp.ones((), dtype), jnp.zeros((), bool), zero, *solution(side, lam))
        carry = batched_like(start, s_free)
        need = needed & ~carry[4]  # not yet met (a start is never stuck, and max_steps >= 1 here)

        def incremental(carry):
            side = carry[0]
            held = side != 0
            slots = _rows_first(jnp.where(held, 0, 1), k)
            valid = slot < jnp.sum(held)
            in_set = valid.astype(dtype)
            M = in_set[:, None] * ops.schur(slots) * in_set[None, :] + jnp.diag(1.0 - in_set)
            W = jax.scipy.linalg.cho_solve((jnp.linalg.cholesky(M), True), jnp.eye(k, dtype=dtype))
            out = lax.while_loop(
                lambda c: need & ~c[4] & ~c[5] & (c[6] < max_steps),
                step,
                batched_like((*carry, (slots, valid, W)), s_free),
            )
            side, lam, _, _, met, _, _, (primal, s), _ = out
            index, lam_index = _forces_at_bounds(ops, side, lo, hi, s_free, k)
            fresh = ops.correct(primal_free, index, lam_index)
            done = need & met
            primal, s = (jnp.where(done, a, b) for a, b in zip(fresh, (primal, s), strict=True))
            lam = jnp.where(done, jnp.zeros(p, dtype).at[index].set(lam_index), lam)
            return (side, lam, *out[2:7], (primal, s))

        _, carry = lax.while_loop(lambda c: c[0], lambda c: (jnp.zeros((), bool), incremental(c[1])), (need, carry))
        side, lam, _, _, _, _, _, (primal, s) = carry
        return primal, s, lam

    # Only for the copies that need it: under vmap, gathered into chunks (where_needed), so that neither the start's
    # solves nor the steps run for the copies whose polish was accepted.
    otherwise = (primal_free, s_free, jnp.zeros(p, dtype))
    args = (ops_data, hard, lo, hi, primal_free, s_free, start_side, ~skip)
    return where_needed(method, ~skip, args, otherwise, _chunk(DUAL_ACTIVE_SET_CHUNK))


class _Slots(NamedTuple):
    """The carry of ``_active_set_solve``'s steps (one copy; ``k`` slots)."""

    xi: Any  # (n,) the plan in the coordinates xi
    held: Any  # (p,) bool: the rows of the set
    slots: Any  # (k,) int32: the row in each slot
    valid: Any  # (k,) bool: the slots in use
    upper: Any  # (k,) bool: the slot's row is held at its upper bound (else its lower)
    lam: Any  # (k,) the held rows' multipliers (scaled; > 0 pushes a row down)
    rows: Any  # (k, n) the held rows of GT
    W: Any  # (k, k) the inverse of the held rows' Schur matrix (identity on the free slots)
    j: Any  # the violated row the next step raises
    sigma: Any  # +1: j crosses its upper bound; -1: its lower
    lam_j: Any  # the force on j so far (a step where a held row left first)
    done: Any  # no row is violated
    blocked: Any  # j cannot be met: the rows admit no plan
    overflow: Any  # j would join a set whose slots are all in use
    steps: Any


def _active_set_steps(args, carry: _Slots, tol) -> _Slots:
    """One step of ``_active_set_solve`` (one copy; ``args``: ``(GT, GT_t, lam, lo, hi)``)."""
    GT, GT_t, lam_xi, lo, hi = args
    c = carry
    dtype = c.xi.dtype
    k = c.W.shape[0]
    slot = jnp.arange(k)
    dependent = float(np.sqrt(np.finfo(dtype).eps))
    g_j = GT[c.j]
    direction = g_j / lam_xi  # H^-1 of j's row, in xi (H = diag(lam) there)
    bound = jnp.where(c.sigma > 0, hi[c.j], lo[c.j])
    excess = c.sigma * (g_j @ c.xi - bound)
    move = _dual_step(c.W, c.rows @ direction, g_j @ direction, c.valid, c.lam, c.sigma, excess, dependent)
    blocked = ~jnp.isfinite(move.t)
    overflow = ~blocked & move.joins & jnp.all(c.valid)
    stop = blocked | overflow
    t = jnp.where(stop, 0.0, move.t)
    joins, leaves = ~stop & move.joins, ~stop & ~move.joins
    d = jnp.where(c.valid, t * move.d, 0.0)
    xi = c.xi - (d @ c.rows + t * c.sigma * g_j) / lam_xi
    lam = c.lam + d
    lam_j = c.lam_j + t * c.sigma
    W, free_slot = _follow_set(c.W, move, c.valid, joins, leaves)
    join_at, leave_at = joins & (slot == free_slot), leaves & (slot == move.out)
    leaving = c.slots[move.out]
    p = c.held.shape[0]
    every = jnp.arange(p)
    held = jnp.where(joins & (every == c.j), True, jnp.where(leaves & (every == leaving), False, c.held))
    s = xi @ GT_t
    j, sigma, violation = _most_violated(held, s, lo, hi)
    return _Slots(
        xi=xi,
        held=held,
        slots=jnp.where(join_at, c.j, c.slots).astype(jnp.int32),
        valid=jnp.where(join_at, True, jnp.where(leave_at, False, c.valid)),
        upper=jnp.where(join_at, c.sigma > 0, c.upper),
        lam=jnp.where(join_at, lam_j, jnp.where(leave_at, 0.0, lam)),
        rows=jnp.where(join_at[:, None], g_j[None, :], c.rows),
        W=W,
        # After a row left, j is raised again (its force so far stays); otherwise the next violated row.
        j=jnp.where(leaves, c.j, j),
        sigma=jnp.where(leaves, c.sigma, sigma),
        lam_j=jnp.where(leaves, lam_j, 0.0),
        done=~stop & ~leaves & (violation <= 0.5 * tol),
        blocked=blocked,
        overflow=overflow,
        steps=c.steps + 1,
    )


def _active_set_run(args, h, k: int, max_steps: int, tol, chunk: int | None):
    """``(xi, s, y, status, steps, overflow)`` of ``_active_set_solve`` with ``k`` slots (one copy)."""
    GT, GT_t, lam_xi, lo, hi = args
    dtype = GT.dtype
    n, p = GT.shape[1], GT.shape[0]
    xi = -h / lam_xi  # the minimiser without rows
    held = jnp.zeros(p, bool)
    j, sigma, violation = _most_violated(held, xi @ GT_t, lo, hi)
    false = jnp.zeros((), bool)
    start = _Slots(
        xi=xi, held=held, slots=jnp.zeros(k, jnp.int32), valid=jnp.zeros(k, bool), upper=jnp.zeros(k, bool),
        lam=jnp.zeros(k, dtype), rows=jnp.zeros((k, n), dtype), W=jnp.eye(k, dtype=dtype), j=j, sigma=sigma,
        lam_j=jnp.zeros((), dtype), done=violation <= 0.5 * tol, blocked=false, overflow=false,
        steps=jnp.zeros((), jnp.int32),
    )  # fmt: skip
    start = batched_like(start, h)

    def running(args, c):
        return ~c.done & ~c.blocked & ~c.overflow & (c.steps < max_steps)

    def step(args, c):
        return _active_set_steps(args, c, tol)

    def rest(args, c):
        return lax.while_loop(lambda c: running(args, c), lambda c: step(args, c), c)

    if chunk is None:
        out = rest(args, start)
    else:
        # The first steps over the whole batch (most copies stop there), then the copies still running, gathered.
        early = lax.while_loop(
            lambda c: running(args, c) & (c.steps < ACTIVE_SET_WHOLE_STEPS), lambda c: step(args, c), start
        )
        out = where_needed(rest, running(args, early), (args, early), early, chunk)
    # One correction with the kept inverse puts the held rows at their bounds (the steps' round-off).
    bound = jnp.where(out.upper, hi[out.slots], lo[out.slots])
    correction = jnp.where(out.valid, out.W @ jnp.where(out.valid, out.rows @ out.xi - bound, 0.0), 0.0)
    xi = out.xi - (correction @ out.rows) / lam_xi
    lam = jnp.where(out.valid, out.lam + correction, 0.0)
    s = xi @ GT_t
    # The multipliers by row: a sum over the slots (a scatter under vmap writes one entry at a time).
    y = jnp.sum(jnp.where(out.slots[:, None] == jnp.arange(p)[None, :], lam[:, None], 0.0), axis=0)
    finite = jnp.all(jnp.isfinite(xi)) & jnp.all(jnp.isfinite(y))
    status = jnp.where(
        ~finite, NUMERICAL, jnp.where(out.done, CONVERGED, jnp.where(out.blocked, INFEASIBLE, MAX_ITERATIONS))
    ).astype(jnp.int32)
    return xi, s, y, status, out.steps, out.overflow


def _active_set_solve(GT, GT_t, lam_xi, h, data: _Scaled, settings: Settings) -> _Result:
    """Goldfarb and Idnani's dual active-set method on a prepared QP from its minimiser without rows (one copy, in
    the coordinates ``xi`` where ``H = diag(lam)``; every row hard): ``Settings.method = "dual_active_set"``.

    Each step takes the free row that crosses its bound the most and raises its force until it reaches its bound
    (it joins the set) or a held row's multiplier reaches zero first (that row leaves, and the next step raises the
    same row again). Every multiplier keeps its sign, the objective rises at every step, and the method cannot cycle.
    It stops when no free row crosses its bound by more than half of the polish's tolerance (``CONVERGED``), when a
    violated row depends on the set and no held multiplier can give way (the rows admit no plan: ``INFEASIBLE``), or
    after ``max_iterations`` steps (``MAX_ITERATIONS``, with the violation of the last plan). The set is kept in
    ``active_set_slots`` slots: its rows of ``GT`` and the inverse of its Schur matrix, updated in ``O(k^2 + k n)``
    per step (``_follow_set``); a step also forms every row's value (``p n``), about an ADMM iteration. A copy whose
    set would outgrow the slots is solved again with ``ACTIVE_SET_GROWTH`` times as many, up to ``min(n, p)`` (only
    those copies: ``where_needed``).
    At the end one correction with the kept inverse puts the held rows at their bounds.

    Where most rows stay free at the solution this takes few steps: on linear MPC's check problems (1,000 random
    states each) the mean is 0.7 (cart-pole, 2D quadrotor with input bounds) to 7 steps (1D quadrotor under its
    ceiling), the most 41 (an infeasible 2D quadrotor state). Under ``vmap`` on a CPU the first
    ``ACTIVE_SET_WHOLE_STEPS`` steps run over the whole batch and the copies still running then are gathered,
    ``ACTIVE_SET_CHUNK`` at a time (``scg_jax.tracing.where_needed``).

    Goldfarb, D., and Idnani, A. (1983). A numerically stable dual method for solving strictly convex quadratic
    programs. Mathematical Programming 27, 1-33.
    """
    dtype = GT.dtype
    n, p = GT.shape[1], GT.shape[0]
    tol = min(float(np.sqrt(np.finfo(dtype).eps)), POLISH_TOL) if settings.polish_tol is None else settings.polish_tol
    args = (GT, GT_t, lam_xi, data.lo, data.hi)
    most = min(n, p)
    k = min(settings.active_set_slots, most)
    result = _active_set_run(args, h, k, settings.max_iterations, tol, _chunk(ACTIVE_SET_CHUNK))
    while k < most:  # the copies whose set outgrew k slots, again with up to ACTIVE_SET_GROWTH times as many
        k = min(ACTIVE_SET_GROWTH * k, most)

        def again(args, h, k=k):
            return _active_set_run(args, h, k, settings.max_iterations, tol, None)

        result = where_needed(again, result[5], (args, h), result, _chunk(ACTIVE_SET_CHUNK))
    xi, s, y, status, steps, _ = result
    violation = _norm(jnp.maximum(jnp.maximum(s - data.hi, data.lo - s), 0.0) * data.norms)
    converged = status == CONVERGED
    return _Result(
        primal=xi,
        s=jnp.where(converged, jnp.clip(s, data.lo, data.hi), s),
        y=y,
        t=jnp.zeros((), dtype),  # no step size: a warm start from this plan is cold
        status=status,
        iterations=steps,
        r_prim=violation,
        r_dual=jnp.zeros((), dtype),  # every step keeps the multipliers' signs and stationarity
        violation=violation,
    )


def _start(data: _Scaled, warm: Warm | None, settings: Settings, rho0):
    """Scaled ``(s0, y0, t0)`` from a warm start in problem units, holding the rows of ``data`` (cold, or a warm
    start with a non-finite entry there: the pre-stabilised trajectory, y = 0)."""
    dtype = data.lo.dtype
    p = data.lo.shape[0]
    if warm is None:
        return jnp.zeros(p, dtype), jnp.zeros(p, dtype), jnp.asarray(rho0, dtype)
    values, multipliers, rho = (jnp.asarray(a, dtype) for a in warm)
    ok = jnp.all(jnp.isfinite(values)) & jnp.all(jnp.isfinite(multipliers)) & jnp.isfinite(rho) & (rho > 0)
    s0 = jnp.where(ok, (values - data.off) / data.norms, 0.0)
    y0 = jnp.where(ok, multipliers * data.norms / data.scale, 0.0)
    t0 = jnp.clip(jnp.where(ok, rho, rho0), settings.rho_min, settings.rho_max)
    return s0, y0, t0


def _finish(layout: Layout, data: _Scaled, row_bounds, spread, maps, x_init, result: _Result, v) -> Solution:
    """The ``Solution`` (never NaN: after a non-finite iterate, the pre-stabilised trajectory clipped, status
    NUMERICAL). ``data`` and ``result`` hold the rows the ADMM held; ``spread`` maps them to every row of the layout
    (0 at the others: their value at every plan); ``row_bounds``: ``(low, high)`` (p,) of every row in row units."""
    N, R = layout.horizon, layout.stage_rows
    Ex, ex = maps
    ok = result.status != NUMERICAL
    v = jnp.where(ok, v, 0.0)
    s = jnp.where(ok, result.s, jnp.clip(jnp.zeros_like(result.s), data.lo, data.hi))
    y = jnp.where(ok, result.y, 0.0)
    t = jnp.where(ok, result.t, 0.0)
    values = spread(jnp.where(jnp.isfinite(data.off), s * data.norms + data.off, 0.0))
    multipliers = spread(y * data.scale / data.norms)
    x = jnp.concatenate([x_init[None], jnp.einsum("kxn,n->kx", Ex, v) + ex], axis=0)
    x = jnp.where(jnp.isfinite(x), x, 0.0)
    stages = values.reshape(N, R)
    return Solution(
        u=stages[:, : layout.nu],
        x=x,
        slack=_slack(layout, row_bounds, stages),
        multipliers=multipliers.reshape(N, R),
        warm=Warm(values, multipliers, t),
        status=result.status,
        iterations=result.iterations,
        primal_residual=jnp.where(jnp.isfinite(result.r_prim), result.r_prim, jnp.inf),
        dual_residual=jnp.where(jnp.isfinite(result.r_dual), result.r_dual, jnp.inf),
        violation=jnp.where(ok & jnp.isfinite(result.violation), result.violation, jnp.inf),
    )


def _slack(layout: Layout, row_bounds, stages):
    """(N, stage_rows) violations of the soft rows (row units), 0 for the hard rows; ``row_bounds``: ``(low,
    high)`` (p,) of every row."""
    N, R = layout.horizon, layout.stage_rows
    mask = np.asarray(layout.soft)
    if not mask.any():
        return jnp.zeros((N, R), stages.dtype)
    lo, hi = (jnp.reshape(a, (N, R)) for a in row_bounds)
    excess = jnp.where(mask, jnp.maximum(stages - hi, 0.0) + jnp.maximum(lo - stages, 0.0), 0.0)
    if layout.slack == "shared":
        upper = jnp.max(jnp.maximum(stages - hi, 0.0), axis=0)
        lower = jnp.max(jnp.maximum(lo - stages, 0.0), axis=0)
        excess = jnp.broadcast_to(jnp.where(mask, upper + lower, 0.0), (N, R))
    return excess


# --------------------------------------------------------------------------------------------- per-copy path
def solve(layout: Layout, qp: HorizonQP, x_init, warm: Warm | None = None, settings: Settings = Settings()) -> Solution:
    """Solve one horizon QP with the copy's own matrices (jit/vmap-able; condenses and factorises here).

    Args:
        layout: the static ``Layout``. qp: this copy's ``HorizonQP``. x_init: (nx,) the initial state.
        warm: a ``Warm`` (e.g. ``shift(layout, previous.warm)``) or ``None``. settings: ``Settings``.

    Returns:
        ``Solution``.

    Raises:
        ValueError: ``settings.method`` other than ``"admm"`` (the dual active-set method needs a prepared family).
    """
    if settings.method != "admm":
        raise ValueError(
            f"Settings.method: {settings.method!r} solves prepared families only (solve_prepared); allowed in solve: "
            "'admm'"
        )
    x_init = jnp.asarray(x_init)
    dtype = x_init.dtype
    qp = HorizonQP(*(jnp.asarray(a, dtype) for a in qp))
    Ex, Eu = _maps(layout, qp.A, qp.B, qp.K)
    ex, eu = _offsets(qp.A, qp.B, qp.K, qp.c, x_init)
    H = _hessian(qp.A, qp.B, qp.K, qp.Q, qp.R, Ex)
    g = _gradient(qp.Q, qp.R, qp.q, qp.r, Ex, Eu, ex, eu)
    G = _rows(layout, Ex, Eu, qp.C, qp.D)
    scale = jnp.maximum(_input_scale(layout, H), jnp.finfo(dtype).tiny)
    bounds = tuple(getattr(qp, name) for name in BOUND_FIELDS)
    norms = _row_scales(layout, bounds, G, scale)
    data = _scaled(layout, _row_offsets(layout, ex, eu, qp.C, qp.D), bounds, norms, scale)
    Hs, Gs, gs = H / scale, G / norms[:, None], g / scale
    GTG = Gs.T @ Gs
    ratio = settings.refactor_ratio
    n, p = Gs.shape[1], Gs.shape[0]
    # With a fixed step size, s~ = G v~ comes from one (p, p + 1) matrix, G (H + t G^T G)^-1 [G^T, g], folded once:
    # one product per iteration instead of two (p^2 against 2 p n multiplications); v~ is formed at the checks only.
    fold = (not settings.adaptive_rho) and p <= 2 * n

    make_ops = functools.partial(_solve_admm_ops, fold=fold, ratio=ratio)
    ops_data = (Hs, Gs, gs, GTG)
    rho0 = (DEFAULT_RHO if settings.rho is None else settings.rho) * settings.rho_scale
    s0, y0, t0 = _start(data, warm, settings, rho0)
    # A factor stale for every t, so that the first refactor computes it.
    factor = (
        jax.eval_shape(lambda t: _solve_factorize(ops_data, fold, t), jnp.zeros((), dtype)),
        jnp.asarray(jnp.inf, dtype),
    )
    factor = (jax.tree.map(lambda a: jnp.zeros(a.shape, a.dtype), factor[0]), factor[1])
    # Plain loops here (compact=False): SQP's per-copy QPs gained 7-14% per step from gathering (2D and 3D
    # quadrotor SQP-RTI at 1,024 copies), less than the compile time the gathered loops add to each SQP program.
    result = _admm(layout, make_ops, ops_data, data, s0, y0, t0, factor, settings, compact=False)
    if settings.polish_rounds:
        # H^-1 [G^T, g] once (n, p + 1): the rounds then need products and gathers, no triangular solves (which
        # under vmap cost a round as much as the rest of it).
        inv_GT = jax.scipy.linalg.cho_solve((jnp.linalg.cholesky(Hs), True), jnp.concatenate([Gs.T, gs[:, None]], 1))

        inv_G, inv_g = inv_GT[:, :-1], inv_GT[:, -1]

        result = _polish(layout, _solve_polish_ops, (Gs, inv_G, inv_g), data, result, settings, compact=False)
    row_bounds = (data.lo * data.norms + data.off, data.hi * data.norms + data.off)
    return _finish(layout, data, row_bounds, lambda a: a, (Ex, ex), x_init, result, result.primal)


# --------------------------------------------------------------------------------------------- shared path
class Prepared(NamedTuple):
    """What ``prepare`` computes once for a family of QPs with shared matrices (arrays; a pytree).

    With ``theta = [x_init; vec c]`` (nx + N nx) and ``vectors = [theta; vec q; vec r]``:

    Attributes:
        GT: (k, n) ``G T`` of the kept rows (the scaled rows in eigen-coordinates). lam: (n,) generalised
            eigenvalues. T: (n, n).
        rho: the initial step size (``settings.rho`` or ``lam.min()``, times ``settings.rho_scale``).
        keep: (k,) the rows that are not zero for the whole family (a nonzero row of ``G`` or of the offsets; all
            rows with shared slacks); the others' values are 0 at every ``v`` and the ADMM leaves them out. place:
            (p,) each row's position in ``keep``, ``k`` for the rows left out. fixed:
            ``None`` unless ``adaptive_rho=False`` and ``k <= 2 n``: ``GT diag(1 / (lam + rho)) GT^T`` (k, k).
        h_map: (n, len(vectors)): ``T^T g / scale = h_map vectors``.
        off_map: (k, len(theta)): the kept rows' values at ``v = 0``. ex_map: (N nx, len(theta)): the states there.
        Ex: (N, nx, n). norms: (p,). scale: scalar.
    """

    GT: Any
    lam: Any
    T: Any
    rho: Any
    keep: Any
    place: Any
    fixed: Any
    h_map: Any
    off_map: Any
    ex_map: Any
    Ex: Any
    norms: Any
    scale: Any


def _check_template(template: HorizonQP) -> dict:
    """The template's matrices as float64 numpy arrays, checked."""
    mats = {name: np.asarray(getattr(template, name), dtype=np.float64) for name in MATRIX_FIELDS}
    for name, value in mats.items():
        if not np.all(np.isfinite(value)):
            raise ValueError(f"prepare: template.{name} has non-finite entries")
    R = mats["R"]
    if np.min(np.linalg.eigvalsh(0.5 * (R + np.swapaxes(R, 1, 2)))) <= 0:
        raise ValueError("prepare: template.R must be positive definite at every stage")
    return mats


@functools.partial(jax.jit, static_argnums=0)
def _linear_maps(layout: Layout, m: dict):
    """``(H, G, Ex, g_map, off_map, ex_map)`` of ``prepare`` from the template's matrices ``m`` (float64). One
    compiled program per layout and shapes: ``prepare`` runs once per controller or filter built, and run eagerly
    these scans and Jacobians were traced and compiled again each time."""
    N, nx, nu = layout.horizon, layout.nx, layout.nu
    n_theta = nx + N * nx
    Ex, Eu = _maps(layout, m["A"], m["B"], m["K"])
    H = _hessian(m["A"], m["B"], m["K"], m["Q"], m["R"], Ex)
    G = _rows(layout, Ex, Eu, m["C"], m["D"])

    def offsets(theta):
        return _offsets(m["A"], m["B"], m["K"], theta[nx:].reshape(N, nx), theta[:nx])

    def gradient(vectors):
        ex, eu = offsets(vectors[:n_theta])
        q = vectors[n_theta : n_theta + N * nx].reshape(N, nx)
        r = vectors[n_theta + N * nx :].reshape(N, nu)
        return _gradient(m["Q"], m["R"], q, r, Ex, Eu, ex, eu)

    g_map = jax.jacfwd(gradient)(jnp.zeros(n_theta + N * (nx + nu)))
    off_map = jax.jacfwd(lambda theta: _row_offsets(layout, *offsets(theta), m["C"], m["D"]))(jnp.zeros(n_theta))
    ex_map = jax.jacfwd(lambda theta: offsets(theta)[0].reshape(-1))(jnp.zeros(n_theta))
    return H, G, Ex, g_map, off_map, ex_map


def prepare(layout: Layout, template: HorizonQP, settings: Settings = Settings(), dtype=None) -> Prepared:
    """Precompute, in float64, everything of a QP family whose matrices (``A``, ``B``, ``K``, ``Q``, ``R``, ``C``,
    ``D``) are the template's for every copy; ``solve_prepared`` then takes the vectors (``x_init``, ``c``, ``q``,
    ``r``, bounds). The template's bounds set the rows' units (``_row_scales``) and nothing else; its other vectors
    are not used.

    Raises:
        ValueError: non-finite matrices, an ``R`` that is not positive definite, or ``settings.method`` the dual
            active-set method with soft rows.
    """
    if settings.method == "dual_active_set" and any(layout.soft):
        raise ValueError(
            "Settings.method: 'dual_active_set' holds hard rows only and this layout has soft ones; allowed with soft "
            "rows: 'admm'"
        )
    dtype = jnp.zeros(()).dtype if dtype is None else dtype
    mats = _check_template(template)
    bounds = tuple(np.asarray(getattr(template, name), dtype=np.float64) for name in BOUND_FIELDS)
    with jax.enable_x64(True):
        m = {name: jnp.asarray(value) for name, value in mats.items()}
        H, G, Ex, g_map, off_map, ex_map = _linear_maps(layout, m)
        norms = _row_scales(layout, bounds, G, jnp.maximum(jnp.max(jnp.diagonal(H)), np.finfo(np.float64).tiny))
        H, G, Ex, norms, g_map, off_map, ex_map = (np.asarray(a) for a in (H, G, Ex, norms, g_map, off_map, ex_map))

    scale = max(float(np.max(np.diagonal(H))), np.finfo(np.float64).tiny)
    Hs, Gs = H / scale, G / norms[:, None]
    # Generalised eigenvectors of (H, W = G^T G): with W = L L^T, L^-1 H L^-T = U diag(lam) U^T and T = L^-T U.
    W = Gs.T @ Gs
    L_inv = np.linalg.inv(np.linalg.cholesky(0.5 * (W + W.T)))
    C = L_inv @ Hs @ L_inv.T
    lam, U = np.linalg.eigh(0.5 * (C + C.T))
    T = L_inv.T @ U
    GT = Gs @ T
    rho = (float(lam.min()) if settings.rho is None else settings.rho) * settings.rho_scale
    # Shared slacks price each row over the whole horizon: every row takes part there.
    nonzero = np.any(Gs != 0, axis=1) | np.any(off_map != 0, axis=1) | (layout.slack == "shared")
    keep = np.flatnonzero(nonzero)
    place = np.full(layout.num_dense, keep.size)
    place[keep] = np.arange(keep.size)
    GT = GT[keep]
    fold = not settings.adaptive_rho and keep.size <= 2 * layout.num_decisions
    fixed = (GT / (lam + rho)) @ GT.T if fold else None
    cast = lambda a: None if a is None else jnp.asarray(a, dtype)  # noqa: E731
    return Prepared(
        GT=cast(GT),
        lam=cast(lam),
        T=cast(T),
        rho=cast(rho),
        keep=jnp.asarray(keep, jnp.int32),
        place=jnp.asarray(place, jnp.int32),
        fixed=cast(fixed),
        h_map=cast(T.T @ g_map / scale),
        off_map=cast(off_map[keep]),
        ex_map=cast(ex_map),
        Ex=cast(Ex),
        norms=cast(norms),
        scale=cast(scale),
    )


def suggested_rho(layout: Layout, template: HorizonQP) -> float:
    """The initial step size ``prepare`` would choose for ``template``: the smallest generalised eigenvalue of
    ``(H, G^T G)`` (host, float64). Pass it as ``Settings.rho`` to ``solve`` for problems like ``template``."""
    return float(prepare(layout, template, Settings(), jnp.float64 if jax.config.jax_enable_x64 else None).rho)


def solve_prepared(
    layout: Layout,
    prepared: Prepared,
    x_init,
    c,
    q,
    r,
    bounds,
    warm: Warm | None = None,
    settings: Settings = Settings(),
    warm_steps=0,
) -> Solution:
    """Solve one QP of a ``prepare``-d family (jit/vmap-able; ``prepared`` is shared by the copies).

    Args:
        layout, prepared: as given to and returned by ``prepare`` (with the same ``settings``).
        x_init: (nx,). c: (N, nx). q: (N, nx). r: (N, nu): this copy's vectors (see ``HorizonQP``).
        bounds: ``(u_low, u_high, x_low, x_high, row_low, row_high)`` shaped as in ``HorizonQP``.
        warm: a ``Warm`` or ``None``. settings: ``Settings``.
        warm_steps: start from ``shift(layout, warm, warm_steps)`` (>= 0, may be traced; default 0: ``warm`` as
            given), read in one gather of the rows the solver holds: pass a previous solution's ``warm`` with
            ``warm_steps=1`` rather than shifting it first.

    Returns:
        ``Solution``.
    """
    pr = prepared
    dtype = pr.GT.dtype
    flat = lambda a: jnp.reshape(jnp.asarray(a, dtype), -1)  # noqa: E731
    x_init = jnp.asarray(x_init, dtype)
    theta = jnp.concatenate([x_init, flat(c)])
    # The copy's vectors on the left of every product here (see GT_t below).
    h = jnp.concatenate([theta, flat(q), flat(r)]) @ pr.h_map.T  # T^T g / scale
    bounds = tuple(jnp.asarray(b, dtype) for b in bounds)
    # The ADMM and the polish hold the kept rows only (a static count); the others' values are 0 at every v. Only
    # the warm start in and the solution out hold every row: under vmap every full-layout vector is a pass over
    # memory per copy, and the kept rows are a third of the layout or less (MPSC, tail rows at the last stage).
    if pr.keep.shape[0] == layout.num_dense:
        keep, kept, spread = None, lambda a: a, lambda a: a
    else:
        keep = pr.keep

        def kept(a):
            return a[keep]

        def spread(a):
            # A gather, not a scatter into zeros: under vmap XLA's CPU scatter writes one entry at a time.
            return jnp.concatenate([a, jnp.zeros(1, dtype)])[pr.place]

    row_bounds = _row_bounds(layout, *bounds)  # every row's (low, high): shared by the copies when the bounds are
    off = theta @ pr.off_map.T  # the kept rows' values at v = 0
    norms = kept(pr.norms)
    data = _Scaled(lo=(kept(row_bounds[0]) - off) / norms, hi=(kept(row_bounds[1]) - off) / norms, off=off,
                   norms=norms, scale=pr.scale)  # fmt: skip

    GT_t = pr.GT.T  # products keep the copy's vector on the left (see _prepared_admm_ops)
    if settings.method == "dual_active_set":
        result = _active_set_solve(pr.GT, GT_t, pr.lam, h, data, settings)
        return _finish_prepared(
            layout, pr, row_bounds, spread, keep, theta, x_init, data, result, result.primal @ pr.T.T
        )
    shift_h = None if pr.fixed is None else (h / (pr.lam + pr.rho)) @ GT_t
    ops_data = (pr.GT, GT_t, pr.lam, pr.T, pr.fixed, pr.rho, h, shift_h)
    ops = _prepared_admm_ops(ops_data)
    if warm is not None and not (keep is None and isinstance(warm_steps, int) and warm_steps == 0):
        # Each held row's source in the warm start, moved warm_steps stages ahead (``shift``) in one gather. The
        # left-out rows' entries are never read (nor checked for being finite).
        warm = _read_rows(warm, kept(_shifted_rows(layout, warm_steps)))
    s0, y0, t0 = _start(data, warm, settings, pr.rho)  # a cold start: the prepared step size (rho_scale in it)
    if not settings.adaptive_rho:  # the prepared step size throughout (the folded products are for it)
        t0 = pr.rho
    result = _admm(layout, _prepared_admm_ops, ops_data, data, s0, y0, t0, (), settings, keep)
    if settings.polish_rounds:
        # In the coordinates xi (T^T H T = diag(lam)); on the folded path the primal becomes xi here.
        result = result._replace(primal=ops.to_xi(result.primal))

        result = _polish(layout, _prepared_polish_ops, (pr.GT, GT_t, pr.lam, h), data, result, settings, keep)
        v = result.primal @ pr.T.T
    else:
        v = ops.to_v(result.primal)
    return _finish_prepared(layout, pr, row_bounds, spread, keep, theta, x_init, data, result, v)


def _finish_prepared(layout: Layout, pr: Prepared, row_bounds, spread, keep, theta, x_init, data, result, v):
    """``solve_prepared``'s ``Solution`` from the kept rows' ``result`` and the plan ``v``: a left-out hard row whose
    interval excludes 0 makes the QP ``INFEASIBLE``."""
    N, nx = layout.horizon, layout.nx
    if keep is not None:
        # A left-out row's value is 0 at every plan: a hard one whose interval excludes 0 makes the QP infeasible.
        left_out = jnp.ones(layout.num_dense, bool).at[keep].set(False)
        miss = jnp.maximum(row_bounds[0], -row_bounds[1])  # the distance of 0 from the interval, in row units
        miss = jnp.max(jnp.where(left_out & (jnp.asarray(_soft_mask(layout)) == 0), miss, 0.0), initial=0.0)
        infeasible = (miss > 0) & (result.status != NUMERICAL)
        result = result._replace(
            status=jnp.where(infeasible, INFEASIBLE, result.status).astype(jnp.int32),
            violation=jnp.maximum(result.violation, miss),
        )
    ex = (theta @ pr.ex_map.T).reshape(N, nx)
    return _finish(layout, data, row_bounds, spread, (pr.Ex, ex), x_init, result, v)


# --------------------------------------------------------------------------------------------- warm start
def shift(layout: Layout, warm: Warm, steps=1) -> Warm:
    """The warm start for the QP ``steps`` (>= 0, may be traced) control steps later: every stage's rows and
    multipliers move ``steps`` stages ahead (the last stage repeated); ``rho`` is kept."""
    return _read_rows(warm, _shifted_rows(layout, steps))


def _read_rows(warm: Warm, source) -> Warm:
    """The warm start whose row ``i`` is ``warm``'s row ``source[i]``; ``rho`` is kept."""
    return Warm(jnp.asarray(warm.values)[source], jnp.asarray(warm.multipliers)[source], warm.rho)


def _shifted_rows(layout: Layout, steps):
    """(p,) the row of a warm start that each row reads ``steps`` stages later (``shift``)."""
    N, R = layout.horizon, layout.stage_rows
    stage = jnp.minimum(jnp.arange(N) + steps, N - 1)
    return (stage[:, None] * R + jnp.arange(R)).reshape(-1)


__all__ = [
    "CONVERGED",
    "DEFAULT_RHO",
    "INFEASIBLE",
    "MAX_ITERATIONS",
    "NUMERICAL",
    "STATUS_NAMES",
    "HorizonQP",
    "Layout",
    "Prepared",
    "Settings",
    "Solution",
    "Warm",
    "prepare",
    "shift",
    "solve",
    "solve_prepared",
    "suggested_rho",
]
