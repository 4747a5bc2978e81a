"""What the backup barrier (``cbf``) and the model predictive safety filters (``mpsc_linear``) share: the states a
filter is checked on, and the candidate weights of the backup LQR that holds the plant inside the constraint.

A backup controller is an LQR of the prior about a safe set-point. The set of states from which it keeps every row
is the backup barrier's safe set and the MPSC's terminal set; a faster, tighter backup saves more states where a
coordinate must be held (the cart-pole's pole), a looser one where it may move (a cart far from the centre while the
pole's angle is bounded). ``backup_weights`` proposes both kinds and the filters keep the one whose safe set holds
the most ``validation_states``.
"""

from __future__ import annotations

import jax
import numpy as np

from scg_algorithms.controller_setup import input_limits
from scg_jax.validation import weight_matrix


def state_box(env, prior_params) -> tuple[np.ndarray, np.ndarray]:
    """``(low, high)`` (nx,) the per-coordinate bounds of the env's state constraints (``-inf``/``inf`` if none)."""
    from scg_jax.constraints import box_bounds

    x_low, x_high, _, _ = box_bounds(env.constraint_specs, prior_params.constraints, env.nx, env.nu)
    return x_low, x_high


def validation_box(env, prior_params) -> tuple[np.ndarray, np.ndarray]:
    """``(low, high)`` (nx,) the box ``is_valid_cbf`` and the braking deceleration sample: the state constraint's
    box within the system's failure bounds, and +-2 (the coordinate's units) where both are unbounded."""
    low, high = state_box(env, prior_params)
    low = np.maximum(low, env.system.state_low)
    high = np.minimum(high, env.system.state_high)
    return np.where(np.isfinite(low), low, -2.0), np.where(np.isfinite(high), high, 2.0)


def validation_states(env, prior_params, count: int, key=None) -> np.ndarray:
    """(count, nx) states to check a barrier on: half uniform in ``validation_box``, half uniform in the env's
    initial-state box (all in ``validation_box`` when the initial state is not drawn from a box), so the check
    covers both the whole constrained region and the states episodes start from."""
    key = jax.random.key(0) if key is None else key
    low, high = validation_box(env, prior_params)
    unit = np.asarray(jax.random.uniform(key, (count, env.nx)), dtype=np.float64)
    states = unit * (high - low) + low
    if env.init_state_spec.type == "uniform":
        init_low = np.asarray(prior_params.init_state.low, dtype=np.float64).reshape(env.nx)
        init_high = np.asarray(prior_params.init_state.high, dtype=np.float64).reshape(env.nx)
        half = count // 2
        states[half:] = unit[half:] * (init_high - init_low) + init_low
    return states


def failure_rows(system) -> tuple[np.ndarray, np.ndarray]:
    """``(A (k, nx), b (k,))``: the system's finite failure bounds (``state_low``, ``state_high``, where an episode
    ends out of bounds) as rows ``a^T x <= b``; a backup or a plan that crosses them has lost the plant."""
    A, b = [], []
    for i in range(system.nx):
        for sign, bound in ((1.0, system.state_high[i]), (-1.0, -system.state_low[i])):
            if np.isfinite(bound):
                A.append(sign * np.eye(system.nx)[i])
                b.append(bound)
    return np.asarray(A, dtype=np.float64).reshape(-1, system.nx), np.asarray(b, dtype=np.float64)


def sample_states(low, high, count: int, seed: int = 0) -> np.ndarray:
    """(count, nx) states uniform in the box ``low``, ``high`` from numpy's generator seeded ``seed``."""
    return np.random.default_rng(seed).uniform(low, high, size=(count, len(low)))


def backup_weights(env, prior_params, A, b, x_backup) -> list[tuple[np.ndarray, np.ndarray]]:
    """Candidate diagonal weights ``(q (nx,), r (nu,))`` of the backup LQR; ``backup_setup`` keeps the one whose
    barrier holds the most sampled states safe.

    Bryson's rule on the room the rows leave around ``x_backup``: a coordinate a row bounds alone weighs
    ``1 / d^2``, ``d`` its distance from ``x_backup`` to the nearer bound; velocities weigh 1. The other
    configuration coordinates (``velocity_mask`` 0) weigh either 1 or as much as the tightest bounded one: the first
    leaves them free (a cart far from the centre may return slowly while its pole angle is bounded), the second
    holds them as tightly as the constraint (the pole upright while the cart is bounded, since a falling pole drags
    the cart out). Inputs weigh ``r = 0.1 / (half the input range)^2`` or a hundredth of it (a fast backup keeps
    the plant tighter but saturates).
    """
    bounded = np.zeros(env.nx)
    for row, bound in zip(A, b, strict=True):
        support = np.flatnonzero(row)
        if support.size == 1:
            i = support[0]
            distance = (bound - row @ x_backup) / abs(row[i])
            bounded[i] = max(bounded[i], 1.0 / distance**2)
    free = (np.asarray(env.system.velocity_mask) == 0) & (bounded == 0)
    tightest = max(bounded.max(), 1.0)
    q_options = [np.where(bounded > 0, bounded, 1.0)]
    if np.any(free) and tightest > 1.0:
        q_options.append(np.where(bounded > 0, bounded, np.where(free, tightest, 1.0)))
    u_low, u_high = input_limits(env, prior_params)
    r = 0.1 / (0.5 * (u_high - u_low)) ** 2
    return [(q, scale * r) for q in q_options for scale in (1.0, 0.01)]


def diagonal_weight(value, path: str, default, n: int) -> np.ndarray:
    """(n,) a diagonal weight option: ``value`` checked by ``scg_jax.validation.weight_matrix``, or ``default``
    where the option is not given (``None``)."""
    if value is None:
        return np.asarray(default, dtype=np.float64).reshape(n)
    return np.diag(weight_matrix(value, path, n, diagonal_only=True))


__all__ = [
    "backup_weights",
    "diagonal_weight",
    "failure_rows",
    "sample_states",
    "state_box",
    "validation_box",
    "validation_states",
]
