"""Throughput of the batched environments: control steps per second and real-time factor.

For every (system, batch) two jitted functions are built, compiled and timed in the same run:

- **env**: ``jax.vmap(env.step)`` over the batch, ``lax.scan`` over ``N`` control steps, starting from a state made
  by ``jax.vmap(env.reset)``. The reset runs once, *outside* the timed function, and every timed call restarts
  from that same batched state. The return, the done count and the last observation are carried through the
  scan and returned, so reward, observation and termination are computed (only ``info`` may be pruned).
  No auto-reset: a copy whose episode ended keeps stepping (throughput does not depend on it).
- **bare**: the same integrator and substeps on the bare dynamics only, ``jax.vmap(env.integrate)`` scanned
  over the same ``N`` steps from the same initial states and per-copy physical parameters; no input clipping,
  reward, observation or termination. ``env / bare`` is the share of the physics' speed the env keeps.

The task is stabilization, the action the constant equilibrium (hover) physical input ``u_ref`` of each
system, at ``ctrl_freq`` / ``physics_freq`` (default 50 / 1000 Hz) with the env's integrator (default rk4).

Compile time is ``jax.jit(f).lower(*args)`` plus ``.compile()`` (trace, lower, XLA compile), timed apart from
execution. Execution is timed on the compiled function after one warm-up call: each of ``--repeats`` timed
runs makes ``calls`` back-to-back calls (``calls`` is chosen after the warm-up so that a run lasts at least
``--min-time`` seconds) and blocks on the last result; the time per call is the median (``--stat``) over runs.
The env's and the bare kernel's timed runs alternate, so background load on a shared machine hits both alike.

Run ``python benchmarks/throughput.py --help`` for the options; see benchmarks/README.md.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from machine import (  # benchmarks/machine.py, beside this script
    load_average,
    print_machine,
    run_record,
    write_markdown_table,
)
from rich import box
from rich.console import Console
from rich.table import Table

from scg_jax.files import write_json

# The original safe-control-gym (PyBullet, one env, 50 Hz control / 1000 Hz physics, with constraints and
# disturbances) runs about 2,100 cart-pole control steps per second; printed for scale only.
ORIGINAL_CARTPOLE_STEPS_PER_S = 2100.0

# Targets of the spec (informational: a missed target is reported, never an error exit).
TARGET_ENV_OVER_BARE = 0.60
TARGET_CARTPOLE_STEPS_PER_S = 1_000_000.0
TARGET_CARTPOLE_BATCH = 16384
TARGET_CARTPOLE_CORES = 2
TARGET_COMPILE_S = 3.0

FULL_DEFAULTS = {"batches": [1, 1024, 16384], "repeats": 5, "min_time": 0.2}
QUICK_DEFAULTS = {"batches": [1, 256], "repeats": 2, "min_time": 0.02, "steps": [50]}
DEFAULT_JSON = Path(__file__).resolve().parent / "results" / "throughput.json"
DEFAULT_MARKDOWN = Path(__file__).resolve().parents[1] / "docs" / "benchmarks" / "throughput.md"


def default_steps(batch: int) -> int:
    """Control steps per timed call: about 100k copy-steps, between 5 and 2,000 steps.

    Batch 1 -> 2,000, 1,024 -> 97, 16,384 -> 6. Short scans at large batches keep a call of the slowest
    system (quadrotor_3d) well under a second on 2 CPU cores; the calls per timed run make up the rest.
    """
    return int(min(2000, max(5, 100_000 // batch)))


def _list(values, cast):
    """Flatten ``["1,2", "3"]`` into ``[cast(1), cast(2), cast(3)]`` (comma- or space-separated)."""
    out = []
    for value in values:
        out.extend(cast(item) for item in str(value).replace(",", " ").split())
    return out


def parse_args(argv=None) -> argparse.Namespace:
    from scg_jax.integrators import INTEGRATORS
    from scg_jax.systems import SYSTEMS

    parser = argparse.ArgumentParser(
        description="Control steps per second and real-time factor of the batched envs and of the bare physics.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument("--systems", nargs="+", default=list(SYSTEMS), help="systems (comma or space separated)")
    parser.add_argument("--batches", nargs="+", default=None, help="batch sizes [default: 1 1024 16384]")
    parser.add_argument(
        "--steps",
        nargs="+",
        default=None,
        help="control steps N per timed call: one value for every batch or one per batch "
        "[default: min(2000, max(5, 100000 // batch))]",
    )
    parser.add_argument("--repeats", type=int, default=None, help="timed runs per measurement [default: 5]")
    parser.add_argument(
        "--min-time", type=float, default=None, help="minimum seconds per timed run (sets calls per run) [default: 0.2]"
    )
    parser.add_argument("--stat", choices=("median", "min"), default="median", help="statistic over timed runs")
    parser.add_argument("--integrator", choices=INTEGRATORS, default="rk4")
    parser.add_argument("--ctrl-freq", type=int, default=50, help="control frequency, Hz")
    parser.add_argument("--physics-freq", type=int, default=1000, help="physics frequency, Hz")
    parser.add_argument("--seed", type=int, default=0, help="seed of the reset key")
    parser.add_argument("--x64", action="store_true", help="enable float64 (jax_enable_x64)")
    parser.add_argument("--json", type=Path, default=DEFAULT_JSON, help="where to write the results")
    parser.add_argument(
        "--markdown",
        type=Path,
        default=None,
        help=f"where to write the generated table [default: {DEFAULT_MARKDOWN} for a full run, none with --quick]",
    )
    parser.add_argument(
        "--quick",
        action="store_true",
        help="smoke run: batches 1 256, 50 steps, 2 repeats, 0.02 s per run (explicit options still win)",
    )
    args = parser.parse_args(argv)

    defaults = QUICK_DEFAULTS if args.quick else FULL_DEFAULTS
    args.systems = _list(args.systems, str)
    for name in args.systems:
        if name not in SYSTEMS:
            parser.error(f"--systems: unknown system {name!r}; allowed values are {', '.join(SYSTEMS)}")
    args.batches = _list(args.batches, int) if args.batches is not None else list(defaults["batches"])
    if not args.batches or min(args.batches) < 1:
        parser.error("--batches: batch sizes must be positive integers")
    if args.steps is None:
        steps = defaults.get("steps")
        args.steps = [default_steps(b) for b in args.batches] if steps is None else steps * len(args.batches)
    else:
        steps = _list(args.steps, int)
        if len(steps) == 1:
            steps = steps * len(args.batches)
        if len(steps) != len(args.batches) or min(steps) < 1:
            parser.error("--steps: give one positive value, or one per batch size")
        args.steps = steps
    args.repeats = defaults["repeats"] if args.repeats is None else args.repeats
    args.min_time = defaults["min_time"] if args.min_time is None else args.min_time
    if args.repeats < 1:
        parser.error("--repeats: must be at least 1")
    return args


# The "safe" env of the same run: the default state and input constraints, and white noise on every disturbance
# channel (magnitudes do not change the cost of a step).
SAFETY_OPTIONS = {
    "constraints": [{"type": "default", "on": "state"}, {"type": "default", "on": "input"}],
    "disturbances": {
        "action": [{"type": "white_noise", "std": 0.001}],
        "observation": [{"type": "white_noise", "std": 0.001}],
        "dynamics": [{"type": "white_noise", "std": 0.0001}],
    },
}
TARGET_SAFE_OVER_ENV = 0.7


# --------------------------------------------------------------------------------------------- functions
def build(env, batch: int, steps: int, seed: int):
    """The env and bare-kernel functions of one (system, batch) with their arguments (the reset is done here)."""
    params = env.default_params
    u_ref = jnp.asarray(env.system.equilibrium_input(params.physics), dtype=params.goal.dtype)
    reset = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))
    obs0, state0 = reset(jax.random.split(jax.random.key(seed), batch), params)
    jax.block_until_ready(state0)
    step = jax.vmap(env.step, in_axes=(0, None, None))
    integrate = jax.vmap(env.integrate, in_axes=(0, None, 0))

    def env_fn(obs, state, action, params):
        def body(carry, _):
            _, state, ret, dones = carry
            out = step(state, action, params)
            done = (out.terminated | out.truncated).astype(jnp.int32)
            return (out.obs, out.state, ret + out.reward, dones + done), None

        init = (obs, state, jnp.zeros(batch, obs.dtype), jnp.zeros(batch, jnp.int32))
        (obs, state, ret, dones), _ = lax.scan(body, init, None, length=steps)
        return obs, state.x, ret, dones

    def bare_fn(x, u, physics):
        def body(x, _):
            return integrate(x, u, physics), None

        x, _ = lax.scan(body, x, None, length=steps)
        return x

    env_args = (obs0, state0, u_ref, params)
    bare_args = (state0.x, u_ref, state0.physics)  # the same per-copy physics the env's state carries
    return (env_fn, env_args), (bare_fn, bare_args)


def compile_and_calibrate(fn, args, min_time: float) -> dict:
    """Compile ``fn`` (timed apart from execution), warm it up and choose the calls per timed run."""
    t0 = time.perf_counter()
    lowered = jax.jit(fn).lower(*args)
    t1 = time.perf_counter()
    compiled = lowered.compile()
    t2 = time.perf_counter()

    jax.block_until_ready(compiled(*args))  # warm-up (first-run allocations)
    t = time.perf_counter()
    out = jax.block_until_ready(compiled(*args))
    first = time.perf_counter() - t
    calls = max(1, min(100_000, math.ceil(min_time / max(first, 1e-7))))
    return {
        "compiled": compiled,
        "args": args,
        "lower_s": t1 - t0,
        "xla_compile_s": t2 - t1,
        "compile_s": t2 - t0,
        "calls_per_run": calls,
        "output": out,
        "runs": [],
    }


def timed_run(m: dict) -> None:
    """One timed run: ``calls_per_run`` back-to-back calls, blocking on the last; appends seconds per call."""
    compiled, args, calls = m["compiled"], m["args"], m["calls_per_run"]
    t = time.perf_counter()
    for _ in range(calls):
        out = compiled(*args)
    jax.block_until_ready(out)
    m["runs"].append((time.perf_counter() - t) / calls)


def measure_pair(fns: dict, repeats: int, min_time: float, stat: str) -> dict:
    """Compile and time several functions; their timed runs alternate so background load hits them alike."""
    results = {kind: compile_and_calibrate(fn, args, min_time) for kind, (fn, args) in fns.items()}
    for _ in range(repeats):
        for m in results.values():
            timed_run(m)
    for m in results.values():
        runs = np.asarray(m.pop("runs"))
        del m["compiled"], m["args"]
        m.update(
            call_s=float(np.median(runs) if stat == "median" else runs.min()),
            call_s_min=float(runs.min()),
            call_s_median=float(np.median(runs)),
            call_s_max=float(runs.max()),
        )
    return results


# --------------------------------------------------------------------------------------------- report
def _rate(value: float) -> str:
    return f"{value:,.0f}"


def _ratio_target(rows: list[dict], key: str, threshold: float, target: str) -> dict:
    """PASS when ``row[key] >= threshold`` on every row; the detail names the worst row and every row below."""
    if not rows:
        return {"target": target, "status": "N/A", "detail": "nothing measured"}
    worst = min(rows, key=lambda r: r[key])
    below = [f"{r['system']}/{r['batch']} ({r[key]:.2f})" for r in rows if r[key] < threshold]
    detail = f"min {worst[key]:.2f} at {worst['system']}/{worst['batch']}"
    if below:
        detail += "; below: " + ", ".join(below)
    return {"target": target, "status": "FAIL" if below else "PASS", "detail": detail}


def _targets(rows: list[dict], device: dict, cores: int) -> list[dict]:
    targets = [
        _ratio_target(
            rows, "env_over_bare", TARGET_ENV_OVER_BARE, f"env >= {TARGET_ENV_OVER_BARE:.0%} of bare kernel (every row)"
        )  # fmt: skip
    ]

    name = f"cartpole >= 1M control steps/s at batch {TARGET_CARTPOLE_BATCH} on {TARGET_CARTPOLE_CORES} CPU cores"
    row = next((r for r in rows if r["system"] == "cartpole" and r["batch"] == TARGET_CARTPOLE_BATCH), None)
    if row is None:
        status, detail = "N/A", f"cartpole at batch {TARGET_CARTPOLE_BATCH} not measured"
    else:
        value = row["env_steps_per_s"]
        detail = f"{_rate(value)} steps/s on {device['platform']} ({device['device_kind']}), {cores} CPU cores"
        if device["platform"] != "cpu":
            status, detail = "N/A", detail + "; the target is for CPU"
        else:
            status = "PASS" if value >= TARGET_CARTPOLE_STEPS_PER_S else "FAIL"
            if cores != TARGET_CARTPOLE_CORES:
                detail += f" (target is for {TARGET_CARTPOLE_CORES})"
    targets.append({"target": name, "status": status, "detail": detail})

    if rows:
        worst = max(rows, key=lambda r: r["env_compile_s"])
        bare = max(r["bare_compile_s"] for r in rows)
        status = "PASS" if worst["env_compile_s"] < TARGET_COMPILE_S else "FAIL"
        detail = (
            f"max env compile {worst['env_compile_s']:.2f} s at {worst['system']}/{worst['batch']}; "
            f"max bare compile {bare:.2f} s"
        )
    else:
        status, detail = "N/A", "nothing measured"
    targets.append({"target": f"compile < {TARGET_COMPILE_S:g} s (env function)", "status": status, "detail": detail})

    targets.append(_ratio_target(
        rows, "safe_over_env", TARGET_SAFE_OVER_ENV,
        f"with constraints and disturbances >= {TARGET_SAFE_OVER_ENV:.0%} of the plain env (every row)"))  # fmt: skip
    return targets


def print_report(console: Console, rows: list[dict], targets: list[dict], meta: dict) -> None:
    cfg = meta["config"]
    table = Table(
        title=(
            f"Throughput: {cfg['task']}, constant u_ref, {cfg['ctrl_freq']} Hz control / {cfg['physics_freq']} Hz "
            f"physics, {cfg['integrator']}, {cfg['dtype']}, {meta['device']['platform']} "
            f"({meta['device']['device_kind']}), {meta['cpu_count']} CPU cores, jax {meta['jax_version']}"
        ),
        box=box.SIMPLE_HEAD,
        title_justify="left",
    )
    for header in ("system", "batch", "N x calls"):
        table.add_column(header, justify="right" if header != "system" else "left")
    for header in ("env steps/s", "bare steps/s", "env/bare", "safe steps/s", "safe/env", "real-time factor",
                   "env compile s", "bare compile s", "vs original (2,100/s)"):  # fmt: skip
        table.add_column(header, justify="right")
    for r in rows:
        vs = f"x{r['vs_original']:,.0f}" if r["vs_original"] is not None else ""
        table.add_row(
            r["system"],
            f"{r['batch']:,}",
            f"{r['steps']} x {r['env_calls_per_run']}/{r['bare_calls_per_run']}",
            _rate(r["env_steps_per_s"]),
            _rate(r["bare_steps_per_s"]),
            f"{r['env_over_bare']:.2f}",
            _rate(r["safe_steps_per_s"]),
            f"{r['safe_over_env']:.2f}",
            f"{r['real_time_factor']:,.0f}",
            f"{r['env_compile_s']:.2f}",
            f"{r['bare_compile_s']:.2f}",
            vs,
        )
    console.print(table)
    console.print(
        f"steps/s = batch * N / time per call ({cfg['stat']} of {cfg['repeats']} timed runs, each at least "
        f"{cfg['min_time']:g} s of back-to-back calls; calls per run shown env/bare); reset outside the timed "
        "function.\n"
        "safe = the same env with the default state and input constraints and white noise on the action, "
        "observation and dynamics channels.\n"
        "real-time factor = env steps/s * dt: simulated seconds per wall-clock second, summed over the batch.\n"
        f"compile = jit lower + XLA compile. vs original: cart-pole env steps/s over the ~"
        f"{ORIGINAL_CARTPOLE_STEPS_PER_S:,.0f} control steps/s of the original safe-control-gym (PyBullet, one "
        "env, 50/1000 Hz, with constraints and disturbances); for scale only."
    )
    console.print("\nTargets (informational):")
    for t in targets:
        style = {"PASS": "green", "FAIL": "red"}.get(t["status"], "yellow")
        console.print(f"  [{style}]{t['status']:<4}[/{style}]  {t['target']}: {t['detail']}", highlight=False)


# --------------------------------------------------------------------------------------------- main
def main(argv=None) -> int:
    args = parse_args(argv)
    if args.x64:
        jax.config.update("jax_enable_x64", True)
    import scg_jax

    console = Console()
    if not console.is_terminal:
        console = Console(width=max(console.width, 170))
    started = time.perf_counter()
    meta = {
        **run_record("throughput"),
        "jaxlib_version": getattr(jax.lib, "__version__", None) or jax.__version__,
        "config": {
            "task": "stabilization",
            "action": "constant u_ref = system.equilibrium_input(params.physics), physical",
            "systems": args.systems,
            "batches": args.batches,
            "steps": args.steps,
            "repeats": args.repeats,
            "min_time": args.min_time,
            "stat": args.stat,
            "integrator": args.integrator,
            "ctrl_freq": args.ctrl_freq,
            "physics_freq": args.physics_freq,
            "seed": args.seed,
            "dtype": str(jnp.zeros(()).dtype),
            "quick": args.quick,
            "reset": "vmapped env.reset once, outside the timed function; every call restarts from that state",
        },
        "reference": {
            "original_cartpole_steps_per_s": ORIGINAL_CARTPOLE_STEPS_PER_S,
            "description": "original safe-control-gym, PyBullet, one env, 50/1000 Hz, constraints and disturbances",
        },
    }
    device, cores = meta["device"], meta["cpu_count"]
    print_machine(
        console, meta, suffix=f"; {args.integrator}, {args.ctrl_freq}/{args.physics_freq} Hz, {meta['config']['dtype']}"
    )

    total = len(args.systems) * len(args.batches) * 3
    done = 0
    rows = []
    for name in args.systems:
        options = dict(integrator=args.integrator, ctrl_freq=args.ctrl_freq, physics_freq=args.physics_freq)
        env = scg_jax.make(name, "stabilization", **options)
        safe_env = scg_jax.make(name, "stabilization", **options, **SAFETY_OPTIONS)
        for batch, steps in zip(args.batches, args.steps, strict=True):
            (env_fn, env_args), (bare_fn, bare_args) = build(env, batch, steps, args.seed)
            (safe_fn, safe_args), _ = build(safe_env, batch, steps, args.seed)
            result = measure_pair(
                {"env": (env_fn, env_args), "bare": (bare_fn, bare_args), "safe": (safe_fn, safe_args)},
                args.repeats,
                args.min_time,
                args.stat,
            )
            for kind, m in result.items():
                m["steps_per_s"] = batch * steps / m["call_s"]
                done += 1
                console.print(
                    f"[{done:>{len(str(total))}}/{total}] {name:<13} batch {batch:>6,} {kind:<4} N={steps:<5} "
                    f"compile {m['compile_s']:5.2f} s  {m['call_s'] * 1e3:9.3f} ms/call x {m['calls_per_run']:<5} "
                    f"{_rate(m['steps_per_s']):>12} steps/s",
                    highlight=False,
                )
            x_env = np.asarray(result["env"]["output"][1])
            x_bare = np.asarray(result["bare"]["output"])
            env_sps, bare_sps = result["env"]["steps_per_s"], result["bare"]["steps_per_s"]
            safe_sps = result["safe"]["steps_per_s"]
            row = {
                "system": name,
                "batch": batch,
                "steps": steps,
                "dt": env.dt,
                "substeps": env.substeps,
                "env_steps_per_s": env_sps,
                "bare_steps_per_s": bare_sps,
                "env_over_bare": env_sps / bare_sps,
                "safe_steps_per_s": safe_sps,
                "safe_over_env": safe_sps / env_sps,
                "real_time_factor": env_sps * env.dt,
                "bare_real_time_factor": bare_sps * env.dt,
                "physics_steps_per_s": env_sps * env.substeps,
                "vs_original": env_sps / ORIGINAL_CARTPOLE_STEPS_PER_S if name == "cartpole" else None,
                # final states of env and bare kernel from the same start (same arithmetic; tiny if any)
                "max_abs_diff_final_x": float(np.max(np.abs(x_env - x_bare))),
            }
            for kind in ("env", "bare", "safe"):
                m = result[kind]
                for key in ("compile_s", "lower_s", "xla_compile_s", "calls_per_run", "call_s", "call_s_min",
                            "call_s_median", "call_s_max"):  # fmt: skip
                    row[f"{kind}_{key}"] = m[key]
            rows.append(row)

    targets = _targets(rows, device, cores)
    meta["load_average_end"] = load_average()
    meta["total_runtime_s"] = time.perf_counter() - started
    console.print()
    print_report(console, rows, targets, meta)
    write_json(args.json, {**meta, "rows": rows, "targets": targets})
    markdown = args.markdown or (None if args.quick else DEFAULT_MARKDOWN)
    if markdown is not None:
        write_markdown_table(
            markdown,
            "Environment throughput",
            meta,
            ["system", "batch", "env steps/s", "env / bare", "safe / env", "real-time factor", "compile (s)"],
            [
                [
                    r["system"],
                    r["batch"],
                    r["env_steps_per_s"],
                    r["env_over_bare"],
                    r["safe_over_env"],
                    r["real_time_factor"],
                    r["env_compile_s"],
                ]
                for r in rows
            ],
            notes=f"{args.integrator}, {args.ctrl_freq} Hz control / {args.physics_freq} Hz physics, "
            f"{meta['config']['dtype']}. env: `vmap(env.step)` scanned over control steps; bare: the physics kernel "
            "alone (`vmap(env.integrate)`), measured in the same run; safe: the env with default constraints and "
            "white noise on every disturbance channel. For scale, the original suite steps about "
            f"{ORIGINAL_CARTPOLE_STEPS_PER_S:,.0f} cart-pole control steps/s, one PyBullet env at a time.",
        )
        console.print(f"table written to {markdown}", highlight=False)
    console.print(f"\ntotal runtime {meta['total_runtime_s']:.1f} s; results written to {args.json}", highlight=False)
    return 0


if __name__ == "__main__":
    sys.exit(main())
