"""The ``scg-jax`` command line.

Subcommands (each a ``_add_<name>_parser`` / ``_run_<name>`` pair registered in ``_SUBCOMMANDS``):

- ``rollout``: one episode of ``--num-envs`` parallel copies under a simple policy; prints a metrics table and
  writes ``rollout.npz``, ``metrics.json`` and ``rollout.png`` to ``--out``.
- ``eval``: one controller (a registered name or a trained policy's folder) on ``--episodes`` episodes with the
  paper's metrics; writes the JSON, the trajectories (.npz) and a plot (.png).
- ``compare``: several controllers on the same episodes, side by side.
- ``train``: PPO or SAC with the config's ``training.ALGO`` hyperparameters; writes the policy, checkpoints, the
  learning curve and ``metrics.json`` (training summary and an evaluation of the policy).

``main(argv) -> int`` never raises ``SystemExit`` itself: it returns 0 on success and 2 on bad input (argparse's
convention), so it can be called from tests and from the console script alike.
"""

from __future__ import annotations

import argparse
import dataclasses
import re
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from scg_jax.files import write_atomic, write_json
from scg_jax.integrators import INTEGRATORS
from scg_jax.systems import SYSTEMS
from scg_jax.trajectories import SHAPES

TASKS = ("stabilization", "tracking")
POLICIES = ("zero", "random", "linear")
_AXES = "xyz"

# The env options a flag sets: option (its path under env) -> (flag, argparse dest). An error at that path names the
# flag, the one a user would change (e.g. --physics-freq when 1000 Hz is no multiple of --ctrl-freq 15).
_FLAG_OF_OPTION = {
    "system": ("--system", "system"),
    "task": ("--task", "task"),
    "ctrl_freq": ("--ctrl-freq", "ctrl_freq"),
    "physics_freq": ("--physics-freq", "physics_freq"),
    "episode_len_sec": ("--episode-len", "episode_len"),
    "integrator": ("--integrator", "integrator"),
    "trajectory.shape": ("--shape", "shape"),
    "trajectory.num_cycles": ("--num-cycles", "num_cycles"),
    "trajectory.plane": ("--plane", "plane"),
    "trajectory.offset": ("--offset", "offset"),
    "trajectory.scale": ("--scale", "scale"),
}


_OUT_CHECKED = "; missing folders are created, and a location that cannot be written is refused before any work"


class _UsageError(Exception):
    """Bad command-line input found after parsing; reported through the subcommand's ``parser.error``."""


def _float_list(text: str) -> list[float]:
    """``"a,b,c"`` -> floats; an ``argparse`` type, so a malformed number is reported with the option's name."""
    try:
        values = [float(item) for item in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None
    if not all(np.isfinite(values)):
        raise argparse.ArgumentTypeError(f"values must be finite, got {text!r}")
    return values


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return value


# ----------------------------------------------------------------------------------------------- shared options
def _add_env_arguments(parser: argparse.ArgumentParser) -> None:
    """Options that build an environment; shared by every subcommand that makes one.

    The environment is a config: ``--config FILE`` (or just ``--system``), then the flags given explicitly, then
    every ``--set env.KEY=VALUE`` in order, as overrides of that config.
    """
    env = parser.add_argument_group("environment (a config file, flags, and --set overrides applied in that order)")
    env.add_argument("--config", type=Path, metavar="FILE", help="YAML config file (see configs/)")
    env.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config field by its dotted path, e.g. env.ctrl_freq=15 (repeatable; YAML values)",
    )
    env.add_argument("--system", choices=tuple(SYSTEMS), help="system to simulate (required without --config)")
    env.add_argument("--task", choices=TASKS, help="task (default: stabilization)")
    env.add_argument("--ctrl-freq", type=_positive_int, help="control frequency, Hz (default: 50)")
    env.add_argument("--physics-freq", type=_positive_int, help="physics frequency, Hz, a multiple of --ctrl-freq")
    env.add_argument("--episode-len", type=float, help="episode length, s (default: 5)")
    env.add_argument("--integrator", choices=INTEGRATORS, help="integrator (default: rk4)")
    traj = parser.add_argument_group("tracking reference (--task tracking only; defaults are per system)")
    traj.add_argument("--shape", choices=SHAPES, help="reference shape (default: circle)")
    traj.add_argument("--num-cycles", type=float, help="cycles per episode (default: 1)")
    traj.add_argument("--plane", help="two distinct letters of x, y, z, e.g. xz")
    traj.add_argument("--scale", type=float, help="shape size, m")
    traj.add_argument("--offset", type=_float_list, metavar="A,B", help="in-plane offset, m")


def _make_env(args: argparse.Namespace):
    """``(env, params, config)`` from ``--config``/``--system``, the explicit flags (set as typed values, no YAML
    text) and ``--set``; config and ``make`` errors become ``_UsageError`` naming the flag or the dotted path."""
    from scg_jax.config import load_config, make_from_config
    from scg_jax.validation import FieldError

    if args.config is None and args.system is None:
        raise _UsageError("argument --system: required unless --config is given")
    if args.offset is not None and len(args.offset) != 2:
        raise _UsageError(
            f"argument --offset: expected 2 comma-separated values A,B (m), got {len(args.offset)}: "
            f"{','.join(map(str, args.offset))}"
        )
    flags = {f"env.{option}": getattr(args, dest) for option, (_, dest) in _FLAG_OF_OPTION.items()}
    source = args.config if args.config is not None else {"env": {"system": args.system}}
    try:
        cfg = load_config(source, list(args.set), values=flags)
        env, params = make_from_config(cfg)
        return env, params, cfg
    except FieldError as error:
        option = error.path.removeprefix("env.")
        flag = f"argument {_FLAG_OF_OPTION[option][0]}: " if option in _FLAG_OF_OPTION else ""
        raise _UsageError(f"{flag}{error}") from None
    except (ValueError, OSError) as error:  # e.g. a config file that cannot be read
        raise _UsageError(str(error)) from None


def _output(path: Path, kind: str) -> Path:
    """``--out`` checked before any work (``check_output_dir`` / ``check_output_file``), as a usage error."""
    from scg_jax.files import check_output_dir, check_output_file

    try:
        return check_output_dir(path) if kind == "dir" else check_output_file(path)
    except ValueError as error:
        raise _UsageError(f"argument --out: {error}") from None


def _plane_indices(env) -> tuple[str, tuple[int, int]] | None:
    """The plane a quadrotor's path is drawn in and the state indices of its two position coordinates."""
    if env.system.name not in ("quadrotor_2d", "quadrotor_3d"):
        return None
    plane = env.trajectory_plane or env.system.default_plane
    position_index = {axis: pos for axis, pos, _ in env.system.tracking_axes}
    axes = [_AXES.index(letter) for letter in plane]
    if not all(axis in position_index for axis in axes):
        # e.g. quadrotor_2d asked for a plane with y: it has no y position, so draw its own plane instead.
        plane = env.system.default_plane
        axes = [_AXES.index(letter) for letter in plane]
    return plane, (position_index[axes[0]], position_index[axes[1]])


# ----------------------------------------------------------------------------------------------- output
# ----------------------------------------------------------------------------------------------- rollout
def _add_rollout_parser(subparsers) -> argparse.ArgumentParser:
    parser = subparsers.add_parser(
        "rollout",
        help="roll out a simple policy in parallel copies and save data, metrics and a plot",
        description=(
            "Run one episode of --num-envs parallel copies under a simple policy acting on the physical input "
            "(N): zero holds the reference input (hover thrust, 0 N for the cart-pole), random draws uniformly "
            "within the actuator limits, linear applies u = u_ref - K (x - x_ref)."
        ),
    )
    _add_env_arguments(parser)
    run = parser.add_argument_group("rollout")
    run.add_argument("--policy", default="linear", choices=POLICIES, help="policy (default: %(default)s)")
    run.add_argument(
        "--gain",
        type=_float_list,
        metavar="K11,K12,...",
        help=(
            "gain K of the linear policy u = u_ref - K (x - x_ref) (note the minus sign), nu x nx values, row-major; "
            "e.g. --gain -2.8,-5.2,-43.9,-11.6, about the cart-pole's default (default: LQR about the goal or the "
            "first reference point; the gain used is printed and saved in metrics.json)"
        ),
    )
    run.add_argument("--num-envs", type=_positive_int, default=64, help="parallel copies (default: 64)")
    run.add_argument("--seed", type=int, default=0, help="PRNG seed (default: 0)")
    run.add_argument(
        "--out",
        type=Path,
        help=f"output folder, created if missing (default: results/rollout/SYSTEM-TASK-POLICY-seedSEED){_OUT_CHECKED}",
    )
    return parser


def _make_policy(env, params, args) -> tuple[Callable, np.ndarray | None]:
    """The policy ``policy(obs, state, params, key) -> action`` and the gain K (nu, nx) it uses, if linear."""
    import jax
    import jax.numpy as jnp

    dtype = params.goal.dtype
    gain = None
    if args.gain is not None and args.policy != "linear":
        raise _UsageError(f"argument --gain: only used with --policy linear, not --policy {args.policy}")
    if args.policy == "linear":
        if args.gain is not None:
            if len(args.gain) != env.nu * env.nx:
                raise _UsageError(
                    f"argument --gain: {env.system.name} needs nu x nx = {env.nu} x {env.nx} = {env.nu * env.nx} "
                    f"comma-separated values (row-major), got {len(args.gain)}"
                )
            gain = np.asarray(args.gain, dtype=np.float64).reshape(env.nu, env.nx)
        else:
            from scg_algorithms.lqr import lqr_gain_about

            x0, u0 = jax.jit(env.reference_at)(0, params)
            gain = lqr_gain_about(env, params, np.asarray(x0), np.asarray(u0))
        k = jnp.asarray(gain, dtype=dtype)

    def policy(obs, state, p, key):
        x_ref, u_ref = env.reference_at(state.step, p)
        if args.policy == "zero":
            u = u_ref
        elif args.policy == "random":
            low, high = env.input_bounds(state.physics)
            u = jax.random.uniform(key, (env.nu,), dtype=dtype, minval=low.astype(dtype), maxval=high.astype(dtype))
        else:
            u = u_ref - k @ (state.x - x_ref)
        # The CLI's envs use physical actions, where this is the identity; it keeps the policy right otherwise.
        return env.input_to_action(u, p)

    return policy, gain


def _run_rollout(args: argparse.Namespace, console) -> int:
    import jax
    from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

    from scg_jax.config import dump_config
    from scg_jax.metrics import summarize, trajectory_metrics
    from scg_jax.plotting import plot_rollout
    from scg_jax.rollout import make_rollout

    env, params, cfg = _make_env(args)
    out = args.out or Path("results", "rollout", f"{env.system.name}-{env.task}-{args.policy}-seed{args.seed}")
    _output(out, "dir")

    with Progress(SpinnerColumn(), TextColumn("{task.description}"), TimeElapsedColumn(), console=console) as bar:
        stage = bar.add_task(f"linearising {env.system.name} and building the policy", total=1)
        policy, gain = _make_policy(env, params, args)
        bar.update(stage, completed=1)

        stage = bar.add_task(f"compiling {args.num_envs} copies x {env.num_steps} steps", total=1)
        key = jax.random.key(args.seed)
        start = time.perf_counter()
        rollout = make_rollout(env, policy, args.num_envs, auto_reset=False).lower(key, params).compile()
        compile_s = time.perf_counter() - start
        bar.update(stage, completed=1)

        stage = bar.add_task("running", total=1)
        start = time.perf_counter()
        traj = jax.block_until_ready(rollout(key, params))
        run_s = time.perf_counter() - start
        bar.update(stage, completed=1)

        stage = bar.add_task(f"writing {out}", total=1)
        per_copy = trajectory_metrics(traj)
        summary = summarize(per_copy)
        steps_per_s = args.num_envs * env.num_steps / run_s
        data = _rollout_data(env, params, traj)
        data["config"] = np.asarray(dump_config(cfg))  # the resolved config: rebuilds this exact env
        out.mkdir(parents=True, exist_ok=True)
        write_atomic(out / "rollout.npz", lambda file: np.savez_compressed(file, **data))
        record = {
            "command": "rollout",
            "system": env.system.name,
            "task": env.task,
            "config_file": None if args.config is None else str(args.config),
            "config": dump_config(cfg),
            "overrides": list(args.set),
            "policy": args.policy,
            "num_envs": args.num_envs,
            "num_steps": env.num_steps,
            "seed": args.seed,
            "env": {
                "ctrl_freq": env.ctrl_freq,
                "physics_freq": env.physics_freq,
                "episode_len_sec": env.episode_len_sec,
                "integrator": env.integrator,
                "trajectory_shape": env.trajectory_shape,
                "trajectory_plane": env.trajectory_plane,
            },
            "gain": None if gain is None else gain.tolist(),
            "summary": summary,
            "timing": {"compile_s": compile_s, "run_s": run_s, "steps_per_s": steps_per_s},
            "device": str(jax.devices()[0]),
            "per_copy": {name: np.asarray(values).tolist() for name, values in per_copy.items()},
        }
        write_json(out / "metrics.json", record)
        # The plot reads the saved file, not the in-memory rollout, so it shows exactly what was kept.
        plot_rollout(out / "rollout.npz", out / "rollout.png")
        bar.update(stage, completed=1)

    console.print(_metrics_table(args, env, summary, compile_s, run_s, steps_per_s, gain))
    console.print(f"wrote {out / 'rollout.npz'}, {out / 'metrics.json'}, {out / 'rollout.png'}")
    return 0


def _rollout_data(env, params, traj) -> dict[str, np.ndarray]:
    import jax

    x_ref, u_ref = jax.jit(env.reference)(params)
    info = ("u", "constraint_values", "mse", "out_of_bounds", "nonfinite")
    return {
        **_env_arrays(env, params),
        "x": np.asarray(traj.x),
        "x_final": np.asarray(traj.final_state.x),
        **{name: np.asarray(getattr(traj, name)) for name in ("action", "reward", "cost", "terminated", "truncated")},
        **{name: np.asarray(traj.info[name]) for name in info},
        "x_ref": np.asarray(x_ref),
        "u_ref": np.asarray(u_ref),
    }


def _env_arrays(env, params) -> dict[str, np.ndarray]:
    """What ``plot_rollout`` needs besides the trajectory: times, names, the plane of a quadrotor's path and the
    constraint boxes."""
    from scg_jax.constraints import box_bounds

    data = {
        "t": env.dt * np.arange(env.num_steps, dtype=np.float64),
        "dt": np.float64(env.dt),
        "state_names": np.asarray(env.system.state_names),
        "input_names": np.asarray(env.system.input_names),
        "system": np.asarray(env.system.name),
        "task": np.asarray(env.task),
    }
    plane = _plane_indices(env)
    if plane is not None:
        data["plane"] = np.asarray(plane[0])
        data["plane_indices"] = np.asarray(plane[1], dtype=np.int64)
    x_low, x_high, u_low, u_high = box_bounds(env.constraint_specs, params.constraints, env.nx, env.nu)
    data.update(x_low=x_low, x_high=x_high, u_low=u_low, u_high=u_high)
    return data


def _metrics_table(args, env, summary: dict, compile_s: float, run_s: float, steps_per_s: float, gain=None):
    from rich.table import Table

    title = f"{env.system.name} {env.task} | policy {args.policy} | {args.num_envs} copies x {env.num_steps} steps"
    table = Table(title=title, min_width=len(title) + 4)
    table.add_column("metric")
    table.add_column("value", justify="right")
    table.add_row("rmse (m)", f"{summary['rmse_mean']:.4f} ± {summary['rmse_std']:.4f}")
    table.add_row("return", f"{summary['return_mean']:.3f} ± {summary['return_std']:.3f}")
    table.add_row("length (steps)", f"{summary['length_mean']:.1f} / {env.num_steps}")
    table.add_row("failure rate", f"{summary['failure_rate']:.3f}")
    table.add_row("steps in violation", f"{summary['violation_steps_mean']:.1f} ± {summary['violation_steps_std']:.1f}")
    table.add_row("compile time (s)", f"{compile_s:.2f}")
    table.add_row("run wall time (s)", f"{run_s:.4f}")
    table.add_row("steps/s", f"{steps_per_s:,.0f}")
    if gain is not None:  # printed as --gain takes it, so a user can start from it
        table.add_row("gain K, u = u_ref - K (x - x_ref)", ",".join(f"{k:.4g}" for k in np.ravel(gain)))
    return table


# ----------------------------------------------------------------------------------------------- eval, compare
def _add_controller_arguments(parser: argparse.ArgumentParser) -> None:
    run = parser.add_argument_group("evaluation")
    run.add_argument(
        "--prior-scale",
        type=float,
        default=1.0,
        help="the controller's model has every inertial parameter times this factor (default: 1, the true plant)",
    )
    run.add_argument("--episodes", type=_positive_int, default=16, help="episodes, run in parallel (default: 16)")
    run.add_argument("--seed", type=int, default=0, help="PRNG seed (default: 0)")


def _add_eval_parser(subparsers) -> argparse.ArgumentParser:
    from scg_algorithms import CONTROLLERS

    parser = subparsers.add_parser(
        "eval",
        help="evaluate a controller or a trained policy on N episodes and save metrics, data and a plot",
        description=(
            "Evaluate one controller on --episodes episodes with the paper's metrics (RMSE, its std, worst-case "
            "RMSE as CVaR at 0.5, failure rate, steps in violation, return, length, compute time per step). The "
            "controller's options come from the config's controllers.NAME section. Writes --out (JSON), and the "
            "trajectories (.npz) and a plot (.png) next to it."
        ),
    )
    _add_env_arguments(parser)
    parser.add_argument(
        "--controller",
        required=True,
        metavar="NAME|DIR",
        help=f"controller name ({', '.join(CONTROLLERS)}) or the folder of a policy written by scg-jax train",
    )
    _add_controller_arguments(parser)
    parser.add_argument(
        "--out", type=Path, required=True, metavar="FILE.json", help=f"metrics JSON to write{_OUT_CHECKED}"
    )
    return parser


def _add_compare_parser(subparsers) -> argparse.ArgumentParser:
    from scg_algorithms import CONTROLLERS

    parser = subparsers.add_parser(
        "compare",
        help="evaluate several controllers on one config and print them side by side",
        description="Evaluate each controller as scg-jax eval does, on the same episodes (same seed).",
    )
    _add_env_arguments(parser)
    parser.add_argument(
        "--controllers",
        required=True,
        metavar="A,B,...",
        help=f"comma-separated controller names ({', '.join(CONTROLLERS)}) and/or policy folders",
    )
    _add_controller_arguments(parser)
    parser.add_argument(
        "--out", type=Path, metavar="FILE.json", help=f"write every controller's metrics here{_OUT_CHECKED}"
    )
    return parser


def _build_controller(spec: str, env, params, cfg, prior_scale: float):
    """A controller from a registered name (options from ``cfg.controllers``) or a trained policy's folder."""
    from scg_algorithms import CONTROLLERS, make_controller
    from scg_jax.env import prior_params

    if not (np.isfinite(prior_scale) and prior_scale > 0):
        raise _UsageError(f"argument --prior-scale: must be a positive number, got {prior_scale!r}")
    if spec in CONTROLLERS:
        prior = params if prior_scale == 1.0 else prior_params(env, params, prior_scale)
        try:
            return make_controller(spec, env, prior, cfg.controllers.get(spec))
        except ValueError as error:
            raise _UsageError(str(error)) from None
    path = Path(spec)
    if path.is_dir() and _is_gp_mpc_run(path):
        return _load_gp_mpc_run(path, env, params, cfg, prior_scale)
    if path.is_dir():
        from scg_algorithms.rl.policy import load_policy

        if prior_scale != 1.0:
            raise _UsageError("argument --prior-scale: a trained policy has no model to scale; leave it at 1")
        try:
            return load_policy(path, env, params)
        except (ValueError, OSError) as error:
            raise _UsageError(f"argument --controller: {error}") from None
    raise _UsageError(
        f"argument --controller: {spec!r} is neither a controller name ({', '.join(CONTROLLERS)}) nor a policy "
        "folder written by scg-jax train"
    )


def _is_gp_mpc_run(path: Path) -> bool:
    from scg_algorithms.gp_mpc.run import is_run

    return is_run(path)


def _load_gp_mpc_run(path: Path, env, params, cfg, prior_scale: float):
    """The GP-MPC learned in ``path``, on the prior it was learned with (``--prior-scale`` must agree or stay 1)."""
    import json

    from scg_algorithms.gp_mpc.run import RUN_NAME, load_run
    from scg_jax.env import prior_params

    saved_scale = float(json.loads((path / f"{RUN_NAME}.json").read_text())["prior_scale"])
    if prior_scale not in (1.0, saved_scale):
        raise _UsageError(
            f"argument --prior-scale: {path} learned its GP on a prior of scale {saved_scale:g}; leave --prior-scale "
            f"at 1 or give {saved_scale:g}"
        )
    prior = params if saved_scale == 1.0 else prior_params(env, params, saved_scale)
    try:
        return load_run(path, env, prior, cfg.controllers.get("gp_mpc"))
    except (ValueError, OSError) as error:
        raise _UsageError(f"argument --controller: {error}") from None


def _evaluate(controller, env, params, args, console):
    """``evaluate`` with a spinner (JAX controllers: compile and run) or a progress bar (host controllers)."""
    import contextlib

    import jax

    from scg_algorithms.evaluation import evaluate

    waiting = (
        console.status(f"compiling and running {controller.name} on {args.episodes} episodes")
        if controller.is_jax
        else contextlib.nullcontext()
    )
    with waiting:
        return evaluate(
            env, params, controller, jax.random.key(args.seed), args.episodes, progress=not controller.is_jax
        )


def _format_metric(summary: dict, name: str, spread: str | None = None, digits: int = 4) -> str:
    value = summary[name]
    if value is None:
        return "-"
    text = f"{value:.{digits}g}" if abs(value) < 1e-3 and value != 0 else f"{value:.{digits}f}"
    if spread is not None and summary.get(spread) is not None:
        text += f" ± {summary[spread]:.{digits}f}"
    return text


_TABLE_ROWS = (
    ("rmse (m)", "rmse", "rmse_std", 4),
    ("worst-case rmse, CVaR 0.5 (m)", "worst_case_rmse_at_0.5", None, 4),
    ("failure rate", "failure_rate", None, 3),
    ("steps in violation", "constraint_violation_steps", "constraint_violation_steps_std", 1),
    ("return", "return", "return_std", 3),
    ("length (steps)", "length", None, 1),
    ("compute time per step (ms)", "compute_time_per_step_ms", None, 4),
)


def _summary_table(title: str, summaries: dict[str, dict]):
    from rich.table import Table

    table = Table(title=title, min_width=len(title) + 4)
    table.add_column("metric")
    for name in summaries:
        table.add_column(name, justify="right")
    for label, key, spread, digits in _TABLE_ROWS:
        cells = []
        for summary in summaries.values():
            summary = dict(summary)
            per_step = summary.get("compute_time_per_step_s")
            summary["compute_time_per_step_ms"] = None if per_step is None else 1e3 * per_step
            cells.append(_format_metric(summary, key, spread, digits))
        table.add_row(label, *cells)
    return table


def _evaluation_extra(env, cfg, args, controller) -> dict:
    from scg_jax.config import dump_config

    return {
        "system": env.system.name,
        "task": env.task,
        "config_file": None if args.config is None else str(args.config),
        "config": dump_config(cfg),
        "overrides": list(args.set),
        "prior_scale": args.prior_scale,
        "seed": args.seed,
        "num_steps": env.num_steps,
        "controller_info": _jsonable(getattr(controller, "info", {})),
    }


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray | np.generic):
        return value.tolist()
    if value is None or isinstance(value, bool | int | float | str):
        return value
    return str(value)


def _run_eval(args: argparse.Namespace, console) -> int:
    from scg_algorithms.evaluation import evaluation_record
    from scg_jax.plotting import plot_rollout

    if args.out.suffix != ".json":
        raise _UsageError(f"argument --out: expected a .json file name, got {str(args.out)!r}")
    _output(args.out, "file")
    env, params, cfg = _make_env(args)
    controller = _build_controller(args.controller, env, params, cfg, args.prior_scale)
    evaluation = _evaluate(controller, env, params, args, console)
    npz_path, png_path = args.out.with_suffix(".npz"), args.out.with_suffix(".png")
    data = {
        **_env_arrays(env, params),
        **{name: value for name, value in evaluation.trajectory.items() if name not in ("x", "x_ref")},
        "x": evaluation.trajectory["x"][:-1],
        "x_final": evaluation.trajectory["x"][-1],
        # The plot draws one reference; copies share it unless the params were a sweep.
        "x_ref": evaluation.trajectory["x_ref"][:, 0],
        "controller": np.asarray(controller.name),
    }
    write_atomic(npz_path, lambda file: np.savez_compressed(file, **data))
    record = evaluation_record(evaluation, _evaluation_extra(env, cfg, args, controller))
    write_json(args.out, record)
    plot_rollout(npz_path, png_path)
    title = f"{env.system.name} {env.task} | {controller.name} | {args.episodes} episodes x {env.num_steps} steps"
    console.print(_summary_table(title, {controller.name: evaluation.summary}))
    console.print(f"wrote {args.out}, {npz_path}, {png_path}")
    return 0


def _run_compare(args: argparse.Namespace, console) -> int:
    from scg_algorithms.evaluation import evaluation_record

    env, params, cfg = _make_env(args)
    specs = [item.strip() for item in args.controllers.split(",") if item.strip()]
    if not specs:
        raise _UsageError("argument --controllers: expected at least one controller name or policy folder")
    if len(set(specs)) != len(specs):
        raise _UsageError(f"argument --controllers: a controller is listed twice: {args.controllers}")
    if args.out is not None and args.out.suffix != ".json":
        raise _UsageError(f"argument --out: expected a .json file name, got {str(args.out)!r}")
    if args.out is not None:
        _output(args.out, "file")
    controllers = [_build_controller(spec, env, params, cfg, args.prior_scale) for spec in specs]
    records, summaries = {}, {}
    for spec, controller in zip(specs, controllers, strict=True):
        label = controller.name if spec == controller.name else f"{controller.name} ({Path(spec).name})"
        evaluation = _evaluate(controller, env, params, args, console)
        summaries[label] = evaluation.summary
        records[label] = evaluation_record(evaluation, {"controller_info": _jsonable(getattr(controller, "info", {}))})
    title = f"{env.system.name} {env.task} | {args.episodes} episodes x {env.num_steps} steps | seed {args.seed}"
    console.print(_summary_table(title, summaries))
    if args.out is not None:
        extra = _evaluation_extra(env, cfg, args, controllers[0])
        extra.pop("controller_info")
        write_json(args.out, {**extra, "controllers": records})
        console.print(f"wrote {args.out}")
    return 0


# ----------------------------------------------------------------------------------------------- train
LEARNERS = ("ppo", "sac", "gp_mpc")


def _positive_seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not (np.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected a positive number of seconds, got {text!r}")
    return value


def _add_train_parser(subparsers) -> argparse.ArgumentParser:
    parser = subparsers.add_parser(
        "train",
        help="train PPO or SAC on parallel copies of a config's env; save the policy, learning curve and metrics",
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
    _add_env_arguments(parser)
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
        "--eval-episodes", type=_positive_int, default=16, help="episodes of the final evaluation (default: 16)"
    )
    parser.add_argument(
        "--prior-scale",
        type=float,
        default=1.0,
        help="gp_mpc: the prior model has every inertial parameter times this factor (default: 1)",
    )
    parser.set_defaults(_train_parser=parser)
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
            raise _UsageError(
                f"argument --resume: {args.out} holds a {saved_algo} run, not {args.algo}; resume it with --algo "
                f"{saved_algo}, or train {args.algo} into another --out (or replace the run with --overwrite)"
            )
    elif existing and not args.overwrite:
        what = "has no checkpoint to resume but holds" if args.resume else "already holds"
        raise _UsageError(
            f"argument --out: {args.out} {what} a training run ({', '.join(existing)}); "
            + (
                "pass --overwrite to replace it"
                if args.resume
                else "pass --resume to continue it or --overwrite to replace it"
            )
        )


def _run_train(args: argparse.Namespace, console) -> int:
    _output(args.out, "dir")  # before any work: a file in the way or an unwritable location
    if args.algo == "gp_mpc":
        return _run_train_gp_mpc(args, console)
    if args.prior_scale != 1.0:
        raise _UsageError(f"argument --prior-scale: only gp_mpc learns on a prior model; {args.algo} has none")
    import jax

    from scg_algorithms.base import parse_options
    from scg_algorithms.evaluation import evaluate, evaluation_record
    from scg_algorithms.rl.policy import algorithm_module, load_policy
    from scg_algorithms.rl.training import TrainingInterrupted, run_training
    from scg_jax.config import dump_config

    env, params, cfg = _make_env(args)
    try:
        config = parse_options(
            algorithm_module(args.algo, "Config"), cfg.training.get(args.algo), f"training.{args.algo}"
        )
        learner = algorithm_module(args.algo, "make_learner")(config, env)
    except ValueError as error:
        raise _UsageError(str(error)) from None
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
        )
    except TrainingInterrupted as stop:
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
        raise _UsageError(f"argument --resume: {message.removeprefix('resume: ')}") from None
    policy = load_policy(args.out, env, params)
    try:
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
    record = {
        "command": "train",
        "algo": args.algo,
        "system": env.system.name,
        "task": env.task,
        "config_file": None if args.config is None else str(args.config),
        "config": dump_config(cfg),
        "overrides": list(args.set),
        "seed": args.seed,
        "hyperparameters": _jsonable(dataclasses.asdict(config)),
        "training": _jsonable(summary),
        "evaluation": evaluation_record(evaluation),
        "device": str(jax.devices()[0]),
    }
    write_json(args.out / "metrics.json", record)
    title = (
        f"{env.system.name} {env.task} | {args.algo}, {summary['env_steps']:,} env steps in "
        f"{summary['total_time_s']:.1f} s | {args.eval_episodes} evaluation episodes"
    )
    console.print(_summary_table(title, {args.algo: evaluation.summary}))
    console.print(f"wrote {args.out}/policy.msgpack, progress.csv, learning_curve.png, metrics.json")
    return 0


def _run_train_gp_mpc(args: argparse.Namespace, console) -> int:
    """``train --algo gp_mpc``: the learning loop of ``scg_algorithms.gp_mpc.controller.learn`` with the config's
    ``controllers.gp_mpc`` options, then a final evaluation; writes gp_mpc.json/npz, the learning curve and
    metrics.json."""
    import jax

    from scg_algorithms.base import parse_options
    from scg_algorithms.evaluation import evaluate, evaluation_record
    from scg_algorithms.gp_mpc.controller import PATH, Options, learn
    from scg_algorithms.gp_mpc.run import RUN_NAME, save_run, write_learning_curve
    from scg_algorithms.rl.training import existing_run_files, rmse_label
    from scg_jax.config import dump_config
    from scg_jax.env import prior_params

    env, params, cfg = _make_env(args)
    if not (np.isfinite(args.prior_scale) and args.prior_scale > 0):
        raise _UsageError(f"argument --prior-scale: must be a positive number, got {args.prior_scale!r}")
    options = {**dict(cfg.controllers.get("gp_mpc") or {}), "seed": args.seed}
    try:
        opts = parse_options(Options, options, PATH)
    except ValueError as error:
        raise _UsageError(str(error)) from None
    if opts.rounds < 1:
        raise _UsageError(f"{PATH}.rounds: train needs at least one round, got {opts.rounds}")
    if args.resume:
        raise _UsageError(
            "argument --resume: a gp_mpc run is not resumable (each round refits the GP); use --overwrite"
        )
    others = existing_run_files(args.out)
    mine = [
        name for name in (f"{RUN_NAME}.json", f"{RUN_NAME}.npz", "learning_curve.csv") if (args.out / name).exists()
    ]
    if (others or mine) and not args.overwrite:
        what = f"a training run of another algorithm ({', '.join(others)})" if others and not mine else "a run"
        raise _UsageError(f"argument --out: {args.out} already holds {what}; pass --overwrite to replace it")
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
    record = {
        "command": "train",
        "algo": "gp_mpc",
        "system": env.system.name,
        "task": env.task,
        "config_file": None if args.config is None else str(args.config),
        "config": dump_config(cfg),
        "overrides": list(args.set),
        "seed": args.seed,
        "prior_scale": args.prior_scale,
        "options": _jsonable(dataclasses.asdict(opts)),
        "history": _jsonable(result.history),
        "evaluation": evaluation_record(evaluation),
    }
    write_json(args.out / "metrics.json", record)
    title = f"{env.system.name} {env.task} | gp_mpc after {opts.rounds} rounds | {args.eval_episodes} episodes"
    console.print(_summary_table(title, {"gp_mpc": evaluation.summary}))
    console.print(f"wrote {args.out}/{RUN_NAME}.json, {RUN_NAME}.npz, learning_curve.csv/png, metrics.json")
    return 0


# ----------------------------------------------------------------------------------------------- entry point
_SUBCOMMANDS: dict[str, tuple[Callable, Callable]] = {
    "rollout": (_add_rollout_parser, _run_rollout),
    "eval": (_add_eval_parser, _run_eval),
    "compare": (_add_compare_parser, _run_compare),
    "train": (_add_train_parser, _run_train),
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
        except _UsageError as error:
            subcommand_parsers[args.command].error(str(error))
    except SystemExit as exit_:
        # argparse exits for --help (0) and for bad input (2); return the status instead of raising it.
        code = exit_.code
        return code if isinstance(code, int) else (0 if code is None else 1)
    return 1  # unreachable: parser.error always exits


if __name__ == "__main__":
    sys.exit(main())
