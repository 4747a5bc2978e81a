"""``scg-jax train``: any learner of ``scg_algorithms.learners.LEARNERS`` through ``scg_algorithms.train_run``: the
arguments, the terminal output (progress, the metrics table), Ctrl-C and the exit status."""

from __future__ import annotations

import argparse
from pathlib import Path

from scg_algorithms.learners import LEARNERS, learner_spec, prior_learners
from scg_cli.common import UsageError, add_env_command, check_output, make_env, positive_int, summary_table
from scg_cli.progress import add_progress_argument, command_progress, positive_seconds
from scg_cli.scale import add_scale_arguments, is_main_process, make_mesh, start_distributed

# train_run's arguments as this command's flags: in its error messages, and for the field a FieldError names.
FLAGS = {
    "algo": "--algo",
    "out_dir": "--out",
    "resume": "--resume",
    "overwrite": "--overwrite",
    "prior_scale": "--prior-scale",
    "eval_episodes": "--eval-episodes",
}


def add_train_parser(subparsers) -> argparse.ArgumentParser:
    priors = " and ".join(prior_learners())
    parser = add_env_command(
        subparsers,
        "train",
        "train a learner (" + ", ".join(LEARNERS) + ") on a config's env; save the result, its learning curve "
        "and metrics",
        (
            "Train a learner with the options of its config section (training.ALGO for the JAX learners; "
            "controllers.gp_mpc; safety_filters.learned_cbf; defaults where absent) on the env of the config, with "
            "its randomisation and disturbances. Shows progress (a bar on a terminal, a plain line every "
            "--progress-interval seconds in a log). A JAX learner writes to --out the policy (policy.msgpack/json), "
            "checkpoint.msgpack/json (every --checkpoint-interval seconds, at the end and on Ctrl-C; continue with "
            "--resume), progress.csv and learning_curve.png; then the result is evaluated like scg-jax eval and "
            "metrics.json written. A folder that already holds a run is refused unless --resume or --overwrite is "
            "given."
        ),
    )
    parser.add_argument(
        "--algo",
        required=True,
        choices=tuple(LEARNERS),
        metavar="ALGO",
        help="learner: " + "; ".join(f"{name} ({spec.summary})" for name, spec in LEARNERS.items()),
    )
    parser.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder")
    parser.add_argument("--seed", type=int, default=0, help="PRNG seed; same seed, same result (default: 0)")
    run = parser.add_mutually_exclusive_group()
    run.add_argument(
        "--resume",
        action="store_true",
        help="continue the run in DIR from its checkpoint (same algo and settings; training.ALGO.total_env_steps "
        "may be raised to extend a finished run); bit-identical to an uninterrupted run; a DIR without a run is "
        "refused",
    )
    run.add_argument("--overwrite", action="store_true", help="replace the run already in DIR")
    parser.add_argument(
        "--checkpoint-interval",
        type=positive_seconds,
        default=60.0,
        metavar="SECONDS",
        help="save a checkpoint every this many seconds of training (default: 60; also at the end and on Ctrl-C)",
    )
    add_progress_argument(parser)
    parser.add_argument(
        "--eval-episodes", type=positive_int, default=16, help="episodes of the final evaluation (default: 16)"
    )
    parser.add_argument(
        "--prior-scale",
        type=float,
        default=1.0,
        help=f"{priors}: the prior model has every inertial parameter times this factor (default: 1)",
    )
    parser.set_defaults(_train_parser=parser)
    add_scale_arguments(parser)
    return parser


def _train_command_line(args: argparse.Namespace, **changes) -> str:
    """The ``scg-jax train`` command line of ``args`` (options left at their defaults omitted), with ``changes``
    (``dest -> value``) applied: what to type to resume an interrupted run."""
    import shlex

    parser = args._train_parser
    values = {**vars(args), **changes}
    words = ["scg-jax", "train"]
    for action in parser._actions:
        if not action.option_strings or action.dest in ("help", "_train_parser"):
            continue
        value = values.get(action.dest)
        if value is None or value == action.default:
            continue
        flag = action.option_strings[-1]
        if isinstance(action, argparse._StoreTrueAction):
            words.append(flag)
        elif isinstance(value, list) and action.dest == "offset":
            words += [flag, ",".join(f"{v:g}" for v in value)]
        elif isinstance(value, list):
            for item in value:
                words += [flag, str(item)]
        else:
            words += [flag, str(value)]
    return shlex.join(words)


def _usage_error(error: ValueError) -> UsageError:
    """A ``train_run`` error as a usage error, naming the flag of the argument it is about."""
    from scg_jax.validation import FieldError

    if isinstance(error, FieldError) and error.path in FLAGS:
        return UsageError(f"argument {FLAGS[error.path]}: {error.reason}")
    return UsageError(str(error))


def run_train(args: argparse.Namespace, console) -> int:
    from scg_algorithms.rl.curves import rmse_unit
    from scg_algorithms.rl.training import TrainingInterrupted
    from scg_algorithms.runs import EvaluationInterrupted, train_run

    check_output(args.out, "dir")  # before any work: a file in the way or an unwritable location
    spec = learner_spec(args.algo)
    if args.resume and spec.is_jax:
        _check_resumable_folder(args.out)
    if args.distributed and not spec.is_jax:
        raise UsageError(
            f"argument --distributed: {args.algo} trains in one process; --distributed is for the JAX learners"
        )
    start_distributed(args)  # before any JAX computation
    main = is_main_process()
    record = {"config_file": None if args.config is None else str(args.config), "overrides": list(args.set)}
    try:
        with command_progress(console, f"train {args.algo}", args.progress_interval, main) as progress:
            env, params, cfg = make_env(args)
            mesh = make_mesh(args, cfg) if spec.is_jax else None
            result = train_run(
                args.algo, cfg, args.out, seed=args.seed, resume=args.resume, overwrite=args.overwrite,
                checkpoint_seconds=args.checkpoint_interval, eval_episodes=args.eval_episodes,
                prior_scale=args.prior_scale, mesh=mesh, record=record, names=FLAGS, progress=progress,
            )  # fmt: skip
    except TrainingInterrupted as stop:
        if main:
            _print_line(console, _interrupted_text(args, stop))
        return 130  # the shell's status for a process ended by Ctrl-C (128 + SIGINT)
    except EvaluationInterrupted:
        use = "--filter" if spec.loads_as == "filter" else "--controller"
        _print_line(console, f"interrupted during the final evaluation; the trained {args.algo} is saved in "
                             f"{args.out} (evaluate it with scg-jax eval {use} {args.out})")  # fmt: skip
        return 130
    except KeyboardInterrupt:  # set-up; GP-MPC's rounds, the learned CBF's episodes: written whole at their end
        written = f"interrupted; nothing saved (a {args.algo} run is written when its {spec.unit}s finish)"
        _print_line(console, "interrupted before training started; nothing saved" if spec.is_jax else written)
        return 130
    except ValueError as error:
        raise _usage_error(error) from None
    if not main:  # process 0 writes metrics.json and reports
        return 0
    if _nothing_trained(result):
        _print_line(console, f"nothing to train: the run in {args.out} was already complete at iteration "
                             f"{result.training['iterations']}; it was evaluated again (raise "
                             f"training.{args.algo}.total_env_steps to extend it)")  # fmt: skip
    summary = {result.evaluation.controller: result.evaluation.summary}
    console.print(summary_table(_title(result, args), summary, rmse_unit(env, params)))
    _print_line(console, f"wrote {args.out}/{', '.join(result.files)}")
    return 0


def _check_resumable_folder(out: Path) -> None:
    """``--resume`` needs a run to continue: a folder without a JAX learner's checkpoint is refused (a typo in
    ``--out`` must not start a whole new run)."""
    from scg_algorithms.rl.training import CHECKPOINT_NAME

    if not (out / f"{CHECKPOINT_NAME}.json").is_file():
        what = "does not exist" if not out.exists() else f"holds no run to resume (no {CHECKPOINT_NAME}.json)"
        raise UsageError(
            f"argument --resume: {out} {what}; check --out, or leave out --resume to start a new run there"
        )


def _nothing_trained(result) -> bool:
    """Whether a resumed JAX run was already complete (its checkpoint at the budget): no iteration ran."""
    training = result.training
    return learner_spec(result.algo).is_jax and training.get("resumed_from_iteration") == training["iterations"]


def _interrupted_text(args: argparse.Namespace, stop) -> str:
    from scg_algorithms.rl.training import existing_run_files

    if stop.checkpoint is None:  # no checkpoint to resume: start again, replacing what the first attempt left
        again = _train_command_line(args, resume=False, overwrite=bool(existing_run_files(args.out)))
        return f"interrupted before the first iteration completed; nothing saved. Start again with:\n{again}"
    resume = _train_command_line(args, resume=True, overwrite=False)
    where = f"iteration {stop.iteration}/{stop.num_iterations} saved in {stop.checkpoint}"
    return f"interrupted: {where}\nresume with:\n{resume}"


def _print_line(console, text: str) -> None:
    # Not wrapped and no markup: a command must survive copy and paste ([...] in --set values included).
    console.print(text, soft_wrap=True, markup=False, highlight=False)


def _title(result, args: argparse.Namespace) -> str:
    training, spec = result.training, learner_spec(result.algo)
    if spec.is_jax and _nothing_trained(result):
        what = f"{result.algo}, already trained: {training['env_steps']:,} env steps, none this time"
    elif spec.is_jax and training.get("resumed_from_iteration") is not None:
        what = (f"{result.algo}, resumed at iteration {training['resumed_from_iteration']}: {training['env_steps']:,} "
                f"env steps in all, {training['total_time_s']:.1f} s this time")  # fmt: skip
    elif spec.is_jax:
        what = f"{result.algo}, {training['env_steps']:,} env steps in {training['total_time_s']:.1f} s"
    elif "rounds" in training:
        what = f"{result.algo} after {training['rounds']} rounds"
    else:
        what = f"{result.evaluation.controller} after {training['episodes']} episodes"
    return f"{result.system} {result.task} | {what} | {args.eval_episodes} evaluation episodes"
