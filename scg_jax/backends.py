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


# Each operation as (JAX, CasADi), side by side.
_OPERATIONS = {
    "sin": (jnp.sin, cs.sin),
    "cos": (jnp.cos, cs.cos),
    "tan": (jnp.tan, cs.tan),
    "sqrt": (jnp.sqrt, cs.sqrt),
    "exp": (jnp.exp, cs.exp),
    "dot": (jnp.dot, cs.dot),
    "stack": (jnp.stack, lambda items: cs.vertcat(*items)),
    "concatenate": (jnp.concatenate, lambda items: cs.vertcat(*items)),
    "matmul": (jnp.matmul, cs.mtimes),
    "select": (lambda v, indices: v[np.asarray(indices, dtype=int)], lambda v, indices: v[list(indices)]),
    "constant": (jnp.asarray, cs.DM),
    "repeat": (_repeat_jax, _repeat_python),
}

jax_backend = SimpleNamespace(name="jax", **{name: ops[0] for name, ops in _OPERATIONS.items()})
casadi_backend = SimpleNamespace(name="casadi", **{name: ops[1] for name, ops in _OPERATIONS.items()})
