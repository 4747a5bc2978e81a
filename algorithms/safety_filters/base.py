"""The safety-filter protocol: a filter minimally changes any controller's input so the plant stays safe.

A filter sees what the controller sees (the observation ``obs`` of its copy; its first ``nx`` entries are the state,
``scg_algorithms.base.state_from_obs``) and the controller's physical input ``u_uncertified`` (N), and returns the
certified input::

    filter_state = safety_filter.reset(key)
    u, filter_state, info = safety_filter.certify(obs, u_uncertified, filter_params, filter_state)

``info`` is a ``FilterInfo``: ``feasible`` (the filter's problem was solved; ``False`` means a fallback input was
used), ``slack`` (>= 0, the soft-constraint slack used, 0 when the hard constraints held), ``correction`` (the
change of the input the plant receives: ``u`` minus the uncertified input clipped to the filter's actuator box, N;
``applied_correction``) and ``applied`` (which input was applied: one of ``APPLIED``). ``filter_params`` is a pytree
of traced values (prior physics, barrier parameters, network weights) whose default is ``safety_filter.params``;
passing others (a trained network) needs no recompilation.

Two kinds, as controllers (``scg_algorithms.base``), told apart by ``is_jax``: ``True``, pure JAX functions of one
copy (the harness ``vmap``-s and ``jit``-s them inside the closed loop); ``False``, functions that take and return
numpy arrays of one copy on the host (CasADi / IPOPT / cvxpy). ``Filter`` holds either kind.

``filtered(controller, safety_filter)`` composes a controller with a filter into a controller (JAX iff both are)
whose state is a ``FilteredState``: the controller's state, the filter's state, the last ``FilterInfo`` and running
``FilterStats``. ``scg_algorithms.evaluation`` recognises such a controller and reports the intervention metrics.

Every filter factory has the signature ``make_<name>(env, prior_params, options=None) -> SafetyFilter``, like the
controllers'; the registry is ``scg_algorithms.safety_filters.FILTERS``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from typing import Any, NamedTuple, Protocol, runtime_checkable

import jax
import jax.numpy as jnp
import numpy as np

from scg_algorithms.base import Reference
from scg_jax.caching import CompileCache

# |correction| above this (N) counts as an intervention. Below it is round-off or an iterative solver's tolerance
# (the batched MPSC's ADMM in float32 leaves corrections of ~1e-8 N on inputs it passes): 0.1 mN moves no actuator
# of these systems measurably.
INTERVENTION_THRESHOLD = 1e-4

# What a filter applied at a step (``FilterInfo.applied``, an int code indexing this tuple):
# certified: the solution of the filter's problem (the uncertified input itself where it was safe);
# best_effort: the soft problem's solution with a slack above its tolerance (no input met the condition);
# backup_plan: the next input of the last certified plan (MPSC), continued with the tube feedback;
# backup_controller: the filter's backup controller (the backup barrier's LQR, MPSC's ancillary LQR).
APPLIED = ("certified", "best_effort", "backup_plan", "backup_controller")
CERTIFIED, BEST_EFFORT, BACKUP_PLAN, BACKUP_CONTROLLER = range(len(APPLIED))


class FilterInfo(NamedTuple):
    """What a filter reports about one certification.

    Attributes:
        feasible: bool scalar: the filter's problem was solved (``False``: a fallback input was used).
        slack: float scalar >= 0: the soft-constraint slack used (0 when the hard constraints held).
        correction: (nu,) the change of the input the plant receives, N: ``u`` minus the uncertified input clipped
            to the actuator box (``applied_correction``), so clipping an input the actuators clip anyway is no
            correction.
        applied: int scalar, which input was applied: an index into ``APPLIED`` (``CERTIFIED`` iff ``feasible``).
    """

    feasible: Any
    slack: Any
    correction: Any
    applied: Any


def applied_correction(u, u_uncertified, u_low, u_high, xnp=jnp):
    """``u - clip(u_uncertified, u_low, u_high)`` (nu,), N: the change a filter made to what the actuators apply."""
    u_uncertified = xnp.asarray(u_uncertified)
    lo = xnp.asarray(u_low).astype(u_uncertified.dtype)
    hi = xnp.asarray(u_high).astype(u_uncertified.dtype)
    return u - xnp.clip(u_uncertified, lo, hi)


@runtime_checkable
class SafetyFilter(Protocol):
    """What the harness needs of a safety filter (see the module docstring)."""

    name: str
    is_jax: bool
    system: str
    params: Any

    def reset(self, key) -> Any: ...

    def certify(self, x_or_obs, u_uncertified, filter_params, filter_state) -> tuple[Any, Any, FilterInfo]: ...


@dataclasses.dataclass(frozen=True, eq=False)
class Filter:
    """A filter made of two functions of one copy: pure JAX (``is_jax``, jit- and vmap-able) or host numpy.

    Attributes:
        name: the filter's name (``"cbf"``, ``"learned_cbf"``, ...). system: the env system it was built for.
        params: the default ``filter_params`` pytree (traced when ``is_jax``). reset_fn: ``reset_fn(key) ->
        filter_state``. certify_fn: ``certify_fn(obs, u_uncertified, filter_params, filter_state) -> (u,
        filter_state, FilterInfo)``; with ``is_jax = False`` it takes and returns numpy arrays (``FilterInfo`` of
        numpy scalars). is_jax: which of the two. info: static facts for reports (barrier, solver, slope, the
        validity check); not traced.
    """

    name: str
    system: str
    params: Any
    reset_fn: Callable
    certify_fn: Callable
    is_jax: bool = True
    info: Mapping = dataclasses.field(default_factory=dict)

    def reset(self, key):
        return self.reset_fn(key)

    def certify(self, x_or_obs, u_uncertified, filter_params, filter_state):
        return self.certify_fn(x_or_obs, u_uncertified, filter_params, filter_state)

    def replace(self, **changes) -> Filter:
        """A copy with some fields changed (e.g. ``params`` of a trained network)."""
        return dataclasses.replace(self, **changes)


class FilterStats(NamedTuple):
    """Running intervention statistics of a filtered controller (counts over its ``act`` calls).

    Attributes:
        steps: number of certified inputs. interventions: steps with ``|correction| > INTERVENTION_THRESHOLD``.
        correction_sum: sum of ``|correction|`` (Euclidean norm, N). infeasible: steps with ``feasible = False``.
    """

    steps: Any
    interventions: Any
    correction_sum: Any
    infeasible: Any


class FilteredState(NamedTuple):
    """The state of a filtered controller: the controller's, the filter's, the last ``FilterInfo`` and the stats."""

    controller: Any
    filter: Any
    info: FilterInfo
    stats: FilterStats


def _check_filter(safety_filter) -> None:
    for name in ("name", "is_jax", "system", "params", "reset", "certify"):
        if not hasattr(safety_filter, name):
            raise TypeError(f"safety_filter: missing {name!r}; see scg_algorithms.safety_filters.base.SafetyFilter")


def check_system(safety_filter, env) -> None:
    """Raise ``ValueError`` unless ``safety_filter`` was built for ``env``'s system."""
    if safety_filter.system != env.system.name:
        raise ValueError(
            f"safety filter {safety_filter.name!r}: built for the {safety_filter.system} system, not for "
            f"{env.system.name}; build it with the env it filters (make_filter(name, env, prior_params))"
        )


def _initial_info_and_stats(nu: int, xnp):
    info = FilterInfo(
        feasible=xnp.asarray(True), slack=xnp.asarray(0.0), correction=xnp.zeros(nu), applied=xnp.asarray(CERTIFIED)
    )
    stats = FilterStats(
        steps=xnp.asarray(0), interventions=xnp.asarray(0), correction_sum=xnp.asarray(0.0), infeasible=xnp.asarray(0)
    )
    return info, stats


def _update_stats(stats: FilterStats, info: FilterInfo, xnp) -> FilterStats:
    magnitude = xnp.sqrt(xnp.sum(xnp.square(info.correction)))
    return FilterStats(
        steps=stats.steps + 1,
        interventions=stats.interventions + (magnitude > INTERVENTION_THRESHOLD).astype(stats.interventions.dtype),
        correction_sum=stats.correction_sum + magnitude,
        infeasible=stats.infeasible + xnp.logical_not(info.feasible).astype(stats.infeasible.dtype),
    )


@dataclasses.dataclass(frozen=True, eq=False)
class FilteredController:
    """``controller`` followed by ``safety_filter``: a Controller (``scg_algorithms.base``) whose ``act`` calls the
    controller, then ``certify`` with the filter's ``params``. JAX iff both parts are JAX.

    The key of ``reset`` is split into the controller's and the filter's. ``info`` merges both parts' reports.
    """

    controller: Any
    safety_filter: Any
    nu: int

    @property
    def name(self) -> str:
        return f"{self.controller.name}+{self.safety_filter.name}"

    @property
    def is_jax(self) -> bool:
        return bool(self.controller.is_jax and self.safety_filter.is_jax)

    @property
    def info(self) -> dict:
        return {
            "controller": dict(getattr(self.controller, "info", {}) or {}),
            "safety_filter": {"name": self.safety_filter.name, **dict(getattr(self.safety_filter, "info", {}) or {})},
        }

    def reset(self, key, reference: Reference) -> FilteredState:
        if self.is_jax:
            ctrl_key, filter_key = jax.random.split(key)
            info, stats = _initial_info_and_stats(self.nu, jnp)
            return FilteredState(
                self.controller.reset(ctrl_key, reference), self.safety_filter.reset(filter_key), info, stats
            )
        ctrl_key, filter_key = jax.random.split(key)
        info, stats = _initial_info_and_stats(self.nu, np)
        return FilteredState(self.controller.reset(ctrl_key, reference), self._filter_reset(filter_key), info, stats)

    def act(self, ctrl_state: FilteredState, obs, step, reference: Reference):
        u_unc, controller_state = self.controller.act(ctrl_state.controller, obs, step, reference)
        if self.is_jax:
            u, filter_state, info = self.safety_filter.certify(obs, u_unc, self.safety_filter.params, ctrl_state.filter)
            stats = _update_stats(ctrl_state.stats, info, jnp)
            return u, FilteredState(controller_state, filter_state, info, stats)
        u, filter_state, info = self._filter_certify(obs, u_unc, ctrl_state.filter)
        info = FilterInfo(
            feasible=np.asarray(bool(np.asarray(info.feasible))),
            slack=np.asarray(float(np.asarray(info.slack))),
            correction=np.asarray(info.correction, dtype=np.float64).reshape(self.nu),
            applied=np.asarray(int(np.asarray(info.applied))),
        )
        stats = _update_stats(ctrl_state.stats, info, np)
        return np.asarray(u, dtype=np.float64).reshape(self.nu), FilteredState(
            controller_state, filter_state, info, stats
        )

    # A JAX filter behind a host controller runs jitted on one copy; a host filter is called as is.
    def _filter_reset(self, key):
        if self.safety_filter.is_jax:
            return jax.tree.map(np.asarray, self.safety_filter.reset(key))
        return self.safety_filter.reset(key)

    def _filter_certify(self, obs, u_unc, filter_state):
        if self.safety_filter.is_jax:
            certify = _jitted_certify(self.safety_filter)
            out = certify(jnp.asarray(obs), jnp.asarray(u_unc), self.safety_filter.params, filter_state)
            return jax.tree.map(np.asarray, out)
        return self.safety_filter.certify(
            np.asarray(obs, dtype=np.float64), np.asarray(u_unc, dtype=np.float64), self.safety_filter.params,
            filter_state,
        )  # fmt: skip


# certify_fn is a closure built with the filter (not a bound method), so an entry never keeps its filter alive.
_JITTED = CompileCache(maxsize=32)


def _jitted_certify(safety_filter):
    return _JITTED.get("certify", lambda: jax.jit(safety_filter.certify_fn), owners=(safety_filter,))


def filtered(controller, safety_filter, env=None) -> FilteredController:
    """``controller`` with every input certified by ``safety_filter`` (see ``FilteredController``).

    Args:
        controller: an ``scg_algorithms.base.Controller`` (JAX or host). safety_filter: a ``SafetyFilter``.
        env: when given, the filter must have been built for its system (``ValueError`` otherwise); the
            evaluation harness checks it again against the env it runs.
    """
    for name in ("name", "is_jax", "reset", "act"):
        if not hasattr(controller, name):
            raise TypeError(f"controller: missing {name!r}; see scg_algorithms.base.Controller")
    _check_filter(safety_filter)
    if env is not None:
        check_system(safety_filter, env)
    nu = int(safety_filter.info.get("nu")) if "nu" in getattr(safety_filter, "info", {}) else None
    if nu is None:
        if env is None:
            raise ValueError("filtered: give env, or a filter whose info holds 'nu'")
        nu = env.nu
    return FilteredController(controller, safety_filter, nu)


def is_filtered(controller) -> bool:
    """Whether ``controller`` is a ``FilteredController`` (the harness then reports intervention metrics)."""
    return isinstance(controller, FilteredController)


def filter_record(ctrl_state: FilteredState) -> dict:
    """The per-step entries the harness records for a filtered controller, from its state after ``act``."""
    return {
        "filter_correction": ctrl_state.info.correction,
        "filter_feasible": ctrl_state.info.feasible,
        "filter_slack": ctrl_state.info.slack,
        "filter_applied": ctrl_state.info.applied,
    }


def intervention_metrics(correction, feasible, length, applied=None) -> dict:
    """Intervention metrics over the steps inside each episode.

    Args:
        correction: (T, N, nu) ``FilterInfo.correction``, N. feasible: (T, N) bool. length: (N,) episode lengths.
        applied: (T, N) ``FilterInfo.applied`` codes, or ``None`` (then only the three first metrics).

    Returns:
        ``intervention_fraction`` (steps with ``|correction| > INTERVENTION_THRESHOLD`` / steps),
        ``mean_correction`` (mean ``|correction|`` over steps, N), ``infeasible_fraction`` (steps with
        ``feasible = False`` / steps) and, with ``applied``, ``infeasible_<kind>_fraction`` for each fallback kind
        of ``APPLIED`` (steps on which that input was applied / steps; they sum to ``infeasible_fraction``),
        plain floats over all episodes' steps.
    """
    correction = np.asarray(correction, dtype=np.float64)
    magnitude = np.sqrt(np.sum(np.square(correction), axis=-1))
    in_episode = np.arange(magnitude.shape[0])[:, None] < np.asarray(length)[None, :]
    steps = max(int(in_episode.sum()), 1)
    metrics = {
        "intervention_fraction": float(((magnitude > INTERVENTION_THRESHOLD) & in_episode).sum() / steps),
        "mean_correction": float(np.where(in_episode, magnitude, 0.0).sum() / steps),
        "infeasible_fraction": float((~np.asarray(feasible, dtype=bool) & in_episode).sum() / steps),
    }
    if applied is not None:
        applied = np.asarray(applied)
        for code, kind in enumerate(APPLIED[1:], start=1):
            metrics[f"infeasible_{kind}_fraction"] = float(((applied == code) & in_episode).sum() / steps)
    return metrics
