"""Learning efficiency (the paper's Fig 6): RMSE against seconds of simulated training data (log axis) for GP-MPC
(150 % prior), PPO and SAC, on the cart-pole stabilization and the 2D quadrotor circle.

GP-MPC's curve is its learning loop's rounds (round 0: the prior's MPC, no data); the RL curves evaluate the
deterministic policy with the common harness after a log-spaced series of env-step budgets of one training run.
Training data in seconds: env steps times the control period (RL at 50 Hz, GP-MPC at 10 Hz), as in the paper.
"""

from __future__ import annotations

import math

import numpy as np

import scg_jax
from scg_experiments import common

NAME = "learning_efficiency"
TITLE = "Learning efficiency: RMSE against training data (Fig 6)"

PROFILES = {
    "tiny": {
        "systems": ["cartpole"], "episodes": 2, "gp_mpc": None,
        "rl_points": {"cartpole": {"ppo": [1024, 2048]}},
        "overrides": {"ppo": ["training.ppo.num_envs=32", "training.ppo.num_minibatches=2"]},
    },
    "quick": {
        "systems": ["cartpole", "quadrotor_circle"], "episodes": 4,
        "gp_mpc": common.GP_MPC_LEARNING["quick"],
        "rl_points": {
            "cartpole": {"ppo": [16_384, 65_536, 262_144, 1_048_576], "sac": [10_000, 30_000, 60_000]},
            "quadrotor_circle": {"ppo": [65_536, 262_144, 1_048_576, 2_097_152], "sac": [10_000, 30_000, 60_000]},
        },
        "overrides": {},
    },
    "paper": {
        "systems": ["cartpole", "quadrotor_circle"], "episodes": 10,
        "gp_mpc": common.GP_MPC_LEARNING["paper"],
        "rl_points": {
            "cartpole": {"ppo": [16_384, 65_536, 262_144, 1_048_576, 4_194_304],
                         "sac": [10_000, 25_000, 50_000, 100_000, 150_000]},
            "quadrotor_circle": {"ppo": [65_536, 262_144, 1_048_576, 4_194_304, 8_388_608],
                                 "sac": [10_000, 30_000, 100_000, 300_000]},
        },
        "overrides": {},
    },
}  # fmt: skip

EVAL = ["env.done_on_out_of_bounds=false"]
GP_MPC_RATE = ["env.ctrl_freq=10"]

# The original's GP-MPC curves (gpmpc_fig6_data.csv; spec §1): seconds of data (transitions / 10 Hz) -> RMSE.
ORIGINAL_GP_MPC = {
    "cartpole": [(0.0, 0.818), (9.3, 0.129), (17.7, 0.129), (27.5, 0.129), (37.0, 0.1287), (46.4, 0.1288),
                 (56.0, 0.1288), (63.8, 0.1288)],
    "quadrotor_circle": [(0.0, 0.259), (5.1, 0.112), (10.2, 0.116), (15.3, 0.115), (20.4, 0.108), (25.5, 0.080),
                         (30.6, 0.105), (35.7, 0.104), (40.8, 0.102), (45.9, 0.104)],
}  # fmt: skip


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
                cfg = scg_jax.load_config(common.CONFIG_DIR / f"{system}.yaml", budget["overrides"].get(algo, []))
                curve = common.learning_curve(ctx, algo, cfg, seed, points, env, params, budget["episodes"])
                rows += [{"system": system, "method": algo, "seed": seed, **r} for r in curve]
                curves[system].setdefault(algo, []).append([(r["data_seconds"], r["rmse"]) for r in curve])
            if budget["gp_mpc"] is not None:
                _, history = common.learn_gp_mpc(ctx, system, GP_MPC_RATE, seed, 1.5, budget["gp_mpc"])
                rows += [{"system": system, "method": "gp_mpc", "seed": seed, "env_steps": h["transitions"],
                          "data_seconds": h["data_seconds"], "rmse": h["rmse"],
                          "violation_fraction": float("nan"), "failure_rate": h["failure_rate"],
                          "wall_s": h["fit_s"] + h["eval_s"]} for h in history]  # fmt: skip
                curves[system].setdefault("gp_mpc", []).append([(h["data_seconds"], h["rmse"]) for h in history])
        for method, runs in curves[system].items():
            mean = _mean_curve(runs)
            curves[system][method] = mean
            seconds = [max(s, 0.1) for s, _ in mean]  # round 0 (no data) drawn at 0.1 s on the log axis
            axis.plot(seconds, [r for _, r in mean], "o-", label=method)
        if system in ORIGINAL_GP_MPC and budget["gp_mpc"] is not None:
            data = ORIGINAL_GP_MPC[system]
            axis.plot([max(s, 0.1) for s, _ in data], [r for _, r in data], "k:", label="original GP-MPC")
        axis.set_xscale("log")
        axis.set_yscale("log")
        axis.set_xlabel("training data (s of simulated time)")
        axis.set_ylabel("RMSE")
        axis.set_title(system)
        axis.grid(alpha=0.3)
        axis.legend(fontsize=7)
    section.files.append(common.write_csv(ctx.out / "learning_curves.csv", rows))
    section.files.append(common.save_figure(figure, ctx.out / "learning_efficiency.png"))
    section.claims = claims(curves, missing, ctx.profile)
    section.notes += comparison(curves)
    if missing:
        section.notes.append(f"method {', '.join(sorted(missing))} not available in this build")
    section.notes.append(
        f"RMSE: the harness's per-episode RMSE of the Q-weighted error (cart-pole Q = I: the full state, as in the "
        f"paper; quadrotor Q = (1, 0.1, 1, 0.1, 0.1, 0.1): x and z dominate, where the paper uses x and z only), "
        f"mean over {budget['episodes']} evaluation episodes and {len(ctx.seeds)} seed(s)."
    )
    return section


def _mean_curve(runs: list) -> list[tuple[float, float]]:
    """Seeds' curves averaged point by point (they share the x points)."""
    length = min(len(r) for r in runs)
    return [(float(np.mean([r[i][0] for r in runs])), float(np.mean([r[i][1] for r in runs]))) for i in range(length)]


def claims(curves: dict, missing: set, profile: str) -> list[common.Claim]:
    out = []
    for system in curves:
        c = curves[system]
        rl = {m: c[m] for m in ("ppo", "sac") if m in c}
        text = f"GP-MPC reaches its best RMSE with a tenth (or less) of the data RL needs ({system})"
        if "gp_mpc" not in c or not rl:
            out.append(_absent(text, ["gp_mpc", "ppo", "sac"], c, missing, profile))
            continue
        t_gp = converged_at(c["gp_mpc"])
        t_rl = {m: converged_at(curve) for m, curve in rl.items()}
        out.append(
            common.claim(
                text,
                t_gp <= 0.1 * min(t_rl.values()),
                f"GP-MPC within 10% of its best after {t_gp:.1f} s; "
                + ", ".join(f"{m.upper()} after {t:.0f} s" for m, t in t_rl.items()),
                "RL's convergence is judged within its own training budget (the profile's)",
            )
        )
        untrained = c["gp_mpc"][0][1]
        matched = {m: first_below(curve, untrained) for m, curve in rl.items()}
        first = min(matched.values())
        out.append(common.claim(
            f"The untrained GP-MPC's RMSE is only matched by RL after around 10^3 s of data ({system})",
            first >= 10**2.5, f"prior MPC RMSE {untrained:.4f}; matched by "
            + ", ".join(f"{m.upper()} at {'never' if math.isinf(t) else f'{t:.0f} s'}" for m, t in matched.items()),
            "holds when RL needs at least 10^2.5 s (or never matches within its budget)"))  # fmt: skip
        best_gp = min(r for _, r in c["gp_mpc"])
        for m, curve in rl.items():
            if system == "cartpole" or m == "ppo":
                final = curve[-1][1]
                text = (f"Once converged, {m.upper()} reaches a performance comparable to GP-MPC (final RMSE within "
                        f"1.5x of GP-MPC's best; {system})")  # fmt: skip
                out.append(
                    common.claim(
                        text,
                        final <= 1.5 * best_gp,
                        f"{m.upper()} {final:.4f}, GP-MPC {best_gp:.4f} ({common.ratio_text(final, best_gp)})",
                    )
                )
    return out


def _absent(text, needed, have, missing, profile):
    unavailable = [m for m in needed if m in missing]
    if unavailable:
        return common.claim(text, None, "", missing=unavailable)
    return common.claim(text, None, f"{', '.join(m for m in needed if m not in have)} not run in the {profile} profile")


def comparison(curves: dict) -> list[str]:
    """The GP-MPC curves beside the original's published data (spec §1, gpmpc_fig6_data.csv)."""
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
            "Absolute values differ with the initial states, the episode length and (quadrotor) the RMSE's weights."
        )
    return notes
