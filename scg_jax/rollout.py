"""Auto-reset and batched rollouts: the one place where copies are batched and episodes restarted.

A policy is a pure function ``policy(obs, state, params, key) -> action`` for one copy; ``make_rollout`` vmaps
it together with ``Env.step`` over ``num_envs`` copies and scans over ``num_steps`` control steps.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from scg_jax.env import Env, EnvParams, EnvState, StepOutput

Policy = Callable[[Any, EnvState, EnvParams, Any], Any]

# Env.step draws step k's noise from fold_in(episode key, k); the next episode's reset key comes from an index
# the step counter never reaches, so no key serves twice (split(key)[0] would equal fold_in(key, 0)).
RESET_STREAM = 2**32 - 1


def next_reset_key(episode_key):
    """The reset key of the episode that follows the one whose ``EnvState.key`` is ``episode_key``."""
    return jax.random.fold_in(episode_key, RESET_STREAM)


def initial_reset_keys(key, num_envs: int):
    """The reset keys (num_envs,) of the first episodes of ``make_rollout(...)(key, params)``.

    The Gymnasium vector env's ``reset(seed=s)`` uses ``initial_reset_keys(jax.random.key(s), num_envs)``; pass
    them to the brax wrapper's ``reset`` to get the same episodes there.
    """
    return jax.random.split(jax.random.split(key)[0], num_envs)


def select_where(done, fresh, current):
    """``where(done, fresh, current)`` leafwise over two pytrees, ``done`` (batch...) broadcast over each leaf's
    trailing axes."""
    done = jnp.asarray(done, bool)

    def select(new, old):
        return jnp.where(jnp.reshape(done, done.shape + (1,) * (jnp.ndim(old) - done.ndim)), new, old)

    return jax.tree.map(select, fresh, current)


def restart_done(done, episode_keys, current, reset: Callable[[Any], Any], skip_if_none_done: bool = False):
    """The one auto-reset rule: where ``done``, replace ``current`` by ``reset(next_reset_key(episode_keys))``.

    Every auto-reset of the suite goes through here: ``auto_reset_step`` (and so ``make_rollout``), the
    Gymnasium vector env and the brax wrapper's ``EpisodicAutoResetWrapper``. So one reset key gives one
    sequence of episodes whichever of them runs it: copy ``i`` starts from its reset key, and each following
    episode from ``next_reset_key`` of the finished episode's ``EnvState.key``.

    Args:
        done: bool of shape ``()`` (one copy) or ``(N,)`` (a batch): where to start a new episode.
        episode_keys: the ``EnvState.key`` of the finished episodes, same leading shape as ``done``.
        current: a pytree whose leaves have ``done``'s shape as leading axes (e.g. ``(obs, EnvState)``).
        reset: ``reset(keys) -> pytree`` of ``current``'s structure for the new episodes (batched when ``done``
            is; e.g. ``jax.vmap(lambda k: env.reset(k, params))``).
        skip_if_none_done: batched only: skip the reset computation when no copy is done (``lax.cond``).
    """
    keys = jax.vmap(next_reset_key)(episode_keys) if jnp.ndim(done) else next_reset_key(episode_keys)
    if skip_if_none_done and jnp.ndim(done):
        fresh = jax.lax.cond(jnp.any(done), reset, lambda _: current, keys)
    else:
        fresh = reset(keys)
    return select_where(done, fresh, current)


def auto_reset_step(env: Env, state: EnvState, action, params: EnvParams, adversary=None) -> StepOutput:
    """``env.step``, then a fresh episode wherever it terminated or was truncated (``restart_done``).

    The reset key is ``next_reset_key(finished episode's key)``, so the whole sequence of episodes is still
    determined by the first reset key, and it is never one of the keys the steps drew noise from. The
    observation of the finished step is kept as ``info["final_obs"]`` (equal to ``obs`` where no reset
    happened); ``terminated``, ``truncated``, ``reward`` and the rest of ``info`` describe the finished step.
    """
    out = env.step(state, action, params, adversary)
    done = out.terminated | out.truncated
    obs, next_state = restart_done(done, out.state.key, (out.obs, out.state), lambda key: env.reset(key, params))
    return out._replace(obs=obs, state=next_state, info={**out.info, "final_obs": out.obs})


class Trajectory(NamedTuple):
    """A batched rollout; arrays are ``(num_steps, num_envs, ...)``.

    Attributes:
        obs, x: observation and physical state *before* each step (x of the state the action was taken in).
        action: the policy's actions. reward, cost, terminated, truncated, info: from ``Env.step``.
        final_state: ``EnvState`` after the last step, ``(num_envs, ...)``.
    """

    obs: Any
    x: Any
    action: Any
    reward: Any
    cost: Any
    terminated: Any
    truncated: Any
    info: dict
    final_state: EnvState


def make_rollout(
    env: Env,
    policy: Policy,
    num_envs: int,
    num_steps: int | None = None,
    auto_reset: bool = True,
    batched_params: bool = False,
    mesh=None,
):
    """Build a jitted ``rollout(key, params) -> Trajectory`` of ``num_envs`` copies.

    Args:
        env: the environment. policy: ``policy(obs, state, params, key) -> action`` for one copy.
        num_envs: number of parallel copies. num_steps: control steps (default: one episode).
        auto_reset: restart finished episodes (otherwise a finished copy keeps stepping past its end; its
            ``terminated``/``truncated`` flags tell where to cut).
        batched_params: ``params`` has a leading axis of size ``num_envs`` on every leaf (a sweep).
        mesh: a ``scg_jax.sharding.make_mesh`` mesh: the copies are laid out over its devices (``num_envs`` must
            divide evenly; batched ``params`` are then passed sharded, ``scg_jax.sharding.shard_batch``); ``None``:
            one device.

    Calling the returned function again with new keys or new params values of the same shapes does not
    retrace.
    """
    num_steps = env.num_steps if num_steps is None else int(num_steps)
    params_axis = 0 if batched_params else None
    step_fn = (lambda s, a, p: auto_reset_step(env, s, a, p)) if auto_reset else env.step

    def one_step(obs, state, params, key):
        action = policy(obs, state, params, key)
        out = step_fn(state, action, params)
        return out, action

    batched_step = jax.vmap(one_step, in_axes=(0, 0, params_axis, 0))
    batched_reset = jax.vmap(env.reset, in_axes=(0, params_axis))
    if mesh is not None:
        from scg_jax.sharding import check_divisible, constrain_batch

        check_divisible(num_envs, mesh)
    else:
        constrain_batch = lambda tree, mesh: tree  # noqa: E731

    @jax.jit
    def rollout(key, params: EnvParams) -> Trajectory:
        key_policy = jax.random.split(key)[1]  # [0] makes the reset keys (initial_reset_keys)
        obs, state = batched_reset(constrain_batch(initial_reset_keys(key, num_envs), mesh), params)

        def body(carry, step_key):
            obs, state = constrain_batch(carry, mesh)
            step_keys = constrain_batch(jax.random.split(step_key, num_envs), mesh)
            out, action = batched_step(obs, state, params, step_keys)
            record = (obs, state.x, action, out.reward, out.cost, out.terminated, out.truncated, out.info)
            return (out.obs, out.state), constrain_batch(record, mesh)

        (_, final_state), records = jax.lax.scan(body, (obs, state), jax.random.split(key_policy, num_steps))
        return Trajectory(*records, final_state=final_state)

    return rollout


def rollout(
    env: Env,
    params: EnvParams,
    policy: Policy,
    key,
    num_envs: int,
    num_steps: int | None = None,
    auto_reset: bool = True,
    batched_params: bool = False,
    mesh=None,
) -> Trajectory:
    """One-shot convenience for ``make_rollout(...)(key, params)``; reuse ``make_rollout`` in loops."""
    return make_rollout(env, policy, num_envs, num_steps, auto_reset, batched_params, mesh)(key, params)
