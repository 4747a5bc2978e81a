"""The LQR controller: gains against the Riccati equations, stabilisation, and the cost of a wrong prior."""

import jax
import numpy as np
import pytest
import scipy.linalg

import scg_jax
from scg_algorithms.evaluation import evaluate
from scg_algorithms.lqr import continuous_lqr_gain, make_lqr
from scg_jax.config import load_config, make_from_config
from scg_jax.env import prior_params

EPISODES = 16


@pytest.fixture(scope="module")
def cartpole():
    """The cart-pole of configs/cartpole_stabilization.yaml: the paper's initial range U(-0.05, 0.05) on each
    entry, masses randomised +-10%, sensor noise, default state and input constraints."""
    return make_from_config(load_config("configs/cartpole_stabilization.yaml"))


def test_discrete_gain_solves_the_riccati_equation_of_the_prior_model(cartpole):
    env, params = cartpole
    lqr = make_lqr(env, params)
    (K,) = lqr.info["K"]
    lin = env.symbolic_model(params).linearize(np.zeros(4), np.zeros(1))
    Q, R = np.asarray(params.Q, np.float64), np.asarray(params.R, np.float64)
    P = scipy.linalg.solve_discrete_are(lin.Ad, lin.Bd, Q, R)
    np.testing.assert_allclose(K, np.linalg.solve(R + lin.Bd.T @ P @ lin.Bd, lin.Bd.T @ P @ lin.Ad), rtol=1e-8)
    assert np.max(np.abs(np.linalg.eigvals(lin.Ad - lin.Bd @ K))) < 1.0


def test_continuous_gain_solves_the_continuous_riccati_equation(cartpole):
    env, params = cartpole
    lin = env.symbolic_model(params).linearize(np.zeros(4), np.zeros(1))
    Q, R = np.eye(4), np.array([[0.1]])
    K, P = continuous_lqr_gain(lin.A, lin.B, Q, R)
    residual = lin.A.T @ P + P @ lin.A - P @ lin.B @ np.linalg.solve(R, lin.B.T @ P) + Q
    np.testing.assert_allclose(residual, 0.0, atol=1e-8)
    np.testing.assert_allclose(K, np.linalg.solve(R, lin.B.T @ P))
    assert np.max(np.linalg.eigvals(lin.A - lin.B @ K).real) < 0.0
    continuous = make_lqr(env, params, {"discrete": False})
    np.testing.assert_allclose(continuous.info["K"][0], K, rtol=1e-8)


def test_lqr_stabilises_the_cartpole_and_a_wrong_prior_costs_accuracy(cartpole):
    env, params = cartpole
    key = jax.random.key(0)
    true_prior = evaluate(env, params, make_lqr(env, params), key, EPISODES, measure_time=False).summary
    wrong_prior = make_lqr(env, prior_params(env, params, 1.5))
    wrong = evaluate(env, params, wrong_prior, key, EPISODES, measure_time=False).summary
    # Each of the four initial entries is within 0.05, so the error (mse_weight weighs all four) starts below
    # sqrt(4) 0.05 = 0.1; a stabilising controller that does not overshoot keeps the episode's RMS below it.
    assert true_prior["failure_rate"] == 0.0 and true_prior["rmse"] < 0.1
    assert wrong["failure_rate"] == 0.0 and wrong["rmse"] < 0.1
    assert wrong["rmse"] > 1.05 * true_prior["rmse"]


def test_lqr_stabilises_the_2d_quadrotor_at_hover():
    hover = [0.0, 0.0, 1.0, 0.0, 0.0, 0.0]
    env = scg_jax.make(
        "quadrotor_2d",
        goal=hover,
        init_state={
            "type": "uniform",
            "low": [-0.02, -0.02, 0.98, -0.02, -0.02, -0.02],
            "high": [0.02, 0.02, 1.02, 0.02, 0.02, 0.02],
        },
        constraints=[{"type": "default", "on": "state"}, {"type": "default", "on": "input"}],
    )
    params = env.default_params
    summary = evaluate(env, params, make_lqr(env, params), jax.random.key(1), EPISODES, measure_time=False).summary
    # Near hover (LQR with R = 0.1 N^-2 is aggressive: a 5 cm start already asks a motor for less than its
    # minimum thrust). Position errors start within 0.02 m per axis, 0.028 m in the plane: the RMS stays below.
    assert summary["failure_rate"] == 0.0 and summary["rmse"] < 0.028
    assert summary["length"] == env.num_steps


def test_tracking_about_the_reference_uses_one_gain_per_step():
    env = scg_jax.make("quadrotor_2d", "tracking", episode_len_sec=1.0)
    lqr = make_lqr(env, env.default_params)
    assert lqr.info["mode"] == "reference" and lqr.info["K"].shape == (env.num_steps + 1, 2, 6)
    goal_only = make_lqr(env, env.default_params, {"mode": "goal"})
    assert goal_only.info["K"].shape == (1, 2, 6)


@pytest.mark.parametrize(
    "options, message",
    [
        ({"mode": "nearest"}, r"controllers.lqr.mode: unknown value 'nearest'; allowed values are auto, goal"),
        ({"q_diag": [1.0, 2.0]}, r"controllers.lqr.q_diag: expected 4 values"),
        ({"discrete": "yes"}, r"controllers.lqr.discrete: expected true or false"),
        ({"gain": 1.0}, r"controllers.lqr.gain: unknown key; allowed keys are mode, discrete, q_diag, r_diag"),
    ],
)
def test_bad_options_name_the_field(cartpole, options, message):
    env, params = cartpole
    with pytest.raises(ValueError, match=message):
        make_lqr(env, params, options)
