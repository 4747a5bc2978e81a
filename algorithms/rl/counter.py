"""An exact step counter past 2^31 without ``jax_enable_x64``: two ``uint32`` words, ``value = hi * 2^32 + lo``.

JAX's default integer is int32 (int64 needs x64 mode, which slows everything else), and an int32 count of env
steps overflows at 2^31 ~ 2.1e9, a few hours of a GPU run; float32 stops counting exactly at 2^24. A ``Count`` adds
with a carry from ``lo`` into ``hi``, so it is exact up to 2^64. Inside ``jit`` it is read approximately as a float
(``count_to_float``, for curves); on the host ``count_value`` gives the exact Python integer.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np

_WORD = 2**32


class Count(NamedTuple):
    """A non-negative integer ``hi * 2^32 + lo``; both fields ``uint32`` arrays of the same shape (scalars in a
    runner state, (T,) in a scan's metrics)."""

    hi: Any
    lo: Any


def zero_count() -> Count:
    """``Count`` of 0 (scalar)."""
    return Count(jnp.zeros((), jnp.uint32), jnp.zeros((), jnp.uint32))


def add_count(count: Count, n) -> Count:
    """``count + n`` exactly; ``n`` a non-negative integer below 2^32 (a Python int, checked, or a traced uint32 /
    int32 scalar). ``lo`` wraps modulo 2^32 (unsigned arithmetic) and the wrap carries one into ``hi``."""
    if isinstance(n, int) and not 0 <= n < _WORD:
        raise ValueError(f"add_count: n must be in [0, 2^32), got {n}")
    n = jnp.asarray(n).astype(jnp.uint32)
    lo = count.lo + n
    carry = (lo < count.lo).astype(jnp.uint32)
    return Count(count.hi + carry, lo)


def count_at_least(count: Count, n: int):
    """``count >= n`` (bool array) for a Python int ``0 <= n < 2^32``."""
    if not 0 <= n < _WORD:
        raise ValueError(f"count_at_least: n must be in [0, 2^32), got {n}")
    return (count.hi > 0) | (count.lo >= jnp.uint32(n))


def count_to_float(count: Count, dtype=jnp.float32):
    """``hi * 2^32 + lo`` as a float (exact below 2^24 in float32; for plots and rates, not for bookkeeping)."""
    return count.hi.astype(dtype) * float(_WORD) + count.lo.astype(dtype)


def count_value(count: Count):
    """The exact value on the host: a Python ``int`` for scalars, a ``uint64`` numpy array otherwise."""
    value = (np.asarray(count.hi).astype(np.uint64) << np.uint64(32)) | np.asarray(count.lo).astype(np.uint64)
    return int(value) if value.ndim == 0 else value
