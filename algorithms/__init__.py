"""Controllers and learners for ``scg_jax`` environments, all behind the protocol in ``scg_algorithms.base``.

``make_controller(name, env, prior_params, options)`` builds any registered controller by name;
``train_run(algo, config, out_dir, ...)`` trains any learner of ``LEARNERS`` (``scg_algorithms.learners``) into a
folder. The modules are imported on first use, so importing this package stays cheap.
"""

from __future__ import annotations

from collections.abc import Mapping

from scg_algorithms.learners import LEARNERS
from scg_algorithms.registry import lookup

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
    return lookup(CONTROLLERS, name, "controller")


def make_controller(name: str, env, prior_params, options: Mapping | None = None):
    """Build the controller ``name`` for ``env`` from the prior model ``prior_params`` and its ``options``."""
    return controller_factory(name)(env, prior_params, options)


def __getattr__(name: str):
    """``train_run`` and ``TrainResult`` (``scg_algorithms.runs``), imported when first asked for."""
    if name in ("train_run", "TrainResult"):
        from scg_algorithms import runs

        return getattr(runs, name)
    raise AttributeError(f"module 'scg_algorithms' has no attribute {name!r}")


__all__ = ["CONTROLLERS", "LEARNERS", "TrainResult", "controller_factory", "make_controller", "train_run"]
