"""Infinite-horizon discrete-time LQR gains.

Convention (used by every caller in this package): the feedback law is

    u = u_ref - K (x - x_ref)

with ``K`` of shape (nu, nx), so a *positive* gain entry pushes the input *against* a positive state error. For
the linearisation ``dx_{k+1} = Ad dx_k + Bd du_k`` (``dx = x - x_ref``, ``du = u - u_ref``) the gain minimises
``sum_k dx_k^T Q dx_k + du_k^T R du_k`` and the closed loop is ``dx_{k+1} = (Ad - Bd K) dx_k``. ``P`` is the
stabilising solution of the discrete algebraic Riccati equation, so the optimal cost from ``dx_0`` is
``dx_0^T P dx_0`` (the env's reward has a factor 1/2 on both terms, which scales ``P`` but leaves ``K`` alone).
"""

from __future__ import annotations

import numpy as np
import scipy.linalg


def _matrix(name: str, value, shape: tuple[int, int]) -> np.ndarray:
    array = np.asarray(value, dtype=np.float64)
    if array.shape != shape:
        raise ValueError(f"{name}: expected shape {shape}, got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name}: entries must be finite")
    return array


def discrete_lqr_gain(Ad, Bd, Q, R) -> tuple[np.ndarray, np.ndarray]:
    """Discrete LQR gain and Riccati solution.

    Args:
        Ad: (nx, nx) discrete state Jacobian. Bd: (nx, nu) discrete input Jacobian.
        Q: (nx, nx) symmetric positive semidefinite state weight. R: (nu, nu) symmetric positive definite input
            weight. Units follow the state and input (SI: m, rad, N); computed in float64.

    Returns:
        ``(K, P)``: K (nu, nx) with ``u = u_ref - K (x - x_ref)``, i.e. ``K = (R + Bd^T P Bd)^-1 Bd^T P Ad``;
        P (nx, nx), the symmetric stabilising solution of
        ``P = Ad^T P Ad - Ad^T P Bd (R + Bd^T P Bd)^-1 Bd^T P Ad + Q``.

    Raises:
        ValueError: on inconsistent shapes, non-finite entries, or when no stabilising solution exists (for
            example an unstabilisable ``(Ad, Bd)``).
    """
    Ad = np.asarray(Ad, dtype=np.float64)
    if Ad.ndim != 2 or Ad.shape[0] != Ad.shape[1]:
        raise ValueError(f"Ad: expected a square (nx, nx) matrix, got shape {Ad.shape}")
    nx = Ad.shape[0]
    Bd = np.asarray(Bd, dtype=np.float64)
    if Bd.ndim != 2 or Bd.shape[0] != nx:
        raise ValueError(f"Bd: expected shape ({nx}, nu), got {Bd.shape}")
    nu = Bd.shape[1]
    Ad = _matrix("Ad", Ad, (nx, nx))
    Bd = _matrix("Bd", Bd, (nx, nu))
    Q = _matrix("Q", Q, (nx, nx))
    R = _matrix("R", R, (nu, nu))
    try:
        P = scipy.linalg.solve_discrete_are(Ad, Bd, Q, R)
    except (np.linalg.LinAlgError, ValueError) as error:
        raise ValueError(f"discrete_lqr_gain: no stabilising Riccati solution ({error})") from error
    # The solver returns P up to round-off asymmetry; symmetrising keeps x^T P x consistent for callers.
    P = 0.5 * (P + P.T)
    K = np.linalg.solve(R + Bd.T @ P @ Bd, Bd.T @ P @ Ad)
    return K, P


def lqr_gain_about(env, params, x0, u0) -> np.ndarray:
    """LQR gain of ``env``'s discrete dynamics linearised about ``(x0, u0)`` with the cost weights in ``params``.

    The linearisation is that of ``env.symbolic_model(params)`` (the env's own integrator and substeps over one
    control period), so the gain is for the plant as the controller's prior ``params`` describe it.

    Args:
        env: an ``scg_jax.Env``. params: unbatched ``EnvParams``; ``params.Q`` (nx, nx) and ``params.R``
            (nu, nu) are the weights. x0: (nx,) operating state. u0: (nu,) operating input, N (e.g. the hover
            thrust from ``env.reference_at``).

    Returns:
        K (nu, nx) float64, for ``u = u_ref - K (x - x_ref)``.
    """
    lin = env.symbolic_model(params).linearize(np.asarray(x0, dtype=np.float64), np.asarray(u0, dtype=np.float64))
    K, _ = discrete_lqr_gain(lin.Ad, lin.Bd, np.asarray(params.Q), np.asarray(params.R))
    return K
