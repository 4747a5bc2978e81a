"""Safe RL on the paper's constraint task (Fig 7 top): vanilla PPO, safety-layer PPO and PPO-Lagrangian.

For each learner, its ``training.<algo>`` section of ``--config`` (default
``configs/paper_cartpole_constraint_rl.yaml``: about 50,000 env steps = 1,000 s of simulated data at 50 Hz;
``--budget-scale`` multiplies it) is trained on ``--seeds`` seeds at once (``jax.vmap`` over keys; safety-layer
PPO's pretraining runs in ``init``, timed apart). Then each seed's deterministic policy is evaluated by
``scg_algorithms.evaluation.evaluate`` on ``--eval-episodes`` episodes of the same env with
``done_on_out_of_bounds: false`` (every episode 250 steps, as the paper evaluated), giving the fraction of steps in
violation and the RMSE. Reported per learner: median over seeds of the evaluation's violating fraction, mean RMSE
and its ratio to PPO's, the violating fraction of the training rollouts over the last 20 % of iterations,
PPO-Lagrangian's final multiplier, the safety layer's held-out MSE, and env steps/s of the training iterations
(compile excluded; the learners' compiled runs repeated alternately, the fastest kept) next to PPO's in the same
run. Writes ``benchmarks/results/safe_rl[_xSCALE].json`` and ``docs/benchmarks/safe_rl[_xSCALE].md``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from machine import run_record, write_markdown_table  # benchmarks/machine.py, beside this script

from scg_algorithms.evaluation import evaluate
from scg_algorithms.rl.policy import algorithm_module, policy_controller
from scg_jax.config import load_config, make_from_config
from scg_jax.files import write_json

ROOT = Path(__file__).resolve().parent.parent
ALGOS = ("ppo", "safe_ppo", "ppo_lagrangian")


def _train(learner, params, keys):
    """(init seconds with compile, ``timed()`` -> seconds of the compiled iterations on the same initial states,
    final runner states, metrics (S, I))."""
    start = time.perf_counter()
    initial = jax.block_until_ready(jax.jit(jax.vmap(learner.init, in_axes=(0, None)))(keys, params))
    init_s = time.perf_counter() - start

    def run(runners):
        step = lambda r, _: learner.update(r, params)  # noqa: E731
        return jax.vmap(lambda r: jax.lax.scan(step, r, None, learner.num_iterations))(runners)

    compiled = jax.jit(run).lower(initial).compile()

    def timed():
        start = time.perf_counter()
        jax.block_until_ready(compiled(initial))
        return time.perf_counter() - start

    runners, metrics = jax.block_until_ready(compiled(initial))
    return init_s, timed, runners, metrics


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", type=Path, default=ROOT / "configs/paper_cartpole_constraint_rl.yaml")
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--algos", nargs="+", default=list(ALGOS), choices=ALGOS)
    parser.add_argument("--budget-scale", type=int, default=1, help="multiply every total_env_steps by this")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per learner, alternating (min kept)")
    parser.add_argument("--json", type=Path, help="default benchmarks/results/safe_rl[_xSCALE].json")
    parser.add_argument("--markdown", type=Path, help="default docs/benchmarks/safe_rl[_xSCALE].md")
    args = parser.parse_args(argv)
    suffix = "" if args.budget_scale == 1 else f"_x{args.budget_scale}"
    args.json = args.json or ROOT / f"benchmarks/results/safe_rl{suffix}.json"
    args.markdown = args.markdown or ROOT / f"docs/benchmarks/safe_rl{suffix}.md"

    cfg = load_config(args.config)
    env, params = make_from_config(cfg)
    eval_env, eval_params = make_from_config(load_config(args.config, ["env.done_on_out_of_bounds=false"]))
    keys = jnp.stack([jax.random.key(seed) for seed in range(args.seeds)])
    results, timers = {}, {}
    for algo in args.algos:
        options = dict(cfg.training.get(algo) or {})
        options["total_env_steps"] = options.get("total_env_steps", 51200) * args.budget_scale
        learner = algorithm_module(algo, "make_learner")(options, env)
        print(f"{algo}: {learner.num_iterations} iterations x {learner.steps_per_iteration} steps, {args.seeds} seeds",
              flush=True)  # fmt: skip
        init_s, timers[algo], runners, metrics = _train(learner, params, keys)
        fractions, rmses = [], []
        for seed in range(args.seeds):
            runner = jax.tree.map(lambda x, s=seed: x[s], runners)
            controller = policy_controller(eval_env, eval_params, learner, learner.policy_params(runner))
            evaluation = evaluate(eval_env, eval_params, controller, jax.random.key(1000 + seed), args.eval_episodes,
                                  measure_time=False)  # fmt: skip
            fractions.append(evaluation.summary["constraint_violation_steps"] / evaluation.summary["length"])
            rmses.append(evaluation.summary["rmse"])
        tail = max(1, learner.num_iterations // 5)
        train_fraction = np.asarray(metrics["violation_fraction"])[:, -tail:].mean(axis=1)
        record = {
            "eval_violation_fraction": [float(f) for f in fractions],
            "eval_violation_fraction_median": float(np.median(fractions)),
            "eval_rmse": [float(r) for r in rmses],
            "eval_rmse_mean": float(np.mean(rmses)),
            "train_violation_fraction_last20": [float(f) for f in train_fraction],
            "train_violation_fraction_last20_median": float(np.median(train_fraction)),
            "simulated_seconds": learner.num_iterations * learner.steps_per_iteration / env.ctrl_freq,
            "train_env_steps": args.seeds * learner.num_iterations * learner.steps_per_iteration,
            "init_s": init_s,
        }
        for name in ("lagrange_multiplier", "constraint_model_mse", "constraint_model_baseline_mse"):
            if name in metrics:
                record[name] = [float(v) for v in np.asarray(metrics[name])[:, -1]]
        results[algo] = record
        print(algo, record, flush=True)
    # Speed: the compiled iterations of every learner again, alternating, so the machine's load is shared alike.
    seconds = {algo: [] for algo in results}
    for _ in range(args.repeats):
        for algo in results:
            seconds[algo].append(timers[algo]())
    for algo, record in results.items():
        record["train_steps_per_s"] = record["train_env_steps"] / min(seconds[algo])
    base = results.get("ppo")
    for record in results.values():
        if base is not None:
            record["rmse_over_ppo"] = record["eval_rmse_mean"] / base["eval_rmse_mean"]
            record["speed_over_ppo"] = record["train_steps_per_s"] / base["train_steps_per_s"]
    out = {**run_record("safe_rl"), "config": str(args.config), "seeds": args.seeds,
           "budget_scale": args.budget_scale, "results": results}  # fmt: skip
    write_json(args.json, out)
    rows = [
        [algo, r["simulated_seconds"], r["eval_violation_fraction_median"], r["train_violation_fraction_last20_median"],
         r["eval_rmse_mean"], r.get("rmse_over_ppo"), r["train_steps_per_s"], r.get("speed_over_ppo"),
         ", ".join(f"{v:.3g}" for v in r.get("lagrange_multiplier", r.get("constraint_model_mse", [])))]
        for algo, r in results.items()
    ]  # fmt: skip
    notes = (
        "Evaluation: deterministic policy, done_on_out_of_bounds false, "
        f"{args.eval_episodes} episodes per seed; violating fraction = median over {args.seeds} seeds of steps in "
        "violation / 250. Training fraction: rollouts (with exploration noise) over the last 20 % of iterations. "
        "Last column: PPO-Lagrangian's final multiplier per seed, or the safety layer's held-out MSE per seed. "
        "Steps/s: training iterations (compile excluded, safety-layer pretraining excluded), all seeds together."
    )
    write_markdown_table(
        args.markdown, "Safe RL on the constraint task (Fig 7 top)", out,
        ["learner", "sim. s", "eval viol. frac. (median)", "train viol. frac. last 20%", "RMSE", "RMSE / PPO",
         "train steps/s", "speed / PPO", "lambda or layer MSE"],
        rows, notes=notes,
    )  # fmt: skip
    print(f"wrote {args.json} and {args.markdown}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
