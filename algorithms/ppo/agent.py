"""PPO's agent: the one PPO update that every PPO-based learner runs (PPO, safety-layer PPO, PPO-Lagrangian, and
the protagonist and adversaries of RARL and RAP).

An agent is a diagonal Gaussian policy ``N(mu(obs), diag(exp(log_std))^2)`` over unbounded actions (an ``MLP`` mean
and a state-independent ``log_std``) with a separate value network (``Networks``), and its optimiser state
(``Agent``). Its parameters are ``{"actor": flax params, "critic": flax params, "log_std": (d,)}``. From a rollout
it learns in two steps:

1. ``gae_batch``: GAE advantages and value targets, and every field of the rollout flattened to one batch;
2. ``ppo_epochs``: ``num_epochs`` passes of ``num_minibatches`` shuffled minibatches, one step of the optimiser
   (``make_optimizer``: global gradient-norm clip, Adam, optional linear decay to 0) on a loss per minibatch,
   usually ``minibatch_loss`` (PPO's clipped loss, optionally with per-sample weights).

``config`` is any learner ``Config`` with PPO's fields (``scg_algorithms.ppo.Config`` or a subclass).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax

from scg_algorithms.ppo import losses
from scg_algorithms.rl.networks import MLP, value_network
from scg_algorithms.rl.normalization import normalize
from scg_algorithms.rl.training import raw_key


class Agent(NamedTuple):
    """One PPO agent: ``params`` ``{"actor", "critic", "log_std"}`` and its optax state (a population: every leaf
    stacked on a leading member axis)."""

    params: Any
    opt_state: Any


class Networks(NamedTuple):
    """An agent's networks: ``actor`` (obs -> mean (..., action_size)) and ``critic`` (obs -> (..., 1))."""

    actor: MLP
    critic: MLP
    action_size: int

    def mean(self, params, obs):
        """The policy mean (..., action_size) of ``params`` at (normalised) ``obs`` (..., obs_size)."""
        return self.actor.apply(params["actor"], obs)

    def value(self, params, obs):
        """The value (...) of ``params`` at (normalised) ``obs`` (..., obs_size)."""
        return self.critic.apply(params["critic"], obs)[..., 0]


def make_networks(actor_hidden, critic_hidden, activation: str, action_size: int) -> Networks:
    """The actor (last layer initialised at 0.01 scale: a mean near 0) and the critic."""
    actor = MLP((*actor_hidden, action_size), activation, final_scale=0.01)
    return Networks(actor, value_network(critic_hidden, activation), action_size)


def init_params(networks: Networks, key_actor, key_critic, obs_size: int, init_log_std: float) -> dict:
    """Fresh parameters ``{"actor", "critic", "log_std"}``, ``log_std`` filled with ``init_log_std``."""
    dummy = jnp.zeros((1, obs_size))
    return {
        "actor": networks.actor.init(key_actor, dummy),
        "critic": networks.critic.init(key_critic, dummy),
        "log_std": jnp.full((networks.action_size,), init_log_std, jnp.float32),
    }


def _num_updates(config, num_updating_iterations: int) -> int:
    return max(1, num_updating_iterations * config.num_epochs * config.num_minibatches)


def make_optimizer(config, learning_rate: float, num_updating_iterations: int) -> optax.GradientTransformation:
    """Global gradient-norm clip (``max_grad_norm``) and Adam at ``learning_rate``, decayed linearly to 0 over the
    optimiser steps of ``num_updating_iterations`` iterations when ``lr_decay``."""
    if config.lr_decay:
        schedule = optax.linear_schedule(
            learning_rate, 0.0, transition_steps=_num_updates(config, num_updating_iterations)
        )
        learning_rate = schedule
    return optax.chain(optax.clip_by_global_norm(config.max_grad_norm), optax.adam(learning_rate, eps=1e-5))


def current_learning_rate(config, learning_rate: float, num_updating_iterations: int, opt_state):
    """The step size ``make_optimizer``'s Adam used last (the schedule at its count), for the metrics."""
    if not config.lr_decay:
        return jnp.asarray(learning_rate, jnp.float32)
    count = opt_state[1][0].count
    total = _num_updates(config, num_updating_iterations)
    return learning_rate * (1.0 - jnp.minimum(count, total) / total)


def observe(config, stats, obs):
    """``obs`` as the networks see it: normalised with ``stats`` (clipped to ``obs_clip``) when
    ``normalize_observations``, else unchanged."""
    return normalize(stats, obs, config.obs_clip) if config.normalize_observations else obs


def sample_action(key, mean, log_std):
    """A sample ``mean + exp(log_std) * noise`` (unclipped: the env clips it) of the Gaussian policy."""
    return mean + jnp.exp(log_std) * jax.random.normal(key, mean.shape, mean.dtype)


def policy_action(mean, log_std, key=None):
    """The acting policy's action in [-1, 1]: ``clip(mean)`` without a key, a clipped sample with one."""
    if key is None:
        return jnp.clip(mean, -1.0, 1.0)
    noise = jax.random.normal(raw_key(key), mean.shape, mean.dtype)
    return jnp.clip(mean + jnp.exp(log_std) * noise, -1.0, 1.0)


def saved_policy(params, obs_stats) -> dict:
    """What a trained agent's policy needs to act: ``{"actor", "log_std", "obs_stats"}``."""
    return {"actor": params["actor"], "log_std": params["log_std"], "obs_stats": obs_stats}


def make_policy(config, policy_mean: Callable, policy_params: Mapping):
    """``policy(obs, key=None) -> a`` in [-1, 1] (``policy_action``) of ``policy_params`` (``saved_policy``, plus
    what ``policy_mean`` reads), where ``policy_mean(policy_params, obs, raw_obs) -> mean`` takes the normalised and
    the raw observation."""

    def policy(obs, key=None):
        mean = policy_mean(policy_params, observe(config, policy_params["obs_stats"], obs), obs)
        return policy_action(mean, policy_params["log_std"], key)

    return policy


def gae_batch(config, reward, value, next_value, terminated, truncated, **fields) -> dict:
    """GAE of a time-major rollout (``losses.gae`` with ``gamma``, ``gae_lambda``) as one flat batch.

    Args:
        reward, value, next_value: (T, N) floats (``next_value``: of the observation each step reached).
        terminated, truncated: (T, N) bools. fields: pytrees with leaves (T, N, ...) to batch with them
            (``obs``, ``action``, ``log_prob``, ...).

    Returns:
        ``{**fields, "value", "advantages", "returns"}``, every leaf (T * N, ...).
    """
    advantages, returns = losses.gae(reward, value, next_value, terminated, truncated, config.gamma, config.gae_lambda)
    flat = lambda x: jnp.reshape(x, (-1, *x.shape[2:]))  # noqa: E731
    batch = {name: jax.tree.map(flat, field) for name, field in fields.items()}
    return {**batch, "value": flat(value), "advantages": flat(advantages), "returns": flat(returns)}


def minibatch_loss(config, mean, log_std, values, minibatch: Mapping, advantages=None, weight=None):
    """PPO's loss (``losses.ppo_loss`` with ``config``'s coefficients) of a minibatch of ``gae_batch``.

    Args:
        mean: (B, d) the policy's means at ``minibatch["obs"]``. log_std: (d,). values: (B,) the critic's.
        advantages: (B,) the actor's advantages; default ``minibatch["advantages"]``, standardised (with
            ``weight``) when ``normalize_advantages``. weight: optional (B,) per-sample weights (``ppo_loss``).
    """
    if advantages is None:
        advantages = minibatch["advantages"]
        if config.normalize_advantages:
            advantages = losses.normalize_advantages(advantages, weight=weight)
    return losses.ppo_loss(
        mean,
        log_std,
        values,
        minibatch["action"],
        minibatch["log_prob"],
        minibatch["value"],
        advantages,
        minibatch["returns"],
        clip_eps=config.clip_eps,
        value_clip_eps=config.value_clip_eps if config.value_clip_eps > 0 else None,
        vf_coef=config.vf_coef,
        ent_coef=config.ent_coef,
        weight=weight,
    )


def ppo_epochs(loss: Callable, optimizer, agent: Agent, data: Mapping, key, config, aux=(), aux_step=None):
    """``num_epochs`` passes over ``data`` in ``num_minibatches`` minibatches, shuffled afresh each epoch (a
    permutation drawn from that epoch's key), one ``optimizer`` step of ``loss`` on each minibatch.

    Args:
        loss: ``loss(params, aux, minibatch) -> (loss, info)``. optimizer: optax. agent: ``Agent``. data: the batch
            (``gae_batch``), every leaf (B, ...). key: PRNG key, split ``num_epochs`` ways. aux: state of the
            learner's own that ``loss`` reads and ``aux_step`` updates (``()`` for none).
        aux_step: optional ``aux_step(aux, minibatch) -> (aux, info)``, run after each optimiser step (a variant's
            own networks, with their own optimiser).

    Returns:
        ``(agent, aux, info)``: ``info`` the means over every minibatch of ``loss``'s info, ``loss``,
        ``grad_norm`` (of the unclipped gradient) and ``aux_step``'s info.
    """
    grad_fn = jax.value_and_grad(loss, has_aux=True)
    batch = jax.tree.leaves(data)[0].shape[0]
    minibatch = batch // config.num_minibatches

    def sgd_step(carry, mb):
        agent, aux = carry
        (value, info), grads = grad_fn(agent.params, aux, mb)
        updates, opt_state = optimizer.update(grads, agent.opt_state, agent.params)
        agent = Agent(optax.apply_updates(agent.params, updates), opt_state)
        info = {**info, "loss": value, "grad_norm": optax.tree.norm(grads)}
        if aux_step is not None:
            aux, aux_info = aux_step(aux, mb)
            info = {**info, **aux_info}
        return (agent, aux), info

    def epoch(carry, epoch_key):
        permutation = jax.random.permutation(epoch_key, batch)
        shuffled = jax.tree.map(
            lambda x: jnp.reshape(x[permutation], (config.num_minibatches, minibatch, *x.shape[1:])), data
        )
        return jax.lax.scan(sgd_step, carry, shuffled)

    (agent, aux), infos = jax.lax.scan(epoch, (agent, aux), jax.random.split(key, config.num_epochs))
    return agent, aux, jax.tree.map(jnp.mean, infos)
