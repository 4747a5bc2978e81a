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

from scg_jax._pytree import pytree_dataclass

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


def channel_vector(path: str, value, dim: int) -> np.ndarray:
    """A number (broadcast) or ``dim`` finite values, for a per-dimension channel quantity; ValueError naming
    ``path`` otherwise."""
    array = (
        np.broadcast_to(np.asarray(value, dtype=float), (dim,))
        if np.ndim(value) == 0
        else np.asarray(value, dtype=float)
    )
    if array.shape != (dim,):
        raise ValueError(f"{path}: expected a number or {dim} values, got shape {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{path}: values must be finite, got {array.tolist()!r}")
    return np.array(array)


def parse_disturbance(path: str, raw: dict, channel: str, dim: int, num_steps: int):
    """Validate one disturbance option; return ``(DisturbanceSpec, dict of numpy defaults)``."""
    if not isinstance(raw, dict):
        raise ValueError(f"{path}: expected a mapping with a 'type' key, got {raw!r}")
    kind = raw.get("type")
    if kind not in DISTURBANCE_TYPES:
        raise ValueError(f"{path}.type: unknown value {kind!r}; allowed values are {', '.join(DISTURBANCE_TYPES)}")
    allowed = ("type", "mask") + _KEYS[kind]
    for key in raw:
        if key not in allowed:
            raise ValueError(
                f"{path}.{key}: unknown key for a {kind} disturbance; allowed keys are {', '.join(allowed)}"
            )
    for key in _KEYS[kind]:
        if key not in raw and key not in _DEFAULTS:
            raise ValueError(f"{path}.{key}: required for a {kind} disturbance")
    values = {name: np.zeros(dim) for name in ("std", "low", "high", "magnitude", "scale")}
    values.update(
        start_step=np.asarray(0, np.int32),
        duration=np.asarray(0, np.int32),
        decay=np.asarray(1.0),
        frequency=np.asarray(0.0),
    )
    values["mask"] = channel_vector(f"{path}.mask", raw.get("mask", 1.0), dim)
    random_start = False
    for key in _KEYS[kind]:
        value = raw.get(key, _DEFAULTS.get(key))
        if key == "start_step":
            if kind == "impulse" and value == "random":
                random_start = True
                continue
            if (
                isinstance(value, bool)
                or not isinstance(value, int | float)
                or not float(value).is_integer()
                or value < 0
            ):
                allowed_text = "a non-negative integer or 'random'" if kind == "impulse" else "a non-negative integer"
                raise ValueError(f"{path}.start_step: expected {allowed_text}, got {value!r}")
            values[key] = np.asarray(int(value), np.int32)
        elif key == "duration":
            valid = isinstance(value, int | float) and not isinstance(value, bool) and float(value).is_integer()
            if not valid or not 1 <= value <= num_steps:
                raise ValueError(
                    f"{path}.duration: expected an integer number of steps in [1, {num_steps}], got {value!r}"
                )
            values[key] = np.asarray(int(value), np.int32)
        elif key == "decay":
            if not 0.0 < float(value) <= 1.0:
                raise ValueError(f"{path}.decay: expected a factor per step in (0, 1], got {value!r}")
            values[key] = np.asarray(float(value))
        elif key == "frequency":
            if not float(value) > 0.0:
                raise ValueError(f"{path}.frequency: expected a positive frequency in Hz, got {value!r}")
            values[key] = np.asarray(float(value))
        else:
            values[key] = channel_vector(f"{path}.{key}", value, dim)
    if kind == "white_noise" and np.any(values["std"] < 0):
        raise ValueError(f"{path}.std: must be non-negative, got {values['std'].tolist()!r}")
    if kind == "uniform" and np.any(values["low"] > values["high"]):
        raise ValueError(
            f"{path}.low: must not exceed high, got {values['low'].tolist()} and {values['high'].tolist()}"
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
