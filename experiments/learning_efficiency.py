"""Learning efficiency (the paper's Fig 6): RMSE against seconds of simulated training data (log axis) for GP-MPC
(150 % prior), PPO and SAC, on the cart-pole stabilization and the 2D quadrotor circle.

GP-MPC's curve is its learning loop's rounds (round 0: the prior's MPC, no data) in the original's GP-MPC setting of
this figure (cart-pole: ``experiments/configs/cartpole_gp_mpc.yaml``, 10 Hz; quadrotor: ``quadrotor_circle.yaml``'s
``controllers.gp_mpc`` at 10 Hz). The RL curves evaluate the deterministic policy with the common harness after a
series of env-step budgets of one training run on the RL env (50 Hz), updating as often as the original (PPO on the
cart-pole every 400 env steps, 8 s of data). Training data in seconds: transitions times the control period, as in
the paper. The RMSE is the paper's: the full state, unweighted, on the cart-pole; x and z only on the quadrotor.
"""

from __future__ import annotations

import math

import numpy as np

import scg_jax
from scg_experiments import common

NAME = "learning_efficiency"
TITLE = "Learning efficiency: RMSE against training data (Fig 6)"

# The RL curves' update sizes: PPO on the cart-pole updates every 8 x 50 = 400 env steps (8 s of data) like the
# original's 4 x 100, with 10 epochs per batch; on the quadrotor every 64 x 50 = 3,200 (64 s) to keep its 5e6-step
# budget affordable on 2 cores.
PPO_CARTPOLE = {"num_envs": 8, "rollout_length": 50, "num_epochs": 10, "num_minibatches": 5}
PPO_QUADROTOR = {"num_envs": 64, "rollout_length": 50, "num_epochs": 10, "num_minibatches": 5}


def _ppo(options: dict) -> list[str]:
    return [f"training.ppo.{key}={value}" for key, value in options.items()]


PROFILES = {
    "tiny": {
        "systems": ["cartpole"], "episodes": 2, "gp_mpc": None,
        "rl_points": {"cartpole": {"ppo": [400, 800]}},
        "overrides": {"cartpole": {"ppo": _ppo(PPO_CARTPOLE)}},
    },
    "quick": {
        "systems": ["cartpole", "quadrotor_circle"], "episodes": 4,
        "gp_mpc": common.GP_MPC_LEARNING["quick"],
        "rl_points": {
            "cartpole": {"ppo": [4_000, 10_000, 20_000, 40_000, 100_000], "sac": [5_000, 10_000, 30_000, 60_000]},
            "quadrotor_circle": {"ppo": [6_400, 16_000, 32_000, 64_000, 320_000, 1_600_000],
                                 "sac": [10_000, 30_000, 60_000]},
        },
        "overrides": {"cartpole": {"ppo": _ppo(PPO_CARTPOLE)}, "quadrotor_circle": {"ppo": _ppo(PPO_QUADROTOR)}},
    },
    "paper": {
        "systems": ["cartpole", "quadrotor_circle"], "episodes": 10,
        "gp_mpc": common.GP_MPC_LEARNING["paper"],
        "rl_points": {
            "cartpole": {"ppo": [4_000, 10_000, 20_000, 40_000, 100_000, 200_000, 400_000, 1_000_000],
                         "sac": [5_000, 10_000, 25_000, 50_000, 100_000, 150_000]},
            "quadrotor_circle": {"ppo": [6_400, 16_000, 32_000, 64_000, 320_000, 1_600_000, 3_200_000, 5_001_600],
                                 "sac": [10_000, 30_000, 100_000, 300_000]},
        },
        "overrides": {"cartpole": {"ppo": _ppo(PPO_CARTPOLE)}, "quadrotor_circle": {"ppo": _ppo(PPO_QUADROTOR)}},
    },
}  # fmt: skip

EVAL = ["env.done_on_out_of_bounds=false"]
# GP-MPC's config and rate per system: the cart-pole's own Fig 6 setting (10 Hz already), the quadrotor's circle at
# 10 Hz.
GP_MPC_SETTING = {"cartpole": ("cartpole_gp_mpc", []), "quadrotor_circle": ("quadrotor_circle", ["env.ctrl_freq=10"])}

# The original's GP-MPC curves (gpmpc_fig6_data.csv; spec §1): seconds of data (transitions / 10 Hz) -> RMSE.
ORIGINAL_GP_MPC = {
    "cartpole": [(0.0, 0.818), (9.3, 0.129), (17.7, 0.129), (27.5, 0.129), (37.0, 0.1287), (46.4, 0.1288),
                 (56.0, 0.1288), (63.8, 0.1288)],
    "quadrotor_circle": [(0.0, 0.259), (5.1, 0.112), (10.2, 0.116), (15.3, 0.115), (20.4, 0.108), (25.5, 0.080),
                         (30.6, 0.105), (35.7, 0.104), (40.8, 0.102), (45.9, 0.104)],
}  # fmt: skip
MATCHED_AFTER = 10**2.5  # s: "only matched after around 10^3 s" holds when RL first matches at or after this
COMPARABLE = 1.5  # "comparable": a final RMSE within this factor of GP-MPC's best


def converged_at(curve: list[tuple[float, float]], tolerance: float = 1.1) -> float:
    """Seconds of data at which a curve first comes within ``tolerance`` times its best RMSE."""
    best = min(r for _, r in curve)
    return next(s for s, r in curve if r <= tolerance * best)


def first_below(curve: list[tuple[float, float]], level: float) -> float:
    """Seconds of data at which a curve first reaches ``level`` (inf when it never does)."""
    return next((s for s, r in curve if r <= level), math.inf)


def run(ctx: common.Context) -> common.Section:
    budget = ctx.budget(PROFILES)
    section = common.Section(NAME, TITLE)
    plt = common.pyplot()
    figure, axes = plt.subplots(1, len(budget["systems"]), figsize=(5.5 * len(budget["systems"]), 3.8), squeeze=False)
    rows, curves, missing = [], {}, set()
    for axis, system in zip(axes[0], budget["systems"], strict=True):
        _, env, params = common.load(system, EVAL)
        curves[system] = {}
        for seed in ctx.seeds:
            for algo, points in budget["rl_points"].get(system, {}).items():
                if not common.learner_available(algo):
                    missing.add(algo)
                    continue
                overrides = budget["overrides"].get(system, {}).get(algo, [])
                cfg = scg_jax.load_config(common.CONFIG_DIR / f"{system}.yaml", overrides)
                curve = common.learning_curve(ctx, algo, cfg, seed, points, env, params, budget["episodes"])
                rows += [{"system": system, "method": algo, "seed": seed, **r} for r in curve]
                curves[system].setdefault(algo, []).append([(r["data_seconds"], r["rmse"]) for r in curve])
            if budget["gp_mpc"] is not None:
                name, rate = GP_MPC_SETTING[system]
                _, history = common.learn_gp_mpc(ctx, name, rate, seed, 1.5, budget["gp_mpc"])
                rows += [{"system": system, "method": "gp_mpc", "seed": seed, "env_steps": h["transitions"],
                          "data_seconds": h["data_seconds"], "rmse": h["rmse"],
                          "violation_fraction": float("nan"), "failure_rate": h["failure_rate"],
                          "wall_s": h["fit_s"] + h["eval_s"]} for h in history]  # fmt: skip
                curves[system].setdefault("gp_mpc", []).append([(h["data_seconds"], h["rmse"]) for h in history])
        for method, runs in curves[system].items():
            median = median_curve(runs)
            seconds = [max(s, 0.1) for s, _ in median]  # round 0 (no data) drawn at 0.1 s on the log axis
            axis.plot(seconds, [r for _, r in median], "o-", label=method)
        if system in ORIGINAL_GP_MPC and budget["gp_mpc"] is not None:
            data = ORIGINAL_GP_MPC[system]
            axis.plot([max(s, 0.1) for s, _ in data], [r for _, r in data], "k:", label="original GP-MPC")
        axis.set_xscale("log")
        axis.set_yscale("log")
        common.style_system_axis(axis, system, "training data (s of simulated time)", "RMSE (median over seeds)")
    section.files.append(common.write_csv(ctx.out / "learning_curves.csv", rows))
    section.files.append(common.save_figure(figure, ctx.out / "learning_efficiency.png"))
    section.claims = claims(curves, missing, ctx.profile)
    section.notes += comparison({s: {m: median_curve(r) for m, r in c.items()} for s, c in curves.items()})
    if missing:
        section.notes.append(f"method {', '.join(sorted(missing))} not available in this build")
    section.notes.append(
        f"RMSE: the harness's per-episode RMSE, as the paper's: the full state, unweighted, on the cart-pole; x and "
        f"z only on the quadrotor; mean over {budget['episodes']} evaluation episodes (GP-MPC: its config's "
        f"eval_episodes), curves drawn as the median over {len(ctx.seeds)} seed(s). RL at 50 Hz, GP-MPC at 10 Hz."
    )
    return section


def median_curve(runs: list) -> list[tuple[float, float]]:
    """Seeds' curves, point by point (they share the x points): median x and median RMSE."""
    length = min(len(r) for r in runs)
    return [(float(np.median([r[i][0] for r in runs])), float(np.median([r[i][1] for r in runs])))
            for i in range(length)]  # fmt: skip


def claims(curves: dict, missing: set, profile: str) -> list[common.Claim]:
    """The figure's claims from ``curves`` (``{system: {method: [per-seed [(seconds, rmse), ...]]}}``), each judged on
    the median over seeds and testing every RL method it names (PPO and SAC where both ran)."""
    out = []
    for system, c in curves.items():
        rl = [m for m in ("ppo", "sac") if m in c]
        names = ["gp_mpc", *rl]
        text = f"GP-MPC reaches its best RMSE with a tenth (or less) of the data RL needs ({system})"
        if "gp_mpc" not in c or not rl:
            out.append(_absent(text, ["gp_mpc", "ppo", "sac"], c, missing, profile))
            continue
        times = {m: [converged_at(curve) for curve in c[m]] for m in names}
        out.append(common.seed_claim(
            text, times, lambda v, rl=rl: all(v["gp_mpc"] <= 0.1 * v[m] for m in rl),
            lambda v, rl=rl: f"GP-MPC within 10% of its best after {v['gp_mpc']:.1f} s; "
            + ", ".join(f"{m.upper()} after {v[m]:.0f} s" for m in rl),
            "RL's convergence is judged within its own training budget (the profile's)",
            needs_convergence=True, profile=profile))  # fmt: skip
        untrained = [curve[0][1] for curve in c["gp_mpc"]]
        matched = {m: [first_below(curve, level) for curve, level in zip(c[m], untrained, strict=True)] for m in rl}
        never = any(math.isinf(np.median(t)) for t in matched.values())
        out.append(common.seed_claim(
            f"The untrained GP-MPC's RMSE is only matched by RL after around 10^3 s of data ({system}; every RL "
            "method)", {**matched, "untrained": untrained},
            lambda v, rl=rl: all(MATCHED_AFTER <= v[m] < math.inf for m in rl),
            lambda v, rl=rl: f"prior MPC RMSE {v['untrained']:.4f}; matched by "
            + ", ".join(f"{m.upper()} at {'never' if math.isinf(v[m]) else f'{v[m]:.0f} s'}" for m in rl),
            "holds when every RL method first matches it at or after 10^2.5 s of data; never matching within the "
            "budget does not hold", needs_convergence=never, profile=profile))  # fmt: skip
        best_gp = [min(r for _, r in curve) for curve in c["gp_mpc"]]
        for m in rl:
            if system == "cartpole" or m == "ppo":
                out.append(common.seed_claim(
                    f"Once converged, {m.upper()} reaches a performance comparable to GP-MPC (final RMSE within "
                    f"{COMPARABLE:g}x of GP-MPC's best; {system})",
                    {m: [curve[-1][1] for curve in c[m]], "gp_mpc": best_gp},
                    lambda v, m=m: v[m] <= COMPARABLE * v["gp_mpc"],
                    lambda v, m=m: f"{m.upper()} {v[m]:.4f}, GP-MPC {v['gp_mpc']:.4f} "
                    f"({common.ratio_text(v[m], v['gp_mpc'])})",
                    needs_convergence=True, profile=profile))  # fmt: skip
    return out


def _absent(text, needed, have, missing, profile):
    unavailable = [m for m in needed if m in missing]
    if unavailable:
        return common.claim(text, None, "", missing=unavailable)
    return common.claim(text, None, f"{', '.join(m for m in needed if m not in have)} not run in the {profile} profile")


def comparison(curves: dict) -> list[str]:
    """The GP-MPC curves (median over seeds) beside the original's published data (spec §1,
    gpmpc_fig6_data.csv)."""
    notes = []
    for system, original in ORIGINAL_GP_MPC.items():
        ours = curves.get(system, {}).get("gp_mpc")
        theirs = "; ".join(f"{s:g} s: {r:.3f}" for s, r in original)
        if ours is None:
            notes.append(f"Original GP-MPC curve, {system} ({theirs}): GP-MPC not run in this profile.")
            continue
        mine = "; ".join(f"{s:g} s: {r:.3f}" for s, r in ours)
        ratio_0 = ours[0][1] / original[0][1]
        ratio_best = min(r for _, r in ours) / min(r for _, r in original)
        notes.append(
            f"GP-MPC vs the original's published curve, {system}: ours {mine}; original {theirs}. Untrained "
            f"(prior MPC) RMSE ours/original {ratio_0:.2f}, best RMSE ours/original {ratio_best:.2f}; within 10% of "
            f"its best after {converged_at(ours):g} s of data here, {converged_at(original):g} s in the original. "
            "Ours keeps every transition of a round's episodes and averages the RMSE over the steps after the reset; "
            "the original keeps part of each episode and its RMSE includes the initial state."
        )
    return notes
