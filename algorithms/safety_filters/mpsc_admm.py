"""An OSQP-style ADMM for many small QPs that share their matrices: ``min 1/2 z^T H z + q^T z  s.t.  G z <= h`` with
``H`` (nz, nz) and ``G`` (p, nz) the same for every copy and only ``q`` and ``h`` per copy.

The linear system of every iteration, ``(H + sigma I + rho G^T G) x = rhs``, has the same matrix for every copy and
every iteration, so it is inverted once on the host (float64, then cast) and each iteration is two small matrix
products; under ``jax.vmap`` they become one batched product against the shared matrix. A fixed number of
iterations (``lax.fori_loop``) keeps every lane in step, so a vmapped batch costs what one lane costs per
iteration. Iteration (Stellato et al. 2020, with relaxation ``alpha`` and one-sided bounds)::

    x~ = M^-1 (sigma x - q + G^T (rho s - y))       M = H + sigma I + rho G^T G
    s~ = G x~
    x  = alpha x~ + (1 - alpha) x,   r = alpha s~ + (1 - alpha) s
    s  = min(r + y / rho, h),        y = y + rho (r - s)

Accuracy is set by the iteration count (no early stop; see ``benchmarks/mpsc.py`` for the error against a
reference); the returned ``violation`` ``max(G x - h)`` tells an infeasible or unconverged QP (in the rows' units).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np


class ADMMSolution(NamedTuple):
    """``z`` (nz,) primal iterate, ``y`` (p,) dual iterate (warm start of the next solve), ``violation`` the largest
    ``G z - h``."""

    z: Any
    y: Any
    violation: Any


def admm_inverse(hess, G, rho: float, sigma: float, dtype=None):
    """The shared ``(H + sigma I + rho G^T G)^-1`` (nz, nz), computed in float64 on the host and cast to ``dtype``."""
    hess = np.asarray(hess, dtype=np.float64)
    G = np.asarray(G, dtype=np.float64)
    M = hess + sigma * np.eye(hess.shape[0]) + rho * G.T @ G
    dtype = jnp.zeros(()).dtype if dtype is None else dtype
    return jnp.asarray(np.linalg.inv(0.5 * (M + M.T)), dtype)


def admm_solve(M_inv, G, q, h, *, iterations: int, rho: float, sigma: float, alpha: float, z0=None, y0=None):
    """Solve one QP (jit/vmap-able; vmap over ``q``, ``h``, ``z0``, ``y0`` with ``M_inv`` and ``G`` shared).

    Args:
        M_inv: (nz, nz) from ``admm_inverse`` with the same ``rho``, ``sigma``. G: (p, nz). q: (nz,). h: (p,).
        iterations: fixed iteration count. rho, sigma, alpha: ADMM step, proximal weight, relaxation (0, 2).
        z0, y0: warm start (default zeros); the slack starts at ``min(G z0, h)``.

    Returns:
        ``ADMMSolution``.
    """
    dtype = M_inv.dtype
    z = jnp.zeros(G.shape[1], dtype) if z0 is None else jnp.asarray(z0, dtype)
    y = jnp.zeros(G.shape[0], dtype) if y0 is None else jnp.asarray(y0, dtype)
    q = jnp.asarray(q, dtype)
    h = jnp.asarray(h, dtype)
    s = jnp.minimum(G @ z, h)

    def body(_, carry):
        z, s, y = carry
        z_tilde = M_inv @ (sigma * z - q + G.T @ (rho * s - y))
        s_tilde = G @ z_tilde
        z = alpha * z_tilde + (1.0 - alpha) * z
        r = alpha * s_tilde + (1.0 - alpha) * s
        s_new = jnp.minimum(r + y / rho, h)
        y = y + rho * (r - s_new)
        return z, s_new, y

    z, s, y = jax.lax.fori_loop(0, iterations, body, (z, s, y))
    return ADMMSolution(z, y, jnp.max(G @ z - h))


__all__ = ["ADMMSolution", "admm_inverse", "admm_solve"]
