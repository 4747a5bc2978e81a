"""The learners' one data collector: ``num_steps`` steps of the batched ``TrainEnv`` under an ``act`` function.

Every learner (PPO, SAC, and the safe and robust variants built on them) collects the same way:

1. ``act(obs, key) -> ActOutput`` picks the actions of all N copies from the raw observations (N, obs_size); it
   normalises them itself with the statistics *as they were at the start of the collection* (the learner closes
   over them), so what it computes is exactly what its update later recomputes;
2. ``TrainEnv.step`` applies them (with the adversary's input where ``act`` gives one), auto-resetting finished
   episodes and keeping each step's ``final_obs``;
3. ``update_episode_stats`` accumulates each copy's return, cost, squared error and length;

and after the scan the raw observations acted on are merged into the observation normaliser, and the means of the
episodes that finished are reported (``episode_means``; the previous value where none did).

The ``Transitions`` carry what any of the learners needs: reward and ``cost`` (the constrained-MDP signal of a
cost critic / Lagrangian), ``terminated`` and ``truncated`` apart (bootstrapping at a time limit), the raw
``next_obs`` (``final_obs``, before any reset), the adversary's input, chosen ``info`` entries (e.g.
``constraint_values`` for a safety layer), and whatever ``act`` returned in ``extras`` (log-probabilities, values).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from scg_algorithms.rl.envs import (
    EPISODE_METRICS,
    EpisodeStats,
    TrainEnv,
    episode_means,
    init_episode_stats,
    initial_episode_means,
    update_episode_stats,
)
from scg_algorithms.rl.normalization import RunningStats, init_stats, update_stats


class CollectorState(NamedTuple):
    """What collection carries from one iteration to the next (part of every learner's runner state).

    Attributes:
        env_state: batched ``EnvState`` of the N copies. obs: (N, obs_size) raw observations to act on next.
        episode_stats: per-copy running sums of the current episodes. last_episode: ``{EPISODE_METRICS: scalar}``,
        the means last reported. obs_stats: ``RunningStats`` of every raw observation acted on so far.
    """

    env_state: Any
    obs: Any
    episode_stats: EpisodeStats
    last_episode: dict
    obs_stats: RunningStats


class ActOutput(NamedTuple):
    """What an ``act`` function returns for the N copies.

    Attributes:
        action: (N, action_size) policy actions (the env clips them to [-1, 1]).
        extras: dict of (N, ...) arrays stored with the step (e.g. ``log_prob``, ``value``); ``{}`` for none.
        adversary: (N, adversary_dim) input in [-1, 1] of the env's adversary channel, or None (no adversary).
    """

    action: Any
    extras: dict
    adversary: Any = None


class Transitions(NamedTuple):
    """The collected steps, every leaf (T, N, ...).

    Attributes:
        obs: raw observation acted on. action: the action taken (as ``act`` gave it, before the env's clip).
        reward: (T, N) reward. cost: (T, N) constrained-MDP cost (1 at a step in violation).
        terminated, truncated: (T, N) bools (no bootstrap / bootstrap from ``next_obs``).
        next_obs: raw observation the step reached, before any reset (``final_obs``).
        info: the ``info_keys`` entries of the env's ``info``. extras: ``ActOutput.extras``.
        adversary: ``ActOutput.adversary`` (None without an adversary).
    """

    obs: Any
    action: Any
    reward: Any
    cost: Any
    terminated: Any
    truncated: Any
    next_obs: Any
    info: dict
    extras: dict
    adversary: Any


def init_collector(train_env: TrainEnv, key, params, dtype=None) -> CollectorState:
    """Reset the N copies from ``key``; zero episode sums and empty normaliser statistics.

    ``dtype``: of the observations and statistics (default: the env's observation dtype).
    """
    obs, env_state = train_env.reset(key, params)
    if dtype is not None:
        obs = obs.astype(dtype)
    return CollectorState(
        env_state=env_state,
        obs=obs,
        episode_stats=init_episode_stats(train_env.num_envs, jnp.float32),
        last_episode=initial_episode_means(jnp.float32),
        obs_stats=init_stats(train_env.obs_size, obs.dtype),
    )


class CopyLabels(NamedTuple):
    """A per-copy integer label carried through a collection (e.g. which adversary drives each copy).

    Attributes:
        index: (N,) int32, each copy's label for its next step.
        redraw: ``redraw(key, index, done) -> index``: the labels after a step, ``done`` (N,) marking the copies
            whose episode ended with it (e.g. a fresh draw there, the old label elsewhere).
    """

    index: Any
    redraw: Callable


class Collected(NamedTuple):
    """What ``collect`` returns.

    Attributes:
        state: the new ``CollectorState``. transitions: ``Transitions`` (T, N, ...). episode: ``episode_means`` of
        the episodes finished during the collection (``episode_return``, ``episode_cost``, ``episode_rmse``,
        ``episode_length``, ``episodes_finished``). labels: the labels (N,) after the last step, with
        ``CopyLabels`` (None without).
    """

    state: CollectorState
    transitions: Transitions
    episode: dict
    labels: Any = None


def collect(
    train_env: TrainEnv,
    params,
    state: CollectorState,
    act,
    key,
    num_steps: int,
    *,
    update_normalizer: bool = True,
    info_keys: tuple[str, ...] = (),
    labels: CopyLabels | None = None,
) -> Collected:
    """Scan ``num_steps`` steps of ``train_env`` under ``act``.

    Args:
        train_env: the ``TrainEnv`` (N copies). params: unbatched ``EnvParams``. state: ``CollectorState``.
        act: ``act(obs (N, obs_size), key) -> ActOutput``, called once per step with that step's key (``key``
            split ``num_steps`` ways); with ``labels``, ``act(obs, key, index (N,))``, ``key`` the first of the
            step's key split in two (the second re-draws the labels).
        num_steps: T, steps per copy. update_normalizer: merge the observations acted on into ``obs_stats`` after
            the scan. info_keys: entries of the env's ``info`` to keep in ``Transitions.info``.
        labels: ``CopyLabels`` to carry, or None; the label each step acted under is stored as
            ``transitions.extras["label"]`` (T, N).

    Returns:
        ``Collected(state, transitions, episode, labels)``.
    """

    def step(carry, step_key):
        env_state, obs, episode_stats, index = carry
        if labels is None:
            out_act = act(obs, step_key)
            extras = dict(out_act.extras)
        else:
            key_act, key_redraw = jax.random.split(step_key)
            out_act = act(obs, key_act, index)
            extras = {**out_act.extras, "label": index}
        out = train_env.step(env_state, out_act.action, params, adversary=out_act.adversary)
        episode_stats, finished = update_episode_stats(episode_stats, out)
        transition = Transitions(
            obs=obs,
            action=out_act.action,
            reward=out.reward,
            cost=out.cost,
            terminated=out.terminated,
            truncated=out.truncated,
            next_obs=out.final_obs,
            info={name: out.info[name] for name in info_keys},
            extras=extras,
            adversary=out_act.adversary,
        )
        if labels is not None:
            index = labels.redraw(key_redraw, index, finished.done)
        return (out.state, out.obs.astype(obs.dtype), episode_stats, index), (transition, finished)

    carry = (state.env_state, state.obs, state.episode_stats, None if labels is None else labels.index)
    (env_state, obs, episode_stats, index), (transitions, finished) = jax.lax.scan(
        step, carry, jax.random.split(key, num_steps)
    )
    obs_stats = update_stats(state.obs_stats, transitions.obs) if update_normalizer else state.obs_stats
    episode = episode_means(finished, state.last_episode)
    new_state = CollectorState(
        env_state=env_state,
        obs=obs,
        episode_stats=episode_stats,
        last_episode={name: episode[name] for name in EPISODE_METRICS},
        obs_stats=obs_stats,
    )
    return Collected(new_state, transitions, episode, index)
