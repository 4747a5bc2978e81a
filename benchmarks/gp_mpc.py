"""Cost of GP-MPC: solve time per control step against the nonlinear MPC, and GP fit time against data size.

For each system (the cart-pole in the paper's data-efficiency setting, 10 Hz, and the 2D quadrotor tracking a
circle, 10 Hz), in one run:

1. One learning round (``scg_algorithms.gp_mpc.controller.learn`` with ``rounds=1``): LQR on the 150% prior with
   exploration noise collects ``--train-episodes`` episodes, and the GP is fit (FITC, ``--inducing`` points).
2. ``--episodes`` closed-loop episodes of the nonlinear MPC on the 150% prior and of GP-MPC, through the harness,
   on the same episodes. Every ``act`` is timed (IPOPT's wall time): median and 95th percentile per step, and their
   ratio GP-MPC / nonlinear MPC (the baseline measured in the same run). The original suite's GP-MPC is reported by
   its users as slow and partly broken; its figure is not known well enough to print.
3. GP fit time (hyperparameters on at most ``max_fit_points`` transitions, then the FITC posterior on all of them)
   for growing data sizes, and its ratio to the smallest size.

Results go to ``benchmarks/results/gp_mpc.json``; a full run also writes ``docs/benchmarks/gp_mpc.md``.
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
from scg_algorithms.evaluation import evaluate
from scg_algorithms.gp_mpc.controller import learn, make_gp_mpc
from scg_algorithms.gp_mpc.model import fit_model_error
from scg_algorithms.mpc.nonlinear import make_nonlinear_mpc
from scg_jax.files import write_json

DEFAULT_JSON = Path(__file__).resolve().parent / "results" / "gp_mpc.json"
DEFAULT_MARKDOWN = Path(__file__).resolve().parents[1] / "docs" / "benchmarks" / "gp_mpc.md"
SETTINGS = {
    "cartpole": dict(
        system="cartpole", task="stabilization", ctrl_freq=10, physics_freq=1000, episode_len_sec=5,
        Q=[10, 1, 10, 1], R=[0.1],
        init_state={"type": "uniform", "low": [-0.3, -0.1, -0.1, -0.1], "high": [0.3, 0.1, 0.1, 0.1]},
    ),
    "quadrotor_2d": dict(
        system="quadrotor_2d", task="tracking", ctrl_freq=10, physics_freq=1000, episode_len_sec=6,
        trajectory={"shape": "circle", "plane": "xz", "scale": 1.0, "offset": [0.0, 1.0]},
    ),
}  # fmt: skip


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    # The 2D quadrotor's setting is not validated yet (its episodes crash at 10 Hz from the default initial states),
    # so it runs only when asked for.
    parser.add_argument("--systems", nargs="+", default=["cartpole"], choices=list(SETTINGS))
    parser.add_argument("--horizon", type=int, default=20, help="MPC horizon, control steps")
    parser.add_argument("--inducing", type=int, default=30, help="inducing points of the GP")
    parser.add_argument("--train-episodes", type=int, default=4, help="episodes of data for the GP")
    parser.add_argument("--episodes", type=int, default=4, help="timed closed-loop episodes per controller")
    parser.add_argument("--fit-sizes", type=int, nargs="+", default=[100, 200, 400, 800], help="data sizes to fit")
    parser.add_argument("--json", type=Path, default=DEFAULT_JSON)
    parser.add_argument("--markdown", type=Path, default=None, help=f"generated table [default: {DEFAULT_MARKDOWN}]")
    parser.add_argument("--quick", action="store_true", help="smoke run: cart-pole, 1 episode, sizes 100 and 200")
    args = parser.parse_args(argv)
    if args.quick:
        args.systems, args.episodes, args.fit_sizes = ["cartpole"], 1, [100, 200]
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    console = Console()
    record = run_record("gp_mpc")
    print_machine(console, record)
    rows, fit_rows = [], []
    for system in args.systems:
        settings = dict(SETTINGS[system])
        env = scg_jax.make(settings.pop("system"), settings.pop("task"), **settings)
        params = env.default_params
        prior = scg_jax.prior_params(env, params, 1.5)
        options = {"horizon": args.horizon, "num_inducing": args.inducing, "rounds": 1,
                   "train_episodes": args.train_episodes, "eval_episodes": 1}  # fmt: skip
        start = time.perf_counter()
        result = learn(env, params, prior, options)
        console.print(f"{system}: learned in {time.perf_counter() - start:.1f} s", highlight=False)
        key = jax.random.key(1)
        controllers = {
            "nonlinear MPC (150% prior)": make_nonlinear_mpc(env, prior, {"horizon": args.horizon}),
            "GP-MPC (150% prior + GP)": make_gp_mpc(env, prior, options, result.posterior),
        }
        times = {}
        for name, controller in controllers.items():
            evaluation = evaluate(env, params, controller, key, args.episodes, measure_time=True)
            times[name] = (
                evaluation.summary["compute_time_per_step_s"],
                evaluation.timing["controller_p95_s"],
                evaluation.summary["rmse"],
            )
        base_s = times["nonlinear MPC (150% prior)"][0]
        for name, (step_s, p95_s, rmse) in times.items():
            rows.append([system, name, step_s * 1e3, p95_s * 1e3, step_s / base_s, rmse])
            console.print(
                f"  {name:<28} {step_s * 1e3:7.2f} ms/step (p95 {p95_s * 1e3:7.2f})  x{step_s / base_s:5.2f}  "
                f"RMSE {rmse:.3f}"
            )
        inputs, targets = result.data
        rng = np.random.default_rng(0)
        first = None
        for size in args.fit_sizes:
            index = rng.choice(len(inputs), size, replace=size > len(inputs))
            z = inputs[index] + 1e-6 * rng.standard_normal((size, inputs.shape[1]))  # resampled rows stay distinct
            start = time.perf_counter()
            fit_model_error(z, targets[index], num_inducing=args.inducing, key=jax.random.key(size))
            fit_s = time.perf_counter() - start
            first = first or fit_s
            fit_rows.append([system, size, fit_s, fit_s / first])
            console.print(f"  fit on {size:5d} transitions: {fit_s:6.2f} s (x{fit_s / first:.2f})")
    write_json(args.json, {**record, "solve": rows, "fit": fit_rows, "args": vars(args) | {"json": str(args.json)}})
    markdown = args.markdown or (None if args.quick else DEFAULT_MARKDOWN)
    if markdown is not None:
        write_markdown_table(
            markdown, "GP-MPC cost", record,
            ["system", "controller", "ms per step (median)", "p95 ms", "median / nonlinear MPC", "RMSE"], rows,
            notes="GP fit time (hyperparameters on at most 200 transitions, FITC posterior on all):\n\n"
            + "\n".join(f"- {s}: {n} transitions, {t:.2f} s (x{r:.2f})" for s, n, t, r in fit_rows),
        )  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
