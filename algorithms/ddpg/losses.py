"""DDPG's and TD3's pure loss functions (Lillicrap et al. 2016; Fujimoto et al. 2018, "Addressing Function
Approximation Error in Actor-Critic Methods").

Conventions: a batch has B transitions; actions live in [-1, 1]^nu; the actor is deterministic, ``mu(s) =
tanh(net(s))``; K critics are stacked on a leading axis (K = 1 for DDPG, 2 for TD3). Every function is
differentiable with ``jax.grad`` and has worked-number tests in ``tests/test_ddpg.py``. The critics' regression loss
and the Polyak update are the off-policy skeleton's (``scg_algorithms.rl.off_policy``), re-exported here.
"""

from __future__ import annotations

import jax.numpy as jnp

from scg_algorithms.rl.off_policy import critic_loss, polyak_update

__all__ = ["actor_loss", "critic_loss", "critic_target", "polyak_update", "smoothed_target_action"]


def smoothed_target_action(target_mu, noise, noise_clip):
    """TD3's target policy smoothing ``a' = clip(mu'(s') + clip(noise, -c, c), -1, 1)``.

    Args:
        target_mu: (B, nu) the target actor's action at ``s'`` in [-1, 1]. noise: (B, nu) Gaussian noise of std
            ``target_noise`` (zeros: DDPG's ``a' = mu'(s')``). noise_clip: c >= 0.

    Returns:
        (B, nu) the action the target critics are evaluated at.
    """
    return jnp.clip(target_mu + jnp.clip(noise, -noise_clip, noise_clip), -1.0, 1.0)


def critic_target(reward, terminated, next_q, gamma):
    """Bellman target ``y = r + gamma (1 - terminated) min_k Q'_k(s', a')``: with two critics the clipped double-Q
    target of TD3, with one DDPG's ``r + gamma Q'(s', mu'(s'))``.

    ``terminated`` stops bootstrapping (the episode truly ended); a time-limit truncation is stored with
    ``terminated = 0`` and the final observation as ``s'``, so it bootstraps.

    Args:
        reward: (B,) reward (already scaled). terminated: (B,) 0/1 or bool. next_q: (K, B) the target critics at
            ``(s', a')``. gamma: discount.

    Returns:
        (B,) targets; callers stop their gradient.
    """
    return reward + gamma * (1.0 - terminated.astype(reward.dtype)) * jnp.min(next_q, axis=0)


def actor_loss(q):
    """Deterministic policy-gradient loss ``-mean_b Q_1(s_b, mu(s_b))``: the first critic only (TD3 and DDPG alike).

    Args:
        q: (K, B) the online critics at ``(s, mu(s))``; only ``q[0]`` is used (the others get no gradient).

    Returns:
        scalar loss (its gradient flows into the actor through ``mu(s)``).
    """
    return -jnp.mean(q[0])
