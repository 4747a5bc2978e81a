"""Safety filters: certify any controller's input (CBF-QP, learned CBF, linear and nonlinear MPSC).

``make_filter(name, env, prior_params, options)`` builds a registered filter; ``filtered(controller, filter)``
wraps a controller with it (``scg_algorithms.safety_filters.base`` has the protocol). A trained learned CBF is
loaded from its folder with ``load_filter(path, env, true_params)``. Modules are imported on first use.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from pathlib import Path

from scg_algorithms.safety_filters.base import (
    Filter,
    FilteredController,
    FilteredState,
    FilterInfo,
    FilterStats,
    SafetyFilter,
    check_system,
    filtered,
    is_filtered,
)

# ------------------------------------------------------------------------------------------- FILTER REGISTRY
# name -> "module:factory"; every factory is ``factory(env, prior_params, options=None) -> SafetyFilter`` with the
# options of the config's ``safety_filters.<name>`` section. Add new filters here (keep scg_jax.config's
# SAFETY_FILTER_NAMES, the names a config may hold, in step).
FILTERS = {
    "cbf": "scg_algorithms.safety_filters.cbf:make_cbf",
    "learned_cbf": "scg_algorithms.safety_filters.learned_cbf:make_learned_cbf",
    "linear_mpsc": "scg_algorithms.safety_filters.mpsc_linear:make_linear_mpsc",
    "nonlinear_mpsc": "scg_algorithms.safety_filters.mpsc_nonlinear:make_nonlinear_mpsc",
}
# ------------------------------------------------------------------------------------------------------------


def filter_factory(name: str):
    """The factory registered under ``name``; ``ValueError`` naming the allowed names otherwise."""
    if name not in FILTERS:
        raise ValueError(f"safety filter: unknown name {name!r}; allowed values are {', '.join(FILTERS)}")
    module, _, attribute = FILTERS[name].partition(":")
    return getattr(importlib.import_module(module), attribute)


def make_filter(name: str, env, prior_params, options: Mapping | None = None):
    """Build the safety filter ``name`` for ``env`` from the prior model ``prior_params`` and its ``options``."""
    return filter_factory(name)(env, prior_params, options)


def is_filter_folder(path) -> bool:
    """Whether ``path`` is a folder written by a trained filter (``scg-jax train --algo learned_cbf``)."""
    from scg_algorithms.safety_filters.learned_cbf import is_run

    return Path(path).is_dir() and is_run(Path(path))


def load_filter(path, env, params, options: Mapping | None = None):
    """The trained filter saved in ``path`` for ``env``; ``params`` are the true plant's (the saved prior scale is
    applied to them). ``options`` override the saved filter options (not the training ones)."""
    from scg_algorithms.safety_filters.learned_cbf import load_learned_cbf

    return load_learned_cbf(Path(path), env, params, options)


__all__ = [
    "FILTERS",
    "Filter",
    "FilterInfo",
    "FilterStats",
    "FilteredController",
    "FilteredState",
    "SafetyFilter",
    "check_system",
    "filter_factory",
    "filtered",
    "is_filter_folder",
    "is_filtered",
    "load_filter",
    "make_filter",
]
