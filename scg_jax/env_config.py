"""The typed ``env`` section of a configuration: ``EnvConfig``, one checked field per option of ``scg_jax.make``.

``make(system, task, **options)`` reads its options into an ``EnvConfig`` (so ``make`` and a config file accept the
same names, types and defaults: the defaults are ``_OPTION_DEFAULTS``), and ``scg_jax.config`` reads the ``env``
section of a file into one. Constructing a section (``EnvConfig.from_dict`` or the dataclasses directly) checks
keys (per type for constraints, disturbances and distributions), types, structural shapes and the fixed sets of
names, through ``scg_jax.validation``: ``env.ctrl_freq: expected an integer, got 'fast'``. What depends on the system
or on several fields together is checked by ``make``.

This module sits below both ``scg_jax.env`` (which builds an env from an ``EnvConfig``) and ``scg_jax.config``
(which reads files into one and calls ``make``); it imports neither.
"""

from __future__ import annotations

import contextvars
import dataclasses
from collections.abc import Callable, Mapping
from typing import Any, ClassVar

import numpy as np

from scg_jax import constraints as constraints_lib
from scg_jax import disturbances as disturbances_lib
from scg_jax import randomization, trajectories
from scg_jax import validation as V
from scg_jax.integrators import INTEGRATORS
from scg_jax.systems import SYSTEMS

__all__ = [
    "ACTION_MODES",
    "DEFAULT_TASK",
    "REWARD_TYPES",
    "TASKS",
    "AdversaryConfig",
    "ConstraintConfig",
    "DisturbanceConfig",
    "DistributionConfig",
    "EnvConfig",
    "TrajectoryConfig",
]

TASKS = ("stabilization", "tracking")
DEFAULT_TASK = TASKS[0]
ACTION_MODES = ("physical", "normalized")
REWARD_TYPES = ("quadratic", "exponential", "upright")

# The options of ``make`` and their defaults (``None``: the system's default, or none).
_OPTION_DEFAULTS = {
    "ctrl_freq": 50,
    "physics_freq": 1000,
    "episode_len_sec": 5.0,
    "integrator": "rk4",
    "action_mode": "physical",
    "reward_type": "quadratic",
    "obs_goal_horizon": 0,
    "done_on_out_of_bounds": True,
    "done_on_goal": False,
    "trajectory": None,
    "physics": None,
    "Q": None,
    "R": None,
    "goal": None,
    "goal_tolerance": 0.05,
    "init_state": None,
    "physics_randomization": None,
    "mse_weight": None,
    "constraints": None,
    "done_on_violation": False,
    "violation_penalty": 0.0,
    "disturbances": None,
    "adversary": None,
}

# One error type for every bad input (``.path`` is the dotted path of the field).
ConfigError = V.FieldError


# --------------------------------------------------------------------------------------------- converters
# A converter ``conv(value, path) -> normalised value`` checks one field through ``scg_jax.validation`` and returns
# it with lists as tuples and nested sections as their dataclasses; it accepts its own output, so normalising twice
# is harmless. Numbers written as YAML 1.1 strings (``1e-3`` from a plain ``yaml.safe_load``) are read as numbers.
_Converter = Callable[[Any, str], Any]
_YAML = {"yaml_strings": True}


def _number(value, path, allow_inf=False):
    return V.number(value, path, allow_inf=allow_inf, **_YAML)


def _numbers(length: int | None = None, allow_inf: bool = False) -> _Converter:
    """A list of numbers (of ``length`` numbers when given), as a tuple."""
    return lambda value, path: tuple(V.vector(value, path, length, allow_inf=allow_inf, **_YAML).tolist())


def _number_or_numbers(allow_inf: bool = False) -> _Converter:
    def conv(value, path):
        array = V.vector(value, path, broadcast=True, allow_inf=allow_inf, **_YAML)
        return float(array) if array.ndim == 0 else tuple(array.tolist())

    return conv


def _rows(value, path):
    """A non-empty list of equal-length lists of numbers (a matrix), as a tuple of tuples."""
    return tuple(tuple(row) for row in V.matrix(value, path, **_YAML).tolist())


def _vector_or_matrix(value, path):
    """A list of numbers or a list of equal-length lists of numbers."""
    if V.is_sequence(value) and len(value) and V.is_sequence(value[0]):
        return _rows(value, path)
    if V.is_sequence(value):
        return _numbers()(value, path)
    raise ConfigError(
        path, f"expected a list of numbers or a list of equal-length lists of numbers, got {V.show(value)}"
    )


def _integers(value, path):
    if not V.is_sequence(value):
        raise ConfigError(path, f"expected a list of integers, got {V.show(value)}")
    return tuple(V.integer(item, V.join(path, i)) for i, item in enumerate(value))


def _start_step(value, path):
    return value if value == "random" else V.integer(value, path, minimum=0)


def _choice(allowed) -> _Converter:
    allowed = tuple(allowed)

    def conv(value, path):
        return V.name(value, path, allowed)

    conv.allowed = allowed
    return conv


_PLANES = tuple(a + b for a in "xyz" for b in "xyz" if a != b)


def _plane(value, path):
    if value not in _PLANES:
        raise ConfigError(
            path,
            f"unknown value {V.show(value)}; allowed values are two distinct letters of x, y, z ({', '.join(_PLANES)})",
        )
    return value


def _optional(conv: _Converter) -> _Converter:
    def optional(value, path):
        return None if value is None else conv(value, path)

    optional.allowed = getattr(conv, "allowed", None)
    return optional


def _list_of(conv: _Converter, what: str) -> _Converter:
    def list_of(value, path):
        if not isinstance(value, list | tuple):
            raise ConfigError(path, f"expected a list of {what}, got {V.show(value)}")
        return tuple(conv(item, V.join(path, i)) for i, item in enumerate(value))

    return list_of


def _mapping_of(value_conv: _Converter, what: str, keys: tuple[str, ...] | None = None) -> _Converter:
    """A mapping from names (``keys`` when given, else any string) to values checked by ``value_conv``."""

    def mapping_of(value, path):
        if not isinstance(value, Mapping):
            raise ConfigError(path, f"expected a mapping of {what}, got {V.show(value)}")
        for key in value:
            if not isinstance(key, str):
                raise ConfigError(path, f"expected a mapping of {what} with string keys, got the key {V.show(key)}")
        if keys is not None:
            V.check_keys(value, path, keys)
        return {key: value_conv(item, V.join(path, key)) for key, item in value.items()}

    return mapping_of


def _section(cls) -> _Converter:
    def section(value, path):
        return cls.from_dict(value, path)

    return section


def _distribution(value, path):
    """A distribution mapping, or a fixed value (a number or a list of numbers)."""
    if isinstance(value, DistributionConfig | Mapping):
        return DistributionConfig.from_dict(value, path)
    if V.is_number(value) or V.is_sequence(value):
        return _number_or_numbers()(value, path)
    raise ConfigError(
        path,
        f"expected a distribution (a mapping with type: {', '.join(randomization.DISTRIBUTIONS)}), "
        f"a number or a list of numbers, got {V.show(value)}",
    )


def _plain(value):
    """Plain YAML data: sections to dicts (``None`` fields left out), tuples to lists."""
    if isinstance(value, _Section):
        return value.to_dict()
    if isinstance(value, Mapping):
        return {key: _plain(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(item) for item in value]
    if isinstance(value, np.ndarray | np.generic):
        return value.tolist()
    return value


# --------------------------------------------------------------------------------------------- sections
# The path of the section being built by ``from_dict`` (read by ``__post_init__`` for its messages).
_BUILD_PATH: contextvars.ContextVar[str | None] = contextvars.ContextVar("scg_jax_config_path", default=None)


def _field(conv: _Converter, default=dataclasses.MISSING):
    return dataclasses.field(default=default, metadata={"conv": conv})


class _Section:
    """Checked construction (``__post_init__``), ``from_dict`` with unknown-key detection, ``to_dict``."""

    _name: ClassVar[str] = ""

    def __post_init__(self):
        path = _BUILD_PATH.get()
        path = self._name if path is None else path
        for field in dataclasses.fields(self):
            value = field.metadata["conv"](getattr(self, field.name), V.join(path, field.name))
            object.__setattr__(self, field.name, value)
        self._check(path)

    def _check(self, path: str) -> None:
        """Checks across fields; overridden by sections that need them."""

    @classmethod
    def _check_keys(cls, data: Mapping, path: str) -> None:
        """Key checks before construction; sections with a ``type`` name the keys that type takes."""
        kinds = getattr(cls, "_type_keys", None)
        if kinds is not None and isinstance(data.get("type"), str) and data["type"] in kinds:
            allowed = cls._common_keys + kinds[data["type"]]
            V.check_keys(data, path, allowed, where=f"for a {data['type']} {cls._name}")

    @classmethod
    def keys(cls) -> tuple[str, ...]:
        return tuple(field.name for field in dataclasses.fields(cls))

    @classmethod
    def from_dict(cls, data, path: str | None = None):
        """Build from a mapping (e.g. parsed YAML), checking keys and types; ``path`` prefixes messages."""
        path = cls._name if path is None else path
        if isinstance(data, cls):
            return data
        names = cls.keys()
        if not isinstance(data, Mapping):
            raise ConfigError(path, f"expected a mapping with keys {', '.join(names)}, got {V.show(data)}")
        # ``on:`` read by a YAML 1.1 parser (plain yaml.safe_load) is the key True.
        kwargs = {("on" if key is True and "on" in names else key): value for key, value in data.items()}
        cls._check_keys(kwargs, path)
        V.check_keys(kwargs, path, names)
        for field in dataclasses.fields(cls):
            if field.name not in kwargs and field.default is dataclasses.MISSING:
                allowed = getattr(field.metadata["conv"], "allowed", None)
                extra = f"; allowed values are {', '.join(allowed)}" if allowed else ""
                raise ConfigError(V.join(path, field.name), f"required{extra}")
        token = _BUILD_PATH.set(path)
        try:
            return cls(**kwargs)
        finally:
            _BUILD_PATH.reset(token)

    def to_dict(self) -> dict:
        """Plain data (dicts, lists, numbers, strings) that ``from_dict`` and YAML accept; ``None`` fields are
        left out."""
        result = {}
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if value is not None:
                result[field.name] = _plain(value)
        return result


def _check_type_keys(section, path: str, what: str, common, keys, required=None) -> None:
    """The keys set in ``section`` are ones its ``type`` takes, and those it requires are set."""
    allowed = tuple(common) + tuple(keys)
    given = {field.name: None for field in dataclasses.fields(section) if getattr(section, field.name) is not None}
    V.check_keys(given, path, allowed, where=f"for a {section.type} {what}")
    for key in keys if required is None else required:
        if getattr(section, key) is None:
            raise ConfigError(V.join(path, key), f"required for a {section.type} {what}")


@dataclasses.dataclass(frozen=True)
class TrajectoryConfig(_Section):
    """Tracking reference (``make``'s ``trajectory``); a field left ``None`` takes the system's default."""

    _name: ClassVar[str] = "trajectory"

    shape: str | None = _field(_optional(_choice(trajectories.SHAPES)), None)
    num_cycles: float | None = _field(_optional(_number), None)
    plane: str | None = _field(_optional(_plane), None)
    offset: tuple[float, float] | None = _field(_optional(_numbers(2)), None)
    scale: float | None = _field(_optional(_number), None)


@dataclasses.dataclass(frozen=True)
class DistributionConfig(_Section):
    """A distribution of ``scg_jax.randomization``: ``uniform`` (low, high), ``normal`` (mean, std, optional
    truncation low, high) or ``choice`` (values); ``relative`` for physical parameters only."""

    _name: ClassVar[str] = "distribution"
    _common_keys: ClassVar[tuple] = ("type", "relative")
    _type_keys: ClassVar[dict] = randomization._KEYS

    type: str = _field(_choice(randomization.DISTRIBUTIONS))
    low: float | tuple[float, ...] | None = _field(_optional(_number_or_numbers(allow_inf=True)), None)
    high: float | tuple[float, ...] | None = _field(_optional(_number_or_numbers(allow_inf=True)), None)
    mean: float | tuple[float, ...] | None = _field(_optional(_number_or_numbers()), None)
    std: float | tuple[float, ...] | None = _field(_optional(_number_or_numbers()), None)
    values: tuple | None = _field(_optional(_vector_or_matrix), None)
    relative: bool | None = _field(_optional(V.boolean), None)

    def _check(self, path: str) -> None:
        required = {"uniform": ("low", "high"), "normal": ("mean", "std"), "choice": ("values",)}[self.type]
        _check_type_keys(self, path, "distribution", ("type", "relative"), randomization._KEYS[self.type], required)


@dataclasses.dataclass(frozen=True)
class ConstraintConfig(_Section):
    """A constraint of ``scg_jax.constraints``; which keys a type takes is checked by ``make`` (the keys a type
    requires are checked here)."""

    _name: ClassVar[str] = "constraint"
    _common_keys: ClassVar[tuple] = constraints_lib._COMMON_KEYS
    _type_keys: ClassVar[dict] = constraints_lib._KEYS

    type: str = _field(_choice(constraints_lib.CONSTRAINT_TYPES))
    on: str | None = _field(_optional(_choice(constraints_lib.CONSTRAINT_VARIABLES)), None)
    active_dims: tuple[int, ...] | None = _field(_optional(_integers), None)
    strict: bool | None = _field(_optional(V.boolean), None)
    tolerance: float | None = _field(_optional(_number), None)
    low: tuple[float, ...] | None = _field(_optional(_numbers(allow_inf=True)), None)
    high: tuple[float, ...] | None = _field(_optional(_numbers(allow_inf=True)), None)
    bound: float | tuple[float, ...] | None = _field(_optional(_number_or_numbers(allow_inf=True)), None)
    A: tuple[tuple[float, ...], ...] | None = _field(_optional(_rows), None)
    b: float | tuple[float, ...] | None = _field(_optional(_number_or_numbers(allow_inf=True)), None)
    P: tuple[tuple[float, ...], ...] | None = _field(_optional(_rows), None)

    def _check(self, path: str) -> None:
        _check_type_keys(self, path, "constraint", constraints_lib._COMMON_KEYS, constraints_lib._KEYS[self.type])


@dataclasses.dataclass(frozen=True)
class DisturbanceConfig(_Section):
    """A disturbance of ``scg_jax.disturbances``; which keys a type takes and requires is checked by ``make``."""

    _name: ClassVar[str] = "disturbance"
    _common_keys: ClassVar[tuple] = ("type", "mask")
    _type_keys: ClassVar[dict] = disturbances_lib._KEYS

    type: str = _field(_choice(disturbances_lib.DISTURBANCE_TYPES))
    mask: float | tuple[float, ...] | None = _field(_optional(_number_or_numbers()), None)
    std: float | tuple[float, ...] | None = _field(_optional(_number_or_numbers()), None)
    low: float | tuple[float, ...] | None = _field(_optional(_number_or_numbers()), None)
    high: float | tuple[float, ...] | None = _field(_optional(_number_or_numbers()), None)
    magnitude: float | tuple[float, ...] | None = _field(_optional(_number_or_numbers()), None)
    start_step: int | str | None = _field(_optional(_start_step), None)
    duration: int | None = _field(_optional(V.integer), None)
    decay: float | None = _field(_optional(_number), None)
    scale: float | tuple[float, ...] | None = _field(_optional(_number_or_numbers()), None)
    frequency: float | None = _field(_optional(_number), None)

    def _check(self, path: str) -> None:
        required = tuple(key for key in disturbances_lib._KEYS[self.type] if key not in disturbances_lib._DEFAULTS)
        _check_type_keys(self, path, "disturbance", ("type", "mask"), disturbances_lib._KEYS[self.type], required)
        if self.start_step == "random" and self.type != "impulse":
            raise ConfigError(
                V.join(path, "start_step"),
                f"expected a non-negative integer, got 'random' ('random' is only allowed for an impulse "
                f"disturbance, not a {self.type} one)",
            )


@dataclasses.dataclass(frozen=True)
class AdversaryConfig(_Section):
    """The adversary input channel and its scale (``make``'s ``adversary``)."""

    _name: ClassVar[str] = "adversary"

    channel: str = _field(_choice(disturbances_lib.CHANNELS))
    scale: float | tuple[float, ...] | None = _field(_optional(_number_or_numbers()), None)


def _option(name: str, conv: _Converter):
    """A field for ``make`` option ``name`` with ``make``'s default (``None`` allowed where that is the default)."""
    default = _OPTION_DEFAULTS[name]
    return _field(_optional(conv) if default is None else conv, default)


@dataclasses.dataclass(frozen=True)
class EnvConfig(_Section):
    """The ``env`` section: ``make(system, task, **options)`` with one typed field per option.

    ``None`` means ``make``'s default (e.g. the system's Q, R, goal, initial-state range). Sequences are
    stored as tuples and mappings of sections as dicts.
    """

    _name: ClassVar[str] = "env"

    system: str = _field(_choice(SYSTEMS))
    task: str = _field(_choice(TASKS), DEFAULT_TASK)
    ctrl_freq: int = _option("ctrl_freq", V.integer)
    physics_freq: int = _option("physics_freq", V.integer)
    episode_len_sec: float = _option("episode_len_sec", _number)
    integrator: str = _option("integrator", _choice(INTEGRATORS))
    action_mode: str = _option("action_mode", _choice(ACTION_MODES))
    reward_type: str = _option("reward_type", _choice(REWARD_TYPES))
    obs_goal_horizon: int = _option("obs_goal_horizon", V.integer)
    done_on_out_of_bounds: bool = _option("done_on_out_of_bounds", V.boolean)
    done_on_goal: bool = _option("done_on_goal", V.boolean)
    trajectory: TrajectoryConfig | None = _option("trajectory", _section(TrajectoryConfig))
    physics: dict[str, float] | None = _option("physics", _mapping_of(_number, "parameter names to numbers"))
    Q: tuple | None = _option("Q", _vector_or_matrix)
    R: tuple | None = _option("R", _vector_or_matrix)
    goal: tuple[float, ...] | None = _option("goal", _numbers())
    goal_tolerance: float = _option("goal_tolerance", _number)
    init_state: DistributionConfig | float | tuple[float, ...] | None = _option("init_state", _distribution)
    physics_randomization: dict[str, DistributionConfig | float] | None = _option(
        "physics_randomization", _mapping_of(_distribution, "parameter names to distributions")
    )
    mse_weight: tuple[float, ...] | None = _option("mse_weight", _numbers())
    constraints: tuple[ConstraintConfig, ...] | None = _option(
        "constraints", _list_of(_section(ConstraintConfig), "constraint mappings")
    )
    done_on_violation: bool = _option("done_on_violation", V.boolean)
    violation_penalty: float = _option("violation_penalty", _number)
    disturbances: dict[str, tuple[DisturbanceConfig, ...]] | None = _option(
        "disturbances",
        _mapping_of(
            _list_of(_section(DisturbanceConfig), "disturbance mappings"),
            "channels to lists of disturbances",
            keys=disturbances_lib.CHANNELS,
        ),
    )
    adversary: AdversaryConfig | None = _option("adversary", _section(AdversaryConfig))

    @classmethod
    def option_names(cls) -> tuple[str, ...]:
        """The fields that are options of ``make`` (all but ``system`` and ``task``)."""
        return tuple(name for name in cls.keys() if name not in ("system", "task"))

    def make_options(self) -> dict:
        """Keyword arguments for ``make`` as plain data, leaving out the ``None`` (default) ones."""
        options = {}
        for name in self.option_names():
            value = getattr(self, name)
            if value is not None:
                options[name] = _plain(value)
        return options
