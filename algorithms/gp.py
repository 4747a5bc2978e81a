"""Gaussian-process regression of a model error, written once for JAX and CasADi.

One independent GP per output dimension (Hewing et al. 2019; the original suite's GP-MPC): zero mean, an ARD
kernel (squared exponential ``"rbf"`` or Matérn 5/2 ``"matern52"``) with per-output length scales, signal
variance and noise variance. Hyperparameters are fit by maximising the log marginal likelihood with optax's
L-BFGS, in float64, on the host's or accelerator's JAX.

Every posterior, exact or sparse, is stored in one form, so one function evaluates it:

    mean_i(z) = k_i(z, Z)ᵀ w_i,        var_i(z) = s_i − k_i(z, Z)ᵀ V_i k_i(z, Z)

- exact: ``Z = X`` (the data), ``w_i = (K_i + σ_i² I)⁻¹ y_i`` and ``V_i = (K_i + σ_i² I)⁻¹``;
- FITC (Snelson & Ghahramani 2006; what the original's MPC uses): ``Z`` are M inducing points,
  ``w_i = Σ_i⁻¹ K_ZX Γ_i⁻¹ y_i`` and ``V_i = K_ZZ⁻¹ − Σ_i⁻¹`` with ``Σ_i = K_ZZ + K_ZX Γ_i⁻¹ K_XZ`` and
  ``Γ_i = diag(K_XX − Q_XX) + σ_i²``. With ``Z = X`` it equals the exact posterior; its cost per prediction is
  O(M d) instead of O(n d), which bounds the MPC's solve time whatever the amount of data.

``predict(posterior, z, xp)`` is written against the ``xp`` backends of ``scg_jax.backends``: with JAX arrays it
returns ``(mean (m,), var (m,))`` (vmap it for batches); with a CasADi ``SX``/``MX`` column it returns CasADi
expressions ``(m, 1)`` for the MPC. The variance is the latent function's (add ``noise_var`` for a noisy
observation).

Inducing points are chosen by a stated rule, as in the original: k-means (Lloyd) centroids of the training
inputs, each snapped to its nearest training input (distinct points, so they stay on the data).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct
from jax.custom_derivatives import SymbolicZero

from scg_jax.backends import casadi_backend, jax_backend

KERNELS = ("rbf", "matern52")
_SQRT5 = math.sqrt(5.0)
# Added to the scaled squared distance inside the Matérn kernel's square root: its derivative is infinite at 0.
_MATERN_EPS = 1e-12
_JITTER = 1e-6  # relative diagonal jitter of K_ZZ (inducing points can be close)


@struct.dataclass
class GPHyperparams:
    """Hyperparameters of ``m`` independent GPs on ``d`` inputs (positive values, not logs).

    Leaves are numpy float64 arrays as ``hyperparams`` and ``fit_hyperparams`` return them.

    Attributes:
        length_scales: (m, d), in the units of each input.
        signal_var: (m,), in target units squared.
        noise_var: (m,), in target units squared.
    """

    length_scales: jax.Array
    signal_var: jax.Array
    noise_var: jax.Array


@struct.dataclass
class GPPosterior:
    """A fitted GP in the common form above; numpy or JAX arrays.

    Attributes:
        inputs: (M, d) the points ``Z`` the posterior is expressed in (data or inducing points).
        weights: (m, M) mean weights ``w_i``.
        var_matrix: (m, M, M) ``V_i``.
        hyperparams: the ``GPHyperparams``.
        kernel: ``"rbf"`` or ``"matern52"`` (static).
    """

    inputs: jax.Array
    weights: jax.Array
    var_matrix: jax.Array
    hyperparams: GPHyperparams
    kernel: str = struct.field(pytree_node=False, default="rbf")

    @property
    def num_outputs(self) -> int:
        return self.weights.shape[0]

    @property
    def num_inputs(self) -> int:
        return self.inputs.shape[1]


def check_kernel(kernel: str, path: str = "kernel") -> str:
    if kernel not in KERNELS:
        raise ValueError(f"{path}: unknown value {kernel!r}; allowed values are {', '.join(KERNELS)}")
    return kernel


def hyperparams(length_scales, signal_var, noise_var, path: str = "hyperparams") -> GPHyperparams:
    """Checked ``GPHyperparams`` from values: every entry finite and > 0, shapes (m, d), (m,), (m,)."""
    values = {
        "length_scales": np.atleast_2d(np.asarray(length_scales, dtype=float)),
        "signal_var": np.atleast_1d(np.asarray(signal_var, dtype=float)),
        "noise_var": np.atleast_1d(np.asarray(noise_var, dtype=float)),
    }
    m = values["length_scales"].shape[0]
    for name, value in values.items():
        if not np.all(np.isfinite(value)) or np.any(value <= 0.0):
            raise ValueError(f"{path}.{name}: must be positive and finite, got {value.tolist()}")
        if value.shape[0] != m or value.ndim != (2 if name == "length_scales" else 1):
            raise ValueError(f"{path}.{name}: expected {m} outputs, got shape {value.shape}")
    return GPHyperparams(**values)  # numpy float64: JAX would round to float32 outside an x64 scope


# ---------------------------------------------------------------------------------------------------- kernels
def _kernel_of_sq_dist(sq_dist, signal_var, kernel: str, xp):
    """The kernel as a function of the length-scaled squared distance; one definition for both backends."""
    if kernel == "rbf":
        return signal_var * xp.exp(-0.5 * sq_dist)
    r = _SQRT5 * xp.sqrt(sq_dist + _MATERN_EPS)
    return signal_var * (1.0 + r + r * r / 3.0) * xp.exp(-r)


def kernel_matrix(x1, x2, length_scales, signal_var, kernel: str = "rbf"):
    """``K(x1, x2)`` (n1, n2) of one output's kernel; x1 (n1, d), x2 (n2, d), length_scales (d,). JAX only."""
    a, b = x1 / length_scales, x2 / length_scales
    sq = jnp.sum(a * a, -1)[:, None] - 2.0 * a @ b.T + jnp.sum(b * b, -1)[None, :]
    return _kernel_of_sq_dist(jnp.maximum(sq, 0.0), signal_var, kernel, jax_backend)


def _scaled_sq_dist(z, inputs, length_scales, xp):
    """``|(z - x_j) / l|^2`` over the rows ``x_j`` of ``inputs``: (M,) under JAX, (M, 1) under CasADi."""
    inv = 1.0 / np.asarray(length_scales) if xp is casadi_backend else 1.0 / length_scales
    scaled_inputs = inputs * inv  # (M, d) constant
    zs = z * xp.constant(inv)
    sq = xp.dot(zs, zs) - 2.0 * xp.matmul(xp.constant(scaled_inputs), zs)
    return sq + xp.constant((scaled_inputs * scaled_inputs).sum(-1))


def _kernel_vector(z, inputs, length_scales, signal_var, kernel: str, xp):
    """``k(z, Z)``: (M,) under JAX, (M, 1) under CasADi, for one query point z (d,) or (d, 1)."""
    return _kernel_of_sq_dist(_scaled_sq_dist(z, inputs, length_scales, xp), signal_var, kernel, xp)


def predict(posterior: GPPosterior, z, xp=jax_backend):
    """Posterior mean and latent variance at one input ``z``.

    Args:
        posterior: a ``GPPosterior``. For ``xp = casadi_backend`` its arrays must be numpy (``to_numpy``).
        z: (d,) JAX array, or a CasADi column (d, 1) of symbols or numbers.
        xp: the backend namespace.

    Returns:
        ``(mean, var)``: (m,) JAX arrays, or CasADi columns (m, 1).
    """
    hp = posterior.hyperparams
    means, variances = [], []
    for i in range(posterior.num_outputs):
        k = _kernel_vector(z, posterior.inputs, hp.length_scales[i], hp.signal_var[i], posterior.kernel, xp)
        means.append(xp.dot(xp.constant(posterior.weights[i]), k))
        variances.append(hp.signal_var[i] - xp.dot(k, xp.matmul(xp.constant(posterior.var_matrix[i]), k)))
    return xp.stack(means), xp.stack(variances)


@jax.custom_jvp
def predict_mean(posterior: GPPosterior, z):
    """The posterior mean (m,) at ``z`` (d,) in JAX: ``predict``'s mean, with its derivative in ``z`` in closed form.

    Forward-mode derivatives (``jax.jacfwd``, as SQP-RTI linearises its prediction model) get the Jacobian
    ``d mean_i / d z = sum_j w_ij k'_ij 2 (z - x_j) / l_i^2`` (``k'`` the kernel's slope in the scaled squared
    distance ``sq``: ``-k / 2`` for the RBF kernel) once and apply it to every tangent; differentiating the kernel's
    expansion would push each tangent through it. The value is ``predict``'s to the bit; the Jacobian agrees with
    automatic differentiation to round-off. Derivatives in ``posterior`` are ``predict``'s automatic ones.
    """
    return _mean_and_jacobian(posterior, z)[0]


def _mean_and_jacobian(posterior: GPPosterior, z, jacobian: bool = False):
    hp = posterior.hyperparams
    means, rows = [], []
    for i in range(posterior.num_outputs):
        sq = _scaled_sq_dist(z, posterior.inputs, hp.length_scales[i], jax_backend)
        k = _kernel_of_sq_dist(sq, hp.signal_var[i], posterior.kernel, jax_backend)
        means.append(jnp.dot(posterior.weights[i], k))  # predict's operations: the same value
        if jacobian:
            if posterior.kernel == "rbf":
                slope = -0.5 * k
            else:  # Matern 5/2: k = s (1 + r + r^2 / 3) exp(-r), r = sqrt(5 sq); dk/dsq = -5 s (1 + r) exp(-r) / 6
                r = _SQRT5 * jnp.sqrt(sq + _MATERN_EPS)
                slope = -(5.0 / 6.0) * hp.signal_var[i] * (1.0 + r) * jnp.exp(-r)
            inv = 1.0 / hp.length_scales[i]
            diff = (z - posterior.inputs) * inv  # (M, d)
            rows.append(2.0 * inv * jnp.sum((posterior.weights[i] * slope)[:, None] * diff, 0))
    return jnp.stack(means), (jnp.stack(rows) if jacobian else None)


def _predict_mean_jvp(primals, tangents):
    posterior, z = primals
    posterior_tangent, dz = tangents
    if not all(isinstance(t, SymbolicZero) for t in jax.tree.leaves(posterior_tangent)):
        # Derivatives in the posterior (rare: a fit through predictions) go through predict's expression.
        posterior_tangent, dz = (
            jax.tree.map(lambda t, p: jnp.zeros_like(p) if isinstance(t, SymbolicZero) else t, tangent, primal)
            for tangent, primal in ((posterior_tangent, posterior), (dz, z))
        )
        return jax.jvp(lambda p, q: predict(p, q)[0], primals, (posterior_tangent, dz))
    mean, jac = _mean_and_jacobian(posterior, z, jacobian=True)
    if isinstance(dz, SymbolicZero):
        return mean, jnp.zeros_like(mean)
    return mean, jnp.sum(jac * dz[None, :], -1)


predict_mean.defjvp(_predict_mean_jvp, symbolic_zeros=True)


def predict_batch(posterior: GPPosterior, z) -> tuple[np.ndarray, np.ndarray]:
    """``predict`` over a batch ``z`` (N, d) on the host, in float64: mean (N, m), var (N, m) numpy arrays.

    The variance ``s - kᵀ V k`` cancels badly in float32 when the data pins the function down (it can come out
    negative); inside your own jitted code, call ``predict`` under ``jax.enable_x64(True)`` for the same accuracy.
    """
    with jax.enable_x64(True):
        posterior64 = jax.tree.map(lambda a: jnp.asarray(a, jnp.float64), posterior)
        mean, var = jax.vmap(lambda zi: predict(posterior64, zi, jax_backend))(jnp.asarray(z, jnp.float64))
        return np.asarray(mean), np.asarray(var)


def to_numpy(posterior: GPPosterior) -> GPPosterior:
    """The posterior with numpy float64 leaves: what the CasADi path and saving need."""
    return jax.tree.map(lambda a: np.asarray(a, dtype=np.float64), posterior)


@struct.dataclass
class SplitPosterior:
    """A float64 ``GPPosterior`` carried through a float32 program: each leaf as ``hi + lo``, two float32 arrays
    (``hi`` the value rounded to float32, ``lo`` the remainder). A jitted function that takes a GP as an argument
    would round it to float32, and ``s - kᵀ V k`` then loses every digit (``V`` has entries of 1e6 and more when
    inducing points are close); ``predict_split`` rebuilds the float64 values and computes the variance in float64
    inside. ``hi`` alone is the float32 GP (its mean is accurate in float32).

    Attributes:
        hi, lo: ``GPPosterior`` with float32 leaves (``split_posterior``).
    """

    hi: GPPosterior
    lo: GPPosterior


def split_posterior(posterior: GPPosterior) -> SplitPosterior:
    """The ``SplitPosterior`` of a posterior with host (numpy) arrays; ``hi + lo`` equals it to about 1e-14."""
    exact = to_numpy(posterior)
    hi = jax.tree.map(lambda a: a.astype(np.float32), exact)
    lo = jax.tree.map(lambda a, h: (a - h.astype(np.float64)).astype(np.float32), exact, hi)
    return SplitPosterior(hi, lo)


def predict_split(split: SplitPosterior, z):
    """The posterior's latent variance at ``z`` in float64 from a ``SplitPosterior`` (jit- and vmap-able), even with
    x64 off.

    Elementwise operations and sums only, and the distances as differences: under ``vmap`` of a ``lax.scan`` the
    batching of its body happens after the ``enable_x64`` scope is left, and ``dot_general``'s batching rule then
    mixes float32 and float64.

    Args:
        split: the GP. z: (d,) JAX array, float32 or float64.

    Returns:
        var (m,) in ``z``'s dtype.
    """
    with jax.enable_x64(True):
        post = jax.tree.map(lambda h, lo: h.astype(jnp.float64) + lo.astype(jnp.float64), split.hi, split.lo)
        hp = post.hyperparams
        # (m, d, M): the sum over d runs over an axis other than the last, which XLA vectorises (2x faster).
        scaled = (z.astype(jnp.float64)[None, :, None] - post.inputs.T[None]) / hp.length_scales[:, :, None]
        k = _kernel_of_sq_dist(jnp.sum(scaled * scaled, -2), hp.signal_var[:, None], post.kernel, jax_backend)
        # k^T V k = k^T V^T k: summing over V's rows, not its last axis, keeps that axis free for XLA to vectorise.
        var = hp.signal_var - jnp.sum(k * jnp.sum(post.var_matrix * k[:, :, None], -2), -1)
    return var.astype(z.dtype)


def casadi_function(posterior: GPPosterior, name: str = "gp"):
    """``casadi.Function(name, [z (d, 1)], [mean (m, 1), var (m, 1)])`` of the posterior."""
    import casadi as cs

    numpy_posterior = to_numpy(posterior)
    z = cs.SX.sym("z", numpy_posterior.num_inputs)
    mean, var = predict(numpy_posterior, z, casadi_backend)
    return cs.Function(name, [z], [mean, var], ["z"], ["mean", "var"])


# ------------------------------------------------------------------------------------------------- posteriors
def _check_data(inputs, targets):
    x = np.asarray(inputs, dtype=float)
    y = np.asarray(targets, dtype=float)
    if x.ndim != 2 or y.ndim != 2 or x.shape[0] != y.shape[0]:
        raise ValueError(f"data: expected inputs (n, d) and targets (n, m), got {x.shape} and {y.shape}")
    if x.shape[0] == 0:
        raise ValueError("data: no training points")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        raise ValueError("data: inputs and targets must be finite")
    return x, y


def exact_posterior(inputs, targets, hp: GPHyperparams, kernel: str = "rbf") -> GPPosterior:
    """The exact posterior of ``targets`` (n, m) at ``inputs`` (n, d); float64 inside."""
    check_kernel(kernel)
    x, y = _check_data(inputs, targets)
    with jax.enable_x64(True):
        return to_numpy(_exact(jnp.asarray(x), jnp.asarray(y), jax.tree.map(jnp.asarray, hp), kernel))


# Jitted: one compiled program per data shape, where op by op would compile each of its operations apart.
@functools.partial(jax.jit, static_argnames=("kernel",))
def _exact(x, y, hp, kernel):
    def one(ls, s2, noise, yi):
        k = kernel_matrix(x, x, ls, s2, kernel) + noise * jnp.eye(x.shape[0])
        k_inv = jax.scipy.linalg.cho_solve((jnp.linalg.cholesky(k), True), jnp.eye(x.shape[0]))
        return k_inv @ yi, k_inv

    weights, var_matrix = jax.vmap(one)(hp.length_scales, hp.signal_var, hp.noise_var, y.T)
    return GPPosterior(x, weights, var_matrix, hp, kernel)


def fitc_posterior(
    inputs, targets, hp: GPHyperparams, inducing, kernel: str = "rbf", jitter: float = _JITTER
) -> GPPosterior:
    """The FITC sparse posterior on the inducing inputs ``inducing`` (M, d); float64 inside.

    ``jitter`` times the signal variance is added to the diagonal of ``K_ZZ``: inducing points can be close
    together relative to long length scales, and ``K_ZZ`` is then nearly singular.
    """
    check_kernel(kernel)
    x, y = _check_data(inputs, targets)
    z = np.asarray(inducing, dtype=float)
    if z.ndim != 2 or z.shape[1] != x.shape[1]:
        raise ValueError(f"inducing: expected (M, {x.shape[1]}) points, got shape {z.shape}")
    with jax.enable_x64(True):
        return to_numpy(
            _fitc(jnp.asarray(x), jnp.asarray(y), jnp.asarray(z), jax.tree.map(jnp.asarray, hp), kernel, jitter)
        )


@functools.partial(jax.jit, static_argnames=("kernel", "jitter"))
def _fitc(x, y, z, hp, kernel, jitter):
    num_inducing = z.shape[0]

    def one(ls, s2, noise, yi):
        kzz = kernel_matrix(z, z, ls, s2, kernel) + jitter * s2 * jnp.eye(num_inducing)
        kxz = kernel_matrix(x, z, ls, s2, kernel)
        kzz_chol = jnp.linalg.cholesky(kzz)
        kzz_inv = jax.scipy.linalg.cho_solve((kzz_chol, True), jnp.eye(num_inducing))
        q_diag = jnp.sum((kxz @ kzz_inv) * kxz, axis=1)
        gamma = jnp.maximum(s2 - q_diag, 0.0) + noise  # k(x, x) = s2 for both stationary kernels
        sigma = kzz + (kxz / gamma[:, None]).T @ kxz
        sigma_inv = jax.scipy.linalg.cho_solve((jnp.linalg.cholesky(sigma), True), jnp.eye(num_inducing))
        weights = sigma_inv @ (kxz.T @ (yi / gamma))
        return weights, kzz_inv - sigma_inv

    weights, var_matrix = jax.vmap(one)(hp.length_scales, hp.signal_var, hp.noise_var, y.T)
    return GPPosterior(z, weights, var_matrix, hp, kernel)


def select_inducing(inputs, num_inducing: int, key, iterations: int = 20) -> np.ndarray:
    """Indices (num_inducing,) of training inputs used as inducing points.

    The rule: Lloyd's k-means on the inputs (each dimension divided by its standard deviation), started from
    ``num_inducing`` distinct data points drawn with ``key``, run ``iterations`` times; each centroid is then
    snapped to its nearest unused training input.
    """
    x = np.asarray(inputs, dtype=float)
    n = x.shape[0]
    if not isinstance(num_inducing, int | np.integer) or not 1 <= num_inducing <= n:
        raise ValueError(
            f"num_inducing: must be an integer from 1 to the number of data points ({n}), got {num_inducing!r}"
        )
    scale = x.std(axis=0)
    xs = x / np.where(scale > 0, scale, 1.0)
    centroids = xs[np.asarray(jax.random.choice(key, n, (num_inducing,), replace=False))]
    for _ in range(iterations):
        labels = np.argmin(((xs[:, None, :] - centroids[None]) ** 2).sum(-1), axis=1)
        for j in range(num_inducing):
            members = xs[labels == j]
            if len(members):
                centroids[j] = members.mean(axis=0)
    chosen: list[int] = []
    distances = ((centroids[:, None, :] - xs[None]) ** 2).sum(-1)  # (M, n)
    for j in range(num_inducing):
        row = distances[j].copy()
        row[chosen] = np.inf
        chosen.append(int(np.argmin(row)))
    return np.asarray(chosen)


# ------------------------------------------------------------------------------------------ hyperparameters
def negative_log_marginal_likelihood(x, y, hp: GPHyperparams, kernel: str = "rbf"):
    """Sum over outputs of ``-log p(y_i | X, θ_i)``; x (n, d), y (n, m). JAX, differentiable in ``hp``."""
    n = x.shape[0]

    def one(ls, s2, noise, yi):
        k = kernel_matrix(x, x, ls, s2, kernel) + noise * jnp.eye(n)
        chol = jnp.linalg.cholesky(k)
        alpha = jax.scipy.linalg.cho_solve((chol, True), yi)
        return 0.5 * yi @ alpha + jnp.sum(jnp.log(jnp.diag(chol))) + 0.5 * n * jnp.log(2.0 * jnp.pi)

    return jnp.sum(jax.vmap(one)(hp.length_scales, hp.signal_var, hp.noise_var, y.T))


# Bounds of the fit, in standardised units (inputs divided by their standard deviation, targets by theirs): they
# keep the kernel matrix well conditioned when the data is explained by a nearly linear function (the model error
# of a wrong prior often is), which would otherwise drive length scales and signal variance to infinity.
LENGTH_SCALE_BOUNDS = (1e-2, 1e1)
SIGNAL_VAR_BOUNDS = (1e-4, 1e3)
NOISE_VAR_BOUNDS = (1e-4, 1e1)


def _clipped(log_hp: GPHyperparams) -> GPHyperparams:
    """Hyperparameters from their logs, clipped to the bounds of the fit."""
    bounds = (LENGTH_SCALE_BOUNDS, SIGNAL_VAR_BOUNDS, NOISE_VAR_BOUNDS)
    values = (log_hp.length_scales, log_hp.signal_var, log_hp.noise_var)
    return GPHyperparams(*(jnp.exp(jnp.clip(v, *np.log(b))) for v, b in zip(values, bounds, strict=True)))


# Compiled once per data shape, kernel and iteration count: the data are arguments, so every GP-MPC round (new data,
# same shapes) reuses the executable.
@functools.partial(jax.jit, static_argnames=("kernel", "iterations"))
def _fit_standardised(log_hp, x, y, kernel: str, iterations: int):
    """``(fitted hyperparameters, nll at the start, nll at the end)``: ``iterations`` L-BFGS steps from ``log_hp``
    (logs) on standardised data ``x`` (n, d), ``y`` (n, m); float64 under ``jax.enable_x64``."""

    def loss(log_hp):
        return negative_log_marginal_likelihood(x, y, _clipped(log_hp), kernel)

    solver = optax.lbfgs()
    value_and_grad = optax.value_and_grad_from_state(loss)

    def step(carry, _):
        params, state = carry
        value, grad = value_and_grad(params, state=state)
        updates, state = solver.update(grad, state, params, value=value, grad=grad, value_fn=loss)
        return (optax.apply_updates(params, updates), state), value

    (final, _), _ = jax.lax.scan(step, (log_hp, solver.init(log_hp)), None, iterations)
    return _clipped(final), loss(log_hp), loss(final)


def fit_hyperparams(
    inputs,
    targets,
    kernel: str = "rbf",
    init: GPHyperparams | None = None,
    iterations: int = 100,
) -> tuple[GPHyperparams, dict]:
    """Maximise the log marginal likelihood of each output's GP with optax L-BFGS (float64).

    The fit runs on standardised data (each input and target divided by its standard deviation; the GP's mean
    stays zero) over the logs of the hyperparameters, clipped to ``LENGTH_SCALE_BOUNDS``, ``SIGNAL_VAR_BOUNDS``
    and ``NOISE_VAR_BOUNDS`` (standardised units), then maps them back to the data's units exactly (a stationary
    kernel on scaled inputs is the same kernel with scaled length scales). ``iterations`` L-BFGS steps run in one
    compiled ``lax.scan``.

    Returns:
        ``(hyperparams, info)`` in the data's units; ``info`` holds ``nll_initial`` and ``nll_final`` (the summed
        negative log marginal likelihood of the standardised data, nats).
    """
    check_kernel(kernel)
    x, y = _check_data(inputs, targets)
    if not isinstance(iterations, int) or iterations < 1:
        raise ValueError(f"iterations: must be a positive integer, got {iterations!r}")
    x_scale = np.where(x.std(axis=0) > 0, x.std(axis=0), 1.0)
    y_scale = np.where(y.std(axis=0) > 0, y.std(axis=0), 1.0)
    if init is None:
        start = hyperparams(np.ones((y.shape[1], x.shape[1])), np.ones(y.shape[1]), 0.01 * np.ones(y.shape[1]))
    else:
        start = hyperparams(
            np.asarray(init.length_scales) / x_scale, np.asarray(init.signal_var) / y_scale**2,
            np.asarray(init.noise_var) / y_scale**2,
        )  # fmt: skip
    with jax.enable_x64(True):
        log0 = jax.tree.map(lambda v: jnp.log(jnp.asarray(v, jnp.float64)), start)
        fitted, nll0, nll1 = _fit_standardised(
            log0, jnp.asarray(x / x_scale), jnp.asarray(y / y_scale), kernel, iterations
        )
        fitted = jax.tree.map(np.asarray, fitted)
    if not np.isfinite(float(nll1)) or float(nll1) > float(nll0):  # never return worse than the start
        fitted, nll1 = start, nll0
    hyper = hyperparams(
        np.asarray(fitted.length_scales) * x_scale, np.asarray(fitted.signal_var) * y_scale**2,
        np.asarray(fitted.noise_var) * y_scale**2,
    )  # fmt: skip
    return hyper, {"nll_initial": float(nll0), "nll_final": float(nll1)}


def hyperparams_dict(hp: GPHyperparams) -> Mapping[str, list]:
    """JSON-ready hyperparameters."""
    return {name: np.asarray(getattr(hp, name)).tolist() for name in ("length_scales", "signal_var", "noise_var")}
