"""Batched rollouts: auto-reset keeps the final observation, sweeps over params, no retrace."""

import jax
import jax.numpy as jnp
import numpy as np

import scg_jax
from scg_jax.rollout import RESET_STREAM


def _hover(obs, state, params, key):
    return jnp.zeros(1)


def test_auto_reset_restarts_finished_episodes_and_keeps_the_final_observation():
    env = scg_jax.make("cartpole", episode_len_sec=0.2)  # 10 steps per episode
    rollout = scg_jax.make_rollout(env, _hover, num_envs=3, num_steps=25)
    traj = rollout(jax.random.key(0), env.default_params)
    truncated = np.asarray(traj.truncated)
    np.testing.assert_array_equal(np.flatnonzero(truncated[:, 0]), [9, 19])
    steps = np.asarray(traj.info["step"])
    np.testing.assert_array_equal(steps[:12, 0], [1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 1, 2])
    # At a reset the next pre-step observation is a fresh initial state, and final_obs keeps the old one.
    final_obs, obs = np.asarray(traj.info["final_obs"]), np.asarray(traj.obs)
    assert not np.allclose(final_obs[9], obs[10])
    np.testing.assert_array_equal(final_obs[8], obs[9])
    assert np.all(np.abs(obs[10]) <= 0.05)
    # The new episodes differ from the first (different reset keys) and from each other across copies.
    assert not np.allclose(obs[0], obs[10])


def test_rollout_is_deterministic_and_does_not_retrace():
    traces = []

    def policy(obs, state, params, key):
        traces.append(1)
        return jax.random.uniform(key, (1,), minval=-1.0, maxval=1.0)

    env = scg_jax.make("cartpole")
    rollout = scg_jax.make_rollout(env, policy, num_envs=4, num_steps=30)
    params = env.default_params
    a = rollout(jax.random.key(1), params)
    b = rollout(jax.random.key(1), params)
    c = rollout(jax.random.key(2), params.replace(Q=2.0 * params.Q))
    np.testing.assert_array_equal(np.asarray(a.x), np.asarray(b.x))
    assert not np.allclose(np.asarray(a.x), np.asarray(c.x))
    assert len(traces) == 1


def test_batched_params_sweep_over_copies():
    env = scg_jax.make("quadrotor_1d", init_state=[1.0, 0.0])

    def hover_nominal(obs, state, params, key):
        return jnp.asarray(env.system.equilibrium_input(env.default_params.physics))

    base = env.default_params
    masses = jnp.array([0.024, 0.027, 0.030])
    sweep = jax.vmap(lambda m: base.replace(physics=base.physics.replace(mass=m)))(masses)
    traj = scg_jax.rollout(env, sweep, hover_nominal, jax.random.key(0), num_envs=3, num_steps=10, batched_params=True)
    z_dot = np.asarray(traj.final_state.x[:, 1])
    # Nominal hover thrust on a lighter (heavier) plant accelerates it up (down): a = T / m - g, exactly.
    expected = (0.027 * 9.8 / np.asarray(masses) - 9.8) * 10 * env.dt
    np.testing.assert_allclose(z_dot, expected, rtol=1e-4, atol=1e-6)


def test_the_reset_key_of_the_next_episode_is_none_of_the_step_noise_keys():
    env = scg_jax.make("cartpole", episode_len_sec=0.1)
    key = jax.random.key(0)
    _, state = env.reset(key, env.default_params)
    reset_key = jax.random.key_data(jax.random.fold_in(state.key, RESET_STREAM))
    noise_keys = jax.vmap(lambda k: jax.random.key_data(jax.random.fold_in(state.key, k)))(jnp.arange(1000))
    assert not np.any(np.all(np.asarray(noise_keys) == np.asarray(reset_key), axis=1))
    # The old choice collided with step 0's noise key.
    np.testing.assert_array_equal(jax.random.key_data(jax.random.split(state.key)[0]), noise_keys[0])
