"""The ``scg-jax`` command line.

Subcommands (each an ``add_<name>_parser`` / ``run_<name>`` pair in the module of the same name, registered
in ``_SUBCOMMANDS``):

- ``rollout``: one episode of ``--num-envs`` parallel copies under a simple policy; prints a metrics table and
  writes ``rollout.npz``, ``metrics.json`` and ``rollout.png`` to ``--out``.
- ``eval``: one controller (a registered name or a trained policy's folder) on ``--episodes`` episodes with the
  paper's metrics; writes the JSON, the trajectories (.npz) and a plot (.png).
- ``compare``: several controllers on the same episodes, side by side. Both ``eval`` and ``compare`` take
  ``--filter NAME|DIR`` (a safety filter around every controller; ``scg_algorithms.safety_filters``).
- ``train``: a JAX learner (PPO, SAC, DDPG, TD3, safety-layer PPO, PPO-Lagrangian, RARL, RAP) with the config's
  ``training.ALGO`` hyperparameters, or GP-MPC's learning loop with its ``controllers.gp_mpc`` options, or a
  learned CBF (``--algo learned_cbf``); writes the policy (or the GP, or the
  filter), checkpoints, the learning curve and ``metrics.json`` (training summary and an evaluation).
- ``tune``: a hyperparameter study of a learner or an MPC (``scg_algorithms.tune``: Optuna, TPE, median pruner,
  a CVaR objective, optionally P trials trained as one vmapped population); writes the study, ``best.yaml``,
  ``trials.csv`` and a plot.
- ``sweep``: controllers over a grid of config values and seeds as tasks, in-process or on Ray; one table.
- ``reproduce``: the paper's results (``scg_experiments``): data, plots and ``report.md`` with each claim's verdict.

Modules: ``common`` (environment options, the ``--out`` check, usage errors, tables), ``scale`` (``--devices``,
``--distributed``), ``rollout``, ``evaluate`` (eval and compare), ``train``, ``tune``, ``sweep``, ``reproduce``.

``main(argv) -> int`` never raises ``SystemExit`` itself: it returns 0 on success and 2 on bad input (argparse's
convention), so it can be called from tests and from the console script alike.
"""

from __future__ import annotations

import argparse
import re
import sys
from collections.abc import Callable

from scg_cli.common import UsageError
from scg_cli.evaluate import add_compare_parser, add_eval_parser, run_compare, run_eval
from scg_cli.reproduce import add_reproduce_parser, run_reproduce
from scg_cli.rollout import add_rollout_parser, run_rollout
from scg_cli.sweep import add_sweep_parser, run_sweep_command
from scg_cli.train import add_train_parser, run_train
from scg_cli.tune import add_tune_parser, run_tune

_SUBCOMMANDS: dict[str, tuple[Callable, Callable]] = {
    "rollout": (add_rollout_parser, run_rollout),
    "eval": (add_eval_parser, run_eval),
    "compare": (add_compare_parser, run_compare),
    "train": (add_train_parser, run_train),
    "tune": (add_tune_parser, run_tune),
    "sweep": (add_sweep_parser, run_sweep_command),
    "reproduce": (add_reproduce_parser, run_reproduce),
}


def build_parser() -> tuple[argparse.ArgumentParser, dict[str, argparse.ArgumentParser]]:
    """The top-level parser and each subcommand's parser (to report errors against the right usage line)."""
    parser = argparse.ArgumentParser(prog="scg-jax", description="safe-control-gym in JAX")
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    subcommand_parsers = {name: add(subparsers) for name, (add, _) in _SUBCOMMANDS.items()}
    return parser, subcommand_parsers


_LIST_OPTIONS = ("--gain", "--offset")
_NUMBER_LIST = re.compile(r"-[0-9.][0-9.eE+-]*(,[-+]?[0-9.][0-9.eE+-]*)*")


def _join_negative_lists(argv: list[str]) -> list[str]:
    """``--gain -2.8,-5.2`` -> ``--gain=-2.8,-5.2``: argparse would read a value starting with ``-`` as an option."""
    out = []
    for token in argv:
        if out and out[-1] in _LIST_OPTIONS and _NUMBER_LIST.fullmatch(token):
            out[-1] = f"{out[-1]}={token}"
        else:
            out.append(token)
    return out


def main(argv: list[str] | None = None) -> int:
    """Run the CLI on ``argv`` (default: ``sys.argv[1:]``); returns the exit status (0 ok, 2 bad input)."""
    from rich.console import Console

    parser, subcommand_parsers = build_parser()
    try:
        args = parser.parse_args(_join_negative_lists(sys.argv[1:] if argv is None else list(argv)))
        try:
            return _SUBCOMMANDS[args.command][1](args, Console())
        except UsageError as error:
            subcommand_parsers[args.command].error(str(error))
    except SystemExit as exit_:
        # argparse exits for --help (0) and for bad input (2); return the status instead of raising it.
        code = exit_.code
        return code if isinstance(code, int) else (0 if code is None else 1)
    return 1  # unreachable: parser.error always exits
