"""TEMPORARY stand-in for the filter protocol (the ``cbf`` branch owns the real ``base.py``; it implements the same
names). A safety filter takes any controller's input and minimally changes it so the plant stays in a safe set::

    filter_state = filter.reset(key)
    u, filter_state, info = filter.certify(x_or_obs, u_uncertified, filter_params, filter_state)
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from typing import Any, ClassVar, NamedTuple, Protocol, runtime_checkable


class FilterInfo(NamedTuple):
    """``feasible``: the filter's problem was solved (False: the fallback was used); ``slack`` (>= 0): soft-constraint
    slack used; ``correction`` (nu,): ``u - u_uncertified``, N."""

    feasible: Any
    slack: Any
    correction: Any


@runtime_checkable
class SafetyFilter(Protocol):
    name: str
    is_jax: bool
    system: str
    params: Any

    def reset(self, key) -> Any: ...

    def certify(self, x_or_obs, u_uncertified, filter_params, filter_state) -> tuple[Any, Any, FilterInfo]: ...


@dataclasses.dataclass(frozen=True, eq=False)
class JaxFilter:
    """A filter of two pure JAX functions of one copy (jit- and vmap-able)."""

    name: str
    system: str
    params: Any
    reset_fn: Callable
    certify_fn: Callable
    info: Mapping = dataclasses.field(default_factory=dict)
    is_jax: ClassVar[bool] = True

    def reset(self, key):
        return self.reset_fn(key)

    def certify(self, x_or_obs, u_uncertified, filter_params, filter_state):
        return self.certify_fn(x_or_obs, u_uncertified, filter_params, filter_state)


FILTERS: dict = {}
