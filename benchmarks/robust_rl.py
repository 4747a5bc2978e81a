"""Robust RL on the cart-pole (the paper's Fig 8): PPO, PPO^DR, RARL and RAP against pole length and input noise.

Each method is trained for ``--seeds`` seeds (one jitted run ``vmap``-ed over the seeds) from its config:

- PPO: ``configs/cartpole_stabilization.yaml`` (``training.ppo``);
- PPO^DR: ``configs/paper_cartpole_ppo_dr_relative.yaml`` (the original's 0.6-1.5 m) and, with ``--dr absolute``
  or ``both``, ``..._absolute.yaml`` (0.1-1.0 m);
- RARL: ``configs/paper_cartpole_rarl.yaml`` (the original's RA-L setting) and, as ``rarl_joint``,
  ``configs/cartpole_rarl.yaml`` (the suite's: joint updates, 0.01 N);
- RAP: ``configs/paper_cartpole_rap.yaml`` (and each ``--rap-scale`` as an extra RAP run with that adversary scale on
  the action channel);

every one with the same budget (``--steps``, env steps per seed). The deterministic policies are then evaluated by
the harness (``scg_algorithms.evaluation.make_evaluator``, the policy as a controller) on the evaluation env: the
training env without randomisation, with ``done_on_out_of_bounds: false`` (as the original's robustness runs) and
an action-channel white noise. Each sweep is ONE vmapped evaluation with batched ``EnvParams``
(``--episodes`` episodes per point):

- pole length ``l`` (half-length, m) in {0.15, 0.25, 0.5, 0.75, 1.25, 1.65, 2.0, 2.5, 3.0}, no input noise;
- input noise std ``sigma`` (N) in {0, 0.5, 1, 2, 4}, nominal length 0.5 m.

RMSE is the harness's per-episode RMSE (``sqrt`` of the mean ``mse_weight``-weighted squared state error), averaged
over episodes and seeds. The targets (printed, never an error exit): PPO^DR's RMSE averaged over
l in {0.75, 1.25, 1.65} <= 0.7x PPO's; RAP's RMSE at sigma = 2 N <= 0.8x PPO's; RAP and RARL at nominal
(l = 0.5, sigma = 0) within 1.2x of PPO's. Training env steps/s of each learner is reported as a ratio to PPO's in
the same run (compile excluded).

Writes ``benchmarks/results/robust_rl.json`` and ``docs/benchmarks/robust_rl.md``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from machine import print_machine, run_record, write_markdown_table  # benchmarks/machine.py, beside this script
from rich.console import Console

from scg_algorithms.base import JaxController, parse_options
from scg_algorithms.evaluation import make_evaluator
from scg_algorithms.ppo import make_train as make_ppo_train
from scg_algorithms.rl.envs import policy_action_to_input
from scg_algorithms.rl.policy import algorithm_module
from scg_jax.config import load_config, make_from_config
from scg_jax.files import write_json

ROOT = Path(__file__).resolve().parent.parent
LENGTHS = (0.15, 0.25, 0.5, 0.75, 1.25, 1.65, 2.0, 2.5, 3.0)
NOISES = (0.0, 0.5, 1.0, 2.0, 4.0)
DR_LENGTHS = (0.75, 1.25, 1.65)


def _train(config_path: Path, algo: str, steps: int, seeds: int, changes: dict | None = None, adversary=None):
    """Train ``seeds`` seeds at once; returns (learner, per-seed policy params, train seconds, compile seconds)."""
    overrides = []
    cfg = load_config(config_path, overrides=overrides)
    env, params = make_from_config(cfg)[:2]
    if adversary is not None:  # another adversary scale: rebuild the env with it
        from scg_jax.config import EnvConfig
        from scg_jax.env import make

        env_cfg = EnvConfig.from_dict({**cfg.env.to_dict(), "adversary": adversary}, "env")
        env = make(env_cfg)
        params = env.default_params
    options = {**dict(cfg.training.get(algo) or {}), "total_env_steps": steps, **(changes or {})}
    config = parse_options(algorithm_module(algo, "Config"), options, f"training.{algo}")
    learner = algorithm_module(algo, "make_learner")(config, env)
    train = make_ppo_train(config, env) if algo == "ppo" else algorithm_module(algo, "make_train")(config, env)
    keys = jax.random.split(jax.random.key(0), seeds)
    run = jax.jit(jax.vmap(train, in_axes=(0, None)))
    start = time.perf_counter()
    compiled = run.lower(keys, params).compile()
    compile_s = time.perf_counter() - start
    start = time.perf_counter()
    runner, metrics = jax.block_until_ready(compiled(keys, params))
    train_s = time.perf_counter() - start
    policies = [jax.tree.map(lambda x, i=i: x[i], learner.policy_params(runner)) for i in range(seeds)]
    final_return = np.asarray(metrics["episode_return"])[:, -1]
    env_steps = learner.num_iterations * learner.steps_per_iteration * seeds
    return learner, policies, {"train_s": train_s, "compile_s": compile_s, "env_steps": env_steps,
                               "final_return": final_return.tolist()}  # fmt: skip


def _eval_env():
    cfg = load_config(
        ROOT / "configs/cartpole_stabilization.yaml",
        overrides=["env.done_on_out_of_bounds=false", "env.physics_randomization=null"],
    )
    base = cfg.env.to_dict()
    base["disturbances"] = {**(base.get("disturbances") or {}), "action": [{"type": "white_noise", "std": 0.0}]}
    from scg_jax.config import EnvConfig
    from scg_jax.env import make

    env = make(EnvConfig.from_dict(base, "env"))
    return env, env.default_params


def _sweep_params(params, lengths=None, noises=None, episodes=10):
    """Batched ``EnvParams``: one row per episode, ``episodes`` rows per sweep point."""
    n = len(lengths if lengths is not None else noises)
    length = jnp.repeat(jnp.asarray(lengths if lengths is not None else [0.5] * n, jnp.float32), episodes)
    noise = jnp.repeat(jnp.asarray(noises if noises is not None else [0.0] * n, jnp.float32), episodes)
    action = params.disturbances["action"][0]

    def one(l_value, s_value):
        return params.replace(
            physics=params.physics.replace(pole_half_length=l_value),
            disturbances={**params.disturbances, "action": (action.replace(std=jnp.full(1, s_value)),)},
        )

    return jax.vmap(one)(length, noise)


def _evaluators(env, params, learner, episodes):
    physics = params.physics  # nominal: the policy's action -> force conversion does not know the plant
    scale = getattr(learner.config, "action_scale", 1.0)

    def build(policy_params):
        policy = learner.make_policy(policy_params)

        def act(ctrl_state, obs, step, reference):
            return policy_action_to_input(env, policy(obs), physics, scale), ctrl_state

        return JaxController(learner.name, lambda key, reference: (), act)

    length_fn = make_evaluator(env, build, len(LENGTHS) * episodes, batched_params=True)
    noise_fn = make_evaluator(env, build, len(NOISES) * episodes, batched_params=True)
    return length_fn, noise_fn


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=2_097_152, help="env steps per seed (default 2^21)")
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--episodes", type=int, default=10, help="evaluation episodes per sweep point and seed")
    parser.add_argument("--dr", choices=("relative", "absolute", "both"), default="both")
    parser.add_argument("--rap-scale", type=float, action="append", default=[], help="extra RAP adversary scale (N)")
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks/results/robust_rl.json")
    parser.add_argument("--markdown", type=Path, default=ROOT / "docs/benchmarks/robust_rl.md")
    parser.add_argument(
        "--report-only", action="store_true", help="rewrite the page from --out (also a partial run's) without training"
    )
    args = parser.parse_args(argv)
    console = Console()
    if args.report_only:
        saved = json.loads(args.out.read_text())
        record = {k: v for k, v in saved.items() if k not in ("partial", "steps_per_seed", "results")}
        args.steps = saved["steps_per_seed"]
        return report(args, record, saved["results"], console, partial=saved.get("partial", False))
    record = run_record("robust_rl")
    print_machine(console, record)

    methods = [("ppo", "ppo", ROOT / "configs/cartpole_stabilization.yaml", None)]
    if args.dr in ("relative", "both"):
        methods.append(("ppo_dr_relative", "ppo", ROOT / "configs/paper_cartpole_ppo_dr_relative.yaml", None))
    if args.dr in ("absolute", "both"):
        methods.append(("ppo_dr_absolute", "ppo", ROOT / "configs/paper_cartpole_ppo_dr_absolute.yaml", None))
    methods.append(("rarl", "rarl", ROOT / "configs/paper_cartpole_rarl.yaml", None))
    methods.append(("rarl_joint", "rarl", ROOT / "configs/cartpole_rarl.yaml", None))
    methods.append(("rap", "rap", ROOT / "configs/paper_cartpole_rap.yaml", None))
    for scale in args.rap_scale:
        methods.append((f"rap_scale{scale:g}", "rap", ROOT / "configs/paper_cartpole_rap.yaml",
                        {"channel": "action", "scale": scale}))  # fmt: skip

    env, params = _eval_env()
    length_params = _sweep_params(params, lengths=LENGTHS, episodes=args.episodes)
    noise_params = _sweep_params(params, noises=NOISES, episodes=args.episodes)
    results = {}
    for name, algo, path, adversary in methods:
        what = f"training {name} ({algo}, {path.name}), {args.seeds} seeds x {args.steps:,} steps"
        console.print(what, highlight=False)
        learner, policies, timing = _train(path, algo, args.steps, args.seeds, adversary=adversary)
        length_fn, noise_fn = _evaluators(env, params, learner, args.episodes)
        by_length, by_noise = [], []
        for seed, policy in enumerate(policies):
            key = jax.random.key(6161 + seed)
            ev = length_fn(policy, key, length_params)
            by_length.append(np.asarray(ev.per_episode["rmse"]).reshape(len(LENGTHS), args.episodes).mean(axis=1))
            ev = noise_fn(policy, jax.random.key(616161 + seed), noise_params)
            by_noise.append(np.asarray(ev.per_episode["rmse"]).reshape(len(NOISES), args.episodes).mean(axis=1))
        results[name] = {
            "algo": algo,
            "config": str(path.relative_to(ROOT)),
            "adversary": adversary,
            "rmse_by_length": np.mean(by_length, axis=0).tolist(),
            "rmse_by_length_per_seed": np.asarray(by_length).tolist(),
            "rmse_by_noise": np.mean(by_noise, axis=0).tolist(),
            "rmse_by_noise_per_seed": np.asarray(by_noise).tolist(),
            "env_steps_per_s": timing["env_steps"] / timing["train_s"],
            **timing,
        }
        console.print(
            f"  {timing['train_s']:.0f} s ({timing['compile_s']:.0f} s compile), "
            f"{results[name]['env_steps_per_s']:,.0f} steps/s; RMSE by length "
            + " ".join(f"{v:.3f}" for v in results[name]["rmse_by_length"])
            + "; by noise "
            + " ".join(f"{v:.3f}" for v in results[name]["rmse_by_noise"]),
            highlight=False,
        )
        args.out.parent.mkdir(parents=True, exist_ok=True)
        write_json(args.out, {**record, "partial": True, "steps_per_seed": args.steps, "results": results})

    return report(args, record, results, console)


def report(args, record: dict, results: dict, console, partial: bool = False) -> int:
    """Ratios against PPO, the goals met or missed, the JSON and the Markdown page."""
    ppo = results["ppo"]
    nominal = lambda r: r["rmse_by_length"][LENGTHS.index(0.5)]  # noqa: E731
    dr_mean = lambda r: float(np.mean([r["rmse_by_length"][LENGTHS.index(v)] for v in DR_LENGTHS]))  # noqa: E731
    at_2n = lambda r: r["rmse_by_noise"][NOISES.index(2.0)]  # noqa: E731
    checks = []
    for name, r in results.items():
        row = {
            "method": name,
            "dr_ratio": dr_mean(r) / dr_mean(ppo),
            "noise2_ratio": at_2n(r) / at_2n(ppo),
            "nominal_ratio": nominal(r) / nominal(ppo),
            "speed_ratio": r["env_steps_per_s"] / ppo["env_steps_per_s"],
        }
        checks.append(row)
    goals = {
        "ppo_dr_relative": ("dr_ratio", 0.7),
        "ppo_dr_absolute": ("dr_ratio", 0.7),
        "rap": ("noise2_ratio", 0.8),
    }
    lines = []
    for row in checks:
        name = row["method"]
        if name in goals:
            metric, limit = goals[name]
            verdict = "met" if row[metric] <= limit else "MISSED"
            lines.append(f"{name}: {metric} {row[metric]:.3f} (goal <= {limit}) -> {verdict}")
        if name.startswith(("rap", "rarl")):
            lines.append(
                f"{name}: nominal_ratio {row['nominal_ratio']:.3f} (goal <= 1.2) -> "
                f"{'met' if row['nominal_ratio'] <= 1.2 else 'MISSED'}"
            )
    for line in lines:
        console.print(line, highlight=False)

    payload = {**record, "partial": partial, "steps_per_seed": args.steps, "seeds": args.seeds,
               "episodes": args.episodes, "lengths": LENGTHS, "noises": NOISES, "results": results, "ratios": checks,
               "goals": lines}  # fmt: skip
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_json(args.out, payload)
    columns = ["method", *[f"l={v:g}" for v in LENGTHS], *[f"σ={v:g} N" for v in NOISES], "steps/s vs PPO"]
    rows = [
        [name, *r["rmse_by_length"], *r["rmse_by_noise"], r["env_steps_per_s"] / ppo["env_steps_per_s"]]
        for name, r in results.items()
    ]
    notes = (
        f"Average RMSE (harness per-episode RMSE, weighted state error) over {args.seeds} seeds x {args.episodes} "
        f"episodes per point; each method trained {args.steps:,} env steps per seed (the seeds vmapped in one jitted "
        "run). Left: pole half-length l (m), no input noise; right: white noise of std σ on the cart force, "
        "l = 0.5 m. Evaluation env: configs/cartpole_stabilization.yaml without randomisation, "
        "done_on_out_of_bounds false. Last column: training env steps/s over PPO's, same run, compile excluded; "
        "the methods train one after another, so on a busy machine (see the load above) the ratio mostly measures "
        "the load. Per-seed values are in benchmarks/results/robust_rl.json."
        + (
            " PARTIAL: the run was stopped before every method had finished; the rows are those that did."
            if partial
            else ""
        )
        + "\n\n"
        + "\n".join(f"- {line}" for line in lines)
    )
    write_markdown_table(args.markdown, "Robust RL on the cart-pole (Fig 8)", record, columns, rows, notes)
    console.print(f"wrote {args.out} and {args.markdown}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
