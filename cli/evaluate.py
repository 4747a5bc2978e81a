"""``scg-jax eval`` and ``compare``: controllers (registered names, trained policy folders, learned GP-MPC
folders) on the same episodes through the evaluation harness; JSON, trajectories (.npz) and a plot."""

from __future__ import annotations

import argparse
import difflib
from pathlib import Path

import numpy as np

from scg_cli.common import (
    OUT_CHECKED,
    UsageError,
    add_env_command,
    check_output,
    env_arrays,
    jsonable,
    make_env,
    positive_int,
    summary_table,
)
from scg_cli.progress import add_progress_argument, command_progress
from scg_cli.scale import add_scale_arguments, check_batch, is_main_process, make_mesh, start_distributed
from scg_jax.files import write_atomic, write_json


def _add_controller_arguments(parser: argparse.ArgumentParser) -> None:
    run = parser.add_argument_group("evaluation")
    run.add_argument(
        "--prior-scale",
        type=float,
        default=1.0,
        help="the controller's model has every inertial parameter times this factor (default: 1, the true plant)",
    )
    run.add_argument(
        "--filter",
        metavar="NAME|DIR",
        help="certify every input with a safety filter: a registered name (cbf, learned_cbf, ...; options from the "
        "config's safety_filters.NAME section) or the folder of a learned CBF written by scg-jax train",
    )
    run.add_argument(
        "--filter-prior-scale",
        type=float,
        help="the filter's model has every inertial parameter times this factor (default: --prior-scale)",
    )
    run.add_argument("--episodes", type=positive_int, default=16, help="episodes, run in parallel (default: 16)")
    run.add_argument("--seed", type=int, default=0, help="PRNG seed (default: 0)")
    add_progress_argument(run)


def add_eval_parser(subparsers) -> argparse.ArgumentParser:
    from scg_algorithms import CONTROLLERS

    parser = add_env_command(
        subparsers,
        "eval",
        "evaluate a controller or a trained policy on N episodes and save metrics, data and a plot",
        (
            "Evaluate one controller on --episodes episodes with the paper's metrics (RMSE, its std, worst-case "
            "RMSE as CVaR at 0.5, failure rate, steps in violation, return, length, compute time per step). The "
            "controller's options come from the config's controllers.NAME section. Writes --out (JSON), and the "
            "trajectories (.npz) and a plot (.png) next to it."
        ),
    )
    parser.add_argument(
        "--controller",
        required=True,
        metavar="NAME|DIR",
        help=f"controller name ({', '.join(CONTROLLERS)}) or the folder of a policy written by scg-jax train",
    )
    _add_controller_arguments(parser)
    parser.add_argument(
        "--out", type=Path, required=True, metavar="FILE.json", help=f"metrics JSON to write{OUT_CHECKED}"
    )
    add_scale_arguments(parser)
    return parser


def add_compare_parser(subparsers) -> argparse.ArgumentParser:
    from scg_algorithms import CONTROLLERS

    parser = add_env_command(
        subparsers,
        "compare",
        "evaluate several controllers on one config and print them side by side",
        "Evaluate each controller as scg-jax eval does, on the same episodes (same seed).",
    )
    parser.add_argument(
        "--controllers",
        required=True,
        metavar="A,B,...",
        help=f"comma-separated controller names ({', '.join(CONTROLLERS)}) and/or policy folders",
    )
    _add_controller_arguments(parser)
    parser.add_argument(
        "--out", type=Path, metavar="FILE.json", help=f"write every controller's metrics here{OUT_CHECKED}"
    )
    return parser


def _build_controller(spec: str, env, params, cfg, prior_scale: float, flag: str = "--controller"):
    """A controller from a registered name (options from ``cfg.controllers``) or a trained policy's folder; errors
    name ``flag`` (``--controllers`` for compare)."""
    from scg_algorithms import CONTROLLERS, make_controller
    from scg_jax.env import prior_params

    if not (np.isfinite(prior_scale) and prior_scale > 0):
        raise UsageError(f"argument --prior-scale: must be a positive number, got {prior_scale!r}")
    if spec in CONTROLLERS:
        prior = params if prior_scale == 1.0 else prior_params(env, params, prior_scale)
        try:
            return make_controller(spec, env, prior, cfg.controllers.get(spec))
        except ValueError as error:
            raise UsageError(str(error)) from None
    path = Path(spec)
    if path.is_dir() and _is_gp_mpc_run(path):
        return _load_gp_mpc_run(path, env, params, cfg, prior_scale, flag)
    if path.is_dir():
        from scg_algorithms.rl.policy import load_policy

        if prior_scale != 1.0:
            raise UsageError("argument --prior-scale: a trained policy has no model to scale; leave it at 1")
        try:
            return load_policy(path, env, params)
        except (ValueError, OSError) as error:
            raise UsageError(f"argument {flag}: {error}") from None
    close = difflib.get_close_matches(spec, list(CONTROLLERS), n=1)
    raise UsageError(
        f"argument {flag}: {spec!r} is neither a controller name ({', '.join(CONTROLLERS)}) nor a policy "
        "folder written by scg-jax train" + (f" (did you mean {close[0]!r}?)" if close else "")
    )


def _with_filter(controller, env, params, cfg, args):
    """``controller`` certified by the ``--filter`` (unchanged without one)."""
    if args.filter is None:
        return controller
    from scg_algorithms.safety_filters import FILTERS, filtered, is_filter_folder, load_filter, make_filter
    from scg_jax.env import prior_params

    scale = args.prior_scale if args.filter_prior_scale is None else args.filter_prior_scale
    if not (np.isfinite(scale) and scale > 0):
        raise UsageError(f"argument --filter-prior-scale: must be a positive number, got {scale!r}")
    try:
        if args.filter in FILTERS:
            prior = params if scale == 1.0 else prior_params(env, params, scale)
            safety_filter = make_filter(args.filter, env, prior, cfg.safety_filters.get(args.filter))
        elif is_filter_folder(args.filter):
            if args.filter_prior_scale is not None:
                raise UsageError("argument --filter-prior-scale: a trained filter keeps the prior it learned on")
            safety_filter = load_filter(args.filter, env, params)
        else:
            raise UsageError(
                f"argument --filter: {args.filter!r} is neither a filter name ({', '.join(FILTERS)}) nor a folder "
                "written by scg-jax train --algo learned_cbf"
            )
        return filtered(controller, safety_filter, env)
    except (ValueError, OSError) as error:
        raise UsageError(f"argument --filter: {error}") from None


def _is_gp_mpc_run(path: Path) -> bool:
    from scg_algorithms.gp_mpc.run import is_run

    return is_run(path)


def _load_gp_mpc_run(path: Path, env, params, cfg, prior_scale: float, flag: str):
    """The GP-MPC learned in ``path``, on the prior it was learned with (``--prior-scale`` must agree or stay 1)."""
    import json

    from scg_algorithms.gp_mpc.run import RUN_NAME, load_run
    from scg_jax.env import prior_params

    saved_scale = float(json.loads((path / f"{RUN_NAME}.json").read_text())["prior_scale"])
    if prior_scale not in (1.0, saved_scale):
        raise UsageError(
            f"argument --prior-scale: {path} learned its GP on a prior of scale {saved_scale:g}; leave --prior-scale "
            f"at 1 or give {saved_scale:g}"
        )
    prior = params if saved_scale == 1.0 else prior_params(env, params, saved_scale)
    try:
        return load_run(path, env, prior, cfg.controllers.get("gp_mpc"))
    except (ValueError, OSError) as error:
        raise UsageError(f"argument {flag}: {error}") from None


def _evaluate(controller, env, params, args, progress, mesh=None):
    """``evaluate`` with ``--seed`` and ``--episodes``, reporting to ``progress``."""
    import jax

    from scg_algorithms.evaluation import evaluate

    return evaluate(env, params, controller, jax.random.key(args.seed), args.episodes, progress=progress, mesh=mesh)


def _evaluation_extra(env, cfg, args, controller) -> dict:
    from scg_jax.config import dump_config

    return {
        "system": env.system.name,
        "task": env.task,
        "config_file": None if args.config is None else str(args.config),
        "config": dump_config(cfg),
        "overrides": list(args.set),
        "prior_scale": args.prior_scale,
        "filter": args.filter,
        "seed": args.seed,
        "num_steps": env.num_steps,
        "controller_info": jsonable(getattr(controller, "info", {})),
    }


def run_eval(args: argparse.Namespace, console) -> int:
    from scg_algorithms.evaluation import evaluation_record
    from scg_algorithms.progress import Task, running
    from scg_algorithms.rl.curves import rmse_unit
    from scg_jax.plotting import plot_rollout

    if args.out.suffix != ".json":
        raise UsageError(f"argument --out: expected a .json file name, got {str(args.out)!r}")
    start_distributed(args)  # before any JAX computation
    check_output(args.out, "file")
    main = is_main_process()
    with command_progress(console, f"eval {args.controller}", args.progress_interval, main) as progress:
        env, params, cfg = make_env(args)
        mesh = make_mesh(args, cfg)
        check_batch(mesh, args.episodes, "--episodes")
        controller = _with_filter(
            _build_controller(args.controller, env, params, cfg, args.prior_scale), env, params, cfg, args
        )
        evaluation = _evaluate(controller, env, params, args, progress, mesh)
        if not main:  # every process holds every copy's metrics; process 0 writes them
            return 0
        npz_path, png_path = args.out.with_suffix(".npz"), args.out.with_suffix(".png")
        data = {
            **env_arrays(env, params),
            **{name: value for name, value in evaluation.trajectory.items() if name not in ("x", "x_ref")},
            "x": evaluation.trajectory["x"][:-1],
            "x_final": evaluation.trajectory["x"][-1],
            # The plot draws one reference; copies share it unless the params were a sweep.
            "x_ref": evaluation.trajectory["x_ref"][:, 0],
            "controller": np.asarray(controller.name),
        }
        with running(progress, Task(f"writing {args.out} and its .npz and .png")):
            write_atomic(npz_path, lambda file: np.savez_compressed(file, **data))
            record = evaluation_record(evaluation, _evaluation_extra(env, cfg, args, controller))
            write_json(args.out, record)
            plot_rollout(npz_path, png_path)
    title = f"{env.system.name} {env.task} | {controller.name} | {args.episodes} episodes x {env.num_steps} steps"
    console.print(summary_table(title, {controller.name: evaluation.summary}, rmse_unit(env, params)))
    console.print(f"wrote {args.out}, {npz_path}, {png_path}")
    return 0


def run_compare(args: argparse.Namespace, console) -> int:
    from scg_algorithms.evaluation import evaluation_record
    from scg_algorithms.rl.curves import rmse_unit

    specs = [item.strip() for item in args.controllers.split(",") if item.strip()]
    if not specs:
        raise UsageError("argument --controllers: expected at least one controller name or policy folder")
    if len(set(specs)) != len(specs):
        raise UsageError(f"argument --controllers: a controller is listed twice: {args.controllers}")
    if args.out is not None and args.out.suffix != ".json":
        raise UsageError(f"argument --out: expected a .json file name, got {str(args.out)!r}")
    if args.out is not None:
        check_output(args.out, "file")
    with command_progress(console, f"compare {','.join(specs)}", args.progress_interval) as progress:
        env, params, cfg = make_env(args)
        controllers = [_build_controller(spec, env, params, cfg, args.prior_scale, "--controllers") for spec in specs]
        labels = [
            c.name if spec == c.name else f"{c.name} ({Path(spec).name})"
            for spec, c in zip(specs, controllers, strict=True)
        ]
        if args.filter is not None:
            suffix = f"+{Path(args.filter).name if Path(args.filter).is_dir() else args.filter}"
            labels = [label + suffix for label in labels]
            controllers = [_with_filter(c, env, params, cfg, args) for c in controllers]
        records, summaries = {}, {}
        for label, controller in zip(labels, controllers, strict=True):
            evaluation = _evaluate(controller, env, params, args, progress)
            summaries[label] = evaluation.summary
            info = {"controller_info": jsonable(getattr(controller, "info", {}))}
            records[label] = evaluation_record(evaluation, info)
        if args.out is not None:
            extra = _evaluation_extra(env, cfg, args, controllers[0])
            extra.pop("controller_info")
            write_json(args.out, {**extra, "controllers": records})
    title = f"{env.system.name} {env.task} | {args.episodes} episodes x {env.num_steps} steps | seed {args.seed}"
    console.print(summary_table(title, summaries, rmse_unit(env, params)))
    if args.out is not None:
        console.print(f"wrote {args.out}")
    return 0
