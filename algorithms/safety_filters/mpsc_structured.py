"""The linear MPSC's QP as a family of ``scg_algorithms.mpc.structured`` horizon QPs (host set-up, numpy float64).

The QP of ``mpsc_linear`` (see its docstring) in the structured solver's stage form, with the ancillary LQR ``K`` as
its pre-stabilising gain (``u_k = -K x_k + v_k``, offsets apart):

- **Cost.** ``1/2 |u_0 - u_L|^2 + 1/2 sum_{k=1}^{H-1} v_k^T W v_k`` with ``v_k = u_k - u_eq + K (x_k - x_goal)``
  (``plan_weight``). The solver takes costs on states and inputs only, so the ``v`` weight is written as the
  LQR cost of the ancillary weights ``Q``, ``R`` scaled by ``c``: ``c Q`` on ``x_2..x_{H-1}``, ``c (Q - P)`` on
  ``x_1``, ``c P`` on ``x_H`` (``P`` the Riccati solution), ``c R`` on ``u_1..u_{H-1}``. Completing the square
  along the linear model, ``sum_{k>=1} (x_k^T Q x_k + u_k^T R u_k) + x_H^T P x_H = x_1^T P x_1 + sum_{k>=1} v_k^T
  (R + B^T P B) v_k`` (deviations from the goal), so the ``x_1`` term cancels and ``W = c (R + B^T P B)``;
  ``c = regularization / lambda_max(R + B^T P B)``, so with one input ``W`` is ``regularization`` as before.
- **Rows.** Single-input rows become the input box, single-state rows the state box (the tightest per stage),
  the others general rows, each with its stage's tightening subtracted. The plan's tail (``terminal_horizon``
  seconds under the ancillary LQR) is a set of rows on ``x_H`` alone: every tail row is an affine function of
  ``x_H``. The QP holds ``terminal_rows`` of them, the nearest to the goal that the ones kept before do not imply
  (a linear program per candidate, scipy's HiGHS; the cart-pole within +-0.1 m at 50 Hz has 800 tail rows, 56 of
  them non-redundant at horizon 20), imposed at the last stage (zero rows with infinite bounds at the others). The
  set they bound contains the tail's, so the caller checks the plan on every tail row after the solve.

``prepare`` factorises the family once; per copy only ``x``, ``u_L`` and the warm start change.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from scg_algorithms.mpc import structured

REDUNDANCY_TOL = 1e-9  # a tail row whose largest value over the others' set is within this of its bound is dropped


@dataclasses.dataclass(frozen=True)
class StructuredMPSC:
    """The linear MPSC as a ``structured`` QP family (host data).

    Attributes:
        layout: ``structured.Layout``. settings: ``structured.Settings``. prepared: ``structured.Prepared``.
        c: (H, nx) the model's offsets. q: (H, nx), r: (H, nu) the linear cost terms without the proposal
            (``r[0]`` is ``-u_L`` per copy). bounds: ``(u_low, u_high, x_low, x_high, row_low, row_high)``, each
            (H, ...), the tightened rows. terminal_rows: how many rows the terminal set kept.
    """

    layout: structured.Layout
    settings: structured.Settings
    prepared: Any
    c: np.ndarray
    q: np.ndarray
    r: np.ndarray
    bounds: tuple
    terminal_rows: int


def plan_weight(problem) -> tuple[float, np.ndarray]:
    """``(c, W)``: the scale of the LQR weights in the cost and the weight (nu, nu) of ``v_1..v_{H-1}``."""
    B = problem.affine.Bd[0]
    W = problem.R_lqr + B.T @ problem.P_lqr @ B
    c = problem.options.regularization / float(np.linalg.eigvalsh(0.5 * (W + W.T)).max())
    return c, c * W


def _tail_rows(problem) -> tuple[np.ndarray, np.ndarray]:
    """``(F (n, nx), high (n,))``: every row of the plan's tail as ``F x_H <= high`` (unit-norm coefficients)."""
    affine = problem.affine
    return tail_rows(
        (affine.Ad[0], affine.Bd[0], affine.c[0]), problem.K, problem.x_bar, problem.u_bar, problem.rows,
        problem.margins, problem.horizon, "safety_filters.linear_mpsc",
    )  # fmt: skip


def tail_rows(
    model, K, x_bar, u_bar, rows, margins, horizon: int, path: str, normalize: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """``(F (n, nx), high (n,))``: the rows ``rows`` (``Ax x + Au u <= b - margins[j]``) at the tail's stages
    ``horizon..len(margins)-1`` along the ancillary LQR ``u = u_bar - K (x - x_bar)`` on the affine ``model``
    ``(A, B, c)`` (``x+ = A x + B u + c``) from ``x_H``, as ``F x_H <= high`` (unit-norm coefficients; rows that do
    not depend on ``x_H`` and hold from every state left out; ``normalize=False``: in the rows' own units). A row
    that no state holds is refused (``path``)."""
    A, B, c = model
    nx = A.shape[0]
    M, m = np.eye(nx), np.zeros(nx)  # x_t = M x_H + m
    F, high = [], []
    for j in range(horizon, margins.shape[0]):
        Mu, mu = -K @ M, u_bar + K @ (x_bar - m)  # u_t = Mu x_H + mu
        M, m = A @ M + B @ Mu, A @ m + B @ mu + c
        F.append(rows.Ax @ M + rows.Au @ Mu)
        high.append(rows.b - margins[j] - rows.Ax @ m - rows.Au @ mu)
    if not F:
        return np.zeros((0, nx)), np.zeros(0)
    F, high = np.concatenate(F), np.concatenate(high)
    norms = np.linalg.norm(F, axis=1)
    keep = norms > 1e-12
    if np.any(~keep & (high < 0)):
        raise ValueError(
            f"{path}.terminal_horizon: the ancillary LQR's tail breaks a row from every state "
            f"(bound {high[~keep & (high < 0)].min():.3g} below zero); shorten terminal_horizon or lower the tightening"
        )
    scale = norms[keep] if normalize else np.ones(int(keep.sum()))
    return F[keep] / scale[:, None], high[keep] / scale


def terminal_rows(problem, box: tuple[np.ndarray, np.ndarray], count: int) -> tuple[np.ndarray, np.ndarray]:
    """At most ``count`` tail rows ``(F (k, nx), high (k,))`` on ``x_H`` (``nonredundant_rows`` of the tail's)."""
    F, high = _tail_rows(problem)
    kept = nonredundant_rows(F, high, problem.x_bar, box, count)
    return F[kept], high[kept]


def nonredundant_rows(F, high, x_bar, box, count: float) -> np.ndarray:
    """Indices of at most ``count`` of the rows ``F x <= high`` ((n, nx) with unit-norm rows, (n,)): the nearest to
    ``x_bar`` first, each kept only if the ones kept before and the state ``box`` ``(low, high)`` (nx,) (infinite
    where none) do not already imply it (a linear program, scipy's HiGHS). The set they bound contains the rows'
    set, and equals it inside the box when no cap cut the list."""
    from scipy.optimize import linprog

    if F.shape[0] == 0 or count == 0:
        return np.zeros(0, int)
    # Parallel rows: only the tightest can bind.
    order = np.lexsort((high, *np.round(F, 9).T[::-1]))
    F, high = F[order], high[order]
    first = np.r_[True, np.any(np.abs(np.diff(F, axis=0)) > 1e-9, axis=1)]
    order, F, high = order[first], F[first], high[first]
    bounds = [(lo if np.isfinite(lo) else None, hi if np.isfinite(hi) else None) for lo, hi in zip(*box, strict=True)]
    kept, hull, hull_of = [], None, -4
    for i in np.argsort(high - F @ x_bar):
        if len(kept) == count:
            break
        # A box around the set of the rows kept so far (2 nx LPs) holds the set of all the kept rows too: it is redone
        # only as the kept rows grow by half, a looser box costs an LP for some rows it leaves undecided.
        if kept and len(kept) >= hull_of + max(4, hull_of // 2):
            hull, hull_of = _bounding_box(F[kept], high[kept], bounds), len(kept)
        if hull is not None and _box_max(F[i], hull) <= high[i] + REDUNDANCY_TOL:
            continue  # implied already over a box that holds the kept rows' set: no LP needed
        if kept:
            result = linprog(-F[i], A_ub=F[kept], b_ub=high[kept], bounds=bounds, method="highs")
        else:
            result = linprog(-F[i], bounds=bounds, method="highs")
        # HiGHS reports an unbounded program as "infeasible or unbounded" (status 2) when its presolve stops early:
        # only a program without a feasible point means that the kept rows and the box admit no state.
        if result.status == 2 and _admits_no_state(F[kept], high[kept], bounds):
            break  # every plan fails the full check anyway
        if not (result.status == 0 and -result.fun <= high[i] + REDUNDANCY_TOL):
            kept.append(int(i))
    return order[kept]


def _admits_no_state(F, high, bounds) -> bool:
    """Whether no ``x`` within ``bounds`` satisfies ``F x <= high`` (a feasibility program)."""
    from scipy.optimize import linprog

    result = linprog(np.zeros(F.shape[1]), A_ub=F if F.shape[0] else None, b_ub=high if F.shape[0] else None,
                     bounds=bounds, method="highs")  # fmt: skip
    return result.status == 2


def _bounding_box(F, high, bounds) -> tuple[np.ndarray, np.ndarray] | None:
    """``(low, high)`` (nx,) of the set ``F x <= high`` within ``bounds`` (infinite where unbounded); ``None`` when
    the set is empty or an LP fails."""
    from scipy.optimize import linprog

    nx = F.shape[1]
    low, up = np.full(nx, -np.inf), np.full(nx, np.inf)
    for d in range(nx):
        for sign, out in ((1.0, up), (-1.0, low)):  # linprog minimises: -x_d for the largest x_d, x_d for the least
            result = linprog(-sign * np.eye(nx)[d], A_ub=F, b_ub=high, bounds=bounds, method="highs")
            if result.status == 0:
                out[d] = -sign * result.fun
            elif result.status != 3:  # 3: unbounded in this direction (the box stays infinite there)
                return None
    return low, up


def _box_max(f, box) -> float:
    """The largest value of ``f @ x`` over the box ``(low, high)`` (infinite if the box is open along ``f``)."""
    low, up = box
    with np.errstate(invalid="ignore"):
        terms = np.where(f > 0, f * up, np.where(f < 0, f * low, 0.0))
    return float(terms.sum())


def _split_rows(problem):
    """The tightened rows of the H free stages as the solver's input box, state box and general rows."""
    rows, H, nx, nu = problem.rows, problem.horizon, problem.nx, problem.nu
    margins = problem.margins[:H]
    u_low, u_high = np.tile(problem.u_low, (H, 1)), np.tile(problem.u_high, (H, 1))
    x_bounds, general = {}, []
    for index, (ax, au, b) in enumerate(zip(rows.Ax, rows.Au, rows.b, strict=True)):
        states, inputs = np.flatnonzero(ax), np.flatnonzero(au)
        bound = b - margins[:, index]
        if states.size == 0 and inputs.size == 1:
            i, a = int(inputs[0]), au[inputs[0]]
            if a > 0:
                u_high[:, i] = np.minimum(u_high[:, i], bound / a)
            else:
                u_low[:, i] = np.maximum(u_low[:, i], bound / a)
        elif states.size == 1 and inputs.size == 0:
            i, a = int(states[0]), ax[states[0]]
            low, high = x_bounds.setdefault(i, (np.full(H, -np.inf), np.full(H, np.inf)))
            if a > 0:
                np.minimum(high, bound / a, out=high)
            else:
                np.maximum(low, bound / a, out=low)
        elif states.size or inputs.size:
            general.append(index)
    x_rows = tuple(sorted(x_bounds))
    x_low = np.stack([x_bounds[i][0] for i in x_rows], axis=1) if x_rows else np.zeros((H, 0))
    x_high = np.stack([x_bounds[i][1] for i in x_rows], axis=1) if x_rows else np.zeros((H, 0))
    norms = np.linalg.norm(np.concatenate([rows.Ax, rows.Au], axis=1)[general], axis=1)
    C = np.tile((rows.Ax[general] / norms[:, None])[None], (H, 1, 1))
    D = np.tile((rows.Au[general] / norms[:, None])[None], (H, 1, 1))
    row_high = (rows.b[general] - margins[:, general]) / norms
    box = (np.full(nx, -np.inf), np.full(nx, np.inf))
    for column, i in enumerate(x_rows):
        box[0][i], box[1][i] = x_low[-1, column], x_high[-1, column]
    return (u_low, u_high, x_rows, x_low, x_high), (C, D, row_high), box, nu


def build(problem) -> StructuredMPSC:
    """The ``StructuredMPSC`` of a ``mpsc_linear.Problem`` (prepared once; raises ``ValueError`` naming
    ``safety_filters.linear_mpsc.terminal_horizon`` when the terminal set is empty)."""
    opts, H, nx, nu = problem.options, problem.horizon, problem.nx, problem.nu
    (u_low, u_high, x_rows, x_low, x_high), (C, D, row_high), box, _ = _split_rows(problem)
    F, f_high = terminal_rows(problem, box, opts.terminal_rows)
    if F.shape[0]:
        C_term = np.zeros((H, F.shape[0], nx))
        C_term[-1] = F
        term_high = np.full((H, F.shape[0]), np.inf)
        term_high[-1] = f_high
        C = np.concatenate([C, C_term], axis=1)
        D = np.concatenate([D, np.zeros((H, F.shape[0], nu))], axis=1)
        row_high = np.concatenate([row_high, term_high], axis=1)
    # Every row on the state is soft at the exact-penalty price violation_penalty (0: hard rows): where a plan holds
    # every row the solution is that of the hard QP (the price exceeds every multiplier), elsewhere the
    # least-violating plan.
    soft = opts.violation_penalty > 0
    layout = structured.Layout(
        num_rows=C.shape[1],  # the general rows: the constraints' and the terminal set's
        horizon=H,
        nx=nx,
        nu=nu,
        x_rows=x_rows,
        soft_x=(soft,) * len(x_rows),
        soft_rows=tuple(soft and bool(np.any(C[:, i])) for i in range(C.shape[1])),
        l1=opts.violation_penalty,
    )
    tol = opts.structured_tol  # one option for the absolute and the relative residual tolerance
    named_alike = (
        "check_every", "polish_rounds", "polish_soft_rows", "dual_active_set_steps", "adaptive_rho", "rho_scale",
    )  # fmt: skip
    settings = structured.Settings(
        method=opts.structured_method,
        max_iterations=opts.structured_max_iter,
        eps_abs=tol,
        eps_rel=tol,
        **{name: getattr(opts, f"structured_{name}") for name in named_alike},  # the option is structured_<name>
    )
    scale, _ = plan_weight(problem)
    Q, R, P = problem.Q_lqr, problem.R_lqr, problem.P_lqr
    stage_Q = np.stack([scale * (Q - P)] + [scale * Q] * (H - 2) + [scale * P])[-H:] if H > 1 else np.zeros((1, nx, nx))
    stage_R = np.stack([np.eye(nu)] + [scale * R] * (H - 1))
    q = -np.einsum("kxy,y->kx", stage_Q, problem.x_bar)
    r = -np.einsum("kuv,v->ku", stage_R, problem.u_bar)
    r[0] = 0.0
    bounds = (u_low, u_high, x_low, x_high, np.full_like(row_high, -np.inf), row_high)
    affine = problem.affine
    template = structured.HorizonQP(
        A=np.repeat(affine.Ad[:1], H, axis=0),
        B=np.repeat(affine.Bd[:1], H, axis=0),
        c=np.repeat(affine.c[:1], H, axis=0),
        K=np.repeat(problem.K[None], H, axis=0),
        Q=stage_Q,
        q=q,
        R=stage_R,
        r=r,
        u_low=u_low,
        u_high=u_high,
        x_low=x_low,
        x_high=x_high,
        C=C,
        D=D,
        row_low=bounds[4],
        row_high=row_high,
    )
    prepared = structured.prepare(layout, template, settings)
    return StructuredMPSC(layout, settings, prepared, template.c, q, r, bounds, F.shape[0])


__all__ = ["StructuredMPSC", "build", "nonredundant_rows", "plan_weight", "tail_rows", "terminal_rows"]
