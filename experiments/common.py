"""What every result of the reproduction shares: profiles, the run context, cached training, availability of the
methods, files written whole, and the claims of the paper with their verdicts.

A result module (``control_performance``, ``learning_efficiency``, ...) is a small script over the public API with
``NAME``, ``TITLE``, ``PROFILES`` (budgets per profile: ``tiny`` for the tests, ``quick`` for 2 CPU cores in a few
minutes, ``paper`` for the paper's budgets) and ``run(ctx) -> Section``. ``scg-jax reproduce`` builds the ``Context``
and writes each ``Section`` into ``report.md``.

Caching: a trained policy, a learned GP or a learning curve lives in ``<cache>/<method>-<hash>/``, where the hash is
over everything that determines it (the method, the full config text after overrides, the budget, the seed and
``CACHE_VERSION``); a rerun finds it and only evaluates. Results may run in parallel processes (``reproduce(...,
jobs=N)``): each entry is made under an exclusive lock on ``<cache>/<method>-<hash>.lock``, so a process that needs an
entry another is making waits for it and then reads it, and no entry is written twice.

Verdicts: a claim is judged on the median over seeds of each quantity it names, and says how many seeds' own numbers
give the same verdict (``seed_claim``). A claim that needs an RL method to have converged reads ``NOT_CONVERGED``
instead of ``FAILS`` outside the ``paper`` profile.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import fcntl
import hashlib
import io
import json
import math
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import scg_jax
from scg_algorithms.learners import available, build_learner
from scg_algorithms.progress import SILENT, Progress, Task, running
from scg_jax.files import write_atomic, write_json

CONFIG_DIR = Path(__file__).resolve().parent / "configs"
PROFILES = ("tiny", "quick", "paper")
CACHE_VERSION = 2  # bump when a cached artefact's meaning changes

# GP-MPC's learning loop per profile, over each config's controllers.gp_mpc (which holds the original's loop for its
# figure: rounds after the prior's data, episodes collected per round, episodes each round is evaluated on); the same
# in every result that learns on the same config, so they share one cached GP.
GP_MPC_LEARNING = {
    "quick": {"rounds": 2, "eval_episodes": 2},
    "paper": {},
}
# The solver of every GP-MPC the results learn and run: "sqp_rti", the batched SQP-RTI solver in the harness's jitted
# loop (docs/controllers.md: the same RMSE as IPOPT's in the Fig 6 setting, about 100x less time per copy and step);
# None keeps controllers.gp_mpc's default, IPOPT on the host, one solve per copy and step.
GP_MPC_SOLVER: str | None = "sqp_rti"

HOLDS, FAILS, UNAVAILABLE, NOT_MEASURED = "holds", "does not hold", "method not available", "not measured"
NOT_CONVERGED = "not converged at this budget (see the paper profile)"

# The cart-pole's failure (the original's out-of-bounds, DESIGN.md): the cart leaves the track or the pole falls.
CARTPOLE_TRACK_LIMIT = 2.4  # |x| (m)
CARTPOLE_ANGLE_LIMIT = math.pi / 2  # |theta| (rad)


# --------------------------------------------------------------------------------------------- context
@dataclasses.dataclass(frozen=True)
class Context:
    """Where and how a result runs.

    Attributes:
        out: the result's own folder (``<--out>/<NAME>``). cache: the shared cache folder (``<--out>/cache``).
        profile: ``tiny``, ``quick`` or ``paper``. seeds: training/evaluation seeds (``--seeds N`` gives 0..N-1).
        progress: where progress and messages go (``scg_algorithms.progress``; silent by default, the command line
            draws them). stats: ``cache_hits`` and ``cache_misses`` of this result's cached artefacts (``cached``).
    """

    out: Path
    cache: Path
    profile: str
    seeds: tuple[int, ...]
    progress: Progress = SILENT
    stats: dict = dataclasses.field(default_factory=lambda: {"cache_hits": 0, "cache_misses": 0})

    def budget(self, profiles: Mapping[str, Mapping]) -> dict:
        """The result's budget for this profile."""
        return dict(profiles[self.profile])

    def log(self, message: str) -> None:
        self.progress.note(message)

    @contextlib.contextmanager
    def step(self, what: str):
        """``what`` as a task while the block runs, then a line with its wall time."""
        start = time.perf_counter()
        with running(self.progress, Task(what)):
            yield
        self.log(f"  {what}: {time.perf_counter() - start:.1f} s")


@dataclasses.dataclass(frozen=True)
class Claim:
    """One claim of the paper and what was measured.

    Attributes:
        text: the claim, quoted or paraphrased from the paper. verdict: ``HOLDS``, ``FAILS``, ``UNAVAILABLE`` or
        ``NOT_MEASURED``. measured: the numbers behind the verdict. note: why, where it does not hold, as far as
        can be told.
    """

    text: str
    verdict: str
    measured: str
    note: str = ""
    seeds: str = ""  # how many seeds agree with the verdict, e.g. "2/3 seeds"; empty for a one-run claim


def verdict(holds: bool, needs_convergence: bool = False, profile: str = "paper") -> str:
    """``HOLDS`` or ``FAILS``; ``NOT_CONVERGED`` for a failing claim that needs an RL method to have converged, outside
    the paper profile (its budgets are the paper's; the others' are not meant to converge)."""
    if holds:
        return HOLDS
    return NOT_CONVERGED if needs_convergence and profile != "paper" else FAILS


def claim(text: str, holds: bool | None, measured: str, note: str = "", missing: Sequence[str] = (), *,
          needs_convergence: bool = False, profile: str = "paper") -> Claim:  # fmt: skip
    """A one-run ``Claim``; ``UNAVAILABLE`` (naming the methods) when a method it needs is missing, ``NOT_MEASURED``
    when ``holds`` is None (e.g. a NaN); otherwise ``verdict(holds, needs_convergence, profile)``."""
    if missing:
        return Claim(text, UNAVAILABLE, f"method {', '.join(missing)} not available in this build", note)
    if holds is None:
        return Claim(text, NOT_MEASURED, measured, note)
    return Claim(text, verdict(holds, needs_convergence, profile), measured, note)


def seed_claim(text: str, values: Mapping[str, Sequence[float]], test: Callable[[Mapping[str, float]], bool],
               measured: Callable[[Mapping[str, float]], str], note: str = "", *, needs_convergence: bool = False,
               profile: str = "paper") -> Claim:  # fmt: skip
    """A claim judged over seeds.

    Args:
        values: each quantity the claim names -> its value per seed (every sequence as long as the seeds; ``inf`` is
            a value, e.g. "never", NaN is not measured).
        test: the claim on one set of values (``{name: value}``), e.g. ``lambda v: v["gp_mpc"] < v["ppo"]``; a claim
            that names several methods tests each of them.
        measured: the text of the numbers behind the verdict, given the medians.
        needs_convergence, profile: as ``verdict``.

    Returns:
        The ``Claim`` of ``test`` on the medians over seeds, its ``seeds`` field saying how many seeds' own values
        give the same verdict ("2/3 seeds"); ``NOT_MEASURED`` when a value is NaN or missing.
    """
    lengths = {len(v) for v in values.values()}
    if len(lengths) != 1 or 0 in lengths:
        counts = {name: len(v) for name, v in values.items()}
        return Claim(text, NOT_MEASURED, f"not measured: values per seed {counts}")
    per_seed = {name: np.asarray(v, dtype=float) for name, v in values.items()}
    if any(np.isnan(v).any() for v in per_seed.values()):
        return Claim(text, NOT_MEASURED, "not measured: " + ", ".join(f"{k} {v.tolist()}" for k, v in per_seed.items()))
    medians = {name: float(np.median(v)) for name, v in per_seed.items()}
    holds = bool(test(medians))
    seeds = lengths.pop()
    agree = sum(bool(test({name: float(v[i]) for name, v in per_seed.items()})) == holds for i in range(seeds))
    text_measured = measured(medians) + (f" (median over {seeds} seeds)" if seeds > 1 else "")
    return Claim(text, verdict(holds, needs_convergence, profile), text_measured, note, f"{agree}/{seeds} seeds")


@dataclasses.dataclass
class Section:
    """A result's part of ``report.md``: its claims, notes (comparisons with the original's data, methods not
    available, budgets), the files it wrote, and its wall time (set by the runner)."""

    name: str
    title: str
    claims: list = dataclasses.field(default_factory=list)
    notes: list = dataclasses.field(default_factory=list)
    files: list = dataclasses.field(default_factory=list)
    wall_s: float = float("nan")

    def markdown(self) -> str:
        lines = [f"## {self.title}", "", f"Result `{self.name}`, wall time {self.wall_s:.1f} s.", ""]
        if self.claims:
            lines += ["| claim | verdict | measured | note |", "|---|---|---|---|"]
            for c in self.claims:
                cells = (c.text, f"**{c.verdict}**" + (f" ({c.seeds})" if c.seeds else ""), c.measured, c.note)
                lines.append("| " + " | ".join(str(cell).replace("|", "\\|") for cell in cells) + " |")
            lines.append("")
        lines += [f"- {note}" for note in self.notes]
        if self.notes:
            lines.append("")
        pngs = [f for f in self.files if f.endswith(".png")]
        lines += [f"![{name}]({self.name}/{name})" for name in pngs]
        data = [f for f in self.files if not f.endswith(".png")]
        if data:
            lines += ["", "Data: " + ", ".join(f"`{self.name}/{name}`" for name in data)]
        return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------------------------- configs
def load(name: str, overrides: Iterable[str] = ()):
    """``(cfg, env, params)`` of ``experiments/configs/<name>.yaml`` with ``overrides`` (``"env.KEY=VALUE"``)."""
    cfg = scg_jax.load_config(CONFIG_DIR / f"{name}.yaml", list(overrides))
    env, params = scg_jax.make_from_config(cfg)
    return cfg, env, params


def with_method(cfg, source: Path, keys: Sequence[str], overrides: Iterable[str] = ()):
    """``cfg`` (a ``scg_jax.Config``) with the dotted ``keys`` (e.g. ``env.adversary``, ``training.rarl``) taken from
    the config file ``source``, then ``overrides``: a method's own settings (its adversary, its randomisation, its
    learner section) on the plant every method of a result is scored on. ``KeyError`` naming the key and the file
    when ``source`` lacks one."""
    data = scg_jax.load_config(source).to_dict()
    values = {}
    for dotted in keys:
        node = data
        for part in dotted.split("."):
            if not isinstance(node, Mapping) or node.get(part) is None:
                raise KeyError(f"{source}: no {dotted}")
            node = node[part]
        values[dotted] = node
    return scg_jax.load_config(cfg.to_dict(), list(overrides), values=values)


def failure_text(error: BaseException) -> str:
    """One line for the report: the error's type and the first line of its message."""
    message = str(error).strip().splitlines()
    return f"{type(error).__name__}: {message[0] if message else ''}"[:300]


def config_hash(*parts) -> str:
    """A short stable hash of JSON-able ``parts`` (config text, budget, seed, ...)."""
    text = json.dumps([CACHE_VERSION, *parts], sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


# --------------------------------------------------------------------------------------------- availability
def train_algorithms() -> tuple[str, ...]:
    """The learners of ``scg_algorithms.learners.LEARNERS`` available in this build."""
    from scg_algorithms.learners import LEARNERS

    return tuple(name for name in LEARNERS if available(name))


def learner_available(algo: str) -> bool:
    return available(algo)


def safety_filter(name: str):
    """The registry entry of the safety filter ``name`` in ``scg_algorithms.safety_filters.FILTERS``, or None when
    the package or the name is missing from this build."""
    try:
        import scg_algorithms.safety_filters as filters
    except ImportError:
        return None
    registry = getattr(filters, "FILTERS", {})
    return registry.get(name) if name in registry else None


def repo_configs(pattern: str) -> list[Path]:
    """Config files of the project's ``configs/`` folder matching ``pattern`` (e.g. PPO^DR's)."""
    import scg_algorithms

    folder = Path(scg_algorithms.__file__).resolve().parents[1] / "configs"
    return sorted(folder.glob(pattern)) if folder.is_dir() else []


# --------------------------------------------------------------------------------------------- training (cached)
@contextlib.contextmanager
def cached(ctx: Context, directory: Path, marker: str):
    """Whether the cache entry ``directory`` is complete (its file ``marker`` exists), yielded while this process
    holds an exclusive lock on ``<directory>.lock``: a process that finds it incomplete makes it inside the block,
    and another process asking for the same entry meanwhile waits and then finds it complete. Counts the hit or miss
    in ``ctx.stats``."""
    directory.parent.mkdir(parents=True, exist_ok=True)
    with open(directory.parent / f"{directory.name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes, also if the block raises
        hit = (directory / marker).is_file()
        ctx.stats["cache_hits" if hit else "cache_misses"] += 1
        yield hit


def train_policy(ctx: Context, algo: str, cfg, seed: int, total_env_steps: int, env, params):
    """A policy trained by ``scg_algorithms.train_run`` (as ``scg-jax train --algo ALGO`` does) on ``cfg`` (a
    ``scg_jax.Config``) with the budget ``total_env_steps``, as a controller for ``env``/``params``; cached (the
    folder also keeps the config as ``config.yaml``). Returns ``(controller, metrics.json)``."""
    from scg_algorithms.rl.policy import load_policy
    from scg_algorithms.runs import train_run

    text = scg_jax.dump_config(cfg)
    directory = ctx.cache / f"{algo}-{config_hash(algo, text, seed, total_env_steps)}"
    with cached(ctx, directory, "metrics.json") as hit:
        if not hit:
            directory.mkdir(parents=True, exist_ok=True)
            config_file = directory / "config.yaml"
            write_atomic(config_file, lambda f: f.write(text.encode()))
            ctx.log(f"  training {algo} (seed {seed}, {total_env_steps:,} env steps) -> {directory}")
            train_run(algo, cfg, directory, seed=seed, total_env_steps=total_env_steps, overwrite=True,
                      eval_episodes=2, progress=ctx.progress, record={"config_file": str(config_file)})  # fmt: skip
    metrics = json.loads((directory / "metrics.json").read_text())
    return load_policy(directory, env, params), metrics


def gp_mpc_options(options: Mapping) -> dict:
    """``options`` for ``controllers.gp_mpc`` with the results' solver (``GP_MPC_SOLVER``) when one is set."""
    return {**dict(options), **({"solver": GP_MPC_SOLVER} if GP_MPC_SOLVER else {})}


def learn_gp_mpc(ctx: Context, name: str, overrides: Sequence[str], seed: int, prior_scale: float, options: Mapping):
    """GP-MPC learned by ``scg_algorithms.train_run`` on the env of ``experiments/configs/<name>.yaml`` with
    ``overrides``, from the prior ``prior_scale`` times the true inertial parameters, with ``options`` over the
    config's ``controllers.gp_mpc``; cached. The learning env's cost weights ``Q``, ``R`` are the GP-MPC's
    (``q_diag``, ``r_diag``), as in the original, whose GP-MPC configs give the env's cost: they set the weights of
    round 0's exploring LQR on the prior (the figure's ``Q`` may be the RL reward's, which no controller can use).
    Returns ``(folder, history)``: load the controller for an env with ``load_gp_mpc``; ``history`` rows are the
    learning rounds (``data_seconds``, ``rmse``, ``constraint_violation_steps``, ...)."""
    from scg_algorithms.runs import train_run

    cfg, _, _ = load(name, overrides)
    options = gp_mpc_options({**dict(cfg.controllers.get("gp_mpc") or {}), **dict(options), "seed": seed})
    weights = [f"env.{key}={list(options[field])}" for key, field in (("Q", "q_diag"), ("R", "r_diag"))
               if options.get(field) is not None]  # fmt: skip
    cfg, _, _ = load(name, [*overrides, *weights])
    directory = ctx.cache / f"gp_mpc-{config_hash('gp_mpc', scg_jax.dump_config(cfg), options, prior_scale)}"
    with cached(ctx, directory, "gp_mpc.json") as hit:
        if not hit:
            ctx.log(f"  learning gp_mpc on {name} (seed {seed}, {options.get('rounds')} rounds) -> {directory}")
            learning = scg_jax.load_config(cfg, values={"controllers.gp_mpc": options})
            train_run("gp_mpc", learning, directory, seed=seed, overwrite=True, eval_episodes=None,
                      prior_scale=prior_scale, progress=ctx.progress,
                      record={"overrides": list(overrides)})  # fmt: skip
    return directory, json.loads((directory / "gp_mpc.json").read_text())["history"]


def load_gp_mpc(directory: Path, env, params, prior_scale: float = 1.5, options: Mapping | None = None):
    """The GP-MPC saved in ``directory`` as a controller for ``env`` (prior: ``prior_scale`` times ``params``'s
    inertial parameters), with ``options`` over its saved MPC options (the GP stays as learned)."""
    from scg_algorithms.gp_mpc.run import load_run

    return load_run(directory, env, scg_jax.prior_params(env, params, prior_scale), gp_mpc_options(options or {}))


def learning_curve(ctx: Context, algo: str, cfg, seed: int, points: Sequence[int], eval_env, eval_params, episodes: int,
                   score: Callable | None = None) -> list[dict]:  # fmt: skip
    """Train ``algo`` (a package ``scg_algorithms.<algo>`` with ``Config`` and ``make_learner``) on ``cfg``'s env
    and evaluate its deterministic policy with the common harness after ``points`` env steps (ascending); cached.

    One compiled training iteration and one compiled evaluation serve every point. Rows: ``env_steps``,
    ``data_seconds`` (env steps times the training env's control period, the paper's x-axis), ``rmse``,
    ``violation_fraction`` (steps in violation over episode length), ``failure_rate``, ``wall_s`` and what
    ``score(evaluation)`` adds.
    """
    text = scg_jax.dump_config(cfg)
    directory = ctx.cache / f"{algo}-curve-{config_hash(algo, text, seed, list(points), episodes, eval_env.num_steps)}"
    with cached(ctx, directory, "curve.json") as hit:
        if not hit:
            rows = _learn_curve(ctx, algo, cfg, seed, points, eval_env, eval_params, episodes, score)
            write_json(directory / "curve.json", {"algo": algo, "seed": seed, "rows": rows})
    return json.loads((directory / "curve.json").read_text())["rows"]


def _learn_curve(ctx, algo, cfg, seed, points, eval_env, eval_params, episodes, score) -> list[dict]:
    """``learning_curve``'s rows, computed (no cache)."""
    from scg_algorithms.base import JaxController
    from scg_algorithms.evaluation import make_evaluator
    from scg_algorithms.rl.envs import policy_action_to_input

    env, params = scg_jax.make_from_config(cfg)
    options = {**dict(cfg.training.get(algo) or {}), "total_env_steps": int(points[-1])}
    config, learner = build_learner(algo, options, env)
    physics = eval_params.physics
    action_scale = getattr(config, "action_scale", 1.0)

    def build(policy_params):
        policy = learner.make_policy(policy_params)

        def act(ctrl_state, obs, step, reference):
            return policy_action_to_input(eval_env, policy(obs, None), physics, action_scale), ctrl_state

        return JaxController(algo, lambda key, reference: (), act)

    evaluate_fn = make_evaluator(eval_env, build, episodes)

    @jax.jit
    def advance(state, n):
        return jax.lax.fori_loop(0, n, lambda i, s: learner.update(s, params)[0], state)

    key = jax.random.key(seed)
    train_key, eval_key = jax.random.split(key)
    state = learner.init(train_key, params)
    done_iterations, rows, start = 0, [], time.perf_counter()
    ctx.log(f"  learning curve of {algo} (seed {seed}, up to {points[-1]:,} env steps)")
    for point in points:
        target = max(1, math.ceil(point / learner.steps_per_iteration))
        if target > done_iterations:
            state = jax.block_until_ready(advance(state, jnp.int32(target - done_iterations)))
            done_iterations = target
        evaluation = evaluate_fn(learner.policy_params(state), eval_key, eval_params)
        steps = done_iterations * learner.steps_per_iteration
        row = {
            "env_steps": steps,
            "data_seconds": steps * env.dt,
            "rmse": float(evaluation.summary["rmse"]),
            "violation_fraction": violation_fraction(evaluation),
            "failure_rate": float(evaluation.summary["failure_rate"]),
            "wall_s": time.perf_counter() - start,
            **(score(evaluation) if score else {}),
        }
        rows.append(row)
        ctx.log(f"    {steps:>10,} steps ({row['data_seconds']:.0f} s of data): RMSE {row['rmse']:.4f}")
    return rows


# --------------------------------------------------------------------------------------------- measures
def violation_fraction(evaluation) -> float:
    """Fraction of control steps in constraint violation: mean over episodes of violating steps / length."""
    per = evaluation.per_episode
    steps = np.asarray(per["violation_steps"], dtype=float)
    length = np.maximum(np.asarray(per["length"], dtype=float), 1.0)
    return float(np.mean(steps / length))


def error_norm(evaluation, dims: Sequence[int] | None = None) -> np.ndarray:
    """|Δe| over time: the Euclidean norm of ``x - x_ref`` (over ``dims``, default all), (T + 1, episodes)."""
    traj = evaluation.trajectory
    diff = np.asarray(traj["x"]) - np.asarray(traj["x_ref"])
    if dims is not None:
        diff = diff[..., list(dims)]
    return np.linalg.norm(diff, axis=-1)


def rmse_dims(evaluation, dims: Sequence[int] | None = None) -> float:
    """RMSE of ``x - x_ref`` over ``dims`` (unweighted), averaged over episodes: the paper's quadrotor x-z RMSE."""
    traj = evaluation.trajectory
    diff = (np.asarray(traj["x"]) - np.asarray(traj["x_ref"]))[1:]
    if dims is not None:
        diff = diff[..., list(dims)]
    return float(np.mean(np.sqrt(np.mean(np.sum(diff**2, axis=-1), axis=0))))


def cartpole_failed(x) -> np.ndarray:
    """Which cart-pole episodes failed: ``x`` (T + 1, N, 4) states of whole episodes (reset to the last step) ->
    (N,) bool, True where the cart left the track (|x| > 2.4 m) or the pole fell (|theta| > pi/2) at some step, or
    the state stopped being finite."""
    x = np.asarray(x, dtype=float)
    with np.errstate(invalid="ignore"):
        out = (np.abs(x[..., 0]) > CARTPOLE_TRACK_LIMIT) | (np.abs(x[..., 2]) > CARTPOLE_ANGLE_LIMIT)
    return np.any(out | ~np.all(np.isfinite(x), axis=-1), axis=0)


def ratio_text(a: float, b: float) -> str:
    return f"{a / b:.2f}x" if b and np.isfinite(a) and np.isfinite(b) else "n/a"


# --------------------------------------------------------------------------------------------- files
def write_csv(path: Path, rows: Sequence[Mapping]) -> str:
    """``rows`` (dicts with the same keys) as CSV, whole or not at all; returns the file name."""
    buffer = io.StringIO()
    if rows:
        writer = csv.DictWriter(buffer, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    data = buffer.getvalue().encode()
    write_atomic(path, lambda f: f.write(data))
    return path.name


def write_data(path: Path, data) -> str:
    """``data`` as JSON (numpy values converted), whole or not at all; returns the file name."""
    from scg_algorithms.rl.training import json_ready

    write_json(path, json_ready(data))
    return path.name


def save_figure(figure, path: Path) -> str:
    """A matplotlib figure as PNG, whole or not at all; closes it and returns the file name."""
    import matplotlib.pyplot as plt

    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=110, bbox_inches="tight")  # keep axis labels inside the image
    plt.close(figure)
    write_atomic(path, lambda f: f.write(buffer.getvalue()))
    return path.name


def style_system_axis(axis, system: str, xlabel: str, ylabel: str) -> None:
    """Label a panel of one system's results: axis labels (the y label notes "(x, z)" on a quadrotor, whose error
    counts x and z only), the system as title, a light grid and a small legend."""
    axis.set_xlabel(xlabel)
    axis.set_ylabel(ylabel + (" (x, z)" if system.startswith("quadrotor") else ""))
    axis.set_title(system)
    axis.grid(alpha=0.3)
    axis.legend(fontsize=7)


def pyplot():
    """matplotlib's pyplot on the headless Agg backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt
