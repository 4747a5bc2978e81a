"""Proximal policy optimisation (clipped objective) in JAX, on ``scg_algorithms.rl.envs.TrainEnv`` copies.

One iteration:

1. roll out ``rollout_length`` steps on ``num_envs`` copies with the current stochastic policy (the learners' shared
   ``scg_algorithms.rl.collector``); observations are
   normalised with the running statistics *as they were at the start of the iteration* and stored normalised, so
   the stored log-probabilities are exactly those the optimisation later recomputes (the statistics are updated
   with the raw observations after the rollout);
2. ``gae`` with the value of each step's ``final_obs`` (bootstrap at a time limit, none at a termination);
3. ``num_epochs`` passes of ``num_minibatches`` shuffled minibatches of the clipped PPO loss with Adam (global
   gradient-norm clip, optional linear step-size decay).

Steps 2 and 3 are PPO's one update (``scg_algorithms.ppo.agent``), which the safe variants (a ``Variant`` of this
iteration: ``scg_algorithms.safe_ppo``, ``scg_algorithms.ppo_lagrangian``) and both sides of the adversarial game
(``scg_algorithms.robust``) run as well.

Networks: separate actor and critic ``MLP``s; the policy is ``N(mu(obs), diag(exp(log_std))^2)`` with a
state-independent ``log_std`` vector, its samples clipped to [-1, 1] by the env wrapper (see ``losses``); the
deterministic policy is ``clip(mu, -1, 1)``.

Everything is a pure function of the key and the ``EnvParams``: ``make_train(config, env)(key, params)`` (the
learners' one ``scg_algorithms.rl.learner.make_train``) is the whole run and can be ``jax.jit``-ed and
``jax.vmap``-ed over keys (seeds); ``make_learner`` exposes the same iteration to the host driver
``scg_algorithms.rl.training.run_training``. Domain randomisation and disturbances are
the env's (drawn at every reset from ``params``), so training on a randomised pole length is a config change.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from scg_algorithms.base import parse_options
from scg_algorithms.ppo import agent as agent_lib
from scg_algorithms.ppo import losses
from scg_algorithms.ppo.agent import Agent, Networks
from scg_algorithms.ppo.config import Config
from scg_algorithms.rl import learner as learner_lib
from scg_algorithms.rl.collector import ActOutput, CollectorState, collect, init_collector
from scg_algorithms.rl.counter import Count, add_count, zero_count
from scg_algorithms.rl.envs import TrainEnv, make_train_env
from scg_algorithms.rl.normalization import RunningStats
from scg_algorithms.rl.training import Learner, raw_key

NAME = "ppo"


class Transition(NamedTuple):
    """What an iteration learns from, (T, N, ...) (built from the collector's ``Transitions``).

    Attributes:
        obs: normalised observation acted on. action: unclipped Gaussian sample (N, d). log_prob: its log-density.
        value: V(obs). next_value: V(final_obs), the value of the observation the step reached (before any reset).
        reward: scaled reward. terminated, truncated: bools. cost: (T, N) constrained-MDP cost (1 at a step in
        violation). next_obs: normalised ``final_obs``. context: the ``Variant.context`` of the step (``()`` for
        plain PPO).
    """

    obs: Any
    action: Any
    log_prob: Any
    value: Any
    next_value: Any
    reward: Any
    terminated: Any
    truncated: Any
    cost: Any = None
    next_obs: Any = None
    context: Any = ()


class Variant(NamedTuple):
    """What a PPO variant changes in the one PPO iteration (``_update``); every field ``None`` is plain PPO.

    Attributes:
        init_aux: ``init_aux(key, params) -> aux``: the variant's own state (a pretrained safety layer, a Lagrange
            multiplier and cost critic), carried in ``RunnerState.aux``. ``key`` is derived from the run's key
            without consuming it, so PPO's own random numbers are unchanged.
        context: ``context(layer, raw_obs (..., obs_size)) -> pytree (..., ...)``: what ``project`` needs per
            observation, computed when acting and stored with the step; ``layer = policy_aux(aux)``.
        project: ``project(context, mean (..., d)) -> mean (..., d)``: an action projection of the policy mean
            (part of the policy: the log-probabilities are those of the projected mean).
        prepare: ``prepare(aux, traj, episode, data, flat) -> (aux, data, metrics)``: after GAE, before the
            SGD epochs (e.g. the multiplier update and the cost advantages); ``data`` the flat batch dict.
        advantages: ``advantages(aux, minibatch) -> (B,)``: the advantages the actor's loss uses (default:
            ``data["advantages"]``, normalised per minibatch when ``normalize_advantages``).
        aux_step: ``aux_step(aux, minibatch) -> (aux, info)``: a gradient step of the variant's own networks on
            each minibatch (its own optimiser, so PPO's gradient clipping is unchanged).
        policy_aux: ``policy_aux(aux) -> pytree`` saved with the policy as ``policy_params["layer"]``.
    """

    init_aux: Callable | None = None
    context: Callable | None = None
    project: Callable | None = None
    prepare: Callable | None = None
    advantages: Callable | None = None
    aux_step: Callable | None = None
    policy_aux: Callable | None = None


class RunnerState(NamedTuple):
    """Everything a PPO run carries between iterations (one pytree, checkpointed whole).

    Attributes:
        params: ``{"actor": flax params, "critic": flax params, "log_std": (d,)}``. opt_state: optax state.
        collector: ``scg_algorithms.rl.collector.CollectorState`` (batched env state, observations to act on next,
        episode sums, the last episode means, the observation normaliser). key: raw PRNG key.
        env_steps: ``Count`` (exact past 2^31) of env steps so far. aux: a ``Variant``'s own state (``()``, no
        leaves, for plain PPO).
    """

    params: Any
    opt_state: Any
    collector: CollectorState
    key: Any
    env_steps: Count
    aux: Any = ()

    @property
    def obs_stats(self) -> RunningStats:
        """The observation normaliser (``collector.obs_stats``)."""
        return self.collector.obs_stats


PLAIN = Variant()
"""Plain PPO: no variant."""


class _Parts(NamedTuple):
    """The static pieces of a PPO run (decided at ``make_learner``)."""

    config: Config
    variant: Variant
    train_env: TrainEnv
    networks: Networks
    optimizer: Any


def _parts(config: Config, env, variant: Variant) -> _Parts:
    train_env = make_train_env(env, config.num_envs, config.action_scale)
    networks = agent_lib.make_networks(
        config.actor_hidden, config.critic_hidden, config.activation, train_env.action_size
    )
    optimizer = agent_lib.make_optimizer(config, config.learning_rate, config.num_iterations)
    return _Parts(config, variant, train_env, networks, optimizer)


def _layer(parts: _Parts, aux):
    """The variant's part of the saved policy (``policy_params["layer"]``), None for plain PPO."""
    return None if parts.variant.policy_aux is None else parts.variant.policy_aux(aux)


def _context(parts: _Parts, layer, raw_obs):
    return () if parts.variant.context is None else parts.variant.context(layer, raw_obs)


def _policy_mean(parts: _Parts, params, obs, context):
    """The policy mean at normalised ``obs``: the actor's, projected by the variant when it projects."""
    mean = parts.networks.mean(params, obs)
    return mean if parts.variant.project is None else parts.variant.project(context, mean)


def _init(parts: _Parts, key, params) -> RunnerState:
    key = raw_key(key)
    key, key_actor, key_critic, key_env = jax.random.split(key, 4)
    net_params = agent_lib.init_params(
        parts.networks, key_actor, key_critic, parts.train_env.obs_size, parts.config.init_log_std
    )
    # The variant's key is folded from the env key: PPO's own splits (and so its numbers) stay as they were.
    variant = parts.variant
    aux = () if variant.init_aux is None else variant.init_aux(jax.random.fold_in(key_env, 1), params)
    return RunnerState(
        params=net_params,
        opt_state=parts.optimizer.init(net_params),
        collector=init_collector(parts.train_env, key_env, params),
        key=key,
        env_steps=zero_count(),
        aux=aux,
    )


def _rollout(parts: _Parts, runner: RunnerState, params, key):
    """The collector under the current stochastic policy; observations normalised with the statistics as they
    were at the start of the iteration (the collector merges the new ones after the scan)."""
    config, networks = parts.config, parts.networks
    net, stats = runner.params, runner.collector.obs_stats
    layer = _layer(parts, runner.aux)

    def act(raw_obs, step_key) -> ActOutput:
        obs = agent_lib.observe(config, stats, raw_obs)
        context = _context(parts, layer, raw_obs)
        mean = _policy_mean(parts, net, obs, context)
        action = agent_lib.sample_action(step_key, mean, net["log_std"])
        extras = {
            "log_prob": losses.gaussian_log_prob(mean, net["log_std"], action),
            "value": networks.value(net, obs),
            "context": context,
        }
        return ActOutput(action, extras)

    collected = collect(
        parts.train_env, params, runner.collector, act, key, config.rollout_length,
        update_normalizer=config.normalize_observations,
    )  # fmt: skip
    steps = collected.transitions
    next_obs = agent_lib.observe(config, stats, steps.next_obs)
    traj = Transition(
        obs=agent_lib.observe(config, stats, steps.obs),
        action=steps.action,
        log_prob=steps.extras["log_prob"],
        value=steps.extras["value"],
        next_value=networks.value(net, next_obs),
        reward=steps.reward * config.reward_scale,
        terminated=steps.terminated,
        truncated=steps.truncated,
        cost=steps.cost,
        next_obs=next_obs,
        context=steps.extras["context"],
    )
    return collected.state, traj, collected.episode


def _loss(parts: _Parts, net_params, aux, mb):
    """PPO's loss of a minibatch, with the variant's projection of the mean and its advantages."""
    mean = _policy_mean(parts, net_params, mb["obs"], mb["context"])
    values = parts.networks.value(net_params, mb["obs"])
    advantages = None if parts.variant.advantages is None else parts.variant.advantages(aux, mb)
    return agent_lib.minibatch_loss(parts.config, mean, net_params["log_std"], values, mb, advantages)


def _update(parts: _Parts, runner: RunnerState, params) -> tuple[RunnerState, dict]:
    """One iteration: rollout, GAE, the variant's ``prepare``, then PPO's epochs (and the variant's ``aux_step``)."""
    config, variant = parts.config, parts.variant
    key, key_rollout, key_sgd = jax.random.split(runner.key, 3)
    collector, traj, episode = _rollout(parts, runner, params, key_rollout)
    data = agent_lib.gae_batch(
        config, traj.reward, traj.value, traj.next_value, traj.terminated, traj.truncated,
        obs=traj.obs, action=traj.action, log_prob=traj.log_prob, context=traj.context,
    )  # fmt: skip
    aux, variant_metrics = runner.aux, {}
    if variant.prepare is not None:
        flat = lambda x: jnp.reshape(x, (config.batch_size, *x.shape[2:]))  # noqa: E731
        aux, data, variant_metrics = variant.prepare(aux, traj, episode, data, flat)
    agent, aux, info = agent_lib.ppo_epochs(
        lambda p, a, mb: _loss(parts, p, a, mb), parts.optimizer, Agent(runner.params, runner.opt_state), data,
        key_sgd, config, aux, variant.aux_step,
    )  # fmt: skip
    env_steps = add_count(runner.env_steps, config.batch_size)
    residual = data["returns"] - data["value"]
    metrics = {
        "env_steps": env_steps,
        **episode,
        **info,
        "learning_rate": agent_lib.current_learning_rate(
            config, config.learning_rate, config.num_iterations, agent.opt_state
        ),
        "policy_std": jnp.mean(jnp.exp(agent.params["log_std"])),
        "explained_variance": 1.0 - jnp.var(residual) / jnp.maximum(jnp.var(data["returns"]), 1e-8),
        "mean_reward": jnp.mean(traj.reward) / config.reward_scale,
        "violation_fraction": jnp.mean(traj.cost),
        **variant_metrics,
    }
    new_runner = RunnerState(
        params=agent.params, opt_state=agent.opt_state, collector=collector, key=key, env_steps=env_steps, aux=aux
    )
    return new_runner, metrics


def _policy_params(parts: _Parts, runner: RunnerState) -> dict:
    saved = agent_lib.saved_policy(runner.params, runner.collector.obs_stats)
    if parts.variant.policy_aux is not None:
        saved["layer"] = parts.variant.policy_aux(runner.aux)
    return saved


def _make_policy(parts: _Parts, policy_params: Mapping) -> Callable:
    """``policy(obs, key=None) -> a`` in [-1, 1]: ``clip(mu)`` without a key, a clipped sample with one."""

    def policy_mean(saved, obs, raw_obs):
        return _policy_mean(parts, saved, obs, _context(parts, saved.get("layer"), raw_obs))

    return agent_lib.make_policy(parts.config, policy_mean, policy_params)


def make_variant_learner(name: str, config: Config, env, variant: Variant = PLAIN) -> Learner:
    """PPO changed as ``variant`` says (``config`` a checked ``Config``, or a subclass's) as a ``Learner`` named
    ``name``."""
    parts = _parts(config, env, variant)
    return Learner(
        name=name,
        config=config,
        init=lambda key, params: _init(parts, key, params),
        update=lambda runner, params: _update(parts, runner, params),
        num_iterations=config.num_iterations,
        steps_per_iteration=config.batch_size,
        policy_params=lambda runner: _policy_params(parts, runner),
        make_policy=lambda policy_params: _make_policy(parts, policy_params),
        collect=lambda runner, params: _rollout(parts, runner, params, jax.random.split(runner.key, 3)[1])[:2],
    )


def make_learner(config, env) -> Learner:
    """PPO as a ``Learner`` for ``run_training``.

    Args:
        config: a ``Config`` or a mapping (the ``training.ppo`` section; ``None`` for defaults). env: an
            ``scg_jax.Env`` (any action mode; the policy acts in [-1, 1]).
    """
    return make_variant_learner(NAME, parse_options(Config, config, f"training.{NAME}"), env)


def make_train(config, env):
    """The whole PPO run as one pure function ``train(key, params) -> (runner_state, metrics)``
    (``scg_algorithms.rl.learner.make_train`` of ``make_learner``): jit it, ``jax.vmap`` it over keys for seeds."""
    return learner_lib.make_train(make_learner(config, env))
