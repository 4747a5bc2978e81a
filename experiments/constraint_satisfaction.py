"""Constraint satisfaction (the paper's Fig 7).

Top: fraction of control steps in violation of θ, θ̇ ∈ [-0.2, 0.2] against seconds of simulated training data, for
GP-MPC (150 % prior; its learning rounds at 10 Hz, the original's Fig 7 settings), PPO, safety-layer PPO
(``safe_ppo``), PPO-Lagrangian (``ppo_lagrangian``) (learning curves at 50 Hz updating every 400 env steps, 8 s of
data, as the original's PPO; each point the deterministic policy scored by the common harness) and the learned CBF
(``scg_algorithms.safety_filters``, filtering the 150 %-prior LQR). Curves are per seed; the claims are judged on
the median over seeds.

Bottom: the "impossible" 2D quadrotor tracking (a circle wider than the state box), one episode of 51 points at
10 Hz, for linear MPC with the 150 % prior, GP-MPC and safety-layer PPO, drawn in the x-z plane with the box; the
count of points outside the box beside the original's published counts (25 of 51 for linear MPC, 0 for GP-MPC).
"""

from __future__ import annotations

import importlib

import jax
import numpy as np

import scg_jax
from scg_algorithms import make_controller
from scg_algorithms.evaluation import evaluate
from scg_experiments import common

NAME = "constraint_satisfaction"
TITLE = "Constraint satisfaction (Fig 7)"

PROFILES = {
    "tiny": {"episodes": 2, "rl_points": {}, "gp_mpc": None, "impossible": ["linear_mpc"], "overrides": {},
             "impossible_rl_steps": 0},
    "quick": {
        "episodes": 4,
        "rl_points": {name: [4_000, 10_000, 20_000, 40_000, 100_000] for name in ("ppo", "safe_ppo", "ppo_lagrangian")},
        "gp_mpc": common.GP_MPC_LEARNING["quick"],
        "impossible": ["linear_mpc", "gp_mpc", "safe_ppo"], "impossible_rl_steps": 1_048_576, "overrides": {},
        "cbf": {"num_episodes": 8, "num_copies": 64, "train_iterations": 100, "eval_episodes": 32},
    },
    "paper": {
        "episodes": 10,
        "rl_points": {name: [4_000, 10_000, 20_000, 40_000, 100_000, 200_000, 400_000, 1_000_000]
                      for name in ("ppo", "safe_ppo", "ppo_lagrangian")},
        "gp_mpc": common.GP_MPC_LEARNING["paper"],
        "impossible": ["linear_mpc", "gp_mpc", "safe_ppo"], "impossible_rl_steps": 4_194_304, "overrides": {},
        "cbf": {"num_episodes": 20},
    },
}  # fmt: skip

EVAL = ["env.done_on_out_of_bounds=false"]
GP_MPC_RATE = ["env.ctrl_freq=10"]
BOX = {"x": (-0.4, 0.4), "z": (-0.01, 0.9)}  # the impossible task's state box (m)
IMPOSSIBLE = " (impossible tracking)"  # suffix of a method's failure on the impossible task in ``failed``
ORIGINAL_OUTSIDE = {"linear_mpc": 25, "gp_mpc": 0}  # of 51 points (spec §1, fig7_csvs)


def learned_cbf_curve(ctx, env, params, key, episodes: int, learning: dict) -> tuple[list | None, str]:
    """The learned CBF on the 150 % prior: ``(rows, note)``; rows None when the filter is missing.

    Looks the filter up by its registry name (``FILTERS['learned_cbf']``, a ``module:factory`` string or a
    factory). When its module has a ``train_learned_cbf`` learning loop, the curve is its history (violation
    fraction of the filter under random inputs against seconds of data, options ``learning``); the last point adds
    the trained filter certifying the 150 %-prior LQR, scored by the harness. Otherwise one point: the untrained
    filter on that LQR.
    """
    entry = common.safety_filter("learned_cbf")
    if entry is None:
        return None, "method learned_cbf not available in this build"
    try:
        filters = importlib.import_module("scg_algorithms.safety_filters")
        factory, module = entry, None
        if isinstance(entry, str):
            module_name, _, attribute = entry.partition(":")
            module = importlib.import_module(module_name)
            factory = getattr(module, attribute)
        prior = scg_jax.prior_params(env, params, 1.5)
        cfg = scg_jax.load_config(common.CONFIG_DIR / "cartpole_constraint.yaml")
        rows, what = [], "the untrained filter"
        if module is not None and hasattr(module, "train_learned_cbf"):
            result = module.train_learned_cbf(env, params, prior, learning)
            flt, what = result.filter, f"after {len(result.history) - 1} blending episodes"
            rows = [{"data_seconds": float(h["data_seconds"]), "violation_fraction": float(h["violation_fraction"]),
                     "rmse": float("nan")} for h in result.history]  # fmt: skip
        else:
            flt = factory(env, prior, None)
        controller = filters.filtered(make_controller("lqr", env, prior, cfg.controllers["lqr"]), flt)
        evaluation = evaluate(env, params, controller, key, episodes, measure_time=False)
    except Exception as error:  # a filter whose interface differs from the one this result was written against
        return None, f"learned_cbf is registered but could not be run by this result: {type(error).__name__}: {error}"
    lqr_row = {
        "data_seconds": rows[-1]["data_seconds"] if rows else 0.0,
        "violation_fraction": common.violation_fraction(evaluation),
        "rmse": float(evaluation.summary["rmse"]),
    }
    note = (
        f"learned_cbf: curve = its learning loop's violation fraction under random inputs; {what}, certifying the "
        f"150%-prior LQR: violation fraction {lqr_row['violation_fraction']:.3f}, RMSE {lqr_row['rmse']:.4f}"
    )
    return (rows or [lqr_row]), note


def top(ctx, budget, failed: dict) -> tuple[dict, set, list[str], list[dict]]:
    """Violation fraction against training data per method, ``{method: [one [(seconds, fraction), ...] per seed]}``
    (the learned CBF: one run); a method whose learning fails is added to ``failed`` (``{method: error}``) and left
    out."""
    _, env, params = common.load("cartpole_constraint", EVAL)
    curves, missing, notes, rows = {}, set(), [], []
    for seed in ctx.seeds:
        for algo, points in budget["rl_points"].items():
            if not common.learner_available(algo):
                missing.add(algo)
                continue
            if algo in failed:
                continue
            try:
                overrides = budget["overrides"].get(algo, [])
                cfg = scg_jax.load_config(common.CONFIG_DIR / "cartpole_constraint.yaml", overrides)
                curve = common.learning_curve(ctx, algo, cfg, seed, points, env, params, budget["episodes"])
            except Exception as error:  # reported in the claims; the other methods still run
                failed[algo] = common.failure_text(error)
                ctx.log(f"  {algo} failed: {failed[algo]}")
                continue
            rows += [{"method": algo, "seed": seed, **r} for r in curve]
            curves.setdefault(algo, []).append([(r["data_seconds"], r["violation_fraction"]) for r in curve])
        if budget["gp_mpc"] is not None and "gp_mpc" not in failed:
            try:
                _, history = common.learn_gp_mpc(ctx, "cartpole_constraint", GP_MPC_RATE, seed, 1.5, budget["gp_mpc"])
            except Exception as error:
                failed["gp_mpc"] = common.failure_text(error)
                ctx.log(f"  gp_mpc failed: {failed['gp_mpc']}")
                continue
            length = 5.0 * 10  # control steps per 5 s episode at 10 Hz
            curve = [(h["data_seconds"], h["constraint_violation_steps"] / length) for h in history]
            rows += [{"method": "gp_mpc", "seed": seed, "data_seconds": s, "violation_fraction": v} for s, v in curve]
            curves.setdefault("gp_mpc", []).append(curve)
    for method in failed:  # a method that failed on one seed is not averaged over the others
        curves.pop(method, None)
    if budget["rl_points"]:  # the learned CBF belongs to the learning comparison, not to the tiny profile
        cbf_rows, note = learned_cbf_curve(ctx, env, params, jax.random.key(7), budget["episodes"], budget["cbf"])
        notes.append("The learned CBF is one run (seed-independent), set beside every seed of the others in the claims")
        notes.append(note)
        if cbf_rows is None and "not available" in note:
            missing.add("learned_cbf")
        elif cbf_rows is None:
            failed["learned_cbf"] = note.split(": ", 1)[-1]
        elif cbf_rows:
            rows += [{"method": "learned_cbf", "seed": 0, **r} for r in cbf_rows]
            curves["learned_cbf"] = [[(r["data_seconds"], r["violation_fraction"]) for r in cbf_rows]]
    return curves, missing, notes, rows


def median_curve(runs: list) -> list[tuple[float, float]]:
    """Per-seed curves point by point (they share the x points): median x, median violation fraction."""
    return [(float(np.median([r[i][0] for r in runs])), float(np.median([r[i][1] for r in runs])))
            for i in range(min(len(r) for r in runs))]  # fmt: skip


def impossible(ctx, budget, failed: dict) -> tuple[dict, set, list[str]]:
    """x-z paths of one episode of the impossible task per method, and the methods not available; a method that
    fails is added to ``failed`` (``{method: error}``)."""
    cfg, env, params = common.load("quadrotor_impossible")
    key = jax.random.key(0)
    prior = scg_jax.prior_params(env, params, 1.5)
    paths, missing, notes, reference = {}, set(), [], None
    for method in budget["impossible"]:
        if method not in ("linear_mpc", "gp_mpc") and not common.learner_available(method):
            missing.add(method)
            continue
        try:
            if method == "linear_mpc":
                controller = make_controller("linear_mpc", env, prior, cfg.controllers["linear_mpc"])
            elif method == "gp_mpc":
                directory, _ = common.learn_gp_mpc(ctx, "quadrotor_impossible", [], ctx.seeds[0], 1.5,
                                                   budget["gp_mpc"])  # fmt: skip
                controller = common.load_gp_mpc(directory, env, params)
            else:
                train_cfg = scg_jax.load_config(cfg, budget["overrides"].get(method, []))
                steps = budget["impossible_rl_steps"]
                controller, _ = common.train_policy(ctx, method, train_cfg, ctx.seeds[0], steps, env, params)
            with ctx.step(f"impossible tracking: {method}"):
                evaluation = evaluate(env, params, controller, key, 1, measure_time=False)
        except Exception as error:  # reported in the claims; the other methods still run
            failed[method + IMPOSSIBLE] = common.failure_text(error)
            ctx.log(f"  {method} (impossible tracking) failed: {failed[method + IMPOSSIBLE]}")
            continue
        paths[method] = np.asarray(evaluation.trajectory["x"])[:, 0][:, [0, 2]]
        reference = np.asarray(evaluation.trajectory["x_ref"])[:, 0][:, [0, 2]]
    paths["reference"] = reference
    return paths, missing, notes


def outside(path: np.ndarray) -> int:
    """Points of an (N, 2) x-z path outside the box."""
    x, z = path[:, 0], path[:, 1]
    return int(np.sum((x < BOX["x"][0]) | (x > BOX["x"][1]) | (z < BOX["z"][0]) | (z > BOX["z"][1])))


def run(ctx: common.Context) -> common.Section:
    budget = ctx.budget(PROFILES)
    section = common.Section(NAME, TITLE)
    failed = {}
    curves, missing, notes, rows = top(ctx, budget, failed)
    paths, missing_b, notes_b = impossible(ctx, budget, failed)
    missing |= missing_b
    plt = common.pyplot()
    figure, (upper, lower) = plt.subplots(1, 2, figsize=(11, 4), constrained_layout=True)
    medians = {method: median_curve(runs) for method, runs in curves.items()}
    for method, curve in medians.items():
        upper.plot([max(s, 0.1) for s, _ in curve], [v for _, v in curve], "o-", label=method)
    upper.set_xscale("log")
    upper.set_xlabel("training data (s of simulated time)")
    upper.set_ylabel("fraction of steps in violation (median over seeds)")
    upper.set_title("cart-pole, θ and θ̇ in ±0.2")
    upper.grid(alpha=0.3)
    if curves:
        upper.legend(fontsize=7)
    counts = {}
    for method, path in paths.items():
        if path is None:
            continue
        if method == "reference":
            lower.plot(path[:, 0], path[:, 1], "k:", label="reference")
            continue
        counts[method] = outside(path)
        lower.plot(path[:, 0], path[:, 1], ".-", label=f"{method} ({counts[method]} of {len(path)} outside)")
    (x0, x1), (z0, z1) = BOX["x"], BOX["z"]
    lower.plot([x0, x1, x1, x0, x0], [z0, z0, z1, z1, z0], "r-", lw=1, label="constraints")
    lower.set_xlabel("x (m)")
    lower.set_ylabel("z (m)")
    lower.set_aspect("equal")
    lower.set_title('2D quadrotor, "impossible" tracking')
    lower.legend(fontsize=7)
    section.files.append(common.write_csv(ctx.out / "violations.csv", rows) if rows else None)
    section.files.append(
        common.write_data(
            ctx.out / "impossible_paths.json", {m: (None if p is None else p.tolist()) for m, p in paths.items()}
        )
    )
    section.files.append(common.save_figure(figure, ctx.out / "constraint_satisfaction.png"))
    section.files = [f for f in section.files if f]
    points = next((len(p) for p in paths.values() if p is not None), 51)
    section.claims = claims(curves, counts, missing, ctx.profile, points, failed, len(ctx.seeds))
    section.notes += notes + notes_b
    section.notes += [f"{name} not measured: {error}" for name, error in sorted(failed.items())]
    for method, count in counts.items():
        if method in ORIGINAL_OUTSIDE:
            section.notes.append(f"Impossible tracking, {method}: {count} of 51 points outside the box here; the "
                                 f"original's published count: {ORIGINAL_OUTSIDE[method]} of 51.")  # fmt: skip
    if "gp_mpc" in medians:
        section.notes.append(
            "GP-MPC violating steps per 50-step episode (median over seeds), here: "
            + ", ".join(f"{s:.0f} s: {v * 50:.2f}" for s, v in medians["gp_mpc"])
            + "; the original (gpmpc_number_viols.csv): prior MPC mean 0.5 (max 1), then 0 after 192, 376, ... "
            "1280 transitions."
        )
    if missing:
        section.notes.append(f"method {', '.join(sorted(missing))} not available in this build")
    return section


def claims(curves: dict, counts: dict, missing: set, profile: str, points: int, failed: dict | None = None,
           seeds: int = 1) -> list[common.Claim]:  # fmt: skip
    """The claims of the figure; a method in ``missing`` makes a claim ``UNAVAILABLE``, one in ``failed``
    (``{method: error}``, the impossible task's as ``"<method> (impossible tracking)"``) ``NOT_MEASURED`` with the
    error. ``curves``: ``{method: [per-seed curve]}``; a method with one run (the learned CBF) stands beside each of
    the ``seeds`` of the others. Claims naming RL read ``NOT_CONVERGED`` outside the paper profile when they do not
    hold."""
    out, failed = [], dict(failed or {})

    def per_seed(method, value):
        runs = curves[method]
        return [value(run) for run in (runs if len(runs) > 1 else runs * seeds)]

    def final(run):
        return run[-1][1]

    def reached(run):  # seconds of data at which a curve first reaches its final level
        return next(s for s, v in run if v <= run[-1][1] + 1e-9)

    def absent(text, *names, task=""):
        unavailable = [n for n in names if n in missing]
        if unavailable:
            return common.claim(text, None, "", missing=unavailable)
        broken = [n + task for n in names if n + task in failed]
        if broken:
            return common.claim(text, None, "not measured: " + "; ".join(f"{n} failed: {failed[n]}" for n in broken))
        return common.claim(
            text, None, f"{', '.join(n for n in names if n not in curves)} not run in the {profile} profile"
        )

    def fractions(v):
        return ", ".join(f"{n} {x:.3f}" for n, x in v.items())

    text = "After training, GP-MPC, the learned CBF and safety-layer PPO reach similar constraint satisfaction (final violation fractions within 0.02 of each other)"  # noqa: E501
    names = ("gp_mpc", "learned_cbf", "safe_ppo")
    if all(n in curves for n in names):
        out.append(common.seed_claim(text, {n: per_seed(n, final) for n in names},
                                     lambda v: max(v.values()) - min(v.values()) <= 0.02, fractions,
                                     needs_convergence=True, profile=profile))  # fmt: skip
    else:
        out.append(absent(text, *names))
    for better in ("gp_mpc", "learned_cbf", "safe_ppo"):
        text = f"Vanilla PPO cannot match {better}'s constraint satisfaction after training (final violation fraction)"
        if "ppo" in curves and better in curves:
            note = ("the learned CBF's curve is its learning loop's evaluation under random inputs, a harsher test "
                    "than a trained policy's own episodes" if better == "learned_cbf" else "")  # fmt: skip
            out.append(common.seed_claim(text, {"ppo": per_seed("ppo", final), better: per_seed(better, final)},
                                         lambda v, b=better: v["ppo"] > v[b], fractions, note,
                                         needs_convergence=True, profile=profile))  # fmt: skip
        else:
            out.append(absent(text, "ppo", better))
    text = "GP-MPC and the learned CBF need much less training data than safety-layer PPO to minimise violations (seconds of data to reach their final level, each below safety-layer PPO's)"  # noqa: E501
    names = ("gp_mpc", "learned_cbf", "safe_ppo")
    if all(n in curves for n in names):
        out.append(common.seed_claim(text, {n: per_seed(n, reached) for n in names},
                                     lambda v: v["gp_mpc"] < v["safe_ppo"] and v["learned_cbf"] < v["safe_ppo"],
                                     lambda v: ", ".join(f"{n} {x:.0f} s" for n, x in v.items()),
                                     needs_convergence=True, profile=profile))  # fmt: skip
    else:
        out.append(absent(text, *names))
    text = "Impossible tracking: linear MPC with the 150% prior violates the box"
    if "linear_mpc" in counts:
        out.append(
            common.claim(
                text,
                counts["linear_mpc"] > 0,
                f"{counts['linear_mpc']} of {points} points outside (original: 25 of 51)",
            )
        )
    else:
        out.append(absent(text, "linear_mpc", task=IMPOSSIBLE))
    text = "Impossible tracking: GP-MPC meets the constraints (fewer points outside than linear MPC 150%, at most 2)"
    if "gp_mpc" in counts and "linear_mpc" in counts:
        g, l = counts["gp_mpc"], counts["linear_mpc"]
        out.append(common.claim(text, g < l and g <= 2, f"GP-MPC {g}, linear MPC {l} of {points} (original: 0 and 25)"))
    else:
        out.append(absent(text, "gp_mpc", task=IMPOSSIBLE))
    text = (
        "Impossible tracking: safety-layer PPO does not fully guarantee constraint satisfaction (some points outside)"
    )
    if "safe_ppo" in counts:
        out.append(common.claim(text, counts["safe_ppo"] > 0, f"{counts['safe_ppo']} of {points} points outside",
                                needs_convergence=True, profile=profile))  # fmt: skip
    else:
        out.append(absent(text, "safe_ppo", task=IMPOSSIBLE))
    return out
