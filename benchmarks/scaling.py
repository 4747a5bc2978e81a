"""Scaling of the sharded batch over devices: env steps/s of a rollout and of PPO-style collection vs device count.

For each device count N (default 1, 2, 4, 8) a fresh process is started with
``XLA_FLAGS=--xla_force_host_platform_device_count=N`` (the device count is fixed when JAX starts), and times, on
the same global batch (strong scaling):

- **rollout**: ``scg_jax.rollout.make_rollout`` of ``--num-envs`` cart-pole copies x ``--steps`` control steps under a
  linear feedback policy, with ``mesh=make_mesh(N)`` (no mesh at N = 1);
- **PPO collection**: ``scg_algorithms.rl.collector.collect`` of the same copies under a 64x64 tanh MLP Gaussian
  policy (what a PPO iteration collects), its collector state laid out with ``shard_runner_state``.

Each is compiled, run once, then timed ``--repeats`` times; the fastest call counts (on a shared machine the
minimum is the least disturbed estimate). Scaling efficiency is
``(steps/s at N) / (N x steps/s at 1)``. On a CPU host the simulated devices share the physical cores, so
efficiency falls once N exceeds the cores (2 on the development machine); on a GPU/TPU host run it with
``--no-force`` to use the real devices.

Writes ``docs/benchmarks/scaling.md`` and ``benchmarks/results/scaling.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent


def _worker(args) -> dict:
    import jax
    import jax.numpy as jnp

    import scg_jax
    from scg_algorithms.rl.collector import ActOutput, collect, init_collector
    from scg_algorithms.rl.envs import make_train_env
    from scg_algorithms.rl.networks import MLP
    from scg_algorithms.rl.sharding import shard_runner_state
    from scg_jax import sharding
    from scg_jax.rollout import make_rollout

    mesh = sharding.make_mesh(jax.device_count())
    env = scg_jax.make("cartpole")
    params = env.default_params
    result = {"devices": jax.device_count()}

    def timed(fn, *inputs):
        start = time.perf_counter()
        compiled = fn.lower(*inputs).compile()
        compile_s = time.perf_counter() - start
        jax.block_until_ready(compiled(*inputs))
        times = []
        for _ in range(args.repeats):
            start = time.perf_counter()
            jax.block_until_ready(compiled(*inputs))
            times.append(time.perf_counter() - start)
        return min(times), compile_s

    gain = jnp.asarray([[0.5, 0.8, 6.0, 1.0]])

    def policy(obs, state, p, key):
        return jnp.clip(gain @ obs[:4], -1.0, 1.0)

    rollout = make_rollout(env, policy, args.num_envs, args.steps, mesh=mesh)
    seconds, compile_s = timed(rollout, jax.random.key(0), params)
    result["rollout_steps_per_s"] = args.num_envs * args.steps / seconds
    result["rollout_compile_s"] = compile_s

    train_env = make_train_env(env, args.num_envs)
    actor = MLP((64, 64, train_env.action_size), "tanh", final_scale=0.01)
    weights = actor.init(jax.random.key(1), jnp.zeros((1, train_env.obs_size)))
    state = init_collector(train_env, jax.random.key(2), params)
    if mesh is not None:
        state = shard_runner_state(state, mesh)
        weights, params = sharding.replicate((weights, params), mesh)

    def collect_once(weights, state, params, key):
        def act(obs, step_key):
            mean = actor.apply(weights, obs)
            return ActOutput(mean + 0.3 * jax.random.normal(step_key, mean.shape), {})

        return collect(train_env, params, state, act, key, args.steps)[0]

    layout = None if mesh is None else sharding.shardings_of(state)
    collect_jit = jax.jit(collect_once, out_shardings=layout)
    seconds, compile_s = timed(collect_jit, weights, state, params, jax.random.key(3))
    result["collect_steps_per_s"] = args.num_envs * args.steps / seconds
    result["collect_compile_s"] = compile_s
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--devices", default="1,2,4,8", help="device counts (default: %(default)s)")
    parser.add_argument("--num-envs", type=int, default=2048, help="global batch, divisible by every count")
    parser.add_argument("--steps", type=int, default=100, help="control steps per call (default: %(default)s)")
    parser.add_argument("--repeats", type=int, default=5, help="timed calls, the fastest counts (default: %(default)s)")
    parser.add_argument("--no-force", action="store_true", help="use the real devices (a GPU host); one count")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks" / "scaling.md")
    args = parser.parse_args()
    if args.worker:
        print("RESULT " + json.dumps(_worker(args)), flush=True)
        return

    sys.path.insert(0, str(HERE))
    from machine import run_record, write_markdown_table

    counts = [int(n) for n in args.devices.split(",")]
    results = []
    for n in counts:
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
        if not args.no_force:
            env["XLA_FLAGS"] = f"--xla_force_host_platform_device_count={n}"
        command = [sys.executable, __file__, "--worker", "--num-envs", str(args.num_envs), "--steps", str(args.steps)]
        run = subprocess.run([*command, "--repeats", str(args.repeats)], env=env, capture_output=True, text=True)
        if run.returncode:
            raise SystemExit(f"the worker for {n} device(s) failed:\n{run.stderr[-3000:]}")
        output = run.stdout
        result = json.loads(next(line for line in output.splitlines() if line.startswith("RESULT "))[7:])
        results.append(result)
        print(
            f"{result['devices']} device(s): rollout {result['rollout_steps_per_s']:,.0f} steps/s, "
            f"PPO collection {result['collect_steps_per_s']:,.0f} steps/s",
            flush=True,
        )

    record = run_record("scaling")
    record["device"]["count"] = "/".join(str(r["devices"]) for r in results)  # this parent process has one
    base = results[0]
    rows = []
    for r in results:
        n = r["devices"] / base["devices"]
        rows.append(
            [
                r["devices"],
                r["rollout_steps_per_s"],
                r["rollout_steps_per_s"] / (n * base["rollout_steps_per_s"]),
                r["collect_steps_per_s"],
                r["collect_steps_per_s"] / (n * base["collect_steps_per_s"]),
                r["rollout_compile_s"],
                r["collect_compile_s"],
            ]
        )
    record.update({"num_envs": args.num_envs, "steps": args.steps, "repeats": args.repeats, "results": results})
    results_dir = HERE / "results"
    results_dir.mkdir(exist_ok=True)
    (results_dir / "scaling.json").write_text(json.dumps(record, indent=2) + "\n")
    notes = (
        f"Global batch {args.num_envs} cart-pole copies x {args.steps} control steps per call (strong scaling), "
        f"fastest of {args.repeats} calls after compilation; each device count in its own process with "
        "`XLA_FLAGS=--xla_force_host_platform_device_count=N`. Efficiency = steps/s at N / (N x steps/s at "
        f"{base['devices']}). The simulated CPU devices share the machine's {record['cpu_count']} cores, so beyond "
        f"{record['cpu_count']} devices the efficiency must fall (the same work is only cut into more pieces); the "
        "figures above that count measure the partitioning overhead, not a speed-up. On a shared, loaded machine "
        "the absolute numbers are low; the ratios within one run are what to read. A GPU/TPU host: run with "
        "`--no-force --devices K` for K real devices."
    )
    write_markdown_table(
        args.out,
        "Scaling of the sharded batch over devices",
        record,
        [
            "devices",
            "rollout steps/s",
            "rollout efficiency",
            "PPO collection steps/s",
            "collection efficiency",
            "rollout compile s",
            "collection compile s",
        ],
        rows,
        notes,
    )
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
