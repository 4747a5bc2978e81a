"""Disturbances: pure functions of a key, their parameters, a per-episode state and the step index.

Channels (where the value is added):

- ``action`` (nu,): to the commanded physical input ``u`` before actuator saturation, N;
- ``observation`` (nx,): to the state part of the observation the controller sees; the true state is
  unaffected;
- ``dynamics`` (f_ext_dim,): the external force ``f_ext`` on the plant, N, held over the physics substeps.

Types (each value is multiplied by the per-dimension ``mask``; several per channel are summed in order):

- ``white_noise``: ``N(0, std^2)`` per dimension and step;
- ``uniform``: ``U(low, high)`` per dimension and step;
- ``step``: ``magnitude`` from step ``start_step`` on;
- ``impulse``: ``magnitude * decay^(k - start)`` for ``start <= k < start + duration``; ``start`` is
  ``start_step`` or, with ``start_step: random``, drawn once per episode uniformly in
  ``[0, num_steps - duration]``;
- ``periodic``: ``scale * sin(2 pi frequency t + phase)`` with ``t = k dt`` and ``phase ~ U(0, 2 pi)`` per
  dimension, drawn once per episode.

The step index ``k`` is the control step the value belongs to: the step whose input it disturbs (action,
dynamics), or the index of the observed state (observation: 0 at reset). Magnitudes live in ``EnvParams``, so
a sweep over them is a ``vmap``.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from scg_jax import validation as V
from scg_jax._pytree import pytree_dataclass
from scg_jax.validation import FieldError

CHANNELS = ("action", "observation", "dynamics")
DISTURBANCE_TYPES = ("white_noise", "uniform", "step", "impulse", "periodic")
_KEYS = {
    "white_noise": ("std",),
    "uniform": ("low", "high"),
    "step": ("magnitude", "start_step"),
    "impulse": ("magnitude", "start_step", "duration", "decay"),
    "periodic": ("scale", "frequency"),
}
_DEFAULTS = {"start_step": 0, "decay": 1.0}


@dataclasses.dataclass(frozen=True)
class DisturbanceSpec:
    """Static structure of one disturbance."""

    type: str
    channel: str
    dim: int
    random_start: bool = False


@pytree_dataclass
class DisturbanceParams:
    """Traced values of one disturbance; fields a type does not use are zero. Shapes: (dim,) or scalar."""

    mask: object
    std: object
    low: object
    high: object
    magnitude: object
    start_step: object
    duration: object
    decay: object
    scale: object
    frequency: object


@pytree_dataclass
class DisturbanceState:
    """Per-episode draws: ``phase`` (dim,) for periodic, ``start`` (int32) for impulse."""

    phase: object
    start: object


def parse_disturbance(path: str, d, channel: str, dim: int, num_steps: int):
    """Check one disturbance against its channel; return ``(DisturbanceSpec, dict of numpy defaults)``.

    Args:
        path: dotted name for messages (``"disturbances.action[0]"``). d: a ``scg_jax.env_config.DisturbanceConfig``
            (type, keys and value types already checked). channel, dim: the channel and its dimension.
        num_steps: control steps per episode (an impulse's duration must fit).

    Raises:
        scg_jax.validation.FieldError: naming ``path.<key>``.
    """
    kind = d.type
    values = {name: np.zeros(dim) for name in ("std", "low", "high", "magnitude", "scale")}
    values.update(
        start_step=np.asarray(0, np.int32),
        duration=np.asarray(0, np.int32),
        decay=np.asarray(1.0),
        frequency=np.asarray(0.0),
    )
    values["mask"] = V.vector(1.0 if d.mask is None else d.mask, f"{path}.mask", dim, broadcast=True)
    random_start = False
    for key in _KEYS[kind]:
        value = getattr(d, key)
        value = _DEFAULTS.get(key) if value is None else value
        at = f"{path}.{key}"
        if key == "start_step":
            random_start = value == "random"  # only impulses may say so (checked with the config)
            if not random_start:
                values[key] = np.asarray(V.integer(value, at, minimum=0), np.int32)
        elif key == "duration":
            if not 1 <= value <= num_steps:
                raise FieldError(at, f"expected an integer number of steps in [1, {num_steps}], got {value!r}")
            values[key] = np.asarray(value, np.int32)
        elif key == "decay":
            if not 0.0 < value <= 1.0:
                raise FieldError(at, f"expected a factor per step in (0, 1], got {value!r}")
            values[key] = np.asarray(value)
        elif key == "frequency":
            if not value > 0.0:
                raise FieldError(at, f"expected a positive frequency in Hz, got {value!r}")
            values[key] = np.asarray(value)
        else:
            values[key] = V.vector(value, at, dim, broadcast=True)
    if kind == "white_noise" and np.any(values["std"] < 0):
        raise FieldError(f"{path}.std", f"must be >= 0, got {V.show(d.std)}")
    if kind == "uniform" and np.any(values["low"] > values["high"]):
        raise FieldError(
            f"{path}.low", f"must not exceed high, got {values['low'].tolist()} and {values['high'].tolist()}"
        )
    return DisturbanceSpec(kind, channel, dim, random_start), values


def initial_state(spec: DisturbanceSpec, params: DisturbanceParams, key, num_steps: int) -> DisturbanceState:
    """The per-episode draws of one disturbance (called at reset)."""
    key_phase, key_start = jax.random.split(key)
    dtype = jnp.asarray(params.mask).dtype
    phase = (
        jax.random.uniform(key_phase, (spec.dim,), dtype=dtype, maxval=2.0 * jnp.pi)
        if spec.type == "periodic"
        else jnp.zeros(spec.dim, dtype)
    )
    if spec.random_start:
        start = jax.random.randint(key_start, (), 0, num_steps - params.duration + 1, dtype=jnp.int32)
    else:
        start = jnp.asarray(params.start_step, jnp.int32)
    return DisturbanceState(phase=phase, start=start)


RANDOM_TYPES = ("white_noise", "uniform")


def draw_standard_noise(specs_by_channel: dict, key, dtype) -> dict:
    """All per-step randomness of an env in one draw: ``{(channel, index): standard sample (dim,)}``.

    White-noise disturbances get ``N(0, 1)`` samples and uniform ones ``U(0, 1)`` samples, each taken from a
    single vector draw for all channels together (one normal and at most one uniform draw per step), because the
    number of PRNG calls, not their size, dominates the cost of a step of these small systems.
    """
    layout = {kind: [] for kind in RANDOM_TYPES}
    for channel in CHANNELS:
        for index, spec in enumerate(specs_by_channel.get(channel, ())):
            if spec.type in RANDOM_TYPES:
                layout[spec.type].append(((channel, index), spec.dim))
    needed = [kind for kind in RANDOM_TYPES if layout[kind]]
    keys = dict(zip(needed, jax.random.split(key, len(needed)) if len(needed) > 1 else [key], strict=True))
    samples = {}
    for kind in needed:
        total = sum(dim for _, dim in layout[kind])
        draw = (jax.random.normal if kind == "white_noise" else jax.random.uniform)(keys[kind], (total,), dtype)
        start = 0
        for name, dim in layout[kind]:
            samples[name] = draw[start : start + dim]
            start += dim
    return samples


def sample(spec: DisturbanceSpec, params: DisturbanceParams, state: DisturbanceState, noise, step, dt: float):
    """The value (dim,) of one disturbance at control step ``step``.

    ``noise`` is this disturbance's standard sample from ``draw_standard_noise`` (unused by the deterministic
    types).
    """
    dtype = jnp.asarray(params.mask).dtype
    if spec.type == "white_noise":
        value = params.std * noise
    elif spec.type == "uniform":
        value = params.low + (params.high - params.low) * noise
    elif spec.type == "step":
        value = params.magnitude * (step >= state.start)
    elif spec.type == "impulse":
        elapsed = step - state.start
        active = (elapsed >= 0) & (elapsed < params.duration)
        value = jnp.where(active, params.magnitude * params.decay ** jnp.maximum(elapsed, 0), 0.0)
    else:
        value = params.scale * jnp.sin(2.0 * jnp.pi * params.frequency * step * dt + state.phase)
    return (params.mask * value).astype(dtype)


def channel_value(channel: str, specs, params_list, states, noise: dict, step, dt: float, dim: int, dtype):
    """Sum of a channel's disturbances, applied in order; zeros (dim,) when the channel has none."""
    total = jnp.zeros(dim, dtype)
    for index, (spec, params, state) in enumerate(zip(specs, params_list, states, strict=True)):
        total = total + sample(spec, params, state, noise.get((channel, index)), step, dt)
    return total
