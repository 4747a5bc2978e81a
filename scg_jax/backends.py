"""Backend namespaces ``xp`` through which every system's ``dynamics`` and every constraint is written.

A system's equations call only ``xp.sin``, ``xp.cos``, ``xp.tan``, ``xp.sqrt`` and ``xp.stack`` plus Python
arithmetic and indexing, so the same function returns a ``jax.numpy`` array of shape ``(n,)`` when given JAX
arrays and a CasADi ``SX`` column of shape ``(n, 1)`` when given CasADi symbols. ``xp.constant`` turns a numpy
array into the backend's constant type and ``xp.repeat(n, body, x)`` applies ``body`` n times (a
``lax.fori_loop`` under JAX, so the compiled graph does not grow with the number of physics substeps).
``xp.exp`` and ``xp.dot`` (inner product of two vectors) serve the Gaussian-process posterior, which is written
once and evaluated on both backends like the dynamics.
"""

from __future__ import annotations

from types import SimpleNamespace

import casadi as cs
import jax.numpy as jnp
import numpy as np
from jax import lax


def _repeat_jax(n: int, body, x):
    return lax.fori_loop(0, n, lambda _, value: body(value), x)


def _repeat_python(n: int, body, x):
    for _ in range(n):
        x = body(x)
    return x


jax_backend = SimpleNamespace(
    name="jax",
    sin=jnp.sin,
    cos=jnp.cos,
    tan=jnp.tan,
    sqrt=jnp.sqrt,
    exp=jnp.exp,
    dot=jnp.dot,
    stack=jnp.stack,
    concatenate=jnp.concatenate,
    matmul=jnp.matmul,
    select=lambda v, indices: v[np.asarray(indices, dtype=int)],
    constant=jnp.asarray,
    repeat=_repeat_jax,
)

casadi_backend = SimpleNamespace(
    name="casadi",
    sin=cs.sin,
    cos=cs.cos,
    tan=cs.tan,
    sqrt=cs.sqrt,
    exp=cs.exp,
    dot=cs.dot,
    stack=lambda items: cs.vertcat(*items),
    concatenate=lambda items: cs.vertcat(*items),
    matmul=cs.mtimes,
    select=lambda v, indices: v[list(indices)],
    constant=cs.DM,
    repeat=_repeat_python,
)
