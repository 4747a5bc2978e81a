"""``scg-jax rollout``: one episode of ``--num-envs`` parallel copies under a zero, random or linear policy;
writes ``rollout.npz``, ``metrics.json`` and ``rollout.png``."""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from scg_cli.common import (
    OUT_CHECKED,
    UsageError,
    add_env_command,
    check_output,
    env_arrays,
    float_list,
    make_env,
    positive_int,
)
from scg_cli.scale import add_scale_arguments, check_batch, is_main_process, make_mesh, start_distributed
from scg_jax.caching import jitted_method
from scg_jax.files import write_atomic, write_json

POLICIES = ("zero", "random", "linear")


def add_rollout_parser(subparsers) -> argparse.ArgumentParser:
    parser = add_env_command(
        subparsers,
        "rollout",
        "roll out a simple policy in parallel copies and save data, metrics and a plot",
        (
            "Run one episode of --num-envs parallel copies under a simple policy acting on the physical input "
            "(N): zero holds the reference input (hover thrust, 0 N for the cart-pole), random draws uniformly "
            "within the actuator limits, linear applies u = u_ref - K (x - x_ref)."
        ),
    )
    run = parser.add_argument_group("rollout")
    run.add_argument("--policy", default="linear", choices=POLICIES, help="policy (default: %(default)s)")
    run.add_argument(
        "--gain",
        type=float_list,
        metavar="K11,K12,...",
        help=(
            "gain K of the linear policy u = u_ref - K (x - x_ref) (note the minus sign), nu x nx values, row-major; "
            "e.g. --gain -2.8,-5.2,-43.9,-11.6, about the cart-pole's default (default: LQR about the goal or the "
            "first reference point; the gain used is printed and saved in metrics.json)"
        ),
    )
    run.add_argument("--num-envs", type=positive_int, default=64, help="parallel copies (default: 64)")
    run.add_argument("--seed", type=int, default=0, help="PRNG seed (default: 0)")
    run.add_argument(
        "--out",
        type=Path,
        help=f"output folder, created if missing (default: results/rollout/SYSTEM-TASK-POLICY-seedSEED){OUT_CHECKED}",
    )
    add_scale_arguments(parser)
    return parser


def _make_policy(env, params, args) -> tuple[Callable, np.ndarray | None]:
    """The policy ``policy(obs, state, params, key) -> action`` and the gain K (nu, nx) it uses, if linear."""
    import jax
    import jax.numpy as jnp

    dtype = params.goal.dtype
    gain = None
    if args.gain is not None and args.policy != "linear":
        raise UsageError(f"argument --gain: only used with --policy linear, not --policy {args.policy}")
    if args.policy == "linear":
        if args.gain is not None:
            if len(args.gain) != env.nu * env.nx:
                raise UsageError(
                    f"argument --gain: {env.system.name} needs nu x nx = {env.nu} x {env.nx} = {env.nu * env.nx} "
                    f"comma-separated values (row-major), got {len(args.gain)}"
                )
            gain = np.asarray(args.gain, dtype=np.float64).reshape(env.nu, env.nx)
        else:
            from scg_algorithms.lqr import lqr_gain_about

            x0, u0 = jitted_method(env, "reference_at")(0, params)
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


def run_rollout(args: argparse.Namespace, console) -> int:
    import jax
    from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

    from scg_jax.config import dump_config
    from scg_jax.metrics import summarize, trajectory_metrics
    from scg_jax.plotting import plot_rollout
    from scg_jax.rollout import make_rollout
    from scg_jax.sharding import to_host

    start_distributed(args)  # before any JAX computation
    env, params, cfg = make_env(args)
    mesh = make_mesh(args, cfg)
    check_batch(mesh, args.num_envs, "--num-envs")
    out = args.out or Path("results", "rollout", f"{env.system.name}-{env.task}-{args.policy}-seed{args.seed}")
    check_output(out, "dir")

    main = is_main_process()
    progress = Progress(
        SpinnerColumn(), TextColumn("{task.description}"), TimeElapsedColumn(), console=console, disable=not main
    )
    with progress as bar:
        stage = bar.add_task(f"linearising {env.system.name} and building the policy", total=1)
        policy, gain = _make_policy(env, params, args)
        bar.update(stage, completed=1)

        stage = bar.add_task(f"compiling {args.num_envs} copies x {env.num_steps} steps", total=1)
        key = jax.random.key(args.seed)
        start = time.perf_counter()
        rollout = make_rollout(env, policy, args.num_envs, auto_reset=False, mesh=mesh).lower(key, params).compile()
        compile_s = time.perf_counter() - start
        bar.update(stage, completed=1)

        stage = bar.add_task("running", total=1)
        start = time.perf_counter()
        traj = jax.block_until_ready(rollout(key, params))
        run_s = time.perf_counter() - start
        bar.update(stage, completed=1)
        if jax.process_count() > 1:  # every copy's data on every process (a collective); process 0 writes it
            traj = to_host(traj)
            if not main:
                return 0

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
            # The devices the copies were laid out over (--devices, or the config's devices; one without either).
            "devices": [str(device) for device in (jax.devices()[:1] if mesh is None else mesh.devices.flat)],
            "per_copy": {name: np.asarray(values).tolist() for name, values in per_copy.items()},
        }
        write_json(out / "metrics.json", record)
        # The plot reads the saved file, not the in-memory rollout, so it shows exactly what was kept.
        plot_rollout(out / "rollout.npz", out / "rollout.png")
        bar.update(stage, completed=1)

    console.print(_metrics_table(args, env, params, summary, compile_s, run_s, steps_per_s, gain))
    console.print(f"wrote {out / 'rollout.npz'}, {out / 'metrics.json'}, {out / 'rollout.png'}")
    return 0


def _rollout_data(env, params, traj) -> dict[str, np.ndarray]:
    x_ref, u_ref = jitted_method(env, "reference")(params)
    info = ("u", "constraint_values", "mse", "out_of_bounds", "nonfinite")
    return {
        **env_arrays(env, params),
        "x": np.asarray(traj.x),
        "x_final": np.asarray(traj.final_state.x),
        **{name: np.asarray(getattr(traj, name)) for name in ("action", "reward", "cost", "terminated", "truncated")},
        **{name: np.asarray(traj.info[name]) for name in info},
        "x_ref": np.asarray(x_ref),
        "u_ref": np.asarray(u_ref),
    }


def _metrics_table(args, env, params, summary: dict, compile_s: float, run_s: float, steps_per_s: float, gain=None):
    from rich.table import Table

    from scg_algorithms.rl.curves import rmse_unit

    title = f"{env.system.name} {env.task} | policy {args.policy} | {args.num_envs} copies x {env.num_steps} steps"
    table = Table(title=title, min_width=len(title) + 4)
    table.add_column("metric")
    table.add_column("value", justify="right")
    table.add_row(f"rmse ({rmse_unit(env, params)})", f"{summary['rmse_mean']:.4f} ± {summary['rmse_std']:.4f}")
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
