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

Networks: separate actor and critic ``MLP``s; the policy is ``N(mu(obs), diag(exp(log_std))^2)`` with a
state-independent ``log_std`` vector, its samples clipped to [-1, 1] by the env wrapper (see ``losses``); the
deterministic policy is ``clip(mu, -1, 1)``.

Everything is a pure function of the key and the ``EnvParams``: ``make_train(config, env)(key, params)`` is the
whole run and can be ``jax.jit``-ed and ``jax.vmap``-ed over keys (seeds); ``make_learner`` exposes the same
iteration to the host driver ``scg_algorithms.rl.training.run_training``. Domain randomisation and disturbances are
the env's (drawn at every reset from ``params``), so training on a randomised pole length is a config change.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax

from scg_algorithms.ppo import losses
from scg_algorithms.ppo.config import Config
from scg_algorithms.rl.collector import ActOutput, CollectorState, collect, init_collector
from scg_algorithms.rl.config import parse_learner_config
from scg_algorithms.rl.counter import Count, add_count, zero_count
from scg_algorithms.rl.envs import make_train_env
from scg_algorithms.rl.networks import MLP, value_network
from scg_algorithms.rl.normalization import RunningStats, normalize
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
    """What a PPO variant changes in the one PPO skeleton (``_functions``); every field ``None`` is plain PPO.

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


def _parse(config) -> Config:
    return parse_learner_config(Config, config, "training.ppo")


def _networks(config: Config, action_size: int):
    actor = MLP((*config.actor_hidden, action_size), config.activation, final_scale=0.01)
    return actor, value_network(config.critic_hidden, config.activation)


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


PLAIN = Variant()
"""Plain PPO: no variant."""


def _functions(config: Config, env, variant: Variant = PLAIN):
    """init, update, policy_params and make_policy of a PPO run on ``env``, changed as ``variant`` says."""
    train_env = make_train_env(env, config.num_envs, config.action_scale)
    actor, critic = _networks(config, train_env.action_size)
    optimizer = _optimizer(config)
    batch = config.batch_size
    minibatch = batch // config.num_minibatches
    value_clip = config.value_clip_eps if config.value_clip_eps > 0 else None

    def observe(stats, obs):
        return normalize(stats, obs, config.obs_clip) if config.normalize_observations else obs

    def value_fn(critic_params, obs):
        return critic.apply(critic_params, obs)[..., 0]

    def policy_mean(actor_params, obs, context):
        mean = actor.apply(actor_params, obs)
        return mean if variant.project is None else variant.project(context, mean)

    def layer_of(aux):
        return None if variant.policy_aux is None else variant.policy_aux(aux)

    def context_of(layer, raw_obs):
        return () if variant.context is None else variant.context(layer, raw_obs)

    def init(key, params) -> RunnerState:
        key = raw_key(key)
        key, key_actor, key_critic, key_env = jax.random.split(key, 4)
        dummy = jnp.zeros((1, train_env.obs_size))
        net_params = {
            "actor": actor.init(key_actor, dummy),
            "critic": critic.init(key_critic, dummy),
            "log_std": jnp.full((train_env.action_size,), config.init_log_std, jnp.float32),
        }
        # The variant's key is folded from the env key: PPO's own splits (and so its numbers) stay as they were.
        aux = () if variant.init_aux is None else variant.init_aux(jax.random.fold_in(key_env, 1), params)
        return RunnerState(
            params=net_params,
            opt_state=optimizer.init(net_params),
            collector=init_collector(train_env, key_env, params),
            key=key,
            env_steps=zero_count(),
            aux=aux,
        )

    def rollout(runner: RunnerState, params, key):
        """The collector under the current stochastic policy; observations normalised with the statistics as
        they were at the start of the iteration (the collector merges the new ones after the scan)."""
        net = runner.params
        stats = runner.collector.obs_stats
        std = jnp.exp(net["log_std"])
        layer = layer_of(runner.aux)

        def act(raw_obs, step_key) -> ActOutput:
            obs = observe(stats, raw_obs)
            context = context_of(layer, raw_obs)
            mean = policy_mean(net["actor"], obs, context)
            action = mean + std * jax.random.normal(step_key, mean.shape, mean.dtype)
            extras = {
                "log_prob": losses.gaussian_log_prob(mean, net["log_std"], action),
                "value": value_fn(net["critic"], obs),
                "context": context,
            }
            return ActOutput(action, extras)

        collector, steps, episode = collect(
            train_env,
            params,
            runner.collector,
            act,
            key,
            config.rollout_length,
            update_normalizer=config.normalize_observations,
        )
        next_obs = observe(stats, steps.next_obs)
        traj = Transition(
            obs=observe(stats, steps.obs),
            action=steps.action,
            log_prob=steps.extras["log_prob"],
            value=steps.extras["value"],
            next_value=value_fn(net["critic"], next_obs),
            reward=steps.reward * config.reward_scale,
            terminated=steps.terminated,
            truncated=steps.truncated,
            cost=steps.cost,
            next_obs=next_obs,
            context=steps.extras["context"],
        )
        return collector, traj, episode

    def loss_fn(net_params, aux, mb):
        mean = policy_mean(net_params["actor"], mb["obs"], mb["context"])
        values = value_fn(net_params["critic"], mb["obs"])
        if variant.advantages is not None:
            advantages = variant.advantages(aux, mb)
        else:
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
        net_params, opt_state, aux = carry
        (loss, info), grads = grad_fn(net_params, aux, mb)
        updates, opt_state = optimizer.update(grads, opt_state, net_params)
        net_params = optax.apply_updates(net_params, updates)
        info = {**info, "loss": loss, "grad_norm": optax.tree.norm(grads)}
        if variant.aux_step is not None:
            aux, aux_info = variant.aux_step(aux, mb)
            info = {**info, **aux_info}
        return (net_params, opt_state, aux), info

    def epoch(carry, key, data):
        permutation = jax.random.permutation(key, batch)
        shuffled = jax.tree.map(
            lambda x: jnp.reshape(x[permutation], (config.num_minibatches, minibatch, *x.shape[1:])), data
        )
        return jax.lax.scan(sgd_step, carry, shuffled)

    def update(runner: RunnerState, params) -> tuple[RunnerState, dict]:
        key, key_rollout, key_sgd = jax.random.split(runner.key, 3)
        collector, traj, episode = rollout(runner, params, key_rollout)
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
            "context": jax.tree.map(flat, traj.context),
        }
        aux, variant_metrics = runner.aux, {}
        if variant.prepare is not None:
            aux, data, variant_metrics = variant.prepare(aux, traj, episode, data, flat)
        (net_params, opt_state, aux), infos = jax.lax.scan(
            lambda carry, k: epoch(carry, k, data),
            (runner.params, runner.opt_state, aux),
            jax.random.split(key_sgd, config.num_epochs),
        )
        env_steps = add_count(runner.env_steps, batch)
        residual = data["returns"] - data["value"]
        metrics = {
            "env_steps": env_steps,
            **{name: value for name, value in episode.items()},
            **{name: jnp.mean(value) for name, value in infos.items()},
            "learning_rate": _learning_rate(config, opt_state),
            "policy_std": jnp.mean(jnp.exp(net_params["log_std"])),
            "explained_variance": 1.0 - jnp.var(residual) / jnp.maximum(jnp.var(data["returns"]), 1e-8),
            "mean_reward": jnp.mean(traj.reward) / config.reward_scale,
            "violation_fraction": jnp.mean(traj.cost),
            **variant_metrics,
        }
        new_runner = RunnerState(
            params=net_params, opt_state=opt_state, collector=collector, key=key, env_steps=env_steps, aux=aux
        )
        return new_runner, metrics

    def policy_params(runner: RunnerState) -> dict:
        saved = {
            "actor": runner.params["actor"],
            "log_std": runner.params["log_std"],
            "obs_stats": runner.collector.obs_stats,
        }
        if variant.policy_aux is not None:
            saved["layer"] = variant.policy_aux(runner.aux)
        return saved

    def make_policy(policy_params: Mapping):
        """``policy(obs, key=None) -> a`` in [-1, 1]: ``clip(mu)`` without a key, a clipped sample with one."""

        def policy(obs, key=None):
            context = context_of(policy_params.get("layer"), obs)
            mean = policy_mean(policy_params["actor"], observe(policy_params["obs_stats"], obs), context)
            if key is None:
                return jnp.clip(mean, -1.0, 1.0)
            noise = jax.random.normal(raw_key(key), mean.shape, mean.dtype)
            return jnp.clip(mean + jnp.exp(policy_params["log_std"]) * noise, -1.0, 1.0)

        return policy

    return init, update, policy_params, make_policy


def make_variant_learner(name: str, config, env, variant: Variant) -> Learner:
    """A PPO ``variant`` (a checked ``Config`` subclass instance) as a ``Learner`` named ``name``."""
    init, update, policy_params, make_policy = _functions(config, env, variant)
    return Learner(
        name=name,
        config=config,
        init=init,
        update=update,
        num_iterations=config.num_iterations,
        steps_per_iteration=config.batch_size,
        policy_params=policy_params,
        make_policy=make_policy,
    )


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
        steps_per_iteration=config.batch_size,
        policy_params=policy_params,
        make_policy=make_policy,
    )


def make_train(config, env):
    """The whole PPO run as one pure function.

    Returns:
        ``train(key, params) -> (runner_state, metrics)``: ``config.num_iterations`` iterations from
        ``init(key, params)``; ``metrics`` is a dict of (num_iterations,) arrays (see ``update``; ``env_steps`` is an
        ``scg_algorithms.rl.counter.Count``, exact past 2^31: ``count_value`` gives the integers). Jit it once and
        ``jax.vmap`` it over keys for several seeds (``params`` unbatched, or batched with ``in_axes`` for
        sweeps).
    """
    learner = make_learner(config, env)

    def train(key, params):
        runner = learner.init(key, params)
        return jax.lax.scan(lambda state, _: learner.update(state, params), runner, None, learner.num_iterations)

    return train
