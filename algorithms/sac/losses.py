"""SAC's pure loss functions (Haarnoja et al. 2018, "Soft Actor-Critic Algorithms and Applications").

Conventions: a batch has B transitions; actions live in [-1, 1]^nu as ``a = tanh(u)`` with
``u ~ N(mean, exp(log_std)^2)`` (the pre-squash sample ``u``); ``alpha`` is the entropy temperature; log-probs are
of the squashed action ``a`` (nats). Every function is differentiable with ``jax.grad`` and has worked-number tests
in ``tests/test_sac.py``. The tanh-Gaussian density and sampler are the learners' shared ones
(``scg_algorithms.rl.distributions``), and the critics' regression loss and the Polyak update the off-policy
skeleton's (``scg_algorithms.rl.off_policy``), re-exported here.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from scg_algorithms.rl.distributions import (
    log1m_tanh_sq,
    sample_tanh_gaussian,
    tanh_gaussian_log_prob,
)
from scg_algorithms.rl.off_policy import critic_loss, polyak_update

__all__ = [
    "actor_loss",
    "critic_loss",
    "critic_target",
    "log1m_tanh_sq",
    "polyak_update",
    "sample_tanh_gaussian",
    "tanh_gaussian_log_prob",
    "temperature_loss",
]


def critic_target(reward, terminated, next_q, next_log_prob, alpha, gamma):
    """Soft Bellman target ``y = r + gamma (1 - terminated) (min_j Q'_j(s', a') - alpha log pi(a'|s'))``.

    ``terminated`` stops bootstrapping (the episode truly ended: the value after it is 0); a *truncated* episode
    (time limit) is stored with ``terminated = 0`` and the final observation as ``s'``, so it bootstraps.

    Args:
        reward: (B,) reward (already scaled). terminated: (B,) 0/1 or bool. next_q: (2, B) the target critics at
            ``(s', a')`` with ``a' ~ pi(.|s')``. next_log_prob: (B,) ``log pi(a'|s')``. alpha: scalar temperature.
        gamma: discount.

    Returns:
        (B,) targets; callers stop their gradient.
    """
    soft_value = jnp.min(next_q, axis=0) - alpha * next_log_prob
    return reward + gamma * (1.0 - terminated.astype(reward.dtype)) * soft_value


def actor_loss(q, log_prob, alpha):
    """Policy loss ``mean_b (alpha log pi(a_b|s_b) - min_j Q_j(s_b, a_b))`` with ``a_b`` the reparameterised sample.

    Args:
        q: (2, B) the online critics at ``(s, a ~ pi)``. log_prob: (B,). alpha: scalar temperature (gradient
            stopped here: the actor does not move the temperature).

    Returns:
        scalar loss (its gradient flows into the actor through ``a`` and ``log_prob``).
    """
    return jnp.mean(jax.lax.stop_gradient(alpha) * log_prob - jnp.min(q, axis=0))


def temperature_loss(log_alpha, log_prob, target_entropy):
    """Temperature loss ``mean_b alpha (-log pi(a_b|s_b) - target_entropy)``, ``alpha = exp(log_alpha)``.

    Its gradient in ``log_alpha`` is ``alpha (H_hat - target_entropy)`` with ``H_hat = -mean log pi``: the
    temperature falls while the policy's entropy is above the target and rises below it.

    Args:
        log_alpha: scalar, the optimised variable. log_prob: (B,) (gradient stopped here). target_entropy: scalar
            (``-nu`` by default).

    Returns:
        scalar loss.
    """
    return jnp.mean(jnp.exp(log_alpha) * (-jax.lax.stop_gradient(log_prob) - target_entropy))
