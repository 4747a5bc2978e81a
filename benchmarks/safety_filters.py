"""Safety filters: certification speed, parity, and the 1D-quadrotor ceiling acceptance numbers, in one run.

1. **Filter calls per second** for each case of ``CASES`` (a list; append a ``Case`` to add a filter, e.g. an
   MPSC): one ``jax.jit``-ed ``vmap`` of ``certify`` over ``B`` copies (B = 1, 1,024, 16,384), random states in the
   constraint box and random inputs 20 % beyond the actuator box; calls/s = B / median time per batch call.
   Host cases (``is_jax = False``) report the median time of one call instead.
2. **Parity**: the closed-form filter against the CasADi/qpOASES QP built from the same barrier, at ``--parity``
   random points (float64): the largest input difference (N); and the qpax filter (two barriers) likewise.
3. **Overhead on the evaluation loop**: ``evaluate`` of random inputs on the ceiling task, bare and filtered, at
   1,024 episodes; ratio of the closed loops' run times (compile excluded).
4. **Ceiling acceptance** (``--episodes``, 4,096 by default): violating steps and overshoot, unfiltered, filtered with
   the true model, with a 150 %-mass prior, and with the learned CBF trained on that prior (its default budget).
5. ``is_valid_cbf`` on the original's cart-pole ellipsoid (box +-(2, 2, 0.2, 2), +-10 N) and on the ceiling barrier.

Writes ``benchmarks/results/safety_filters.json`` and ``docs/benchmarks/safety_filters.md``. Float64 unless
``--float32``. Run ``python benchmarks/safety_filters.py --help``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import median_seconds, print_machine, run_record, write_markdown_table  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_JSON = ROOT / "benchmarks" / "results" / "safety_filters.json"
DEFAULT_MD = ROOT / "docs" / "benchmarks" / "safety_filters.md"
CEILING = 1.5
TRUE_BRAKING = 0.9 * (9.8 - 4 * 0.02816 / 0.027)


def ceiling_env():
    import scg_jax

    return scg_jax.make(
        "quadrotor_1d",
        init_state={"type": "uniform", "low": [0.1, -0.01], "high": [1.4, 0.01]},
        done_on_out_of_bounds=False,
        constraints=[{"type": "bounded", "on": "state", "active_dims": [0], "low": [-10.0], "high": [CEILING]}],
    )


def cartpole_env():
    import scg_jax

    box = [2.0, 2.0, 0.2, 2.0]
    return scg_jax.make(
        "cartpole", constraints=[{"type": "bounded", "on": "state", "low": [-b for b in box], "high": box}]
    )


@dataclasses.dataclass(frozen=True)
class Case:
    """One filter to time: ``build() -> (env, filter)``; ``label`` names the row."""

    label: str
    build: Callable


def _cbf_case(label, env_fn, options):
    def build():
        from scg_algorithms.safety_filters import make_filter

        env = env_fn()
        return env, make_filter("cbf", env, env.default_params, options)

    return Case(label, build)


# Extend this list to time more filters (the same columns are measured for each).
CASES = [
    _cbf_case("CBF closed form (cart-pole ellipsoid)", cartpole_env, {"barrier": "ellipsoid"}),
    _cbf_case("CBF qpax (cart-pole ellipsoid)", cartpole_env, {"barrier": "ellipsoid", "solver": "qpax"}),
    _cbf_case("CBF qpax (cart-pole position, 2 barriers)", cartpole_env, {"barrier": "cartpole_position"}),
    _cbf_case("CBF CasADi qpOASES (cart-pole ellipsoid)", cartpole_env, {"barrier": "ellipsoid", "solver": "casadi"}),
]


def _samples(env, n, seed=0):
    from scg_algorithms.controller_setup import input_limits
    from scg_jax.constraints import box_bounds

    params = env.default_params
    x_low, x_high, _, _ = box_bounds(env.constraint_specs, params.constraints, env.nx, env.nu)
    x_low = np.where(np.isfinite(x_low), x_low, -2.0)
    x_high = np.where(np.isfinite(x_high), x_high, 2.0)
    u_low, u_high = input_limits(env, params)
    pad = 0.2 * (u_high - u_low)
    rng = np.random.default_rng(seed)
    return rng.uniform(x_low, x_high, (n, env.nx)), rng.uniform(u_low - pad, u_high + pad, (n, env.nu))


def time_case(case: Case, batches, repeats: int) -> dict:
    import jax
    import jax.numpy as jnp

    env, flt = case.build()
    row = {"case": case.label, "is_jax": flt.is_jax}
    if not flt.is_jax:
        xs, us = _samples(env, 500)
        times = []
        for i in range(len(xs)):
            start = time.perf_counter()
            flt.certify(xs[i], us[i], flt.params, ())
            times.append(time.perf_counter() - start)
        row["host_call_s"] = float(np.median(times))
        return row
    certify = jax.jit(jax.vmap(lambda x, u: flt.certify(x, u, flt.params, ())))
    for batch in batches:
        xs, us = (jnp.asarray(a) for a in _samples(env, batch))
        row[f"calls_per_s_{batch}"] = batch / median_seconds(lambda xs=xs, us=us: certify(xs, us), repeats)
    return row


def parity(num_points: int) -> dict:
    import jax
    import jax.numpy as jnp

    from scg_algorithms.safety_filters import make_filter

    env = cartpole_env()
    params = env.default_params
    out = {}
    for barrier in ("ellipsoid", "cartpole_position"):
        jax_filter = make_filter("cbf", env, params, {"barrier": barrier})
        ref = make_filter("cbf", env, params, {"barrier": barrier, "solver": "casadi"})
        xs, us = _samples(env, num_points, seed=1)
        certify = jax.jit(jax.vmap(lambda x, v, f=jax_filter: f.certify(x, v, f.params, ())))
        u, _, info = certify(jnp.asarray(xs), jnp.asarray(us))
        u_ref = np.array([ref.certify(xs[i], us[i], ref.params, ())[0] for i in range(num_points)])
        out[barrier] = {
            "solver": jax_filter.info["solver"],
            "points": num_points,
            "max_abs_difference_N": float(np.max(np.abs(np.asarray(u) - u_ref))),
            "intervened_fraction": float(np.mean(np.abs(np.asarray(info.correction)) > 1e-9)),
            "infeasible_fraction": float(np.mean(~np.asarray(info.feasible))),
        }
    return out


def overhead(episodes: int) -> dict:
    import jax

    from scg_algorithms.evaluation import evaluate
    from scg_algorithms.safety_filters import filtered, make_filter
    from scg_algorithms.safety_filters.uncertified import random_input

    env = ceiling_env()
    params = env.default_params
    bare = random_input(env, params)
    wrapped = filtered(bare, make_filter("cbf", env, params, {"barrier": "ceiling", "slope": 0.5}), env)
    result = {}
    for name, controller in (("bare", bare), ("filtered", wrapped)):
        evaluate(env, params, controller, jax.random.key(0), episodes, measure_time=False)
        runs = [
            evaluate(env, params, controller, jax.random.key(i), episodes, measure_time=False).timing["run_s"]
            for i in range(3)
        ]
        result[f"{name}_run_s"] = float(np.median(runs))
    result["ratio"] = result["filtered_run_s"] / result["bare_run_s"]
    result["episodes"] = episodes
    return result


def ceiling_acceptance(episodes: int, learned_options: dict) -> dict:
    import jax

    from scg_algorithms.evaluation import evaluate
    from scg_algorithms.safety_filters import filtered, make_filter
    from scg_algorithms.safety_filters.learned_cbf import train_learned_cbf
    from scg_algorithms.safety_filters.uncertified import random_input
    from scg_jax.env import prior_params

    env = ceiling_env()
    params = env.default_params
    uncertified = random_input(env, params)
    options = {"barrier": "ceiling", "slope": 0.5, "braking_deceleration": TRUE_BRAKING}
    prior = prior_params(env, params, 1.5)

    def score(controller):
        run = evaluate(env, params, controller, jax.random.key(7), episodes, measure_time=False)
        per = run.per_episode
        z = run.trajectory["x"][:, :, 0]
        return {
            "violating_steps": float(np.sum(per["violation_steps"]) / np.sum(per["length"])),
            "episodes_with_violation": float(np.mean(per["violation_steps"] > 0)),
            "max_overshoot_m": float(max(z.max() - CEILING, 0.0)),
            "intervention_fraction": run.summary.get("intervention_fraction"),
            "mean_correction_N": run.summary.get("mean_correction"),
        }

    start = time.perf_counter()
    learned = train_learned_cbf(env, params, prior, {**options, **learned_options})
    train_s = time.perf_counter() - start
    rows = {
        "unfiltered": score(uncertified),
        "CBF, true model": score(filtered(uncertified, make_filter("cbf", env, params, options), env)),
        "CBF, 150 % mass prior": score(filtered(uncertified, make_filter("cbf", env, prior, options), env)),
        "learned CBF on the 150 % prior": score(filtered(uncertified, learned.filter, env)),
    }
    last = learned.history[-1]
    return {
        "episodes": episodes,
        "rows": rows,
        "learned": {"train_s": train_s, "data_seconds": last["data_seconds"], "history": learned.history},
    }


def validity(num_points: int) -> dict:
    import jax

    from scg_algorithms.safety_filters import make_filter
    from scg_algorithms.safety_filters.cbf import is_valid_cbf

    cart = cartpole_env()
    quad = ceiling_env()
    out = {}
    for label, env, options, box in (
        ("cart-pole ellipsoid (original)", cart, {"barrier": "ellipsoid"}, (None, None)),
        ("cart-pole position (braking)", cart, {"barrier": "cartpole_position"}, (None, None)),
        ("1D quadrotor ceiling (braking)", quad, {"barrier": "ceiling"}, ([-1.0, -5.0], [1.5, 5.0])),
    ):
        report = is_valid_cbf(
            make_filter("cbf", env, env.default_params, options), env, num_points, jax.random.key(0),
            low=box[0], high=box[1],
        )  # fmt: skip
        out[label] = {
            "inside": report.num_inside,
            "infeasible": report.num_infeasible,
            "infeasible_fraction": report.infeasible_fraction,
            "worst_states": report.worst_states[:3].tolist(),
            "worst_margins": report.worst_margins[:3].tolist(),
        }
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--float32", action="store_true", help="time in float32 (default: float64)")
    parser.add_argument("--batches", default="1,1024,16384", help="batch sizes (default: 1,1024,16384)")
    parser.add_argument("--repeats", type=int, default=5, help="timed calls per batch size (median)")
    parser.add_argument("--parity", type=int, default=10_000, help="parity points (default: 10,000)")
    parser.add_argument("--episodes", type=int, default=4096, help="ceiling acceptance episodes (default: 4,096)")
    parser.add_argument("--overhead-episodes", type=int, default=1024)
    parser.add_argument("--learned", default="{}", help="JSON options for the learned CBF (default: its defaults)")
    parser.add_argument("--json", type=Path, default=DEFAULT_JSON)
    parser.add_argument("--markdown", type=Path, default=DEFAULT_MD)
    args = parser.parse_args(argv)

    import jax

    if not args.float32:
        jax.config.update("jax_enable_x64", True)
    from rich.console import Console

    console = Console()
    record = run_record("safety_filters")
    print_machine(console, record)
    batches = [int(b) for b in args.batches.split(",")]
    start = time.perf_counter()
    speed = []
    for case in CASES:
        row = time_case(case, batches, args.repeats)
        console.print(row, highlight=False)
        speed.append(row)
    parity_result = parity(args.parity)
    console.print(parity_result, highlight=False)
    validity_result = validity(10_000)
    console.print(validity_result, highlight=False)
    overhead_result = overhead(args.overhead_episodes)
    console.print(overhead_result, highlight=False)
    acceptance = ceiling_acceptance(args.episodes, json.loads(args.learned))
    console.print(acceptance["rows"], highlight=False)
    record.update(
        dtype="float32" if args.float32 else "float64",
        speed=speed,
        parity=parity_result,
        validity=validity_result,
        overhead=overhead_result,
        acceptance=acceptance,
        total_runtime_s=time.perf_counter() - start,
    )
    args.json.parent.mkdir(parents=True, exist_ok=True)
    from scg_jax.files import write_json

    write_json(args.json, record)

    columns = ["case"] + [f"calls/s, B={b:,}" for b in batches] + ["host time per call (ms)"]
    rows = [
        [r["case"]]
        + [r.get(f"calls_per_s_{b}") for b in batches]
        + [None if "host_call_s" not in r else 1e3 * r["host_call_s"]]
        for r in speed
    ]
    acc_lines = [
        "| case | violating steps | episodes with a violation | max overshoot (m) | interventions "
        "| mean correction (N) |",
        "|---|---|---|---|---|---|",
    ]
    for label, r in acceptance["rows"].items():
        fmt = lambda v: "-" if v is None else f"{v:.3g}"  # noqa: E731
        acc_lines.append(
            f"| {label} | {100 * r['violating_steps']:.4f} % | {100 * r['episodes_with_violation']:.2f} % | "
            f"{r['max_overshoot_m']:.4f} | {fmt(r['intervention_fraction'])} | {fmt(r['mean_correction_N'])} |"
        )
    par = "; ".join(
        f"{k} ({v['solver']}): max |u - u_qpOASES| = {v['max_abs_difference_N']:.2g} N over {v['points']:,} points"
        for k, v in parity_result.items()
    )
    val = "; ".join(
        f"{k}: {v['infeasible']} of {v['inside']} sampled safe states infeasible "
        f"({100 * v['infeasible_fraction']:.1f} %)"
        for k, v in validity_result.items()
    )
    notes = (
        f"Dtype {record['dtype']}. Parity (CasADi/qpOASES reference from the same barrier): {par}.\n\n"
        f"Evaluation-loop overhead (random inputs on the ceiling task, {overhead_result['episodes']:,} episodes): "
        f"filtered / bare run time = {overhead_result['ratio']:.2f}.\n\n"
        f"is_valid_cbf (10,000 random states): {val}.\n\n"
        f"1D quadrotor ceiling z <= {CEILING} m, uniformly random thrust, {acceptance['episodes']:,} episodes x 250 "
        f"steps at 50 Hz (RK4 at 1 kHz), alpha = 0.5, a_b = {TRUE_BRAKING:.3f} m/s^2; the learned CBF trained on the "
        f"150 % prior with {acceptance['learned']['data_seconds']:,.0f} s of simulated data in "
        f"{acceptance['learned']['train_s']:.0f} s:\n\n" + "\n".join(acc_lines)
    )
    write_markdown_table(args.markdown, "Safety filters", record, columns, rows, notes)
    console.print(f"wrote {args.json} and {args.markdown}", highlight=False)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
