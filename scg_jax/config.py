"""Typed configuration files: one YAML file describes an environment, ``make_from_config`` builds it.

Layout (every key of ``env`` but ``system`` and ``task`` is an option of ``scg_jax.make``, same name, same
meaning, same default)::

    env:
      system: cartpole            # cartpole, quadrotor_1d, quadrotor_2d, quadrotor_3d
      task: stabilization         # or tracking
      ctrl_freq: 15               # Hz
      physics_freq: 750           # Hz, a multiple of ctrl_freq
      trajectory: {shape: figure8, num_cycles: 1, plane: xz, offset: [0.0, 1.0], scale: 0.75}  # tracking only
      init_state: {type: uniform, low: [...], high: [...]}          # or a fixed state [...]
      physics_randomization:
        pole_mass: {type: uniform, low: 0.9, high: 1.1, relative: true}
      constraints:
        - {type: default, on: state}
        - {type: abs_bound, on: input, bound: 5.0}
      disturbances:
        observation: [{type: white_noise, std: 0.001}]
      adversary: {channel: action, scale: 1.0}

A key left out (or ``null`` where the default is ``null``) means ``make``'s default; the defaults of
``EnvConfig`` are read from ``scg_jax.env._OPTION_DEFAULTS`` so the two cannot disagree.

Every check goes through ``scg_jax.validation`` and raises its ``FieldError`` (``ConfigError`` here, a
``ValueError``) whose ``path`` is the dotted path of the field. Constructing a section (``load_config``,
``Config.from_dict`` or the dataclasses directly) checks keys (per type for constraints, disturbances and
distributions), types, structural shapes and the fixed sets of names: ``env.ctrl_freq: expected an integer, got
'fast'``, ``env.trajctory: unknown key; allowed keys are ... (did you mean 'trajectory'?)``. ``make_from_config``
passes the typed ``EnvConfig`` to ``make``, which checks what depends on the system or on several fields (vector
lengths, positive masses, frequencies) and raises with paths inside the section; they gain the ``env.`` prefix:
``env.physics_freq: must be a multiple of ctrl_freq (15 Hz), got 1000 Hz; allowed values are 15, 30, ...``.

YAML is read with YAML 1.2 scalars: only ``true``/``false`` are booleans (so the constraint key ``on`` stays
a string, where YAML 1.1 reads it as ``true``) and ``1e-3`` is a number (YAML 1.1 reads it as a string).
Duplicate keys are an error.
"""

from __future__ import annotations

import contextvars
import copy
import dataclasses
import inspect
import os
import re
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import yaml

from scg_jax import constraints as constraints_lib
from scg_jax import disturbances as disturbances_lib
from scg_jax import randomization, trajectories
from scg_jax import validation as V
from scg_jax.env import _OPTION_DEFAULTS, ACTION_MODES, REWARD_TYPES, TASKS, Env, EnvParams, make
from scg_jax.integrators import INTEGRATORS
from scg_jax.systems import SYSTEMS

__all__ = [
    "AdversaryConfig",
    "Config",
    "ConfigError",
    "ConstraintConfig",
    "DisturbanceConfig",
    "DistributionConfig",
    "EnvConfig",
    "TrajectoryConfig",
    "dump_config",
    "load_config",
    "make_from_config",
]


# One error type for every bad input: ``scg_jax.validation.FieldError`` (``.path`` is the dotted path of the field,
# e.g. ``env.constraints[1].type``; ``.reason`` the rest of the message).
ConfigError = V.FieldError


# --------------------------------------------------------------------------------------------- YAML
_BOOL_TAG = "tag:yaml.org,2002:bool"
_FLOAT_TAG = "tag:yaml.org,2002:float"


class _Loader(yaml.SafeLoader):
    """``SafeLoader`` with YAML 1.2 booleans and floats, rejecting duplicate keys."""

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            self.flatten_mapping(node)
            seen = set()
            for key_node, _ in node.value:
                key = self.construct_object(key_node, deep=True)
                try:
                    duplicate = key in seen
                except TypeError:  # an unhashable key: the base class reports it
                    continue
                if duplicate:
                    raise yaml.constructor.ConstructorError(None, None, f"duplicate key {key!r}", key_node.start_mark)
                seen.add(key)
        return super().construct_mapping(node, deep)


_Loader.yaml_implicit_resolvers = {
    first: [(tag, regexp) for tag, regexp in resolvers if tag not in (_BOOL_TAG, _FLOAT_TAG)]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
_Loader.add_implicit_resolver(_BOOL_TAG, re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$"), list("tTfF"))
_Loader.add_implicit_resolver(_FLOAT_TAG, V.YAML_FLOAT, list("-+0123456789."))


def _yaml_load(text: str, where: str):
    try:
        return yaml.load(text, Loader=_Loader)  # a SafeLoader subclass
    except yaml.YAMLError as err:
        raise ConfigError("", f"{where}: invalid YAML: {err}") from None


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


_TASK_DEFAULT = inspect.signature(make).parameters["task"].default


@dataclasses.dataclass(frozen=True)
class EnvConfig(_Section):
    """The ``env`` section: ``make(system, task, **options)`` with one typed field per option.

    ``None`` means ``make``'s default (e.g. the system's Q, R, goal, initial-state range). Sequences are
    stored as tuples and mappings of sections as dicts.
    """

    _name: ClassVar[str] = "env"

    system: str = _field(_choice(SYSTEMS))
    task: str = _field(_choice(TASKS), _TASK_DEFAULT)
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


# The safety filters a config's ``safety_filters`` section may configure (``scg_algorithms.safety_filters.FILTERS``;
# the environment layer does not import the algorithms, so the names are listed here too).
SAFETY_FILTER_NAMES = ("cbf", "learned_cbf", "linear_mpsc", "nonlinear_mpsc")


def _options_mapping(value, path):
    """A mapping of option names to plain values, checked later by the controller or trainer that reads it."""
    if value is None:
        return {}
    if not isinstance(value, Mapping):
        raise ConfigError(path, f"expected a mapping of option names to values, got {V.show(value)}")
    for key in value:
        if not isinstance(key, str):
            raise ConfigError(path, f"expected option names (strings), got the key {V.show(key)}")
    return {key: _plain(item) for key, item in value.items()}


def _devices(value, path):
    from scg_jax.sharding import check_devices

    return check_devices(value, path)


@dataclasses.dataclass(frozen=True)
class Config(_Section):
    """A whole configuration file: the environment, and the settings of the methods run on it.

    ``controllers.<name>`` holds the options of the controller ``name`` (``scg_algorithms.CONTROLLERS``; checked when
    the controller is built, messages name ``controllers.<name>.<key>``), ``training.<algo>`` the hyperparameters
    of the learner ``algo`` (``ppo``, ``sac``; checked by its ``make_train``), ``safety_filters.<name>`` the options
    of the safety filter ``name`` (one of ``SAFETY_FILTER_NAMES``; the options are checked when the filter is built,
    messages name ``safety_filters.<name>.<key>``). All default to empty (every option at its default).
    ``devices`` (``"all"`` or a count N) lays the env copies out over that many devices (``scg_jax.sharding``;
    default: one device).
    """

    _name: ClassVar[str] = ""

    env: EnvConfig = _field(_section(EnvConfig))
    controllers: dict = _field(_optional(_mapping_of(_options_mapping, "controller names to their options")), None)
    training: dict = _field(
        _optional(_mapping_of(_options_mapping, "learner names (ppo, sac) to their hyperparameters")), None
    )
    safety_filters: dict = _field(
        _optional(_mapping_of(_options_mapping, "safety filter names to their options", SAFETY_FILTER_NAMES)), None
    )
    # The devices the env copies are laid out over (scg_jax.sharding): "all", a count N, or None (one device).
    devices: Any = _field(_devices, None)

    def _check(self, path: str) -> None:
        for name in ("controllers", "training", "safety_filters"):
            if getattr(self, name) is None:
                object.__setattr__(self, name, {})

    def to_dict(self) -> dict:
        result = super().to_dict()
        for name in ("controllers", "training", "safety_filters"):
            if not result.get(name):
                result.pop(name, None)
        if result.get("devices") is None:
            result.pop("devices", None)
        return result


# --------------------------------------------------------------------------------------------- overrides
_PART_RE = re.compile(r"([A-Za-z_][A-Za-z0-9_]*)((?:\[[0-9]+\])*)")
_OVERRIDE_EXAMPLE = "e.g. env.ctrl_freq=15 or env.constraints[0].bound=0.5"


def _format_path(tokens) -> str:
    text = ""
    for token in tokens:
        text += f"[{token}]" if isinstance(token, int) else (f".{token}" if text else token)
    return text


def _parse_override(text) -> tuple[list, Any]:
    if not isinstance(text, str) or "=" not in text:
        raise ConfigError("", f"override {V.show(text)}: expected dotted.key=value, {_OVERRIDE_EXAMPLE}")
    key, _, raw = text.partition("=")
    return _parse_key(key.strip(), text), _yaml_load(raw, f"override {text!r}")


def _parse_key(key: str, text: str) -> list:
    """``"env.constraints[0].bound"`` -> ``["env", "constraints", 0, "bound"]``; ``text`` is the override quoted in
    messages."""
    tokens: list = []
    for part in key.split("."):
        match = _PART_RE.fullmatch(part)
        if match is None:
            raise ConfigError(
                "",
                f"override {text!r}: malformed key {key!r}; expected names separated by dots, each optionally "
                f"followed by [index], {_OVERRIDE_EXAMPLE}",
            )
        tokens.append(match.group(1))
        tokens.extend(int(index) for index in re.findall(r"\[([0-9]+)\]", match.group(2)))
    return tokens


def _set_path(data: dict, tokens: list, value, text: str) -> None:
    node = data
    for i, token in enumerate(tokens):
        last = i == len(tokens) - 1
        where = _format_path(tokens[:i])
        if isinstance(token, str):
            if not isinstance(node, dict):
                raise ConfigError(
                    where, f"is {V.show(node)}, not a mapping, so {token!r} cannot be set in it (override {text!r})"
                )
            if last:
                node[token] = value
            elif node.get(token) is None:
                node[token] = {}
        else:
            if not isinstance(node, list):
                raise ConfigError(
                    where, f"is {V.show(node)}, not a list, so [{token}] cannot be set in it (override {text!r})"
                )
            if token >= len(node):
                raise ConfigError(
                    _format_path(tokens[: i + 1]),
                    f"index out of range; the list has {len(node)} entries (override {text!r})",
                )
            if last:
                node[token] = value
            elif node[token] is None:
                node[token] = {}
        if not last:
            node = node[token]


def _mutable_copy(data):
    if isinstance(data, Mapping):
        return {key: _mutable_copy(value) for key, value in data.items()}
    if isinstance(data, list | tuple):
        return [_mutable_copy(value) for value in data]
    return copy.deepcopy(data)


def _related(a: str, b: str) -> bool:
    """Whether one dotted path is the other or lies inside it."""
    if a == b:
        return True
    short, long = sorted((a, b), key=len)
    return long.startswith(short) and long[len(short)] in ".["


# --------------------------------------------------------------------------------------------- public API
def _read(source) -> tuple[Any, str | None]:
    if isinstance(source, Config):
        return source.to_dict(), None
    if isinstance(source, Mapping):
        return source, None
    if isinstance(source, str) and "\n" in source:
        return _yaml_load(source, "config text"), None
    if hasattr(source, "read"):
        name = getattr(source, "name", None)
        name = name if isinstance(name, str) else None
        return _yaml_load(source.read(), name or "config stream"), name
    if isinstance(source, str | os.PathLike):
        path = Path(source)
        return _yaml_load(path.read_text(), str(path)), str(path)
    raise TypeError(
        f"load_config: expected a path, YAML text, a file object, a mapping or a Config, got {type(source).__name__}"
    )


def load_config(source, overrides: Iterable[str] = (), values: Mapping[str, Any] | None = None) -> Config:
    """Read a configuration and check it.

    Args:
        source: a path to a YAML file, YAML text (a string with a newline, e.g. ``dump_config``'s output), a
            file object, a mapping of plain data, or a ``Config`` (to apply overrides to it).
        overrides: ``"dotted.key=value"`` strings applied in order; the value is parsed as YAML, so
            ``env.ctrl_freq=15``, ``env.trajectory.shape=figure8``,
            ``env.disturbances.action=[{type: white_noise, std: 0.1}]`` and ``env.constraints[0].bound=0.5``
            work. Missing mappings on the way are created; list indices must exist.
        values: ``{"dotted.key": value}`` with Python values (no YAML text), set before the overrides; ``None``
            values are skipped. The CLI sets its flags this way (``{"env.ctrl_freq": 15}``).

    Returns:
        the checked ``Config``.

    Raises:
        ConfigError (a ValueError): naming the dotted path of the field and what is allowed there (and the
            override that set it, or the file).
    """
    if isinstance(overrides, str):
        raise TypeError(f"overrides: expected a list of 'dotted.key=value' strings, got the string {overrides!r}")
    data, name = _read(source)
    data = _mutable_copy(data)
    applied = []
    settings = [(_parse_key(key, key), value, key, False) for key, value in (values or {}).items() if value is not None]
    settings += [(*_parse_override(text), text, True) for text in overrides]
    for tokens, value, text, is_override in settings:
        if data is None:
            data = {}
        if not isinstance(data, dict):
            raise ConfigError("", f"expected a mapping at the top level to apply override {text!r}, got {V.show(data)}")
        _set_path(data, tokens, _mutable_copy(value), text)
        if is_override:
            applied.append((_format_path(tokens), text))
    try:
        return Config.from_dict(data)
    except ConfigError as err:
        for path, text in reversed(applied):
            if _related(path, err.path):
                raise ConfigError(err.path, f"{err.reason} (set by override {text!r})") from None
        if name is not None:
            raise ConfigError(err.path, f"{err.reason} (in {name})") from None
        raise


def dump_config(cfg: Config, path: str | os.PathLike | None = None) -> str:
    """YAML text of ``cfg`` (written to ``path`` as well when given); ``load_config`` of it equals ``cfg``."""
    if not isinstance(cfg, Config):
        raise TypeError(f"dump_config: expected a Config, got {type(cfg).__name__}")
    text = yaml.safe_dump(cfg.to_dict(), sort_keys=False, default_flow_style=None, width=120)
    if path is not None:
        Path(path).write_text(text)
    return text


def make_from_config(cfg: Config | EnvConfig) -> tuple[Env, EnvParams]:
    """``make(cfg.env)`` and its ``default_params``.

    Raises:
        ConfigError (a ValueError): with the full dotted path, e.g. ``env.constraints[1].bound: ...`` or
            ``env.physics.pole_mass: must be a positive finite number ...``.
    """
    if isinstance(cfg, Config):
        env_cfg = cfg.env
    elif isinstance(cfg, EnvConfig):
        env_cfg = cfg
    else:
        raise TypeError(f"make_from_config: expected a Config or an EnvConfig, got {type(cfg).__name__}")
    try:
        env = make(env_cfg)
    except ConfigError as err:  # make's paths are relative to the env section
        raise err.within("env") from None
    return env, env.default_params
