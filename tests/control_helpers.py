"""Set-ups shared by the model-based controller tests."""

import jax.numpy as jnp
import numpy as np

import scg_jax


def cartpole_with_full_q():
    """The cart-pole with a non-diagonal state weight (x with theta, x_dot with theta_dot; eigenvalues 0.2-1.8).

    Returns:
        ``(env, params, Q)``: the env, its default params with that ``Q``, and ``Q`` (4, 4) float64.
    """
    env = scg_jax.make("cartpole")
    Q = np.eye(4)
    Q[0, 2] = Q[2, 0] = 0.8
    Q[1, 3] = Q[3, 1] = 0.5
    params = env.default_params.replace(Q=jnp.asarray(Q, env.default_params.Q.dtype))
    return env, params, Q


def env_and_random_states(make_kwargs: dict, spread, count: int, offset=0.0, seed: int = 0):
    """An env from ``make_kwargs`` (with its ``"system"``) and ``count`` random (step, state) pairs around it.

    Returns:
        ``(env, params, reference, steps, states)``: the env, its default params, its reference (float64 numpy),
        the control steps (random for tracking, 0 for stabilization) and the states ``x_ref[step] + offset +
        U(-spread, spread)`` (count, nx).
    """
    from scg_algorithms.base import Reference
    from scg_algorithms.mpc.cases import random_states

    make_kwargs = dict(make_kwargs)
    env = scg_jax.make(make_kwargs.pop("system"), **make_kwargs)
    params = env.default_params
    reference = Reference(*(np.asarray(a, np.float64) for a in env.reference(params)))
    steps, states = random_states(env, reference, offset, spread, count, seed)
    return env, params, reference, steps, states
