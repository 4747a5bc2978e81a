"""The functional environment: determinism, vmap sweeps without retrace, episode ends, rewards, observations."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import scg_jax


def _scan_rollout(env, steps):
    """A jitted single-copy rollout under a key-driven random physical input, returning the states."""

    def run(key, params):
        obs, state = env.reset(key, params)
        u_low, u_high = env.input_bounds(params.physics)

        def body(state, k):
            action = jax.random.uniform(k, (env.nu,), minval=u_low, maxval=u_high)
            out = env.step(state, action, params)
            return out.state, out.state.x

        _, xs = jax.lax.scan(body, state, jax.random.split(jax.random.fold_in(key, 1), steps))
        return xs

    return jax.jit(run)


def test_same_key_same_trajectory_bitwise_and_different_keys_differ(envs):
    env = envs["quadrotor_3d"]
    run = _scan_rollout(env, 50)
    params = env.default_params
    a, b = run(jax.random.key(7), params), run(jax.random.key(7), params)
    c = run(jax.random.key(8), params)
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert not np.allclose(np.asarray(a), np.asarray(c))
    x0 = jax.vmap(lambda k: env.reset(k, params)[1].x)(jax.random.split(jax.random.key(0), 16))
    assert len({tuple(np.asarray(row).round(7)) for row in x0}) == 16
    low, high = np.asarray(params.init_state.low), np.asarray(params.init_state.high)
    assert np.all(np.asarray(x0) >= low) and np.all(np.asarray(x0) <= high)


def test_vmap_over_eight_pole_lengths_gives_eight_trajectories_without_retracing(envs):
    env = envs["cartpole"]
    traces = []

    def run(params):
        traces.append(1)
        obs, state = env.reset(jax.random.key(0), params)  # same initial state for every copy
        state = state.replace(x=jnp.array([0.0, 0.0, 0.1, 0.0], dtype=state.x.dtype))

        def body(state, _):
            return env.step(state, jnp.zeros(1), params).state, state.x[2]

        return jax.lax.scan(body, state, None, 25)[1]

    sweep = jax.jit(jax.vmap(run))
    base = env.default_params

    def with_lengths(lengths):
        return jax.vmap(lambda l: base.replace(physics=base.physics.replace(pole_half_length=l)))(lengths)

    lengths = jnp.linspace(0.3, 1.0, 8)
    thetas = np.asarray(sweep(with_lengths(lengths)))
    assert thetas.shape == (8, 25)  # vmap over the 8 lengths of a 25-step scan
    final = thetas[:, -1]
    assert len(np.unique(final.round(6))) == 8
    assert np.all(np.diff(final) < 0)  # a longer pole falls more slowly
    sweep(with_lengths(jnp.linspace(0.4, 1.2, 8)))
    assert len(traces) == 1


def test_truncation_at_the_time_limit_and_no_termination_at_equilibrium():
    env = scg_jax.make("cartpole", episode_len_sec=1.0, init_state=[0, 0, 0, 0])
    params = env.default_params
    _, state = env.reset(jax.random.key(0), params)
    step = jax.jit(env.step)
    for k in range(1, env.num_steps + 1):
        out = step(state, jnp.zeros(1), params)
        state = out.state
        assert not bool(out.terminated)
        assert bool(out.truncated) == (k == env.num_steps)
        assert int(out.info["step"]) == k
    assert env.num_steps == 50


def test_pushing_the_cart_terminates_out_of_bounds_not_truncated(jitted_step, envs):
    env = envs["cartpole"]
    params = env.default_params
    _, state = env.reset(jax.random.key(1), params)
    steps = 0
    while steps < env.num_steps:
        out = jitted_step["cartpole"](state, jnp.full(1, 10.0), params)
        state, steps = out.state, steps + 1
        if bool(out.terminated):
            break
    assert bool(out.info["out_of_bounds"]) and not bool(out.truncated)
    assert abs(float(state.x[2])) > np.pi / 2 or abs(float(state.x[0])) > 2.4
    assert steps < env.num_steps


def test_non_finite_state_ends_the_episode_with_a_flag_and_keeps_the_last_finite_state(jitted_step, envs):
    env = envs["quadrotor_2d"]
    params = env.default_params
    _, state = env.reset(jax.random.key(2), params)
    out = jitted_step["quadrotor_2d"](state, jnp.array([jnp.nan, 0.1]), params)
    assert bool(out.terminated) and bool(out.info["nonfinite"])
    np.testing.assert_array_equal(np.asarray(out.state.x), np.asarray(state.x))
    assert np.all(np.isfinite(np.asarray(out.obs)))


@pytest.mark.parametrize("name", ["cartpole", "quadrotor_1d", "quadrotor_2d", "quadrotor_3d"])
def test_an_infinite_or_nan_action_ends_the_episode_like_a_non_finite_state(jitted_step, envs, name):
    """+inf, -inf and NaN in one input entry end the episode on every system (saturation does not turn +-inf into
    the actuator limit, which would let the episode go on): the state is kept, and the reward charges that entry
    as the worst admissible input, c = 1/2 e'Qe + 1/2 R_00 max(|u_low - u_ref|, |u_high - u_ref|)^2."""
    env, step = envs[name], jitted_step[name]
    params = env.default_params
    _, state = env.reset(jax.random.key(3), params)
    x_ref, u_ref = (np.asarray(a, dtype=np.float64) for a in env.reference_at(0, params))
    u_low, u_high = (np.asarray(a, dtype=np.float64) for a in env.input_bounds(params.physics))
    error = np.asarray(state.x, dtype=np.float64) - np.asarray(env.reference_at(1, params)[0], dtype=np.float64)
    worst = max(abs(u_low[0] - u_ref[0]), abs(u_high[0] - u_ref[0]))
    c = 0.5 * error @ np.asarray(params.Q) @ error + 0.5 * float(params.R[0, 0]) * worst**2
    assert env.reward_type == "quadratic"
    for bad in (np.inf, -np.inf, np.nan):
        action = u_ref.copy()
        action[0] = bad
        out = step(state, jnp.asarray(action, dtype=state.x.dtype), params)
        assert bool(out.terminated) and bool(out.info["nonfinite"]) and not bool(out.truncated), bad
        np.testing.assert_array_equal(np.asarray(out.state.x), np.asarray(state.x))
        np.testing.assert_allclose(float(out.reward), -c, rtol=1e-5)
        assert float(out.cost) == 0.0 and np.all(np.isfinite(np.asarray(out.obs)))
    # The actuator limit itself is an admissible action: the episode goes on, charged its own finite input term.
    at_limit = u_ref.copy()
    at_limit[0] = u_high[0]
    out = step(state, jnp.asarray(at_limit, dtype=state.x.dtype), params)
    assert not bool(out.terminated) and not bool(out.info["nonfinite"])


@pytest.mark.parametrize("name", ["cartpole", "quadrotor_1d", "quadrotor_2d", "quadrotor_3d"])
def test_normalized_actions_convert_both_ways(name):
    env = scg_jax.make(name, action_mode="normalized")
    params = env.default_params
    action = jnp.linspace(-1.0, 1.0, env.nu)
    u = env.action_to_input(action, params)
    np.testing.assert_allclose(np.asarray(env.input_to_action(u, params)), np.asarray(action), atol=1e-6)
    if name == "cartpole":
        np.testing.assert_allclose(np.asarray(u), 10.0 * np.asarray(action))
    else:
        hover = np.asarray(env.system.equilibrium_input(params.physics))
        np.testing.assert_allclose(np.asarray(u), hover * (1 + 0.1 * np.asarray(action)), rtol=1e-6)


def test_rewards_match_a_hand_computation():
    for reward_type in ("quadratic", "exponential"):
        env = scg_jax.make(
            "quadrotor_2d", "tracking", reward_type=reward_type, Q=[1, 0.1, 2, 0.1, 0.5, 0.1], R=[3.0, 4.0]
        )
        params = env.default_params
        _, state = env.reset(jax.random.key(3), params)
        u = jnp.array([0.12, 0.15])
        out = env.step(state, u, params)
        x_ref, u_ref = env.reference(params)
        e = np.asarray(out.state.x) - np.asarray(x_ref[1])
        du = np.asarray(u) - np.asarray(u_ref[0])
        c = 0.5 * e @ np.diag([1, 0.1, 2, 0.1, 0.5, 0.1]) @ e + 0.5 * du @ np.diag([3.0, 4.0]) @ du
        expected = -c if reward_type == "quadratic" else np.exp(-c)
        np.testing.assert_allclose(float(out.reward), expected, rtol=1e-5)
        np.testing.assert_allclose(float(out.info["mse"]), e[0] ** 2 + e[2] ** 2, rtol=1e-5)


def test_upright_reward_counts_steps_inside_the_bounds():
    env = scg_jax.make("cartpole", reward_type="upright", init_state=[0, 0, 1.5, 0])
    params = env.default_params
    _, state = env.reset(jax.random.key(0), params)
    rewards, ended = [], False
    while not ended:
        out = env.step(state, jnp.zeros(1), params)
        rewards.append(float(out.reward))
        state, ended = out.state, bool(out.terminated)
    assert rewards[-1] == 0.0 and all(r == 1.0 for r in rewards[:-1]) and len(rewards) > 1


def test_observation_appends_the_next_reference_points_clamped_at_the_end():
    env = scg_jax.make("cartpole", "tracking", obs_goal_horizon=3, episode_len_sec=1.0)
    params = env.default_params
    obs, state = env.reset(jax.random.key(0), params)
    x_ref, _ = env.reference(params)
    assert obs.shape == (env.observation_size,) == (16,)
    np.testing.assert_allclose(np.asarray(obs[4:]).reshape(3, 4), np.asarray(x_ref[1:4]), atol=1e-6)
    late = state.replace(step=jnp.int32(env.num_steps - 1))
    late_obs = env.observe(late, params)
    np.testing.assert_allclose(np.asarray(late_obs[4:]).reshape(3, 4), np.asarray(x_ref)[[50, 50, 50]], atol=1e-6)


def test_goal_reached_ends_the_episode_when_asked():
    goal = [0.0, 0.0, 1.0, 0.0, 0.0, 0.0]
    env = scg_jax.make("quadrotor_2d", done_on_goal=True, init_state=goal)
    params = env.default_params
    _, state = env.reset(jax.random.key(0), params)
    out = env.step(state, jnp.asarray(env.system.equilibrium_input(params.physics)), params)
    assert bool(out.info["goal_reached"]) and bool(out.terminated) and not bool(out.info["out_of_bounds"])
    far = scg_jax.make("quadrotor_2d", done_on_goal=True)
    far_params = far.default_params
    _, state = far.reset(jax.random.key(0), far_params)
    out = far.step(state, jnp.asarray(env.system.equilibrium_input(params.physics)), far_params)
    assert not bool(out.info["goal_reached"]) and not bool(out.terminated)


def test_float32_by_default(envs):
    env = envs["cartpole"]
    obs, state = env.reset(jax.random.key(0), env.default_params)
    assert obs.dtype == jnp.float32 and state.x.dtype == jnp.float32
