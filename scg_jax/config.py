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

A key left out (or ``null`` where the default is ``null``) means ``make``'s default: ``make`` reads its options into
the same ``EnvConfig`` (``scg_jax.env_config``), so the two cannot disagree.

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

import copy
import dataclasses
import os
import re
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any, ClassVar

import yaml

from scg_jax import validation as V
from scg_jax.env import Env, EnvParams, make
from scg_jax.env_config import (
    ConfigError,
    EnvConfig,
    _field,
    _mapping_of,
    _optional,
    _plain,
    _Section,
    _section,
)

# EnvConfig and its sections (TrajectoryConfig, DistributionConfig, ...) live in scg_jax.env_config.
__all__ = [
    "Config",
    "ConfigError",
    "EnvConfig",
    "dump_config",
    "load_config",
    "make_from_config",
]


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


# The safety filters a config's ``safety_filters`` section may configure: the names of the registry
# ``scg_algorithms.safety_filters.FILTERS``. The environment layer does not import the algorithms, so the config holds
# the names and tests/test_config.py checks that the registry has exactly these.
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
    of the learner ``algo`` (checked when it trains), ``safety_filters.<name>`` the options
    of the safety filter ``name`` (one of ``SAFETY_FILTER_NAMES``; the options are checked when the filter is built,
    messages name ``safety_filters.<name>.<key>``). All default to empty (every option at its default).
    ``devices`` (``"all"`` or a count N) lays the env copies out over that many devices (``scg_jax.sharding``;
    default: one device).
    """

    _name: ClassVar[str] = ""

    env: EnvConfig = _field(_section(EnvConfig))
    controllers: dict = _field(_optional(_mapping_of(_options_mapping, "controller names to their options")), None)
    training: dict = _field(_optional(_mapping_of(_options_mapping, "learner names to their hyperparameters")), None)
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
