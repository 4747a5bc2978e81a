"""Checked names, numbers, vectors, matrices and choices: the one place where input values are validated.

Every checker has the form ``check(value, path, ...) -> normalised value`` and raises ``FieldError`` (a
``ValueError``) whose message starts with the dotted path of the field, then what is wrong and what is allowed::

    env.disturbances.action[0].std: must be >= 0, got -1.0
    env.integrator: unknown value 'rk5'; allowed values are euler, semi_implicit_euler, rk4 (did you mean 'rk4'?)
    ctrl_freq: expected an integer, got '50'

The environment (``scg_jax.make``, ``make_from_config``), the typed config (``scg_jax.config``), constraints,
disturbances, randomisation and the controllers' and learners' options all check their inputs through here, so a
given mistake reads the same wherever it is made. Nothing is clipped or coerced silently: a string is not a
number, a bool is not an integer, NaN is never a valid value, and infinity only where a checker says so.
"""

from __future__ import annotations

import difflib
import math
import numbers
import re
from collections.abc import Iterable, Mapping

import numpy as np

__all__ = [
    "FieldError",
    "boolean",
    "check_keys",
    "integer",
    "is_number",
    "is_sequence",
    "join",
    "matrix",
    "name",
    "non_negative",
    "number",
    "positive",
    "show",
    "string",
    "vector",
    "weight_matrix",
]


class FieldError(ValueError):
    """Bad input at ``path`` (dotted, e.g. ``env.constraints[1].bound``); ``reason`` says what and what is allowed.

    ``str(error)`` is ``"<path>: <reason>"`` (just the reason when the path is empty).
    """

    def __init__(self, path: str, reason: str):
        self.path = path
        self.reason = reason
        super().__init__(f"{path}: {reason}" if path else reason)

    def within(self, prefix: str) -> FieldError:
        """The same error with its path inside ``prefix`` (``"env"`` + ``"goal"`` -> ``"env.goal"``)."""
        path = join(prefix, self.path) if self.path else prefix
        return FieldError(path, self.reason)

    def __reduce__(self):  # picklable with both arguments (multiprocessing, pytest-xdist)
        return FieldError, (self.path, self.reason)


def join(path: str, key) -> str:
    """``path.key`` (``path[key]`` for an integer key); just ``key`` at the top level."""
    if isinstance(key, int):
        return f"{path}[{key}]"
    return f"{path}.{key}" if path else str(key)


def show(value) -> str:
    """A short repr for messages (numpy arrays as lists, long values cut at 80 characters)."""
    if isinstance(value, np.ndarray | np.generic):
        value = value.tolist()
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def _hint(value, allowed) -> str:
    close = difflib.get_close_matches(str(value), [str(a) for a in allowed], n=1)
    return f" (did you mean {close[0]!r}?)" if close else ""


# --------------------------------------------------------------------------------------------- names
def name(value, path: str, allowed: Iterable[str]) -> str:
    """``value`` if it is one of the strings ``allowed``; otherwise the allowed values and the closest match."""
    allowed = tuple(allowed)
    if isinstance(value, str) and value in allowed:
        return value
    if isinstance(value, str):
        raise FieldError(
            path, f"unknown value {value!r}; allowed values are {', '.join(allowed)}{_hint(value, allowed)}"
        )
    raise FieldError(path, f"expected one of {', '.join(allowed)}, got {show(value)}")


def check_keys(mapping: Mapping, path: str, allowed: Iterable[str], what: str = "key", where: str = "") -> None:
    """Every key of ``mapping`` is one of ``allowed``; else ``<path>.<key>: unknown <what>[ where]; allowed ...``."""
    allowed = tuple(allowed)
    for key in mapping:
        if key not in allowed:
            where_text = f" {where}" if where else ""
            raise FieldError(
                join(path, key),
                f"unknown {what}{where_text}; allowed {what}s are {', '.join(allowed)}{_hint(key, allowed)}",
            )


def string(value, path: str) -> str:
    if isinstance(value, str):
        return value
    raise FieldError(path, f"expected a string, got {show(value)}")


def boolean(value, path: str) -> bool:
    """``True`` or ``False`` (numpy bools too); ``1``, ``"yes"`` and ``"true"`` are rejected, not guessed."""
    if isinstance(value, bool | np.bool_):
        return bool(value)
    raise FieldError(path, f"expected true or false, got {show(value)}")


# --------------------------------------------------------------------------------------------- numbers
# YAML 1.1 readers (plain ``yaml.safe_load``) leave ``1e-3`` a string; ``number(..., yaml_strings=True)`` reads it.
YAML_FLOAT = re.compile(
    r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
    |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
    |[-+]?\.[0-9_]+(?:[eE][-+]?[0-9]+)?
    |[-+]?\.(?:inf|Inf|INF)
    |\.(?:nan|NaN|NAN))$""",
    re.VERBOSE,
)


def _scalar(value):
    """A 0-d array or numpy scalar as a Python number; anything else unchanged."""
    if isinstance(value, np.generic) or (hasattr(value, "__array__") and np.ndim(value) == 0):
        return np.asarray(value).item()
    return value


def _is_real(value) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def is_number(value) -> bool:
    """A real number (a numpy scalar or 0-d array too), not a bool."""
    return _is_real(_scalar(value))


def number(value, path: str, *, allow_inf: bool = False, yaml_strings: bool = False) -> float:
    """A real number as a float: never a bool or a string (but see ``yaml_strings``), never NaN, and finite unless
    ``allow_inf`` (e.g. a one-sided bound)."""
    value = _scalar(value)
    if yaml_strings and isinstance(value, str) and YAML_FLOAT.match(value):
        value = float(value.replace("_", "").lower().replace(".inf", "inf").replace(".nan", "nan"))
    if not _is_real(value):
        raise FieldError(path, f"expected a {'' if allow_inf else 'finite '}number, got {show(value)}")
    value = float(value)
    if math.isnan(value) or (math.isinf(value) and not allow_inf):
        raise FieldError(path, f"must be finite, got {value}")
    return value


def positive(value, path: str) -> float:
    """A finite number > 0."""
    value = number(value, path)
    if not value > 0:
        raise FieldError(path, f"must be positive, got {value:g}")
    return value


def non_negative(value, path: str) -> float:
    """A finite number >= 0."""
    value = number(value, path)
    if not value >= 0:
        raise FieldError(path, f"must be >= 0, got {value:g}")
    return value


def integer(value, path: str, minimum: int | None = None) -> int:
    """An integer (a whole float such as ``50.0`` too, but no bool or string), ``>= minimum`` when given."""
    value = _scalar(value)
    if _is_real(value) and math.isfinite(value) and float(value).is_integer():
        value = int(value)
    else:
        raise FieldError(path, f"expected an integer, got {show(value)}")
    if minimum is not None and value < minimum:
        what = {0: "a non-negative integer", 1: "a positive integer"}.get(minimum, f"an integer >= {minimum}")
        raise FieldError(path, f"must be {what}, got {value}")
    return value


# --------------------------------------------------------------------------------------------- arrays
def is_sequence(value) -> bool:
    """A list, tuple or array of at least one dimension (not a string, not a mapping)."""
    return isinstance(value, list | tuple | np.ndarray) or (hasattr(value, "__array__") and np.ndim(value) > 0)


def vector(
    value, path: str, n: int | None = None, *, broadcast: bool = False, allow_inf: bool = False, yaml_strings=False
) -> np.ndarray:
    """A list of numbers as a float64 array (n,) (any length when ``n`` is None).

    With ``broadcast``, a single number stands for ``n`` equal values. Each entry is checked by ``number`` (so the
    message of a bad entry names ``path[i]``).
    """
    value = _scalar(value)
    if broadcast and _is_real(value):
        item = number(value, path, allow_inf=allow_inf)
        return np.full(() if n is None else n, item)
    what = "a list of numbers" if n is None else f"{n} values"
    what = f"a number or {what}" if broadcast else what
    if not is_sequence(value) or np.ndim(value) != 1:
        raise FieldError(path, f"expected {what}, got {show(value)}")
    items = list(value)
    if n is not None and len(items) != n:
        raise FieldError(path, f"expected {what}, got {len(items)}: {show(items)}")
    kw = {"allow_inf": allow_inf, "yaml_strings": yaml_strings}
    return np.array([number(item, join(path, i), **kw) for i, item in enumerate(items)], dtype=np.float64)


def matrix(
    value, path: str, rows: int | None = None, cols: int | None = None, *, allow_inf: bool = False, yaml_strings=False
) -> np.ndarray:
    """A non-empty list of equal-length lists of numbers as a float64 array (rows, cols) (any size where None)."""
    value = _scalar(value)
    if not (is_sequence(value) and len(value) and all(is_sequence(row) for row in value)):
        raise FieldError(path, f"expected a matrix (a list of equal-length lists of numbers), got {show(value)}")
    kw = {"allow_inf": allow_inf, "yaml_strings": yaml_strings}
    array = [vector(row, join(path, i), **kw) for i, row in enumerate(value)]
    lengths = sorted({len(row) for row in array})
    if len(lengths) > 1:
        raise FieldError(
            path, f"expected a matrix (a list of equal-length lists of numbers), got rows of lengths {lengths}"
        )
    array = np.array(array, dtype=np.float64)
    expected = (len(array) if rows is None else rows, array.shape[1] if cols is None else cols)
    if array.shape != expected:
        want = f"({'rows' if rows is None else rows}, {'columns' if cols is None else cols})"
        raise FieldError(path, f"expected a matrix of shape {want}, got shape {array.shape}")
    return array


def weight_matrix(value, path: str, n: int, *, diagonal_only: bool = False) -> np.ndarray:
    """A quadratic cost weight (Q or R) as a float64 (n, n) matrix; the one place such weights are built.

    ``value`` is its diagonal (``n`` numbers) or, unless ``diagonal_only`` (options named ``*_diag``), a full
    (n, n) matrix. The result must be symmetric positive semidefinite (a diagonal: every entry >= 0).
    """
    if diagonal_only:
        diagonal = vector(value, path, n)
        if np.any(diagonal < 0):
            raise FieldError(path, f"weights must be >= 0, got {diagonal.tolist()}")
        return np.diag(diagonal)
    array = np.asarray(value, dtype=np.float64)
    if array.shape == (n,):
        array = np.diag(array)
    if array.shape != (n, n):
        raise FieldError(path, f"expected {n} diagonal values or an ({n}, {n}) matrix, got shape {array.shape}")
    finite = np.all(np.isfinite(array))
    if not (finite and np.allclose(array, array.T) and np.linalg.eigvalsh(array).min() >= -1e-12):
        raise FieldError(path, f"must be symmetric positive semidefinite, got {show(array)}")
    return array
