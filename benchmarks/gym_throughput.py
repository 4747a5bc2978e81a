"""Throughput of the Gymnasium adapters next to the functional env, measured in the same run.

Three loops over the same env (default: cart-pole stabilization, 50 Hz control / 1000 Hz physics, rk4,
``action_mode="normalized"`` and ``reward_type="exponential"`` (the ids' defaults), a constant action of 0,
i.e. no force, so poles fall and episodes end):

- **vector**: ``gymnasium.make_vec(id, num_envs=N)`` (``ScgVectorEnv``, NEXT_STEP autoreset) stepped from a
  Python loop with a constant numpy action array, as a user would; each ``step`` is one jitted call for all
  copies and returns numpy observations, rewards, flags and info.
- **functional**: ``jax.jit`` of ``lax.scan`` over ``vmap(auto_reset_step)`` (``env.step`` and a fresh episode
  where one ended, the work the vector env's autoreset does) for the same number of steps, each call continuing
  from the state the previous one ended in, with no host transfer: the ceiling the adapter is compared with.
  (Without autoreset the fallen poles would make the functional env's steps dearer, since sin and cos of large
  angles cost more, and the ratio would flatter the adapter.)
- **single**: ``gymnasium.make(id)`` (one copy; one jitted call per step, reset when an episode ends), bound by
  dispatch rather than arithmetic.

The vector and functional envs are measured at every ``--num-envs`` (default 4,096, the batch of the target,
and 16,384). Each timed run of the vector env is ``--steps`` calls of ``step``; of the functional env one call
of the scan over ``--steps`` steps; of the single env ``--single-steps`` calls. The runs of all loops alternate
over ``--repeats`` rounds, so background load hits them alike; steps/s is the median over runs. "First call" is
the time of the first ``step`` (vector, single) or ``lower + compile`` (functional): mostly compilation.

Targets (informational, at the first batch size): the vector env >= 1M steps/s on 2 CPU cores and >= 50% of the
functional env. On 2 CPU cores XLA runs the cart-pole step of 4,096 copies on one core (CPU time / wall time
about 1.0; about 1.9 at 16,384 copies), so at 4,096 copies the functional env itself stays below 1M steps/s.

Run ``python benchmarks/gym_throughput.py --help`` for the options (``--quick`` for a smoke run).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import gymnasium
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
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

import scg_jax
from scg_jax.adapters import GYMNASIUM_IDS
from scg_jax.files import write_json

TARGET_VECTOR_STEPS_PER_S = 1_000_000.0
TARGET_VECTOR_OVER_FUNCTIONAL = 0.5
TARGET_CORES = 2
DEFAULT_MARKDOWN = Path(__file__).resolve().parents[1] / "docs" / "benchmarks" / "gym_throughput.md"
DEFAULT_JSON = Path(__file__).resolve().parent / "results" / "gym_throughput.json"


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description="Steps per second of the Gymnasium vector and single envs next to the functional env.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument("--system", choices=tuple(GYMNASIUM_IDS), default="cartpole")
    parser.add_argument(
        "--num-envs", type=int, nargs="+", default=[4096, 16384], help="copies (batch sizes); targets use the first"
    )
    parser.add_argument("--steps", type=int, default=250, help="vector and functional steps per timed run")
    parser.add_argument("--single-steps", type=int, default=2000, help="single-env steps per timed run")
    parser.add_argument("--repeats", type=int, default=5, help="timed runs of each")
    parser.add_argument("--action", type=float, default=0.0, help="the constant normalized action")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", type=Path, default=DEFAULT_JSON, help="where to write the results")
    parser.add_argument("--quick", action="store_true", help="smoke run: 256 copies, 20 steps, 2 repeats")
    parser.add_argument(
        "--markdown", type=Path, default=None, help=f"generated table [default: {DEFAULT_MARKDOWN}; none with --quick]"
    )
    args = parser.parse_args(argv)
    if args.quick:
        args.num_envs, args.steps, args.single_steps, args.repeats = [256], 20, 200, 2
    if min(*args.num_envs, args.steps, args.single_steps, args.repeats) < 1:
        parser.error("--num-envs, --steps, --single-steps and --repeats must be positive")
    if not -1.0 <= args.action <= 1.0:
        parser.error("--action: a normalized action in [-1, 1]")
    return args


# --------------------------------------------------------------------------------------------- the three loops
def _timed(fn, *args):
    """``(fn(*args), wall seconds of the call)``."""
    t = time.perf_counter()
    result = fn(*args)
    return result, time.perf_counter() - t


class VectorLoop:
    def __init__(self, env_id: str, num_envs: int, args):
        self.envs = gymnasium.make_vec(env_id, num_envs=num_envs)
        self.steps = args.steps
        nu = self.envs.single_action_space.shape[0]
        self.actions = np.full((num_envs, nu), args.action, np.float32)
        self.envs.reset(seed=args.seed)
        _, self.first_call_s = _timed(self.envs.step, self.actions)
        self.episodes = 0

    def run(self) -> float:
        return _timed(self._steps)[1] / (self.steps * self.envs.num_envs)

    def _steps(self) -> None:
        envs, actions = self.envs, self.actions
        for _ in range(self.steps):
            obs, reward, terminated, truncated, info = envs.step(actions)
            self.episodes += int(np.count_nonzero(terminated | truncated))


class FunctionalLoop:
    def __init__(self, env, params, num_envs: int, args):
        n = num_envs
        reset = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))
        self.obs, self.state = jax.block_until_ready(reset(jax.random.split(jax.random.key(args.seed), n), params))
        self.actions = jnp.full((n, env.nu), args.action, params.goal.dtype)
        # env.step plus a fresh episode where one ended: the same work as the vector env's autoreset (a fallen
        # cart-pole, never reset, costs more per step than an upright one: sin/cos of large angles).
        step = jax.vmap(lambda state, action, params: scg_jax.auto_reset_step(env, state, action, params),
                        in_axes=(0, 0, None))  # fmt: skip
        steps = args.steps

        def scan(obs, state, actions, params):
            def body(carry, _):
                _, state, ret, dones = carry
                out = step(state, actions, params)
                return (out.obs, out.state, ret + out.reward, dones + (out.terminated | out.truncated)), None

            init = (obs, state, jnp.zeros(n, obs.dtype), jnp.zeros(n, jnp.int32))
            (obs, state, ret, dones), _ = lax.scan(body, init, None, length=steps)
            return obs, state, ret, dones

        self.params = params
        self.fn, self.first_call_s = _timed(
            lambda: jax.jit(scan).lower(self.obs, self.state, self.actions, params).compile()
        )
        jax.block_until_ready(self.fn(self.obs, self.state, self.actions, params))  # warm-up
        self.count = n * steps

    def run(self) -> float:
        """One call of the scan, continuing from where the previous one ended (as the vector env does)."""
        (self.obs, self.state, _, _), seconds = _timed(
            lambda: jax.block_until_ready(self.fn(self.obs, self.state, self.actions, self.params))
        )
        return seconds / self.count


class SingleLoop:
    def __init__(self, env_id: str, args):
        self.env = gymnasium.make(env_id)
        self.steps = args.single_steps
        self.action = np.full(self.env.action_space.shape, args.action, np.float32)
        self.env.reset(seed=args.seed)
        _, self.first_call_s = _timed(self.env.step, self.action)
        self.env.reset()  # compiles the unseeded reset's key derivation outside the timed runs
        self.env.reset(seed=args.seed)
        self.episodes = 0

    def run(self) -> float:
        return _timed(self._steps)[1] / self.steps

    def _steps(self) -> None:
        env, action = self.env, self.action
        for _ in range(self.steps):
            obs, reward, terminated, truncated, info = env.step(action)
            if terminated or truncated:
                env.reset()
                self.episodes += 1


# --------------------------------------------------------------------------------------------- main
def main(argv=None) -> int:
    args = parse_args(argv)
    console = Console()
    if not console.is_terminal:
        console = Console(width=max(console.width, 150))
    env_id = GYMNASIUM_IDS[args.system]
    meta = {
        **run_record("gym_throughput"),
        "gymnasium_version": gymnasium.__version__,
        "config": {
            "env_id": env_id,
            "num_envs": args.num_envs,
            "steps": args.steps,
            "single_steps": args.single_steps,
            "repeats": args.repeats,
            "action": args.action,
            "seed": args.seed,
            "quick": args.quick,
            "autoreset_mode": "NEXT_STEP (vector env default)",
            "functional": "jit(scan(vmap(auto_reset_step))), continuing between runs",
            "stat": "median",
        },
    }
    cores = meta["cpu_count"]
    print_machine(console, meta, prefix=f"{env_id} (gymnasium {gymnasium.__version__}): ")

    columns = (TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"))
    loops = {}
    with Progress(*columns, TimeElapsedColumn(), console=console, transient=True) as progress:
        batches = args.num_envs
        task = progress.add_task("compiling", total=(2 * len(batches) + 1) * (1 + args.repeats))
        for n in batches:
            progress.update(task, description=f"compiling: vector env, {n:,} copies")
            vector = loops[("vector", n)] = VectorLoop(env_id, n, args)
            progress.update(task, advance=1, description=f"compiling: functional env, {n:,} copies")
            fenv, params = vector.envs.unwrapped.functional_env, vector.envs.unwrapped.params
            loops[("functional", n)] = FunctionalLoop(fenv, params, n, args)
            progress.update(task, advance=1)
        progress.update(task, description="compiling: single env")
        loops[("single", 1)] = SingleLoop(env_id, args)
        progress.update(task, advance=1)
        runs = {key: [] for key in loops}
        for r in range(args.repeats):
            for (name, n), loop in loops.items():
                progress.update(task, description=f"run {r + 1}/{args.repeats}: {name}, {n:,} copies")
                runs[(name, n)].append(loop.run())
                progress.update(task, advance=1)

    how = {
        "vector": "make_vec, Python loop, numpy in/out",
        "functional": "jit(scan(vmap(auto_reset_step)))",
        "single": "make, Python loop, numpy in/out",
    }
    rows = []
    for (name, n), loop in loops.items():
        per_step = np.asarray(runs[(name, n)])
        functional = runs.get(("functional", n))
        rows.append(
            {
                "loop": name,
                "description": how[name],
                "copies": n,
                "steps_per_run": args.single_steps if name == "single" else args.steps,
                "steps_per_s": float(1.0 / np.median(per_step)),
                "steps_per_s_min": float(1.0 / per_step.max()),
                "steps_per_s_max": float(1.0 / per_step.min()),
                "over_functional": float(np.median(functional) / np.median(per_step)) if functional else None,
                "first_call_s": loop.first_call_s,
            }
        )
    target = next(r for r in rows if r["loop"] == "vector" and r["copies"] == args.num_envs[0])
    vector_rate, ratio = target["steps_per_s"], target["over_functional"]
    targets = [
        {
            "target": f"vector env >= {TARGET_VECTOR_STEPS_PER_S / 1e6:g}M steps/s at {target['copies']:,} copies "
            f"on {TARGET_CORES} CPU cores",
            "status": "PASS" if vector_rate >= TARGET_VECTOR_STEPS_PER_S else "FAIL",
            "detail": f"{vector_rate:,.0f} steps/s on {cores} CPU cores, load average {meta['load_average_start']}",
        },
        {
            "target": f"vector env >= {TARGET_VECTOR_OVER_FUNCTIONAL:.0%} of the functional env at "
            f"{target['copies']:,} copies",
            "status": "PASS" if ratio >= TARGET_VECTOR_OVER_FUNCTIONAL else "FAIL",
            "detail": f"{ratio:.2f}",
        },
    ]
    vector_episodes = sum(loop.episodes for (name, _), loop in loops.items() if name == "vector")
    single_episodes = loops[("single", 1)].episodes
    meta["load_average_end"] = load_average()
    meta["episodes_ended"] = {"vector": vector_episodes, "single": single_episodes}

    table = Table(
        title=f"Gymnasium throughput: {env_id}, constant action {args.action:g}, {cores} CPU cores",
        box=box.SIMPLE_HEAD,
        title_justify="left",
    )
    for header in ("loop", "how", "copies", "steps/run"):
        table.add_column(header, justify="left" if header in ("loop", "how") else "right")
    for header in ("steps/s (median)", "min - max", "/ functional", "first call s"):
        table.add_column(header, justify="right")
    for r in rows:
        table.add_row(
            r["loop"],
            r["description"],
            f"{r['copies']:,}",
            f"{r['steps_per_run']:,}",
            f"{r['steps_per_s']:,.0f}",
            f"{r['steps_per_s_min']:,.0f} - {r['steps_per_s_max']:,.0f}",
            "" if r["over_functional"] is None else f"{r['over_functional']:.2f}",
            f"{r['first_call_s']:.2f}",
        )
    console.print(table)
    console.print(
        "vector: NEXT_STEP autoreset; functional: auto_reset_step (same-step), no host transfer; single: reset() at "
        "episode end.\n"
        f"steps/s: control steps per second, all copies together; median of {args.repeats} alternating timed runs. "
        f"Episodes ended during the timed runs: vector {vector_episodes:,}, single {single_episodes:,}.\n"
        "first call: the first step (vector, single) or lower + compile (functional); mostly compilation. "
        f"Load average at the end {meta['load_average_end']}."
    )
    console.print("\nTargets (informational):")
    for t in targets:
        style = "green" if t["status"] == "PASS" else "red"
        console.print(f"  [{style}]{t['status']:<4}[/{style}]  {t['target']}: {t['detail']}", highlight=False)

    write_json(args.json, {**meta, "rows": rows, "targets": targets})
    console.print(f"\nwrote {args.json}", highlight=False)
    markdown = args.markdown or (None if args.quick else DEFAULT_MARKDOWN)
    if markdown is not None:
        write_markdown_table(
            markdown,
            f"Gymnasium throughput ({env_id})",
            meta,
            ["loop", "how", "copies", "steps/s (median)", "/ functional env"],
            [[r["loop"], r["description"], r["copies"], r["steps_per_s"], r["over_functional"]] for r in rows],
            notes=f"Median of {args.repeats} alternating timed runs; the functional env is the baseline measured in "
            "the same run. vector: NEXT_STEP autoreset, numpy in and out; single: one env, dispatch-bound.",
        )
        console.print(f"wrote {markdown}", highlight=False)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
