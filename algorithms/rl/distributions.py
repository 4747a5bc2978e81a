"""The Gaussian densities of the RL policies, in one place: PPO's diagonal Gaussian and SAC's tanh-squashed one.

All functions are pure ``jax.numpy`` over any leading batch shape; the last axis is the action dimension d. Units:
nats.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

LOG_2PI = math.log(2.0 * math.pi)


def gaussian_log_prob(mean, log_std, x):
    """Log-density of ``x`` under ``N(mean, diag(exp(log_std))^2)``, summed over the last axis.

    ``log p = sum_i [ -0.5 ((x_i - mu_i) / sigma_i)^2 - log sigma_i - 0.5 log(2 pi) ]``.

    Args:
        mean: (..., d). log_std: (d,) or (..., d). x: (..., d).

    Returns:
        (...) log-density.
    """
    z = (x - mean) * jnp.exp(-log_std)
    return jnp.sum(-0.5 * jnp.square(z) - log_std - 0.5 * LOG_2PI, axis=-1)


def gaussian_entropy(log_std):
    """Differential entropy of the diagonal Gaussian, ``sum_i (0.5 (1 + log(2 pi)) + log sigma_i)``.

    Args:
        log_std: (d,) or (..., d). Returns: (...).
    """
    return jnp.sum(0.5 * (1.0 + LOG_2PI) + log_std, axis=-1)


def log1m_tanh_sq(u):
    """``log(1 - tanh(u)^2)`` computed stably as ``2 (log 2 - u - softplus(-2 u))`` (finite for any |u|)."""
    return 2.0 * (math.log(2.0) - u - jax.nn.softplus(-2.0 * u))


def tanh_gaussian_log_prob(u, mean, log_std):
    """Log density of ``a = tanh(u)``, ``u ~ N(mean, exp(log_std)^2)``, evaluated at the pre-squash ``u``.

    Change of variables: ``log p(a) = log N(u) - sum_i log(1 - tanh(u_i)^2)`` (the Jacobian of tanh is diagonal).

    Args:
        u: (..., d) pre-squash sample. mean, log_std: (..., d).

    Returns:
        (...) log-prob of the squashed action.
    """
    return gaussian_log_prob(mean, log_std, u) - jnp.sum(log1m_tanh_sq(u), axis=-1)


def sample_tanh_gaussian(key, mean, log_std):
    """Reparameterised sample ``a = tanh(mean + exp(log_std) * eps)`` and its log-prob.

    Returns:
        ``(a, log_prob)``: a (..., d) in (-1, 1) (may round to +-1 in float32), log_prob (...).
    """
    u = mean + jnp.exp(log_std) * jax.random.normal(key, mean.shape, mean.dtype)
    return jnp.tanh(u), tanh_gaussian_log_prob(u, mean, log_std)
