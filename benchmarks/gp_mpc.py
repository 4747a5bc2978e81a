"""GP-MPC against the paper's settings: control performance, constraint satisfaction, solve time and fit time.

Every part runs the paper's setting from its config file (``configs/paper_*``), with a 150% prior, in one run:

- ``solve`` (``paper_cartpole_gp_mpc.yaml``, Fig. 6): one learning round (``learn`` with ``rounds=1``), then
  ``--episodes`` closed-loop episodes of the nonlinear MPC on the 150% prior, of GP-MPC and of the nonlinear MPC on
  the true model, on the same episodes. Every ``act`` is timed (IPOPT's wall time): median and 95th percentile per
  step, and their ratio to the prior's nonlinear MPC (the baseline measured in the same run).
- ``constraint`` (``paper_cartpole_constraint.yaml``, Fig. 7 top): the learning loop of the config (its rounds and
  episodes); violating steps of the (theta, theta_dot) box in every round's evaluation episodes (round 0: the
  prior's MPC), and of the same MPC on the true model on the same episodes.
- ``quadrotor`` (``paper_quadrotor_2d_gp_mpc.yaml``, Figs. 5 and 6): the learning loop of the config; the x-z RMSE
  of every round (round 0: the prior's MPC) and of the same MPC on the true model, on the same episodes.
- ``fit``: GP fit time (hyperparameters on at most ``max_fit_points`` transitions, then the FITC posterior on all)
  for growing data sizes of the cart-pole data, and its ratio to the smallest size.

The original suite publishes no GP-MPC solve time (its users report it as slow and IPOPT as hitting its iteration
limit, issue #95), so there is no figure of it to print beside ours.

Results go to ``benchmarks/results/gp_mpc.json``; a full run (all parts) also writes ``docs/benchmarks/gp_mpc.md``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax
import numpy as np
from machine import print_machine, run_record, write_markdown_table  # benchmarks/machine.py, beside this script
from rich.console import Console

import scg_jax
from scg_algorithms.base import parse_options
from scg_algorithms.evaluation import evaluate
from scg_algorithms.gp_mpc.controller import PATH, Options, evaluation_key, learn, make_gp_mpc
from scg_algorithms.gp_mpc.model import fit_model_error
from scg_algorithms.mpc.nonlinear import make_nonlinear_mpc
from scg_jax.config import load_config, make_from_config
from scg_jax.files import write_json

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_JSON = Path(__file__).resolve().parent / "results" / "gp_mpc.json"
DEFAULT_MARKDOWN = ROOT / "docs" / "benchmarks" / "gp_mpc.md"
CONFIGS = {
    "solve": ROOT / "configs" / "paper_cartpole_gp_mpc.yaml",
    "constraint": ROOT / "configs" / "paper_cartpole_constraint.yaml",
    "quadrotor": ROOT / "configs" / "paper_quadrotor_2d_gp_mpc.yaml",
}
PARTS = ("solve", "constraint", "quadrotor", "fit")
PRIOR_SCALE = 1.5


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parts", nargs="+", default=list(PARTS), choices=PARTS)
    parser.add_argument("--episodes", type=int, default=4, help="timed closed-loop episodes per controller (solve)")
    parser.add_argument("--fit-sizes", type=int, nargs="+", default=[100, 200, 400, 800], help="data sizes to fit")
    parser.add_argument("--json", type=Path, default=DEFAULT_JSON)
    parser.add_argument("--markdown", type=Path, default=None, help=f"generated page [default: {DEFAULT_MARKDOWN}]")
    parser.add_argument("--quick", action="store_true", help="smoke run: solve only, 1 episode, no page")
    parser.add_argument(
        "--render", type=Path, nargs="+", default=None, metavar="JSON",
        help="measure nothing: write the page from the results of earlier runs (e.g. parts run side by side)",
    )  # fmt: skip
    args = parser.parse_args(argv)
    if args.quick:
        args.parts, args.episodes = ["solve"], 1
    return args


def _setting(part: str, **changes):
    """``(env, params, prior, options)`` of a part's config file, ``changes`` applied to its gp_mpc options."""
    cfg = load_config(CONFIGS[part])
    env, params = make_from_config(cfg)
    options = {**dict(cfg.controllers.get("gp_mpc") or {}), **changes}
    return env, params, scg_jax.prior_params(env, params, PRIOR_SCALE), options


def _learn(console, part: str, env, params, prior, options):
    start = time.perf_counter()

    def report(entry):
        console.print(
            f"  round {entry['round']}: {entry['data_seconds']:.0f} s of data, RMSE {entry['rmse']:.3f}, "
            f"violating steps/episode {entry['constraint_violation_steps']:.2f}, fit {entry['fit_s']:.1f} s",
            highlight=False,
        )

    result = learn(env, params, prior, options, progress=report)
    console.print(f"{part}: learned in {time.perf_counter() - start:.0f} s", highlight=False)
    return result


def solve_part(console) -> list[list]:
    env, params, prior, options = _setting("solve", rounds=1, eval_episodes=1)
    result = _learn(console, "solve", env, params, prior, options)
    key = jax.random.key(1)
    horizon = parse_options(Options, options, PATH).horizon
    controllers = {
        "nonlinear MPC (150% prior)": make_nonlinear_mpc(env, prior, {"horizon": horizon}),
        "GP-MPC (150% prior + GP, 1 round)": make_gp_mpc(env, prior, options, result.posterior),
        "nonlinear MPC (true model)": make_nonlinear_mpc(env, params, {"horizon": horizon}),
    }
    measured = {}
    for name, controller in controllers.items():
        run = evaluate(env, params, controller, key, ARGS.episodes, measure_time=True)
        measured[name] = (run.summary["compute_time_per_step_s"], run.timing["controller_p95_s"], run.summary["rmse"])
    base_s = measured["nonlinear MPC (150% prior)"][0]
    rows = []
    for name, (step_s, p95_s, rmse) in measured.items():
        rows.append([name, step_s * 1e3, p95_s * 1e3, step_s / base_s, rmse])
        console.print(f"  {name:<36} {step_s * 1e3:7.2f} ms/step (p95 {p95_s * 1e3:7.2f}) x{step_s / base_s:5.2f} "
                      f"RMSE {rmse:.3f}")  # fmt: skip
    ARGS.cartpole_data = result.data
    return rows


def _true_model_run(env, params, options):
    """The same MPC formulation on the true model, no GP, on ``learn``'s evaluation episodes."""
    opts = parse_options(Options, options, PATH)
    controller = make_gp_mpc(env, params, options, None)
    return evaluate(env, params, controller, evaluation_key(opts.seed), opts.eval_episodes, measure_time=True)


def constraint_part(console) -> list[list]:
    env, params, prior, options = _setting("constraint")
    result = _learn(console, "constraint", env, params, prior, options)
    episodes = parse_options(Options, options, PATH).eval_episodes
    steps = env.num_steps
    rows = []
    for entry in result.history:
        name = "MPC on the 150% prior (round 0)" if entry["round"] == 0 else f"GP-MPC round {entry['round']}"
        per_episode = entry["constraint_violation_steps"]
        rows.append([name, entry["data_seconds"], per_episode * episodes, per_episode, per_episode / steps,
                     entry["rmse"]])  # fmt: skip
    true_run = _true_model_run(env, params, options)
    per_episode = true_run.summary["constraint_violation_steps"]
    rows.append(["MPC on the true model", 0.0, per_episode * episodes, per_episode, per_episode / steps,
                 true_run.summary["rmse"]])  # fmt: skip
    for row in rows:
        console.print(f"  {row[0]:<32} {row[2]:5.0f} violating steps in {episodes} episodes, RMSE {row[5]:.3f}")
    return rows


def quadrotor_part(console) -> list[list]:
    env, params, prior, options = _setting("quadrotor")
    result = _learn(console, "quadrotor", env, params, prior, options)
    true_run = _true_model_run(env, params, options)
    true_rmse = true_run.summary["rmse"]
    prior_rmse = result.history[0]["rmse"]
    rows = []
    for entry in result.history:
        name = "MPC on the 150% prior (round 0)" if entry["round"] == 0 else f"GP-MPC round {entry['round']}"
        rows.append([name, entry["data_seconds"], entry["rmse"], entry["rmse_std"], entry["rmse"] / true_rmse,
                     1.0 - entry["rmse"] / prior_rmse, entry["failure_rate"],
                     entry["compute_time_per_step_s"] * 1e3])  # fmt: skip
    rows.append(["MPC on the true model", 0.0, true_rmse, true_run.summary["rmse_std"], 1.0,
                 1.0 - true_rmse / prior_rmse, true_run.summary["failure_rate"],
                 true_run.summary["compute_time_per_step_s"] * 1e3])  # fmt: skip
    for row in rows:
        console.print(f"  {row[0]:<32} x-z RMSE {row[2]:.3f} (x{row[4]:.2f} true model, {100 * row[5]:.0f}% better "
                      f"than the prior), failures {row[6]:.2f}, {row[7]:.1f} ms/step")  # fmt: skip
    return rows


def fit_part(console) -> list[list]:
    inputs, targets = getattr(ARGS, "cartpole_data", None) or _cartpole_data(console)
    rng = np.random.default_rng(0)
    rows, first = [], None
    for size in ARGS.fit_sizes:
        index = rng.choice(len(inputs), size, replace=size > len(inputs))
        z = inputs[index] + 1e-6 * rng.standard_normal((size, inputs.shape[1]))  # resampled rows stay distinct
        start = time.perf_counter()
        fit_model_error(z, targets[index], num_inducing=30, key=jax.random.key(size))
        fit_s = time.perf_counter() - start
        first = first or fit_s
        rows.append([size, fit_s, fit_s / first])
        console.print(f"  fit on {size:5d} transitions: {fit_s:6.2f} s (x{fit_s / first:.2f})")
    return rows


def _cartpole_data(console):
    env, params, prior, options = _setting("solve", rounds=1, eval_episodes=1)
    return _learn(console, "fit data", env, params, prior, options).data


def _table(columns, rows) -> str:
    def cell(value):
        return f"{value:.3g}" if isinstance(value, float) else str(value)

    lines = ["| " + " | ".join(columns) + " |", "|" + "|".join("---" for _ in columns) + "|"]
    return "\n".join(lines + ["| " + " | ".join(cell(v) for v in row) + " |" for row in rows])


CONSTRAINT_COLUMNS = ["controller", "data (s)", "violating steps (all episodes)", "per episode", "fraction of time",
                      "RMSE"]  # fmt: skip
QUADROTOR_COLUMNS = ["controller", "data (s)", "x-z RMSE", "std", "/ true model", "better than prior",
                     "failure rate", "ms per step"]  # fmt: skip


def notes(results: dict) -> str:
    parts = []
    if "constraint" in results:
        parts.append(
            "## Constraint satisfaction (Fig. 7 top)\n\n`configs/paper_cartpole_constraint.yaml`: (theta, theta_dot) "
            "in [-0.2, 0.2]^2, 10 Hz, 50-step episodes that run on past a violation, prob 0.99, 150% prior; every "
            "row on the same seeded evaluation episodes (paper: 0.5 violating steps per episode at epoch 0, 0 after)."
            "\n\n" + _table(CONSTRAINT_COLUMNS, results["constraint"])
        )
    if "quadrotor" in results:
        parts.append(
            "## 2D quadrotor circle (Figs. 5 and 6)\n\n`configs/paper_quadrotor_2d_gp_mpc.yaml`: a circle of 1 m "
            "diameter in the x-z plane from the origin, 10 Hz, horizon 15, Q = diag(2, 1, 2, 1, 1, 1), R = diag(1, 1), "
            "prob 0.99, 150% prior; RMSE over x and z, every row on the same seeded evaluation episodes (paper: "
            "0.259 at epoch 0, 0.112 after 5.1 s of data, 0.08-0.116 after).\n\n"
            + _table(QUADROTOR_COLUMNS, results["quadrotor"])
        )
    if "fit" in results:
        parts.append(
            "## GP fit time\n\nHyperparameters on at most 200 transitions, FITC posterior on all (cart-pole data):\n\n"
            + "\n".join(f"- {n} transitions: {t:.2f} s (x{r:.2f})" for n, t, r in results["fit"])
        )
    parts.append(
        "The original suite publishes no GP-MPC solve time; its users report its GP-MPC as slow and its IPOPT as "
        "hitting the iteration limit (issue #95)."
    )
    return "\n\n".join(parts)


ARGS = argparse.Namespace()


def main(argv=None) -> int:
    global ARGS
    ARGS = parse_args(argv)
    console = Console()
    if ARGS.render:
        return render(ARGS.render, ARGS.markdown or DEFAULT_MARKDOWN)
    record = run_record("gp_mpc")
    print_machine(console, record)
    functions = {"solve": solve_part, "constraint": constraint_part, "quadrotor": quadrotor_part, "fit": fit_part}
    results = {}
    for part in ARGS.parts:
        console.print(f"[bold]{part}[/bold]")
        results[part] = functions[part](console)
        args = {k: v for k, v in vars(ARGS).items() if k != "cartpole_data"} | {"json": str(ARGS.json)}
        # Written after every part, so a long run keeps what it measured.
        write_json(ARGS.json, {**record, **results, "args": args | {"markdown": str(ARGS.markdown)}})
    full = set(ARGS.parts) == set(PARTS)
    markdown = ARGS.markdown or (DEFAULT_MARKDOWN if full and not ARGS.quick else None)
    if markdown is not None:
        _write_page(markdown, record, results)
    return 0


def _write_page(markdown, record, results) -> None:
    write_markdown_table(
        markdown, "GP-MPC: cost and the paper's settings", record,
        ["cart-pole (Fig. 6 setting), 4 episodes", "ms per step (median)", "p95 ms", "median / prior NMPC", "RMSE"],
        results.get("solve", []), notes=notes(results),
    )  # fmt: skip


def render(paths, markdown) -> int:
    """The page from result files of earlier runs; the machine line is the first file's."""
    import json

    loaded = [json.loads(Path(path).read_text()) for path in paths]
    results = {part: data[part] for data in loaded for part in PARTS if part in data}
    _write_page(markdown, loaded[0], results)
    return 0


if __name__ == "__main__":
    sys.exit(main())
