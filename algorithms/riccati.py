"""Infinite-horizon LQR gains from the Riccati equations (float64, scipy); ``scg_algorithms.lqr`` has the controller.

Convention (used by every caller in this package): the feedback law is ``u = u_ref - K (x - x_ref)`` with ``K`` of
shape (nu, nx); see ``scg_algorithms.lqr``.
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


def _riccati(caller: str, solve, A, B, Q, R) -> np.ndarray:
    """The symmetric stabilising solution of scipy's ``solve`` (``solve_discrete_are`` or ``solve_continuous_are``);
    a solver failure is a ValueError naming ``caller``."""
    try:
        P = solve(A, B, Q, R)
    except (np.linalg.LinAlgError, ValueError) as error:
        raise ValueError(f"{caller}: no stabilising Riccati solution ({error})") from error
    # The solver returns P up to round-off asymmetry; symmetrising keeps x^T P x consistent for callers.
    return 0.5 * (P + P.T)


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
    P = _riccati("discrete_lqr_gain", scipy.linalg.solve_discrete_are, Ad, Bd, Q, R)
    K = np.linalg.solve(R + Bd.T @ P @ Bd, Bd.T @ P @ Ad)
    return K, P


def continuous_lqr_gain(A, B, Q, R) -> tuple[np.ndarray, np.ndarray]:
    """Continuous LQR: ``K = R^-1 B^T P`` with ``P`` the stabilising solution of ``A^T P + P A - P B R^-1 B^T P + Q
    = 0``; same sign convention as ``discrete_lqr_gain`` (``u = u_ref - K (x - x_ref)``)."""
    A = np.asarray(A, dtype=np.float64)
    B = np.asarray(B, dtype=np.float64)
    nx, nu = B.shape
    A = _matrix("A", A, (nx, nx))
    Q = _matrix("Q", Q, (nx, nx))
    R = _matrix("R", R, (nu, nu))
    P = _riccati("continuous_lqr_gain", scipy.linalg.solve_continuous_are, A, B, Q, R)
    return np.linalg.solve(R, B.T @ P), P


__all__ = ["continuous_lqr_gain", "discrete_lqr_gain"]
