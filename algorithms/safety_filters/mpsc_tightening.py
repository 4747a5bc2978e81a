"""What both model predictive safety filters (MPSC) learn offline: model-error samples, a robust invariant set of the
error under the ancillary LQR feedback, and the constraint tightening it implies.

- ``sample_transitions``: one-step transitions of the plant (its CasADi mirror, mapped over the samples): states
  uniform in the env's initial-state box or in a box around the goal, inputs uniform in the actuator limits.
  The caller forms the model error ``w = x_next - f_model(x, u)`` with its own prediction model.
- ``rpi_ellipsoid``: the robust positively invariant (RPI) ellipsoid ``{e : e^T P e <= 1}`` of the error
  ``e+ = A_cl e + w`` over the samples (Wabersich & Zeilinger's semidefinite program: ``max log det P`` subject to
  one 2x2-block LMI per sample with the S-procedure multiplier ``tau``), solved with cvxpy and an open-source
  conic solver (Clarabel, or SCS), never a licensed one.
- ``ellipsoid_tightening``: the margin of each constraint row under the error tube. Stage ``j``'s row
  ``a_x^T x_{j+1} + a_u^T u_j <= b`` with ``x = z + e`` and ``u = v - K e`` (nominal ``z``, ``v``; ``e_j`` and
  ``e_{j+1}`` both in the ellipsoid) holds for every such error iff the nominal row holds with ``b`` reduced by the
  support functions ``|P^{-1/2} a_x| + |P^{-1/2} K^T a_u|``. For a row on the state or on the input alone this is
  the exact Pontryagin difference of a half-space and the ellipsoid; the original's axis-aligned box around the
  ellipsoid (and its vertex image under ``K`` for the inputs) is never tighter.
- ``reachable_tightening``: per-stage margins of the linearised error tube ``e_{j+1} = A_cl e_j + w``, ``e_0 = 0``,
  with ``w`` in the sampled box ``|w_d - mean_d| <= w_bar_d``: stage ``j``'s margin of a row is
  ``sum_{i<=j} |a_x^T A_cl^i| w_bar + sum_{i<j} |a_u^T K A_cl^i| w_bar`` (support functions of the Minkowski sums
  that ``e_{j+1}`` and ``e_j`` lie in). It grows with the stage like the nonlinear MPSC's ``s_j`` sequence.

Units: states and errors in the state's units (m, rad, m/s, rad/s), inputs N; all numpy float64.
"""

from __future__ import annotations

import numpy as np

SDP_SOLVERS = ("clarabel", "scs")


def sample_transitions(env, plant_params, count: int, seed: int, half_width=None, num_plants: int = 1):
    """``count`` one-step transitions of the plant ``plant_params`` from random states and inputs.

    The step is the plant's CasADi mirror with the env's own integrator and substeps
    (``scg_jax.symbolic.plant_step``, ``env.symbolic_model(plant_params).fd`` with the physics as a parameter, which
    the project's tests hold equal to ``env.step`` without disturbances), mapped over the samples in one call:
    compiling the vmapped JAX step with its physics substeps costs tens of seconds on a small CPU, the mapped CasADi
    call milliseconds.

    Args:
        env: the environment. plant_params: unbatched ``EnvParams`` of the plant (usually ``env.default_params``).
        count: number of samples. seed: seed of numpy's generator (and of the plants' draws).
        half_width: ``None`` (states uniform in the env's initial-state box ``init_state`` low/high) or (nx,)
            half-widths of a box around the plant's goal the states are drawn from uniformly.
        num_plants: plants whose physics ``env.reset`` draws from the env's physics randomisation (an equal share
            of the samples each), so the model error covers the plants episodes meet; 1 (or an env without
            physics randomisation): ``plant_params`` itself.

    Returns:
        ``(x (count, nx), u (count, nu), x_next (count, nx))`` numpy float64; ``u`` uniform in the plant's actuator
        limits (N).
    """
    rng = np.random.default_rng(seed)
    nx = env.nx
    if half_width is None:
        low = np.asarray(plant_params.init_state.low, dtype=np.float64).reshape(nx)
        high = np.asarray(plant_params.init_state.high, dtype=np.float64).reshape(nx)
    else:
        goal = np.asarray(plant_params.goal, dtype=np.float64).reshape(nx)
        half = np.asarray(half_width, dtype=np.float64).reshape(nx)
        low, high = goal - half, goal + half
    x = rng.uniform(low, high, (count, nx))
    u_low, u_high = (
        np.asarray(b, dtype=np.float64).reshape(env.nu) for b in env.system.input_bounds(plant_params.physics)
    )
    u = rng.uniform(u_low, u_high, (count, env.nu))
    plants = [plant_params]
    if num_plants > 1 and env.physics_randomization_specs:
        import jax

        keys = jax.random.split(jax.random.key(seed), num_plants)
        plants = [plant_params.replace(physics=env.reset(key, plant_params)[1].physics) for key in keys]
    from scg_jax.symbolic import physics_vector, plant_step

    fd = plant_step(env)  # one CasADi function for every plant, its physics a parameter
    x_next = np.empty_like(x)
    for share, plant in zip(np.array_split(np.arange(count), len(plants)), plants, strict=True):
        p = np.repeat(physics_vector(plant)[:, None], share.size, axis=1)
        x_next[share] = np.asarray(fd.map(share.size)(x[share].T, u[share].T, p), dtype=np.float64).T
    return x, u, x_next


def rpi_ellipsoid(A_cl, w, tau: float, solver: str = "clarabel", path: str = "tau") -> np.ndarray:
    """``P`` (nx, nx): the smallest-volume ellipsoid ``{e : e^T P e <= 1}`` that is invariant for ``e+ = A_cl e + w``
    for every sample ``w`` (the S-procedure LMI with multiplier ``tau`` per sample).

    Args:
        A_cl: (nx, nx) closed-loop error dynamics ``Ad - Bd K``. w: (n, nx) model-error samples. tau: in (0, 1).
        solver: ``"clarabel"`` or ``"scs"``. path: option path named in errors.

    Raises:
        ValueError: naming ``path`` when the program is infeasible (errors too large for ``tau``: the ellipsoid
            would have to contract by ``tau`` per step yet contain the errors).
    """
    import cvxpy as cp

    A_cl = np.asarray(A_cl, dtype=np.float64)
    w = np.asarray(w, dtype=np.float64)
    nx = A_cl.shape[0]
    # One scale for every coordinate (the largest error): the conic solvers want the data near 1. A scale per
    # coordinate (m vs rad/s errors differ by 300x on the cart-pole) left Clarabel "optimal_inaccurate" with an
    # indefinite P; the uniform one solves to "optimal". P in original units is P_s / scale^2.
    scale = max(float(np.abs(w).max()), 1e-12)
    A_s = A_cl
    w_s = w / scale
    P = cp.Variable((nx, nx), symmetric=True)
    constraints = [P >> 1e-9 * np.eye(nx)]
    for wi in w_s:
        wi = wi.reshape(nx, 1)
        block = cp.bmat([[A_s.T @ P @ A_s - tau * P, A_s.T @ P @ wi], [wi.T @ P @ A_s, wi.T @ P @ wi + tau - 1.0]])
        constraints.append(0.5 * (block + block.T) << 0)
    problem = cp.Problem(cp.Maximize(cp.log_det(P)), constraints)
    try:
        problem.solve(solver=cp.CLARABEL if solver == "clarabel" else cp.SCS)
    except cp.error.SolverError as error:
        raise ValueError(f"{path}: the invariant-set program failed with {solver} ({error})") from None
    if problem.status not in ("optimal", "optimal_inaccurate") or P.value is None:  # infeasible or unbounded
        raise ValueError(
            f"{path}: no invariant ellipsoid of the model error exists for tau={tau} (solver status "
            f"{problem.status!r}); the errors are too large for the ancillary feedback: raise tau towards 1, "
            "sample a smaller state box or use a better prior"
        )
    P_s = 0.5 * (P.value + P.value.T)
    if problem.status != "optimal" or np.linalg.eigvalsh(P_s).min() <= 0:
        raise ValueError(
            f"{path}: the invariant-set program was solved inaccurately by {solver} (status {problem.status!r}); "
            "try the other sdp_solver, fewer samples or another tau"
        )
    return P_s / scale**2


def _tube_parts(Ax, Au, K) -> tuple[np.ndarray, np.ndarray]:
    """(m, nx) twice: each row's coefficients on the state error ``e_{j+1}`` (``Ax``) and, through ``u = v - K e``,
    on the input's error ``e_j`` (``-Au K``)."""
    f64 = lambda a: np.asarray(a, dtype=np.float64)  # noqa: E731
    return f64(Ax), -f64(Au) @ f64(K)


def ellipsoid_tightening(Ax, Au, K, P) -> np.ndarray:
    """(m,) the margin of each row ``Ax x + Au u <= b`` for errors in ``{e^T P e <= 1}`` under ``u = v - K e``."""
    P_inv = np.linalg.inv(np.asarray(P, dtype=np.float64))
    support = lambda C: np.sqrt(np.maximum(np.einsum("mi,ij,mj->m", C, P_inv, C), 0.0))  # noqa: E731
    C_x, C_u = _tube_parts(Ax, Au, K)
    return support(C_x) + support(C_u)


def error_box(w, quantile: float = 1.0):
    """``(mean (nx,), half_width (nx,))`` of the samples ``w`` (n, nx): the per-dimension bound on ``|w - mean|``
    (its ``quantile``; 1.0 is the largest sample, the default)."""
    w = np.asarray(w, dtype=np.float64)
    mean = w.mean(axis=0)
    return mean, np.quantile(np.abs(w - mean), quantile, axis=0)


# The quantiles ``error_quantile: null`` tries, largest first: the first whose tube leaves room (``tube_room``).
# The whole sample bound (1.0) where the error is small next to the constraint (a quadrotor's ceiling); a
# smaller share where the largest errors of the sampled box (full thrust on a plant 10 % lighter) would tighten
# a narrow constraint (the cart within +-0.1 m) away.
AUTO_QUANTILES = (1.0, 0.9, 0.75, 0.5)


def error_quantiles(value) -> tuple[float, ...]:
    """The quantiles to try for the option ``error_quantile``: ``(value,)``, or ``AUTO_QUANTILES`` for ``None``."""
    return AUTO_QUANTILES if value is None else (float(value),)


def tube_room(rows, margins, x_goal, u_eq) -> str | None:
    """``None`` when the goal and its equilibrium input hold every tightened row at every stage
    (``Ax x_goal + Au u_eq <= b - margin_j``), so a plan that rests at the goal exists; else the reason."""
    excess = rows.Ax @ x_goal + rows.Au @ u_eq - (rows.b[None, :] - margins)
    if excess.max() <= 0:
        return None
    j, r = np.unravel_index(int(np.argmax(excess)), excess.shape)
    return (
        f"the tightening of row {r} ({rows.Ax[r].round(4).tolist()} x + {rows.Au[r].round(4).tolist()} u <= "
        f"{rows.b[r]:.4g}) at stage {j} is {margins[j, r]:.3g}, which leaves the goal and its equilibrium input "
        "outside"
    )


def reachable_tightening(Ax, Au, K, A_cl, w_bar, horizon: int) -> np.ndarray:
    """(horizon, m) per-stage margins of the rows for the linearised tube with errors in the box ``|w| <= w_bar``
    (see the module docstring); stage ``j`` is the row of the state ``x_{j+1}`` and the input ``u_j``."""
    C_x, C_u = _tube_parts(Ax, Au, K)
    A_cl = np.asarray(A_cl, dtype=np.float64)
    w_bar = np.asarray(w_bar, dtype=np.float64)
    margins = np.zeros((horizon, C_x.shape[0]))
    power = np.eye(A_cl.shape[0])
    state_part = np.zeros(C_x.shape[0])
    input_part = np.zeros(C_x.shape[0])
    for j in range(horizon):
        state_part = state_part + np.abs(C_x @ power) @ w_bar  # e_{j+1} = sum_{i<=j} A_cl^i w
        margins[j] = state_part + input_part  # e_j = sum_{i<j} A_cl^i w
        input_part = input_part + np.abs(C_u @ power) @ w_bar
        power = A_cl @ power
    return margins


__all__ = [
    "AUTO_QUANTILES",
    "SDP_SOLVERS",
    "error_quantiles",
    "tube_room",
    "ellipsoid_tightening",
    "error_box",
    "reachable_tightening",
    "rpi_ellipsoid",
    "sample_transitions",
]
