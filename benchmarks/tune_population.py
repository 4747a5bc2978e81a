"""P hyperparameter settings trained as one vmapped population against the same P trained one after another.

Both sides train PPO on the cart-pole (``configs/cartpole_stabilization.yaml``) with the same P settings of the
traced options (learning rate, clip range, discount), from the same key:

- **sequential**: each setting as ``scg-jax tune`` trains a trial alone: its own ``make_train``, jitted (compiled),
  run once;
- **population**: ``scg_algorithms.tune.population.make_population_train`` of all P, jitted once, run once.

Printed: compile and run seconds of each side, wall and CPU-process time, and the ratio sequential / population
(how many trials one population's time buys). On a loaded machine the wall times are noisy; the CPU time of this
process is the steadier measure.

    .venv/bin/python benchmarks/tune_population.py --population 4 --total-env-steps 65536
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import run_record  # noqa: E402


def _timed(function):
    wall, cpu = time.perf_counter(), time.process_time()
    result = function()
    return result, time.perf_counter() - wall, time.process_time() - cpu


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--population", type=int, default=4, help="P, the settings trained (default: 4)")
    parser.add_argument("--total-env-steps", type=int, default=65_536, help="each setting's budget (default: 65536)")
    parser.add_argument("--json", type=Path, default=None, help="write the record here too")
    args = parser.parse_args(argv)

    import jax
    import numpy as np

    from scg_algorithms.learners import build_learner, learner_part
    from scg_algorithms.tune.population import check_members, make_population_train, stack_values
    from scg_jax.config import load_config, make_from_config

    record = run_record("tune_population")
    cfg = load_config("configs/cartpole_stabilization.yaml")
    env, params = make_from_config(cfg)
    base = {**cfg.training["ppo"], "total_env_steps": args.total_env_steps}
    config, _ = build_learner("ppo", base, env)
    rng = np.random.default_rng(0)
    members = [
        {"learning_rate": float(10 ** rng.uniform(-4, np.log10(3e-3))), "clip_eps": float(rng.uniform(0.1, 0.3)),
         "gamma": float(rng.uniform(0.95, 0.999))}
        for _ in range(args.population)
    ]  # fmt: skip
    names = tuple(members[0])
    configs = check_members("ppo", config, members)
    key = jax.random.key(0)

    sequential = {"compile_s": 0.0, "run_s": 0.0, "cpu_s": 0.0}
    for member in configs:
        train = jax.jit(learner_part("ppo", "make_train")(member, env))
        compiled, wall, cpu = _timed(lambda train=train: train.lower(key, params).compile())
        sequential["compile_s"] += wall
        sequential["cpu_s"] += cpu
        _, wall, cpu = _timed(lambda compiled=compiled: jax.block_until_ready(compiled(key, params)))
        sequential["run_s"] += wall
        sequential["cpu_s"] += cpu

    keys = jax.numpy.stack([key] * args.population)
    values = stack_values(members, names)
    train = jax.jit(make_population_train("ppo", config, env, names))
    compiled, compile_s, compile_cpu = _timed(lambda: train.lower(keys, params, values).compile())
    _, run_s, run_cpu = _timed(lambda: jax.block_until_ready(compiled(keys, params, values)))
    population = {"compile_s": compile_s, "run_s": run_s, "cpu_s": compile_cpu + run_cpu}

    total = {side: times["compile_s"] + times["run_s"] for side, times in (("sequential", sequential),
                                                                         ("population", population))}  # fmt: skip
    record.update(population=args.population, total_env_steps=args.total_env_steps, members=members,
                  sequential=sequential, vmapped=population,
                  wall_ratio=total["sequential"] / total["population"],
                  cpu_ratio=sequential["cpu_s"] / population["cpu_s"])  # fmt: skip
    load = record["load_average_start"]
    print(f"PPO, cart-pole, {args.population} settings x {args.total_env_steps:,} env steps, load average {load}")
    for side, times in (("sequential", sequential), ("population", population)):
        print(f"  {side:>10}: compile {times['compile_s']:7.1f} s, run {times['run_s']:7.1f} s, "
              f"wall {times['compile_s'] + times['run_s']:7.1f} s, cpu {times['cpu_s']:7.1f} s")  # fmt: skip
    print(f"  sequential / population: wall {record['wall_ratio']:.2f}x, cpu {record['cpu_ratio']:.2f}x")
    if args.json is not None:
        args.json.write_text(json.dumps(record, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
