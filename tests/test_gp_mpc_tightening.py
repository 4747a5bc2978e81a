"""Chance-constraint tightening: the quantile, covariance propagation against Monte Carlo, row offsets."""

from __future__ import annotations

import numpy as np
import pytest

from scg_algorithms.gp_mpc import tightening


def test_quantile_matches_the_original_suites_values():
    assert tightening.quantile(0.95, 4) == pytest.approx(2.4977, abs=1e-4)
    assert tightening.quantile(0.99, 4) == pytest.approx(3.023, abs=1e-3)
    assert tightening.quantile(0.99, 6) == pytest.approx(3.144, abs=1e-3)


def test_covariance_propagation_matches_monte_carlo():
    """A linear system driven by independent noise under δu = -K δx: sample covariances after H steps."""
    rng = np.random.default_rng(0)
    H, nx, nu = 6, 3, 2
    A = np.eye(nx) + 0.1 * rng.standard_normal((H, nx, nx))
    B = 0.2 * rng.standard_normal((H, nx, nu))
    K = 0.5 * rng.standard_normal((nu, nx))
    var = rng.uniform(0.01, 0.05, (H, nx))
    sigma0 = np.diag([0.02, 0.01, 0.03])
    sigmas = tightening.propagate_covariance(A, B, K, var, sigma0)
    n = 200_000
    dx = rng.multivariate_normal(np.zeros(nx), sigma0, n)
    for i in range(H):
        du = -dx @ K.T
        dx = dx @ A[i].T + du @ B[i].T + rng.standard_normal((n, nx)) * np.sqrt(var[i])
    np.testing.assert_allclose(np.cov(dx.T), sigmas[-1], rtol=0.03, atol=2e-4)


def test_state_rows_use_the_next_covariance_and_input_rows_the_feedback_of_the_current_one():
    sigma_now = np.array([[0.04, 0.01], [0.01, 0.09]])
    sigma_next = np.array([[0.25, 0.0], [0.0, 0.16]])
    K = np.array([[2.0, 1.0]])
    z_q = tightening.quantile(0.95, 2)
    rows_x = np.array([[1.0, 0.0], [0.0, -1.0], [0.0, 0.0], [1.0, 0.0]])
    rows_u = np.array([[0.0], [0.0], [1.0], [1.0]])
    out = tightening.margins(rows_x, rows_u, np.stack([sigma_now, sigma_next]), K, z_q)
    # x_{i+1} stds 0.5 and 0.4; the input deviation -K δx_i has variance K Σ_i Kᵀ = 4*0.04 + 2*2*0.01 + 0.09.
    input_std = np.sqrt(0.16 + 0.04 + 0.09)
    np.testing.assert_allclose(out[0], z_q * np.array([0.5, 0.4, input_std, 0.5 + input_std]), rtol=1e-12)


def test_bad_probability_is_named():
    with pytest.raises(ValueError, match=r"prob: must be in \(0, 1\), got 1.0"):
        tightening.quantile(1.0, 4)
