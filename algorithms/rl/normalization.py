"""Running mean and variance of observations (parallel Welford / Chan et al.) and observation normalisation.

``update_stats`` merges a batch into the running statistics with the pairwise formula of Chan, Golub and LeVeque,
so after any sequence of batches ``mean`` and ``var`` equal ``np.mean`` and ``np.var`` (population, ``ddof=0``) of
their concatenation, without keeping the data. Before the first update ``mean = 0`` and ``var = 1``, so
``normalize`` is the identity (up to the clip).
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import jax.numpy as jnp


class RunningStats(NamedTuple):
    """Statistics of everything seen so far.

    Attributes:
        mean: (size,) mean. var: (size,) population variance (1 before the first update).
        count: scalar, number of samples seen (float, so it merges without integer overflow).
    """

    mean: Any
    var: Any
    count: Any


def init_stats(size: int, dtype=jnp.float32) -> RunningStats:
    """Empty statistics of vectors of ``size`` entries."""
    return RunningStats(mean=jnp.zeros(size, dtype), var=jnp.ones(size, dtype), count=jnp.zeros((), dtype))


def update_stats(stats: RunningStats, batch) -> RunningStats:
    """Merge ``batch`` (B, size) (or any (..., size): every leading axis counts as samples) into ``stats``.

    With ``n_a = count``, ``n_b = B``, ``d = mean_b - mean_a``, ``n = n_a + n_b``:
    ``mean = mean_a + d n_b / n`` and ``var = (n_a var_a + n_b var_b + d^2 n_a n_b / n) / n``.
    """
    batch = jnp.asarray(batch, stats.mean.dtype)
    if batch.shape[-1:] != stats.mean.shape[-1:]:
        raise ValueError(f"batch of shape {batch.shape} does not end in the statistics' size {stats.mean.shape[-1]}")
    # Reduce over the leading axes in place rather than reshaping to (B, size) first: when the env axis of a
    # (T, N, size) batch is sharded over a mesh, merging T and N into one axis has no sharded layout, so GSPMD
    # all-gathered the whole buffer to every device; a reduction over (T, N) is a local sum plus an all-reduce
    # of (size,) partial sums.
    axes = tuple(range(batch.ndim - 1))
    n_b = jnp.asarray(math.prod(batch.shape[:-1]), stats.count.dtype)
    mean_b = jnp.mean(batch, axis=axes)
    var_b = jnp.mean(jnp.square(batch - mean_b), axis=axes)
    n_a = stats.count
    n = n_a + n_b
    delta = mean_b - stats.mean
    mean = stats.mean + delta * (n_b / n)
    # var_a is 1 (a placeholder) while n_a = 0; the weight n_a removes it.
    m2 = stats.var * n_a + var_b * n_b + jnp.square(delta) * (n_a * n_b / n)
    return RunningStats(mean=mean, var=m2 / n, count=n)


def normalize(stats: RunningStats, obs, clip: float = 10.0):
    """``clip((obs - mean) / sqrt(var + 1e-8), -clip, clip)``, elementwise over the last axis of ``obs``."""
    scaled = (obs - stats.mean) / jnp.sqrt(stats.var + 1e-8)
    return jnp.clip(scaled, -clip, clip)
