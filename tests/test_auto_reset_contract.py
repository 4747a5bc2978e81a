"""One auto-reset: the same key gives the same episodes through make_rollout, the Gymnasium vector env and brax."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import scg_jax
from scg_jax.adapters import brax as brax_adapter
from scg_jax.adapters import gymnasium as gymnasium_adapter
from scg_jax.rollout import initial_reset_keys, next_reset_key

NUM_ENVS, NUM_STEPS, SEED = 6, 70, 5
OPTIONS = {"action_mode": "normalized", "episode_len_sec": 0.6}  # 30 steps per episode


def _action(obs):
    # Destabilising with a bias: copies fall over (terminate) at different steps, some reach the time limit.
    return jnp.clip(jnp.tanh(-3.0 * obs[..., 2:3]) + 0.6 * jnp.sign(obs[..., 0:1]) + 0.4, -1.0, 1.0) * 0.8


@pytest.fixture(scope="module")
def functional_run():
    vector_env = gymnasium_adapter.ScgVectorEnv(NUM_ENVS, "cartpole", autoreset_mode="same_step", **OPTIONS)
    env, params = vector_env.functional_env, vector_env.params
    traj = scg_jax.make_rollout(env, lambda obs, state, p, key: _action(obs), NUM_ENVS, NUM_STEPS)(
        jax.random.key(SEED), params
    )
    return vector_env, env, params, traj


def _episode_starts(terminated, truncated):
    """(step, copy) pairs where a new episode starts after the step."""
    return sorted(zip(*np.nonzero(np.asarray(terminated) | np.asarray(truncated)), strict=True))


def test_the_functional_rollout_has_both_kinds_of_episode_end(functional_run):
    _, env, params, traj = functional_run
    terminated, truncated = np.asarray(traj.terminated), np.asarray(traj.truncated)
    assert terminated.sum() >= NUM_ENVS and truncated.sum() >= 1
    # The first episode of copy i starts from initial_reset_keys(key, N)[i]; the next from next_reset_key of it.
    keys = initial_reset_keys(jax.random.key(SEED), NUM_ENVS)
    _, first = jax.vmap(env.reset, in_axes=(0, None))(keys, params)
    # To a few float32 ulps, not bit for bit: the rollout's reset is fused into its compiled loop and these resets
    # run on their own, so XLA may round them differently (seen in CI: 3.7e-9 apart); another key's state would be
    # about 1e-2 away (initial states are uniform in +-0.05).
    np.testing.assert_allclose(np.asarray(traj.x[0]), np.asarray(first.x), rtol=1e-6, atol=1e-8)
    step, copy = _episode_starts(traj.terminated, traj.truncated)[0]
    _, second = env.reset(next_reset_key(first.key[copy]), params)
    np.testing.assert_allclose(np.asarray(traj.x[step + 1, copy]), np.asarray(second.x), rtol=1e-6, atol=1e-8)


def test_gymnasium_vector_env_replays_the_functional_rollout(functional_run):
    vector_env, env, params, traj = functional_run
    obs, _ = vector_env.reset(seed=SEED)
    xs, terminated, truncated = [], [], []
    for _ in range(NUM_STEPS):
        xs.append(np.asarray(vector_env.state.x))
        obs, _, term, trunc, _ = vector_env.step(np.asarray(_action(jnp.asarray(obs))))
        terminated.append(term)
        truncated.append(trunc)
    np.testing.assert_array_equal(np.array(terminated), np.asarray(traj.terminated))
    np.testing.assert_array_equal(np.array(truncated), np.asarray(traj.truncated))
    np.testing.assert_allclose(np.array(xs), np.asarray(traj.x), rtol=1e-5, atol=1e-6)


def test_gymnasium_next_step_mode_has_the_same_episode_sequence(functional_run):
    """NEXT_STEP spends one extra call per reset, but copy i's episodes start from the same states."""
    vector_env, env, params, traj = functional_run
    next_step = gymnasium_adapter.ScgVectorEnv(NUM_ENVS, "cartpole", **OPTIONS)
    obs, _ = next_step.reset(seed=SEED)
    starts = [[np.asarray(next_step.state.x[i])] for i in range(NUM_ENVS)]
    previous_done = np.zeros(NUM_ENVS, bool)
    for _ in range(NUM_STEPS + 10):
        obs, _, term, trunc, _ = next_step.step(np.asarray(_action(jnp.asarray(obs))))
        for i in np.flatnonzero(previous_done):  # this call ignored the action and started a new episode
            starts[i].append(np.asarray(next_step.state.x[i]))
        previous_done = term | trunc
    expected = [[np.asarray(traj.x[0, i])] for i in range(NUM_ENVS)]
    for step, copy in _episode_starts(traj.terminated, traj.truncated):
        if step + 1 < NUM_STEPS:
            expected[copy].append(np.asarray(traj.x[step + 1, copy]))
    for i in range(NUM_ENVS):
        assert len(starts[i]) >= len(expected[i])
        np.testing.assert_allclose(np.array(starts[i][: len(expected[i])]), np.array(expected[i]), atol=1e-6)


def test_brax_wrapper_replays_the_functional_rollout(functional_run):
    _, env, params, traj = functional_run
    wrapped = brax_adapter.wrap_for_training(brax_adapter.BraxEnv(env, params), episode_length=env.num_steps)
    state = jax.jit(wrapped.reset)(initial_reset_keys(jax.random.key(SEED), NUM_ENVS))
    step = jax.jit(wrapped.step)
    xs, terminated, truncated = [], [], []
    for _ in range(NUM_STEPS):
        xs.append(np.asarray(state.pipeline_state.x))
        state = step(state, _action(state.obs))
        truncation = np.asarray(state.info["truncation"]) > 0
        done = np.asarray(state.done) > 0
        terminated.append(done & ~truncation)
        truncated.append(truncation)
    np.testing.assert_array_equal(np.array(terminated), np.asarray(traj.terminated))
    np.testing.assert_array_equal(np.array(truncated), np.asarray(traj.truncated))
    np.testing.assert_allclose(np.array(xs), np.asarray(traj.x), rtol=1e-5, atol=1e-6)
