"""``scg-jax tune``: a hyperparameter study through ``scg_algorithms.tune``: the arguments, the terminal output
(progress, the best trial), Ctrl-C and the exit status."""

from __future__ import annotations

import argparse
import shlex
from pathlib import Path

from scg_algorithms.tune.spaces import SEARCH_SPACES
from scg_cli.common import UsageError, add_env_command, check_output, make_env, positive_int
from scg_cli.progress import add_progress_argument, command_progress

# tune's arguments as this command's flags, for its error messages.
FLAGS = {
    "algo": "--algo",
    "out_dir": "--out",
    "trials": "--trials",
    "population": "--population",
    "seed": "--seed",
    "metric": "--metric",
    "alpha": "--alpha",
    "eval_episodes": "--eval-episodes",
}


def _tail_share(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not 0.0 < value <= 1.0:
        raise argparse.ArgumentTypeError(f"expected a number in (0, 1], got {text!r}")
    return value


def add_tune_parser(subparsers) -> argparse.ArgumentParser:
    parser = add_env_command(
        subparsers,
        "tune",
        "search a method's hyperparameters (" + ", ".join(SEARCH_SPACES) + ") with Optuna; write the best config",
        (
            "Tune a method's options on the env of a config with Optuna (TPE sampler, median pruner). Each trial "
            "trains the method (a learner, or GP-MPC) with options drawn from its search space on top of the config's "
            "section (training.ALGO, controllers.gp_mpc; an MPC is only evaluated), evaluates it on --eval-episodes "
            "episodes and scores it with the CVaR at --alpha of the per-episode RMSE or return. The study is stored "
            "in DIR/study.db: running the same command again continues it until --trials trials have finished. "
            "Writes DIR/best.yaml (the config with the best options: scg-jax train --config DIR/best.yaml), "
            "trials.csv and trials.png; a trial trained alone keeps its run in DIR/trials/NNNN."
        ),
    )
    parser.add_argument(
        "--algo", required=True, choices=tuple(SEARCH_SPACES), metavar="ALGO",
        help="method to tune: " + ", ".join(SEARCH_SPACES),
    )  # fmt: skip
    parser.add_argument("--out", type=Path, required=True, metavar="DIR", help="the study's folder")
    parser.add_argument(
        "--trials", type=positive_int, required=True, help="trials finished in the study when it stops (in all runs)"
    )
    parser.add_argument(
        "--population", type=positive_int, default=1, metavar="P",
        help="JAX learners: train P trials at once as one vmapped program, their traced options (learning rates, "
        "coefficients) differing and the structural ones (network sizes, batch sizes) shared (default: 1)",
    )  # fmt: skip
    parser.add_argument(
        "--metric", choices=("rmse", "return"), default="rmse",
        help="objective: the evaluation's per-episode RMSE (minimised) or return (maximised) (default: rmse)",
    )  # fmt: skip
    parser.add_argument(
        "--alpha", type=_tail_share, default=0.5,
        help="CVaR tail share in (0, 1]: the objective is the mean of the worst alpha share of the episodes "
        "(1: the mean; default: 0.5, the paper's worst-case RMSE)",
    )  # fmt: skip
    parser.add_argument(
        "--eval-episodes", type=positive_int, default=16, help="evaluation episodes per trial (default: 16)"
    )
    parser.add_argument("--seed", type=int, default=0, help="training and evaluation seed of every trial (default: 0)")
    add_progress_argument(parser)
    return parser


def _usage_error(error: ValueError) -> UsageError:
    from scg_jax.validation import FieldError

    if isinstance(error, FieldError) and error.path in FLAGS:
        return UsageError(f"argument {FLAGS[error.path]}: {error.reason}")
    return UsageError(str(error))


def _command_line(args: argparse.Namespace) -> str:
    words = ["scg-jax", "tune", "--algo", args.algo]
    if args.config is not None:
        words += ["--config", str(args.config)]
    for item in args.set:
        words += ["--set", item]
    words += ["--trials", str(args.trials), "--out", str(args.out)]
    for flag, value, default in (("--population", args.population, 1), ("--metric", args.metric, "rmse"),
                                 ("--alpha", args.alpha, 0.5), ("--eval-episodes", args.eval_episodes, 16),
                                 ("--seed", args.seed, 0)):  # fmt: skip
        if value != default:
            words += [flag, str(value)]
    return shlex.join(words)


def run_tune(args: argparse.Namespace, console) -> int:
    from scg_algorithms.tune import TuneInterrupted, tune

    check_output(args.out, "dir")
    _, _, cfg = make_env(args)
    try:
        with command_progress(console, f"tune {args.algo}", args.progress_interval) as progress:
            result = tune(
                args.algo, cfg, args.out, trials=args.trials, population=args.population, seed=args.seed,
                metric=args.metric, alpha=args.alpha, eval_episodes=args.eval_episodes, names=FLAGS,
                progress=progress,
            )  # fmt: skip
    except TuneInterrupted as stop:
        _print_line(console, f"interrupted after {stop.finished} of {stop.trials} trials; the study in {stop.out_dir} "
                             f"continues with:\n{_command_line(args)}")  # fmt: skip
        return 130  # the shell's status for a process ended by Ctrl-C (128 + SIGINT)
    except ValueError as error:
        raise _usage_error(error) from None
    if result.best is None:
        _print_line(console, f"no trial of {result.finished} completed; see {args.out}/trials.csv")
    else:
        best = result.best
        options = ", ".join(f"{name}={value}" for name, value in best["options"].items())
        _print_line(console, f"best of {result.finished} trials: trial {best['number']}, CVaR {args.alpha:g} of the "
                             f"{args.metric} {best['value']:.6g} ({options})")  # fmt: skip
    _print_line(console, f"wrote {args.out}/{', '.join(result.files)}")
    return 0


def _print_line(console, text: str) -> None:
    # Not wrapped and no markup: a command must survive copy and paste ([...] in --set values included).
    console.print(text, soft_wrap=True, markup=False, highlight=False)
