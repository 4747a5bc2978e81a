"""Robustness (the paper's Fig 8): cart-pole stabilization RMSE and failure rate against the pole length and against
the standard deviation of white noise on the input, for LQR, GP-MPC (150 % prior), PPO, PPO^DR, RAP and RARL.

Each method's two sweeps are ONE evaluation by the common harness: every (grid value, episode) pair is a copy with
its own env params (``batched_params=True``), so JAX methods run the whole grid in one vmapped closed loop (GP-MPC, a
host controller, steps all copies together). Episodes start from the task's randomised initial states (x ~ U[-0.3,
0.3] m, theta ~ U[-0.1, 0.1] rad), drawn per seed and episode; as in the original (episode i seeded i at every grid
value), episode i starts from the same state at every grid value and for every method of a seed. Evaluation runs
with ``done_on_out_of_bounds`` off, as in the original, so a fallen pole keeps its whole error; an episode whose cart
leaves the track (|x| > 2.4 m) or whose pole falls (|theta| > pi/2) counts as a failure.

Scores: per seed and grid value, the median over episodes of the per-episode RMSE (full state, unweighted) and the
failure rate; the claims compare medians (so a few runaway episodes do not decide them) and report the failure
rates beside them; each claim is judged on the median over seeds and says how many seeds agree.
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

# The original's grids (utils/rl_cartpole_robustness.sh): pole half-lengths (m) and input-noise std (N); its GP-MPC
# sweeps 0.5 m x (0.3, 0.5, 1, 1.5, 3.3) (gpmpc_cartpole_pole_length_robustness_150.yaml).
POLE_LENGTHS = (0.15, 0.25, 0.5, 0.75, 1.25, 1.65, 2.0, 2.5, 3.0)
GP_MPC_POLE_LENGTHS = (0.15, 0.25, 0.5, 0.75, 1.65)
NOISE_STDS = (0.0, 0.005, 0.5, 1.0, 2.0, 4.0)
NOMINAL_LENGTH = 0.5
OFF_NOMINAL = (0.75, 1.25, 1.65)  # the lengths PPO^DR's gain is judged over, inside its U(0.1, 1.0) m
MODEL_OFF_NOMINAL = (0.15, 0.25, 0.75, 1.65)  # the off-nominal lengths every method (GP-MPC too) runs at
HIGH_NOISE = (2.0, 4.0)  # the noise levels RAP's gain is judged at
EPISODE_KEY = 6161  # the original's seed of the pole-length sweep; a seed's episodes are drawn from key(6161 + seed)

PROFILES = {
    "tiny": {"episodes": 2, "rl_steps": {}, "gp_mpc": None},
    "quick": {"episodes": 3, "rl_steps": {"ppo": 1_048_576, "ppo_dr": 1_048_576, "rap": 1_048_576, "rarl": 1_048_576},
              "gp_mpc": common.GP_MPC_LEARNING["quick"]},
    "paper": {"episodes": 10, "rl_steps": {"ppo": 4_194_304, "ppo_dr": 4_194_304, "rap": 4_194_304, "rarl": 4_194_304},
              "gp_mpc": common.GP_MPC_LEARNING["paper"]},
}  # fmt: skip

EVAL = ["env.done_on_out_of_bounds=false"]
GP_MPC_RATE = ["env.ctrl_freq=10"]
# The original's gpmpc_cartpole_{pole_length,input_white_noise}_robustness_150.yaml: the GP of the control figure
# (experiments/configs/cartpole.yaml's controllers.gp_mpc, learned once per seed) run with horizon 25, Q = diag(3,
# 1, 3, 1), R = 1, prob 0.95.
GP_MPC_OPTIONS = {"horizon": 25, "q_diag": (3.0, 1.0, 3.0, 1.0), "r_diag": (1.0,), "prob": 0.95}
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


def with_initial_state(params, x0):
    """``params`` whose episodes start at ``x0`` (nx,): the initial-state distribution narrowed to that point."""
    x0 = jnp.asarray(x0, params.init_state.low.dtype)
    return params.replace(init_state=params.init_state.replace(low=x0, high=x0))


def initial_states(env, params, seed: int, episodes: int) -> np.ndarray:
    """(episodes, nx) initial states of a seed's episodes, drawn from the task's distribution (``params.init_state``)
    with the keys ``split(key(EPISODE_KEY + seed), episodes)``."""
    from scg_jax import randomization

    keys = jax.random.split(jax.random.key(EPISODE_KEY + seed), episodes)
    return np.asarray(jax.vmap(lambda k: randomization.draw(env.init_state_spec, params.init_state, k))(keys))


def grid(lengths=POLE_LENGTHS) -> list[tuple[str, float, float, float]]:
    """The sweeps' grid points ``(sweep, value, pole length, noise std)``: the lengths without noise, then the noise
    levels at the nominal length."""
    return [("pole_length", v, v, 0.0) for v in lengths] + [
        ("input_noise_std", s, NOMINAL_LENGTH, s) for s in NOISE_STDS
    ]


def sweep(env, params, controller, key, starts: np.ndarray, lengths=POLE_LENGTHS) -> dict:
    """Both sweeps of one controller in ONE evaluation of ``len(grid(lengths)) * episodes`` copies with batched
    params; episode ``e`` of every grid point starts at ``starts[e]``.

    Returns:
        ``{"grid": grid(lengths), "rmse": (points, episodes), "failed": (points, episodes) bool, "x0": (points,
        episodes, nx)}`` with the RMSE (the harness's, full state unweighted) and ``common.cartpole_failed`` per
        episode, and the initial states as simulated.
    """
    points = grid(lengths)
    episodes = len(starts)
    values = np.repeat(np.asarray([(length, std) for _, _, length, std in points], np.float32), episodes, axis=0)
    x0 = np.tile(np.asarray(starts, np.float32), (len(points), 1))

    def copy_params(value, start):
        return with_initial_state(with_input_noise(with_pole_length(params, value[0]), value[1]), start)

    batched = jax.vmap(copy_params)(jnp.asarray(values), jnp.asarray(x0))
    evaluation = evaluate(env, batched, controller, key, len(values), batched_params=True, measure_time=False)
    shape = (len(points), episodes)
    x = np.asarray(evaluation.trajectory["x"])
    return {
        "grid": points,
        "rmse": np.asarray(evaluation.per_episode["rmse"], dtype=float).reshape(shape),
        "failed": common.cartpole_failed(x).reshape(shape),
        "x0": x[0].reshape(*shape, -1),
    }


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
            controller = common.load_gp_mpc(directory, env10, params10, options=GP_MPC_OPTIONS)
            out["gp_mpc"] = (controller, env10, params10)
        except Exception as error:
            failed["gp_mpc"] = common.failure_text(error)
            ctx.log(f"  gp_mpc failed: {failed['gp_mpc']}")
    return out, missing, failed


def run(ctx: common.Context) -> common.Section:
    budget = ctx.budget(PROFILES)
    _, env, params = common.load("cartpole", EVAL)
    _, env10, params10 = common.load("cartpole", EVAL + GP_MPC_RATE)
    results, missing, failed, episode_rows = {}, set(), {}, []
    for seed in ctx.seeds:
        methods, absent, broken = controllers(ctx, seed, budget, env, params, env10, params10)
        missing |= set(absent)
        failed.update(broken)
        starts = initial_states(env, params, seed, budget["episodes"])
        for name, (controller, e, p) in methods.items():
            lengths = GP_MPC_POLE_LENGTHS if name == "gp_mpc" else POLE_LENGTHS
            try:
                with ctx.step(f"seed {seed}: {name}, both sweeps in one evaluation"):
                    swept = sweep(e, p, controller, jax.random.key(EPISODE_KEY + seed), starts, lengths)
            except Exception as error:
                failed[name] = common.failure_text(error)
                ctx.log(f"  {name} failed: {failed[name]}")
                continue
            results.setdefault(name, {})[seed] = swept
            episode_rows += episode_table(name, seed, swept)
    results = {name: per_seed for name, per_seed in results.items() if name not in failed}

    section = common.Section(NAME, TITLE)
    summary = summary_table(results)
    section.files.append(common.write_csv(ctx.out / "robustness.csv", summary))
    section.files.append(common.write_csv(ctx.out / "robustness_episodes.csv", episode_rows))
    section.files.append(common.save_figure(figure(summary), ctx.out / "robustness.png"))
    section.claims = claims(results, missing, ctx.profile, failed)
    section.notes += [f"{name} not measured: {error}" for name, error in sorted(failed.items())]
    if missing:
        section.notes.append(f"method {', '.join(sorted(missing))} not available in this build")
    section.notes.append(
        f"{budget['episodes']} episodes per grid point and seed, {len(ctx.seeds)} seed(s), from the task's "
        "randomised initial states (the same ones for every grid point and method of a seed). A grid point's RMSE is "
        "the median over its episodes of the per-episode RMSE (full state, unweighted), so runaway episodes do not "
        "decide it; an episode fails when the cart leaves the track (|x| > 2.4 m) or the pole falls (|θ| > π/2), "
        "and the failure rate is given beside the RMSE. A claim compares medians per seed and is judged on the "
        "median over seeds. GP-MPC runs at 10 Hz on the original's GP-MPC pole lengths (0.15, 0.25, 0.5, 0.75, "
        "1.65 m), the rest at 50 Hz; the noise is drawn every control step."
    )
    return section


def episode_table(method: str, seed: int, swept: dict) -> list[dict]:
    """One row per episode of a method's sweeps: method, seed, sweep, value, episode, initial state, RMSE, failed."""
    rows = []
    for i, (sweep_name, value, _, _) in enumerate(swept["grid"]):
        for e in range(swept["rmse"].shape[1]):
            x0 = swept["x0"][i, e]
            rows.append({"method": method, "seed": seed, "sweep": sweep_name, "value": value, "episode": e,
                         **{f"x0_{k}": float(v) for k, v in enumerate(x0)},
                         "rmse": float(swept["rmse"][i, e]), "failed": int(swept["failed"][i, e])})  # fmt: skip
    return rows


def point_scores(per_seed: dict, sweep_name: str, values) -> tuple[np.ndarray, np.ndarray]:
    """Per seed, over the grid points ``values`` of ``sweep_name`` pooled: ``(median RMSE over their episodes,
    failure rate)``, each (seeds,)."""
    medians, rates = [], []
    for swept in per_seed.values():
        rows = [i for i, (s, v, _, _) in enumerate(swept["grid"]) if s == sweep_name and v in values]
        medians.append(float(np.median(swept["rmse"][rows])))
        rates.append(float(np.mean(swept["failed"][rows])))
    return np.asarray(medians), np.asarray(rates)


def summary_table(results: dict) -> list[dict]:
    """One row per method, sweep and grid value: the median over seeds of the per-seed median RMSE, the failure rate
    over every episode and seed, and the per-seed medians."""
    rows = []
    for method, per_seed in results.items():
        for sweep_name, value, _, _ in next(iter(per_seed.values()))["grid"]:
            medians, rates = point_scores(per_seed, sweep_name, (value,))
            rows.append({"method": method, "sweep": sweep_name, "value": value,
                         "rmse_median": float(np.median(medians)), "failure_rate": float(np.mean(rates)),
                         "rmse_median_per_seed": " ".join(f"{m:.4f}" for m in medians)})  # fmt: skip
    return rows


def figure(summary: list[dict]):
    plt = common.pyplot()
    fig, axes = plt.subplots(2, 2, figsize=(10, 6), sharex="col", constrained_layout=True)
    for column, (sweep_name, label) in enumerate(
        (("pole_length", "pole half-length l (m)"), ("input_noise_std", "input noise std σ_u (N)"))
    ):
        for method in dict.fromkeys(r["method"] for r in summary):
            rows = [r for r in summary if r["method"] == method and r["sweep"] == sweep_name]
            values = [r["value"] for r in rows]
            axes[0, column].plot(values, [r["rmse_median"] for r in rows], "o-", label=method)
            axes[1, column].plot(values, [r["failure_rate"] for r in rows], "o-", label=method)
        axes[0, column].set_ylabel("RMSE (median over episodes and seeds)")
        axes[0, column].set_yscale("log")
        axes[1, column].set_ylabel("failure rate")
        axes[1, column].set_xlabel(label)
        for axis in axes[:, column]:
            axis.grid(alpha=0.3)
            axis.legend(fontsize=7)
    return fig


def claims(results: dict, missing: set, profile: str, failed: dict | None = None) -> list[common.Claim]:
    """The claims of the figure from ``results`` (``{method: {seed: sweep(...)}}``); a method in ``missing`` makes a
    claim ``UNAVAILABLE``, one in ``failed`` (``{method: error}``) ``NOT_MEASURED`` with the error. RL claims outside
    the paper profile read ``NOT_CONVERGED`` when they do not hold."""
    out, failed = [], dict(failed or {})

    def absent(text, *names):
        unavailable = [n for n in names if n in missing]
        if unavailable:
            return common.claim(text, None, "", missing=unavailable)
        broken = [n for n in names if n in failed]
        if broken:
            return common.claim(text, None, "not measured: " + "; ".join(f"{n} failed: {failed[n]}" for n in broken))
        return common.claim(text, None, f"{', '.join(n for n in names if n not in results)} not run in the {profile} "
                                        "profile")  # fmt: skip

    def scores(names, sweep_name, values):
        """Per-seed medians and the failure rates (over every seed) of ``names`` over ``values`` of ``sweep_name``."""
        pairs = {n: point_scores(results[n], sweep_name, values) for n in names}
        return {n: m for n, (m, _) in pairs.items()}, {n: float(np.mean(r)) for n, (_, r) in pairs.items()}

    def numbers(rates):
        return lambda v: ", ".join(f"{n} {v[n]:.4f} (failures {rates[n]:.0%})" for n in v)

    def check(text, names, sweep_name, values, test, rl=True, note=""):
        if any(n not in results for n in names):
            return absent(text, *names)
        medians, rates = scores(names, sweep_name, values)
        return common.seed_claim(text, medians, test, numbers(rates), note, needs_convergence=rl, profile=profile)

    text = "RMSE rises with the input noise σ (LQR; median RMSE at σ = 0, 1 and 4 N)"
    if "lqr" in results:
        by_sigma = {f"σ={s:g}": point_scores(results["lqr"], "input_noise_std", (s,))[0] for s in (0.0, 1.0, 4.0)}
        out.append(common.seed_claim(text, by_sigma, lambda v: v["σ=4"] > v["σ=1"] > v["σ=0"],
                                     lambda v: ", ".join(f"{k}: {x:.4f}" for k, x in v.items())))  # fmt: skip
    else:
        out.append(common.claim(text, None, f"not measured: lqr failed: {failed.get('lqr', 'not run')}"))
    lengths = ", ".join(f"{v:g}" for v in OFF_NOMINAL)
    out.append(check(f"PPO^DR is more robust to pole length than PPO (median RMSE over l = {lengths} m)",
                     ("ppo_dr", "ppo"), "pole_length", OFF_NOMINAL, lambda v: v["ppo_dr"] < v["ppo"]))  # fmt: skip
    noise = " and ".join(f"{v:g}" for v in HIGH_NOISE)
    out.append(check(f"RAP is more robust to input noise than PPO (median RMSE at σ = {noise} N)",
                     ("rap", "ppo"), "input_noise_std", HIGH_NOISE, lambda v: v["rap"] < v["ppo"]))  # fmt: skip
    out.append(check(f"RAP is less robust to parameter mismatch than PPO^DR (median RMSE over l = {lengths} m)",
                     ("rap", "ppo_dr"), "pole_length", OFF_NOMINAL, lambda v: v["rap"] > v["ppo_dr"]))  # fmt: skip
    model_lengths = ", ".join(f"{v:g}" for v in MODEL_OFF_NOMINAL)
    out.append(check(
        f"LQR and GP-MPC are less affected by pole length than PPO (median RMSE over l = {model_lengths} m, each "
        "below PPO's)", ("lqr", "gp_mpc", "ppo"), "pole_length", MODEL_OFF_NOMINAL,
        lambda v: v["lqr"] < v["ppo"] and v["gp_mpc"] < v["ppo"],
        note="LQR's and GP-MPC's models are the nominal and the 150% pole, fixed while the true length varies",
    ))  # fmt: skip
    out.append(check(
        "LQR and GP-MPC are no less resilient to input noise than PPO (median RMSE over every σ, each within 1.2x of "
        "PPO's or lower)", ("lqr", "gp_mpc", "ppo"), "input_noise_std", NOISE_STDS,
        lambda v: v["lqr"] <= 1.2 * v["ppo"] and v["gp_mpc"] <= 1.2 * v["ppo"],
        note="GP-MPC acts at 10 Hz, so each noise draw acts 5x as long as at 50 Hz (the original's explanation)",
    ))  # fmt: skip
    return out
