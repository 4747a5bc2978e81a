"""Soft actor-critic in JAX: the whole training loop is one pure function of a key and the env params.

One *iteration* collects ``rollout_steps`` control steps in each of the ``num_envs`` auto-resetting copies
(``scg_algorithms.rl.envs.TrainEnv``, actions in [-1, 1], through the learners' shared ``scg_algorithms.rl.collector``,
which also merges the observations into the running normaliser), writes the transitions to the replay buffer, then
takes ``utd * num_envs * rollout_steps`` gradient steps. Each
gradient step samples a batch uniformly from the buffer and updates, in this order, the twin critics (soft Bellman
target from the Polyak-averaged target critics, no bootstrapping where the episode *terminated*; a time-limit
truncation bootstraps from the stored final observation), the actor (reparameterised tanh-Gaussian, against the
freshly updated critics), the temperature (towards the entropy target ``target_entropy_per_action * nu``), and the
target critics (``tau``). The first ``warmup_iterations`` act uniformly at random and do not learn.

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

from scg_algorithms.rl import envs as rl_envs
from scg_algorithms.rl import learner as learner_lib
from scg_algorithms.rl.collector import ActOutput, CollectorState, collect, init_collector
from scg_algorithms.rl.counter import Count, add_count, count_at_least, zero_count
from scg_algorithms.rl.networks import QNetwork, TanhGaussianActor, twin_q
from scg_algorithms.rl.normalization import RunningStats, init_stats, normalize
from scg_algorithms.rl.training import Learner, raw_key
from scg_algorithms.sac import losses, replay
from scg_algorithms.sac.config import Config, parse_config

NAME = "sac"

# The shared networks (``scg_algorithms.rl.networks``) under SAC's names.
Actor = TanhGaussianActor
Critic = QNetwork


def make_networks(config: Config, action_size: int) -> tuple[TanhGaussianActor, QNetwork]:
    """The actor and critic modules of ``config``."""
    actor = TanhGaussianActor(
        config.hidden_sizes, action_size, config.activation, config.log_std_min, config.log_std_max
    )
    return actor, QNetwork(config.hidden_sizes, config.activation)


# --------------------------------------------------------------------------------------------- policy
class PolicyParams(NamedTuple):
    """What a SAC policy needs to act: the actor's flax params and the observation normaliser."""

    actor: Any
    obs_stats: RunningStats


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


# --------------------------------------------------------------------------------------------- state
class Learning(NamedTuple):
    """What a gradient step changes (the carry of the gradient-step scan).

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


_RunnerFields = NamedTuple(
    "RunnerState",
    [
        *Learning.__annotations__.items(),
        ("buffer", replay.ReplayBuffer),
        ("collector", CollectorState),
        ("key", Any),
        ("iteration", Count),
        ("env_steps", Count),
        ("grad_steps", Count),
    ],
)


class RunnerState(_RunnerFields):
    """Everything the training loop carries (a pytree; checkpointable): ``Learning``'s fields, then the rest.

    Attributes:
        actor, critic, target_critic, log_alpha, actor_opt, critic_opt, alpha_opt: as in ``Learning``.
        buffer: ``replay.ReplayBuffer`` of dicts ``obs, action, reward, next_obs, terminated, cost``.
        collector: ``scg_algorithms.rl.collector.CollectorState`` (batched env state, observations to act on next,
            episode sums, the last episode means, the normaliser of the observations collected so far).
        key: raw PRNG key. iteration, env_steps, grad_steps: ``Count``s (exact past 2^31).
    """

    __slots__ = ()

    @property
    def obs_stats(self) -> RunningStats:
        """The observation normaliser (``collector.obs_stats``)."""
        return self.collector.obs_stats

    @property
    def learning(self) -> Learning:
        """The fields a gradient step changes."""
        return Learning(*(getattr(self, name) for name in Learning._fields))


LOSS_METRICS = ("critic_loss", "actor_loss", "alpha_loss", "alpha", "entropy", "q_mean")


def _optimizer(learning_rate: float, max_grad_norm: float):
    adam = optax.adam(learning_rate)
    return optax.chain(optax.clip_by_global_norm(max_grad_norm), adam) if max_grad_norm > 0 else adam


class _Parts(NamedTuple):
    """The static pieces of a SAC run (decided at ``make_learner``)."""

    config: Config
    train_env: rl_envs.TrainEnv
    actor: TanhGaussianActor
    critic: QNetwork
    policy_fn: Callable
    actor_tx: Any
    critic_tx: Any
    alpha_tx: Any
    target_entropy: float

    def norm(self, stats, obs):
        """``obs`` as the networks see it (normalised with ``stats`` when ``normalize_observations``)."""
        return normalize(stats, obs) if self.config.normalize_observations else obs


def _parts(config: Config, env) -> _Parts:
    train_env = rl_envs.make_train_env(env, config.num_envs, config.action_scale)
    actor, critic = make_networks(config, train_env.action_size)
    return _Parts(
        config=config,
        train_env=train_env,
        actor=actor,
        critic=critic,
        policy_fn=make_policy_fn(config, train_env.action_size),
        actor_tx=_optimizer(config.actor_lr, config.max_grad_norm),
        critic_tx=_optimizer(config.critic_lr, config.max_grad_norm),
        alpha_tx=optax.adam(config.alpha_lr),
        target_entropy=config.target_entropy_per_action * train_env.action_size,
    )


def _init(parts: _Parts, key, params) -> RunnerState:
    config, obs_size, action_size = parts.config, parts.train_env.obs_size, parts.train_env.action_size
    key_env, key_actor, key_critic, key = jax.random.split(key, 4)
    dummy_obs, dummy_action = jnp.zeros((obs_size,)), jnp.zeros((action_size,))
    actor_params = parts.actor.init(key_actor, dummy_obs)
    critic_params = jax.vmap(parts.critic.init, in_axes=(0, None, None))(
        jax.random.split(key_critic, 2), dummy_obs, dummy_action
    )
    log_alpha = jnp.asarray(math.log(config.init_alpha), jnp.float32)
    example = {
        "obs": dummy_obs,
        "action": dummy_action,
        "reward": jnp.zeros(()),
        "next_obs": dummy_obs,
        "terminated": jnp.zeros(()),
        "cost": jnp.zeros(()),
    }
    return RunnerState(
        actor=actor_params,
        critic=critic_params,
        target_critic=critic_params,
        log_alpha=log_alpha,
        actor_opt=parts.actor_tx.init(actor_params),
        critic_opt=parts.critic_tx.init(critic_params),
        alpha_opt=parts.alpha_tx.init(log_alpha),
        buffer=replay.init_buffer(config.capacity, example),
        collector=init_collector(parts.train_env, key_env, params, jnp.float32),
        key=raw_key(key),  # raw data, as PPO: the state serialises the same whatever key was passed
        iteration=zero_count(),
        env_steps=zero_count(),
        grad_steps=zero_count(),
    )


def _gradient_step(parts: _Parts, carry: Learning, key, buffer, stats) -> tuple[Learning, dict]:
    """One gradient step of the critics, the actor, the temperature and the target critics, in that order."""
    config, actor, critic = parts.config, parts.actor, parts.critic
    key_sample, key_next, key_pi = jax.random.split(key, 3)
    batch = replay.sample(buffer, key_sample, config.batch_size)
    obs, next_obs = parts.norm(stats, batch["obs"]), parts.norm(stats, batch["next_obs"])
    log_alpha = carry.log_alpha
    alpha = jnp.exp(log_alpha)

    next_mean, next_log_std = actor.apply(carry.actor, next_obs)
    next_action, next_log_prob = losses.sample_tanh_gaussian(key_next, next_mean, next_log_std)
    next_q = twin_q(critic, carry.target_critic, next_obs, next_action)
    target = losses.critic_target(
        config.reward_scale * batch["reward"], batch["terminated"], next_q, next_log_prob, alpha, config.gamma
    )
    target = jax.lax.stop_gradient(target)

    def critic_objective(c_params):
        q = twin_q(critic, c_params, obs, batch["action"])
        return losses.critic_loss(q, target), q

    (critic_loss, q), critic_grads = jax.value_and_grad(critic_objective, has_aux=True)(carry.critic)
    updates, critic_opt = parts.critic_tx.update(critic_grads, carry.critic_opt, carry.critic)
    critic_params = optax.apply_updates(carry.critic, updates)

    def actor_objective(a_params):
        mean, log_std = actor.apply(a_params, obs)
        action, log_prob = losses.sample_tanh_gaussian(key_pi, mean, log_std)
        q_pi = twin_q(critic, critic_params, obs, action)
        return losses.actor_loss(q_pi, log_prob, alpha), log_prob

    (actor_loss, log_prob), actor_grads = jax.value_and_grad(actor_objective, has_aux=True)(carry.actor)
    updates, actor_opt = parts.actor_tx.update(actor_grads, carry.actor_opt, carry.actor)
    actor_params = optax.apply_updates(carry.actor, updates)

    alpha_opt = carry.alpha_opt
    alpha_loss, alpha_grad = jax.value_and_grad(losses.temperature_loss)(log_alpha, log_prob, parts.target_entropy)
    if config.autotune_alpha:
        updates, alpha_opt = parts.alpha_tx.update(alpha_grad, alpha_opt, log_alpha)
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


def _collect(parts: _Parts, state: RunnerState, params, key, learning):
    """One iteration's transitions (``collect``), acting with the policy (``learning``) or uniformly at random."""
    config, num_envs, action_size = parts.config, parts.config.num_envs, parts.train_env.action_size
    policy_params = PolicyParams(state.actor, state.collector.obs_stats)

    def act(obs, key_step) -> ActOutput:
        key_policy, key_random = jax.random.split(key_step)
        policy_action = jax.vmap(parts.policy_fn, in_axes=(None, 0, 0))(
            policy_params, obs, jax.random.split(key_policy, num_envs)
        )
        random_action = jax.random.uniform(key_random, (num_envs, action_size), minval=-1.0, maxval=1.0)
        return ActOutput(jnp.where(learning, policy_action, random_action), {})

    return collect(
        parts.train_env, params, state.collector, act, key, config.rollout_steps,
        update_normalizer=config.normalize_observations,
    )  # fmt: skip


def _iteration(parts: _Parts, state: RunnerState, params, learning):
    """One iteration; ``learning`` (bool scalar, may be traced) selects policy actions and gradient steps, or
    uniform random actions and none (warm-up). A ``learning`` that does not depend on vmapped values keeps
    the ``lax.cond`` a real branch under ``jax.vmap``, so warm-up iterations skip the gradient work."""
    config = parts.config
    key, key_collect, key_learn = jax.random.split(state.key, 3)
    collector, steps, episode, _ = _collect(parts, state, params, key_collect, learning)
    transitions = {
        "obs": steps.obs,
        "action": steps.action,
        "reward": steps.reward,
        "next_obs": steps.next_obs,
        "terminated": steps.terminated,
        "cost": steps.cost,
    }
    buffer = replay.add(state.buffer, jax.tree.map(lambda x: x.reshape(-1, *x.shape[2:]), transitions))
    obs_stats = collector.obs_stats

    def learn(carry, key):
        carry, step_metrics = jax.lax.scan(
            lambda c, k: _gradient_step(parts, c, k, buffer, obs_stats),
            carry,
            jax.random.split(key, config.grad_steps_per_iteration),
        )
        return carry, jax.tree.map(lambda m: jnp.mean(m).astype(jnp.float32), step_metrics)

    def skip(carry, key):
        metrics = {name: jnp.zeros((), jnp.float32) for name in LOSS_METRICS}
        return carry, {**metrics, "alpha": jnp.exp(carry.log_alpha).astype(jnp.float32)}

    carry, loss_metrics = jax.lax.cond(learning, learn, skip, state.learning, key_learn)
    num_grad = jnp.where(learning, config.grad_steps_per_iteration, 0).astype(jnp.uint32)
    new_state = state._replace(
        **carry._asdict(),
        buffer=buffer,
        collector=collector,
        key=key,
        iteration=add_count(state.iteration, 1),
        env_steps=add_count(state.env_steps, config.transitions_per_iteration),
        grad_steps=add_count(state.grad_steps, num_grad),
    )
    metrics = {
        "env_steps": new_state.env_steps,
        "grad_steps": new_state.grad_steps,
        **episode,
        **{name: loss_metrics[name].astype(jnp.float32) for name in LOSS_METRICS},
    }
    return new_state, metrics


# --------------------------------------------------------------------------------------------- public API
def policy_params(state: RunnerState) -> PolicyParams:
    """The part of the runner state a policy needs (saved as ``policy.msgpack`` by the host driver)."""
    return PolicyParams(actor=state.actor, obs_stats=state.collector.obs_stats)


def _learner(config: Config | Mapping | None, env) -> tuple[Learner, Callable]:
    """SAC as a ``Learner`` and its ``update_at`` for ``scg_algorithms.rl.learner.make_train``."""
    config = parse_config(config)
    parts = _parts(config, env)
    warmup = config.warmup_iterations

    def make_policy(p: PolicyParams):
        return lambda obs, key=None: parts.policy_fn(p, obs, key)

    learner = Learner(
        name=NAME,
        config=config,
        init=lambda key, params: _init(parts, key, params),
        update=lambda state, params: _iteration(parts, state, params, count_at_least(state.iteration, warmup)),
        num_iterations=config.num_iterations,
        steps_per_iteration=config.transitions_per_iteration,
        policy_params=policy_params,
        make_policy=make_policy,
    )
    # The iteration index comes from make_train's scan, not from the (possibly vmapped) state, so the warm-up test
    # stays unbatched under jax.vmap and its lax.cond keeps skipping the gradient steps.
    return learner, lambda state, params, i: _iteration(parts, state, params, i >= warmup)


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
