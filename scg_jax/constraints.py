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

from scg_jax._pytree import pytree_dataclass

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


def _matrix(path: str, value, shape) -> np.ndarray:
    try:
        array = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{path}: expected numbers of shape {shape}, got {value!r}") from None
    if array.shape != shape:
        raise ValueError(f"{path}: expected shape {shape}, got {array.shape}")
    if np.any(np.isnan(array)):
        raise ValueError(f"{path}: values must not be NaN")
    return array


def parse_constraint(path: str, raw: dict, system, state_bounds, input_bounds):
    """Validate one constraint option and return ``(ConstraintSpec, default params as numpy)``.

    Args:
        path: dotted name for error messages, e.g. ``"constraints[1]"``.
        raw: the option dict. system: the ``System``. state_bounds, input_bounds: ``(low, high)`` numpy pairs.
    """
    if not isinstance(raw, dict):
        raise ValueError(f"{path}: expected a mapping with a 'type' key, got {raw!r}")
    kind = raw.get("type")
    if kind not in CONSTRAINT_TYPES:
        raise ValueError(f"{path}.type: unknown value {kind!r}; allowed values are {', '.join(CONSTRAINT_TYPES)}")
    allowed = _COMMON_KEYS + _KEYS[kind]
    for key in raw:
        if key not in allowed:
            raise ValueError(
                f"{path}.{key}: unknown key for a {kind} constraint; allowed keys are {', '.join(allowed)}"
            )
    on = raw.get("on", "state")
    if on not in CONSTRAINT_VARIABLES:
        raise ValueError(f"{path}.on: unknown value {on!r}; allowed values are {', '.join(CONSTRAINT_VARIABLES)}")
    size = {"state": system.nx, "input": system.nu, "input_and_state": system.nx + system.nu}[on]
    dims = raw.get("active_dims")
    dims = tuple(range(size)) if dims is None else tuple(dims)
    if (
        not dims
        or any((not isinstance(d, int | np.integer)) or d < 0 or d >= size for d in dims)
        or len(set(dims)) != len(dims)
    ):
        raise ValueError(
            f"{path}.active_dims: expected distinct integers in [0, {size}), got {raw.get('active_dims')!r}"
        )
    d = len(dims)
    tolerance = float(raw.get("tolerance", 0.0))
    if not np.isfinite(tolerance):
        raise ValueError(f"{path}.tolerance: must be finite, got {raw.get('tolerance')!r}")
    strict = raw.get("strict", False)
    if not isinstance(strict, bool):
        raise ValueError(f"{path}.strict: expected true or false, got {strict!r}")

    for key in _KEYS[kind]:
        if key not in raw:
            raise ValueError(f"{path}.{key}: required for a {kind} constraint")
    if kind == "quadratic":
        P = _matrix(f"{path}.P", raw["P"], (d, d))
        b = _matrix(f"{path}.b", raw["b"], ())
        spec = ConstraintSpec(kind, on, dims, strict, "quadratic", 1)
        return spec, {"P": P, "b": b, "tolerance": np.asarray(tolerance)}
    if kind == "linear":
        try:
            A = np.asarray(raw["A"], dtype=float)
        except (TypeError, ValueError):
            raise ValueError(f"{path}.A: expected a matrix of numbers of shape (rows, {d}), got {raw['A']!r}") from None
        if A.ndim != 2 or A.shape[1] != d:
            raise ValueError(f"{path}.A: expected shape (rows, {d}), got {A.shape}")
        b = _matrix(f"{path}.b", raw.get("b"), (A.shape[0],))
    else:
        if kind == "bounded":
            low = _matrix(f"{path}.low", raw["low"], (d,))
            high = _matrix(f"{path}.high", raw["high"], (d,))
        elif kind == "abs_bound":
            bound = np.asarray(raw["bound"], dtype=float)
            bound = _matrix(f"{path}.bound", np.full(d, bound) if bound.ndim == 0 else bound, (d,))
            if np.any(bound < 0):
                raise ValueError(f"{path}.bound: must be non-negative, got {np.asarray(raw.get('bound')).tolist()!r}")
            low, high = -bound, bound
        else:
            both = tuple(np.concatenate(pair) for pair in zip(state_bounds, input_bounds, strict=True))
            bounds = {"state": state_bounds, "input": input_bounds, "input_and_state": both}[on]
            low, high = (np.asarray(bound, dtype=float)[list(dims)] for bound in bounds)
        if np.any(low > high):
            raise ValueError(f"{path}: low must not exceed high, got {low.tolist()} and {high.tolist()}")
        eye = np.eye(d)
        A = np.concatenate([eye, -eye])
        b = np.concatenate([high, -low])
        finite = np.isfinite(b)
        A, b = A[finite], b[finite]
        if A.shape[0] == 0:
            raise ValueError(f"{path}: every bound is infinite, so the constraint has no row")
    spec = ConstraintSpec(kind, on, dims, strict, "linear", A.shape[0])
    return spec, {"A": A, "b": b, "tolerance": np.asarray(tolerance)}


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
