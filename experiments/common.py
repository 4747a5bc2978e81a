"""What every result of the reproduction shares: profiles, the run context, cached training, availability of the
methods, files written whole, and the claims of the paper with their verdicts.

A result module (``control_performance``, ``learning_efficiency``, ...) is a small script over the public API with
``NAME``, ``TITLE``, ``PROFILES`` (budgets per profile: ``tiny`` for the tests, ``quick`` for 2 CPU cores in a few
minutes, ``paper`` for the paper's budgets) and ``run(ctx) -> Section``. ``scg-jax reproduce`` builds the ``Context``
and writes each ``Section`` into ``report.md``.

Caching: a trained policy, a learned GP or a learning curve lives in ``<cache>/<method>-<hash>/``, where the hash is
over everything that determines it (the method, the full config text after overrides, the budget, the seed and
``CACHE_VERSION``); a rerun finds it and only evaluates.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
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
CACHE_VERSION = 1  # bump when a cached artefact's meaning changes

# GP-MPC's learning loop per profile (over each config's controllers.gp_mpc), the same in every result that learns
# on the same config, so they share one cached GP: rounds after the prior's data, episodes collected per round,
# episodes each round is evaluated on.
GP_MPC_LEARNING = {
    "quick": {"rounds": 2, "train_episodes": 1, "eval_episodes": 2},
    "paper": {"rounds": 6, "train_episodes": 2, "eval_episodes": 4},
}

HOLDS, FAILS, UNAVAILABLE, NOT_MEASURED = "holds", "does not hold", "method not available", "not measured"


# --------------------------------------------------------------------------------------------- context
@dataclasses.dataclass(frozen=True)
class Context:
    """Where and how a result runs.

    Attributes:
        out: the result's own folder (``<--out>/<NAME>``). cache: the shared cache folder (``<--out>/cache``).
        profile: ``tiny``, ``quick`` or ``paper``. seeds: training/evaluation seeds (``--seeds N`` gives 0..N-1).
        progress: where progress and messages go (``scg_algorithms.progress``; silent by default, the command line
            draws them).
    """

    out: Path
    cache: Path
    profile: str
    seeds: tuple[int, ...]
    progress: Progress = SILENT

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


def claim(text: str, holds: bool | None, measured: str, note: str = "", missing: Sequence[str] = ()) -> Claim:
    """A ``Claim``; ``UNAVAILABLE`` (naming the methods) when a method it needs is missing, ``NOT_MEASURED`` when
    ``holds`` is None (e.g. a NaN)."""
    if missing:
        return Claim(text, UNAVAILABLE, f"method {', '.join(missing)} not available in this build", note)
    if holds is None:
        return Claim(text, NOT_MEASURED, measured, note)
    return Claim(text, HOLDS if holds else FAILS, measured, note)


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
                cells = (c.text, f"**{c.verdict}**", c.measured, c.note)
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
def train_policy(ctx: Context, algo: str, cfg, seed: int, total_env_steps: int, env, params):
    """A policy trained by ``scg_algorithms.train_run`` (as ``scg-jax train --algo ALGO`` does) on ``cfg`` (a
    ``scg_jax.Config``) with the budget ``total_env_steps``, as a controller for ``env``/``params``; cached (the
    folder also keeps the config as ``config.yaml``). Returns ``(controller, metrics.json)``."""
    from scg_algorithms.rl.policy import load_policy
    from scg_algorithms.runs import train_run

    text = scg_jax.dump_config(cfg)
    directory = ctx.cache / f"{algo}-{config_hash(algo, text, seed, total_env_steps)}"
    if not (directory / "metrics.json").is_file():
        directory.mkdir(parents=True, exist_ok=True)
        config_file = directory / "config.yaml"
        write_atomic(config_file, lambda f: f.write(text.encode()))
        ctx.log(f"  training {algo} (seed {seed}, {total_env_steps:,} env steps) -> {directory}")
        train_run(algo, cfg, directory, seed=seed, total_env_steps=total_env_steps, overwrite=True, eval_episodes=2,
                  progress=ctx.progress, record={"config_file": str(config_file)})  # fmt: skip
    metrics = json.loads((directory / "metrics.json").read_text())
    return load_policy(directory, env, params), metrics


def learn_gp_mpc(ctx: Context, name: str, overrides: Sequence[str], seed: int, prior_scale: float, options: Mapping):
    """GP-MPC learned by ``scg_algorithms.train_run`` on the env of ``experiments/configs/<name>.yaml`` with
    ``overrides``, from the prior ``prior_scale`` times the true inertial parameters, with ``options`` over the
    config's ``controllers.gp_mpc``; cached. Returns ``(folder, history)``: load the controller for an env with
    ``load_gp_mpc``; ``history`` rows are the learning rounds (``data_seconds``, ``rmse``,
    ``constraint_violation_steps``, ...)."""
    from scg_algorithms.runs import train_run

    cfg, _, _ = load(name, overrides)
    options = {**dict(cfg.controllers.get("gp_mpc") or {}), **dict(options), "seed": seed}
    directory = ctx.cache / f"gp_mpc-{config_hash('gp_mpc', scg_jax.dump_config(cfg), options, prior_scale)}"
    if not (directory / "gp_mpc.json").is_file():
        ctx.log(f"  learning gp_mpc on {name} (seed {seed}, {options.get('rounds')} rounds) -> {directory}")
        learning = scg_jax.load_config(cfg, values={"controllers.gp_mpc": options})
        train_run("gp_mpc", learning, directory, seed=seed, overwrite=True, eval_episodes=None,
                  prior_scale=prior_scale, progress=ctx.progress, record={"overrides": list(overrides)})  # fmt: skip
    return directory, json.loads((directory / "gp_mpc.json").read_text())["history"]


def load_gp_mpc(directory: Path, env, params, prior_scale: float = 1.5, options: Mapping | None = None):
    """The GP-MPC saved in ``directory`` as a controller for ``env`` (prior: ``prior_scale`` times ``params``'s
    inertial parameters)."""
    from scg_algorithms.gp_mpc.run import load_run

    return load_run(directory, env, scg_jax.prior_params(env, params, prior_scale), options)


def learning_curve(ctx: Context, algo: str, cfg, seed: int, points: Sequence[int], eval_env, eval_params, episodes: int,
                   score: Callable | None = None) -> list[dict]:  # fmt: skip
    """Train ``algo`` (a package ``scg_algorithms.<algo>`` with ``Config`` and ``make_learner``) on ``cfg``'s env
    and evaluate its deterministic policy with the common harness after ``points`` env steps (ascending); cached.

    One compiled training iteration and one compiled evaluation serve every point. Rows: ``env_steps``,
    ``data_seconds`` (env steps times the training env's control period, the paper's x-axis), ``rmse``,
    ``violation_fraction`` (steps in violation over episode length), ``failure_rate``, ``wall_s`` and what
    ``score(evaluation)`` adds.
    """
    from scg_algorithms.base import JaxController
    from scg_algorithms.evaluation import make_evaluator
    from scg_algorithms.rl.envs import policy_action_to_input

    text = scg_jax.dump_config(cfg)
    directory = ctx.cache / f"{algo}-curve-{config_hash(algo, text, seed, list(points), episodes, eval_env.num_steps)}"
    cached = directory / "curve.json"
    if cached.is_file():
        return json.loads(cached.read_text())["rows"]
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
    write_json(cached, {"algo": algo, "seed": seed, "rows": rows})
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


def pyplot():
    """matplotlib's pyplot on the headless Agg backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt
