"""What every ``scg-jax`` subcommand shares: the environment options, the output-location check, bad-input
errors (exit status 2) and the metrics tables."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from scg_jax.integrators import INTEGRATORS
from scg_jax.plotting import plane_indices
from scg_jax.systems import SYSTEMS
from scg_jax.trajectories import SHAPES

TASKS = ("stabilization", "tracking")


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


OUT_CHECKED = "; missing folders are created, and a location that cannot be written is refused before any work"


class UsageError(Exception):
    """Bad command-line input found after parsing; reported through the subcommand's ``parser.error``."""


def float_list(text: str) -> list[float]:
    """``"a,b,c"`` -> floats; an ``argparse`` type, so a malformed number is reported with the option's name."""
    try:
        values = [float(item) for item in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None
    if not all(np.isfinite(values)):
        raise argparse.ArgumentTypeError(f"values must be finite, got {text!r}")
    return values


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return value


def add_env_command(subparsers, name: str, summary: str, description: str) -> argparse.ArgumentParser:
    """The subcommand ``name`` of a command that builds an environment: its parser, with the environment options
    of :func:`add_env_arguments` already added. ``summary`` is the line of ``scg-jax --help``, ``description`` the
    text of ``scg-jax NAME --help``."""
    parser = subparsers.add_parser(name, help=summary, description=description)
    add_env_arguments(parser)
    return parser


def add_env_arguments(parser: argparse.ArgumentParser) -> None:
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
    env.add_argument("--ctrl-freq", type=positive_int, help="control frequency, Hz (default: 50)")
    env.add_argument("--physics-freq", type=positive_int, help="physics frequency, Hz, a multiple of --ctrl-freq")
    env.add_argument("--episode-len", type=float, help="episode length, s (default: 5)")
    env.add_argument("--integrator", choices=INTEGRATORS, help="integrator (default: rk4)")
    traj = parser.add_argument_group("tracking reference (--task tracking only; defaults are per system)")
    traj.add_argument("--shape", choices=SHAPES, help="reference shape (default: circle)")
    traj.add_argument("--num-cycles", type=float, help="cycles per episode (default: 1)")
    traj.add_argument("--plane", help="two distinct letters of x, y, z, e.g. xz")
    traj.add_argument("--scale", type=float, help="shape size, m")
    traj.add_argument("--offset", type=float_list, metavar="A,B", help="in-plane offset, m")


def make_env(args: argparse.Namespace):
    """``(env, params, config)`` from ``--config``/``--system``, the explicit flags (set as typed values, no YAML
    text) and ``--set``; config and ``make`` errors become ``UsageError`` naming the flag or the dotted path."""
    from scg_jax.config import load_config, make_from_config
    from scg_jax.validation import FieldError

    if args.config is None and args.system is None:
        raise UsageError("argument --system: required unless --config is given")
    if args.offset is not None and len(args.offset) != 2:
        raise UsageError(
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
        if any(_related(text.partition("=")[0].strip(), error.path) for text in args.set):
            flag = "argument --set: "  # the value came from an override, not from the flag of that option
        elif option in _FLAG_OF_OPTION:
            flag = f"argument {_FLAG_OF_OPTION[option][0]}: "
        else:
            flag = ""
        raise UsageError(f"{flag}{error}") from None
    except (ValueError, OSError) as error:  # e.g. a config file that cannot be read
        raise UsageError(str(error)) from None


def _related(key: str, path: str) -> bool:
    """Whether the dotted override key ``key`` is the field ``path`` or lies inside it, or ``path`` inside ``key``."""
    short, long = sorted((key, path), key=len)
    return long == short or (long.startswith(short) and long[len(short)] in ".[")


def check_output(path: Path, kind: str) -> Path:
    """``--out`` checked before any work (``check_output_dir`` / ``check_output_file``), as a usage error."""
    from scg_jax.files import check_output_dir, check_output_file

    try:
        return check_output_dir(path) if kind == "dir" else check_output_file(path)
    except ValueError as error:
        raise UsageError(f"argument --out: {error}") from None


def env_arrays(env, params) -> dict[str, np.ndarray]:
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
    plane = plane_indices(env)
    if plane is not None:
        data["plane"] = np.asarray(plane[0])
        data["plane_indices"] = np.asarray(plane[1], dtype=np.int64)
    x_low, x_high, u_low, u_high = box_bounds(env.constraint_specs, params.constraints, env.nx, env.nu)
    data.update(x_low=x_low, x_high=x_high, u_low=u_low, u_high=u_high)
    return data


def _format_metric(summary: dict, name: str, spread: str | None = None, digits: int = 4) -> str:
    value = summary[name]
    if value is None:
        return "-"
    text = f"{value:.{digits}g}" if abs(value) < 1e-3 and value != 0 else f"{value:.{digits}f}"
    if spread is not None and summary.get(spread) is not None:
        text += f" ± {summary[spread]:.{digits}f}"
    return text


_TABLE_ROWS = (  # {unit}: what the RMSE measures (scg_algorithms.rl.curves.rmse_unit)
    ("rmse ({unit})", "rmse", "rmse_std", 4),
    ("worst-case rmse, CVaR 0.5 ({unit})", "worst_case_rmse_at_0.5", None, 4),
    ("failure rate", "failure_rate", None, 3),
    ("steps in violation", "constraint_violation_steps", "constraint_violation_steps_std", 1),
    ("return", "return", "return_std", 3),
    ("length (steps)", "length", None, 1),
    ("compute time per step (ms)", "compute_time_per_step_ms", None, 4),
)
# Rows shown when a column comes from a safety-filtered controller.
_FILTER_ROWS = (
    ("filter intervention fraction", "intervention_fraction", None, 4),
    ("filter mean correction (N)", "mean_correction", None, 4),
    ("filter infeasible fraction", "infeasible_fraction", None, 4),
)


def summary_table(title: str, summaries: dict[str, dict], rmse_unit: str):
    """The metrics of each column's summary; ``rmse_unit`` (``scg_algorithms.rl.curves.rmse_unit``: ``"m"`` or
    ``"weighted state error, mixed units"``) names what the RMSE rows measure."""
    from rich.table import Table

    table = Table(title=title, min_width=len(title) + 4)
    table.add_column("metric")
    for name in summaries:
        table.add_column(name, justify="right")
    rows = _TABLE_ROWS
    if any("intervention_fraction" in summary for summary in summaries.values()):
        rows = rows + _FILTER_ROWS
    for label, key, spread, digits in rows:
        cells = []
        for summary in summaries.values():
            summary = dict(summary)
            summary.setdefault(key, None)
            per_step = summary.get("compute_time_per_step_s")
            summary["compute_time_per_step_ms"] = None if per_step is None else 1e3 * per_step
            cells.append(_format_metric(summary, key, spread, digits))
        table.add_row(label.format(unit=rmse_unit), *cells)
    return table


def jsonable(value):
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [jsonable(v) for v in value]
    if isinstance(value, np.ndarray | np.generic):
        return value.tolist()
    if value is None or isinstance(value, bool | int | float | str):
        return value
    return str(value)
