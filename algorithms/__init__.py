"""Controllers and learners for ``scg_jax`` environments, all behind the protocol in ``scg_algorithms.base``.

``make_controller(name, env, prior_params, options)`` builds any registered controller by name; the modules are
imported on first use, so importing this package stays cheap.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping

# name -> "module:factory"; every factory is ``factory(env, prior_params, options=None) -> Controller``.
CONTROLLERS = {
    "pid": "scg_algorithms.pid:make_pid",
    "lqr": "scg_algorithms.lqr:make_lqr",
    "ilqr": "scg_algorithms.ilqr:make_ilqr",
    "linear_mpc": "scg_algorithms.mpc.linear:make_linear_mpc",
    "linear_mpc_casadi": "scg_algorithms.mpc.linear:make_linear_mpc_casadi",
    "nonlinear_mpc": "scg_algorithms.mpc.nonlinear:make_nonlinear_mpc",
    "gp_mpc": "scg_algorithms.gp_mpc.controller:make_gp_mpc",
}


def controller_factory(name: str):
    """The factory registered under ``name``; ``ValueError`` naming the allowed names otherwise."""
    if name not in CONTROLLERS:
        raise ValueError(f"controller: unknown name {name!r}; allowed values are {', '.join(CONTROLLERS)}")
    module, _, attribute = CONTROLLERS[name].partition(":")
    return getattr(importlib.import_module(module), attribute)


def make_controller(name: str, env, prior_params, options: Mapping | None = None):
    """Build the controller ``name`` for ``env`` from the prior model ``prior_params`` and its ``options``."""
    return controller_factory(name)(env, prior_params, options)
