"""The ``scg-jax`` command line.

Subcommands (each an ``add_<name>_parser`` / ``run_<name>`` pair in the module of the same name, registered
in ``_SUBCOMMANDS``):

- ``rollout``: one episode of ``--num-envs`` parallel copies under a simple policy; prints a metrics table and
  writes ``rollout.npz``, ``metrics.json`` and ``rollout.png`` to ``--out``.
- ``eval``: one controller (a registered name or a trained policy's folder) on ``--episodes`` episodes with the
  paper's metrics; writes the JSON, the trajectories (.npz) and a plot (.png).
- ``compare``: several controllers on the same episodes, side by side. Both ``eval`` and ``compare`` take
  ``--filter NAME|DIR`` (a safety filter around every controller; ``scg_algorithms.safety_filters``).
- ``train``: any learner of ``scg_algorithms.learners.LEARNERS`` (the JAX learners with the config's
  ``training.ALGO`` hyperparameters, GP-MPC's learning loop with its ``controllers.gp_mpc`` options, a learned CBF)
  through ``scg_algorithms.train_run``; writes the policy (or the GP, or the filter), checkpoints, the learning
  curve and ``metrics.json`` (training summary and an evaluation).
- ``tune``: a hyperparameter study of a learner or an MPC (``scg_algorithms.tune``: Optuna, TPE, median pruner,
  a CVaR objective, optionally P trials trained as one vmapped population); writes the study, ``best.yaml``,
  ``trials.csv`` and a plot.
- ``sweep``: controllers over a grid of config values and seeds as tasks, in-process or on Ray; one table.
- ``reproduce``: the paper's results (``scg_experiments``): data, plots and ``report.md`` with each claim's verdict.

Modules: ``common`` (environment options, the ``--out`` check, usage errors, tables), ``scale`` (``--devices``,
``--distributed``), ``rollout``, ``evaluate`` (eval and compare), ``train``, ``tune``, ``sweep``, ``reproduce``.

``main(argv) -> int`` never raises ``SystemExit`` itself: it returns 0 on success, 2 on bad input (argparse's
convention; the message is one line, ``scg-jax CMD: error: ...``) and 130 on Ctrl-C (one line saying what was kept),
so it can be called from tests and from the console script alike. ``scg-jax --version`` prints the installed
distribution's version.
"""

from __future__ import annotations

import argparse
import re
import sys
from collections.abc import Callable

from scg_cli.common import UsageError
from scg_cli.evaluate import add_compare_parser, add_eval_parser, run_compare, run_eval
from scg_cli.progress import catch_swallowed_interrupts
from scg_cli.reproduce import add_reproduce_parser, run_reproduce
from scg_cli.rollout import add_rollout_parser, run_rollout
from scg_cli.sweep import add_sweep_parser, run_sweep_command
from scg_cli.train import add_train_parser, run_train
from scg_cli.tune import add_tune_parser, run_tune

_NOTHING_WRITTEN = "interrupted; nothing written"
# name -> (add its parser, run it, what Ctrl-C leaves behind: a line formatted with the parsed arguments).
_SUBCOMMANDS: dict[str, tuple[Callable, Callable, str]] = {
    "rollout": (add_rollout_parser, run_rollout, _NOTHING_WRITTEN),
    "eval": (add_eval_parser, run_eval, _NOTHING_WRITTEN),
    "compare": (add_compare_parser, run_compare, _NOTHING_WRITTEN),
    # train reports its own interruptions (the checkpoint and the resume command); this is for Ctrl-C before training.
    "train": (add_train_parser, run_train, "interrupted before training started; nothing written"),
    "tune": (add_tune_parser, run_tune, "interrupted before the study started; nothing written"),
    "sweep": (
        add_sweep_parser,
        run_sweep_command,
        "interrupted; the finished tasks are kept in {out}/tasks: run the same command again to resume",
    ),
    "reproduce": (
        add_reproduce_parser,
        run_reproduce,
        "interrupted; the finished results and trained policies are kept in {out}: run the same command again to "
        "continue (cached training is reused)",
    ),
}


class _Parser(argparse.ArgumentParser):
    """An ``ArgumentParser`` whose usage errors are one line (argparse prints the whole usage first, up to 20 lines
    for ``eval``): ``scg-jax eval: error: MESSAGE (see scg-jax eval --help)``."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _version() -> str:
    """The installed distribution's version (``pip install -e .`` installs it), or a note where it is not."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("scg-jax")
    except PackageNotFoundError:
        return "(not installed: run pip install -e . in the checkout)"


def build_parser() -> tuple[argparse.ArgumentParser, dict[str, argparse.ArgumentParser]]:
    """The top-level parser and each subcommand's parser (to report errors against the right command)."""
    parser = _Parser(prog="scg-jax", description="safe-control-gym in JAX")
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    subcommand_parsers = {name: add(subparsers) for name, (add, _, _) in _SUBCOMMANDS.items()}
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
    """Run the CLI on ``argv`` (default: ``sys.argv[1:]``); returns the exit status (0 ok, 2 bad input, 130 Ctrl-C)."""
    from rich.console import Console

    parser, subcommand_parsers = build_parser()
    try:
        args, extras = parser.parse_known_args(_join_negative_lists(sys.argv[1:] if argv is None else list(argv)))
        if extras:  # reported against the subcommand, whose --help lists what it takes
            subcommand_parsers[args.command].error(f"unrecognized arguments: {' '.join(extras)}")
    except SystemExit as exit_:
        # argparse exits for --help and --version (0) and for bad input (2); return the status instead of raising it.
        code = exit_.code
        return code if isinstance(code, int) else (0 if code is None else 1)
    _, run, interrupted = _SUBCOMMANDS[args.command]
    console = Console()
    try:
        with catch_swallowed_interrupts():
            return run(args, console)
    except UsageError as error:
        print(f"{subcommand_parsers[args.command].prog}: error: {error}", file=sys.stderr, flush=True)
        return 2
    except KeyboardInterrupt:
        # One line, no traceback: what Ctrl-C leaves behind. 130 is the shell's status for a process ended by SIGINT.
        console.print(interrupted.format(**vars(args)), soft_wrap=True, markup=False, highlight=False)
        return 130
