"""Throughput (this suite's own headline): cart-pole env steps per second against the number of parallel copies,
beside the original suite's single PyBullet env (about 2,100 control steps/s, 50 Hz control over 1000 Hz physics),
and the wall time to a trained PPO policy.

The env is the control-performance cart-pole (50 / 1000 Hz, rk4, constraints and an input-noise channel) under a
constant input, through the public ``scg_jax.make_rollout`` with auto-reset; compile is timed apart from the runs,
and each batch size is timed by the median of ``repeats`` runs. The machine may be shared: the numbers are
comparable within one run, not across machines.
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np

import scg_jax
from scg_experiments import common

NAME = "throughput"
TITLE = "Throughput: env steps/s against parallel copies, and time to a trained policy"

ORIGINAL_STEPS_PER_S = 2100.0  # the original suite's cart-pole, one env (DESIGN.md reference facts)

PROFILES = {
    "tiny": {"batches": [1, 16], "steps": 50, "repeats": 1, "ppo_steps": 0},
    "quick": {"batches": [1, 16, 256, 4096], "steps": 250, "repeats": 3, "ppo_steps": 1_048_576},
    "paper": {"batches": [1, 16, 256, 4096, 16384], "steps": 250, "repeats": 5, "ppo_steps": 4_194_304},
}


def steps_per_second(env, params, batch: int, steps: int, repeats: int) -> dict:
    """Env steps/s of ``batch`` copies over ``steps`` control steps (median of ``repeats`` timed runs)."""
    u = jnp.asarray(env.system.equilibrium_input(params.physics))
    action = env.input_to_action(u, params)
    rollout = scg_jax.make_rollout(env, lambda obs, state, p, key: action, num_envs=batch, num_steps=steps)
    key = jax.random.key(0)
    start = time.perf_counter()
    jax.block_until_ready(rollout(key, params))  # compile and first run
    compile_s = time.perf_counter() - start
    times = []
    for i in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(rollout(jax.random.key(i + 1), params))
        times.append(time.perf_counter() - start)
    run_s = float(np.median(times))
    return {"copies": batch, "steps_per_s": batch * steps / run_s, "run_s": run_s, "compile_and_first_run_s": compile_s}


def run(ctx: common.Context) -> common.Section:
    budget = ctx.budget(PROFILES)
    _, env, params = common.load("cartpole")
    rows = []
    for batch in budget["batches"]:
        with ctx.step(f"{batch} copies"):
            rows.append(steps_per_second(env, params, batch, budget["steps"], budget["repeats"]))
    for row in rows:
        row["x_original"] = row["steps_per_s"] / ORIGINAL_STEPS_PER_S
    section = common.Section(NAME, TITLE)
    section.files.append(common.write_csv(ctx.out / "throughput.csv", rows))
    training = None
    if budget["ppo_steps"]:
        cfg = scg_jax.load_config(common.CONFIG_DIR / "cartpole.yaml")
        _, metrics = common.train_policy(ctx, "ppo", cfg, ctx.seeds[0], budget["ppo_steps"], env, params)
        training = {"env_steps": metrics["training"]["env_steps"], "total_time_s": metrics["training"]["total_time_s"],
                    "rmse": metrics["evaluation"]["rmse"]}  # fmt: skip
        section.files.append(common.write_data(ctx.out / "time_to_policy.json", training))
    plt = common.pyplot()
    figure, axis = plt.subplots(figsize=(5.5, 3.8), constrained_layout=True)
    axis.plot([r["copies"] for r in rows], [r["steps_per_s"] for r in rows], "o-", label="scg-jax (this machine)")
    axis.axhline(ORIGINAL_STEPS_PER_S, color="k", linestyle=":", label="original, one PyBullet env")
    axis.set_xscale("log")
    axis.set_yscale("log")
    axis.set_xlabel("parallel copies")
    axis.set_ylabel("cart-pole env steps/s")
    axis.grid(alpha=0.3)
    axis.legend(fontsize=8)
    section.files.append(common.save_figure(figure, ctx.out / "throughput.png"))
    best = max(rows, key=lambda r: r["steps_per_s"])
    single = rows[0]
    section.claims = [
        common.claim(
            "Batched JAX simulation outruns the original's single env by orders of magnitude (at least 100x)",
            best["x_original"] >= 100,
            f"{best['steps_per_s']:,.0f} steps/s at {best['copies']:,} copies ({best['x_original']:,.0f}x the "
            f"original's {ORIGINAL_STEPS_PER_S:,.0f}); one copy: {single['steps_per_s']:,.0f} steps/s",
        ),
        common.claim(
            "Steps/s grow with the number of copies (largest batch faster than one copy)",
            rows[-1]["steps_per_s"] > rows[0]["steps_per_s"],
            ", ".join(f"{r['copies']:,}: {r['steps_per_s']:,.0f}" for r in rows),
        ),
    ]
    if training:
        original_s = training["env_steps"] / ORIGINAL_STEPS_PER_S
        section.notes.append(
            f"Time to a trained PPO policy (cart-pole, {training['env_steps']:,} env steps, compile included): "
            f"{training['total_time_s']:.1f} s, RMSE {training['rmse']:.4f}; simulating the same steps one env at a "
            f"time at the original's rate alone would take {original_s:,.0f} s ({original_s / 3600:.1f} h)."
        )
    section.notes.append(f"{budget['steps']} control steps per run, median of {budget['repeats']}; shared machine.")
    return section
