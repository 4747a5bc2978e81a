"""The shared set-up of the model-based controllers (LQR, iLQR, linear MPC, nonlinear MPC).

Every model-based controller builds the same four things from ``(env, prior_params, options)``, and builds them
here, so that ``scg_algorithms.evaluation.compare`` scores controllers that optimise the same cost about the same
point of the same model:

- **Weights** (``cost_weights``): the prior's full ``Q`` (nx, nx) and ``R`` (nu, nu), or a diagonal given by the
  ``q_diag`` / ``r_diag`` options. Never only the diagonal of a full matrix.
- **Linearisation point** (``linearization_mode``, ``linearization_points``): the goal (one point) or every
  reference point (one per control step); ``"auto"`` is the goal for stabilization and the reference for tracking.
  The input there is the prior's equilibrium input ``u_eq`` (``equilibrium_input``: hover thrust, zero force).
- **Terminal weight** (``terminal_weight``): ``"dare"``, the stabilising solution ``P`` of the discrete algebraic
  Riccati equation of the prior linearised about ``(goal, u_eq)`` with the stage weights (the infinite-horizon LQR
  cost-to-go), or ``"stage"`` (``P = Q``, the original suite's choice).
- **The prior's discrete model**: ``prior_model`` (the CasADi ``SymbolicModel`` of ``prior_params`` with the
  chosen discretisation: ``"env"``, the env's integrator and substeps, or ``"rk4"``, one RK4 step per control
  period) and ``prior_step_fn`` (the same discrete step as a JAX function, for iLQR).

All arrays are numpy float64 (the controllers cast them to their dtype); units are the state's and the input's
(SI: m, rad, m/s, N). Errors name ``<path>.<field>`` of the controller's options.

``MPCOptions`` holds the option fields the MPCs' ``Options`` (linear, nonlinear, GP-MPC) start with.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from scg_algorithms.base import option
from scg_algorithms.riccati import discrete_lqr_gain
from scg_jax.validation import weight_matrix

LINEARIZE_ABOUT = ("auto", "goal", "reference")
TERMINAL_WEIGHTS = ("dare", "stage")
DISCRETIZATIONS = ("env", "rk4")


def discretization_option(default: str, model: str = "prediction model"):
    """The shared declaration of a controller's or filter's ``discretization`` option (``DISCRETIZATIONS``)."""
    return option(
        default, f"{model}: the env's integrator and substeps (env), or one RK4 step per control period (rk4)",
        choices=DISCRETIZATIONS,
    )  # fmt: skip


def terminal_weight_option():
    """The shared declaration of an MPC's ``terminal_weight`` option (``TERMINAL_WEIGHTS``, see ``terminal_weight``)."""
    return option(
        "dare",
        "terminal weight: dare (the LQR cost-to-go P, the discrete Riccati solution of the prior linearised about "
        "the goal at the equilibrium input) or stage (the stage weight Q)",
        choices=TERMINAL_WEIGHTS,
    )


@dataclasses.dataclass(frozen=True)
class MPCOptions:
    """The first fields of every MPC's ``Options`` (``scg_algorithms.mpc.linear``, ``scg_algorithms.mpc.nonlinear``,
    ``scg_algorithms.gp_mpc.controller``): the horizon and the diagonal weights, passed to ``cost_weights``."""

    horizon: int = option(20, "prediction horizon H, control steps")
    q_diag: tuple | None = option(None, "diagonal state weight (nx,); default: the prior's Q")
    r_diag: tuple | None = option(None, "diagonal input weight (nu,); default: the prior's R")


def cost_weights(env, prior_params, q_diag, r_diag, path: str, positive_definite_r: bool = True):
    """The stage weights ``(Q (nx, nx), R (nu, nu))`` a controller optimises.

    Args:
        env: the environment. prior_params: unbatched ``EnvParams``; its ``Q`` and ``R`` (full matrices) are the
            default. q_diag, r_diag: the options' diagonal overrides (nx / nu numbers >= 0) or ``None``.
        path: the options' path for error messages, e.g. ``"controllers.lqr"``.
        positive_definite_r: raise unless ``R`` is positive definite (every method that inverts ``R + B^T P B``
            or solves a Riccati equation needs it).

    Raises:
        ValueError: ``"<path>.q_diag: expected nx values ..."``, negative weights, or a singular ``R``.
    """
    Q = np.asarray(prior_params.Q, dtype=np.float64).reshape(env.nx, env.nx)
    R = np.asarray(prior_params.R, dtype=np.float64).reshape(env.nu, env.nu)
    if q_diag is not None:
        Q = weight_matrix(q_diag, f"{path}.q_diag", env.nx, diagonal_only=True)
    if r_diag is not None:
        R = weight_matrix(r_diag, f"{path}.r_diag", env.nu, diagonal_only=True)
    if positive_definite_r and np.linalg.eigvalsh(0.5 * (R + R.T)).min() <= 0:
        raise ValueError(
            f"{path}.r_diag: the input weight must be positive definite (the prior's R when r_diag is not set), "
            f"got {np.diag(R).tolist()} on the diagonal"
        )
    return Q, R


def equilibrium_input(env, prior_params) -> np.ndarray:
    """(nu,) the prior's equilibrium input (hover thrust per motor, zero cart force), N."""
    return np.asarray(env.system.equilibrium_input(prior_params.physics), dtype=np.float64).reshape(env.nu)


def input_limits(env, prior_params) -> tuple[np.ndarray, np.ndarray]:
    """``(u_low, u_high)`` (nu,) each: the actuator limits of the prior physics, N."""
    # The system's own function, not ``env.input_bounds``: that one returns jnp arrays, float32 without x64.
    low, high = env.system.input_bounds(prior_params.physics)
    return (np.asarray(low, dtype=np.float64).reshape(env.nu), np.asarray(high, dtype=np.float64).reshape(env.nu))


def prior_model(env, prior_params, discretization: str = "env"):
    """The prior's CasADi ``SymbolicModel`` with the chosen discretisation (``"env"`` or ``"rk4"``)."""
    if discretization not in DISCRETIZATIONS:
        raise ValueError(
            f"discretization: unknown value {discretization!r}; allowed values are {', '.join(DISCRETIZATIONS)}"
        )
    return env.symbolic_model(prior_params, discretization)


def prior_step_fn(env, prior_params, discretization: str = "rk4"):
    """The prior's discrete step ``f(x (nx,), u (nu,)) -> x_next (nx,)`` over one control period, in JAX.

    ``"env"``: the env's integrator with its physics substeps (``env.discrete_dynamics()``); ``"rk4"``: one RK4
    step of length ``env.dt``. Both call the system's one ``dynamics`` with ``prior_params.physics``, so the step
    equals ``prior_model(env, prior_params, discretization).fd`` (the tests compare them).
    """
    from scg_jax.backends import jax_backend
    from scg_jax.integrators import make_discrete_dynamics

    if discretization not in DISCRETIZATIONS:
        raise ValueError(
            f"discretization: unknown value {discretization!r}; allowed values are {', '.join(DISCRETIZATIONS)}"
        )
    if discretization == "env":
        discrete = env.discrete_dynamics()
    else:
        discrete = make_discrete_dynamics(env.system.dynamics, "rk4", env.dt, 1, env.system.velocity_mask)
    physics = prior_params.physics

    def step_fn(x, u):
        return discrete(x, u, physics, jax_backend)

    return step_fn


def linearization_mode(env, mode: str) -> str:
    """``"goal"`` or ``"reference"``: ``mode`` itself, or for ``"auto"`` the goal in stabilization tasks and the
    reference in tracking tasks."""
    if mode not in LINEARIZE_ABOUT:
        raise ValueError(f"linearize_about: unknown value {mode!r}; allowed values are {', '.join(LINEARIZE_ABOUT)}")
    if mode == "auto":
        return "goal" if env.task == "stabilization" else "reference"
    return mode


def linearization_points(env, prior_params, model, mode: str) -> np.ndarray:
    """The states the model is linearised about: (1, nx) the prior's goal, or (num_steps + 1, nx) the reference
    (``model.x_ref``, one point per control step); ``mode`` is ``"goal"`` or ``"reference"`` (resolved)."""
    if mode == "goal":
        return np.asarray(prior_params.goal, dtype=np.float64).reshape(1, env.nx)
    if mode == "reference":
        return np.asarray(model.x_ref, dtype=np.float64).reshape(-1, env.nx)
    raise ValueError(f"mode: expected 'goal' or 'reference', got {mode!r}")


def linearize_along(model, x_bar, u_bar):
    """The discrete model linearised about each point: ``x_next ~ Ad_i x + Bd_i u + c_i`` near ``(x_bar_i, u_bar)``.

    Args:
        model: a ``SymbolicModel``. x_bar: (n, nx) states. u_bar: (nu,) input, N (the same at every point).

    Returns:
        ``(Ad (n, nx, nx), Bd (n, nx, nu), c (n, nx))`` with ``c_i = fd(x_bar_i, u_bar) - Ad_i x_bar_i - Bd_i
        u_bar`` (the affine offset, so the model is exact at the points).
    """
    x_bar = np.asarray(x_bar, dtype=np.float64)
    u_bar = np.asarray(u_bar, dtype=np.float64).reshape(-1)
    n, nx = x_bar.shape
    nu = u_bar.shape[0]
    U = np.repeat(u_bar[:, None], n, axis=1)
    # One mapped call instead of n Python-level calls: the reference has a point per control step.
    Ad_all, Bd_all = model.dfd.map(n)(x_bar.T, U)
    Ad = np.asarray(Ad_all).reshape(nx, n, nx).transpose(1, 0, 2)
    Bd = np.asarray(Bd_all).reshape(nx, n, nu).transpose(1, 0, 2)
    f_bar = np.asarray(model.fd.map(n)(x_bar.T, U)).T.reshape(n, nx)
    c = f_bar - np.einsum("ixy,iy->ix", Ad, x_bar) - Bd @ u_bar
    return Ad, Bd, c


def goal_lqr(
    env, prior_params, model, Q, R, path: str, field: str = "terminal_weight", hint: str = "use terminal_weight 'stage'"
):
    """``(K (nu, nx), P (nx, nx))``: discrete LQR of ``model`` linearised about ``(goal, u_eq)`` with ``Q``, ``R``.

    Raises:
        ValueError: ``"<path>.<field>: ... no stabilising solution ..."`` when the Riccati equation has none.
    """
    goal = np.asarray(prior_params.goal, dtype=np.float64).reshape(env.nx)
    lin = model.linearize(goal, equilibrium_input(env, prior_params))
    try:
        return discrete_lqr_gain(lin.Ad, lin.Bd, Q, R)
    except ValueError as error:
        raise ValueError(
            f"{path}.{field}: the discrete Riccati equation about the goal has no stabilising solution ({error}); "
            f"{hint} or change q_diag / r_diag"
        ) from None


def terminal_weight(kind: str, env, prior_params, model, Q, R, path: str) -> np.ndarray:
    """The terminal weight (nx, nx): ``"dare"``, the Riccati solution about ``(goal, u_eq)`` (``goal_lqr``), or
    ``"stage"``, ``Q`` itself."""
    if kind not in TERMINAL_WEIGHTS:
        raise ValueError(
            f"{path}.terminal_weight: unknown value {kind!r}; allowed values are {', '.join(TERMINAL_WEIGHTS)}"
        )
    if kind == "stage":
        return np.array(Q, dtype=np.float64)
    return goal_lqr(env, prior_params, model, Q, R, path)[1]


__all__ = [
    "DISCRETIZATIONS",
    "LINEARIZE_ABOUT",
    "TERMINAL_WEIGHTS",
    "cost_weights",
    "equilibrium_input",
    "goal_lqr",
    "input_limits",
    "linearization_mode",
    "linearization_points",
    "linearize_along",
    "prior_model",
    "prior_step_fn",
    "terminal_weight",
]
