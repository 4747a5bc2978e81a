"""Episode metrics of a batched rollout, in plain numpy (no JAX: the inputs may be saved ``.npz`` arrays).

All functions look at the *first* episode of each copy of a rollout made with ``auto_reset=False``: arrays are
time-major ``(T, N, ...)`` as in ``scg_jax.Trajectory``, and a copy that finished keeps stepping past its end, so
everything after its first ``terminated | truncated`` step is ignored.

Definitions, per copy ``i`` (``k`` is the control step, 0-based):

- ``length``: ``k* + 1`` for the first ``k*`` where ``terminated[k] | truncated[k]``; ``T`` when neither is ever
  set (the rollout was shorter than the episode). In control steps.
- ``return``: ``sum_{k < length} reward[k]``.
- ``rmse``: ``sqrt(mean_{k < length} mse[k])``, with ``mse`` the env's ``info["mse"]`` (the ``mse_weight``-weighted
  squared error of ``x_{k+1}`` against ``x_ref[k+1]``, m^2 with the default weights), so in m.
- ``crashed``: the episode ended by ``terminated`` (not by the time limit) and the final step was
  ``info["out_of_bounds"] | info["nonfinite"]``. Reaching the goal with ``done_on_goal`` is not a crash.
- ``violation_steps``: ``sum_{k < length} cost[k]``, the env's constrained-MDP cost (1 at a step with any violated
  constraint row), i.e. the number of steps in violation; 0 without constraints.
- ``failed``: the paper's failure, an episode with any violation: ``violation_steps > 0`` or ``crashed`` (leaving
  the failure bounds counts even when no state constraint is configured).

The summary takes the mean and the population standard deviation (``ddof=0``) over copies. ``cvar`` gives the
paper's worst-case RMSE: the conditional value at risk of the per-episode RMSE at level 0.5, the mean of the worst
half of the episodes.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np


def episode_lengths(terminated, truncated) -> np.ndarray:
    """Length of each copy's first episode in control steps.

    Args:
        terminated, truncated: (T, N) booleans from ``Env.step``.

    Returns:
        (N,) int64 in ``[1, T]``.
    """
    done = np.asarray(terminated, dtype=bool) | np.asarray(truncated, dtype=bool)
    if done.ndim != 2:
        raise ValueError(f"terminated, truncated: expected (T, N) arrays, got shape {done.shape}")
    return np.where(done.any(axis=0), done.argmax(axis=0) + 1, done.shape[0]).astype(np.int64)


def episode_metrics(reward, terminated, truncated, mse, out_of_bounds, nonfinite, cost=None) -> dict[str, np.ndarray]:
    """Per-copy metrics of the first episode (definitions in the module docstring).

    Args:
        reward, mse: (T, N) floats. terminated, truncated, out_of_bounds, nonfinite: (T, N) booleans.
        cost: optional (T, N) constrained-MDP cost (zeros when omitted).

    Returns:
        ``{"length": (N,) int64, "return": (N,) float64, "rmse": (N,) float64, "crashed": (N,) bool,
        "violation_steps": (N,) float64, "failed": (N,) bool}``.
    """
    terminated = np.asarray(terminated, dtype=bool)
    truncated = np.asarray(truncated, dtype=bool)
    reward = np.asarray(reward, dtype=np.float64)
    mse = np.asarray(mse, dtype=np.float64)
    cost = np.zeros(mse.shape) if cost is None else np.asarray(cost, dtype=np.float64)
    failure = np.asarray(out_of_bounds, dtype=bool) | np.asarray(nonfinite, dtype=bool)
    shape = terminated.shape
    checks = (("truncated", truncated), ("reward", reward), ("mse", mse), ("out_of_bounds", failure), ("cost", cost))
    for name, array in checks:
        if array.shape != shape:
            raise ValueError(f"{name}: expected shape {shape} like terminated, got {array.shape}")

    length = episode_lengths(terminated, truncated)
    in_episode = np.arange(shape[0])[:, None] < length[None, :]
    # np.where rather than a product: steps past the episode's end may hold inf or nan and must not leak in.
    episode_return = np.where(in_episode, reward, 0.0).sum(axis=0)
    rmse = np.sqrt(np.where(in_episode, mse, 0.0).sum(axis=0) / length)
    last = length - 1
    copies = np.arange(shape[1])
    crashed = terminated[last, copies] & failure[last, copies]
    violation_steps = np.where(in_episode, cost, 0.0).sum(axis=0)
    return {
        "length": length,
        "return": episode_return,
        "rmse": rmse,
        "crashed": crashed,
        "violation_steps": violation_steps,
        "failed": crashed | (violation_steps > 0),
    }


def trajectory_metrics(trajectory: Any) -> dict[str, np.ndarray]:
    """``episode_metrics`` of a non-auto-reset ``scg_jax.Trajectory`` (or any object with the same fields)."""
    info = trajectory.info
    return episode_metrics(
        trajectory.reward,
        trajectory.terminated,
        trajectory.truncated,
        info["mse"],
        info["out_of_bounds"],
        info["nonfinite"],
        trajectory.cost,
    )


def summarize(per_copy: Mapping[str, np.ndarray]) -> dict[str, float]:
    """Mean and std over copies of ``episode_metrics``'s output.

    Returns:
        ``rmse_mean``, ``rmse_std`` (m with the default ``mse_weight``), ``return_mean``, ``return_std``,
        ``length_mean``, ``length_std`` (control steps), ``violation_steps_mean``, ``violation_steps_std``,
        ``worst_case_rmse_at_0.5`` (``cvar(rmse, 0.5)``), ``failure_rate`` and ``crash_rate`` (fractions of failed
        and crashed copies in [0, 1]) and ``num_envs``; plain Python numbers, ready for JSON.
    """
    summary: dict[str, float] = {}
    for name in ("rmse", "return", "length", "violation_steps"):
        values = np.asarray(per_copy[name], dtype=np.float64)
        summary[f"{name}_mean"] = float(values.mean())
        summary[f"{name}_std"] = float(values.std())
    summary["worst_case_rmse_at_0.5"] = cvar(per_copy["rmse"], 0.5)
    summary["failure_rate"] = float(np.asarray(per_copy["failed"], dtype=np.float64).mean())
    summary["crash_rate"] = float(np.asarray(per_copy["crashed"], dtype=np.float64).mean())
    summary["num_envs"] = int(np.asarray(per_copy["failed"]).shape[0])
    return summary


def cvar(values, alpha: float = 0.5) -> float:
    """Conditional value at risk of the upper tail: the mean of the largest ``alpha`` share of ``values``.

    With ``n`` values sorted in decreasing order ``v_1 >= ... >= v_n``, the tail holds ``alpha n`` values; when that
    is not a whole number the boundary value enters with its fractional weight (the exact CVaR of the empirical
    distribution), so ``cvar(v, 1) == mean(v)`` and ``cvar(v, 1 / n) == max(v)``. ``cvar([1, 2, 3, 4], 0.5)`` is
    3.5; ``cvar([1, 2, 3], 0.5)`` is ``(3 + 0.5 * 2) / 1.5 = 2.667``.

    Args:
        values: (n,) finite numbers, n >= 1 (e.g. per-episode RMSEs in m). alpha: tail share in (0, 1].

    Returns:
        A float in the units of ``values``.
    """
    values = np.sort(np.asarray(values, dtype=np.float64).ravel())[::-1]
    if values.size == 0:
        raise ValueError("values: expected at least one value")
    if not np.all(np.isfinite(values)):
        raise ValueError("values: must be finite")
    if not 0.0 < alpha <= 1.0:
        raise ValueError(f"alpha: must be in (0, 1], got {alpha!r}")
    tail = alpha * values.size
    weights = np.clip(tail - np.arange(values.size), 0.0, 1.0)
    return float(np.dot(weights, values) / tail)
