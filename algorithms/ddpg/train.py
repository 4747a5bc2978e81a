"""DDPG and TD3 in JAX on the learners' off-policy skeleton (``scg_algorithms.rl.off_policy``): the whole training
loop is one pure function of a key and the env params.

The skeleton collects, replays and warms up as for SAC. The deterministic actor-critic's gradient step:

1. the target action ``a' = clip(mu'(s') + clip(eps, -c, c), -1, 1)`` of the target actor, ``eps ~ N(0,
   target_noise^2)`` (target policy smoothing; none with ``target_noise = 0``);
2. the critics regress on ``y = r + gamma (1 - terminated) min_k Q'_k(s', a')`` (the clipped double-Q target with
   ``twin_critics``, DDPG's target with one critic);
3. every ``policy_delay``-th critic update, the actor ascends ``Q_1(s, mu(s))`` against the freshly updated critic,
   and the target actor and critics move towards the online ones by ``tau``.

DDPG is this with one critic, no smoothing and no delay; TD3 with twin critics, smoothing and a delay of 2
(``scg_algorithms.ddpg.td3``). Exploration adds Gaussian noise of std ``exploration_noise`` to ``mu(s)``; the
deterministic policy, used for evaluation, is ``mu(s)``.

``learner_functions(name, config_cls)`` builds ``make_learner`` and ``make_train`` for each of the two names.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax

from scg_algorithms.base import parse_options
from scg_algorithms.ddpg import losses
from scg_algorithms.ddpg.config import Config
from scg_algorithms.rl import learner as learner_lib
from scg_algorithms.rl import off_policy
from scg_algorithms.rl.networks import DeterministicActor, QNetwork, twin_q
from scg_algorithms.rl.normalization import normalize
from scg_algorithms.rl.off_policy import PolicyParams
from scg_algorithms.rl.training import Learner

__all__ = ["LOSS_METRICS", "Learning", "learner_functions", "make_networks"]


def make_networks(config: Config, action_size: int) -> tuple[DeterministicActor, QNetwork]:
    """The actor and critic modules of ``config``."""
    return (
        DeterministicActor(config.hidden_sizes, action_size, config.activation),
        QNetwork(config.hidden_sizes, config.activation),
    )


class Learning(NamedTuple):
    """What a DDPG/TD3 gradient step changes (``RunnerState.learning``).

    Attributes:
        actor, target_actor: flax params of the actor and its Polyak average.
        critic, target_critic: flax params of the K critics stacked on a leading axis (K = 2 with
            ``twin_critics``), and their Polyak averages.
        actor_opt, critic_opt: optax states.
        phase: int32 scalar, critic updates since the last actor update (modulo ``policy_delay``).
    """

    actor: Any
    critic: Any
    target_actor: Any
    target_critic: Any
    actor_opt: Any
    critic_opt: Any
    phase: Any


LOSS_METRICS = ("critic_loss", "actor_loss", "q_mean", "actor_updates")
"""Per iteration: the means over its gradient steps of the critics' loss and Q, the actor's loss over the steps that
updated the actor (0 when none did), and the fraction of steps that did."""


def _summarize(step_metrics: dict) -> dict:
    updates = step_metrics["actor_updates"]
    actor_loss = jnp.sum(step_metrics["actor_loss"] * updates) / jnp.maximum(jnp.sum(updates), 1.0)
    return {**{name: jnp.mean(value) for name, value in step_metrics.items()}, "actor_loss": actor_loss}


def make_policy_fn(config: Config, action_size: int) -> Callable:
    """``policy_fn(policy_params, obs, key=None) -> a`` in [-1, 1]^nu: ``mu(obs)`` without a key, with one
    ``clip(mu(obs) + exploration_noise * N(0, 1), -1, 1)``. Works on (obs_size,) or batched obs."""
    actor, _ = make_networks(config, action_size)

    def policy_fn(policy_params: PolicyParams, obs, key=None):
        if config.normalize_observations:
            obs = normalize(policy_params.obs_stats, obs)
        mu = actor.apply(policy_params.actor, obs)
        if key is None:
            return mu
        return jnp.clip(mu + config.exploration_noise * jax.random.normal(key, mu.shape), -1.0, 1.0)

    return policy_fn


def _algorithm(config: Config, action_size: int) -> off_policy.Algorithm:
    """The deterministic actor-critic's part of the off-policy skeleton."""
    actor, critic = make_networks(config, action_size)
    policy_fn = make_policy_fn(config, action_size)
    actor_tx = off_policy.make_optimizer(config.actor_lr, config.max_grad_norm)
    critic_tx = off_policy.make_optimizer(config.critic_lr, config.max_grad_norm)
    num_critics, delay = (2 if config.twin_critics else 1), config.policy_delay

    def init(key_actor, key_critic, dummy_obs, dummy_action) -> Learning:
        actor_params, critic_params = off_policy.init_networks(
            actor, critic, num_critics, key_actor, key_critic, dummy_obs, dummy_action
        )
        optimizers = actor_tx.init(actor_params), critic_tx.init(critic_params)
        # The targets start as copies of the networks; no critic update has happened yet (phase 0).
        return Learning(actor_params, critic_params, actor_params, critic_params, *optimizers, jnp.zeros((), jnp.int32))

    def update(carry: Learning, keys, batch) -> tuple[Learning, dict]:
        (key_noise,) = keys
        obs, next_obs = batch["obs"], batch["next_obs"]
        target_mu = actor.apply(carry.target_actor, next_obs)
        smoothing = config.target_noise * jax.random.normal(key_noise, target_mu.shape)
        next_action = losses.smoothed_target_action(target_mu, smoothing, config.target_noise_clip)
        next_q = twin_q(critic, carry.target_critic, next_obs, next_action)
        target = jax.lax.stop_gradient(losses.critic_target(batch["reward"], batch["terminated"], next_q, config.gamma))

        critic_params, critic_opt, critic_loss, q = off_policy.critic_step(
            critic, critic_tx, carry.critic, carry.critic_opt, obs, batch["action"], target
        )
        phase = (carry.phase + 1) % delay

        def improve(_):
            """The actor's step against the updated critics, then both targets."""

            def actor_objective(a_params):
                return losses.actor_loss(twin_q(critic, critic_params, obs, actor.apply(a_params, obs)))

            actor_loss, actor_grads = jax.value_and_grad(actor_objective)(carry.actor)
            updates, actor_opt = actor_tx.update(actor_grads, carry.actor_opt, carry.actor)
            actor_params = optax.apply_updates(carry.actor, updates)
            target_actor = losses.polyak_update(carry.target_actor, actor_params, config.tau)
            target_critic = losses.polyak_update(carry.target_critic, critic_params, config.tau)
            return actor_params, actor_opt, target_actor, target_critic, actor_loss, jnp.ones(())

        def hold(_):
            return carry.actor, carry.actor_opt, carry.target_actor, carry.target_critic, jnp.zeros(()), jnp.zeros(())

        # Without a delay every step improves the actor: no branch to trace.
        outcome = improve(None) if delay == 1 else jax.lax.cond(phase == 0, improve, hold, None)
        actor_params, actor_opt, target_actor, target_critic, actor_loss, updated = outcome
        new = Learning(actor_params, critic_params, target_actor, target_critic, actor_opt, critic_opt, phase)
        metrics = {"critic_loss": critic_loss, "actor_loss": actor_loss, "q_mean": jnp.mean(q)}
        return new, {**metrics, "actor_updates": updated}

    return off_policy.Algorithm(
        init=init,
        explore=lambda policy, obs, key: policy_fn(policy, obs, key),
        update=update,
        idle=lambda carry: {name: jnp.zeros((), jnp.float32) for name in LOSS_METRICS},
        policy=policy_fn,
        metric_names=LOSS_METRICS,
        num_update_keys=1,
        summarize=_summarize,
    )


def learner_functions(name: str, config_cls) -> tuple[Callable, Callable]:
    """``make_learner`` and ``make_train`` of the learner ``name`` whose options are ``config_cls`` (``Config`` or
    ``scg_algorithms.ddpg.td3.Config``), each ``f(config, env)``:

    - ``make_learner(config, env) -> Learner`` for ``run_training``; ``config`` a ``config_cls``, a mapping (the
      ``training.<name>`` section) or ``None`` for the defaults. Raises ValueError naming a bad option
      (``training.<name>.<field>``).
    - ``make_train(config, env)``: the whole run as one pure function ``train(key, params) -> (runner_state,
      metrics)`` (``scg_algorithms.rl.learner.make_train``; jit it, vmap it over keys for seeds); ``metrics`` a dict
      of (num_iterations,) arrays: ``env_steps``, ``grad_steps`` (``Count``s), the episode means and
      ``LOSS_METRICS`` (0 during warm-up).
    """

    def learner(config, env) -> tuple[Learner, Callable]:
        config = parse_options(config_cls, config, f"training.{name}")
        return off_policy.make_learner(name, config, env, _algorithm(config, env.action_size))

    def make_learner(config, env) -> Learner:
        return learner(config, env)[0]

    def make_train(config, env) -> Callable:
        return learner_lib.make_train(*learner(config, env))

    return make_learner, make_train
