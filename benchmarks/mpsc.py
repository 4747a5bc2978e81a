"""Model predictive safety filters: calls per second of the batched linear MPSC (shared-factorisation ADMM, qpax) at
1, 1,024 and 16,384 copies, the CasADi filters' time per call (linear qpOASES, nonlinear IPOPT), and the closed-loop
acceptance experiment at scale (``mpsc_experiment``: episodes with any violation, unfiltered vs filtered, true model
and 150% prior).

Each batch size is timed on random cart-pole states after one compile call; 16,384 copies runs only while the
time cap allows (``--cap-s``). Writes ``docs/benchmarks/mpsc.md``. Run: ``python benchmarks/mpsc.py``.
"""

from __future__ import annotations

import argparse
import pathlib
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from machine import run_record, write_markdown_table  # noqa: E402

from scg_algorithms.safety_filters import mpsc_experiment as E  # noqa: E402
from scg_algorithms.safety_filters.mpsc_linear import make_linear_mpsc, make_linear_mpsc_casadi  # noqa: E402
from scg_algorithms.safety_filters.mpsc_nonlinear import make_nonlinear_mpsc  # noqa: E402
from scg_jax.env import prior_params  # noqa: E402

OPTIONS = {"n_samples": 300, "sample_half_width": list(E.SAMPLE_HALF_WIDTH)}


def _states(count, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.uniform([-0.4, -1.0, -0.1, -0.5], [0.45, 1.0, 0.1, 0.5], (count, 4)).astype(np.float32)
    return jnp.asarray(x), jnp.asarray(rng.uniform(-10, 10, (count, 1)).astype(np.float32))


def time_batched(f, count, repeats=3):
    x, u = _states(count)
    state = jax.vmap(f.reset)(jnp.arange(count))
    run = jax.jit(jax.vmap(f.certify, in_axes=(0, 0, None, 0)))
    jax.block_until_ready(run(x, u, f.params, state))
    tick = time.perf_counter()
    for _ in range(repeats):
        jax.block_until_ready(run(x, u, f.params, state))
    return count * repeats / (time.perf_counter() - tick)


def time_host(f, count=20):
    x, u = _states(count)
    state = f.reset(None)
    tick = time.perf_counter()
    for xi, ui in zip(np.asarray(x, np.float64), np.asarray(u, np.float64), strict=True):
        f.certify(xi, ui, None, state)
    return (time.perf_counter() - tick) / count


def closed_loop_table(episodes: int) -> str:
    """The acceptance experiment as a Markdown table (one row per variant)."""
    env = E.make_env()
    params = env.default_params
    controller = E.setpoint_lqr(env, params)
    key = jax.random.PRNGKey(0)
    prior = prior_params(env, params, 1.5)
    variants = [
        ("unfiltered", None, None),
        ("linear_mpsc, true model", params, OPTIONS),
        ("linear_mpsc, true model, tightening none", params, {**OPTIONS, "tightening": "none"}),
        ("linear_mpsc, 150% prior, reachable tightening", prior, OPTIONS),
        ("linear_mpsc, 150% prior, tightening none", prior, {**OPTIONS, "tightening": "none"}),
        (
            "linear_mpsc, 150% prior, none + 0.03 m margin",
            prior,
            {**OPTIONS, "tightening": "none", "constraint_margin": 0.03},
        ),
    ]
    lines = [
        f"Closed loop ({episodes} episodes of {env.num_steps} steps, LQR towards x = {E.SETPOINT} m, bound "
        f"|x| <= {E.POSITION_BOUND} m):",
        "",
        "| variant | episodes with a violation | violating steps | feasible steps | max x (m) |",
        "|---|---|---|---|---|",
    ]
    for name, model, options in variants:
        try:
            f = None if model is None else make_linear_mpsc(env, model, options)
        except ValueError as error:
            lines.append(f"| {name} | build refused: {str(error).split(';')[0]} | | | |")
            continue
        r = E.closed_loop(env, params, controller, f, key, episodes)
        row = (r["violating"].any(axis=1).mean(), r["violating"].mean(), r["feasible"].mean(), r["x"][:, :, 0].max())
        lines.append(f"| {name} | {row[0]:.1%} | {row[1]:.2%} | {row[2]:.1%} | {row[3]:.3f} |")
        print(lines[-1], flush=True)
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--cap-s", type=float, default=120.0, help="skip 16,384 copies once this much time is spent")
    parser.add_argument("--out", default="docs/benchmarks/mpsc.md")
    parser.add_argument("--episodes", type=int, default=256, help="closed-loop episodes per variant")
    args = parser.parse_args(argv)
    record = run_record("mpsc")
    env = E.make_env()
    params = env.default_params
    start = time.perf_counter()
    rows = []
    filters = {
        "linear_mpsc ADMM 200 it": make_linear_mpsc(env, params, {**OPTIONS, "admm_iterations": 200}),
        "linear_mpsc ADMM 500 it (default)": make_linear_mpsc(env, params, OPTIONS),
        "linear_mpsc qpax 40 it": make_linear_mpsc(env, params, {**OPTIONS, "solver": "qpax"}),
    }
    for name, f in filters.items():
        rates = []
        for count in (1, 1024, 16384):
            if count == 16384 and time.perf_counter() - start > args.cap_s:
                rates.append(None)
                continue
            rates.append(time_batched(f, count))
            print(name, count, rates[-1], flush=True)
        rows.append([name, *rates, None])
    linear_casadi = make_linear_mpsc_casadi(env, params, OPTIONS)
    rows.append(["linear_mpsc_casadi (qpOASES)", None, None, None, 1e3 * time_host(linear_casadi)])
    nonlinear = make_nonlinear_mpsc(env, params, OPTIONS)
    rows.append(["nonlinear_mpsc (IPOPT, RK4 model)", None, None, None, 1e3 * time_host(nonlinear, 10)])
    for row in rows:
        print(row, flush=True)
    notes = (
        "Cart-pole at 15 Hz, horizon 20 (20 decisions, 80 one-sided rows), float32, random states inside the position "
        "box and random proposed inputs. Batched columns: certify calls per second (one call per copy) of the "
        "jit-ed, vmap-ed filter; empty at 16,384 where the time cap was reached. Last column: host filters, ms per "
        "call, one copy. The machine is shared: compare the rows of one run only."
    )
    notes += "\n\n" + closed_loop_table(args.episodes)
    columns = ["filter", "calls/s, 1 copy", "calls/s, 1,024", "calls/s, 16,384", "ms/call (host)"]
    write_markdown_table(args.out, "Model predictive safety filters", record, columns, rows, notes)


if __name__ == "__main__":
    main()
