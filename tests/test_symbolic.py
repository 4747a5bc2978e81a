"""The CasADi mirror against the JAX environment: whole rollouts, discretisation options, cost derivatives."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import scg_jax

from .conftest import SYSTEM_NAMES


@pytest.mark.parametrize("name", SYSTEM_NAMES)
@pytest.mark.parametrize("integrator", ["rk4", "semi_implicit_euler"])
def test_one_second_of_env_steps_equals_repeated_model_fd(name, integrator):
    env = scg_jax.make(name, integrator=integrator, ctrl_freq=50, physics_freq=500)
    with jax.enable_x64(True):
        params = env.default_params
        model = env.symbolic_model(params)
        _, state = env.reset(jax.random.key(4), params)
        u_eq = np.asarray(env.system.equilibrium_input(params.physics))
        u_low, u_high = (np.asarray(b) for b in env.input_bounds(params.physics))
        step = jax.jit(env.step)
        x_model = np.asarray(state.x)
        for k in range(env.ctrl_freq):  # 1 s
            # A varying input inside the actuator limits, so clipping plays no part.
            u = np.clip(u_eq + 0.05 * (u_high - u_low) * np.sin(0.3 * k + np.arange(env.nu)), u_low, u_high)
            state = step(state, jnp.asarray(u), params).state
            x_model = np.asarray(model.fd(x_model, u)).ravel()
        assert state.x.dtype == jnp.float64
    np.testing.assert_allclose(np.asarray(state.x), x_model, rtol=1e-9, atol=1e-9)
    assert np.abs(x_model - np.asarray(env.reset(jax.random.key(4), env.default_params)[1].x)).max() > 1e-3


def test_rk4_discretisation_is_one_step_of_length_dt():
    env = scg_jax.make("cartpole", ctrl_freq=15, physics_freq=750)
    params = env.default_params
    model = env.symbolic_model(params, discretization="rk4")
    x, u = np.array([0.1, -0.2, 0.15, 0.3]), np.array([2.0])
    f = lambda x: np.asarray(model.fc(x, u)).ravel()  # noqa: E731
    dt = 1 / 15
    k1 = f(x)
    k2 = f(x + dt / 2 * k1)
    k3 = f(x + dt / 2 * k2)
    k4 = f(x + dt * k3)
    np.testing.assert_allclose(np.asarray(model.fd(x, u)).ravel(), x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4), rtol=1e-12)
    # With 50 RK4 substeps the env's own discretisation differs from one coarse step, but only slightly.
    fine = np.asarray(env.symbolic_model(params).fd(x, u)).ravel()
    assert 1e-9 < np.abs(fine - np.asarray(model.fd(x, u)).ravel()).max() < 1e-3


def test_cost_and_its_derivatives_match_the_closed_form():
    env = scg_jax.make("quadrotor_2d", Q=[1, 2, 3, 4, 5, 6], R=[0.5, 0.25])
    model = env.symbolic_model(env.default_params)
    rng = np.random.default_rng(0)
    x, u, xr, ur = rng.normal(size=6), rng.normal(size=2), rng.normal(size=6), rng.normal(size=2)
    Q, R = np.diag([1, 2, 3, 4, 5, 6.0]), np.diag([0.5, 0.25])
    l, l_x, l_u, l_xx, l_uu, l_xu = (np.asarray(v) for v in model.cost(x, u, xr, ur))
    np.testing.assert_allclose(l.item(), 0.5 * (x - xr) @ Q @ (x - xr) + 0.5 * (u - ur) @ R @ (u - ur), rtol=1e-6)
    np.testing.assert_allclose(l_x.ravel(), Q @ (x - xr), rtol=1e-6)
    np.testing.assert_allclose(l_u.ravel(), R @ (u - ur), rtol=1e-6)
    np.testing.assert_allclose(l_xx, Q, rtol=1e-6)
    np.testing.assert_allclose(l_uu, R, rtol=1e-6)
    np.testing.assert_allclose(l_xu, np.zeros((6, 2)))


def test_model_carries_sizes_period_and_reference():
    env = scg_jax.make("quadrotor_3d", "tracking", ctrl_freq=25, episode_len_sec=2.0)
    params = env.default_params
    model = env.symbolic_model(params)
    x_ref, u_ref = env.reference(params)
    assert (model.nx, model.nu, model.dt) == (12, 4, 0.04)
    np.testing.assert_allclose(model.x_ref, np.asarray(x_ref), atol=2e-6)
    np.testing.assert_allclose(model.u_ref, np.asarray(u_ref), rtol=1e-6)
    assert model.x_ref.shape == (51, 12) and model.u_ref.shape == (50, 4)


def test_prior_parameters_change_the_model_and_batched_params_are_refused():
    env = scg_jax.make("cartpole")
    params = env.default_params
    heavy = params.replace(physics=params.physics.replace(pole_mass=params.physics.pole_mass * 1.5))
    x, u = np.array([0.0, 0.0, 0.2, 0.0]), np.array([1.0])
    nominal = np.asarray(env.symbolic_model(params).fc(x, u)).ravel()
    heavier = np.asarray(env.symbolic_model(heavy).fc(x, u)).ravel()
    np.testing.assert_array_equal(nominal[[0, 2]], heavier[[0, 2]])  # velocities are states: unchanged
    assert np.all(np.abs(nominal[[1, 3]] - heavier[[1, 3]]) > 1e-3 * np.abs(nominal[[1, 3]]))  # accelerations
    batched = jax.vmap(lambda m: params.replace(physics=params.physics.replace(cart_mass=m)))(jnp.ones(3))
    with pytest.raises(ValueError, match="params.physics.cart_mass must be a scalar"):
        env.symbolic_model(batched)
    with pytest.raises(ValueError, match="discretization: unknown value 'zoh'; allowed values are env, rk4"):
        env.symbolic_model(params, discretization="zoh")


@pytest.mark.parametrize("name", ["cartpole", "quadrotor_3d"])
def test_evaluate_fc_and_fd_take_rollout_arrays_and_match_the_jax_dynamics(name):
    with jax.enable_x64(True):
        env = scg_jax.make(name, episode_len_sec=0.4)
        params = env.default_params
        u_low, u_high = env.input_bounds(params.physics)

        def policy(obs, state, p, key):
            return jax.random.uniform(key, (env.nu,), minval=u_low, maxval=u_high, dtype=u_low.dtype)

        traj = scg_jax.rollout(env, params, policy, jax.random.key(2), num_envs=3, auto_reset=False)  # (T, N, .)
        xs, us = np.asarray(traj.x), np.asarray(traj.info["u"])
        model = env.symbolic_model(params)
        physics = params.physics
        x_dot = jax.vmap(jax.vmap(lambda x, u: env.system.dynamics(x, u, physics, scg_jax.backends.jax_backend)))
        np.testing.assert_allclose(model.evaluate_fc(xs, us), np.asarray(x_dot(xs, us)), rtol=1e-9, atol=1e-9)
        x_next = model.evaluate_fd(xs, us)
        assert x_next.shape == xs.shape
        np.testing.assert_allclose(x_next[:-1], xs[1:], rtol=1e-9, atol=1e-9)  # no reset: step on step
        # A trajectory (T, nx) with (T, nu), CasADi's own map (columns are points) and one point agree.
        mapped = np.asarray(model.fc.map(len(xs))(xs[:, 0].T, us[:, 0].T)).T
        np.testing.assert_allclose(model.evaluate_fc(xs[:, 0], us[:, 0]), mapped, rtol=1e-12)
        np.testing.assert_allclose(model.evaluate_fc(xs[0, 0], us[0, 0]), mapped[0], rtol=1e-12)
        # Many states with one input broadcast.
        one_u = model.evaluate_fd(xs[:, 0], us[0, 0])
        np.testing.assert_allclose(one_u[1], np.asarray(model.fd(xs[1, 0], us[0, 0])).ravel(), rtol=1e-12)


def test_evaluate_fc_names_the_size_it_expects():
    model = scg_jax.make("quadrotor_2d").symbolic_model(scg_jax.make("quadrotor_2d").default_params)
    with pytest.raises(ValueError, match=r"evaluate_fc: u must have shape \(..., nu\) with nu = 2, got \(5, 4\)"):
        model.evaluate_fc(np.zeros((5, 6)), np.zeros((5, 4)))
    with pytest.raises(ValueError, match=r"evaluate_fd: x must have shape \(..., nx\) with nx = 6, got \(6, 5\)"):
        model.evaluate_fd(np.zeros((6, 5)), np.zeros((5, 2)))
    with pytest.raises(ValueError, match=r"evaluate_fc: the leading axes of x \(5,\) and u \(4,\) do not broadcast"):
        model.evaluate_fc(np.zeros((5, 6)), np.zeros((4, 2)))


@pytest.mark.parametrize("name", SYSTEM_NAMES)
def test_plant_step_with_a_plants_physics_equals_that_plants_model_fd(name):
    """``plant_step`` (physics as a parameter, built once per env) gives each plant's own ``fd`` bit for bit."""
    from scg_jax.symbolic import physics_vector, plant_step

    env = scg_jax.make(name)
    rng = np.random.default_rng(0)
    fd = plant_step(env)
    assert plant_step(env) is fd  # one function per env
    base = env.default_params
    for scale in (0.8, 1.25):
        fields = {f: getattr(base.physics, f) * scale for f in ("mass", "pole_mass") if hasattr(base.physics, f)}
        assert fields, "a physics field to vary"
        params = base.replace(physics=base.physics.replace(**fields))
        x = rng.uniform(-0.5, 0.5, (5, env.nx))
        u = np.asarray(env.system.equilibrium_input(params.physics)) + rng.uniform(-0.2, 0.2, (5, env.nu))
        p = np.repeat(physics_vector(params)[:, None], 5, axis=1)
        ours = np.asarray(fd.map(5)(x.T, u.T, p)).T
        reference = np.asarray(env.symbolic_model(params).fd.map(5)(x.T, u.T)).T
        np.testing.assert_array_equal(ours, reference)
        assert np.abs(ours - np.asarray(env.symbolic_model(base).fd.map(5)(x.T, u.T)).T).max() > 1e-6
