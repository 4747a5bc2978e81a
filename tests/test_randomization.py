"""Reset-time randomisation: ranges and moments, absolute vs relative, reproducibility, the plant uses the draw."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats

import scg_jax

N = 10_000


def _draws(env, key=0):
    params = env.default_params
    _, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(jax.random.key(key), N), params)
    return state


def test_absolute_and_relative_uniform_physics():
    env = scg_jax.make(
        "cartpole",
        physics={"pole_mass": 0.2},
        physics_randomization={
            "cart_mass": {"type": "uniform", "low": 0.5, "high": 1.5},  # as written, kg
            "pole_mass": {"type": "uniform", "low": 0.9, "high": 1.1, "relative": True},  # nominal 0.2 kg x U(0.9, 1.1)
        },
    )
    physics = _draws(env).physics
    cart, pole = np.asarray(physics.cart_mass), np.asarray(physics.pole_mass)
    assert 0.5 <= cart.min() and cart.max() <= 1.5
    np.testing.assert_allclose([cart.mean(), cart.std()], [1.0, 1.0 / np.sqrt(12)], rtol=0.02)
    assert 0.18 <= pole.min() and pole.max() <= 0.22
    np.testing.assert_allclose([pole.mean(), pole.std()], [0.2, 0.04 / np.sqrt(12)], rtol=0.02)
    np.testing.assert_allclose(np.asarray(physics.pole_half_length), 0.5)  # not randomised: nominal


def test_truncated_normal_and_choice():
    env = scg_jax.make(
        "quadrotor_2d",
        physics_randomization={
            "mass": {"type": "normal", "mean": 0.027, "std": 0.003, "low": 0.024, "high": 0.033},
            "iyy": {"type": "choice", "values": [1.0, 1.5, 2.0], "relative": True},
        },
    )
    physics = _draws(env).physics
    mass = np.asarray(physics.mass)
    assert 0.024 <= mass.min() and mass.max() <= 0.033
    truncated = scipy.stats.truncnorm(-1.0, 2.0, loc=0.027, scale=0.003)
    np.testing.assert_allclose([mass.mean(), mass.std()], [truncated.mean(), truncated.std()], rtol=0.02)
    iyy = np.asarray(physics.iyy) / 1.4e-5
    values, counts = np.unique(iyy.round(5), return_counts=True)
    np.testing.assert_allclose(values, [1.0, 1.5, 2.0])
    np.testing.assert_allclose(counts / N, 1 / 3, atol=0.02)


def test_initial_state_distributions():
    normal = scg_jax.make("quadrotor_1d", init_state={"type": "normal", "mean": [1.0, 0.0], "std": [0.1, 0.01]})
    x = np.asarray(_draws(normal).x)
    np.testing.assert_allclose(x.mean(axis=0), [1.0, 0.0], atol=3e-3)
    np.testing.assert_allclose(x.std(axis=0), [0.1, 0.01], rtol=0.03)
    default = np.asarray(_draws(scg_jax.make("quadrotor_2d")).x)
    np.testing.assert_allclose(default.min(axis=0), [-0.5, -0.01, 0.1, -0.01, -0.3, -0.01], atol=2e-3)
    np.testing.assert_allclose(default.max(axis=0), [0.5, 0.01, 1.5, 0.01, 0.3, 0.01], atol=2e-3)
    fixed = np.asarray(_draws(scg_jax.make("quadrotor_1d", init_state=[0.7, 0.1])).x)
    np.testing.assert_array_equal(fixed, np.tile(np.float32([0.7, 0.1]), (N, 1)))


def test_same_key_same_draws_different_key_different_draws():
    env = scg_jax.make(
        "quadrotor_3d", physics_randomization={"mass": {"type": "uniform", "low": 0.8, "high": 1.2, "relative": True}}
    )
    a, b, c = _draws(env, 1), _draws(env, 1), _draws(env, 2)
    np.testing.assert_array_equal(np.asarray(a.physics.mass), np.asarray(b.physics.mass))
    np.testing.assert_array_equal(np.asarray(a.x), np.asarray(b.x))
    assert not np.allclose(np.asarray(a.physics.mass), np.asarray(c.physics.mass))


def test_the_plant_uses_the_drawn_parameters():
    env = scg_jax.make(
        "quadrotor_1d",
        init_state=[1.0, 0.0],
        physics_randomization={"mass": {"type": "uniform", "low": 0.02, "high": 0.04}},
    )
    params = env.default_params
    obs, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(jax.random.key(0), 8), params)
    out = jax.vmap(env.step, in_axes=(0, None, None))(state, jnp.array([0.2646]), params)
    m = np.asarray(state.physics.mass)
    np.testing.assert_allclose(np.asarray(out.state.x[:, 1]), (0.2646 / m - 9.8) * env.dt, rtol=1e-4)


def test_prior_params_scale_the_inertial_parameters_only():
    env = scg_jax.make("cartpole")
    params = env.default_params
    prior = scg_jax.prior_params(env, params, scale=1.5)
    assert float(prior.physics.cart_mass) == 1.5 and float(prior.physics.pole_half_length) == 0.75
    np.testing.assert_allclose(float(prior.physics.pole_mass), 0.15)
    assert prior.physics.gravity is params.physics.gravity and prior.physics.force_max is params.physics.force_max
    model, true_model = env.symbolic_model(prior), env.symbolic_model(params)
    x, u = np.array([0.0, 0.0, 0.2, 0.0]), np.array([1.0])
    assert not np.allclose(np.asarray(model.fc(x, u)), np.asarray(true_model.fc(x, u)))
    with pytest.raises(ValueError, match="fields: unknown parameter 'length' of cartpole"):
        scg_jax.prior_params(env, params, fields=["length"])


@pytest.mark.parametrize(
    ("option", "message"),
    [
        (
            {"mass": {"type": "uniform", "low": 0.0, "high": 0.03}},
            r"physics_randomization.mass.low: must be positive so every drawn value is",
        ),
        (
            {"mass": {"type": "normal", "mean": 0.027, "std": 0.01}},
            r"physics_randomization.mass.low: a normal distribution of a positive parameter needs a truncation",
        ),
        (
            {"mass": {"type": "choice", "values": [1.0, -1.0], "relative": True}},
            r"physics_randomization.mass.values: must all be positive",
        ),
        (
            {"mass": {"type": "beta"}},
            r"physics_randomization.mass.type: unknown value 'beta'; allowed values are "
            r"uniform, normal, choice",
        ),
        ({"weight": {"type": "uniform", "low": 1, "high": 2}}, r"physics_randomization.weight: unknown parameter"),
    ],
)
def test_invalid_randomisation_is_rejected_at_make(option, message):
    with pytest.raises(ValueError, match=message):
        scg_jax.make("quadrotor_2d", physics_randomization=option)


def test_relative_is_not_allowed_for_the_initial_state():
    with pytest.raises(ValueError, match=r"init_state.relative: unknown key for a uniform distribution here"):
        scg_jax.make("quadrotor_1d", init_state={"type": "uniform", "low": [0, 0], "high": [1, 0], "relative": True})
