"""The one interface every method implements, so the harness, the CLI and the safety filters can swap them.

A controller sees what a deployed controller would see: the observation of its own copy (``obs``, possibly
noisy, possibly with the next reference points appended) and the task reference; never the env state or the
true plant parameters. It returns the *physical* input ``u`` (N for every system here); the harness converts
it to the env's action (``env.input_to_action``) when the env runs with ``action_mode="normalized"``.

Two kinds, told apart by ``is_jax``:

- ``is_jax = True``: ``reset`` and ``act`` are pure JAX functions of one copy. The harness ``jax.vmap``-s them
  over thousands of copies and runs the whole closed loop in one ``jax.jit``-ed ``lax.scan``.
- ``is_jax = False`` (CasADi/IPOPT and other host solvers): ``reset`` and ``act`` take and return numpy
  arrays of one copy and run on the host, one copy at a time; the harness steps the batch of envs together.

Protocol (per copy; ``reference`` is that copy's ``Reference``)::

    ctrl_state = controller.reset(key, reference)
    u, ctrl_state = controller.act(ctrl_state, obs, step, reference)

``step`` is the control-step index ``k`` of the state the observation shows (0 right after reset), so
``reference.x_ref[k]`` is where the plant should be now and ``reference.u_ref[k]`` the feedforward input of this
step. ``ctrl_state`` is the controller's memory (PID integrators, a warm start, a previous plan); an empty tuple
when it has none. A controller that learns from data (GP-MPC, RL) may add ``learn(data) -> Controller``.

Every factory has the signature ``make_<name>(env, prior_params, options=None) -> Controller``: the controller is
built from ``env.symbolic_model(prior_params)`` (or ``prior_params.physics`` with the same ``dynamics``
function), so a deliberately wrong prior is a choice of the caller. ``options`` is a mapping (a config file's
``controllers.<name>`` section) parsed by ``parse_options`` into the controller's frozen ``Options``.
"""

from __future__ import annotations

import dataclasses
import numbers
import sys
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any, ClassVar, NamedTuple, Protocol, runtime_checkable

from scg_jax import validation as V


class Reference(NamedTuple):
    """The task reference of one copy (``env.reference(params)``).

    Attributes:
        x_ref: (num_steps + 1, nx) state reference; ``x_ref[k]`` is the target at control step k.
        u_ref: (num_steps, nu) input reference (hover thrust, zero force), N.
    """

    x_ref: Any
    u_ref: Any


@runtime_checkable
class Controller(Protocol):
    """What the evaluation harness needs of a method (see the module docstring)."""

    name: str
    is_jax: bool

    def reset(self, key, reference: Reference) -> Any: ...

    def act(self, ctrl_state, obs, step, reference: Reference) -> tuple[Any, Any]: ...


@dataclasses.dataclass(frozen=True, eq=False)
class JaxController:
    """A controller made of two pure JAX functions of one copy (jit- and vmap-able).

    Attributes:
        name: the method's name (``"lqr"``, ``"pid"``, ...), used in tables and JSON.
        reset_fn: ``reset_fn(key, reference) -> ctrl_state`` (a pytree; ``()`` when stateless).
        act_fn: ``act_fn(ctrl_state, obs, step, reference) -> (u, ctrl_state)``, ``u`` (nu,) in N.
        info: static facts about the controller for reports (gains, horizon, ...); not traced.
    """

    name: str
    reset_fn: Callable
    act_fn: Callable
    info: Mapping = dataclasses.field(default_factory=dict)
    is_jax: ClassVar[bool] = True

    def reset(self, key, reference: Reference):
        return self.reset_fn(key, reference)

    def act(self, ctrl_state, obs, step, reference: Reference):
        return self.act_fn(ctrl_state, obs, step, reference)


def state_from_obs(env, obs):
    """The physical-state part of an observation: its first ``nx`` entries (the rest is reference look-ahead)."""
    return obs[..., : env.nx]


# --------------------------------------------------------------------------------------------- options
def _positive(value, path: str):
    V.positive(value, path)
    return value


def _non_negative(value, path: str):
    V.non_negative(value, path)
    return value


def _unit_interval(value, path: str):
    if not 0.0 <= value <= 1.0:
        raise V.FieldError(path, f"must be in [0, 1], got {value!r}")
    return value


def _layer_sizes(value, path: str) -> tuple[int, ...]:
    if value is None or len(value) == 0:
        raise V.FieldError(path, "expected a list of layer sizes, e.g. [64, 64]")
    if any(v < 1 for v in value):
        raise V.FieldError(path, f"layer sizes must be positive integers, got {list(value)}")
    return tuple(value)


# What ``option(check=...)`` may ask of a value, each ``check(value, path) -> value`` raising ``FieldError``.
CHECKS = {
    "positive": _positive,  # a number > 0
    "non_negative": _non_negative,  # a number >= 0
    "unit_interval": _unit_interval,  # a number in [0, 1]
    "layer_sizes": _layer_sizes,  # hidden layer sizes: a non-empty tuple of positive ints
}


def option(default, doc: str = "", choices: Sequence[str] | None = None, check: str | None = None):
    """A field of an options dataclass (a controller's or filter's ``Options``, a learner's ``Config``).

    Args:
        default: the value when the field is not given; its type is the field's (bool, int, float, str, a tuple
            of ints such as hidden layer sizes, a tuple of floats or ``None`` for a vector such as a diagonal
            weight). doc: one line for listings. choices: the allowed strings. check: a key of ``CHECKS``
            (``positive``, ``non_negative``, ``unit_interval``, ``layer_sizes``) that every value must pass.
    """
    if check is not None and check not in CHECKS:
        raise ValueError(f"option check: unknown value {check!r}; allowed values are {', '.join(CHECKS)}")
    metadata = {"doc": doc, "choices": tuple(choices) if choices else None, "check": check}
    return dataclasses.field(default=default, metadata=metadata)


def _integers(values: tuple, path: str) -> tuple[int, ...]:
    if any(not float(v).is_integer() for v in values):
        raise V.FieldError(path, f"expected integers, got {list(values)}")
    return tuple(int(v) for v in values)


def _check_value(path: str, value, field: dataclasses.Field):
    """``value`` converted to the type of ``field``'s default through ``scg_jax.validation`` and passed through
    its ``check``, or a ``FieldError`` naming ``path``."""
    default, choices, check = field.default, field.metadata.get("choices"), field.metadata.get("check")
    if choices is not None:
        value = V.name(value, path, choices)
    elif isinstance(default, bool):
        value = V.boolean(value, path)
    elif isinstance(default, numbers.Integral):
        value = V.integer(value, path)
    elif isinstance(default, numbers.Real):
        value = V.number(value, path)
    elif isinstance(default, str):
        value = V.string(value, path)
    elif default is None or isinstance(default, tuple):
        if value is not None:
            value = tuple(V.vector(value, path, broadcast=True).reshape(-1).tolist())
            if default and all(isinstance(v, numbers.Integral) for v in default):
                value = _integers(value, path)
    if check is not None and value is not None:
        value = CHECKS[check](value, path)
    return value


def parse_options(cls, options: Mapping | None, path: str):
    """Build the frozen options dataclass ``cls`` from a mapping, checking every key and value.

    Fields are declared with ``option``: a field's default fixes its type, its ``choices`` and ``check`` what it
    may hold. A class may define ``_check(self, path)`` for checks across fields. An instance built directly is
    checked the same way (its fields are parsed again), so no unchecked options reach a method.

    Args:
        cls: the dataclass. options: a mapping of field names to values, ``None`` for all defaults, or an
            instance of ``cls`` (or of a subclass, kept). path: prefix of error messages, e.g.
            ``"controllers.nonlinear_mpc"``.

    Raises:
        ValueError: ``"<path>.<key>: unknown key; allowed keys are ..."`` or ``"<path>.<key>: expected ..."``.
    """
    if options is None:
        options = {}
    if isinstance(options, cls):
        cls, options = type(options), {f.name: getattr(options, f.name) for f in dataclasses.fields(options)}
    if not isinstance(options, Mapping):
        raise V.FieldError(path, f"expected a mapping of options, got {V.show(options)}")
    fields = {field.name: field for field in dataclasses.fields(cls)}
    V.check_keys(options, path, fields)
    result = cls(**{key: _check_value(f"{path}.{key}", value, fields[key]) for key, value in options.items()})
    check = getattr(result, "_check", None)
    if check is not None:
        check(path)
    return result


def with_defaults(cls, doc: str, **defaults):
    """A subclass of the options dataclass ``cls`` that differs from it only in the ``defaults`` given (same
    fields, docs, checks and ``_check``), documented by ``doc``: one declaration serving methods that differ by
    their defaults (RARL's options are RAP's with one adversary and the alternating schedule)."""
    fields = {field.name: field for field in dataclasses.fields(cls)}
    V.check_keys(defaults, f"{cls.__name__} defaults", fields)
    changed = [
        (name, fields[name].type, dataclasses.field(default=value, metadata=fields[name].metadata))
        for name, value in defaults.items()
    ]
    # The caller's module, as collections.namedtuple does: where the class is defined for repr and pickling.
    namespace = {"__doc__": doc, "__module__": sys._getframe(1).f_globals.get("__name__", __name__)}
    return dataclasses.make_dataclass(cls.__name__, changed, bases=(cls,), namespace=namespace, frozen=True)


def positive(path: str, value) -> None:
    """Raise ``FieldError`` (a ValueError) naming ``path`` unless ``value > 0`` (``scg_jax.validation.positive``)."""
    V.positive(value, path)


def check_fields(
    config,
    path: str,
    *,
    positive_fields: Iterable[str] = (),
    nonnegative: Iterable[str] = (),
    closed_unit: Iterable[str] = (),
) -> None:
    """Check groups of ``config``'s fields (an ``Options`` dataclass, errors named ``<path>.<field>``): ``> 0``,
    ``>= 0``, in ``[0, 1]``."""
    for name in positive_fields:
        positive(f"{path}.{name}", getattr(config, name))
    for name in nonnegative:
        if getattr(config, name) < 0:
            raise ValueError(f"{path}.{name}: must be >= 0, got {getattr(config, name)!r}")
    for name in closed_unit:
        if not 0.0 <= getattr(config, name) <= 1.0:
            raise ValueError(f"{path}.{name}: must be in [0, 1], got {getattr(config, name)!r}")
