"""PPO's pure pieces: the diagonal Gaussian policy, generalised advantage estimation and the clipped losses.

Action convention: the policy is a diagonal Gaussian ``N(mu(obs), diag(exp(log_std))^2)`` over *unbounded*
actions; the environment wrapper (``scg_algorithms.rl.envs``) clips a sample to [-1, 1] before applying it. The clip is
part of the environment as the learner sees it, so the log-probabilities, ratios and entropy are those of the
unclipped Gaussian sample the learner stored (exact, closed form), and the deterministic action is
``clip(mu, -1, 1)``. (tanh squashing would need a Jacobian correction and has no closed-form entropy; near the
upright equilibrium the actions are small and the clip is rarely active.)

All functions are pure ``jax.numpy`` and work on any leading batch shape. The Gaussian's density and entropy are
the learners' shared ones (``scg_algorithms.rl.distributions``), re-exported here.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from scg_algorithms.rl.distributions import LOG_2PI, gaussian_entropy, gaussian_log_prob

__all__ = [
    "LOG_2PI",
    "clipped_surrogate_loss",
    "gae",
    "gaussian_entropy",
    "gaussian_log_prob",
    "normalize_advantages",
    "ppo_loss",
    "value_loss",
    "weighted_mean",
]


def gae(rewards, values, next_values, terminated, truncated, gamma: float, lam: float):
    """Generalised advantage estimation over a time-major rollout that may span several episodes.

    For step t: ``delta_t = r_t + gamma (1 - terminated_t) V'_t - V_t``, where ``V'_t`` is the value of the
    observation the step *reached* (``final_obs``, before any reset): at a time limit (``truncated``) the return
    is bootstrapped from it, at a termination it is not. ``A_t = delta_t + gamma lam (1 - done_t) A_{t+1}`` with
    ``done = terminated | truncated``: the trace stops at every episode boundary, and after the last step of the
    rollout (``A_T = 0``; its ``delta`` already bootstraps from ``V'``). The value targets are ``A_t + V_t``.

    Args:
        rewards, values, next_values: (T, ...) floats. terminated, truncated: (T, ...) bools.
        gamma: discount in [0, 1]. lam: GAE lambda in [0, 1] (1: Monte-Carlo returns bootstrapped at the end).

    Returns:
        ``(advantages, returns)``, each (T, ...).
    """
    dtype = values.dtype
    not_terminated = 1.0 - terminated.astype(dtype)
    not_done = 1.0 - (terminated | truncated).astype(dtype)
    deltas = rewards + gamma * not_terminated * next_values - values

    def backward(advantage_next, step):
        delta, continues = step
        advantage = delta + gamma * lam * continues * advantage_next
        return advantage, advantage

    _, advantages = jax.lax.scan(backward, jnp.zeros_like(deltas[0]), (deltas, not_done), reverse=True)
    return advantages, advantages + values


def weighted_mean(x, weight=None):
    """``mean(x)``, or with per-sample ``weight`` (same shape, >= 0) ``sum(weight x) / max(sum(weight), 1)``: with
    0/1 weights the mean over the samples weighted 1, and 0 (not NaN) when there are none."""
    if weight is None:
        return jnp.mean(x)
    return jnp.sum(weight * x) / jnp.maximum(jnp.sum(weight), 1.0)


def clipped_surrogate_loss(log_prob, old_log_prob, advantages, clip_eps: float, weight=None):
    """PPO's clipped policy objective, as a loss to minimise.

    ``L = -mean( min(rho A, clip(rho, 1 - eps, 1 + eps) A) )`` with ``rho = exp(log_prob - old_log_prob)``; every
    mean is ``weighted_mean`` with the per-sample ``weight`` when given.

    Returns:
        ``(loss, info)`` with ``info = {"clip_fraction": share of samples with |rho - 1| > eps,
        "approx_kl": mean((rho - 1) - log rho)}`` (the non-negative KL estimator of Schulman).
    """
    log_ratio = log_prob - old_log_prob
    ratio = jnp.exp(log_ratio)
    unclipped = ratio * advantages
    clipped = jnp.clip(ratio, 1.0 - clip_eps, 1.0 + clip_eps) * advantages
    loss = -weighted_mean(jnp.minimum(unclipped, clipped), weight)
    info = {
        "clip_fraction": weighted_mean((jnp.abs(ratio - 1.0) > clip_eps).astype(ratio.dtype), weight),
        "approx_kl": weighted_mean((ratio - 1.0) - log_ratio, weight),
    }
    return loss, info


def value_loss(values, old_values, returns, clip_eps: float | None = None, weight=None):
    """Half the mean squared error of the value, optionally clipped around the rollout's values.

    Unclipped: ``0.5 mean((V - R)^2)``. Clipped (``clip_eps`` given): with ``V_c = V_old + clip(V - V_old, -eps,
    eps)``, ``0.5 mean(max((V - R)^2, (V_c - R)^2))``, so a value step beyond ``eps`` from ``V_old`` earns no
    further reduction. The mean is ``weighted_mean`` with the per-sample ``weight`` when given.
    """
    error = jnp.square(values - returns)
    if clip_eps is not None:
        clipped = old_values + jnp.clip(values - old_values, -clip_eps, clip_eps)
        error = jnp.maximum(error, jnp.square(clipped - returns))
    return 0.5 * weighted_mean(error, weight)


def normalize_advantages(advantages, eps: float = 1e-8, weight=None):
    """``(A - mean A) / (std A + eps)`` over the whole array (a minibatch); with per-sample ``weight``, the mean
    and the (population) std are ``weighted_mean``-s, so 0/1 weights standardise the samples weighted 1."""
    if weight is None:
        return (advantages - jnp.mean(advantages)) / (jnp.std(advantages) + eps)
    centre = weighted_mean(advantages, weight)
    std = jnp.sqrt(weighted_mean(jnp.square(advantages - centre), weight))
    return (advantages - centre) / (std + eps)


def ppo_loss(
    mean,
    log_std,
    values,
    actions,
    old_log_prob,
    old_values,
    advantages,
    returns,
    *,
    clip_eps: float,
    value_clip_eps: float | None,
    vf_coef: float,
    ent_coef: float,
    weight=None,
):
    """The total PPO loss ``L_clip + vf_coef L_V - ent_coef H`` of a minibatch.

    Args:
        mean: (B, d) policy means. log_std: (d,). values: (B,) critic outputs. actions: (B, d) stored (unclipped)
            samples. old_log_prob, old_values: (B,) from the rollout. advantages, returns: (B,) from ``gae``
            (already normalised if wanted). weight: optional (B,) per-sample weights (>= 0): every mean is then a
            weighted mean (``weighted_mean``), e.g. 0/1 weights give the loss of the samples weighted 1 (one
            adversary's steps in a batch of all), and all-zero weights a zero loss and gradient (the entropy
            bonus too).

    Returns:
        ``(loss, info)``; ``info`` holds ``policy_loss``, ``value_loss``, ``entropy``, ``clip_fraction``,
        ``approx_kl``.
    """
    log_prob = gaussian_log_prob(mean, log_std, actions)
    policy_loss, info = clipped_surrogate_loss(log_prob, old_log_prob, advantages, clip_eps, weight)
    v_loss = value_loss(values, old_values, returns, value_clip_eps, weight)
    entropy = gaussian_entropy(log_std)
    if weight is None:
        bonus = ent_coef * entropy
    else:  # no sample, no bonus: a member of a population that did not act this minibatch is left alone
        bonus = (jnp.sum(weight) > 0).astype(mean.dtype) * ent_coef * entropy
    loss = policy_loss + vf_coef * v_loss - bonus
    return loss, {"policy_loss": policy_loss, "value_loss": v_loss, "entropy": entropy, **info}
