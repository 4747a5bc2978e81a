"""Training speed of the JAX learners: throughput next to the raw env, and time to an LQR-level policy.

Two measurements, each against a baseline measured in the same run:

1. **Throughput** (``--batches``, default 1,024 and 4,096 copies): env steps per second of PPO's and SAC's
   training iterations (``Learner.update``, jitted and chained with ``lax.fori_loop``; compile excluded), next to
   the raw env's steps per second for the same copies (``scg_jax.rollout.make_rollout`` with auto-reset and a
   constant action: the bare cost of simulating what the learner consumes). The ratio is the share of the env's
   speed the learner keeps.
2. **Time to threshold** (``--threshold``): wall time from the start of training (compile included, evaluation
   excluded) until the deterministic policy's stabilisation RMSE, evaluated on ``--eval-episodes`` episodes by
   ``scg_algorithms.evaluation.evaluate``, is within ``--rmse-factor`` (1.5) times LQR's on the same episodes, with no
   crash. Our PPO is trained in chunks of iterations and evaluated after each; brax's PPO (through
   ``scg_jax.adapters.brax``) with the same env, copies, rollout length, epochs, minibatches, learning rate and
   networks, evaluated in its ``policy_params_fn`` callback at ``--brax-evals`` points. The ratio brax / ours of
   time to threshold is printed (> 1: ours is faster).

3. **Run split** (``--split``): where the wall time of one whole training run at the config's settings goes:
   collection (env and policy, ``Learner.collect``), update (losses, gradients, optimiser) and everything else
   (host syncs, logging, checkpoints, final files: the run's wall time beyond its iterations' compute), with
   compilation reported apart. The run's saved policy is then evaluated against LQR: this is the check that the
   config's *default* budget learns (no crash and an RMSE within ``DEFAULT_BUDGET_RMSE_FACTOR`` (4) times LQR's
   on ``--eval-episodes`` episodes, for PPO and SAC); tests/test_learning.py checks learning at a small budget only.

The env and the hyperparameters are those of the config (default ``configs/cartpole_stabilization.yaml``, its
``training.ppo`` section). Results go to ``benchmarks/results/train.json``.

Run ``python benchmarks/train.py --help``; see benchmarks/README.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import sys
import time
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
from machine import (  # benchmarks/machine.py, beside this script
    load_average,
    median_seconds,
    print_machine,
    run_record,
    write_markdown_table,
)
from rich.console import Console
from rich.table import Table

from scg_algorithms.base import JaxController, parse_options
from scg_algorithms.evaluation import evaluate, make_evaluator
from scg_algorithms.lqr import make_lqr
from scg_algorithms.rl.envs import policy_action_to_input
from scg_algorithms.rl.policy import algorithm_module
from scg_jax.config import load_config, make_from_config
from scg_jax.files import write_json
from scg_jax.rollout import make_rollout

# Goals of the issue (printed next to the measurement; never an error exit).
GOAL_CARTPOLE_S = 60.0
GOAL_QUADROTOR_2D_S = 600.0


def _config(cfg, algo: str, **changes):
    config_class = algorithm_module(algo, "Config")
    options = dict(cfg.training.get(algo, {}))
    options.update(changes)
    return parse_options(config_class, options, f"training.{algo}")


def _policy_evaluator(env, params, episodes: int, make_policy, name: str, action_scale: float = 1.0):
    """``evaluate_fn(policy_params, key) -> Evaluation`` of the deterministic policy ``make_policy(policy_params)``
    (actions in [-1, 1], times ``action_scale``); compiled once, so evaluating after every chunk of training costs
    no compile."""
    physics = params.physics

    def build(policy_params):
        policy = make_policy(policy_params)

        def act(ctrl_state, obs, step, reference):
            return policy_action_to_input(env, policy(obs), physics, action_scale), ctrl_state

        return JaxController(name, lambda key, reference: (), act)

    build.__name__ = name
    evaluate_fn = make_evaluator(env, build, episodes)
    return lambda policy_params, key: evaluate_fn(policy_params, key, params)


# --------------------------------------------------------------------------------------------- throughput
def _update_runner(learner, iterations: int):
    def run(state, params):
        return jax.lax.fori_loop(0, iterations, lambda i, s: learner.update(s, params)[0], state)

    return jax.jit(run)


def throughput(env, params, cfg, algo: str, batch: int, iterations: int, repeats: int) -> dict:
    """Training env steps/s of ``algo`` at ``batch`` copies, and the raw env's steps/s for the same steps."""
    changes = {"num_envs": batch}
    if algo == "ppo":
        base = _config(cfg, "ppo")
        changes["total_env_steps"] = batch * base.rollout_length * iterations
        # Keep the minibatch size of the config (the batch grows with the copies).
        minibatch = base.batch_size // base.num_minibatches
        changes["num_minibatches"] = max(1, batch * base.rollout_length // minibatch)
    config = _config(cfg, algo, **changes)
    learner = algorithm_module(algo, "make_learner")(config, env)
    state = learner.init(jax.random.key(0), params)
    update = jax.jit(learner.update)
    # Past SAC's random-action warm-up (iterations without gradient steps), so the timed iterations learn.
    for _ in range(max(1, getattr(config, "warmup_iterations", 0))):
        state, _ = update(state, params)
    steps_per_iteration = learner.steps_per_iteration
    run = _update_runner(learner, iterations)
    start = time.perf_counter()
    compiled = run.lower(state, params).compile()
    compile_s = time.perf_counter() - start
    train_rate = steps_per_iteration * iterations / median_seconds(lambda: compiled(state, params), repeats)

    # The raw env for the same number of steps: constant (zero normalised) action, auto-reset.
    num_steps = max(1, steps_per_iteration * iterations // batch)
    zero = jnp.zeros(env.nu)
    rollout = make_rollout(
        env, lambda obs, s, p, k: env.input_to_action(policy_action_to_input(env, zero, p.physics), p), batch, num_steps
    )
    env_rate = batch * num_steps / median_seconds(lambda: rollout(jax.random.key(1), params), repeats)
    return {
        "algo": algo,
        "batch": batch,
        "steps_per_iteration": steps_per_iteration,
        "iterations": iterations,
        "compile_s": compile_s,
        "train_steps_per_s": train_rate,
        "env_steps_per_s": env_rate,
        "train_over_env": train_rate / env_rate,
    }


# A whole run at the config's default budget has learned when its deterministic policy never crashes and its RMSE is
# within this times LQR's (true model) on the same episodes; the untrained policy falls or drifts to over 10x.
DEFAULT_BUDGET_RMSE_FACTOR = 4.0


def run_split(env, params, cfg, algo: str, repeats: int, episodes: int = 32) -> dict:
    """Where the wall time of one whole training run goes, at the config's own settings (copies, budget).

    One iteration is timed in two parts: the data collection alone (``Learner.collect``: the env and the acting
    policy) and the rest of the iteration, the update (losses, gradients, optimiser; GAE and replay for the
    learners that have them), both jitted and compile excluded. Then the whole run is trained by
    ``scg_algorithms.rl.training.run_training`` (chunks of iterations, CSV rows, checkpoints, the policy file and
    the learning curve), and what its wall time (compile excluded) holds beyond its iterations' compute is
    "everything else": host syncs, logging, checkpoints and the final files. SAC's warm-up iterations (random
    actions, no gradient step) count as collection only.

    The saved policy is evaluated on ``episodes`` episodes (key 123) next to LQR on the same ones: ``learned`` says
    whether the default budget learned (no crash, whole episodes, RMSE within ``DEFAULT_BUDGET_RMSE_FACTOR`` x LQR's).
    """
    import tempfile

    from scg_algorithms.rl.policy import load_policy
    from scg_algorithms.rl.training import run_training

    config = _config(cfg, algo)
    learner = algorithm_module(algo, "make_learner")(config, env)
    eval_key = jax.random.key(123)
    with tempfile.TemporaryDirectory(prefix="scg-jax-train-split-") as out_dir:
        result = run_training(learner, env, params, jax.random.key(0), out_dir)
        final = evaluate(env, params, load_policy(out_dir, env, params), eval_key, episodes, measure_time=False)
    lqr = evaluate(env, params, make_lqr(env, params), eval_key, episodes, measure_time=False).summary
    final = final.summary
    # The parts, timed from a state past SAC's warm-up; iterations chained so that a timed call lasts about 0.5 s
    # (one iteration of a small config is milliseconds: alone, its time would be the machine's noise).
    state = learner.init(jax.random.key(0), params)
    update = jax.jit(learner.update)
    warmup = int(getattr(config, "warmup_iterations", 0))
    for _ in range(max(1, warmup)):
        state, _ = update(state, params)
    chained = max(1, round(0.5 * result["iterations"] / max(result["train_time_s"], 1e-9)))
    chain = _update_runner(learner, chained)
    iteration_s = median_seconds(lambda: chain(state, params), repeats) / chained
    collect = jax.jit(learner.collect)
    # Not clipped at iteration_s: a collection timed longer than the whole iteration shows the machine's noise.
    collect_s = median_seconds(lambda: collect(state, params), 3 * repeats)
    iterations = int(result["iterations"])
    learning = iterations - min(warmup, iterations)
    compute_s = learning * iteration_s + (iterations - learning) * collect_s
    run_s = float(result["train_time_s"])
    return {
        "algo": algo,
        "copies": int(config.num_envs),
        "iterations": iterations,
        "collect_s_per_iteration": collect_s,
        "update_s_per_iteration": iteration_s - collect_s,
        "collect_share": iterations * collect_s / run_s,
        "update_share": learning * (iteration_s - collect_s) / run_s,
        "other_share": (run_s - compute_s) / run_s,
        "run_s": run_s,
        "compile_s": float(result["compile_time_s"]),
        "final_rmse_over_lqr": float(final["rmse"] / lqr["rmse"]),
        "final_crash_rate": float(final["crash_rate"]),
        "learned": bool(
            final["crash_rate"] == 0.0
            and final["length"] == env.num_steps
            and final["rmse"] < DEFAULT_BUDGET_RMSE_FACTOR * lqr["rmse"]
        ),
    }


# --------------------------------------------------------------------------------------------- time to threshold
def lqr_threshold(env, params, eval_key, episodes: int, factor: float) -> dict:
    summary = evaluate(env, params, make_lqr(env, params), eval_key, episodes, measure_time=False).summary
    return {"lqr_rmse": summary["rmse"], "threshold_rmse": factor * summary["rmse"]}


def _point(clock: float, steps: int, summary: dict) -> dict:
    return {"time_s": clock, "env_steps": steps, "rmse": summary["rmse"], "crash_rate": summary["crash_rate"]}


def _meets(summary: dict, threshold: float) -> bool:
    return summary["crash_rate"] == 0.0 and summary["rmse"] <= threshold


def ours_time_to_threshold(env, params, cfg, threshold, eval_key, episodes, max_s, chunk_s, console) -> dict:
    """Train our PPO in chunks of iterations; evaluate after each; stop at the threshold or the time limit."""
    config = _config(cfg, "ppo")
    learner = algorithm_module("ppo", "make_learner")(config, env)
    evaluate_policy = _policy_evaluator(
        env, params, episodes, lambda p: lambda obs: learner.make_policy(p)(obs, None), "ppo", config.action_scale
    )
    # The chunk length is traced (a while loop), so changing it never recompiles.
    chunk_jit = jax.jit(
        lambda state, params, n: jax.lax.fori_loop(0, n, lambda i, s: learner.update(s, params)[0], state)
    )
    curve = []
    eval_s = 0.0
    start = time.perf_counter()
    state = jax.jit(learner.init)(jax.random.key(0), params)
    iterations, n = 0, 1
    while iterations < learner.num_iterations:
        n = min(n, learner.num_iterations - iterations)
        tick = time.perf_counter()
        state = jax.block_until_ready(chunk_jit(state, params, jnp.int32(n)))
        per_iteration_s = (time.perf_counter() - tick) / n  # the first chunk includes the compile
        iterations += n
        clock = time.perf_counter() - start - eval_s
        tick = time.perf_counter()
        summary = evaluate_policy(learner.policy_params(state), eval_key).summary
        eval_s += time.perf_counter() - tick
        steps = iterations * config.batch_size
        curve.append(
            {"time_s": clock, "env_steps": steps, "rmse": summary["rmse"], "crash_rate": summary["crash_rate"]}
        )
        console.print(f"  ours  t={clock:6.1f} s  steps={steps:>9,}  rmse={summary['rmse']:.4f}")
        if _meets(summary, threshold):
            return {"reached": True, "time_s": clock, "env_steps": steps, "curve": curve}
        if clock > max_s:
            break
        # At most doubling, so the first evaluations come early.
        n = max(1, min(2 * n, int(chunk_s / max(per_iteration_s, 1e-6))))
    return {
        "reached": False,
        "time_s": time.perf_counter() - start - eval_s,
        "env_steps": iterations * config.batch_size,
        "curve": curve,
    }


# brax_ppo.train's arguments that are fields of our PPO config: brax's name -> ours.
_BRAX_PPO = {
    "num_timesteps": "total_env_steps", "num_envs": "num_envs", "unroll_length": "rollout_length",
    "num_updates_per_batch": "num_epochs", "learning_rate": "learning_rate", "entropy_cost": "ent_coef",
    "discounting": "gamma", "gae_lambda": "gae_lambda", "clipping_epsilon": "clip_eps",
    "max_grad_norm": "max_grad_norm", "normalize_observations": "normalize_observations",
    "reward_scaling": "reward_scale",
}  # fmt: skip


def brax_time_to_threshold(env, params, cfg, threshold, eval_key, episodes, max_s, num_evals, console) -> dict:
    """brax PPO with the same env and matched hyperparameters, evaluated in its ``policy_params_fn``."""
    from brax.training.agents.ppo import networks as ppo_networks
    from brax.training.agents.ppo import train as brax_ppo

    from scg_jax.adapters.brax import BraxEnv, wrap_for_training

    config = _config(cfg, "ppo")
    if env.action_mode != "normalized":
        raise SystemExit("brax comparison: the config's env must use action_mode: normalized")
    curve = []
    eval_time = [0.0]
    start = time.perf_counter()
    reached = {}

    evaluators = {}

    def policy_params_fn(step, make_policy, brax_params):
        if reached:
            return
        tick = time.perf_counter()
        if "fn" not in evaluators:
            evaluators["fn"] = _policy_evaluator(
                env,
                params,
                episodes,
                lambda p: lambda obs: make_policy(p, deterministic=True)(obs, jax.random.key(0))[0],
                "brax_ppo",
            )
        summary = evaluators["fn"](brax_params, eval_key).summary
        eval_time[0] += time.perf_counter() - tick
        clock = time.perf_counter() - start - eval_time[0]
        curve.append(
            {"time_s": clock, "env_steps": int(step), "rmse": summary["rmse"], "crash_rate": summary["crash_rate"]}
        )
        console.print(f"  brax  t={clock:6.1f} s  steps={int(step):>9,}  rmse={summary['rmse']:.4f}")
        if _meets(summary, threshold):
            reached.update(time_s=clock, env_steps=int(step))

    num_minibatches = config.num_minibatches
    batch_size = config.num_envs // num_minibatches  # one unroll of every copy per update, as ours
    network = functools.partial(
        ppo_networks.make_ppo_networks,
        policy_hidden_layer_sizes=tuple(config.actor_hidden),
        value_hidden_layer_sizes=tuple(config.critic_hidden),
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        brax_ppo.train(
            BraxEnv(env), episode_length=env.num_steps, wrap_env_fn=wrap_for_training, batch_size=batch_size,
            num_minibatches=num_minibatches, network_factory=network, num_evals=num_evals, num_eval_envs=16, seed=0,
            policy_params_fn=policy_params_fn, **{brax: getattr(config, ours) for brax, ours in _BRAX_PPO.items()},
        )  # fmt: skip
    total = time.perf_counter() - start - eval_time[0]
    if reached:
        return {"reached": True, **reached, "curve": curve}
    return {"reached": False, "time_s": total, "env_steps": config.total_env_steps, "curve": curve}


# --------------------------------------------------------------------------------------------- main
def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", default="configs/cartpole_stabilization.yaml", help="env and training config")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config overrides")
    parser.add_argument("--batches", type=int, nargs="+", default=[1024, 4096], help="copies for the throughput")
    parser.add_argument("--algos", nargs="+", default=["ppo", "sac"], choices=["ppo", "sac"], help="throughput")
    parser.add_argument("--iterations", type=int, default=4, help="iterations per timed throughput call")
    parser.add_argument("--repeats", type=int, default=3, help="timed throughput calls (median)")
    parser.add_argument(
        "--split", action=argparse.BooleanOptionalAction, default=True, help="where a whole run's time goes"
    )
    parser.add_argument("--threshold", action=argparse.BooleanOptionalAction, default=True, help="time to threshold")
    parser.add_argument("--brax", action=argparse.BooleanOptionalAction, default=True, help="brax PPO comparison")
    parser.add_argument("--rmse-factor", type=float, default=1.5, help="threshold: this times LQR's RMSE")
    parser.add_argument("--eval-episodes", type=int, default=32, help="episodes per evaluation")
    parser.add_argument("--max-seconds", type=float, default=300.0, help="give up after this much training time")
    parser.add_argument("--chunk-seconds", type=float, default=3.0, help="training time between evaluations")
    parser.add_argument("--brax-evals", type=int, default=20, help="evaluation points of the brax run")
    parser.add_argument("--json", type=Path, default=Path("benchmarks/results/train.json"), help="results file")
    parser.add_argument(
        "--markdown",
        type=Path,
        default=Path(__file__).resolve().parents[1] / "docs" / "benchmarks" / "train.md",
        help="generated table (every run; pass another path to keep the committed page)",
    )
    args = parser.parse_args(argv)
    console = Console()

    cfg = load_config(args.config, args.set)
    env, params = make_from_config(cfg)
    record = {
        **run_record("train"),
        "config": str(args.config),
        "overrides": args.set,
        "hyperparameters": {algo: dataclasses.asdict(_config(cfg, algo)) for algo in ("ppo", "sac")},
    }

    print_machine(console, record)

    rows = []
    for algo in args.algos:
        for batch in args.batches:
            console.print(f"throughput: {algo} at {batch} copies")
            rows.append(throughput(env, params, cfg, algo, batch, args.iterations, args.repeats))
    record["throughput"] = rows
    if rows:
        device = f"{record['device']['platform']} ({record['device']['device_kind']})"
        table = Table(title=f"training throughput, {env.system.name} {env.task}, {device}")
        for column in ("algo", "copies", "train steps/s", "env steps/s", "train / env", "compile s"):
            table.add_column(column, justify="right")
        for row in rows:
            table.add_row(
                row["algo"],
                f"{row['batch']:,}",
                f"{row['train_steps_per_s']:,.0f}",
                f"{row['env_steps_per_s']:,.0f}",
                f"{row['train_over_env']:.3f}",
                f"{row['compile_s']:.1f}",
            )
        console.print(table)

    if args.split:
        splits = []
        for algo in args.algos:
            console.print(f"run split: {algo}, a whole run at the config's settings")
            splits.append(run_split(env, params, cfg, algo, args.repeats, args.eval_episodes))
        record["run_split"] = splits
        table = Table(title="where a training run's wall time goes (compile apart)")
        columns = ("algo", "copies", "iterations", "collection", "update", "everything else", "run s", "compile s",
                   "RMSE / LQR", "learned")  # fmt: skip
        for column in columns:
            table.add_column(column, justify="right")
        for row in splits:
            table.add_row(
                row["algo"],
                f"{row['copies']:,}",
                str(row["iterations"]),
                f"{row['collect_share']:.0%}",
                f"{row['update_share']:.0%}",
                f"{row['other_share']:.0%}",
                f"{row['run_s']:.1f}",
                f"{row['compile_s']:.1f}",
                f"{row['final_rmse_over_lqr']:.2f}",
                str(row["learned"]),
            )
        console.print(table)

    if args.threshold:
        eval_key = jax.random.key(123)
        threshold = lqr_threshold(env, params, eval_key, args.eval_episodes, args.rmse_factor)
        console.print(
            f"LQR rmse {threshold['lqr_rmse']:.4f}; threshold {args.rmse_factor} x = {threshold['threshold_rmse']:.4f}"
        )
        # Both runs: the same env, config, threshold, evaluation episodes and time limit.
        race = (env, params, cfg, threshold["threshold_rmse"], eval_key, args.eval_episodes, args.max_seconds)
        ours = ours_time_to_threshold(*race, args.chunk_seconds, console)
        record["time_to_threshold"] = {**threshold, "rmse_factor": args.rmse_factor, "ours": ours}
        brax = None
        if args.brax:
            brax = brax_time_to_threshold(*race, args.brax_evals, console)
            record["time_to_threshold"]["brax"] = brax
        goal = GOAL_CARTPOLE_S if env.system.name == "cartpole" else GOAL_QUADROTOR_2D_S
        table = Table(title=f"time to {args.rmse_factor} x LQR's RMSE ({threshold['threshold_rmse']:.4f})")
        for column in ("learner", "reached", "time s (compile incl.)", "env steps", f"goal {goal:.0f} s"):
            table.add_column(column, justify="right")
        for name, result in (("ours (PPO)", ours), ("brax PPO", brax)):
            if result is None:
                continue
            met = "met" if result["reached"] and result["time_s"] <= goal else "missed"
            table.add_row(name, str(result["reached"]), f"{result['time_s']:.1f}", f"{result['env_steps']:,}", met)
        console.print(table)
        if brax is not None and ours["reached"]:
            ratio = brax["time_s"] / ours["time_s"]
            prefix = "" if brax["reached"] else ">= "
            record["time_to_threshold"]["brax_over_ours"] = ratio
            console.print(f"brax / ours time to threshold: {prefix}{ratio:.2f} (> 1: ours is faster)")
    record["load_average_end"] = load_average()
    args.json.parent.mkdir(parents=True, exist_ok=True)
    write_json(args.json, record)
    console.print(f"wrote {args.json}")
    threshold = record.get("time_to_threshold", {})
    notes = [f"Config {args.config}; the raw env (make_rollout, constant action) is the baseline in the same run."]
    for name in ("ours", "brax"):
        result = threshold.get(name)
        if result:
            notes.append(
                f"- time to {args.rmse_factor}x LQR's RMSE, {name}: {result['time_s']:.1f} s, "
                f"{result['env_steps']:,} env steps ({'reached' if result['reached'] else 'not reached'})"
            )
    for row in record.get("run_split", []):
        notes.append(
            f"- a whole {row['algo']} run ({row['copies']:,} copies, {row['iterations']} iterations, "
            f"{row['run_s']:.1f} s + {row['compile_s']:.1f} s compile): collection {row['collect_share']:.0%}, "
            f"update {row['update_share']:.0%}, everything else {row['other_share']:.0%}; final policy "
            f"{row['final_rmse_over_lqr']:.2f}x LQR's RMSE, crash rate {row['final_crash_rate']:.0%} "
            f"({'learned' if row['learned'] else 'NOT learned'} within the default budget)"
        )
    if "brax_over_ours" in threshold:
        notes.append(f"- brax / ours: {threshold['brax_over_ours']:.2f}")
    write_markdown_table(
        args.markdown, "Training speed", record,
        ["learner", "copies", "train steps/s", "raw env steps/s", "train / env", "compile (s)"],
        [[r["algo"], r["batch"], r["train_steps_per_s"], r["env_steps_per_s"], r["train_over_env"], r["compile_s"]]
         for r in record.get("throughput", [])],
        notes="\n".join(notes),
    )  # fmt: skip
    console.print(f"wrote {args.markdown}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
