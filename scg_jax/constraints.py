"""Constraints ``g(x, u) <= 0``: satisfied where every row is ``<= 0``, violated where a row is ``> 0``.

One sign convention everywhere. A constraint acts on a variable ``z``: the state ``x`` (nx,), the input ``u``
(nu,) or both stacked, ``[x; u]``, restricted to ``active_dims`` (indices into that variable). Forms:

- ``bounded``: ``low <= z <= high`` as the rows ``z - high`` and ``low - z`` (infinite bounds give no row);
- ``abs_bound``: ``|z| <= bound``, i.e. ``bounded`` with ``low = -bound``, ``high = bound``;
- ``linear``: ``A z - b`` (rows of A);
- ``quadratic``: ``z^T P z - b`` (one row);
- ``default``: ``bounded`` with the system's failure bounds (state) or actuator limits (input); rows whose bound
  is infinite are dropped.

Every form except ``quadratic`` is stored as ``A z - b``, so tightening a bound is a change of ``b`` in
``EnvParams`` and a sweep over it is a ``vmap``. A row counts as violated when ``g > tolerance``
(``strict=False``) or ``g >= tolerance`` (``strict=True``). The input is the one the controller commanded (before
disturbances and actuator saturation); the state is the one the step reached.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from scg_jax import validation as V
from scg_jax._pytree import pytree_dataclass
from scg_jax.validation import FieldError

CONSTRAINT_TYPES = ("bounded", "abs_bound", "linear", "quadratic", "default")
CONSTRAINT_VARIABLES = ("state", "input", "input_and_state")
_KEYS = {
    "bounded": ("low", "high"),
    "abs_bound": ("bound",),
    "linear": ("A", "b"),
    "quadratic": ("P", "b"),
    "default": (),
}
_COMMON_KEYS = ("type", "on", "active_dims", "strict", "tolerance")


@dataclasses.dataclass(frozen=True)
class ConstraintSpec:
    """Static structure of one constraint (decided at ``make``)."""

    type: str
    on: str
    active_dims: tuple[int, ...]
    strict: bool
    form: str  # "linear" (A z - b) or "quadratic" (z^T P z - b)
    num_rows: int


@pytree_dataclass
class LinearConstraintParams:
    """``A (rows, d) z - b (rows,)``; ``tolerance`` scalar."""

    A: object
    b: object
    tolerance: object


@pytree_dataclass
class QuadraticConstraintParams:
    """``z^T P z - b`` with ``P (d, d)``, ``b`` scalar; ``tolerance`` scalar."""

    P: object
    b: object
    tolerance: object


def parse_constraint(path: str, c, system, state_bounds, input_bounds):
    """Check one constraint against the system; return ``(ConstraintSpec, default params as numpy)``.

    Args:
        path: dotted name for error messages, e.g. ``"constraints[1]"``.
        c: a ``scg_jax.env_config.ConstraintConfig`` (its type, keys and value types are already checked).
        system: the ``System``. state_bounds, input_bounds: ``(low, high)`` numpy pairs.

    Raises:
        scg_jax.validation.FieldError: naming ``path.<key>``.
    """
    kind = c.type
    on = c.on or "state"
    size = {"state": system.nx, "input": system.nu, "input_and_state": system.nx + system.nu}[on]
    dims = tuple(range(size)) if c.active_dims is None else tuple(c.active_dims)
    if not dims or any(not 0 <= d < size for d in dims) or len(set(dims)) != len(dims):
        raise FieldError(
            f"{path}.active_dims", f"expected distinct integers in [0, {size}) ({on} has {size}), got {list(dims)}"
        )
    d = len(dims)
    tolerance = np.asarray(0.0 if c.tolerance is None else V.number(c.tolerance, f"{path}.tolerance"))
    strict = bool(c.strict)

    if kind == "quadratic":
        P = V.matrix(c.P, f"{path}.P", d, d)
        b = np.asarray(V.number(c.b, f"{path}.b"))
        spec = ConstraintSpec(kind, on, dims, strict, "quadratic", 1)
        return spec, {"P": P, "b": b, "tolerance": tolerance}
    if kind == "linear":
        A = V.matrix(c.A, f"{path}.A", cols=d)
        b = V.vector(c.b, f"{path}.b", A.shape[0], broadcast=True, allow_inf=True)
    else:
        if kind == "bounded":
            low = V.vector(c.low, f"{path}.low", d, allow_inf=True)
            high = V.vector(c.high, f"{path}.high", d, allow_inf=True)
        elif kind == "abs_bound":
            bound = V.vector(c.bound, f"{path}.bound", d, broadcast=True, allow_inf=True)
            if np.any(bound < 0):
                raise FieldError(f"{path}.bound", f"must be >= 0, got {V.show(c.bound)}")
            low, high = -bound, bound
        else:
            both = tuple(np.concatenate(pair) for pair in zip(state_bounds, input_bounds, strict=True))
            bounds = {"state": state_bounds, "input": input_bounds, "input_and_state": both}[on]
            low, high = (np.asarray(bound, dtype=float)[list(dims)] for bound in bounds)
        if np.any(low > high):
            raise FieldError(f"{path}.low", f"must not exceed high, got {low.tolist()} and {high.tolist()}")
        eye = np.eye(d)
        A = np.concatenate([eye, -eye])
        b = np.concatenate([high, -low])
        finite = np.isfinite(b)
        A, b = A[finite], b[finite]
        if A.shape[0] == 0:
            raise FieldError(path, "every bound is infinite, so the constraint has no row")
    spec = ConstraintSpec(kind, on, dims, strict, "linear", A.shape[0])
    return spec, {"A": A, "b": b, "tolerance": tolerance}


def params_from_numpy(spec: ConstraintSpec, values: dict, as_array):
    cls = QuadraticConstraintParams if spec.form == "quadratic" else LinearConstraintParams
    return cls(**{k: as_array(v) for k, v in values.items()})


def evaluate(spec: ConstraintSpec, params, x, u, xp):
    """Rows ``g`` (num_rows,) of one constraint at ``(x, u)`` through backend ``xp``."""
    z = {"state": lambda: x, "input": lambda: u, "input_and_state": lambda: xp.concatenate([x, u])}[spec.on]()
    z = xp.select(z, spec.active_dims)
    if spec.form == "quadratic":
        P = xp.constant(params.P)
        return xp.stack([xp.matmul(z.T, xp.matmul(P, z)) - params.b])
    return xp.matmul(xp.constant(params.A), z) - xp.constant(params.b)


def evaluate_all(specs, params_list, x, u, xp):
    """All constraints' rows concatenated, in order: (sum of num_rows,)."""
    return xp.concatenate([evaluate(s, p, x, u, xp) for s, p in zip(specs, params_list, strict=True)])


def violated(specs, params_list, values):
    """Per-row violation mask for the concatenated ``values`` (JAX)."""
    masks, start = [], 0
    for spec, params in zip(specs, params_list, strict=True):
        rows = values[start : start + spec.num_rows]
        masks.append(rows >= params.tolerance if spec.strict else rows > params.tolerance)
        start += spec.num_rows
    return jnp.concatenate(masks)


def box_bounds(specs, values, nx: int, nu: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The per-coordinate bounds implied by the single-variable rows of linear constraints (for plots and reports).

    A row ``a z_j - b <= 0`` with one non-zero ``a`` is ``z_j <= b / a`` (``a > 0``) or ``z_j >= b / a`` (``a < 0``);
    rows over several coordinates and quadratic constraints are not boxes and are left out. The tightest bound
    per coordinate wins. ``input_and_state`` constraints act on ``[x; u]``.

    Args:
        specs: the env's ``constraint_specs``. values: ``params.constraints`` (unbatched). nx, nu: sizes.

    Returns:
        ``(x_low, x_high, u_low, u_high)`` float64 arrays, ``-inf`` / ``+inf`` where unbounded.
    """
    low = np.full(nx + nu, -np.inf)
    high = np.full(nx + nu, np.inf)
    for spec, value in zip(specs, values, strict=True):
        if spec.form != "linear":
            continue
        offset = nx if spec.on == "input" else 0
        A = np.asarray(value.A, dtype=np.float64)
        b = np.asarray(value.b, dtype=np.float64)
        for row, rhs in zip(A, b, strict=True):
            nonzero = np.flatnonzero(row)
            if nonzero.size != 1:
                continue
            j = offset + spec.active_dims[nonzero[0]]
            bound = rhs / row[nonzero[0]]
            if row[nonzero[0]] > 0:
                high[j] = min(high[j], bound)
            else:
                low[j] = max(low[j], bound)
    return low[:nx], high[:nx], low[nx:], high[nx:]
