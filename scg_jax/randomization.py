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

from scg_jax._pytree import pytree_dataclass

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


def parse_distribution(path: str, raw, shape: tuple[int, ...], positive: bool, allow_relative: bool):
    """Validate a distribution option; return ``(DistributionSpec, dict of numpy values)``.

    A plain number or list (not a mapping) means a fixed value: ``uniform`` with ``low = high``.
    """
    if not isinstance(raw, dict):
        raw = {"type": "uniform", "low": raw, "high": raw}
    kind = raw.get("type")
    if kind not in DISTRIBUTIONS:
        raise ValueError(f"{path}.type: unknown value {kind!r}; allowed values are {', '.join(DISTRIBUTIONS)}")
    allowed = ("type", "relative") + _KEYS[kind] if allow_relative else ("type",) + _KEYS[kind]
    for key in raw:
        if key not in allowed:
            raise ValueError(
                f"{path}.{key}: unknown key for a {kind} distribution here; allowed keys are {', '.join(allowed)}"
            )
    relative = raw.get("relative", False)
    if not isinstance(relative, bool):
        raise ValueError(f"{path}.relative: expected true or false, got {relative!r}")

    def array(key, target_shape=shape):
        if key not in raw:
            raise ValueError(f"{path}.{key}: required for a {kind} distribution")
        value = np.asarray(raw[key], dtype=float)
        if value.ndim == 0:
            value = np.broadcast_to(value, target_shape)
        if value.shape != target_shape:
            raise ValueError(f"{path}.{key}: expected shape {target_shape}, got {value.shape}")
        if np.any(np.isnan(value)):
            raise ValueError(f"{path}.{key}: values must not be NaN")
        return np.array(value)

    zeros = np.zeros(shape)
    values = {"low": zeros, "high": zeros, "mean": zeros, "std": zeros, "values": zeros[None]}
    truncated = False
    what = "factor" if relative else "value"
    if kind == "uniform":
        values["low"], values["high"] = array("low"), array("high")
        if not (np.all(np.isfinite(values["low"])) and np.all(np.isfinite(values["high"]))):
            raise ValueError(f"{path}: uniform bounds must be finite")
        if np.any(values["low"] > values["high"]):
            raise ValueError(
                f"{path}.low: must not exceed high, got {values['low'].tolist()} and {values['high'].tolist()}"
            )
        if positive and np.any(values["low"] <= 0):
            raise ValueError(f"{path}.low: must be positive so every drawn {what} is, got {values['low'].tolist()}")
    elif kind == "normal":
        values["mean"], values["std"] = array("mean"), array("std")
        if np.any(values["std"] <= 0) or not np.all(np.isfinite(values["std"])):
            raise ValueError(f"{path}.std: must be positive and finite, got {values['std'].tolist()}")
        truncated = "low" in raw or "high" in raw
        if truncated:
            values["low"] = array("low") if "low" in raw else np.full(shape, -np.inf)
            values["high"] = array("high") if "high" in raw else np.full(shape, np.inf)
            if np.any(values["low"] >= values["high"]):
                raise ValueError(f"{path}.low: must be below high")
        if positive and (not truncated or np.any(values["low"] <= 0)):
            raise ValueError(
                f"{path}.low: a normal distribution of a positive parameter needs a truncation "
                f"low > 0 so no non-positive {what} can be drawn"
            )
    else:
        candidates = np.asarray(raw.get("values"), dtype=float)
        if candidates.ndim != len(shape) + 1 or candidates.shape[1:] != shape or candidates.shape[0] == 0:
            raise ValueError(
                f"{path}.values: expected a non-empty list of values of shape {shape}, got shape {candidates.shape}"
            )
        if not np.all(np.isfinite(candidates)):
            raise ValueError(f"{path}.values: values must be finite")
        if positive and np.any(candidates <= 0):
            raise ValueError(f"{path}.values: must all be positive, got {candidates.tolist()}")
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
