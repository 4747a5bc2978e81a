"""GP-MPC's data: exploration noise, transitions cut at episode ends, model-error targets."""

from __future__ import annotations

import jax
import numpy as np
import pytest

import scg_jax
from scg_algorithms import make_controller
from scg_algorithms.base import JaxController
from scg_algorithms.evaluation import evaluate
from scg_algorithms.gp_mpc import data


@pytest.fixture(scope="module")
def cartpole():
    env = scg_jax.make("cartpole", "stabilization", ctrl_freq=10, physics_freq=1000, episode_len_sec=3)
    return env, env.default_params


def test_transitions_stop_at_each_episode_end():
    T, N = 5, 3
    x = np.arange((T + 1) * N * 2, dtype=float).reshape(T + 1, N, 2)
    u = np.arange(T * N, dtype=float).reshape(T, N, 1)
    terminated = np.zeros((T, N), bool)
    truncated = np.zeros((T, N), bool)
    terminated[1, 0] = True  # copy 0 ends after its second step
    truncated[4, 1] = True  # copy 1 at the time limit; copy 2 runs all 5 steps without a flag
    traj = {"x": x, "u": u, "terminated": terminated, "truncated": truncated}
    np.testing.assert_array_equal(data.episode_lengths(traj), [2, 5, 5])
    xs, us, nexts = data.transitions(traj)
    assert xs.shape == (12, 2) and us.shape == (12, 1)
    np.testing.assert_array_equal(xs[:2], x[:2, 0])
    np.testing.assert_array_equal(nexts[:2], x[1:3, 0])
    np.testing.assert_array_equal(us[2:7, 0], u[:, 1, 0])


def test_exploration_is_the_controller_plus_seeded_noise(cartpole):
    env, params = cartpole
    lqr = make_controller("lqr", env, params)
    quiet = evaluate(env, params, data.exploring(lqr, 0.0), jax.random.key(0), 4, measure_time=False)
    plain = evaluate(env, params, lqr, jax.random.key(0), 4, measure_time=False)
    np.testing.assert_allclose(quiet.trajectory["u_cmd"], plain.trajectory["u_cmd"], atol=1e-6)
    # Same key, same noise (two builds; the model-error test's settings, so the run compiles that program once).
    noisy = [evaluate(env, params, data.exploring(lqr, 1.0), jax.random.key(1), 8, measure_time=False) for _ in "ab"]
    np.testing.assert_array_equal(noisy[0].trajectory["u_cmd"], noisy[1].trajectory["u_cmd"])
    # Around a controller that always commands 0 N, the inputs are the noise itself: N(0, 2²) over 64 x 30 draws.
    zero = JaxController("zero", lambda key, ref: (), lambda s, obs, step, ref: (jax.numpy.zeros(1), s))
    run = evaluate(env, params, data.exploring(zero, 2.0), jax.random.key(3), 64, measure_time=False)
    samples = run.trajectory["u_cmd"][: int(data.episode_lengths(run.trajectory).min())].ravel()
    assert abs(samples.mean()) < 0.15 and samples.std() == pytest.approx(2.0, rel=0.06)
    with pytest.raises(ValueError, match=r"exploration_std: must be finite and >= 0"):
        data.exploring(lqr, -1.0)


def test_model_error_is_zero_for_the_true_model_and_the_mismatch_for_a_wrong_prior(cartpole):
    env, params = cartpole
    lqr = make_controller("lqr", env, params)
    run = evaluate(env, params, data.exploring(lqr, 1.0), jax.random.key(1), 8, measure_time=False)
    x, u, x_next = data.transitions(run.trajectory)
    z, e = data.model_error(env.symbolic_model(params).fd, x, u, x_next)
    assert z.shape == (len(x), 5) and e.shape == (len(x), 4)
    assert np.abs(e).max() < 1e-4  # the env's float32 steps against the same model in float64
    prior = scg_jax.prior_params(env, params, 1.5)
    _, e_prior = data.model_error(env.symbolic_model(prior).fd, x, u, x_next)
    true_minus_prior = (
        np.asarray(env.symbolic_model(params).fd.map(len(x))(x.T, u.T)).T
        - np.asarray(env.symbolic_model(prior).fd.map(len(x))(x.T, u.T)).T
    )
    np.testing.assert_allclose(e_prior, true_minus_prior, atol=1e-4)
    assert np.abs(e_prior).max() > 100 * np.abs(e).max()
