"""Infinite-horizon LQR gains and the LQR controller (``make_lqr``).

Convention (used by every caller in this package): the feedback law is

    u = u_ref - K (x - x_ref)

with ``K`` of shape (nu, nx), so a *positive* gain entry pushes the input *against* a positive state error. For
the linearisation ``dx_{k+1} = Ad dx_k + Bd du_k`` (``dx = x - x_ref``, ``du = u - u_ref``) the gain minimises
``sum_k dx_k^T Q dx_k + du_k^T R du_k`` and the closed loop is ``dx_{k+1} = (Ad - Bd K) dx_k``. ``P`` is the
stabilising solution of the discrete algebraic Riccati equation, so the optimal cost from ``dx_0`` is
``dx_0^T P dx_0`` (the env's reward has a factor 1/2 on both terms, which scales ``P`` but leaves ``K`` alone).
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from scg_algorithms import controller_setup as setup
from scg_algorithms.base import JaxController, option, parse_options, state_from_obs
from scg_algorithms.riccati import continuous_lqr_gain, discrete_lqr_gain


def lqr_gain_about(env, params, x0, u0) -> np.ndarray:
    """LQR gain of ``env``'s discrete dynamics linearised about ``(x0, u0)`` with the cost weights in ``params``.

    The linearisation is that of ``env.symbolic_model(params)`` (the env's own integrator and substeps over one
    control period), so the gain is for the plant as the controller's prior ``params`` describe it.

    Args:
        env: an ``scg_jax.Env``. params: unbatched ``EnvParams``; ``params.Q`` (nx, nx) and ``params.R``
            (nu, nu) are the weights. x0: (nx,) operating state. u0: (nu,) operating input, N (e.g. the hover
            thrust from ``env.reference_at``).

    Returns:
        K (nu, nx) float64, for ``u = u_ref - K (x - x_ref)``.
    """
    lin = env.symbolic_model(params).linearize(np.asarray(x0, dtype=np.float64), np.asarray(u0, dtype=np.float64))
    K, _ = discrete_lqr_gain(lin.Ad, lin.Bd, np.asarray(params.Q), np.asarray(params.R))
    return K


# --------------------------------------------------------------------------------------------- controller
@dataclasses.dataclass(frozen=True)
class Options:
    """Options of the LQR controller (a config file's ``controllers.lqr`` section)."""

    mode: str = option(
        "auto",
        "linearise about the goal (one gain) or about the reference point of every step (one gain per step); "
        "auto: goal for stabilization, reference for tracking",
        choices=("auto", "goal", "reference"),
    )
    discrete: bool = option(True, "discrete LQR on (Ad, Bd) at the control period; false: continuous LQR on (A, B)")
    q_diag: tuple | None = option(None, "diagonal state weight (nx,); default: the env's Q")
    r_diag: tuple | None = option(None, "diagonal input weight (nu,); default: the env's R")


def make_lqr(env, prior_params, options=None) -> JaxController:
    """LQR about the goal or about the reference, from the prior model ``env.symbolic_model(prior_params)``.

    The law is ``u = u_eq - K_k (x - x_ref[k])``, with ``x`` the observed state, ``u_eq`` the prior model's
    equilibrium input (hover thrust, zero force) and ``K_k`` the gain of the linearisation about
    ``(x_ref[k], u_eq)``; with ``mode="goal"`` one gain about the goal serves every step. The gains are computed
    once here (float64, scipy) along the reference of ``prior_params``; ``act`` is a gather and a matrix product, so
    it vmaps over thousands of copies. The output is not clipped: saturation is the plant's.

    Args:
        env: the environment. prior_params: ``EnvParams`` of the controller's model (e.g. ``prior_params(env,
            params, 1.5)``); its ``Q`` and ``R`` are the default weights. options: ``Options`` fields as a mapping.

    Returns:
        A ``JaxController`` named ``"lqr"`` whose ``info`` holds the gains ``K`` ((num_gains, nu, nx) numpy).
    """
    opts = parse_options(Options, options, "controllers.lqr")
    path = "controllers.lqr"
    mode = setup.linearization_mode(env, opts.mode)
    Q, R = setup.cost_weights(env, prior_params, opts.q_diag, opts.r_diag, path)
    model = setup.prior_model(env, prior_params, "env")
    u_eq = setup.equilibrium_input(env, prior_params)
    points = setup.linearization_points(env, prior_params, model, mode)
    gains = []
    for x0 in points:
        lin = model.linearize(x0, u_eq)
        if opts.discrete:
            K, _ = discrete_lqr_gain(lin.Ad, lin.Bd, Q, R)
        else:
            K, _ = continuous_lqr_gain(lin.A, lin.B, Q, R)
        gains.append(K)
    gains = np.stack(gains)
    dtype = jnp.zeros(()).dtype
    K_all = jnp.asarray(gains, dtype=dtype)
    u_eq_j = jnp.asarray(u_eq, dtype=dtype)
    last = gains.shape[0] - 1

    def reset(key, reference):
        return ()

    def act(ctrl_state, obs, step, reference):
        k = jnp.clip(step, 0, reference.x_ref.shape[0] - 1)
        K = K_all[jnp.minimum(k, last)]
        x = state_from_obs(env, obs)
        return u_eq_j - K @ (x - reference.x_ref[k]), ctrl_state

    return JaxController("lqr", reset, act, info={"K": gains, "mode": mode, "discrete": opts.discrete})
