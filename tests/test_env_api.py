"""The functional env's Python API: the three adversary channels, action shape errors, NaN actions, checked params."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import scg_jax

HOVER = 0.1323  # 2D quadrotor hover per input: far from both actuator limits, so nothing is saturated
ADVERSARY = jnp.array([0.5, -3.0])  # the second entry is clipped to -1


def _step_pair(channel, scale, adversary=ADVERSARY):
    """One step of the 2D quadrotor with and without an adversary on ``channel``, from the same state."""
    env = scg_jax.make("quadrotor_2d", adversary={"channel": channel, "scale": scale})
    params = env.default_params
    _, state = env.reset(jax.random.key(3), params)
    action = jnp.full(2, HOVER)
    step = jax.jit(env.step)
    return env, params, state, step(state, action, params, adversary), step(state, action, params, 0 * adversary)


def test_action_adversary_adds_scaled_input_and_moves_the_plant_accordingly():
    env, params, state, out, free = _step_pair("action", [0.01, 0.02])
    expected = np.array([0.005, -0.02])  # scale * clip(adversary, -1, 1), N
    np.testing.assert_allclose(np.asarray(out.info["u_cmd"]), [HOVER, HOVER], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(out.info["u"] - free.info["u"]), expected, rtol=1e-4)
    x_expected = env.integrate(state.x, jnp.full(2, HOVER) + expected, state.physics)
    np.testing.assert_allclose(np.asarray(out.state.x), np.asarray(x_expected), rtol=1e-5, atol=1e-7)
    assert not np.allclose(np.asarray(out.state.x), np.asarray(free.state.x))
    np.testing.assert_array_equal(np.asarray(out.obs), np.asarray(out.state.x))  # nothing on the observation


def test_observation_adversary_shifts_the_observation_only():
    adversary = jnp.tile(ADVERSARY, 3)  # the observation channel has nx = 6 entries
    env, params, state, out, free = _step_pair("observation", [0.1, 0.2, 0.3, 0.4, 0.5, 0.6], adversary)
    expected = np.array([0.05, -0.2, 0.15, -0.4, 0.25, -0.6])  # scale * clip(adversary, -1, 1)
    np.testing.assert_allclose(np.asarray(out.obs - out.state.x), expected, rtol=1e-5, atol=1e-7)
    np.testing.assert_array_equal(np.asarray(out.state.x), np.asarray(free.state.x))  # the plant is untouched
    np.testing.assert_array_equal(np.asarray(out.info["u"]), np.asarray(free.info["u"]))
    np.testing.assert_array_equal(np.asarray(free.obs), np.asarray(free.state.x))


def test_observation_adversary_leaves_appended_reference_points_exact():
    env = scg_jax.make("quadrotor_1d", obs_goal_horizon=2, adversary={"channel": "observation", "scale": 0.5})
    params = env.default_params
    _, state = env.reset(jax.random.key(0), params)
    out = env.step(state, jnp.full(1, 0.2646), params, adversary=jnp.array([1.0, -0.2]))
    np.testing.assert_allclose(np.asarray(out.obs[:2] - out.state.x), [0.5, -0.1], rtol=1e-5)
    np.testing.assert_array_equal(np.asarray(out.obs[2:]), np.asarray(env.observe(out.state, params)[2:]))


def test_dynamics_adversary_is_the_external_force_of_the_step():
    env, params, state, out, free = _step_pair("dynamics", [0.002, 0.001])
    expected = np.array([0.001, -0.001])
    np.testing.assert_allclose(np.asarray(out.info["f_ext"]), expected, rtol=1e-6)
    x_expected = env.integrate(state.x, jnp.full(2, HOVER), state.physics, jnp.asarray(expected, jnp.float32))
    np.testing.assert_allclose(np.asarray(out.state.x), np.asarray(x_expected), rtol=1e-5, atol=1e-7)
    assert not np.allclose(np.asarray(out.state.x), np.asarray(free.state.x))
    np.testing.assert_array_equal(np.asarray(out.info["u"]), np.asarray(free.info["u"]))


def test_adversary_of_the_wrong_shape_names_the_channel_dimension():
    env = scg_jax.make("quadrotor_2d", adversary={"channel": "observation", "scale": 1.0})
    params = env.default_params
    _, state = env.reset(jax.random.key(0), params)
    with pytest.raises(ValueError, match=r"adversary: expected shape \(6,\) for the 'observation' channel"):
        env.step(state, jnp.full(2, HOVER), params, adversary=jnp.zeros(2))


@pytest.mark.parametrize(
    ("system", "action", "shape"),
    [
        ("cartpole", np.zeros(2), r"\(2,\)"),
        ("cartpole", np.zeros((1, 1)), r"\(1, 1\)"),
        ("cartpole", [0.0, 1.0], r"\(2,\)"),
        ("cartpole", 0.5, r"\(\)"),
        ("quadrotor_2d", np.full(4, HOVER), r"\(4,\)"),
    ],
)
def test_step_rejects_an_action_of_the_wrong_shape_naming_nu(envs, system, action, shape):
    env = envs[system]
    params = env.default_params
    _, state = env.reset(jax.random.key(0), params)
    nu = env.nu
    with pytest.raises(ValueError, match=rf"action: expected shape \({nu},\) \(nu = {nu}: .*got shape {shape}"):
        env.step(state, action, params)
    with pytest.raises(ValueError, match=rf"nu = {nu}"):
        jax.jit(env.step)(state, jnp.asarray(action), params)


def test_step_accepts_a_list_of_the_right_length_and_checks_per_copy_shape_under_vmap(envs):
    env = envs["cartpole"]
    params = env.default_params
    _, state = env.reset(jax.random.key(0), params)
    np.testing.assert_array_equal(
        np.asarray(env.step(state, [0.3], params).state.x),
        np.asarray(env.step(state, jnp.array([0.3]), params).state.x),
    )
    batched = jax.vmap(env.step, in_axes=(None, 0, None))
    assert batched(state, jnp.zeros((5, 1)), params).state.x.shape == (5, 4)
    with pytest.raises(ValueError, match=r"nu = 1.*got shape \(2,\)"):
        batched(state, jnp.zeros((5, 2)), params)


def test_nan_action_ends_the_episode_with_finite_reward_and_cost():
    constraint = {"type": "abs_bound", "on": "input", "bound": 5.0}
    for reward_type in ("quadratic", "exponential"):
        env = scg_jax.make("cartpole", reward_type=reward_type, constraints=[constraint])
        params = env.default_params
        _, state = env.reset(jax.random.key(0), params)
        out = jax.jit(env.step)(state, jnp.array([jnp.nan]), params)
        assert bool(out.terminated) and bool(out.info["nonfinite"]) and not bool(out.truncated)
        np.testing.assert_array_equal(np.asarray(out.state.x), np.asarray(state.x))  # last finite state kept
        # c = 1/2 e^T Q e + 1/2 R * (worst admissible |u - u_ref| = 10 N)^2
        error = np.asarray(state.x) - np.asarray(params.goal)
        c = 0.5 * error @ np.asarray(params.Q) @ error + 0.5 * float(params.R[0, 0]) * 10.0**2
        expected = -c if reward_type == "quadratic" else np.exp(-c)
        assert np.isfinite(float(out.reward))
        np.testing.assert_allclose(float(out.reward), expected, rtol=1e-5)
        assert float(out.cost) == 1.0 and bool(out.info["constraint_violation"])


def test_nan_action_without_constraints_costs_nothing_and_the_reward_is_finite(envs):
    env = envs["quadrotor_2d"]
    params = env.default_params
    _, state = env.reset(jax.random.key(0), params)
    out = env.step(state, jnp.array([jnp.nan, HOVER]), params)
    assert bool(out.terminated) and np.isfinite(float(out.reward)) and float(out.cost) == 0.0
    assert np.isnan(np.asarray(out.info["u"])[0])  # info reports the input as applied


def test_with_physics_checks_names_and_values_and_replace_is_unchecked(envs):
    env = envs["cartpole"]
    params = env.default_params
    longer = env.with_physics(params, pole_half_length=0.7)
    assert float(longer.physics.pole_half_length) == pytest.approx(0.7)
    assert float(longer.physics.cart_mass) == float(params.physics.cart_mass)
    with pytest.raises(
        ValueError, match=r"^physics.pole_mass: must be a positive finite number for cartpole, got -0.1$"
    ):
        env.with_physics(params, pole_mass=-0.1)
    with pytest.raises(
        ValueError,
        match=r"^physics.pole_mas: unknown parameter of cartpole; allowed parameters are cart_mass, .* "
        r"\(did you mean 'pole_mass'\?\)$",
    ):
        env.with_physics(params, pole_mas=0.1)
    sweep = env.with_physics(params, pole_half_length=jnp.linspace(0.3, 0.9, 4))
    assert sweep.physics.pole_half_length.shape == (4,)
    with pytest.raises(ValueError, match=r"physics.pole_half_length: .*got \[0.3.*, -0.1.*\]"):
        env.with_physics(params, pole_half_length=jnp.array([0.3, -0.1]))
    raw = params.replace(physics=params.physics.replace(pole_mass=jnp.asarray(-0.1)))  # raw replace: unchecked
    with pytest.raises(ValueError, match=r"physics.pole_mass: must be a positive finite number for cartpole"):
        env.validate(raw)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda p: p.replace(Q=-p.Q), r"params.Q: must be symmetric positive semidefinite"),
        (lambda p: p.replace(R=jnp.zeros((2, 2))), r"params.R: expected shape \(1, 1\)"),
        (lambda p: p.replace(goal_tolerance=jnp.asarray(0.0)), r"params.goal_tolerance: must be positive"),
        (lambda p: p.replace(violation_penalty=jnp.asarray(-1.0)), r"params.violation_penalty: must be finite"),
        (lambda p: p.replace(goal=jnp.full(4, jnp.nan)), r"params.goal: must be finite"),
        (lambda p: p.replace(constraints=(1,)), r"params: structure differs from env.default_params"),
    ],
)
def test_validate_names_the_field(envs, change, message):
    env = envs["cartpole"]
    assert env.validate(env.default_params) is not None
    with pytest.raises(ValueError, match=message):
        env.validate(change(env.default_params))


def test_validate_accepts_batched_params_and_refuses_traced_ones(envs):
    env = envs["quadrotor_2d"]
    params = env.default_params
    batched = jax.tree.map(lambda leaf: jnp.stack([leaf, leaf]), params)
    assert env.validate(batched) is batched
    with pytest.raises(ValueError, match="validate needs concrete values; call it outside jit"):
        jax.jit(env.validate)(params)
