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
