"""Chance-constraint tightening from a propagated state covariance (the "cautious" part of GP-MPC).

Along a plan ``(x_i, u_i)`` the deviation ``δx`` of the true state is driven by the GP's predictive variance
``var_i`` (one independent GP per state dimension) and fed back by an ancillary gain ``K`` (``δu = -K δx``, the
LQR gain of the prior's linearisation, as in the original suite). With the plan's linearisation
``δx_{i+1} = A_i δx_i + B_i δu_i + w_i`` and ``w_i ~ N(0, diag(var_i))``, the covariance propagates as

    Σ_{i+1} = (A_i - B_i K) Σ_i (A_i - B_i K)ᵀ + diag(var_i),      Σ_0 given (measurement uncertainty)

(Hewing et al. 2020, eq. 22, the "mean equivalence" approximation evaluated along the previous plan).

A linear constraint row ``a_x ᵀ x_{i+1} + a_u ᵀ u_i <= b`` (the pair the env checks after step ``i``) holds with
probability ``prob`` (jointly over the ``nx`` dimensions, by a two-sided Bonferroni bound as in the original) when
the nominal plan satisfies it with the margin

    margin_i = z_q · ( sqrt(a_xᵀ Σ_{i+1} a_x) + sqrt(a_uᵀ K Σ_i Kᵀ a_u) ),     z_q = Φ⁻¹(1 - (1 - prob) / (2 nx)).

For a row on states only or inputs only this is z_q times the row's exact standard deviation; for a mixed row the
sum of the two standard deviations bounds the combined one from above (Cauchy-Schwarz), so the margin is safe.
The original multiplies ``|a|`` by the marginal standard deviations, which is the same for rows on a single
entry (box constraints).
"""

from __future__ import annotations

import numpy as np
from scipy.stats import norm


def quantile(prob: float, nx: int) -> float:
    """``z_q = Φ⁻¹(1 - (1 - prob) / (2 nx))``; e.g. 2.4977 for ``prob = 0.95``, ``nx = 4``."""
    if not 0.0 < prob < 1.0:
        raise ValueError(f"prob: must be in (0, 1), got {prob!r}")
    if nx < 1:
        raise ValueError(f"nx: must be a positive integer, got {nx!r}")
    return float(norm.ppf(1.0 - (1.0 - prob) / (2.0 * nx)))


def propagate_covariance(A, B, K, model_var, sigma0) -> np.ndarray:
    """State covariances along a horizon.

    Args:
        A: (H, nx, nx) and B: (H, nx, nu), the linearisation of the prediction model at each stage of the plan.
        K: (nu, nx) the ancillary feedback gain (``δu = -K δx``).
        model_var: (H, nx) the GP's predictive variance of the model error at each stage.
        sigma0: (nx, nx) covariance of the initial state.

    Returns:
        (H + 1, nx, nx) covariances ``Σ_0 .. Σ_H``.
    """
    A, B, K = np.asarray(A, float), np.asarray(B, float), np.asarray(K, float)
    model_var = np.asarray(model_var, float)
    sigmas = [np.asarray(sigma0, float)]
    for i in range(A.shape[0]):
        closed = A[i] - B[i] @ K
        sigma = closed @ sigmas[-1] @ closed.T + np.diag(model_var[i])
        sigmas.append(0.5 * (sigma + sigma.T))  # symmetric against round-off
    return np.stack(sigmas)


def propagate_covariance_scan(A, B, K, model_var, sigma0):
    """``propagate_covariance`` in JAX (a ``lax.scan``; jit- and vmap-able), same arguments, a JAX array."""
    import jax
    import jax.numpy as jnp

    from scg_algorithms.mpc.structured import small_matmul
    from scg_jax.tracing import batched_like

    def stage(sigma, inputs):
        A_i, B_i, var_i = inputs
        closed = A_i - small_matmul(B_i, K)
        sigma = small_matmul(small_matmul(closed, sigma), closed.T) + jnp.diag(var_i)
        sigma = 0.5 * (sigma + sigma.T)
        return sigma, sigma

    sigma0 = jnp.asarray(sigma0, A.dtype)
    _, rest = jax.lax.scan(stage, batched_like(sigma0, A), (A, B, model_var))
    return jnp.concatenate([sigma0[None], rest], axis=0)


def margins(rows_x, rows_u, sigmas, K, z_q: float, xp=np):
    """Tightening of every linear row at every stage of a horizon.

    Args:
        rows_x: (ng, nx) and rows_u: (ng, nu): the rows ``a_x``, ``a_u`` of ``a_x x_{i+1} + a_u u_i <= b``; or
            (H, ng, nx) and (H, ng, nu), one set per stage (the Jacobians of nonlinear constraints along a plan).
        sigmas: (H + 1, nx, nx) state covariances ``Σ_0 .. Σ_H`` from ``propagate_covariance``.
        K: (nu, nx) the ancillary gain. z_q: the quantile from ``quantile``. xp: ``numpy`` (float64 arrays) or
            ``jax.numpy`` (traced, in the JAX GP-MPC).

    Returns:
        (H, ng) margins to subtract from ``b`` (or add to ``g``) at stages ``0 .. H-1``.
    """
    dtype = float if xp is np else sigmas.dtype
    sigmas, K = xp.asarray(sigmas, dtype), xp.asarray(K, dtype)
    H = sigmas.shape[0] - 1
    rows_x = xp.broadcast_to(xp.asarray(rows_x, dtype), (H, *np.shape(rows_x)[-2:]))
    rows_u = xp.broadcast_to(xp.asarray(rows_u, dtype), (H, *np.shape(rows_u)[-2:]))
    state_var = xp.einsum("sgi,sij,sgj->sg", rows_x, sigmas[1:], rows_x)
    input_rows = rows_u @ K  # a_uᵀ K, per stage
    input_var = xp.einsum("sgi,sij,sgj->sg", input_rows, sigmas[:-1], input_rows)
    return z_q * (xp.sqrt(xp.maximum(state_var, 0.0)) + xp.sqrt(xp.maximum(input_var, 0.0)))
