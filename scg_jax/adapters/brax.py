"""brax adapter: any scg-jax environment as a ``brax.envs.base.Env``, trained by brax's PPO and SAC unmodified.

```python
import scg_jax
from brax.training.agents.ppo import train as ppo
from scg_jax.adapters.brax import BraxEnv, wrap_for_training

env = scg_jax.make("cartpole", action_mode="normalized", reward_type="exponential", episode_len_sec=2,
                   constraints=[{"type": "abs_bound", "on": "state", "active_dims": [2], "bound": 0.2}])
brax_env = BraxEnv(env)  # params default to env.default_params
make_policy, params, metrics = ppo.train(
    brax_env, num_timesteps=100_000, episode_length=env.num_steps, wrap_env_fn=wrap_for_training,
    num_envs=64, batch_size=32, num_minibatches=8, unroll_length=20, num_updates_per_batch=8,
    learning_rate=3e-3, discounting=0.97, normalize_observations=True, num_evals=3,
)
metrics["eval/episode_reward"], metrics["eval/episode_cost"]  # return and constraint cost per episode
```

``BraxEnv`` is one copy (brax's convention; the wrappers vmap it). Its ``State`` holds the scg ``EnvState`` as
``pipeline_state``, ``done = terminated | truncated`` as a float, ``info["truncation"]`` (and the same flag as
``info["time_out"]`` for ``bootstrap_on_timeout``) set at the time limit only, and per-step ``metrics``
``cost`` (the constrained-MDP cost), ``mse`` and ``constraint_violation``; brax's evaluator sums them over an
episode into ``eval/episode_cost``, ``eval/episode_mse`` and ``eval/episode_constraint_violation``.

Pass ``wrap_env_fn=wrap_for_training`` to the trainers. brax's default ``envs.training.wrap`` runs, but its
``AutoResetWrapper`` restarts every finished episode from the *first* state of the batch (cached at the first
reset), so later episodes never draw a new initial state, new physical parameters or new disturbance phases,
and its ``EpisodeWrapper`` reports a time-limit end as a termination (``truncation = 1 - done``) when the env
itself truncates at the same step. ``wrap_for_training`` fixes both: ``EpisodeWrapper`` keeps the env's own
truncation flag, ``EpisodicAutoResetWrapper`` calls the env's ``reset`` wherever an episode ends, with the key
``scg_jax.rollout.restart_done`` (the suite's one auto-reset) derives from the finished episode, so reset keys
``scg_jax.rollout.initial_reset_keys(key, N)`` replay the episodes of ``scg_jax.make_rollout(...)(key, params)``.

brax's ``randomization_fn`` (``(sys, rng) -> (batched sys, in_axes)``) becomes ``(params, rng) -> (batched
EnvParams, in_axes)`` here: each parallel slot keeps its drawn ``EnvParams`` for the whole run (brax's semantics),
on top of the env's own ``physics_randomization``, which is drawn again at every reset.

Versions: brax 0.14.2's trainers call ``jax.device_put_replicated``, removed in jax 0.10 (google/brax issue
671); the package pins jax 0.9.2, where it is only deprecated.
"""

from __future__ import annotations

import contextlib
import io
import sys
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

from scg_jax.env import Env, EnvParams
from scg_jax.rollout import restart_done

# brax imports mujoco.mjx, whose optional GPU backend prints "Failed to import warp: ..." and "Failed to import
# mujoco_warp: ..." to stdout when the warp package is absent (it is not needed here). Drop exactly those lines
# and pass any other output of the import through.
_WARP_MESSAGES = ("Failed to import warp:", "Failed to import mujoco_warp:")
with contextlib.redirect_stdout(io.StringIO()) as _import_output:
    from brax.envs.base import Env as _BraxBaseEnv
    from brax.envs.base import State, Wrapper
    from brax.envs.wrappers.training import VmapWrapper
sys.stdout.write(
    "".join(line for line in _import_output.getvalue().splitlines(True) if not line.startswith(_WARP_MESSAGES))
)
del _import_output

__all__ = [
    "METRIC_NAMES",
    "BraxEnv",
    "EpisodeWrapper",
    "EpisodicAutoResetWrapper",
    "ParamsRandomizationVmapWrapper",
    "State",
    "wrap_for_training",
]

METRIC_NAMES = ("cost", "mse", "constraint_violation")
"""Per-step entries of ``State.metrics``; brax's evaluator reports their episode sums as ``eval/episode_<name>``."""


class BraxEnv(_BraxBaseEnv):
    """One scg-jax environment copy behind brax's ``Env`` interface.

    Args:
        env: an ``scg_jax.Env`` made with ``action_mode="normalized"`` (brax's policies output tanh-squashed
            actions in [-1, 1]).
        params: its ``EnvParams`` (default ``env.default_params``); unbatched: the wrappers vmap over copies.

    Raises:
        ValueError: if ``env`` takes physical inputs (``action_mode="physical"``).
    """

    def __init__(self, env: Env, params: EnvParams | None = None):
        if not isinstance(env, Env):
            raise TypeError(f"env: expected an scg_jax.Env (from scg_jax.make), got {type(env).__name__}")
        if env.action_mode != "normalized":
            raise ValueError(
                f"env: action_mode is {env.action_mode!r}, but brax's policies output actions in [-1, 1]; make the "
                "env with action_mode='normalized', e.g. scg_jax.make(system, task, action_mode='normalized', ...)"
            )
        self.scg_env = env
        self.params = env.default_params if params is None else params

    def with_params(self, params: EnvParams) -> BraxEnv:
        """The same environment with other ``EnvParams``."""
        return BraxEnv(self.scg_env, params)

    @property
    def observation_size(self) -> int:
        return self.scg_env.observation_size

    @property
    def action_size(self) -> int:
        return self.scg_env.action_size

    @property
    def backend(self) -> str:
        return "scg_jax"

    def reset(self, rng: jax.Array) -> State:
        """Start an episode (``env.reset(rng, params)``): zero reward, done, metrics and truncation flags."""
        obs, env_state = self.scg_env.reset(rng, self.params)
        zero = jnp.zeros((), obs.dtype)
        return State(
            pipeline_state=env_state,
            obs=obs,
            reward=zero,
            done=zero,
            metrics={name: zero for name in METRIC_NAMES},
            info={"truncation": zero, "time_out": zero},
        )

    def step(self, state: State, action: jax.Array) -> State:
        """One control step (``env.step``). Entries other wrappers put in ``metrics`` and ``info`` are kept."""
        out = self.scg_env.step(state.pipeline_state, action, self.params)
        dtype = out.obs.dtype
        truncated = out.truncated.astype(dtype)
        metrics = {
            **state.metrics,
            "cost": out.cost.astype(dtype),
            "mse": out.info["mse"].astype(dtype),
            "constraint_violation": out.info["constraint_violation"].astype(dtype),
        }
        return state.replace(
            pipeline_state=out.state,
            obs=out.obs,
            reward=out.reward.astype(dtype),
            done=(out.terminated | out.truncated).astype(dtype),
            metrics=metrics,
            info={**state.info, "truncation": truncated, "time_out": truncated},
        )


def _where_done(done: jax.Array, x: jax.Array, y: jax.Array) -> jax.Array:
    """``x`` where ``done`` (a (batch,) float vector, broadcast over trailing axes), else ``y``."""
    if done.shape and x.shape[:1] != done.shape[:1]:  # a leaf without the batch axis (as brax's wrapper does)
        return y
    return jnp.where(jnp.reshape(done, done.shape + (1,) * (x.ndim - done.ndim)) > 0, x, y)


class ParamsRandomizationVmapWrapper(Wrapper):
    """brax's ``DomainRandomizationVmapWrapper`` for ``EnvParams``: one drawn ``EnvParams`` per parallel slot.

    ``randomization_fn(params) -> (batched params, in_axes)`` (the trainers bind its ``rng`` argument with one key
    per slot). The slots keep their parameters for the whole run; the env's own ``physics_randomization`` still
    draws new physical parameters at every reset, around each slot's nominal values.
    """

    def __init__(self, env: _BraxBaseEnv, randomization_fn: Callable[[EnvParams], tuple[EnvParams, Any]]):
        super().__init__(env)
        base = env.unwrapped
        if not isinstance(base, BraxEnv):
            raise TypeError(f"env: expected a BraxEnv (possibly wrapped), got {type(base).__name__}")
        self._params_v, self._in_axes = randomization_fn(base.params)

    @contextlib.contextmanager
    def _params(self, params: EnvParams):
        # Like brax's wrapper: swap the params while tracing, so wrappers between this one and the BraxEnv stay.
        base = self.env.unwrapped
        old = base.params
        try:
            base.params = params
            yield self.env
        finally:
            base.params = old

    def reset(self, rng: jax.Array) -> State:
        def reset(params, key):
            with self._params(params) as env:
                return env.reset(key)

        return jax.vmap(reset, in_axes=(self._in_axes, 0))(self._params_v, rng)

    def step(self, state: State, action: jax.Array) -> State:
        def step(params, s, a):
            with self._params(params) as env:
                return env.step(s, a)

        return jax.vmap(step, in_axes=(self._in_axes, 0, 0))(self._params_v, state, action)


class EpisodeWrapper(Wrapper):
    """brax's ``EpisodeWrapper`` (step counter, time limit, ``episode_metrics``) that keeps the env's truncation.

    ``done`` is the env's done or ``steps >= episode_length``; ``info["truncation"]`` (and ``info["time_out"]``)
    is 1 where the episode ended by a time limit, the env's own or this one's, and not by a termination. With
    ``action_repeat > 1`` a copy whose episode ends within the repeated steps stops there (its reward and metrics
    are summed over the steps it took). ``info["episode_metrics"]`` sums the reward (``sum_reward``), the steps
    (``length``) and every per-step metric over the current episode, as brax's training-metrics logger expects.
    """

    def __init__(self, env: _BraxBaseEnv, episode_length: int, action_repeat: int = 1):
        super().__init__(env)
        if int(episode_length) <= 0 or int(action_repeat) <= 0:
            raise ValueError(
                f"episode_length and action_repeat: must be positive, got {episode_length!r}, {action_repeat!r}"
            )
        self.episode_length = int(episode_length)
        self.action_repeat = int(action_repeat)

    def reset(self, rng: jax.Array) -> State:
        state = self.env.reset(rng)
        zero = jnp.zeros_like(state.reward)
        episode_metrics = {"sum_reward": zero, "length": zero, **{name: zero for name in state.metrics}}
        info = {
            **state.info,
            "steps": zero,
            "truncation": zero,
            "time_out": zero,
            "episode_done": zero,
            "episode_metrics": episode_metrics,
        }
        return state.replace(info=info)

    def _repeat_step(self, state: State, action: jax.Array):
        """``action_repeat`` steps; returns the last state, summed reward and summed metrics."""
        if self.action_repeat == 1:
            nstate = self.env.step(state, action)
            return nstate, nstate.reward, nstate.metrics

        def body(carry, _):
            current, finished = carry
            stepped = self.env.step(current, action)
            live = 1 - finished
            out = (stepped.reward * live, jax.tree.map(lambda m: m * live, stepped.metrics))
            stepped = jax.tree.map(lambda old, new: _where_done(finished, old, new), current, stepped)
            return (stepped, jnp.maximum(finished, stepped.done)), out

        (nstate, _), (rewards, metrics) = jax.lax.scan(
            body, (state, jnp.zeros_like(state.done)), None, length=self.action_repeat
        )
        return nstate, jnp.sum(rewards, axis=0), jax.tree.map(lambda m: jnp.sum(m, axis=0), metrics)

    def step(self, state: State, action: jax.Array) -> State:
        nstate, reward, metrics = self._repeat_step(state, action)
        steps = state.info["steps"] + self.action_repeat
        env_truncation = nstate.info.get("truncation", jnp.zeros_like(nstate.done))
        terminated = nstate.done * (1 - env_truncation)
        done = jnp.maximum(nstate.done, (steps >= self.episode_length).astype(nstate.done.dtype))
        truncation = done * (1 - terminated)

        keep = 1 - state.info["episode_done"]
        previous = state.info["episode_metrics"]
        episode_metrics = {
            name: previous[name] * keep + (reward if name == "sum_reward" else metrics[name])
            for name in previous
            if name != "length"
        }
        episode_metrics["length"] = previous["length"] * keep + self.action_repeat
        info = {
            **nstate.info,
            "steps": steps,
            "truncation": truncation,
            "time_out": truncation,
            "episode_done": done,
            "episode_metrics": episode_metrics,
        }
        return nstate.replace(reward=reward, metrics=metrics, done=done, info=info)


class EpisodicAutoResetWrapper(Wrapper):
    """Auto-reset that starts every episode with a fresh ``reset``: new initial state, parameters and phases.

    Unlike brax's ``AutoResetWrapper`` (which restores the state cached at the first reset), a copy whose episode
    ended gets a fresh ``reset`` through ``scg_jax.rollout.restart_done``, the suite's one auto-reset: the key is
    ``next_reset_key`` of the finished episode's ``EnvState.key``, exactly as in ``make_rollout`` and the
    Gymnasium vector env, so reset keys ``scg_jax.rollout.initial_reset_keys(key, N)`` give the episodes of
    ``make_rollout(...)(key, params)``. ``reward``, ``done``, ``metrics`` and ``info`` describe the finished step;
    ``obs`` and ``pipeline_state`` are those of the new episode (brax's convention).
    """

    def reset(self, rng: jax.Array) -> State:
        return self.env.reset(rng)

    def step(self, state: State, action: jax.Array) -> State:
        info = dict(state.info)
        if "steps" in info:
            info["steps"] = jnp.where(state.done > 0, jnp.zeros_like(info["steps"]), info["steps"])
        state = self.env.step(state.replace(done=jnp.zeros_like(state.done), info=info), action)

        def reset(keys):
            fresh = self.env.reset(keys)
            return fresh.obs, fresh.pipeline_state

        obs, pipeline_state = restart_done(
            state.done > 0, state.pipeline_state.key, (state.obs, state.pipeline_state), reset
        )
        return state.replace(pipeline_state=pipeline_state, obs=obs)


def wrap_for_training(
    env: _BraxBaseEnv,
    episode_length: int = 1000,
    action_repeat: int = 1,
    randomization_fn: Callable[[EnvParams], tuple[EnvParams, Any]] | None = None,
) -> Wrapper:
    """``wrap_env_fn`` for ``brax.training.agents.ppo.train`` and ``sac.train``, with per-episode resets.

    Vmaps ``env`` (a ``BraxEnv``, possibly wrapped) over the leading axis of the reset keys
    (``ParamsRandomizationVmapWrapper`` when ``randomization_fn`` is given), counts steps and sums episode metrics
    (``EpisodeWrapper``) and restarts finished episodes with fresh resets (``EpisodicAutoResetWrapper``).

    Args:
        env: the environment. episode_length: time limit in env steps, on top of the env's own (pass
            ``scg_env.num_steps`` to make them agree; brax's evaluator runs ``episode_length // action_repeat``
            steps). action_repeat: env steps per agent step. randomization_fn: ``params -> (batched params,
            in_axes)``, as the trainers call it (they bind ``rng``).
    """
    if randomization_fn is None:
        env = VmapWrapper(env)
    else:
        env = ParamsRandomizationVmapWrapper(env, randomization_fn)
    env = EpisodeWrapper(env, episode_length, action_repeat)
    return EpisodicAutoResetWrapper(env)
