"""N auto-resetting copies of an ``scg_jax`` env for RL training, acting in normalised actions ``a`` in [-1, 1].

RL policies here always output ``a`` in [-1, 1] per input channel, whatever the env's ``action_mode``: the
conversion ``u = env.system.action_to_input(a, params.physics)`` (cart-pole ``F = force_max a``, quadrotors
``T = hover (1 + 0.1 a)``) uses the *nominal* physics of ``params`` (a policy cannot know a randomised mass), and
``env.input_to_action(u, params)`` turns ``u`` into the env's own action. The actuator saturation is still the
env's (it clips the applied input to the plant's limits).

Per-episode randomisation (initial state, ``physics_randomization``) and disturbances come from ``params`` and the
env's options: every reset (the first and each automatic one) draws them afresh, so domain randomisation is a
matter of configuration. Auto-reset is ``scg_jax.rollout.auto_reset_step`` (one place for it); the observation of
the step that ended an episode is kept as ``final_obs`` so a learner can bootstrap from its value at a time limit.

``EpisodeStats`` accumulates each copy's running return, cost, squared error and length, so learners can report
``episode_return``, ``episode_cost``, ``episode_rmse`` and ``episode_length`` of the episodes finished in an
iteration (``episode_means``).
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from scg_jax.env import Env, EnvParams
from scg_jax.rollout import auto_reset_step


class EnvStep(NamedTuple):
    """One step of ``TrainEnv`` (arrays with a leading axis N).

    Attributes:
        obs: (N, obs_size) observation to act on next (the first one of a new episode where one ended).
        state: batched ``EnvState`` after the step (reset where an episode ended).
        reward: (N,) reward of the step. cost: (N,) constrained-MDP cost (1 at a step in violation).
        terminated: (N,) bool, the episode ended by failure/goal (no bootstrapping).
        truncated: (N,) bool, the episode hit its time limit (bootstrap from ``final_obs``).
        final_obs: (N, obs_size) observation reached by the step, before any reset (equal to ``obs`` where no
            episode ended).
        info: dict of (N, ...) arrays from ``Env.step`` (``mse``, ``out_of_bounds``, ``constraint_violation``,
            ``u``, ...).
    """

    obs: Any
    state: Any
    reward: Any
    cost: Any
    terminated: Any
    truncated: Any
    final_obs: Any
    info: dict


def policy_action_to_input(env: Env, a, physics, action_scale: float = 1.0):
    """Physical input ``u`` (nu,) in N for a policy action ``a`` (nu,): ``a`` is clipped to [-1, 1], multiplied by
    ``action_scale`` and converted as the env's normalised action.

    With ``action_scale`` 1 a policy has the env's normalised range: the cart-pole's whole force range, but only
    +-10% of hover thrust for the quadrotors (the original suite's scale); 10 gives a quadrotor policy 0-2x hover
    thrust, about the actuator range (the plant still clips to its limits).

    Args:
        env: the ``scg_jax.Env``. a: (nu,) policy action. physics: the system's ``Params`` (nominal values).
        action_scale: factor on the clipped action (a learner's ``action_scale`` option).
    """
    return env.system.action_to_input(action_scale * jnp.clip(a, -1.0, 1.0), physics)


@dataclasses.dataclass(frozen=True, eq=False)
class TrainEnv:
    """``num_envs`` copies of ``env`` with auto-reset and normalised actions; build it with ``make_train_env``.

    Hashable by identity, so it may be a static argument or a closure constant of jitted functions.

    Attributes:
        env: the ``scg_jax.Env``. num_envs: N. obs_size: ``env.observation_size``. action_size: ``env.action_size``.
        action_scale: factor on the policy's action before the env's conversion (``policy_action_to_input``).
    """

    env: Env
    num_envs: int
    obs_size: int
    action_size: int
    action_scale: float = 1.0

    def reset(self, key, params: EnvParams):
        """N fresh episodes from ``key`` (split N ways). Returns ``(obs (N, obs_size), batched EnvState)``."""
        return jax.vmap(self.env.reset, in_axes=(0, None))(jax.random.split(key, self.num_envs), params)

    def step(self, state, action, params: EnvParams, adversary=None) -> EnvStep:
        """Step every copy with the normalised action ``action`` (N, action_size), restarting finished episodes.

        ``params`` is unbatched (shared by the copies); what differs between copies comes from their reset keys.
        ``adversary``: None, or (N, dim) inputs in [-1, 1] of the env's adversary channel (``Env.step``'s
        ``adversary``; the env must be made with one).
        """

        def one(state, a, adv):
            u = policy_action_to_input(self.env, a, params.physics, self.action_scale)
            action = self.env.input_to_action(u, params)
            if adv is None:
                return auto_reset_step(self.env, state, action, params)
            # Needs ``scg_jax.rollout.auto_reset_step`` to forward ``adversary`` to ``Env.step``.
            return auto_reset_step(self.env, state, action, params, adversary=adv)

        out = jax.vmap(one)(state, action, adversary)
        info = dict(out.info)
        final_obs = info.pop("final_obs")
        return EnvStep(out.obs, out.state, out.reward, out.cost, out.terminated, out.truncated, final_obs, info)


def make_train_env(env: Env, num_envs: int, action_scale: float = 1.0) -> TrainEnv:
    """``TrainEnv`` of ``num_envs`` copies of ``env`` (any ``action_mode``; policies act in [-1, 1], times
    ``action_scale``)."""
    if isinstance(num_envs, bool) or int(num_envs) != num_envs or num_envs < 1:
        raise ValueError(f"num_envs: must be a positive integer, got {num_envs!r}")
    if not action_scale > 0:
        raise ValueError(f"action_scale: must be positive, got {action_scale!r}")
    return TrainEnv(
        env=env,
        num_envs=int(num_envs),
        obs_size=env.observation_size,
        action_size=env.action_size,
        action_scale=float(action_scale),
    )


# --------------------------------------------------------------------------------------------- episode statistics
class EpisodeStats(NamedTuple):
    """Running sums of each copy's current episode, (N,) each.

    Attributes:
        episode_return: sum of rewards. episode_cost: sum of costs (steps in violation).
        episode_sq_error: sum of ``info["mse"]``. episode_length: control steps so far.
    """

    episode_return: Any
    episode_cost: Any
    episode_sq_error: Any
    episode_length: Any


class FinishedEpisodes(NamedTuple):
    """What ``update_episode_stats`` reports for the episodes that ended at a step, (N,) each.

    Attributes:
        done: bool, an episode ended here (terminated or truncated). episode_return, episode_cost, episode_length:
            its totals (0 where ``done`` is false). episode_rmse: ``sqrt(sum mse / length)``, m with the default
            ``mse_weight`` (as ``scg_jax.metrics``).
    """

    done: Any
    episode_return: Any
    episode_cost: Any
    episode_rmse: Any
    episode_length: Any


EPISODE_METRICS = ("episode_return", "episode_cost", "episode_rmse", "episode_length")
"""Keys of ``episode_means``'s result (plus ``episodes_finished``)."""


def init_episode_stats(num_envs: int, dtype=jnp.float32) -> EpisodeStats:
    """Zero running sums for ``num_envs`` copies."""
    zeros = jnp.zeros(num_envs, dtype)
    return EpisodeStats(zeros, zeros, zeros, zeros)


def update_episode_stats(stats: EpisodeStats, step: EnvStep) -> tuple[EpisodeStats, FinishedEpisodes]:
    """Add one ``TrainEnv`` step to the running sums; report and zero the copies whose episode ended."""
    dtype = stats.episode_return.dtype
    total = EpisodeStats(
        stats.episode_return + step.reward.astype(dtype),
        stats.episode_cost + step.cost.astype(dtype),
        stats.episode_sq_error + step.info["mse"].astype(dtype),
        stats.episode_length + 1.0,
    )
    done = step.terminated | step.truncated
    keep = lambda value: jnp.where(done, value, 0.0)  # noqa: E731
    finished = FinishedEpisodes(
        done=done,
        episode_return=keep(total.episode_return),
        episode_cost=keep(total.episode_cost),
        episode_rmse=keep(jnp.sqrt(total.episode_sq_error / total.episode_length)),
        episode_length=keep(total.episode_length),
    )
    return jax.tree.map(lambda value: jnp.where(done, 0.0, value), total), finished


def episode_means(finished: FinishedEpisodes, previous: dict) -> dict:
    """Means over the episodes in ``finished`` (any shape, e.g. (T, N) from a rollout's scan).

    Args:
        finished: ``FinishedEpisodes`` stacked over steps. previous: dict with the ``EPISODE_METRICS`` keys (scalars),
            the values reported last time; they are repeated where no episode finished (NaN before the first
            episode has ended: ``initial_episode_means``, so a curve plots nothing there rather than a made-up 0).

    Returns:
        ``{"episode_return", "episode_cost", "episode_rmse", "episode_length", "episodes_finished"}`` scalars.
    """
    count = jnp.sum(finished.done)
    means = {}
    for name in EPISODE_METRICS:
        total = jnp.sum(getattr(finished, name))
        means[name] = jnp.where(count > 0, total / jnp.maximum(count, 1), previous[name]).astype(total.dtype)
    means["episodes_finished"] = count.astype(jnp.float32)
    return means


def initial_episode_means(dtype=jnp.float32) -> dict:
    """The ``previous`` argument of the first ``episode_means`` call: NaN, "no episode has ended yet"."""
    return {name: jnp.full((), jnp.nan, dtype) for name in EPISODE_METRICS}
