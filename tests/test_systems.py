"""Each system's one ``dynamics``: JAX vs CasADi, fixed points, exact linearisation, closed-form references."""

import casadi as cs
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import scg_jax
from scg_jax.backends import casadi_backend, jax_backend
from scg_jax.systems import cartpole, crazyflie, quadrotor_2d, quadrotor_3d

from .conftest import SYSTEM_NAMES


def _random_points(system, rng, n):
    """States inside the failure bounds (angles well away from the Euler singularity), inputs in bounds."""
    low = np.where(np.isfinite(system.state_low), system.state_low, -5.0)
    high = np.where(np.isfinite(system.state_high), system.state_high, 5.0)
    x = rng.uniform(low, high, size=(n, system.nx))
    u_low, u_high = system.input_bounds(system.params_cls())
    u = rng.uniform(u_low, u_high, size=(n, system.nu))
    f_ext = rng.normal(0.0, 0.05, size=(n, system.f_ext_dim))
    return x, u, f_ext


@pytest.mark.parametrize("name", SYSTEM_NAMES)
def test_jax_and_casadi_dynamics_agree_at_1000_random_points(name):
    system = scg_jax.SYSTEMS[name]
    params = system.params_cls()
    x, u, f_ext = _random_points(system, np.random.default_rng(0), 1000)

    xs, us, fs = cs.SX.sym("x", system.nx), cs.SX.sym("u", system.nu), cs.SX.sym("f", system.f_ext_dim)
    casadi_f = cs.Function("f", [xs, us, fs], [system.dynamics(xs, us, params, casadi_backend, fs)])
    expected = np.array(casadi_f.map(1000)(x.T, u.T, f_ext.T)).T

    with jax.enable_x64(True):
        params64 = jax.tree.map(lambda v: jnp.asarray(v, jnp.float64), params)
        jax_f = jax.vmap(lambda x, u, f: system.dynamics(x, u, params64, jax_backend, f))
        actual = np.asarray(jax_f(jnp.asarray(x), jnp.asarray(u), jnp.asarray(f_ext)))

    assert actual.dtype == np.float64
    assert np.abs(expected).max() > 1.0  # the comparison is not between zeros
    np.testing.assert_allclose(actual, expected, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("name", SYSTEM_NAMES)
def test_goal_with_equilibrium_input_is_a_fixed_point(name):
    system = scg_jax.SYSTEMS[name]
    params = system.params_cls()
    with jax.enable_x64(True):
        x_dot = system.dynamics(
            jnp.asarray(system.goal), jnp.asarray(system.equilibrium_input(params)), params, jax_backend
        )
    np.testing.assert_allclose(np.asarray(x_dot), 0.0, atol=1e-12)


def test_quadrotor_3d_hover_is_a_fixed_point_at_any_yaw():
    params = crazyflie.Params()
    x = quadrotor_3d.SYSTEM.goal.copy()
    x[8] = 1.234
    with jax.enable_x64(True):
        x_dot = quadrotor_3d.dynamics(
            jnp.asarray(x), jnp.full(4, params.mass * params.gravity / 4), params, jax_backend
        )
    np.testing.assert_allclose(np.asarray(x_dot), 0.0, atol=1e-12)


def test_quadrotor_1d_linearisation_is_exact():
    env = scg_jax.make("quadrotor_1d")
    with jax.enable_x64(True):
        params = env.default_params
        m = float(params.physics.mass)
        x0, u0 = jnp.array([0.7, -0.3]), jnp.array([0.31])
        A = jax.jacfwd(lambda x: env.system.dynamics(x, u0, params.physics, jax_backend))(x0)
        B = jax.jacfwd(lambda u: env.system.dynamics(x0, u, params.physics, jax_backend))(u0)
        lin = env.symbolic_model(params).linearize(np.asarray(x0), np.asarray(u0))
    np.testing.assert_allclose(np.asarray(A), [[0.0, 1.0], [0.0, 0.0]], atol=1e-15)
    np.testing.assert_allclose(np.asarray(B), [[0.0], [1.0 / m]], rtol=1e-15)
    np.testing.assert_allclose(lin.A, A, atol=1e-15)
    np.testing.assert_allclose(lin.B, B, rtol=1e-15)
    # RK4 integrates a double integrator under a held input exactly: the discrete model is the exact ZOH one.
    dt = env.dt
    np.testing.assert_allclose(lin.Ad, [[1.0, dt], [0.0, 1.0]], atol=1e-13)
    np.testing.assert_allclose(lin.Bd, [[dt**2 / (2 * m)], [dt / m]], rtol=1e-12)


def test_cartpole_matches_the_lagrangian_mass_matrix_solve_with_external_force():
    """Independent reference: solve M(q) q_dd = tau from the Lagrangian, including the force on the pole."""
    params = cartpole.Params()
    mc, mp, l, g = params.cart_mass, params.pole_mass, params.pole_half_length, params.gravity
    rng = np.random.default_rng(1)
    for _ in range(50):
        x = rng.uniform([-2, -3, -1.5, -4], [2, 3, 1.5, 4])
        force, fx, fz = rng.uniform(-10, 10), rng.normal(0, 0.5), rng.normal(0, 0.5)
        th, th_d = x[2], x[3]
        mass = np.array([[mc + mp, mp * l * np.cos(th)], [mp * l * np.cos(th), 4.0 / 3.0 * mp * l**2]])
        tau = np.array(
            [
                force + fx + mp * l * th_d**2 * np.sin(th),
                mp * g * l * np.sin(th) + l * (fx * np.cos(th) - fz * np.sin(th)),
            ]
        )
        x_dd, th_dd = np.linalg.solve(mass, tau)
        with jax.enable_x64(True):
            x_dot = cartpole.dynamics(jnp.asarray(x), jnp.array([force]), params, jax_backend, jnp.array([fx, fz]))
        np.testing.assert_allclose(np.asarray(x_dot), [x[1], x_dd, th_d, th_dd], rtol=1e-10, atol=1e-12)


def test_quadrotor_3d_reduces_to_2d_in_the_xz_plane():
    params = crazyflie.Params()
    rng = np.random.default_rng(2)
    for _ in range(20):
        x2 = rng.uniform(-0.5, 0.5, size=6)
        t1, t2 = rng.uniform(0.06, 0.29, size=2)
        f2 = rng.normal(0, 0.01, size=2)
        x3 = np.zeros(12)
        x3[[0, 1, 4, 5, 7, 10]] = x2  # x, x_dot, z, z_dot, theta, q
        u3 = np.array([t1 / 2, t2 / 2, t2 / 2, t1 / 2])  # front pair f1 + f4, back pair f2 + f3
        with jax.enable_x64(True):
            d2 = np.asarray(quadrotor_2d.dynamics(jnp.asarray(x2), jnp.array([t1, t2]), params, jax_backend, f2))
            d3 = np.asarray(
                quadrotor_3d.dynamics(
                    jnp.asarray(x3), jnp.asarray(u3), params, jax_backend, jnp.array([f2[0], 0.0, f2[1]])
                )
            )
        np.testing.assert_allclose(d3[[0, 1, 4, 5, 7, 10]], d2, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(d3[[2, 3, 6, 8, 9, 11]], 0.0, atol=1e-12)


def test_quadrotor_3d_yaw_moment_uses_km_over_kf():
    params = crazyflie.Params()
    hover, delta = params.mass * params.gravity / 4, 0.001
    u = hover + np.array([-delta, delta, -delta, delta])
    with jax.enable_x64(True):
        x_dot = np.asarray(
            quadrotor_3d.dynamics(jnp.asarray(quadrotor_3d.SYSTEM.goal), jnp.asarray(u), params, jax_backend)
        )
    np.testing.assert_allclose(x_dot[11], params.km / params.kf * 4 * delta / params.izz, rtol=1e-12)
    np.testing.assert_allclose(np.delete(x_dot, 11), 0.0, atol=1e-12)


def test_reference_parameters_of_the_original_suite():
    cf = crazyflie.Params()
    assert (cf.mass, cf.arm_length, cf.ixx, cf.iyy, cf.izz) == (0.027, 0.0397, 1.4e-5, 1.4e-5, 2.17e-5)
    np.testing.assert_allclose(scg_jax.SYSTEMS["quadrotor_1d"].input_bounds(cf), ([0.11264], [0.59336]))
    np.testing.assert_allclose(scg_jax.SYSTEMS["quadrotor_1d"].equilibrium_input(cf), [0.2646])
    np.testing.assert_allclose(scg_jax.SYSTEMS["quadrotor_2d"].equilibrium_input(cf), [0.1323, 0.1323])
    np.testing.assert_allclose(scg_jax.SYSTEMS["quadrotor_3d"].equilibrium_input(cf), np.full(4, 0.06615))
    cp = cartpole.Params()
    assert (cp.cart_mass, cp.pole_mass, cp.pole_half_length, cp.gravity, cp.force_max) == (1.0, 0.1, 0.5, 9.8, 10.0)


@pytest.mark.parametrize(
    ("system", "field", "value", "reason"),
    [
        ("cartpole", "pole_mass", -0.1, "must be a positive finite number for cartpole, got -0.1"),
        ("quadrotor_2d", "mass", 0.0, "must be a positive finite number for quadrotor_2d, got 0.0"),
        ("quadrotor_3d", "izz", float("nan"), "must be finite, got nan"),
    ],
)
def test_non_physical_parameters_fail_at_make_naming_the_field(system, field, value, reason):
    with pytest.raises(ValueError) as err:  # a FieldError naming the make option physics.<field>
        scg_jax.make(system, physics={field: value})
    assert (err.value.path, err.value.reason) == (f"physics.{field}", reason)
    assert str(err.value) == f"physics.{field}: {reason}"


def test_per_system_knowledge_comes_from_the_record():
    from scg_jax.adapters import GYMNASIUM_IDS
    from scg_jax.plotting import plane_indices
    from scg_jax.render import VIEWS

    assert GYMNASIUM_IDS == {
        "cartpole": "scg_jax/CartPole-v0",
        "quadrotor_1d": "scg_jax/Quadrotor1D-v0",
        "quadrotor_2d": "scg_jax/Quadrotor2D-v0",
        "quadrotor_3d": "scg_jax/Quadrotor3D-v0",
    }
    assert {name: system.path_plane for name, system in scg_jax.SYSTEMS.items()} == {
        "cartpole": None,
        "quadrotor_1d": None,
        "quadrotor_2d": "xz",
        "quadrotor_3d": "xz",
    }
    assert all(system.view in VIEWS for system in scg_jax.SYSTEMS.values())
    assert plane_indices(scg_jax.make("cartpole", "tracking")) is None
    assert plane_indices(scg_jax.make("quadrotor_2d", "tracking", trajectory={"plane": "xy"})) == ("xz", (0, 2))
    assert plane_indices(scg_jax.make("quadrotor_3d", "tracking", trajectory={"plane": "zy"})) == ("zy", (4, 2))
