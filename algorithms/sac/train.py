"""Soft actor-critic in JAX on the learners' off-policy skeleton (``scg_algorithms.rl.off_policy``): the whole
training loop is one pure function of a key and the env params.

The skeleton collects, replays and warms up (``rollout_steps`` control steps in each of ``num_envs`` copies per
iteration, then ``utd * num_envs * rollout_steps`` gradient steps on batches drawn uniformly from the buffer; the
first ``warmup_iterations`` act uniformly at random and do not learn). SAC's part is the gradient step, which
updates, in this order, the twin critics (soft Bellman target from the Polyak-averaged target critics, no
bootstrapping where the episode *terminated*; a time-limit truncation bootstraps from the stored final
observation), the actor (reparameterised tanh-Gaussian, against the freshly updated critics), the temperature
(towards the entropy target ``target_entropy_per_action * nu``), and the target critics (``tau``); exploration
samples the tanh-Gaussian policy.

``make_train(config, env)(key, params)`` runs the budget in one ``lax.scan`` (``scg_algorithms.rl.learner``): jit it,
vmap it over keys for seeds. ``make_learner(config, env)`` exposes the same iteration to the host driver
(``scg_algorithms.rl.training.run_training``), choosing warm-up or learning with ``lax.cond`` on the iteration count.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax

from scg_algorithms.rl import learner as learner_lib
from scg_algorithms.rl import off_policy
from scg_algorithms.rl.networks import QNetwork, TanhGaussianActor, twin_q
from scg_algorithms.rl.normalization import init_stats, normalize
from scg_algorithms.rl.off_policy import PolicyParams, RunnerState, policy_params
from scg_algorithms.rl.training import Learner
from scg_algorithms.sac import losses
from scg_algorithms.sac.config import Config, parse_config

__all__ = [
    "LOSS_METRICS",
    "NAME",
    "Learning",
    "PolicyParams",
    "RunnerState",
    "make_learner",
    "make_networks",
    "make_policy_fn",
    "make_policy_from_config",
    "make_train",
    "policy_params",
]

NAME = "sac"


def make_networks(config: Config, action_size: int) -> tuple[TanhGaussianActor, QNetwork]:
    """The actor and critic modules of ``config``."""
    actor = TanhGaussianActor(
        config.hidden_sizes, action_size, config.activation, config.log_std_min, config.log_std_max
    )
    return actor, QNetwork(config.hidden_sizes, config.activation)


# --------------------------------------------------------------------------------------------- policy
def make_policy_fn(config: Config, action_size: int) -> Callable:
    """``policy_fn(policy_params, obs, key=None) -> a``: a sampled action in [-1, 1]^nu (``tanh(mean)`` when
    ``key`` is None, the deterministic policy used for evaluation). Works on (obs_size,) or batched obs."""
    actor, _ = make_networks(config, action_size)

    def policy_fn(policy_params: PolicyParams, obs, key=None):
        if config.normalize_observations:
            obs = normalize(policy_params.obs_stats, obs)
        mean, log_std = actor.apply(policy_params.actor, obs)
        if key is None:
            return jnp.tanh(mean)
        action, _ = losses.sample_tanh_gaussian(key, mean, log_std)
        return action

    return policy_fn


def make_policy_from_config(config_dict: Mapping | Config, obs_size: int, action_size: int):
    """Rebuild a saved SAC policy: ``(init, apply)`` for ``scg_algorithms.rl.policy.load_policy``.

    Args:
        config_dict: the saved ``Config.to_dict()`` (or a ``Config``). obs_size, action_size: of the env.

    Returns:
        ``init(key) -> PolicyParams`` (the structure to restore a checkpoint into) and
        ``apply(policy_params, obs, key=None) -> a`` in [-1, 1]^nu (deterministic when ``key`` is None).
    """
    config = parse_config(config_dict)
    actor, _ = make_networks(config, action_size)

    def init(key) -> PolicyParams:
        return PolicyParams(actor=actor.init(key, jnp.zeros((obs_size,))), obs_stats=init_stats(obs_size))

    return init, make_policy_fn(config, action_size)


# --------------------------------------------------------------------------------------------- learning
class Learning(NamedTuple):
    """What a SAC gradient step changes (``RunnerState.learning``).

    Attributes:
        actor, critic, target_critic: flax params (critics: two sets stacked on a leading axis).
        log_alpha: scalar log temperature. actor_opt, critic_opt, alpha_opt: optax states.
    """

    actor: Any
    critic: Any
    target_critic: Any
    log_alpha: Any
    actor_opt: Any
    critic_opt: Any
    alpha_opt: Any


LOSS_METRICS = ("critic_loss", "actor_loss", "alpha_loss", "alpha", "entropy", "q_mean")


def _algorithm(config: Config, action_size: int) -> off_policy.Algorithm:
    """SAC's part of the off-policy skeleton."""
    actor, critic = make_networks(config, action_size)
    policy_fn = make_policy_fn(config, action_size)
    actor_tx = off_policy.make_optimizer(config.actor_lr, config.max_grad_norm)
    critic_tx = off_policy.make_optimizer(config.critic_lr, config.max_grad_norm)
    alpha_tx = optax.adam(config.alpha_lr)
    target_entropy = config.target_entropy_per_action * action_size

    def init(key_actor, key_critic, dummy_obs, dummy_action) -> Learning:
        actor_params, critic_params = off_policy.init_networks(
            actor, critic, 2, key_actor, key_critic, dummy_obs, dummy_action
        )
        log_alpha = jnp.asarray(math.log(config.init_alpha), jnp.float32)
        return Learning(
            actor=actor_params,
            critic=critic_params,
            target_critic=critic_params,
            log_alpha=log_alpha,
            actor_opt=actor_tx.init(actor_params),
            critic_opt=critic_tx.init(critic_params),
            alpha_opt=alpha_tx.init(log_alpha),
        )

    def explore(policy: PolicyParams, obs, key):
        return jax.vmap(policy_fn, in_axes=(None, 0, 0))(policy, obs, jax.random.split(key, obs.shape[0]))

    def update(carry: Learning, keys, batch) -> tuple[Learning, dict]:
        """The critics, the actor, the temperature and the target critics, in that order."""
        key_next, key_pi = keys
        obs, next_obs = batch["obs"], batch["next_obs"]
        log_alpha = carry.log_alpha
        alpha = jnp.exp(log_alpha)

        next_mean, next_log_std = actor.apply(carry.actor, next_obs)
        next_action, next_log_prob = losses.sample_tanh_gaussian(key_next, next_mean, next_log_std)
        next_q = twin_q(critic, carry.target_critic, next_obs, next_action)
        target = losses.critic_target(batch["reward"], batch["terminated"], next_q, next_log_prob, alpha, config.gamma)
        target = jax.lax.stop_gradient(target)

        critic_params, critic_opt, critic_loss, q = off_policy.critic_step(
            critic, critic_tx, carry.critic, carry.critic_opt, obs, batch["action"], target
        )

        def actor_objective(a_params):
            mean, log_std = actor.apply(a_params, obs)
            action, log_prob = losses.sample_tanh_gaussian(key_pi, mean, log_std)
            q_pi = twin_q(critic, critic_params, obs, action)
            return losses.actor_loss(q_pi, log_prob, alpha), log_prob

        (actor_loss, log_prob), actor_grads = jax.value_and_grad(actor_objective, has_aux=True)(carry.actor)
        updates, actor_opt = actor_tx.update(actor_grads, carry.actor_opt, carry.actor)
        actor_params = optax.apply_updates(carry.actor, updates)

        alpha_opt = carry.alpha_opt
        alpha_loss, alpha_grad = jax.value_and_grad(losses.temperature_loss)(log_alpha, log_prob, target_entropy)
        if config.autotune_alpha:
            updates, alpha_opt = alpha_tx.update(alpha_grad, alpha_opt, log_alpha)
            log_alpha = optax.apply_updates(log_alpha, updates)

        target_params = losses.polyak_update(carry.target_critic, critic_params, config.tau)
        metrics = {
            "critic_loss": critic_loss,
            "actor_loss": actor_loss,
            "alpha_loss": alpha_loss,
            "alpha": alpha,
            "entropy": -jnp.mean(log_prob),
            "q_mean": jnp.mean(q),
        }
        new = Learning(actor_params, critic_params, target_params, log_alpha, actor_opt, critic_opt, alpha_opt)
        return new, metrics

    def idle(carry: Learning) -> dict:
        return {**{name: jnp.zeros((), jnp.float32) for name in LOSS_METRICS}, "alpha": jnp.exp(carry.log_alpha)}

    return off_policy.Algorithm(
        init=init, explore=explore, update=update, idle=idle, policy=policy_fn, metric_names=LOSS_METRICS,
        num_update_keys=2,
    )  # fmt: skip


# --------------------------------------------------------------------------------------------- public API
def _learner(config: Config | Mapping | None, env) -> tuple[Learner, Callable]:
    """SAC as a ``Learner`` and its ``update_at`` for ``scg_algorithms.rl.learner.make_train``."""
    config = parse_config(config)
    return off_policy.make_learner(NAME, config, env, _algorithm(config, env.action_size))


def make_learner(config: Config | Mapping | None, env) -> Learner:
    """``scg_algorithms.rl.training.Learner`` for the host driver (``run_training``).

    ``update`` is one iteration; warm-up or learning is chosen from ``runner_state.iteration``, so a chain of
    ``num_iterations`` updates is the same computation as ``make_train``.
    """
    return _learner(config, env)[0]


def make_train(config: Config | Mapping | None, env) -> Callable:
    """``train(key, params) -> (runner_state, metrics)``: the whole budget, jit- and vmap-able (over keys), as
    ``scg_algorithms.rl.learner.make_train`` of SAC's learner.

    Args:
        config: a ``Config`` or a ``training.sac`` mapping. env: an ``scg_jax.Env`` (any ``action_mode``).

    Returns:
        ``train``: ``key`` a PRNG key, ``params`` unbatched ``EnvParams``; ``metrics`` a dict of
        (num_iterations,) arrays: ``env_steps``, ``grad_steps`` (``scg_algorithms.rl.counter.Count``s of
        (num_iterations,) uint32 words; ``count_value`` gives the exact integers), ``episode_return``, ``episode_cost``,
        ``episode_rmse``, ``episode_length``, ``episodes_finished`` and the means over the iteration's gradient
        steps of ``critic_loss``, ``actor_loss``, ``alpha_loss``, ``alpha``, ``entropy``, ``q_mean`` (0 during
        warm-up).
    """
    return learner_lib.make_train(*_learner(config, env))
