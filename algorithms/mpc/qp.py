"""The condensed quadratic program of linear MPC: built once on the host (numpy), solved in JAX with qpax.

Model (one affine model per linearisation point ``i``; the QP at control step ``k`` uses point ``min(k + j, last)``
at stage ``j``)::

    x_{j+1} = Ad_j x_j + Bd_j u_j + c_j,     c_j = fd(x_bar_j, u_bar) - Ad_j x_bar_j - Bd_j u_bar

Decision: the inputs are written ``u_j = u_bar - K_j (x_j - x_bar_j) + v_j`` and ``v = (v_0, ..., v_{H-1})`` is the
decision (pre-stabilised condensing, Rossiter 1998). With ``K_j`` the LQR gain, the predictions
``x_j = Phi_j x_0 + Gamma_j v + ...`` are built from the stable closed loop ``Ad_j - Bd_j K_j``, so the condensed
Hessian stays well conditioned over long horizons on unstable plants (the upright pole grows by about e^7 over
20 steps at 15 Hz). The change of variables is a bijection, so the optimal inputs are those of the plain
formulation (``K_j = 0``, option ``prestabilize=False``).

Objective (the states are eliminated)::

    J/2 = 1/2 sum_{j=1}^{H-1} |x_j - r_j|_Q^2 + 1/2 |x_H - r_H|_P^2 + 1/2 sum_{j=0}^{H-1} |u_j - u_bar|_R^2
          [+ slack_l1 * sum(e) + 1/2 slack_l2 * |e|^2]

Constraints: every row ``Ax x_{j+1} + Au u_j <= b`` (the env's convention: constraints are evaluated at the state a
step reaches and the input that was commanded) at every stage ``j = 0..H-1``. Softened rows (those that involve
the state, with ``soft_constraints``) become ``... <= b + |[Ax Au]| e`` with a slack ``e >= 0`` in the row's units
(m, rad, N for box rows), so the QP is always feasible while the input rows stay hard:

- ``slack_per_stage=False`` (default): one slack per softened row shared by the whole horizon (as
  safe-control-gym's MPC does); the penalty costs each row's worst violation over the horizon.
- ``slack_per_stage=True``: one slack per softened row and stage, so ``sum(e)`` is the total violation and a plan
  that stays outside longer costs more; ``H`` times the slack variables, which the dense interior-point solver
  pays for cubically.

Neither makes a constraint set that is not control invariant safe. Cart-pole, ``|x| <= 0.08 m`` on the cart,
every initial state entry within 0.05 (16 episodes, horizon 20; LQR: 17 steps outside, peak 0.18 m): hard rows
hold the cart at the bound while the pole falls (25% crashes; an infeasible QP falls back to LQR), per-stage
slacks do the same, shared slacks never crash but, once outside, postpone the return (31 steps outside, peak
0.36 m), because staying outside for the rest of the horizon costs nothing more.

Every QP is ``min 1/2 z^T hess z + q^T z  s.t.  G z <= h`` with ``z = [v; e]`` and, for the parameter vector
``theta = [x_0; c_0..c_{H-1}; w_0..w_{H-1}; 1]`` (``w_j = u_bar + K_j x_bar_j``) and the reference window
``r = [r_1..r_H]``::

    q = q_map @ [theta; r],   h = h_map @ theta,   u_0 = u0_map @ [z; theta]

``hess``, ``G``, ``q_map``, ``h_map``, ``u0_map`` are the same for every copy; they have a leading axis of one
entry when the linearisations are the same at every reference point (always for stabilization, and for the
quadrotors' tracking references, whose attitude is level), else one entry per control step.

Scaling (leaves the solution alone): rows are scaled to unit norm in ``(x, u)``, so a row's slack ``h - G z`` is
in m, rad or N, and the objective so that the largest Hessian diagonal entry is ``OBJECTIVE_DIAGONAL`` (100).
qpax floors every slack and dual at ``sqrt(eps)`` before each Newton step (3.5e-4 in float32), so each of the
hundreds of inactive rows keeps a dual of at least the floor, whose force ``G^T z`` on the stationarity condition
shifts the solution by ``hess^-1 G^T z``. A large objective makes that shift small. On the 2D quadrotor's tracking
QP (horizon 10-30, state, input and position boxes, hard or soft, 12-30 random feasible states 0.1 off the
reference) the worst float32 first input is 3e-2 to 1e-1 N off the qpOASES solution with the largest diagonal
at 1, and 6e-5 to 6e-3 N at 100 (median below 2e-6 N); on the cart-pole both are within 1e-6 N. Larger objectives
cost interior-point iterations (the cart-pole with a horizon of 30 needs more than 30 at 100), hence the default
of 40 iterations.

Solver: ``qpax.solve_qp`` (primal-dual interior point, jit/vmap-able). qpax 0.1.4 has no warm-start argument (it
initialises every solve from its own least-squares guess), so none is used. Its convergence flag tests the
infinity norm of the KKT residual against ``solver_tol``; that is a poor measure of the error in ``z`` here: in
float64 a tolerance of 1e-6 stops the 2D quadrotor's tracking QP after 7-10 iterations with inputs up to 7e-4 N
off the qpOASES solution, while 40 iterations reach 1e-13 N. The default ``solver_tol`` (1e-8) is therefore below
what the floored slacks and duals let the residual reach, so every solve runs ``max_iter`` iterations (which a
vmapped batch pays for anyway: a while loop runs until its slowest lane stops). Hence the status of ``solve_qp``
accepts a finished iterate whose constraint violation is within ``feasibility_tol`` (status 1) and only reports
failure (status 2) for a non-finite or infeasible iterate, which the controller replaces by a clipped LQR input.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import qpax

OBJECTIVE_DIAGONAL = 100.0  # the largest diagonal entry of the scaled Hessian (see the module docstring)
STATUS_SOLVED = 0  # qpax converged and the solution is feasible
STATUS_INACCURATE = 1  # max_iter reached, iterate finite and feasible within feasibility_tol (used as is)
STATUS_FAILED = 2  # non-finite or infeasible iterate (infeasible QP or numerical failure): do not use it


@dataclasses.dataclass(frozen=True)
class AffineModel:
    """Affine discrete models about linearisation points ``i`` (numpy, float64).

    Attributes:
        Ad: (n_points, nx, nx). Bd: (n_points, nx, nu). c: (n_points, nx) offset, ``x+ = Ad x + Bd u + c``.
        x_bar: (n_points, nx) linearisation states. u_bar: (nu,) linearisation input (equilibrium), N; also the
            input reference of the cost.
        K: (n_points, nu, nx) pre-stabilising gains (zeros for the plain formulation).
        P: (n_points, nx, nx) terminal weights (the cost of the last predicted state).
    """

    Ad: np.ndarray
    Bd: np.ndarray
    c: np.ndarray
    x_bar: np.ndarray
    u_bar: np.ndarray
    K: np.ndarray
    P: np.ndarray

    @property
    def num_points(self) -> int:
        return self.Ad.shape[0]

    @property
    def time_invariant(self) -> bool:
        """Whether ``Ad``, ``Bd``, ``K`` and ``P`` are the same at every point (only the offsets then differ)."""
        return all(same_along_axis0(a) for a in (self.Ad, self.Bd, self.K, self.P))


@dataclasses.dataclass(frozen=True)
class ConstraintRows:
    """Linear constraint rows ``Ax x_{j+1} + Au u_j <= b`` imposed at every stage (numpy, float64).

    Attributes:
        Ax: (m, nx). Au: (m, nu). b: (m,). soft: (m,) bool, rows that get a slack when softening is on.
    """

    Ax: np.ndarray
    Au: np.ndarray
    b: np.ndarray
    soft: np.ndarray

    @property
    def num_rows(self) -> int:
        return self.b.shape[0]


@dataclasses.dataclass(frozen=True)
class CondensedQP:
    """The parametric condensed QP (numpy; see the module docstring for the layout).

    Attributes:
        hess: (n_k, nz, nz). G: (n_k, p, nz). q_map: (n_k, nz, n_theta + H nx). h_map: (n_k, p, n_theta).
        u0_map: (n_k, nu, nz + n_theta). ``n_k`` is 1 (one QP for every step) or the number of linearisation
            points (QP ``k`` for control step ``k``, clamped).
        c_table: (n_points, nx) and w_table: (n_points, nu), gathered into ``theta`` per stage.
        horizon, nx, nu: sizes. num_slacks: slack variables (0 without softening). objective_scale: the
            factor the objective ``J/2`` was divided by (``hess`` and ``q`` are ``J/2``'s over it).
    """

    hess: np.ndarray
    G: np.ndarray
    q_map: np.ndarray
    h_map: np.ndarray
    u0_map: np.ndarray
    c_table: np.ndarray
    w_table: np.ndarray
    horizon: int
    nx: int
    nu: int
    num_slacks: int
    objective_scale: float

    @property
    def num_decisions(self) -> int:
        return self.hess.shape[-1]

    @property
    def num_inequalities(self) -> int:
        return self.G.shape[-2]

    @property
    def num_theta(self) -> int:
        return self.nx + self.horizon * (self.nx + self.nu) + 1


def same_along_axis0(array: np.ndarray) -> bool:
    """Whether every entry of ``array`` along its first axis equals the first (to 1e-12 relative)."""
    scale = max(1.0, float(np.abs(array).max(initial=0.0)))
    return bool(np.all(np.abs(array - array[:1]) <= 1e-12 * scale))


def _stage_points(k: int, horizon: int, num_points: int) -> np.ndarray:
    """Linearisation point of stages ``j = 0..H`` of the QP at step ``k``."""
    return np.minimum(k + np.arange(horizon + 1), num_points - 1)


def _condense_one(
    model: AffineModel, points: np.ndarray, horizon: int, Q: np.ndarray, R: np.ndarray, rows: ConstraintRows
):
    """Condensed data of one QP in the variables ``[v; theta]`` before slacks and scaling (float64)."""
    nx, nu = Q.shape[0], R.shape[0]
    H = horizon
    nv = H * nu
    n_theta = nx + H * (nx + nu) + 1
    width = nv + n_theta
    c_col = lambda j: nv + nx + j * nx  # noqa: E731
    w_col = lambda j: nv + nx + H * nx + j * nu  # noqa: E731
    one_col = width - 1

    X = np.zeros((nx, width))
    X[:, nv : nv + nx] = np.eye(nx)
    u_ref = np.zeros((nu, width))
    u_ref[:, one_col] = model.u_bar
    q_ref = np.zeros((nv, H * nx))
    G_rows, h_rows = [], []
    states, weighted, inputs = [], [], []  # per stage: X, weight @ X, U - u_ref, each (n, width)
    U0 = None
    for j in range(H):
        i = points[j]
        U = -model.K[i] @ X
        U[:, j * nu : (j + 1) * nu] += np.eye(nu)
        U[:, w_col(j) : w_col(j) + nu] += np.eye(nu)
        X = model.Ad[i] @ X + model.Bd[i] @ U
        X[:, c_col(j) : c_col(j) + nx] += np.eye(nx)
        if j == 0:
            U0 = U
        weight = model.P[points[H]] if j == H - 1 else Q
        states.append(X)
        weighted.append(weight @ X)
        inputs.append(U - u_ref)
        q_ref[:, j * nx : (j + 1) * nx] = -X[:, :nv].T @ weight
        if rows.num_rows:
            M = rows.Ax @ X + rows.Au @ U
            G_rows.append(M[:, :nv])
            h_theta = -M[:, nv:]
            h_theta[:, -1] += rows.b
            h_rows.append(h_theta)
    # sum_j X_j^T W_j X_j + dU_j^T R dU_j as two products of the stacked stages: one (width x width) pass each, where
    # a sum over the stages made 2 H of them (the 3D quadrotor's MPSC QP, 125 stages 2,513 wide: 3.1-3.4 s, now
    # 0.5-0.6 s, the same matrices to 2e-15 relative).
    du = np.concatenate(inputs)
    cost = np.concatenate(states).T @ np.concatenate(weighted) + du.T @ np.concatenate([R @ d for d in inputs])
    cost = 0.5 * (cost + cost.T)
    hess = cost[:nv, :nv]
    q_map = np.concatenate([cost[:nv, nv:], q_ref], axis=1)
    G = np.concatenate(G_rows) if G_rows else np.zeros((0, nv))
    h_map = np.concatenate(h_rows) if h_rows else np.zeros((0, n_theta))
    return hess, q_map, G, h_map, U0


def build_qp(
    model: AffineModel,
    horizon: int,
    Q,
    R,
    rows: ConstraintRows,
    *,
    soft_constraints: bool = False,
    slack_per_stage: bool = False,
    slack_l1: float = 1e3,
    slack_l2: float = 1e2,
) -> CondensedQP:
    """Condense the MPC problem of ``model`` into the parametric QP (host, numpy float64).

    Args:
        model: ``AffineModel`` (one point: a time-invariant model; ``n`` points: the reference's).
        horizon: H >= 1, control steps. Q: (nx, nx) stage state weight. R: (nu, nu) input weight (positive
            definite). The terminal weight is ``model.P``.
        rows: the constraint rows (``ConstraintRows``; may have zero rows).
        soft_constraints: give each row with ``rows.soft`` a slack (see the module docstring).
        slack_per_stage: one slack per softened row and stage (True) or per row, shared by the stages (False).
        slack_l1, slack_l2: weights of ``sum(e)`` and ``1/2 |e|^2`` in the objective ``J/2`` (units of the cost per
            unit of violation); ignored without softening.

    Returns:
        ``CondensedQP``.
    """
    Q = np.asarray(Q, dtype=np.float64)
    R = np.asarray(R, dtype=np.float64)
    nx, nu = Q.shape[0], R.shape[0]
    H = int(horizon)
    norms = np.linalg.norm(np.concatenate([rows.Ax, rows.Au], axis=1), axis=1) if rows.num_rows else np.zeros(0)
    if np.any(norms == 0.0):
        raise ValueError("build_qp: a constraint row has all-zero coefficients")
    scaled = ConstraintRows(rows.Ax / norms[:, None], rows.Au / norms[:, None], rows.b / norms, rows.soft)
    starts = [0] if model.time_invariant else list(range(model.num_points))
    parts = [_condense_one(model, _stage_points(k, H, model.num_points), H, Q, R, scaled) for k in starts]
    hess, q_map, G, h_map, U0 = (np.stack(a) for a in zip(*parts, strict=True))
    n_k, nv = hess.shape[0], hess.shape[-1]
    n_theta = h_map.shape[-1]

    soft_rows = np.flatnonzero(scaled.soft) if soft_constraints else np.zeros(0, int)
    num_soft = soft_rows.size
    ns = num_soft * H if slack_per_stage else num_soft
    if ns:
        # Stage j's rows sit at j * m + r; slack s of base row r relaxes stage j's copy (per stage) or all of them.
        m = scaled.num_rows
        E = np.zeros((H * m, ns))
        for s, r in enumerate(soft_rows):
            if slack_per_stage:
                E[r + m * np.arange(H), s + num_soft * np.arange(H)] = -1.0
            else:
                E[r + m * np.arange(H), s] = -1.0
        G = np.concatenate(
            [
                np.concatenate([G, np.broadcast_to(E, (n_k, *E.shape))], axis=2),
                np.broadcast_to(np.concatenate([np.zeros((ns, nv)), -np.eye(ns)], axis=1), (n_k, ns, nv + ns)),
            ],
            axis=1,
        )
        h_map = np.concatenate([h_map, np.zeros((n_k, ns, n_theta))], axis=1)
        hess_full = np.zeros((n_k, nv + ns, nv + ns))
        hess_full[:, :nv, :nv] = hess
        hess_full[:, nv:, nv:] = slack_l2 * np.eye(ns)
        q_slack = np.zeros((n_k, ns, q_map.shape[-1]))
        q_slack[:, :, n_theta - 1] = slack_l1
        hess, q_map = hess_full, np.concatenate([q_map, q_slack], axis=1)
    nz = nv + ns

    largest = float(np.max(np.diagonal(hess[:, :nv, :nv], axis1=1, axis2=2)))
    objective_scale = largest / OBJECTIVE_DIAGONAL if largest > 0 else 1.0
    u0_map = np.zeros((n_k, nu, nz + n_theta))
    u0_map[:, :, :nv] = U0[:, :, :nv]
    u0_map[:, :, nz:] = U0[:, :, nv:]
    c_table = np.asarray(model.c, dtype=np.float64)
    w_table = model.u_bar[None, :] + np.einsum("iux,ix->iu", model.K, model.x_bar)
    return CondensedQP(
        hess=hess / objective_scale,
        G=np.ascontiguousarray(G),
        q_map=q_map / objective_scale,
        h_map=h_map,
        u0_map=u0_map,
        c_table=c_table,
        w_table=w_table,
        horizon=H,
        nx=nx,
        nu=nu,
        num_slacks=ns,
        objective_scale=objective_scale,
    )


# --------------------------------------------------------------------------------------------- JAX side
class QPArrays(NamedTuple):
    """``CondensedQP`` as JAX arrays in one dtype (a pytree; closed over by the controller)."""

    hess: Any
    G: Any
    q_map: Any
    h_map: Any
    u0_map: Any
    c_table: Any
    w_table: Any


def qp_arrays(qp: CondensedQP, dtype=None) -> QPArrays:
    """The JAX arrays of ``qp`` in ``dtype`` (default: the current default float)."""
    dtype = jnp.zeros(()).dtype if dtype is None else dtype
    return QPArrays(*(jnp.asarray(getattr(qp, f), dtype=dtype) for f in QPArrays._fields))


def qp_vectors(qp: CondensedQP, arrays: QPArrays, step, x0, x_ref):
    """The QP of one copy at control step ``step``: ``(hess, q, G, h, theta, index)`` (JAX, jit/vmap-able).

    Args:
        qp: the ``CondensedQP`` (static sizes). arrays: ``qp_arrays(qp)``. step: control step k (int scalar).
        x0: (nx,) current state. x_ref: (T + 1, nx) the task reference; stage j's target is
            ``x_ref[min(k + j, T)]``.

    Returns:
        ``hess`` (nz, nz), ``q`` (nz,), ``G`` (p, nz), ``h`` (p,), ``theta`` (n_theta,) and ``index``, the QP
        entry used (for ``first_input``).
    """
    H = qp.horizon
    n_points = qp.c_table.shape[0]
    stages = jnp.clip(step + jnp.arange(H), 0, n_points - 1)
    targets = jnp.clip(step + 1 + jnp.arange(H), 0, x_ref.shape[0] - 1)
    dtype = arrays.hess.dtype
    theta = jnp.concatenate(
        [
            jnp.asarray(x0, dtype),
            arrays.c_table[stages].reshape(-1),
            arrays.w_table[stages].reshape(-1),
            jnp.ones(1, dtype),
        ]
    )
    r = jnp.asarray(x_ref, dtype)[targets].reshape(-1)
    if qp.hess.shape[0] == 1:
        index = 0  # static: the matrices stay unbatched under vmap
    else:
        index = jnp.clip(step, 0, qp.hess.shape[0] - 1)
    q = arrays.q_map[index] @ jnp.concatenate([theta, r])
    h = arrays.h_map[index] @ theta
    return arrays.hess[index], q, arrays.G[index], h, theta, index


def first_input(arrays: QPArrays, z, theta, index):
    """The first input ``u_0`` (nu,), N, of the QP solution ``z``."""
    return arrays.u0_map[index] @ jnp.concatenate([z, theta])


class QPSolution(NamedTuple):
    """``z`` (nz,) (zeros where the solver failed), ``status`` (``STATUS_*``), ``iterations``, ``violation`` (the
    largest ``G z - h`` in unit-norm row units)."""

    z: Any
    status: Any
    iterations: Any
    violation: Any


def solve_qp(hess, q, G, h, *, max_iter: int = 40, solver_tol: float = 1e-8, feasibility_tol: float = 1e-3):
    """Solve ``min 1/2 z^T hess z + q^T z  s.t.  G z <= h`` for one copy with ``qpax.solve_qp`` (jit/vmap-able).

    Returns:
        ``QPSolution``; status ``STATUS_SOLVED`` when qpax reports convergence and the iterate is feasible within
        ``feasibility_tol``, ``STATUS_INACCURATE`` when it ran out of iterations but the iterate is finite and
        feasible within the tolerance, ``STATUS_FAILED`` otherwise (then ``z`` is zeros).
    """
    nz = hess.shape[-1]
    dtype = hess.dtype
    A = jnp.zeros((0, nz), dtype)
    b = jnp.zeros((0,), dtype)
    if G.shape[0] == 0:
        z = jnp.linalg.solve(hess, -q)
        converged, iterations = jnp.ones((), bool), jnp.zeros((), jnp.int32)
        violation = jnp.zeros((), dtype)
    else:
        z, _, _, _, converged, iterations = qpax.solve_qp(hess, q, A, b, G, h, solver_tol=solver_tol, max_iter=max_iter)
        violation = jnp.max(G @ z - h)
        converged = converged == 1
    finite = jnp.all(jnp.isfinite(z)) & jnp.isfinite(violation)
    feasible = finite & (violation <= feasibility_tol)
    status = jnp.where(feasible, jnp.where(converged, STATUS_SOLVED, STATUS_INACCURATE), STATUS_FAILED)
    z = jnp.where(feasible, z, jnp.zeros_like(z))
    return QPSolution(z, status.astype(jnp.int32), jnp.asarray(iterations, jnp.int32), violation)


def solve_qp_batch(hess, q, G, h, **settings) -> QPSolution:
    """``solve_qp`` over a batch: ``q`` (N, nz), ``h`` (N, p); ``hess`` and ``G`` shared ((nz, nz), (p, nz)) or
    batched ((N, nz, nz), (N, p, nz)). Not jitted here; wrap it in ``jax.jit`` (settings static)."""
    in_axes = (0 if hess.ndim == 3 else None, 0, 0 if G.ndim == 3 else None, 0)
    return jax.vmap(lambda a, b, c, d: solve_qp(a, b, c, d, **settings), in_axes=in_axes)(hess, q, G, h)


# --------------------------------------------------------------------------------------------- reference solver
def solve_qp_casadi(hess, q, G, h, solver: str = "qpoases") -> tuple[np.ndarray, bool]:
    """Reference solve of the same QP on the host with CasADi's conic interface (``qpoases`` or ``osqp``).

    Returns ``(z (nz,), success)`` in float64. qpOASES (active set) is exact to round-off; OSQP is run with
    tolerances of 1e-10 and solution polishing.
    """
    import casadi as cs

    hess = np.asarray(hess, dtype=np.float64)
    G = np.asarray(G, dtype=np.float64)
    H = cs.DM(0.5 * (hess + hess.T))
    A = cs.DM(G)
    options = casadi_qp_options(solver)
    conic = cs.conic("ref", solver, {"h": H.sparsity(), "a": A.sparsity()}, options)
    out = conic(h=H, g=np.asarray(q, np.float64), a=A, lba=-np.inf, uba=np.asarray(h, np.float64))
    return np.asarray(out["x"]).ravel(), bool(conic.stats()["success"])


def casadi_qp_options(solver: str, tolerance: float = 1e-10) -> dict:
    """CasADi's options for the QP solver ``solver``: qpOASES quiet, or OSQP at absolute and relative
    ``tolerance`` with polishing; a failed solve is reported in the stats, never raised."""
    if solver == "qpoases":
        return {"printLevel": "none", "error_on_fail": False}
    if solver == "osqp":
        return {
            "osqp": {"eps_abs": tolerance, "eps_rel": tolerance, "max_iter": 100000, "polish": True, "verbose": False},
            "error_on_fail": False,
        }
    raise ValueError(f"solver: unknown value {solver!r}; allowed values are qpoases, osqp")
