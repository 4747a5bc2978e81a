"""The off-policy skeleton that SAC, DDPG and TD3 share: options, runner state, the iteration and the learner.

One *iteration* collects ``rollout_steps`` control steps in each of the ``num_envs`` auto-resetting copies (the
learners' shared ``scg_algorithms.rl.collector``, which also merges the observations into the running normaliser),
writes the transitions to the replay buffer (``scg_algorithms.rl.replay``), then takes ``utd * num_envs *
rollout_steps`` gradient steps, each on a batch drawn uniformly from the buffer. The first ``warmup_iterations``
act uniformly at random in [-1, 1] and do not learn.

What differs between the algorithms is an ``Algorithm``: what it learns (``init``: networks, targets, optimiser
states; always with an ``actor`` field), how it explores (``explore``), its gradient step on a batch (``update``:
losses, actor and target rules) and the metrics of an iteration without learning (``idle``). The batch it gets has
its observations normalised with the statistics of the observations collected so far and its reward times
``reward_scale``; a time-limit truncation is stored with ``terminated = 0`` and the final observation as
``next_obs``, so it bootstraps, while a termination does not.

``make_learner(name, config, env, algorithm)`` gives the ``Learner`` for the host driver
(``scg_algorithms.rl.training.run_training``) and the ``update_at`` of ``scg_algorithms.rl.learner.make_train`` (the
whole budget in one ``lax.scan``, with the warm-up decided by the scan's iteration index so it stays a real branch
under ``jax.vmap``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax

from scg_algorithms.base import option
from scg_algorithms.rl import envs as rl_envs
from scg_algorithms.rl import replay
from scg_algorithms.rl.collector import ActOutput, CollectorState, collect, init_collector
from scg_algorithms.rl.config import check_budget, hidden_sizes_option, learner_option
from scg_algorithms.rl.counter import Count, add_count, count_at_least, zero_count
from scg_algorithms.rl.networks import twin_q
from scg_algorithms.rl.normalization import RunningStats, normalize
from scg_algorithms.rl.training import Learner, raw_key

__all__ = [
    "Algorithm",
    "Config",
    "PolicyParams",
    "RunnerState",
    "critic_loss",
    "critic_step",
    "init_networks",
    "make_learner",
    "make_optimizer",
    "polyak_update",
]


# --------------------------------------------------------------------------------------------- options
@dataclasses.dataclass(frozen=True)
class Config:
    """The options every off-policy learner has (a learner's ``Config`` adds its own and may redeclare a field to
    give it another default). Steps count transitions summed over the parallel copies.

    Budget: ``total_env_steps`` transitions and ``utd * total_env_steps`` gradient steps; each iteration collects
    ``num_envs * rollout_steps`` transitions, then takes ``utd * num_envs * rollout_steps`` gradient steps (an
    integer, checked).
    """

    total_env_steps: int = learner_option("total_env_steps", 150_000)
    num_envs: int = learner_option("num_envs", 64)
    rollout_steps: int = option(1, "control steps per copy collected per iteration", check="positive")
    utd: float = option(0.25, "gradient steps per environment transition (update-to-data ratio)", check="positive")
    warmup_steps: int = option(
        5_000, "transitions collected with uniform random actions before learning starts", check="non_negative"
    )
    buffer_size: int = option(100_000, "replay capacity in transitions (clipped to total_env_steps)", check="positive")
    batch_size: int = option(256, "transitions per gradient step", check="positive")
    gamma: float = option(0.99, "discount factor per control step")
    tau: float = option(0.005, "Polyak factor of the target networks: target <- (1 - tau) target + tau online")
    actor_lr: float = option(1e-3, "Adam learning rate of the actor", check="positive")
    critic_lr: float = option(1e-3, "Adam learning rate of the critics", check="positive")
    hidden_sizes: tuple = hidden_sizes_option((64, 64), "hidden layer widths of the actor and of each critic")
    activation: str = learner_option("activation", "relu")
    reward_scale: float = learner_option("reward_scale", 1.0)
    normalize_observations: bool = learner_option("normalize_observations", True)
    max_grad_norm: float = option(0.0, "global gradient-norm clip of every optimiser (0: off)", check="non_negative")
    action_scale: float = learner_option("action_scale", 1.0)

    def _check(self, path: str) -> None:
        if not 0.0 < self.gamma < 1.0:
            raise ValueError(f"{path}.gamma: must be in (0, 1), got {self.gamma}")
        if not 0.0 < self.tau <= 1.0:
            raise ValueError(f"{path}.tau: must be in (0, 1], got {self.tau}")
        per_iteration = self.utd * self.transitions_per_iteration
        if not math.isclose(per_iteration, round(per_iteration)) or round(per_iteration) < 1:
            raise ValueError(
                f"{path}.utd: utd * num_envs * rollout_steps must be a positive integer (gradient steps per "
                f"iteration), got {self.utd} * {self.num_envs} * {self.rollout_steps} = {per_iteration:g}"
            )
        check_budget(path, self.total_env_steps, self.transitions_per_iteration, "num_envs * rollout_steps")
        if self.transitions_per_iteration > self.capacity:
            raise ValueError(
                f"{path}.buffer_size: must hold one iteration's {self.transitions_per_iteration} transitions, "
                f"got {self.buffer_size}"
            )

    # ------------------------------------------------------------------------------------------ derived
    @property
    def transitions_per_iteration(self) -> int:
        return self.num_envs * self.rollout_steps

    @property
    def grad_steps_per_iteration(self) -> int:
        return round(self.utd * self.transitions_per_iteration)

    @property
    def num_iterations(self) -> int:
        """Iterations of the whole budget (rounded down to whole iterations)."""
        return self.total_env_steps // self.transitions_per_iteration

    @property
    def warmup_iterations(self) -> int:
        """Iterations that act randomly and do not learn (at least ``warmup_steps`` transitions, whole
        iterations, and at least one batch in the buffer), at most ``num_iterations``."""
        needed = max(self.warmup_steps, self.batch_size)
        return min(-(-needed // self.transitions_per_iteration), self.num_iterations)

    @property
    def capacity(self) -> int:
        """Replay capacity: ``buffer_size`` clipped to the budget (a larger buffer would never fill)."""
        return min(self.buffer_size, max(self.total_env_steps, 1))

    def to_dict(self) -> dict:
        """Plain JSON-able mapping that parses back into an equal ``Config``."""
        values = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        return {name: list(value) if isinstance(value, tuple) else value for name, value in values.items()}


# --------------------------------------------------------------------------------------------- shared losses
def critic_loss(q, target):
    """Regression loss of K stacked critics ``sum_k 1/2 mean_b (Q_k(s_b, a_b) - y_b)^2``.

    Args:
        q: (K, B) the critics at the replayed ``(s, a)`` (K = 2 for twin critics, 1 for DDPG's).
        target: (B,) the Bellman target (its gradient is stopped here).

    Returns:
        scalar loss.
    """
    return 0.5 * jnp.sum(jnp.mean((q - jax.lax.stop_gradient(target)[None]) ** 2, axis=-1))


def polyak_update(target, online, tau):
    """``target <- (1 - tau) target + tau online`` leaf by leaf (pytrees of equal structure)."""
    return jax.tree.map(lambda t, o: (1.0 - tau) * t + tau * o, target, online)


def init_networks(actor, critic, num_critics: int, key_actor, key_critic, obs, action) -> tuple:
    """``(actor params, critic params)``: the flax ``actor`` initialised at ``obs``, and ``num_critics`` critics
    initialised from ``split(key_critic, num_critics)`` at ``(obs, action)``, stacked on a leading axis."""
    critic_keys = jax.random.split(key_critic, num_critics)
    return actor.init(key_actor, obs), jax.vmap(critic.init, in_axes=(0, None, None))(critic_keys, obs, action)


def critic_step(critic, optimizer, critic_params, opt_state, obs, action, target) -> tuple:
    """One optimiser step of the K stacked critics (``critic_loss`` towards ``target``, gradient stopped).

    Returns:
        ``(critic params, optimiser state, loss, q)``: ``q`` (K, B) the critics at ``(obs, action)`` before the step.
    """

    def objective(params):
        q = twin_q(critic, params, obs, action)
        return critic_loss(q, target), q

    (loss, q), grads = jax.value_and_grad(objective, has_aux=True)(critic_params)
    updates, opt_state = optimizer.update(grads, opt_state, critic_params)
    return optax.apply_updates(critic_params, updates), opt_state, loss, q


def make_optimizer(learning_rate, max_grad_norm: float):
    """Adam at ``learning_rate`` (a float, or a traced scalar of a population), after a global gradient-norm clip
    when ``max_grad_norm > 0``."""
    adam = optax.adam(learning_rate)
    return optax.chain(optax.clip_by_global_norm(max_grad_norm), adam) if max_grad_norm > 0 else adam


# --------------------------------------------------------------------------------------------- algorithm
class PolicyParams(NamedTuple):
    """What an off-policy policy needs to act: the actor's flax params and the observation normaliser."""

    actor: Any
    obs_stats: RunningStats


class Algorithm(NamedTuple):
    """What an off-policy learner adds to the skeleton (module docstring).

    Attributes:
        init: ``init(key_actor, key_critic, obs (obs_size,), action (nu,)) -> learning``: a pytree with an
            ``actor`` field (flax params), plus whatever else a gradient step changes.
        explore: ``explore(policy_params, obs (N, obs_size) raw, key) -> (N, nu)`` actions in [-1, 1] while
            learning.
        update: ``update(learning, keys (num_update_keys,), batch) -> (learning, metrics)``: one gradient step;
            ``batch`` a dict of (B, ...) arrays ``obs``, ``next_obs`` (normalised), ``action``, ``reward`` (scaled),
            ``terminated`` (0/1), ``cost``; ``metrics`` a dict of scalars named ``metric_names``.
        idle: ``idle(learning) -> metrics`` of an iteration that does not learn (warm-up).
        policy: ``policy(policy_params, obs, key=None) -> a`` in [-1, 1]^nu, deterministic without a key.
        metric_names: the names of ``update``'s metrics.
        num_update_keys: how many keys ``update`` takes (split with the batch's sampling key).
        summarize: ``summarize(step_metrics) -> metrics``: an iteration's metrics from its steps' (each (G,));
            default the mean of each.
    """

    init: Callable
    explore: Callable
    update: Callable
    idle: Callable
    policy: Callable
    metric_names: tuple[str, ...]
    num_update_keys: int
    summarize: Callable | None = None


class RunnerState(NamedTuple):
    """Everything an off-policy run carries between iterations (a pytree; checkpointed whole).

    Attributes:
        learning: the ``Algorithm``'s pytree (networks, targets, optimiser states).
        buffer: ``replay.ReplayBuffer`` of dicts ``obs, action, reward, next_obs, terminated, cost``.
        collector: ``scg_algorithms.rl.collector.CollectorState`` (batched env state, observations to act on next,
            episode sums, the last episode means, the normaliser of the observations collected so far).
        key: raw PRNG key. iteration, env_steps, grad_steps: ``Count``s (exact past 2^31).
    """

    learning: Any
    buffer: replay.ReplayBuffer
    collector: CollectorState
    key: Any
    iteration: Count
    env_steps: Count
    grad_steps: Count

    @property
    def actor(self):
        """The actor's flax params (``learning.actor``)."""
        return self.learning.actor

    @property
    def obs_stats(self) -> RunningStats:
        """The observation normaliser (``collector.obs_stats``)."""
        return self.collector.obs_stats


def policy_params(state: RunnerState) -> PolicyParams:
    """The part of the runner state a policy needs (saved as ``policy.msgpack`` by the host driver)."""
    return PolicyParams(actor=state.actor, obs_stats=state.collector.obs_stats)


class _Parts(NamedTuple):
    """The static pieces of an off-policy run (decided at ``make_learner``)."""

    config: Config
    train_env: rl_envs.TrainEnv
    algorithm: Algorithm

    def norm(self, stats, obs):
        """``obs`` as the networks see it (normalised with ``stats`` when ``normalize_observations``)."""
        return normalize(stats, obs) if self.config.normalize_observations else obs


def _init(parts: _Parts, key, params) -> RunnerState:
    config, obs_size, action_size = parts.config, parts.train_env.obs_size, parts.train_env.action_size
    key_env, key_actor, key_critic, key = jax.random.split(key, 4)
    dummy_obs, dummy_action = jnp.zeros((obs_size,)), jnp.zeros((action_size,))
    example = {
        "obs": dummy_obs,
        "action": dummy_action,
        "reward": jnp.zeros(()),
        "next_obs": dummy_obs,
        "terminated": jnp.zeros(()),
        "cost": jnp.zeros(()),
    }
    return RunnerState(
        learning=parts.algorithm.init(key_actor, key_critic, dummy_obs, dummy_action),
        buffer=replay.init_buffer(config.capacity, example),
        collector=init_collector(parts.train_env, key_env, params, jnp.float32),
        key=raw_key(key),  # raw data, as PPO: the state serialises the same whatever key was passed
        iteration=zero_count(),
        env_steps=zero_count(),
        grad_steps=zero_count(),
    )


def _gradient_step(parts: _Parts, learning, key, buffer, stats):
    """One gradient step of the algorithm on a batch drawn uniformly from ``buffer``."""
    config = parts.config
    key_sample, *update_keys = jax.random.split(key, 1 + parts.algorithm.num_update_keys)
    batch = replay.sample(buffer, key_sample, config.batch_size)
    batch = {
        **batch,
        "obs": parts.norm(stats, batch["obs"]),
        "next_obs": parts.norm(stats, batch["next_obs"]),
        "reward": config.reward_scale * batch["reward"],
    }
    return parts.algorithm.update(learning, update_keys, batch)


def _collect(parts: _Parts, state: RunnerState, params, key, learning):
    """One iteration's transitions, acting with the algorithm's exploration (``learning``) or uniformly at
    random."""
    config, num_envs, action_size = parts.config, parts.config.num_envs, parts.train_env.action_size
    policy = policy_params(state)

    def act(obs, key_step) -> ActOutput:
        key_policy, key_random = jax.random.split(key_step)
        policy_action = parts.algorithm.explore(policy, obs, key_policy)
        random_action = jax.random.uniform(key_random, (num_envs, action_size), minval=-1.0, maxval=1.0)
        return ActOutput(jnp.where(learning, policy_action, random_action), {})

    return collect(
        parts.train_env, params, state.collector, act, key, config.rollout_steps,
        update_normalizer=config.normalize_observations,
    )  # fmt: skip


def _mean_metrics(step_metrics: dict) -> dict:
    return {name: jnp.mean(value) for name, value in step_metrics.items()}


def _iteration(parts: _Parts, state: RunnerState, params, learning):
    """One iteration; ``learning`` (bool scalar, may be traced) selects exploration and gradient steps, or
    uniform random actions and none (warm-up). A ``learning`` that does not depend on vmapped values keeps the
    ``lax.cond`` a real branch under ``jax.vmap``, so warm-up iterations skip the gradient work."""
    config, algorithm = parts.config, parts.algorithm
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
    summarize = algorithm.summarize or _mean_metrics

    def learn(carry, key):
        carry, step_metrics = jax.lax.scan(
            lambda c, k: _gradient_step(parts, c, k, buffer, obs_stats),
            carry,
            jax.random.split(key, config.grad_steps_per_iteration),
        )
        return carry, {name: value.astype(jnp.float32) for name, value in summarize(step_metrics).items()}

    def skip(carry, key):
        return carry, {name: value.astype(jnp.float32) for name, value in algorithm.idle(carry).items()}

    carry, loss_metrics = jax.lax.cond(learning, learn, skip, state.learning, key_learn)
    num_grad = jnp.where(learning, config.grad_steps_per_iteration, 0).astype(jnp.uint32)
    new_state = RunnerState(
        learning=carry,
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
        **{name: loss_metrics[name] for name in algorithm.metric_names},
    }
    return new_state, metrics


def make_learner(name: str, config: Config, env, algorithm: Algorithm) -> tuple[Learner, Callable]:
    """The off-policy learner ``name`` with the checked ``config`` and ``algorithm``, and its ``update_at`` for
    ``scg_algorithms.rl.learner.make_train``.

    ``Learner.update`` is one iteration; warm-up or learning is chosen from ``runner_state.iteration``, so a chain
    of ``num_iterations`` updates is the same computation as ``make_train``. ``update_at`` takes the iteration
    index from ``make_train``'s scan instead (unbatched under ``jax.vmap``, so the warm-up's ``lax.cond`` keeps
    skipping the gradient steps for every seed).
    """
    parts = _Parts(config, rl_envs.make_train_env(env, config.num_envs, config.action_scale), algorithm)
    warmup = config.warmup_iterations

    def make_policy(p: PolicyParams):
        return lambda obs, key=None: algorithm.policy(p, obs, key)

    learner = Learner(
        name=name,
        config=config,
        init=lambda key, params: _init(parts, key, params),
        update=lambda state, params: _iteration(parts, state, params, count_at_least(state.iteration, warmup)),
        num_iterations=config.num_iterations,
        steps_per_iteration=config.transitions_per_iteration,
        policy_params=policy_params,
        make_policy=make_policy,
        collect=lambda state, params: _collect(parts, state, params, jax.random.split(state.key, 3)[1], True)[:2],
    )
    return learner, lambda state, params, i: _iteration(parts, state, params, i >= warmup)
