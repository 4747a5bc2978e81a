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
def option(default, doc: str = "", choices: Sequence[str] | None = None):
    """A field of a controller's ``Options`` dataclass: its default, a one-line doc and the allowed strings."""
    return dataclasses.field(default=default, metadata={"doc": doc, "choices": tuple(choices) if choices else None})


def _check_value(path: str, value, default, choices):
    """``value`` converted to the type of ``default`` through ``scg_jax.validation``, or a ``FieldError`` naming
    ``path``."""
    if choices is not None:
        return V.name(value, path, choices)
    if isinstance(default, bool):
        return V.boolean(value, path)
    if isinstance(default, numbers.Integral):
        return V.integer(value, path)
    if isinstance(default, numbers.Real):
        return V.number(value, path)
    if isinstance(default, str):
        return V.string(value, path)
    if default is None or isinstance(default, tuple):
        return None if value is None else tuple(V.vector(value, path, broadcast=True).reshape(-1).tolist())
    return value


def parse_options(cls, options: Mapping | None, path: str):
    """Build the frozen ``Options`` dataclass ``cls`` from a mapping, checking every key and value.

    Fields are declared with ``option``; a field's default fixes its type (bool, int, float, str, or a tuple of
    floats / ``None`` for vectors such as a diagonal weight). A class may define ``_check(self, path)`` for
    checks across fields.

    Args:
        cls: the dataclass. options: a mapping of field names to values, ``None`` for all defaults, or an
            instance of ``cls`` (returned unchanged). path: prefix of error messages, e.g.
            ``"controllers.nonlinear_mpc"``.

    Raises:
        ValueError: ``"<path>.<key>: unknown key; allowed keys are ..."`` or ``"<path>.<key>: expected ..."``.
    """
    if options is None:
        options = {}
    if isinstance(options, cls):
        return options
    if not isinstance(options, Mapping):
        raise V.FieldError(path, f"expected a mapping of options, got {V.show(options)}")
    fields = {field.name: field for field in dataclasses.fields(cls)}
    V.check_keys(options, path, fields)
    kwargs = {}
    for key, value in options.items():
        field = fields[key]
        kwargs[key] = _check_value(f"{path}.{key}", value, field.default, field.metadata.get("choices"))
    result = cls(**kwargs)
    check = getattr(result, "_check", None)
    if check is not None:
        check(path)
    return result


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
