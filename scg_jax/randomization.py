"""Distributions drawn at every reset: the initial state and the plant's physical parameters.

A distribution is written as a mapping with a ``type``:

- ``uniform``: ``low``, ``high``;
- ``normal``: ``mean``, ``std`` (> 0), optional truncation ``low``, ``high`` (required for physical parameters,
  with ``low > 0``, so a non-positive mass cannot be drawn);
- ``choice``: ``values``, a list of candidates drawn with equal probability.

Values are drawn as written (absolute). With ``relative: true`` (physical parameters only) the draw is a factor
on the nominal value in ``params.physics``: ``mass: {type: uniform, low: 0.9, high: 1.1, relative: true}`` is
"nominal times U(0.9, 1.1)". The randomisable physical parameters are all positive quantities; ranges that
could produce a non-positive value are rejected when the env is made.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from scg_jax import validation as V
from scg_jax._pytree import pytree_dataclass
from scg_jax.validation import FieldError

DISTRIBUTIONS = ("uniform", "normal", "choice")
_KEYS = {"uniform": ("low", "high"), "normal": ("mean", "std", "low", "high"), "choice": ("values",)}


@dataclasses.dataclass(frozen=True)
class DistributionSpec:
    """Static structure: the type, whether it is relative, whether the normal is truncated, and the shape."""

    type: str
    relative: bool
    truncated: bool
    shape: tuple[int, ...]


@pytree_dataclass
class DistributionParams:
    """Traced values; fields a type does not use are zero. ``values`` is (num_choices, *shape)."""

    low: object
    high: object
    mean: object
    std: object
    values: object


def parse_distribution(path: str, dist, shape: tuple[int, ...], positive: bool, allow_relative: bool):
    """Check a distribution against its shape; return ``(DistributionSpec, dict of numpy values)``.

    Args:
        path: dotted name for messages (``"init_state"``, ``"physics_randomization.mass"``).
        dist: a ``scg_jax.env_config.DistributionConfig`` (type and keys already checked), or a fixed value (a number
            or a list of numbers), which means ``uniform`` with ``low = high``.
        shape: ``()`` for a physical parameter, ``(nx,)`` for the initial state. positive: every drawable value
            must be > 0. allow_relative: whether ``relative`` may be set.

    Raises:
        scg_jax.validation.FieldError: naming ``path.<key>``.
    """
    if not hasattr(dist, "type"):  # a fixed value
        kind, relative, get = "uniform", False, {"low": dist, "high": dist}.get
    else:
        kind, relative, get = dist.type, bool(dist.relative), lambda key: getattr(dist, key)
        if dist.relative is not None and not allow_relative:
            V.check_keys({"relative": None}, path, ("type", *_KEYS[kind]), where=f"for a {kind} distribution here")

    def array(key, allow_inf=False):
        at = f"{path}.{key}"
        if shape == ():
            return np.asarray(V.number(get(key), at, allow_inf=allow_inf))
        return V.vector(get(key), at, shape[0], broadcast=True, allow_inf=allow_inf)

    zeros = np.zeros(shape)
    values = {"low": zeros, "high": zeros, "mean": zeros, "std": zeros, "values": zeros[None]}
    truncated = False
    what = "factor" if relative else "value"
    if kind == "uniform":
        values["low"], values["high"] = array("low"), array("high")
        if np.any(values["low"] > values["high"]):
            raise FieldError(
                f"{path}.low", f"must not exceed high, got {values['low'].tolist()} and {values['high'].tolist()}"
            )
        if positive and np.any(values["low"] <= 0):
            raise FieldError(f"{path}.low", f"must be positive so every drawn {what} is, got {values['low'].tolist()}")
    elif kind == "normal":
        values["mean"], values["std"] = array("mean"), array("std")
        if np.any(values["std"] <= 0):
            raise FieldError(f"{path}.std", f"must be positive, got {values['std'].tolist()}")
        truncated = get("low") is not None or get("high") is not None
        if truncated:
            values["low"] = array("low", True) if get("low") is not None else np.full(shape, -np.inf)
            values["high"] = array("high", True) if get("high") is not None else np.full(shape, np.inf)
            if np.any(values["low"] >= values["high"]):
                raise FieldError(
                    f"{path}.low", f"must be below high, got {values['low'].tolist()} and {values['high'].tolist()}"
                )
        if positive and (not truncated or np.any(values["low"] <= 0)):
            raise FieldError(
                f"{path}.low",
                f"a normal distribution of a positive parameter needs a truncation low > 0 so no non-positive {what} "
                "can be drawn",
            )
    else:
        raw = get("values")
        if shape == ():
            candidates = V.vector(raw, f"{path}.values")
        else:
            candidates = V.matrix(raw, f"{path}.values", cols=shape[0])
        if candidates.shape[0] == 0:
            raise FieldError(f"{path}.values", f"expected a non-empty list of values of shape {shape}, got []")
        if positive and np.any(candidates <= 0):
            raise FieldError(f"{path}.values", f"must all be positive, got {candidates.tolist()}")
        values["values"] = candidates
    return DistributionSpec(kind, relative, truncated, shape), values


def draw(spec: DistributionSpec, params: DistributionParams, key, nominal=None):
    """One draw of shape ``spec.shape``; ``nominal`` multiplies it when ``spec.relative``."""
    dtype = jnp.asarray(params.low).dtype
    if spec.type == "uniform":
        value = jax.random.uniform(key, spec.shape, dtype, minval=params.low, maxval=params.high)
    elif spec.type == "normal":
        if spec.truncated:
            lower = (params.low - params.mean) / params.std
            upper = (params.high - params.mean) / params.std
            value = params.mean + params.std * jax.random.truncated_normal(key, lower, upper, spec.shape, dtype)
        else:
            value = params.mean + params.std * jax.random.normal(key, spec.shape, dtype)
    else:
        index = jax.random.randint(key, (), 0, params.values.shape[0])
        value = params.values[index]
    return nominal * value if spec.relative else value
