"""GP-MPC's prediction model: prior + GP mean in CasADi, learned from cart-pole data, and its plan uncertainty."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import scg_jax
from scg_algorithms import gp, make_controller
from scg_algorithms.evaluation import evaluate
from scg_algorithms.gp_mpc import data, tightening
from scg_algorithms.gp_mpc.model import PlanUncertainty, fit_model_error, learned_model


@pytest.fixture(scope="module")
def learned():
    """The 150%-prior cart-pole at 10 Hz: data from 16 noisy LQR episodes, a GP of the model error, held-out data."""
    env = scg_jax.make(
        "cartpole",
        "stabilization",
        ctrl_freq=10,
        physics_freq=1000,
        episode_len_sec=4,
        init_state={"type": "uniform", "low": [-0.3, -0.1, -0.1, -0.1], "high": [0.3, 0.1, 0.1, 0.1]},
    )
    params = env.default_params
    prior = scg_jax.prior_params(env, params, 1.5)
    fd = env.symbolic_model(prior, discretization="rk4").fd
    explorer = data.exploring(make_controller("lqr", env, prior), 1.0)
    train = evaluate(env, params, explorer, jax.random.key(0), 16, measure_time=False)
    test = evaluate(env, params, explorer, jax.random.key(1), 8, measure_time=False)
    z, e = data.model_error(fd, *data.transitions(train.trajectory))
    z_test, e_test = data.model_error(fd, *data.transitions(test.trajectory))
    posterior, info = fit_model_error(z, e, num_inducing=40, iterations=30, key=jax.random.key(2))
    return env, prior, fd, posterior, info, z, e, z_test, e_test


def test_the_gp_learns_most_of_the_prior_mismatch(learned):
    env, prior, fd, posterior, info, z, e, z_test, e_test = learned
    assert info["num_points"] == len(z) and len(info["inducing_indices"]) == 40
    mean, _ = gp.predict_batch(posterior, jnp.asarray(z_test))
    residual = e_test - np.asarray(mean)
    # Held out: the learned model's one-step error is at most a fifth of the 150% prior's, in every state.
    assert np.all(np.sqrt((residual**2).mean(0)) < 0.2 * np.sqrt((e_test**2).mean(0)))


def test_learned_model_is_the_prior_plus_the_gp_mean(learned):
    env, prior, fd, posterior, info, z, e, z_test, e_test = learned
    model = learned_model(fd, posterior)
    x, u = z_test[:20, :4], z_test[:20, 4:]
    with jax.enable_x64(True):
        mean, _ = gp.predict_batch(jax.tree.map(jnp.asarray, posterior), jnp.asarray(z_test[:20]))
    expected = np.asarray(fd.map(20)(x.T, u.T)).T + np.asarray(mean)
    np.testing.assert_allclose(np.asarray(model.map(20)(x.T, u.T)).T, expected, atol=1e-9)
    np.testing.assert_allclose(
        np.asarray(learned_model(fd, None)(x[0], u[0])).ravel(), np.asarray(fd(x[0], u[0])).ravel()
    )
    with pytest.raises(ValueError, match=r"gp: expected a GP from \[x; u\] \(5 inputs\) to the state \(4 outputs\)"):
        learned_model(fd, gp.exact_posterior(z[:5, :3], e[:5], gp.hyperparams(np.ones((4, 3)), np.ones(4), np.ones(4))))


def test_plan_covariance_uses_the_models_jacobians_and_the_gp_variance(learned):
    env, prior, fd, posterior, info, z, e, z_test, e_test = learned
    model = learned_model(fd, posterior)
    K = np.array([[-1.0, -2.0, -20.0, -4.0]])
    uncertainty = PlanUncertainty(model, posterior, K, prob=0.95, sigma0=1e-4 * np.eye(4))
    x_plan, u_plan = z_test[:6, :4], z_test[:5, 4:]
    sigmas = uncertainty.covariances(x_plan, u_plan)
    # The same propagation from central finite differences of the learned model and the GP variance at the plan.
    A, B = [], []
    for x, u in zip(x_plan[:5], u_plan, strict=True):
        f = lambda xx, uu: np.asarray(model(xx, uu)).ravel()  # noqa: E731
        A.append(np.stack([(f(x + h, u) - f(x - h, u)) / 2e-6 for h in 1e-6 * np.eye(4)], axis=1))
        B.append(np.stack([(f(x, u + h) - f(x, u - h)) / 2e-6 for h in 1e-6 * np.eye(1)], axis=1))
    with jax.enable_x64(True):
        _, var = gp.predict_batch(jax.tree.map(jnp.asarray, posterior), jnp.asarray(np.c_[x_plan[:5], u_plan]))
    expected = tightening.propagate_covariance(np.stack(A), np.stack(B), K, np.asarray(var), 1e-4 * np.eye(4))
    np.testing.assert_allclose(sigmas, expected, rtol=1e-5, atol=1e-9)
    margins = uncertainty.margins(x_plan, u_plan, np.eye(4)[[2]], np.zeros((1, 1)))
    np.testing.assert_allclose(margins[:, 0], tightening.quantile(0.95, 4) * np.sqrt(sigmas[1:, 2, 2]), rtol=1e-12)
    # The GP's variance only adds uncertainty: the margins exceed those of the same plan without it.
    certain = PlanUncertainty(model, None, K, prob=0.95, sigma0=1e-4 * np.eye(4))
    assert np.all(margins[:, 0] > certain.margins(x_plan, u_plan, np.eye(4)[[2]], np.zeros((1, 1)))[:, 0])


def test_more_inducing_points_than_data_is_named():
    with pytest.raises(ValueError, match=r"controllers.gp_mpc.num_inducing: must be an integer from 1 to the number"):
        fit_model_error(np.zeros((5, 2)), np.zeros((5, 1)), num_inducing=6, key=jax.random.key(0))
