"""The shared controller set-up (scg_algorithms.controller_setup): one set of weights, linearisation points, terminal
weight and prior model for every model-based controller, checked against the symbolic model and the Riccati
equation, and the same weights seen by every controller."""

import jax.numpy as jnp
import numpy as np
import pytest

import scg_jax
from scg_algorithms import controller_setup as setup
from scg_algorithms.ilqr import make_ilqr
from scg_algorithms.lqr import discrete_lqr_gain, make_lqr
from scg_algorithms.mpc.linear import build_problem
from scg_algorithms.mpc.nonlinear import make_nonlinear_mpc
from scg_jax.env import prior_params
from tests.control_helpers import cartpole_with_full_q


@pytest.fixture(scope="module")
def cartpole_full_q():
    """The cart-pole with a non-diagonal state weight (``tests.control_helpers.cartpole_with_full_q``)."""
    return cartpole_with_full_q()


def test_every_model_based_controller_gets_the_full_weights(cartpole_full_q):
    env, params, Q = cartpole_full_q
    R = np.asarray(params.R, np.float64)
    Q_set, R_set = setup.cost_weights(env, params, None, None, "controllers.x")
    np.testing.assert_allclose(Q_set, Q, rtol=1e-6)
    np.testing.assert_allclose(R_set, R)
    # LQR's gain is the Riccati gain of the full Q; iLQR, the linear MPC and the nonlinear MPC hold the same Q.
    model = setup.prior_model(env, params, "env")
    lin = model.linearize(np.asarray(params.goal, np.float64), setup.equilibrium_input(env, params))
    K, _ = discrete_lqr_gain(lin.Ad, lin.Bd, Q_set, R_set)
    np.testing.assert_allclose(make_lqr(env, params).info["K"][0], K, rtol=1e-9)
    np.testing.assert_allclose(make_ilqr(env, params).info["Q"], Q_set)
    np.testing.assert_allclose(build_problem(env, params).Q, Q_set)
    np.testing.assert_allclose(make_nonlinear_mpc(env, params, {"horizon": 5}).Q, Q_set)
    # A diagonal option replaces the matrix, it is not merged with it.
    Q_diag, _ = setup.cost_weights(env, params, [1.0, 2.0, 3.0, 4.0], None, "controllers.x")
    np.testing.assert_array_equal(Q_diag, np.diag([1.0, 2.0, 3.0, 4.0]))


def test_linearisations_along_the_reference_are_the_models_own():
    env = scg_jax.make("quadrotor_2d", "tracking")
    params = prior_params(env, env.default_params, 1.5)
    model = setup.prior_model(env, params, "rk4")
    assert setup.linearization_mode(env, "auto") == "reference"
    points = setup.linearization_points(env, params, model, "reference")
    assert points.shape == (env.num_steps + 1, env.nx)
    u_eq = setup.equilibrium_input(env, params)
    Ad, Bd, c = setup.linearize_along(model, points[::50], u_eq)
    for i, x0 in enumerate(points[::50]):
        lin = model.linearize(x0, u_eq)
        np.testing.assert_allclose(Ad[i], lin.Ad, atol=1e-12)
        np.testing.assert_allclose(Bd[i], lin.Bd, atol=1e-12)
        # Exact at the point: Ad x + Bd u + c = fd(x, u).
        np.testing.assert_allclose(Ad[i] @ x0 + Bd[i] @ u_eq + c[i], np.asarray(model.fd(x0, u_eq)).ravel(), atol=1e-12)


@pytest.mark.parametrize("discretization", ["rk4", "env"])
def test_the_jax_prior_step_is_the_casadi_prior_step(discretization):
    env = scg_jax.make("quadrotor_2d")
    params = prior_params(env, env.default_params, 1.5)
    x = np.array([0.1, -0.2, 1.0, 0.3, 0.2, -0.4])
    u = np.array([0.12, 0.15])
    step = setup.prior_step_fn(env, params, discretization)
    expected = np.asarray(setup.prior_model(env, params, discretization).fd(x, u)).ravel()
    # float32 JAX against float64 CasADi.
    np.testing.assert_allclose(np.asarray(step(jnp.asarray(x), jnp.asarray(u))), expected, rtol=1e-5, atol=1e-6)


def test_the_dare_terminal_weight_solves_the_riccati_equation():
    env = scg_jax.make("cartpole")
    params = env.default_params
    model = setup.prior_model(env, params, "rk4")
    Q, R = setup.cost_weights(env, params, None, None, "controllers.x")
    P = setup.terminal_weight("dare", env, params, model, Q, R, "controllers.x")
    lin = model.linearize(np.asarray(params.goal, np.float64), setup.equilibrium_input(env, params))
    A, B = lin.Ad, lin.Bd
    residual = A.T @ P @ A - A.T @ P @ B @ np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A) + Q - P
    assert np.abs(residual).max() < 1e-8 * np.abs(P).max()
    np.testing.assert_array_equal(setup.terminal_weight("stage", env, params, model, Q, R, "controllers.x"), Q)


@pytest.mark.parametrize(
    "call, message",
    [
        (
            lambda env, p: setup.cost_weights(env, p, [1.0], None, "controllers.x"),
            r"controllers\.x\.q_diag: expected 4",
        ),
        (
            lambda env, p: setup.cost_weights(env, p, None, [0.0], "controllers.x"),
            r"controllers\.x\.r_diag: the input weight must be positive definite",
        ),
        (lambda env, p: setup.linearization_mode(env, "start"), r"linearize_about: unknown value 'start'.*auto"),
        (lambda env, p: setup.prior_model(env, p, "euler"), r"discretization: unknown value 'euler'.*env, rk4"),
    ],
)
def test_bad_set_up_names_the_field(call, message):
    env = scg_jax.make("cartpole")
    with pytest.raises(ValueError, match=message):
        call(env, env.default_params)
