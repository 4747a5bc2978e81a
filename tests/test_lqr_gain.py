"""Discrete LQR gain: the Riccati equation, the gain formula, and a stable closed loop."""

import numpy as np
import pytest
import scipy.linalg

import scg_jax
from scg_algorithms.lqr import discrete_lqr_gain, lqr_gain_about


def test_gain_solves_the_discrete_riccati_equation_for_the_cartpole():
    env = scg_jax.make("cartpole")
    params = env.default_params
    lin = env.symbolic_model(params).linearize(np.zeros(4), np.zeros(1))
    Q, R = np.asarray(params.Q, float), np.asarray(params.R, float)
    K, P = discrete_lqr_gain(lin.Ad, lin.Bd, Q, R)
    A, B = lin.Ad, lin.Bd
    residual = A.T @ P @ A - A.T @ P @ B @ np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A) + Q - P
    assert np.abs(residual).max() < 1e-8 * max(1.0, np.abs(P).max())
    np.testing.assert_allclose(K, np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A), rtol=1e-12)
    np.testing.assert_allclose(P, scipy.linalg.solve_discrete_are(A, B, Q, R), rtol=1e-9)
    assert np.abs(np.linalg.eigvals(A)).max() > 1.0  # the upright pole is unstable ...
    assert np.abs(np.linalg.eigvals(A - B @ K)).max() < 1.0  # ... and the gain stabilises it
    np.testing.assert_allclose(lqr_gain_about(env, params, np.zeros(4), np.zeros(1)), K, rtol=1e-12)


def test_scalar_case_matches_the_closed_form():
    # x+ = a x + b u, cost q x^2 + r u^2: p solves p = q + a^2 p r / (r + b^2 p).
    a, b, q, r = 1.2, 0.5, 2.0, 0.3
    K, P = discrete_lqr_gain([[a]], [[b]], [[q]], [[r]])
    p = float(P[0, 0])
    np.testing.assert_allclose(p, q + a**2 * p * r / (r + b**2 * p), rtol=1e-12)
    np.testing.assert_allclose(float(K[0, 0]), a * b * p / (r + b**2 * p), rtol=1e-12)


def test_bad_shapes_name_the_argument():
    with pytest.raises(ValueError, match=r"Bd: expected shape \(2, nu\)"):
        discrete_lqr_gain(np.eye(2), np.ones((3, 1)), np.eye(2), np.eye(1))
    with pytest.raises(ValueError, match=r"R: expected shape \(1, 1\)"):
        discrete_lqr_gain(np.eye(2), np.ones((2, 1)), np.eye(2), np.eye(2))
