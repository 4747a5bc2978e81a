"""Proximal policy optimisation (clipped objective) in JAX, on ``algorithms.rl.envs.TrainEnv`` copies.

One iteration:

1. roll out ``rollout_length`` steps on ``num_envs`` copies with the current stochastic policy; observations are
   normalised with the running statistics *as they were at the start of the iteration* and stored normalised, so
   the stored log-probabilities are exactly those the optimisation later recomputes (the statistics are updated
   with the raw observations after the rollout);
2. ``gae`` with the value of each step's ``final_obs`` (bootstrap at a time limit, none at a termination);
3. ``num_epochs`` passes of ``num_minibatches`` shuffled minibatches of the clipped PPO loss with Adam (global
   gradient-norm clip, optional linear step-size decay).

Networks: separate actor and critic ``MLP``s; the policy is ``N(mu(obs), diag(exp(log_std))^2)`` with a
state-independent ``log_std`` vector, its samples clipped to [-1, 1] by the env wrapper (see ``losses``); the
deterministic policy is ``clip(mu, -1, 1)``.

Everything is a pure function of the key and the ``EnvParams``: ``make_train(config, env)(key, params)`` is the
whole run and can be ``jax.jit``-ed and ``jax.vmap``-ed over keys (seeds); ``make_learner`` exposes the same
iteration to the host driver ``algorithms.rl.training.run_training``. Domain randomisation and disturbances are
the env's (drawn at every reset from ``params``), so training on a randomised pole length is a config change.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax

from algorithms.base import parse_options
from algorithms.ppo import losses
from algorithms.ppo.config import Config
from algorithms.rl.envs import (
    episode_means,
    init_episode_stats,
    initial_episode_means,
    make_train_env,
    update_episode_stats,
)
from algorithms.rl.networks import MLP
from algorithms.rl.normalization import RunningStats, init_stats, normalize, update_stats
from algorithms.rl.training import Learner, raw_key

NAME = "ppo"


class Transition(NamedTuple):
    """What the rollout stores per step, (T, N, ...) after the scan.

    Attributes:
        obs: normalised observation acted on. action: unclipped Gaussian sample (N, d). log_prob: its log-density.
        value: V(obs). next_value: V(final_obs), the value of the observation the step reached (before any reset).
        reward: scaled reward. terminated, truncated: bools.
    """

    obs: Any
    action: Any
    log_prob: Any
    value: Any
    next_value: Any
    reward: Any
    terminated: Any
    truncated: Any


class RunnerState(NamedTuple):
    """Everything a PPO run carries between iterations (one pytree, checkpointed whole).

    Attributes:
        params: ``{"actor": flax params, "critic": flax params, "log_std": (d,)}``. opt_state: optax state.
        obs_stats: ``RunningStats`` of raw observations. env_state: batched ``EnvState``. obs: (N, obs) raw
        observations to act on next. episode_stats: per-copy running sums. last_episode: the latest
        ``episode_means`` (repeated when no episode finishes). key: raw PRNG key. env_steps: int32 total so far.
    """

    params: Any
    opt_state: Any
    obs_stats: RunningStats
    env_state: Any
    obs: Any
    episode_stats: Any
    last_episode: dict
    key: Any
    env_steps: Any


def _parse(config) -> Config:
    config = parse_options(Config, config, "training.ppo")
    config._check("training.ppo")  # also for a Config built directly (layer sizes as ints, cross-field checks)
    return config


def _networks(config: Config, action_size: int):
    actor = MLP((*config.actor_hidden, action_size), config.activation, final_scale=0.01)
    critic = MLP((*config.critic_hidden, 1), config.activation, final_scale=1.0)
    return actor, critic


def _optimizer(config: Config):
    updates_per_iteration = config.num_epochs * config.num_minibatches
    if config.lr_decay:
        learning_rate = optax.linear_schedule(
            config.learning_rate, 0.0, transition_steps=config.num_iterations * updates_per_iteration
        )
    else:
        learning_rate = config.learning_rate
    return optax.chain(optax.clip_by_global_norm(config.max_grad_norm), optax.adam(learning_rate, eps=1e-5))


def _learning_rate(config: Config, opt_state):
    """The step size Adam used last (the schedule at its count), for the metrics."""
    if not config.lr_decay:
        return jnp.asarray(config.learning_rate, jnp.float32)
    count = opt_state[1][0].count
    total = config.num_iterations * config.num_epochs * config.num_minibatches
    return config.learning_rate * (1.0 - jnp.minimum(count, total) / total)


def _functions(config: Config, env):
    """init, update, policy_params and make_policy of a PPO run on ``env``."""
    train_env = make_train_env(env, config.num_envs, config.action_scale)
    actor, critic = _networks(config, train_env.action_size)
    optimizer = _optimizer(config)
    n, batch = config.num_envs, config.batch_size
    minibatch = batch // config.num_minibatches
    value_clip = config.value_clip_eps if config.value_clip_eps > 0 else None

    def observe(stats, obs):
        return normalize(stats, obs, config.obs_clip) if config.normalize_observations else obs

    def value_fn(critic_params, obs):
        return critic.apply(critic_params, obs)[..., 0]

    def init(key, params) -> RunnerState:
        key = raw_key(key)
        key, key_actor, key_critic, key_env = jax.random.split(key, 4)
        dummy = jnp.zeros((1, train_env.obs_size))
        net_params = {
            "actor": actor.init(key_actor, dummy),
            "critic": critic.init(key_critic, dummy),
            "log_std": jnp.full((train_env.action_size,), config.init_log_std, jnp.float32),
        }
        obs, env_state = train_env.reset(key_env, params)
        return RunnerState(
            params=net_params,
            opt_state=optimizer.init(net_params),
            obs_stats=init_stats(train_env.obs_size, obs.dtype),
            env_state=env_state,
            obs=obs,
            episode_stats=init_episode_stats(n, jnp.float32),
            last_episode=initial_episode_means(jnp.float32),
            key=key,
            env_steps=jnp.zeros((), jnp.int32),
        )

    def rollout(runner: RunnerState, params, key):
        net = runner.params
        std = jnp.exp(net["log_std"])

        def step(carry, step_key):
            env_state, raw_obs, episode_stats = carry
            obs = observe(runner.obs_stats, raw_obs)
            mean = actor.apply(net["actor"], obs)
            action = mean + std * jax.random.normal(step_key, mean.shape, mean.dtype)
            out = train_env.step(env_state, action, params)
            next_value = value_fn(net["critic"], observe(runner.obs_stats, out.final_obs))
            episode_stats, finished = update_episode_stats(episode_stats, out)
            transition = Transition(
                obs=obs,
                action=action,
                log_prob=losses.gaussian_log_prob(mean, net["log_std"], action),
                value=value_fn(net["critic"], obs),
                next_value=next_value,
                reward=out.reward * config.reward_scale,
                terminated=out.terminated,
                truncated=out.truncated,
            )
            return (out.state, out.obs, episode_stats), (transition, finished, raw_obs)

        keys = jax.random.split(key, config.rollout_length)
        carry = (runner.env_state, runner.obs, runner.episode_stats)
        (env_state, obs, episode_stats), (traj, finished, raw_obs) = jax.lax.scan(step, carry, keys)
        return env_state, obs, episode_stats, traj, finished, raw_obs

    def loss_fn(net_params, mb):
        mean = actor.apply(net_params["actor"], mb["obs"])
        values = value_fn(net_params["critic"], mb["obs"])
        advantages = mb["advantages"]
        if config.normalize_advantages:
            advantages = losses.normalize_advantages(advantages)
        return losses.ppo_loss(
            mean,
            net_params["log_std"],
            values,
            mb["action"],
            mb["log_prob"],
            mb["value"],
            advantages,
            mb["returns"],
            clip_eps=config.clip_eps,
            value_clip_eps=value_clip,
            vf_coef=config.vf_coef,
            ent_coef=config.ent_coef,
        )

    grad_fn = jax.value_and_grad(loss_fn, has_aux=True)

    def sgd_step(carry, mb):
        net_params, opt_state = carry
        (loss, info), grads = grad_fn(net_params, mb)
        updates, opt_state = optimizer.update(grads, opt_state, net_params)
        net_params = optax.apply_updates(net_params, updates)
        return (net_params, opt_state), {**info, "loss": loss, "grad_norm": optax.tree.norm(grads)}

    def epoch(carry, key, data):
        permutation = jax.random.permutation(key, batch)
        shuffled = jax.tree.map(
            lambda x: jnp.reshape(x[permutation], (config.num_minibatches, minibatch, *x.shape[1:])), data
        )
        return jax.lax.scan(sgd_step, carry, shuffled)

    def update(runner: RunnerState, params) -> tuple[RunnerState, dict]:
        key, key_rollout, key_sgd = jax.random.split(runner.key, 3)
        env_state, obs, episode_stats, traj, finished, raw_obs = rollout(runner, params, key_rollout)
        advantages, returns = losses.gae(
            traj.reward,
            traj.value,
            traj.next_value,
            traj.terminated,
            traj.truncated,
            config.gamma,
            config.gae_lambda,
        )
        flat = lambda x: jnp.reshape(x, (batch, *x.shape[2:]))  # noqa: E731
        data = {
            "obs": flat(traj.obs),
            "action": flat(traj.action),
            "log_prob": flat(traj.log_prob),
            "value": flat(traj.value),
            "advantages": flat(advantages),
            "returns": flat(returns),
        }
        (net_params, opt_state), infos = jax.lax.scan(
            lambda carry, k: epoch(carry, k, data),
            (runner.params, runner.opt_state),
            jax.random.split(key_sgd, config.num_epochs),
        )
        obs_stats = update_stats(runner.obs_stats, raw_obs) if config.normalize_observations else runner.obs_stats
        episode = episode_means(finished, runner.last_episode)
        env_steps = runner.env_steps + batch
        residual = data["returns"] - data["value"]
        metrics = {
            "env_steps": env_steps,
            **{name: value for name, value in episode.items()},
            **{name: jnp.mean(value) for name, value in infos.items()},
            "learning_rate": _learning_rate(config, opt_state),
            "policy_std": jnp.mean(jnp.exp(net_params["log_std"])),
            "explained_variance": 1.0 - jnp.var(residual) / jnp.maximum(jnp.var(data["returns"]), 1e-8),
            "mean_reward": jnp.mean(traj.reward) / config.reward_scale,
        }
        new_runner = RunnerState(
            params=net_params,
            opt_state=opt_state,
            obs_stats=obs_stats,
            env_state=env_state,
            obs=obs,
            episode_stats=episode_stats,
            last_episode={name: episode[name] for name in runner.last_episode},
            key=key,
            env_steps=env_steps,
        )
        return new_runner, metrics

    def policy_params(runner: RunnerState) -> dict:
        return {"actor": runner.params["actor"], "log_std": runner.params["log_std"], "obs_stats": runner.obs_stats}

    def make_policy(policy_params: Mapping):
        """``policy(obs, key=None) -> a`` in [-1, 1]: ``clip(mu)`` without a key, a clipped sample with one."""

        def policy(obs, key=None):
            mean = actor.apply(policy_params["actor"], observe(policy_params["obs_stats"], obs))
            if key is None:
                return jnp.clip(mean, -1.0, 1.0)
            noise = jax.random.normal(raw_key(key), mean.shape, mean.dtype)
            return jnp.clip(mean + jnp.exp(policy_params["log_std"]) * noise, -1.0, 1.0)

        return policy

    return init, update, policy_params, make_policy


def make_learner(config, env) -> Learner:
    """PPO as a ``Learner`` for ``run_training``.

    Args:
        config: a ``Config`` or a mapping (the ``training.ppo`` section; ``None`` for defaults). env: an
            ``scg_jax.Env`` (any action mode; the policy acts in [-1, 1]).
    """
    config = _parse(config)
    init, update, policy_params, make_policy = _functions(config, env)
    return Learner(
        name=NAME,
        config=config,
        init=init,
        update=update,
        num_iterations=config.num_iterations,
        policy_params=policy_params,
        make_policy=make_policy,
    )


def make_train(config, env):
    """The whole PPO run as one pure function.

    Returns:
        ``train(key, params) -> (runner_state, metrics)``: ``config.num_iterations`` iterations from
        ``init(key, params)``; ``metrics`` is a dict of (num_iterations,) arrays (see ``update``). Jit it once and
        ``jax.vmap`` it over keys for several seeds (``params`` unbatched, or batched with ``in_axes`` for
        sweeps).
    """
    learner = make_learner(config, env)

    def train(key, params):
        runner = learner.init(key, params)
        return jax.lax.scan(lambda state, _: learner.update(state, params), runner, None, learner.num_iterations)

    return train
