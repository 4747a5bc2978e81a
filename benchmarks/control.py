"""Cost of the MPC controllers: IPOPT MPC time per step, and batched linear MPC solves per second.

Two measurements per system (cart-pole and 2D quadrotor, each in its paper configuration), in one run:

1. **Nonlinear MPC** (``algorithms.mpc.nonlinear``, CasADi ``Opti`` + IPOPT, horizon ``--horizon``, default
   options: RK4 prediction model, Riccati terminal weight, primal-dual warm start): ``--episodes`` closed-loop
   episodes through ``algorithms.evaluation.evaluate`` (the host path, one copy at a time). Every ``act`` call is
   timed; reported are the median and 90th percentile per control step of IPOPT's own wall time (the solver call)
   and of the whole ``act`` (packing the parameters and the warm start, the solver call, the fallback logic),
   next to the original safe-control-gym's IPOPT MPC figures (about 6 ms per step on the cart-pole and 11 ms on
   the 2D quadrotor, as quoted in the issue; their machine is not known, so compare orders of magnitude).
2. **Batched linear MPC** (``algorithms.mpc.linear.make_linear_mpc``, the condensed QP solved by qpax, horizon
   ``--horizon``): one jitted ``vmap`` of ``act`` over ``--batch`` copies (their observations from a vmapped
   ``env.reset`` of the config's initial-state distribution, control step 0), timed per call; solves per second =
   batch / time per call. Next to it, in the same run with alternating timed runs, the env's own throughput at the
   same batch: a jitted ``vmap(env.step)`` scanned over ``--env-steps`` control steps with the constant equilibrium
   input (as ``benchmarks/throughput.py``'s env column). The ratio is MPC solves per second over env steps per
   second: how much slower a closed loop with this controller is than the bare simulation.

Configs: ``configs/paper_cartpole_lqr_mpc.yaml`` (stabilization, 15 Hz, 90 steps per episode) and
``configs/paper_quadrotor_2d.yaml`` (figure-8 tracking, 50 Hz, 300 steps). Results go to
``benchmarks/results/control.json``. Run ``python benchmarks/control.py --help``; see benchmarks/README.md.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from machine import load_average, print_machine, run_record  # benchmarks/machine.py, beside this script
from rich import box
from rich.console import Console
from rich.table import Table
from throughput import measure_pair  # benchmarks/throughput.py: compile, calibrate, alternate timed runs

from algorithms.base import Reference
from algorithms.evaluation import evaluate
from algorithms.mpc.linear import make_linear_mpc
from algorithms.mpc.nonlinear import make_nonlinear_mpc
from scg_jax.config import load_config, make_from_config
from scg_jax.files import write_json

ROOT = Path(__file__).resolve().parent.parent
CONFIGS = {
    "cartpole": ROOT / "configs" / "paper_cartpole_lqr_mpc.yaml",
    "quadrotor_2d": ROOT / "configs" / "paper_quadrotor_2d.yaml",
}
# The original suite's IPOPT MPC, ms per control step (figures quoted in the issue; for scale only).
ORIGINAL_NMPC_MS = {"cartpole": 6.0, "quadrotor_2d": 11.0}
DEFAULT_JSON = Path(__file__).resolve().parent / "results" / "control.json"
FULL_DEFAULTS = {"episodes": 2, "batch": 1024, "repeats": 5, "min_time": 0.5}
QUICK_DEFAULTS = {"episodes": 1, "batch": 256, "repeats": 2, "min_time": 0.05}


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description="Nonlinear (IPOPT) MPC time per step and batched linear (qpax) MPC solves per second.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument("--systems", nargs="+", default=list(CONFIGS), choices=list(CONFIGS), help="systems")
    parser.add_argument("--parts", nargs="+", default=["nonlinear", "linear"], choices=["nonlinear", "linear"])
    parser.add_argument("--horizon", type=int, default=20, help="MPC horizon, control steps (both controllers)")
    parser.add_argument("--episodes", type=int, default=None, help="nonlinear MPC episodes per system [default: 2]")
    parser.add_argument("--batch", type=int, default=None, help="copies of the batched linear MPC [default: 1024]")
    parser.add_argument("--env-steps", type=int, default=100, help="control steps per timed env call (lax.scan)")
    parser.add_argument("--repeats", type=int, default=None, help="timed runs per measurement [default: 5]")
    parser.add_argument(
        "--min-time", type=float, default=None, help="minimum seconds per timed run (sets calls per run) [default: 0.5]"
    )
    parser.add_argument("--stat", choices=("median", "min"), default="median", help="statistic over timed runs")
    parser.add_argument("--seed", type=int, default=0, help="seed of the episode and reset keys")
    parser.add_argument("--json", type=Path, default=DEFAULT_JSON, help="where to write the results")
    parser.add_argument(
        "--quick", action="store_true", help="smoke run: 1 episode, batch 256, 2 repeats (explicit options still win)"
    )
    args = parser.parse_args(argv)
    defaults = QUICK_DEFAULTS if args.quick else FULL_DEFAULTS
    for name, value in defaults.items():
        if getattr(args, name) is None:
            setattr(args, name, value)
    for name in ("horizon", "episodes", "batch", "env_steps", "repeats"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')}: must be a positive integer")
    if not args.min_time > 0:
        parser.error("--min-time: must be positive")
    return args


# --------------------------------------------------------------------------------------------- nonlinear MPC
class _Recorder:
    """A host controller that times every ``act`` of the controller it wraps and keeps its final states."""

    is_jax = False

    def __init__(self, controller):
        self.controller = controller
        self.name = controller.name
        self.act_s: list[float] = []
        self.final_states: dict[int, object] = {}

    def reset(self, key, reference):
        return self.controller.reset(key, reference)

    def act(self, ctrl_state, obs, step, reference):
        tick = time.perf_counter()
        u, ctrl_state = self.controller.act(ctrl_state, obs, step, reference)
        self.act_s.append(time.perf_counter() - tick)
        self.final_states[id(reference)] = ctrl_state  # one Reference object per copy in the host path
        return u, ctrl_state


def measure_nonlinear(env, params, horizon: int, episodes: int, seed: int) -> dict:
    tick = time.perf_counter()
    controller = make_nonlinear_mpc(env, params, {"horizon": horizon})
    build_s = time.perf_counter() - tick
    recorder = _Recorder(controller)
    evaluation = evaluate(env, params, recorder, jax.random.key(seed), episodes)
    states = list(recorder.final_states.values())
    solve_ms = 1e3 * np.concatenate([np.asarray(s.solve_time_s) for s in states])
    iterations = np.concatenate([np.asarray(s.iterations) for s in states])
    act_ms = 1e3 * np.asarray(recorder.act_s)
    return {
        "build_s": build_s,
        "steps": int(act_ms.size),
        "ipopt_ms_median": float(np.median(solve_ms)),
        "ipopt_ms_p90": float(np.percentile(solve_ms, 90)),
        "ipopt_ms_max": float(np.max(solve_ms)),
        "act_ms_median": float(np.median(act_ms)),
        "act_ms_p90": float(np.percentile(act_ms, 90)),
        "iterations_median": float(np.median(iterations)),
        "iterations_p90": float(np.percentile(iterations, 90)),
        "failures": int(sum(s.num_failures for s in states)),
        "rmse": float(evaluation.summary["rmse"]),
        "constraint_violation_steps": float(evaluation.summary["constraint_violation_steps"]),
        "crash_rate": float(evaluation.summary["crash_rate"]),
    }


# --------------------------------------------------------------------------------------------- linear MPC
def build_linear(env, params, horizon: int, batch: int, env_steps: int, seed: int):
    """The vmapped linear-MPC ``act`` and the scanned env step of one system, with their arguments."""
    controller = make_linear_mpc(env, params, {"horizon": horizon})
    reference = Reference(*env.reference(params))
    keys = jax.random.split(jax.random.key(seed), batch)
    obs, state = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(keys, params)
    ctrl_state = jax.vmap(controller.reset, in_axes=(0, None))(keys, reference)
    act = jax.vmap(controller.act, in_axes=(0, 0, None, None))

    def mpc_fn(ctrl_state, obs, step, reference):
        return act(ctrl_state, obs, step, reference)

    u_eq = jnp.asarray(env.system.equilibrium_input(params.physics), dtype=params.goal.dtype)
    step_fn = jax.vmap(env.step, in_axes=(0, None, None))

    def env_fn(state, action, params):
        def body(carry, _):
            state, ret = carry
            out = step_fn(state, action, params)
            return (out.state, ret + out.reward), None

        (state, ret), _ = lax.scan(body, (state, jnp.zeros(batch, u_eq.dtype)), None, length=env_steps)
        return state.x, ret

    mpc_args = (ctrl_state, obs, jnp.zeros((), jnp.int32), reference)
    env_args = (state, env.input_to_action(u_eq, params), params)
    return controller, (mpc_fn, mpc_args), (env_fn, env_args)


def measure_linear(env, params, args) -> dict:
    controller, mpc, env_step = build_linear(env, params, args.horizon, args.batch, args.env_steps, args.seed)
    result = measure_pair({"mpc": mpc, "env": env_step}, args.repeats, args.min_time, args.stat)
    u, ctrl_state = result["mpc"]["output"]
    statuses = np.bincount(np.asarray(ctrl_state.status), minlength=3)
    qp = controller.info["qp"]
    mpc_sps = args.batch / result["mpc"]["call_s"]
    env_sps = args.batch * args.env_steps / result["env"]["call_s"]
    row = {
        "qp_decisions": qp.num_decisions,
        "qp_inequalities": qp.num_inequalities,
        "qp_iterations": int(controller.info["options"].max_iter),
        "mpc_solves_per_s": mpc_sps,
        "mpc_us_per_solve": 1e6 / mpc_sps,
        "env_steps_per_s": env_sps,
        "mpc_over_env": mpc_sps / env_sps,
        "status_counts": {"solved": int(statuses[0]), "inaccurate": int(statuses[1]), "failed": int(statuses[2])},
        "u_finite": bool(np.all(np.isfinite(np.asarray(u)))),
    }
    for kind in ("mpc", "env"):
        m = result[kind]
        for key in ("compile_s", "calls_per_run", "call_s", "call_s_min", "call_s_median", "call_s_max"):
            row[f"{kind}_{key}"] = m[key]
    return row


# --------------------------------------------------------------------------------------------- report
def print_report(console: Console, rows: list[dict], meta: dict) -> None:
    cfg = meta["config"]
    where = f"{meta['device']['platform']} ({meta['device']['device_kind']}), {meta['cpu_count']} CPU cores"
    nonlinear = [r for r in rows if "nonlinear" in r]
    if nonlinear:
        table = Table(
            title=f"Nonlinear MPC (CasADi + IPOPT), horizon {cfg['horizon']}, per control step; {where}",
            box=box.SIMPLE_HEAD,
            title_justify="left",
        )
        headers = ("system", "config", "steps", "IPOPT ms median", "IPOPT ms p90", "act ms median", "act ms p90")
        headers += ("iterations median", "original ms", "original / ours", "failures", "rmse")
        for header in headers:
            table.add_column(header, justify="left" if header in ("system", "config") else "right")
        for r in nonlinear:
            n = r["nonlinear"]
            original = ORIGINAL_NMPC_MS[r["system"]]
            table.add_row(
                r["system"],
                r["config"],
                f"{n['steps']}",
                f"{n['ipopt_ms_median']:.2f}",
                f"{n['ipopt_ms_p90']:.2f}",
                f"{n['act_ms_median']:.2f}",
                f"{n['act_ms_p90']:.2f}",
                f"{n['iterations_median']:.0f}",
                f"~{original:g}",
                f"x{original / n['act_ms_median']:.1f}",
                f"{n['failures']}",
                f"{n['rmse']:.3f}",
            )
        console.print(table)
        console.print(
            "IPOPT = the solver call alone; act = the whole controller call (parameters, warm start, solver, "
            "fallbacks). original = the original safe-control-gym's IPOPT MPC as quoted in the issue (machine "
            "unknown); original / ours uses the act median.\n"
        )
    linear = [r for r in rows if "linear" in r]
    if linear:
        table = Table(
            title=(
                f"Batched linear MPC (qpax), horizon {cfg['horizon']}, {cfg['batch']:,} copies, one jitted vmapped "
                f"act per call, {cfg['dtype']}; {where}"
            ),
            box=box.SIMPLE_HEAD,
            title_justify="left",
        )
        for header in ("system", "QP size", "MPC solves/s", "us/solve", "env steps/s", "MPC/env", "MPC compile s",
                       "failed solves"):  # fmt: skip
            table.add_column(header, justify="left" if header == "system" else "right")
        for r in linear:
            m = r["linear"]
            table.add_row(
                r["system"],
                f"{m['qp_decisions']} x {m['qp_inequalities']}",
                f"{m['mpc_solves_per_s']:,.0f}",
                f"{m['mpc_us_per_solve']:.1f}",
                f"{m['env_steps_per_s']:,.0f}",
                f"{m['mpc_over_env']:.4f}",
                f"{m['mpc_compile_s']:.2f}",
                f"{m['status_counts']['failed']}",
            )
        console.print(table)
        console.print(
            f"MPC solves/s = batch / time per vmapped act call; env steps/s = batch * {cfg['env_steps']} / time per "
            f"call of vmap(env.step) scanned over {cfg['env_steps']} steps (constant equilibrium input). "
            f"{cfg['stat']} of {cfg['repeats']} alternating timed runs of at least {cfg['min_time']:g} s. QP size = "
            "decisions x inequality rows; qpax runs its iteration limit on every solve (float32)."
        )


# --------------------------------------------------------------------------------------------- main
def main(argv=None) -> int:
    args = parse_args(argv)
    console = Console()
    if not console.is_terminal:
        console = Console(width=max(console.width, 170))
    started = time.perf_counter()
    meta = {
        **run_record("control"),
        "config": {
            "systems": args.systems,
            "parts": args.parts,
            "configs": {name: str(CONFIGS[name].relative_to(ROOT)) for name in args.systems},
            "horizon": args.horizon,
            "episodes": args.episodes,
            "batch": args.batch,
            "env_steps": args.env_steps,
            "repeats": args.repeats,
            "min_time": args.min_time,
            "stat": args.stat,
            "seed": args.seed,
            "dtype": str(jnp.zeros(()).dtype),
            "quick": args.quick,
        },
        "reference": {
            "original_nmpc_ms_per_step": ORIGINAL_NMPC_MS,
            "description": "original safe-control-gym IPOPT MPC per control step, as quoted in the issue",
        },
    }
    print_machine(console, meta)

    rows = []
    for name in args.systems:
        env, params = make_from_config(load_config(CONFIGS[name]))
        row = {"system": name, "config": CONFIGS[name].stem, "ctrl_freq": 1.0 / env.dt}
        if "nonlinear" in args.parts:
            row["nonlinear"] = n = measure_nonlinear(env, params, args.horizon, args.episodes, args.seed)
            console.print(
                f"{name:<13} nonlinear MPC: {n['steps']} steps, IPOPT {n['ipopt_ms_median']:.2f} ms median "
                f"({n['ipopt_ms_p90']:.2f} p90), act {n['act_ms_median']:.2f} ms, {n['failures']} failed solves",
                highlight=False,
            )
        if "linear" in args.parts:
            row["linear"] = m = measure_linear(env, params, args)
            console.print(
                f"{name:<13} linear MPC x{args.batch}: {m['mpc_solves_per_s']:,.0f} solves/s, env "
                f"{m['env_steps_per_s']:,.0f} steps/s, ratio {m['mpc_over_env']:.4f}, compile "
                f"{m['mpc_compile_s']:.2f} s",
                highlight=False,
            )
        rows.append(row)

    meta["load_average_end"] = load_average()
    meta["total_runtime_s"] = time.perf_counter() - started
    console.print()
    print_report(console, rows, meta)
    write_json(args.json, {**meta, "rows": rows})
    console.print(f"\ntotal runtime {meta['total_runtime_s']:.1f} s; results written to {args.json}", highlight=False)
    return 0


if __name__ == "__main__":
    sys.exit(main())
