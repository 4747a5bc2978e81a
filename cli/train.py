"""``scg-jax train``: PPO or SAC through the learner skeleton's host driver, or GP-MPC's learning loop; the
folder rules (--resume, --overwrite), progress, Ctrl-C and the final evaluation."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np

from scg_cli.common import UsageError, add_env_arguments, check_output, jsonable, make_env, positive_int, summary_table
from scg_cli.scale import add_scale_arguments, check_batch, is_main_process, make_mesh, start_distributed
from scg_jax.files import write_json

LEARNERS = ("ppo", "sac", "gp_mpc", "learned_cbf", "safe_ppo", "ppo_lagrangian", "rarl", "rap")


def _positive_seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not (np.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected a positive number of seconds, got {text!r}")
    return value


def add_train_parser(subparsers) -> argparse.ArgumentParser:
    parser = subparsers.add_parser(
        "train",
        help="train PPO or SAC on parallel copies of a config's env (or GP-MPC, or a learned CBF safety filter); save "
        "the result, learning curve and metrics",
        description=(
            "Train a JAX learner with the hyperparameters of the config's training.ALGO section (defaults where "
            "absent) on the env of the config, with its randomisation and disturbances. Shows progress (a bar on a "
            "terminal, a plain line every --progress-interval seconds in a log); writes to --out the policy "
            "(policy.msgpack/json), checkpoint.msgpack/json (every --checkpoint-interval seconds, at the end and on "
            "Ctrl-C; continue with --resume), progress.csv and learning_curve.png, then evaluates the policy like "
            "scg-jax eval and writes metrics.json. A folder that already holds a run is refused unless --resume "
            "or --overwrite is given."
        ),
    )
    add_env_arguments(parser)
    parser.add_argument("--algo", required=True, choices=LEARNERS, help="learner")
    parser.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder")
    parser.add_argument("--seed", type=int, default=0, help="PRNG seed; same seed, same policy (default: 0)")
    run = parser.add_mutually_exclusive_group()
    run.add_argument(
        "--resume",
        action="store_true",
        help="continue the run in DIR from its checkpoint (same algo and settings; training.ALGO.total_env_steps "
        "may be raised to extend a finished run); bit-identical to an uninterrupted run",
    )
    run.add_argument("--overwrite", action="store_true", help="replace the run already in DIR")
    parser.add_argument(
        "--checkpoint-interval",
        type=_positive_seconds,
        default=60.0,
        metavar="SECONDS",
        help="save a checkpoint every this many seconds of training (default: 60; also at the end and on Ctrl-C)",
    )
    parser.add_argument(
        "--progress-interval",
        type=_positive_seconds,
        default=10.0,
        metavar="SECONDS",
        help="when stdout is not a terminal, print a progress line every this many seconds (default: 10)",
    )
    parser.add_argument(
        "--eval-episodes", type=positive_int, default=16, help="episodes of the final evaluation (default: 16)"
    )
    parser.add_argument(
        "--prior-scale",
        type=float,
        default=1.0,
        help="gp_mpc, learned_cbf: the prior model has every inertial parameter times this factor (default: 1)",
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


def _check_train_folder(args: argparse.Namespace) -> None:
    """Refuse, naming the flags, a --out that holds a run without --resume/--overwrite, and a --resume of another
    algorithm's run."""
    from scg_algorithms.rl.checkpoint import load_metadata
    from scg_algorithms.rl.training import CHECKPOINT_NAME, existing_run_files

    existing = existing_run_files(args.out)
    checkpoint = args.out / f"{CHECKPOINT_NAME}.json"
    if args.resume and checkpoint.exists():
        saved_algo = load_metadata(args.out, CHECKPOINT_NAME).get("algo")
        if saved_algo != args.algo:
            raise UsageError(
                f"argument --resume: {args.out} holds a {saved_algo} run, not {args.algo}; resume it with --algo "
                f"{saved_algo}, or train {args.algo} into another --out (or replace the run with --overwrite)"
            )
    elif existing and not args.overwrite:
        what = "has no checkpoint to resume but holds" if args.resume else "already holds"
        raise UsageError(
            f"argument --out: {args.out} {what} a training run ({', '.join(existing)}); "
            + (
                "pass --overwrite to replace it"
                if args.resume
                else "pass --resume to continue it or --overwrite to replace it"
            )
        )


def _write_metrics(args: argparse.Namespace, env, cfg, evaluation, **specific) -> None:
    """``DIR/metrics.json``: the run's command, config and seed, the algorithm's own entries and the evaluation."""
    from scg_algorithms.evaluation import evaluation_record
    from scg_jax.config import dump_config

    record = {
        "command": "train",
        "algo": args.algo,
        "system": env.system.name,
        "task": env.task,
        "config_file": None if args.config is None else str(args.config),
        "config": dump_config(cfg),
        "overrides": list(args.set),
        "seed": args.seed,
        **{name: jsonable(value) for name, value in specific.items()},
        "evaluation": evaluation_record(evaluation),
    }
    write_json(args.out / "metrics.json", record)


def run_train(args: argparse.Namespace, console) -> int:
    check_output(args.out, "dir")  # before any work: a file in the way or an unwritable location
    if args.distributed and args.algo in ("gp_mpc", "learned_cbf"):
        raise UsageError(
            f"argument --distributed: {args.algo} trains in one process; --distributed is for the JAX learners"
        )
    start_distributed(args)  # before any JAX computation
    if args.algo == "gp_mpc":
        return _run_train_gp_mpc(args, console)
    if args.algo == "learned_cbf":
        return _run_train_learned_cbf(args, console)
    if args.prior_scale != 1.0:
        raise UsageError(
            f"argument --prior-scale: only gp_mpc and learned_cbf learn on a prior model; {args.algo} has none"
        )
    import jax

    from scg_algorithms.base import parse_options
    from scg_algorithms.evaluation import evaluate
    from scg_algorithms.rl.policy import algorithm_module, load_policy
    from scg_algorithms.rl.training import TrainingInterrupted, run_training
    from scg_jax.config import dump_config

    env, params, cfg = make_env(args)
    try:
        config = parse_options(
            algorithm_module(args.algo, "Config"), cfg.training.get(args.algo), f"training.{args.algo}"
        )
        learner = algorithm_module(args.algo, "make_learner")(config, env)
    except ValueError as error:
        raise UsageError(str(error)) from None
    mesh = make_mesh(args, cfg)
    distributed = jax.process_count() > 1  # a mesh over every process's devices (make_mesh checks)
    check_batch(mesh, getattr(config, "num_envs", 1), f"--set training.{args.algo}.num_envs")
    if distributed:  # the final evaluation's episodes are spread over the processes' devices too
        check_batch(mesh, args.eval_episodes, "--eval-episodes")
    _check_train_folder(args)
    key = jax.random.key(args.seed)
    train_key, eval_key = jax.random.split(key)
    try:
        summary = run_training(
            learner,
            env,
            params,
            train_key,
            args.out,
            resume=args.resume,
            overwrite=args.overwrite,
            checkpoint_seconds=args.checkpoint_interval,
            progress=True,
            progress_seconds=args.progress_interval,
            env_config=dump_config(cfg),
            mesh=mesh,
        )
    except TrainingInterrupted as stop:
        if not is_main_process():
            return 130
        resume = _train_command_line(args, resume=True, overwrite=False)
        if stop.checkpoint is None:
            message = f"interrupted before the first iteration completed; nothing saved. Start again with:\n{resume}"
        else:
            message = (
                f"interrupted: iteration {stop.iteration}/{stop.num_iterations} saved in {stop.checkpoint}\n"
                f"resume with:\n{resume}"
            )
        # Not wrapped and no markup: the command must survive copy and paste ([...] in --set values included).
        console.print(message, soft_wrap=True, markup=False, highlight=False)
        return 130  # the shell's status for a process ended by Ctrl-C (128 + SIGINT)
    except ValueError as error:  # a checkpoint that cannot be continued: names the settings that differ
        message = str(error)
        raise UsageError(f"argument --resume: {message.removeprefix('resume: ')}") from None
    policy = load_policy(args.out, env, params)  # every process: run_training returns once process 0 wrote it
    try:
        if distributed:  # a collective: every process evaluates its share of the episodes, process 0 reports
            evaluation = evaluate(env, params, policy, eval_key, args.eval_episodes, mesh=mesh)
        else:
            with console.status(f"evaluating the trained policy on {args.eval_episodes} episodes"):
                evaluation = evaluate(env, params, policy, eval_key, args.eval_episodes)
    except KeyboardInterrupt:
        console.print(
            f"interrupted during the final evaluation; the trained policy is saved in {args.out} (evaluate it with "
            f"scg-jax eval --controller {args.out})",
            soft_wrap=True,
            markup=False,
            highlight=False,
        )
        return 130
    if not is_main_process():  # process 0 writes metrics.json and reports
        return 0
    _write_metrics(
        args, env, cfg, evaluation, hyperparameters=dataclasses.asdict(config), training=summary,
        device=str(jax.devices()[0]),
    )  # fmt: skip
    title = (
        f"{env.system.name} {env.task} | {args.algo}, {summary['env_steps']:,} env steps in "
        f"{summary['total_time_s']:.1f} s | {args.eval_episodes} evaluation episodes"
    )
    console.print(summary_table(title, {args.algo: evaluation.summary}))
    console.print(f"wrote {args.out}/policy.msgpack, progress.csv, learning_curve.png, metrics.json")
    return 0


def _run_train_gp_mpc(args: argparse.Namespace, console) -> int:
    """``train --algo gp_mpc``: the learning loop of ``scg_algorithms.gp_mpc.controller.learn`` with the config's
    ``controllers.gp_mpc`` options, then a final evaluation; writes gp_mpc.json/npz, the learning curve and
    metrics.json."""
    import jax

    from scg_algorithms.base import parse_options
    from scg_algorithms.evaluation import evaluate
    from scg_algorithms.gp_mpc.controller import PATH, Options, learn
    from scg_algorithms.gp_mpc.run import RUN_NAME, save_run, write_learning_curve
    from scg_algorithms.rl.training import existing_run_files, rmse_label
    from scg_jax.config import dump_config
    from scg_jax.env import prior_params

    env, params, cfg = make_env(args)
    if not (np.isfinite(args.prior_scale) and args.prior_scale > 0):
        raise UsageError(f"argument --prior-scale: must be a positive number, got {args.prior_scale!r}")
    options = {**dict(cfg.controllers.get("gp_mpc") or {}), "seed": args.seed}
    try:
        opts = parse_options(Options, options, PATH)
    except ValueError as error:
        raise UsageError(str(error)) from None
    if opts.rounds < 1:
        raise UsageError(f"{PATH}.rounds: train needs at least one round, got {opts.rounds}")
    if args.resume:
        raise UsageError("argument --resume: a gp_mpc run is not resumable (each round refits the GP); use --overwrite")
    others = existing_run_files(args.out)
    mine = [
        name for name in (f"{RUN_NAME}.json", f"{RUN_NAME}.npz", "learning_curve.csv") if (args.out / name).exists()
    ]
    if (others or mine) and not args.overwrite:
        what = f"a training run of another algorithm ({', '.join(others)})" if others and not mine else "a run"
        raise UsageError(f"argument --out: {args.out} already holds {what}; pass --overwrite to replace it")
    prior = params if args.prior_scale == 1.0 else prior_params(env, params, args.prior_scale)
    console.print(
        f"gp_mpc on the {env.system.name} ({env.task}), prior scale {args.prior_scale:g}: {opts.rounds} rounds of "
        f"{opts.train_episodes} episodes, each evaluated on {opts.eval_episodes}",
        highlight=False,
    )

    def report(entry):
        console.print(
            f"round {entry['round']}: {entry['data_seconds']:.1f} s of data, RMSE {entry['rmse']:.4f} "
            f"(std {entry['rmse_std']:.4f}), failure rate {entry['failure_rate']:.2f}, "
            f"fit {entry['fit_s']:.1f} s, evaluation {entry['eval_s']:.1f} s",
            highlight=False,
        )

    try:
        result = learn(env, params, prior, opts, progress=report)
    except KeyboardInterrupt:
        console.print("interrupted; nothing saved (a gp_mpc run is written when its rounds finish)", markup=False)
        return 130
    extra = {"config": dump_config(cfg), "overrides": list(args.set)}
    save_run(args.out, result, opts, system=env.system.name, prior_scale=args.prior_scale, extra=extra)
    write_learning_curve(args.out, result.history, rmse_label(env, params))
    evaluation = evaluate(env, params, result.controller, jax.random.key(args.seed + 1), args.eval_episodes)
    _write_metrics(
        args, env, cfg, evaluation, prior_scale=args.prior_scale, options=dataclasses.asdict(opts),
        history=result.history,
    )  # fmt: skip
    title = f"{env.system.name} {env.task} | gp_mpc after {opts.rounds} rounds | {args.eval_episodes} episodes"
    console.print(summary_table(title, {"gp_mpc": evaluation.summary}))
    console.print(f"wrote {args.out}/{RUN_NAME}.json, {RUN_NAME}.npz, learning_curve.csv/png, metrics.json")
    return 0


def _run_train_learned_cbf(args: argparse.Namespace, console) -> int:
    """``train --algo learned_cbf``: the blending episodes and updates of
    ``scg_algorithms.safety_filters.learned_cbf.train_learned_cbf`` with the config's ``safety_filters.learned_cbf``
    options on a prior of ``--prior-scale``; writes learned_cbf.json/msgpack, progress.csv, learning_curve.png and
    metrics.json (the filter around random inputs, evaluated like scg-jax eval)."""
    import jax

    from scg_algorithms.base import parse_options
    from scg_algorithms.evaluation import evaluate
    from scg_algorithms.rl.training import existing_run_files
    from scg_algorithms.safety_filters import filtered
    from scg_algorithms.safety_filters.learned_cbf import PATH, RUN_NAME, Options, save_run, train_learned_cbf
    from scg_algorithms.safety_filters.uncertified import random_input
    from scg_jax.config import dump_config
    from scg_jax.env import prior_params

    env, params, cfg = make_env(args)
    if not (np.isfinite(args.prior_scale) and args.prior_scale > 0):
        raise UsageError(f"argument --prior-scale: must be a positive number, got {args.prior_scale!r}")
    if args.resume:
        raise UsageError("argument --resume: a learned_cbf run is not resumable; use --overwrite")
    try:
        opts = parse_options(Options, {**dict(cfg.safety_filters.get("learned_cbf") or {}), "seed": args.seed}, PATH)
        prior = params if args.prior_scale == 1.0 else prior_params(env, params, args.prior_scale)
    except ValueError as error:
        raise UsageError(str(error)) from None
    others = existing_run_files(args.out)
    mine = [name for name in (f"{RUN_NAME}.json", f"{RUN_NAME}.msgpack") if (args.out / name).exists()]
    if (others or mine) and not args.overwrite:
        raise UsageError(f"argument --out: {args.out} already holds a run; pass --overwrite to replace it")
    console.print(
        f"learned_cbf on the {env.system.name}, prior scale {args.prior_scale:g}: {opts.num_episodes} blending "
        f"episodes of {opts.num_copies} copies x {env.num_steps} steps",
        highlight=False,
    )

    def report(row):
        console.print(
            f"episode {row['episode']}: {row['data_seconds']:.0f} s of data, violating steps "
            f"{100 * row['violation_fraction']:.3f} %, interventions {100 * row['intervention_fraction']:.1f} %",
            highlight=False,
        )

    try:
        result = train_learned_cbf(env, params, prior, opts, progress=report)
    except KeyboardInterrupt:
        console.print(
            "interrupted; nothing saved (a learned_cbf run is written when its episodes finish)", markup=False
        )
        return 130
    except ValueError as error:
        raise UsageError(str(error)) from None
    extra = {"config": dump_config(cfg), "overrides": list(args.set)}
    save_run(args.out, result, system=env.system.name, prior_scale=args.prior_scale, extra=extra)
    controller = filtered(random_input(env, params), result.filter, env)
    evaluation = evaluate(env, params, controller, jax.random.key(args.seed + 1), args.eval_episodes)
    _write_metrics(
        args, env, cfg, evaluation, prior_scale=args.prior_scale, options=dataclasses.asdict(opts),
        history=result.history,
    )  # fmt: skip
    title = f"{env.system.name} {env.task} | random inputs + learned_cbf | {args.eval_episodes} episodes"
    console.print(summary_table(title, {"random_input+learned_cbf": evaluation.summary}))
    console.print(
        f"wrote {args.out}/{RUN_NAME}.json, {RUN_NAME}.msgpack, progress.csv, learning_curve.png, metrics.json"
    )
    return 0
