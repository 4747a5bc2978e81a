"""Gaussian-process regression: closed forms, JAX = CasADi, FITC = exact on the data, hyperparameter recovery."""

from __future__ import annotations

import casadi as cs
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from scg_algorithms import gp


def _closed_form(x, y, z, ls, s2, noise, kernel="rbf"):
    """Textbook GP posterior (Rasmussen & Williams eq. 2.25-2.26) with numpy, one output."""

    def k(a, b):
        d2 = (((a[:, None, :] - b[None]) / ls) ** 2).sum(-1)
        if kernel == "rbf":
            return s2 * np.exp(-0.5 * d2)
        r = np.sqrt(5.0 * d2)
        return s2 * (1 + r + r * r / 3) * np.exp(-r)

    big_k = k(x, x) + noise * np.eye(len(x))
    ks = k(z, x)
    mean = ks @ np.linalg.solve(big_k, y)
    var = np.diag(k(z, z)) - np.einsum("ij,ji->i", ks, np.linalg.solve(big_k, ks.T))
    return mean, var


def test_two_point_posterior_by_hand():
    """Two data points at 0 and 1 (rbf, l = 1, s2 = 1, noise 0.1): the mean at 0.5 worked out by hand."""
    hp = gp.hyperparams([[1.0]], [1.0], [0.1])
    post = gp.exact_posterior([[0.0], [1.0]], [[1.0], [-1.0]], hp)
    with jax.enable_x64(True):
        mean, var = gp.predict(jax.tree.map(jnp.asarray, post), jnp.array([0.5]))
    # k(0.5, 0) = k(0.5, 1) = e^-0.125; the targets are antisymmetric about 0.5, so the mean there is exactly 0.
    assert abs(float(mean[0])) < 1e-12
    c = np.exp(-0.5)  # k(0, 1)
    kvec = np.exp(-0.125) * np.ones(2)
    expected_var = 1.0 - kvec @ np.linalg.solve(np.array([[1.1, c], [c, 1.1]]), kvec)
    assert float(var[0]) == pytest.approx(expected_var, abs=1e-12)
    assert float(var[0]) == pytest.approx(1.0 - 2 * np.exp(-0.25) / (1.1 + c), abs=1e-12)


@pytest.mark.parametrize("kernel", gp.KERNELS)
def test_exact_posterior_equals_closed_form(kernel):
    rng = np.random.default_rng(0)
    x, z = rng.uniform(-2, 2, (30, 3)), rng.uniform(-2, 2, (50, 3))
    y = np.stack([np.sin(x[:, 0]) + x[:, 1], np.cos(x.sum(1))], axis=1)
    hp = gp.hyperparams([[0.7, 1.1, 2.0], [1.5, 0.4, 0.9]], [1.3, 0.6], [0.01, 0.05])
    post = gp.exact_posterior(x, y, hp, kernel)
    with jax.enable_x64(True):
        mean, var = gp.predict_batch(jax.tree.map(jnp.asarray, post), jnp.asarray(z))
    for i in range(2):
        ls, s2, noise = np.asarray(hp.length_scales[i]), float(hp.signal_var[i]), float(hp.noise_var[i])
        m_ref, v_ref = _closed_form(x, y[:, i], z, ls, s2, noise, kernel)
        np.testing.assert_allclose(np.asarray(mean[:, i]), m_ref, atol=1e-6)
        np.testing.assert_allclose(np.asarray(var[:, i]), v_ref, atol=1e-6)


def test_fitc_on_all_data_points_is_exact():
    """FITC with the training inputs as inducing points is the exact posterior (Snelson & Ghahramani)."""
    rng = np.random.default_rng(1)
    x = rng.uniform(-1, 1, (25, 2))
    y = np.sin(3 * x[:, :1]) * x[:, 1:]
    hp = gp.hyperparams([[0.5, 0.8]], [0.4], [1e-3])
    exact, fitc = gp.exact_posterior(x, y, hp), gp.fitc_posterior(x, y, hp, x, jitter=1e-12)
    z = rng.uniform(-1, 1, (40, 2))
    with jax.enable_x64(True):
        m1, v1 = gp.predict_batch(jax.tree.map(jnp.asarray, exact), jnp.asarray(z))
        m2, v2 = gp.predict_batch(jax.tree.map(jnp.asarray, fitc), jnp.asarray(z))
    np.testing.assert_allclose(np.asarray(m2), np.asarray(m1), atol=1e-6)
    np.testing.assert_allclose(np.asarray(v2), np.asarray(v1), atol=1e-6)


def test_fitc_with_few_inducing_points_approximates_the_mean():
    rng = np.random.default_rng(2)
    x = rng.uniform(-3, 3, (400, 1))
    y = np.sin(x) + 0.05 * rng.standard_normal(x.shape)
    hp = gp.hyperparams([[1.0]], [1.0], [0.0025])
    idx = gp.select_inducing(x, 20, jax.random.key(0))
    assert len(set(idx.tolist())) == 20
    fitc = gp.fitc_posterior(x, y, hp, x[idx])
    z = np.linspace(-2.5, 2.5, 50)[:, None]
    with jax.enable_x64(True):
        mean, _ = gp.predict_batch(jax.tree.map(jnp.asarray, fitc), jnp.asarray(z))
    np.testing.assert_allclose(np.asarray(mean[:, 0]), np.sin(z[:, 0]), atol=0.05)


@pytest.mark.parametrize("kind", ["exact", "fitc"])
@pytest.mark.parametrize("kernel", gp.KERNELS)
def test_jax_and_casadi_agree_at_random_points(kind, kernel):
    rng = np.random.default_rng(3)
    x = rng.uniform(-1, 1, (40, 5))
    y = np.stack([np.sin(2 * x[:, 0]), x[:, 1] * x[:, 2], np.cos(x[:, 3] - x[:, 4])], axis=1)
    hp = gp.hyperparams(rng.uniform(0.3, 2.0, (3, 5)), [0.5, 1.0, 2.0], [1e-3, 1e-2, 1e-4])
    post = gp.exact_posterior(x, y, hp, kernel) if kind == "exact" else gp.fitc_posterior(x, y, hp, x[:12], kernel)
    function = gp.casadi_function(post)
    z = rng.uniform(-1.5, 1.5, (200, 5))
    with jax.enable_x64(True):
        mean, var = gp.predict_batch(jax.tree.map(jnp.asarray, post), jnp.asarray(z))
    cs_mean, cs_var = function.map(len(z))(z.T)
    np.testing.assert_allclose(np.asarray(cs_mean).T, np.asarray(mean), atol=1e-6, rtol=0)
    np.testing.assert_allclose(np.asarray(cs_var).T, np.asarray(var), atol=1e-6, rtol=0)
    # The CasADi expression is differentiable for the MPC: its Jacobian equals JAX's.
    zs = cs.SX.sym("z", 5)
    jac = cs.Function("j", [zs], [cs.jacobian(function(zs)[0], zs)])
    with jax.enable_x64(True):
        jax_jac = jax.jacfwd(lambda q: gp.predict(jax.tree.map(jnp.asarray, post), q)[0])(jnp.asarray(z[0]))
    np.testing.assert_allclose(np.asarray(jac(z[0])), np.asarray(jax_jac), atol=1e-6)


def _known_gp_data(seed: int, true_ls=(0.5, 2.0), s2: float = 1.0, noise: float = 1e-2):
    """200 inputs in [-3, 3]^2 and three independent draws (one per output) of a GP with ARD length scales."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(-3, 3, (200, 2))
    d2 = (((x[:, None, :] - x[None]) / np.asarray(true_ls)) ** 2).sum(-1)
    cov = s2 * np.exp(-0.5 * d2) + noise * np.eye(len(x))
    return x, np.linalg.cholesky(cov) @ rng.standard_normal((len(x), 3))


@pytest.fixture(scope="module")
def known_gp_fit():
    """``(hyperparams, info, compiled fits after it)`` of the fit on ``_known_gp_data(4)``, made once."""
    hp, info = gp.fit_hyperparams(*_known_gp_data(4), iterations=30)
    return hp, info, gp._fit_standardised._cache_size()


def test_fit_recovers_the_length_scales_of_data_drawn_from_a_known_gp(known_gp_fit):
    """Samples of a GP with ARD length scales (0.5, 2.0) m: the fit recovers both within 25%."""
    hp, info, _ = known_gp_fit
    assert info["nll_final"] < info["nll_initial"]
    np.testing.assert_allclose(np.asarray(hp.length_scales), np.tile([0.5, 2.0], (3, 1)), rtol=0.25)
    np.testing.assert_allclose(np.asarray(hp.noise_var), 1e-2, rtol=0.5)


def test_a_fit_on_new_data_of_the_same_shape_reuses_the_compiled_fit(known_gp_fit):
    """The data are arguments of the compiled fit: a fit on new data of the same shapes (a GP-MPC round) does not
    trace again, and finds the new data's length scales, not the old ones."""
    _, _, compiled = known_gp_fit
    hp, info = gp.fit_hyperparams(*_known_gp_data(5, true_ls=(2.0, 0.5)), iterations=30)
    assert gp._fit_standardised._cache_size() == compiled
    assert info["nll_final"] < info["nll_initial"]
    np.testing.assert_allclose(np.asarray(hp.length_scales), np.tile([2.0, 0.5], (3, 1)), rtol=0.25)


def test_bad_input_names_the_field():
    with pytest.raises(ValueError, match=r"hyperparams.length_scales: must be positive"):
        gp.hyperparams([[1.0, -0.1]], [1.0], [0.1])
    with pytest.raises(ValueError, match=r"hyperparams.noise_var: must be positive"):
        gp.hyperparams([[1.0]], [1.0], [0.0])
    with pytest.raises(ValueError, match=r"num_inducing: must be an integer from 1 to the number of data points \(5\)"):
        gp.select_inducing(np.zeros((5, 2)), 6, jax.random.key(0))
    with pytest.raises(ValueError, match=r"kernel: unknown value 'matern'; allowed values are rbf, matern52"):
        gp.exact_posterior(np.zeros((3, 1)), np.zeros((3, 1)), gp.hyperparams([[1.0]], [1.0], [0.1]), "matern")
    with pytest.raises(ValueError, match=r"data: expected inputs \(n, d\) and targets \(n, m\)"):
        gp.fit_hyperparams(np.zeros((4, 2)), np.zeros((3, 1)))


def _random_fitc(kernel: str, seed: int = 4):
    rng = np.random.default_rng(seed)
    x = rng.uniform(-1, 1, (60, 5))
    y = np.stack([np.sin(2 * x[:, 0]), x[:, 1] * x[:, 2], np.cos(x[:, 3] - x[:, 4])], axis=1)
    hp = gp.hyperparams(rng.uniform(0.3, 2.0, (3, 5)), [0.5, 1.0, 2.0], [1e-3, 1e-2, 1e-4])
    return gp.fitc_posterior(x, y, hp, x[:15], kernel), rng.uniform(-1.5, 1.5, (8, 5))


@pytest.mark.parametrize("kernel", gp.KERNELS)
def test_predict_mean_has_predicts_value_and_the_closed_form_jacobian(kernel):
    post, z = _random_fitc(kernel)
    with jax.enable_x64(True):
        post64 = jax.tree.map(jnp.asarray, post)
        for zi in jnp.asarray(z):
            np.testing.assert_array_equal(gp.predict_mean(post64, zi), gp.predict(post64, zi)[0])
            automatic = jax.jacfwd(lambda q: gp.predict(post64, q)[0])(zi)  # through the kernel's expansion
            np.testing.assert_allclose(jax.jacfwd(lambda q: gp.predict_mean(post64, q))(zi), automatic, atol=1e-13)
            np.testing.assert_allclose(jax.jacrev(lambda q: gp.predict_mean(post64, q))(zi), automatic, atol=1e-13)
        # In the posterior (its weights and length scales) it differentiates as predict does.
        z0 = jnp.asarray(z[0])

        def total(mean_fn, w, ls):
            posterior = post64.replace(weights=w, hyperparams=post64.hyperparams.replace(length_scales=ls))
            return jnp.sum(mean_fn(posterior, z0) ** 2)

        args = (post64.weights, post64.hyperparams.length_scales)
        ours = jax.grad(lambda w, ls: total(gp.predict_mean, w, ls), argnums=(0, 1))(*args)
        reference = jax.grad(lambda w, ls: total(lambda p, q: gp.predict(p, q)[0], w, ls), argnums=(0, 1))(*args)
        for a, b in zip(ours, reference, strict=True):
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("kernel", gp.KERNELS)
def test_predict_split_gives_the_float64_variance_inside_a_vmapped_scan(kernel):
    post, z = _random_fitc(kernel)
    _, expected = gp.predict_batch(post, z)
    split = gp.split_posterior(post)
    # Two copies of a scan over the points, with x64 off: the float32 program of a closed-loop evaluation.
    scan = lambda points: jax.lax.scan(lambda c, zi: (c, gp.predict_split(split, zi)), 0.0, points)[1]  # noqa: E731
    var = jax.jit(jax.vmap(scan))(jnp.asarray(np.stack([z, z]), jnp.float32))
    assert var.dtype == jnp.float32
    np.testing.assert_allclose(var[0], expected, rtol=2e-6, atol=0)
    np.testing.assert_array_equal(var[0], var[1])
