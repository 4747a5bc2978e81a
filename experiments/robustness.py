"""Robustness (the paper's Fig 8): cart-pole stabilization RMSE against the pole length and against the standard
deviation of white noise on the input, for LQR, GP-MPC (150 % prior), PPO, PPO^DR, RAP and RARL.

Each sweep of each method is ONE evaluation by the common harness: the grid values are repeated ``episodes`` times
and put on a leading axis of the env params (``batched_params=True``), so JAX methods run every grid point and
episode in one vmapped closed loop (GP-MPC, a host controller, steps all copies together). Evaluation with
``done_on_out_of_bounds`` off, as in the original (a fallen pole counts with its whole error), from one fixed
initial state (x = 0.1 m, θ = 0.1 rad), so the episodes of a grid value differ only in their noise.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

import scg_jax
from scg_algorithms import make_controller
from scg_algorithms.evaluation import evaluate
from scg_experiments import common

NAME = "robustness"
TITLE = "Robustness to pole length and input noise (Fig 8)"

# The original's grids (utils/rl_cartpole_robustness.sh): pole half-lengths (m) and input-noise std (N).
POLE_LENGTHS = (0.15, 0.25, 0.5, 0.75, 1.25, 1.65, 2.0, 2.5, 3.0)
NOISE_STDS = (0.0, 0.005, 0.5, 1.0, 2.0, 4.0)
OFF_NOMINAL = (0.75, 1.25, 1.65)  # the lengths issue 15 averages PPO^DR's gain over

PROFILES = {
    "tiny": {"episodes": 2, "rl_steps": {}, "gp_mpc": None},
    "quick": {"episodes": 3, "rl_steps": {"ppo": 1_048_576, "ppo_dr": 1_048_576, "rap": 1_048_576, "rarl": 1_048_576},
              "gp_mpc": common.GP_MPC_LEARNING["quick"]},
    "paper": {"episodes": 10, "rl_steps": {"ppo": 4_194_304, "ppo_dr": 4_194_304, "rap": 4_194_304, "rarl": 4_194_304},
              "gp_mpc": common.GP_MPC_LEARNING["paper"]},
}  # fmt: skip

# Every copy starts from the same state, so a sweep's grid values differ only in the pole length or the noise (with
# random initial states, their spread hides the effect of the smaller noise levels at a few episodes per point).
EVAL = ["env.done_on_out_of_bounds=false", "env.init_state=[0.1, 0.0, 0.1, 0.0]"]
GP_MPC_RATE = ["env.ctrl_freq=10"]
# Each robust method's own settings, taken from the project's config of it (``configs/``) onto this result's plant
# (experiments/configs/cartpole.yaml), so every method is trained and scored on the same cart-pole: RARL's adversary
# pushes on the pole (dynamics channel, 0.1 N), RAP's two adversaries add to the cart force (action channel, 0.1 N),
# PPO^DR draws the pole length at every reset (absolute U(0.1, 1.0) m, the randomisation the original intended).
METHOD_SETTINGS = {
    "rarl": ("rarl", "paper_cartpole_rarl.yaml", ("env.adversary", "training.rarl")),
    "rap": ("rap", "paper_cartpole_rap.yaml", ("env.adversary", "training.rap")),
    "ppo_dr": ("ppo", "paper_cartpole_ppo_dr_absolute.yaml", ("env.physics_randomization",)),
}


def with_pole_length(params, length):
    return params.replace(physics=params.physics.replace(pole_half_length=length))


def with_input_noise(params, std):
    noise = params.disturbances["action"][0]
    return params.replace(
        disturbances={**params.disturbances, "action": (noise.replace(std=jnp.full_like(noise.std, std)),)}
    )


def sweep(env, params, controller, key, episodes: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean RMSE per pole length and per noise std, from ONE evaluation of ``(9 + 6) * episodes`` copies with
    batched params: the pole-length copies without noise, the noise copies at the nominal length."""
    nominal = float(params.physics.pole_half_length)
    grid = [(length, 0.0) for length in POLE_LENGTHS] + [(nominal, std) for std in NOISE_STDS]
    values = jnp.repeat(jnp.asarray(grid, jnp.float32), episodes, axis=0)
    batched = jax.vmap(lambda v: with_input_noise(with_pole_length(params, v[0]), v[1]))(values)
    evaluation = evaluate(env, batched, controller, key, len(values), batched_params=True, measure_time=False)
    rmse = np.asarray(evaluation.per_episode["rmse"], dtype=float).reshape(len(grid), episodes).mean(axis=1)
    return rmse[: len(POLE_LENGTHS)], rmse[len(POLE_LENGTHS) :]


def method_config(method: str, overrides=()):
    """``(algo, cfg)`` that trains ``method`` (``ppo``, ``ppo_dr``, ``rarl``, ``rap``) with ``overrides``
    (``"training.ALGO.KEY=VALUE"``, applied last), or ``(algo, None)`` in a build without its config file."""
    cfg = scg_jax.load_config(common.CONFIG_DIR / "cartpole.yaml")
    if method not in METHOD_SETTINGS:
        return method, scg_jax.load_config(cfg, list(overrides))
    algo, name, keys = METHOD_SETTINGS[method]
    found = common.repo_configs(name)
    return algo, (common.with_method(cfg, found[0], keys, overrides) if found else None)


def controllers(ctx, seed: int, budget: dict, env, params, env10, params10):
    """``{method: (controller, env, params)}`` for one seed, the methods not available in this build, and
    ``{method: error}`` for those whose training or loading failed (reported, not raised)."""
    cfg = scg_jax.load_config(common.CONFIG_DIR / "cartpole.yaml")
    out = {"lqr": (make_controller("lqr", env, params, cfg.controllers["lqr"]), env, params)}
    missing, failed = [], {}
    for method, steps in budget["rl_steps"].items():
        try:
            algo, train_cfg = method_config(method, budget.get("overrides", {}).get(method, ()))
            if train_cfg is None or not common.learner_available(algo):
                missing.append(method)
                continue
            policy, _ = common.train_policy(ctx, algo, train_cfg, seed, steps, env, params)
        except Exception as error:  # one method's failure is reported in its claims, the rest still run
            failed[method] = common.failure_text(error)
            ctx.log(f"  {method} failed: {failed[method]}")
            continue
        out[method] = (policy, env, params)
    if budget["gp_mpc"] is not None:
        try:
            directory, _ = common.learn_gp_mpc(ctx, "cartpole", GP_MPC_RATE, seed, 1.5, budget["gp_mpc"])
            out["gp_mpc"] = (common.load_gp_mpc(directory, env10, params10), env10, params10)
        except Exception as error:
            failed["gp_mpc"] = common.failure_text(error)
            ctx.log(f"  gp_mpc failed: {failed['gp_mpc']}")
    return out, missing, failed


def run(ctx: common.Context) -> common.Section:
    budget = ctx.budget(PROFILES)
    _, env, params = common.load("cartpole", EVAL)
    _, env10, params10 = common.load("cartpole", EVAL + GP_MPC_RATE)
    lengths, noise, missing, failed = {}, {}, set(), {}
    for seed in ctx.seeds:
        methods, absent, broken = controllers(ctx, seed, budget, env, params, env10, params10)
        missing |= set(absent)
        failed.update(broken)
        for name, (controller, e, p) in methods.items():
            try:
                with ctx.step(f"seed {seed}: {name}, both sweeps in one evaluation"):
                    by_length, by_noise = sweep(e, p, controller, jax.random.key(6161 + seed), budget["episodes"])
            except Exception as error:
                failed[name] = common.failure_text(error)
                ctx.log(f"  {name} failed: {failed[name]}")
                continue
            lengths.setdefault(name, []).append(by_length)
            noise.setdefault(name, []).append(by_noise)
    lengths = {name: np.mean(runs, axis=0) for name, runs in lengths.items() if name not in failed}
    noise = {name: np.mean(runs, axis=0) for name, runs in noise.items() if name not in failed}

    section = common.Section(NAME, TITLE)
    rows = [{"sweep": "pole_length", "value": v, **{m: float(r[i]) for m, r in lengths.items()}}
            for i, v in enumerate(POLE_LENGTHS)]  # fmt: skip
    rows += [{"sweep": "input_noise_std", "value": v, **{m: float(r[i]) for m, r in noise.items()}}
             for i, v in enumerate(NOISE_STDS)]  # fmt: skip
    section.files.append(common.write_csv(ctx.out / "robustness.csv", rows))
    plt = common.pyplot()
    figure, (left, right) = plt.subplots(1, 2, figsize=(10, 3.8), constrained_layout=True)
    for name in lengths:
        left.plot(POLE_LENGTHS, lengths[name], "o-", label=name)
        right.plot(NOISE_STDS, noise[name], "o-", label=name)
    left.set_xlabel("pole half-length l (m)")
    right.set_xlabel("input noise std σ_u (N)")
    for axis in (left, right):
        axis.set_ylabel("RMSE")
        axis.set_yscale("log")
        axis.grid(alpha=0.3)
        axis.legend(fontsize=7)
    section.files.append(common.save_figure(figure, ctx.out / "robustness.png"))
    section.claims = claims(lengths, noise, missing, ctx.profile, failed)
    section.notes += [f"{name} not measured: {error}" for name, error in sorted(failed.items())]
    if missing:
        section.notes.append(f"method {', '.join(sorted(missing))} not available in this build")
    section.notes.append(
        f"{budget['episodes']} episodes per grid point and seed, {len(ctx.seeds)} seed(s); RMSE is the harness's "
        "(Q-weighted) per-episode RMSE, mean over episodes and seeds; GP-MPC at 10 Hz, the rest at 50 Hz."
    )
    return section


def _mean_at(values: dict, name: str, grid, points) -> float:
    return float(np.mean([values[name][grid.index(p)] for p in points]))


def claims(lengths: dict, noise: dict, missing: set, profile: str, failed: dict | None = None) -> list[common.Claim]:
    """The claims of the figure; a method in ``missing`` makes a claim ``UNAVAILABLE``, one in ``failed``
    (``{method: error}``) ``NOT_MEASURED`` with the error."""
    out, failed = [], dict(failed or {})
    text = "RMSE rises with the input noise σ (LQR)"
    if "lqr" in noise:
        lq = noise["lqr"]
        rises = lq[-1] > lq[NOISE_STDS.index(1.0)] > lq[0]
        measured = ", ".join(f"σ={s:g}: {v:.4f}" for s, v in zip(NOISE_STDS, lq, strict=True))
        out.append(common.claim(text, bool(rises), measured))
    else:
        out.append(common.claim(text, None, f"not measured: lqr failed: {failed.get('lqr', 'not run')}"))

    def need(*names):
        return [n for n in names if n not in lengths]

    def absent(text, *names):
        unavailable = [n for n in names if n in missing]
        if unavailable:
            return common.claim(text, None, "", missing=unavailable)
        broken = [n for n in names if n in failed]
        if broken:
            return common.claim(text, None, "not measured: " + "; ".join(f"{n} failed: {failed[n]}" for n in broken))
        return common.claim(text, None, f"{', '.join(need(*names))} not run in the {profile} profile")

    text = "PPO^DR is more robust to pole length than PPO (mean RMSE over l = 0.75, 1.25, 1.65 m)"
    if need("ppo", "ppo_dr"):
        out.append(absent(text, "ppo", "ppo_dr"))
    else:
        a, b = (_mean_at(lengths, n, POLE_LENGTHS, OFF_NOMINAL) for n in ("ppo_dr", "ppo"))
        out.append(common.claim(text, a < b, f"PPO^DR {a:.4f}, PPO {b:.4f} ({common.ratio_text(a, b)})"))
    text = "RAP is more robust to input noise than PPO (RMSE at σ = 2 N)"
    if need("ppo", "rap"):
        out.append(absent(text, "ppo", "rap"))
    else:
        a, b = (noise[n][NOISE_STDS.index(2.0)] for n in ("rap", "ppo"))
        out.append(common.claim(text, a < b, f"RAP {a:.4f}, PPO {b:.4f} ({common.ratio_text(a, b)})"))
    text = "RAP is less robust to parameter mismatch than PPO^DR (mean RMSE over off-nominal pole lengths)"
    if need("rap", "ppo_dr"):
        out.append(absent(text, "rap", "ppo_dr"))
    else:
        a, b = (_mean_at(lengths, n, POLE_LENGTHS, OFF_NOMINAL) for n in ("rap", "ppo_dr"))
        out.append(common.claim(text, a > b, f"RAP {a:.4f}, PPO^DR {b:.4f}"))
    off = [v for v in POLE_LENGTHS if v != 0.5]
    for model in ("lqr", "gp_mpc"):
        text = f"{model.upper()} is less affected by pole length than PPO (mean RMSE over the off-nominal lengths)"
        if need(model, "ppo"):
            out.append(absent(text, model, "ppo"))
        else:
            a, b = (_mean_at(lengths, n, POLE_LENGTHS, off) for n in (model, "ppo"))
            fallen = [v for v, r in zip(POLE_LENGTHS, lengths[model], strict=True) if r > 1.0]
            note = (
                f"{model} loses the pole (RMSE > 1) at l = {', '.join(f'{v:g}' for v in fallen)} m: its model "
                "is the nominal (or 150%) pole, far from these lengths"
                if a >= b and fallen
                else ""
            )
            out.append(common.claim(text, a < b, f"{model} {a:.4f}, PPO {b:.4f} ({common.ratio_text(a, b)})", note))
    text = "LQR is no less resilient to input noise than PPO (mean RMSE over σ within 1.2x of PPO's or lower)"
    if need("ppo"):
        out.append(absent(text, "ppo"))
    else:
        a, b = float(np.mean(noise["lqr"])), float(np.mean(noise["ppo"]))
        out.append(common.claim(text, a <= 1.2 * b, f"LQR {a:.4f}, PPO {b:.4f} ({common.ratio_text(a, b)})"))
    return out
