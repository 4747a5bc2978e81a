"""The host driver of every JAX learner: compiled iterations in chunks, progress, CSV, checkpoints, final policy.

A learner (``algorithms.ppo.make_learner``, ``algorithms.sac.make_learner``) is a ``Learner``: pure ``init`` and
``update`` functions over a runner state (a pytree holding everything: network and optimiser state, observation
statistics, env states, PRNG key). ``run_training`` compiles ``update`` repeated ``n`` times inside one
``lax.fori_loop`` (``n`` is a traced argument, so one compilation serves every chunk length), runs chunks of about a
second each so the progress bar moves, appends each iteration's metrics to ``progress.csv``, checkpoints the runner
state, and saves the final policy. Because every chunk runs the same compiled iteration, the result does not depend
on the chunking: a run resumed from a checkpoint is bit-identical to an uninterrupted one.

Files written in ``out_dir``:

- ``progress.csv``: one row per iteration: ``iteration``, ``env_steps``, ``wall_time_s`` then the learner's metrics.
- ``checkpoint.msgpack`` / ``checkpoint.json``: the runner state and where it stands (``resume=True`` reads them).
- ``policy.msgpack`` / ``policy.json``: what ``algorithms.rl.policy.load_policy`` needs (algo, config, env config
  text, observation normaliser).
- ``learning_curve.png``: ``plot_learning_curve`` of the CSV.
"""

from __future__ import annotations

import csv as csv_lib
import dataclasses
import io
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from algorithms.rl.checkpoint import load_checkpoint, save_checkpoint
from algorithms.rl.normalization import RunningStats
from scg_jax.files import write_atomic

CSV_NAME = "progress.csv"
CHECKPOINT_NAME = "checkpoint"
POLICY_NAME = "policy"
CURVE_NAME = "learning_curve.png"


class Learner(NamedTuple):
    """A learning algorithm as pure functions (see the module docstring).

    Attributes:
        name: ``"ppo"`` or ``"sac"`` (the package ``algorithms.<name>`` that rebuilds it).
        config: the frozen hyperparameter dataclass (``algorithms.<name>.Config``).
        init: ``init(key, params) -> runner_state``; ``params`` unbatched ``EnvParams``.
        update: ``update(runner_state, params) -> (runner_state, metrics)``, one iteration; ``metrics`` a dict of
            scalars with at least ``env_steps`` (total so far), ``episode_return``, ``episode_cost``,
            ``episode_rmse`` (means over the episodes finished in the iteration, the previous value when none did)
            and the losses.
        num_iterations: iterations in the budget (``total_env_steps`` over the env steps per iteration).
        policy_params: ``policy_params(runner_state) -> pytree``: network parameters and observation statistics.
        make_policy: ``make_policy(policy_params) -> policy(obs, key)``: the action in [-1, 1] for ``obs``
            (obs_size,) or (B, obs_size); deterministic (the mean) when ``key`` is None, sampled otherwise.
    """

    name: str
    config: Any
    init: Callable
    update: Callable
    num_iterations: int
    policy_params: Callable
    make_policy: Callable


def config_dict(config) -> dict:
    """A learner's config as a JSON-ready dict (tuples become lists)."""
    return json_ready(dataclasses.asdict(config))


def json_ready(value):
    """``value`` with tuples as lists and numpy/JAX scalars and arrays as Python numbers and lists."""
    if isinstance(value, dict):
        return {str(k): json_ready(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_ready(v) for v in value]
    if isinstance(value, np.ndarray | jax.Array | np.generic):
        return np.asarray(value).tolist()
    return value


def find_obs_stats(policy_params) -> RunningStats | None:
    """The first ``RunningStats`` inside ``policy_params`` (the observation normaliser), or None."""
    found = [
        leaf
        for leaf in jax.tree.leaves(policy_params, is_leaf=lambda x: isinstance(x, RunningStats))
        if isinstance(leaf, RunningStats)
    ]
    return found[0] if found else None


def _make_chunk_runner(learner: Learner, max_chunk: int):
    """``run(runner_state, params, n) -> (runner_state, metrics (max_chunk,) per key)``: n iterations, n traced."""

    def run(runner_state, params, n):
        metric_shapes = jax.eval_shape(lambda s: learner.update(s, params)[1], runner_state)
        # Each metric keeps its dtype (an int32 step counter stays exact beyond float32's 2^24).
        buffer = {name: jnp.zeros((max_chunk,), shape.dtype) for name, shape in metric_shapes.items()}

        def body(i, carry):
            state, buffer = carry
            state, metrics = learner.update(state, params)
            buffer = {name: buffer[name].at[i].set(metrics[name]) for name in buffer}
            return state, buffer

        return jax.lax.fori_loop(0, n, body, (runner_state, buffer))

    return jax.jit(run)


def raw_key(key):
    """Raw ``uint32`` key data (typed keys are converted) so the runner state serialises anywhere."""
    if jax.dtypes.issubdtype(key.dtype, jax.dtypes.prng_key):
        return jax.random.key_data(key)
    return key


def _read_csv_rows(path: Path, last_iteration: int) -> tuple[list[str] | None, list[list[str]]]:
    if not path.exists():
        return None, []
    with path.open(newline="") as file:
        rows = list(csv_lib.reader(file))
    if not rows:
        return None, []
    header, body = rows[0], rows[1:]
    return header, [row for row in body if row and int(row[0]) <= last_iteration]


def _write_csv(path: Path, header: list[str], rows: list[list]) -> None:
    text = io.StringIO()
    writer = csv_lib.writer(text, lineterminator="\n")
    writer.writerow(header)
    writer.writerows(rows)
    write_atomic(path, lambda file: file.write(text.getvalue().encode()))


def _format_row(iteration: int, elapsed: float, names: list[str], metrics: dict, index: int) -> list:
    row = [iteration, int(round(float(metrics["env_steps"][index]))), f"{elapsed:.3f}"]
    row += [f"{float(metrics[name][index]):.7g}" for name in names]
    return row


class _Progress:
    """A rich progress bar with env steps/s and the latest return; a no-op when disabled."""

    def __init__(self, enabled: bool, total: int, completed: int, name: str):
        self.bar = None
        if not enabled:
            return
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

        self.bar = Progress(
            TextColumn(f"[bold]{name}[/bold]"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("it"),
            TimeRemainingColumn(),
            TextColumn("{task.fields[status]}"),
        )
        self.task = self.bar.add_task(name, total=total, completed=completed, status="compiling...")
        self.bar.start()

    def update(self, completed: int, status: str) -> None:
        if self.bar is not None:
            self.bar.update(self.task, completed=completed, status=status)

    def stop(self) -> None:
        if self.bar is not None:
            self.bar.stop()


def run_training(
    learner: Learner,
    env,
    params,
    key,
    out_dir,
    *,
    chunk: int | None = None,
    checkpoint_every: int | None = None,
    resume: bool = False,
    progress: bool = True,
    csv: bool = True,
    env_config: str | None = None,
    target_seconds_per_chunk: float = 1.0,
) -> dict:
    """Train ``learner`` for its ``num_iterations`` on ``env`` with ``params``, writing results to ``out_dir``.

    Args:
        learner: a ``Learner``. env: the ``scg_jax.Env`` it was made for. params: unbatched ``EnvParams`` of the
            training plant (randomisation and disturbances as configured in ``env``/``params``).
        key: PRNG key (raw or typed); the whole run is determined by it.
        out_dir: output folder (created). chunk: iterations per compiled call; ``None`` adapts it so that a call
            takes about ``target_seconds_per_chunk`` (results do not depend on it).
        checkpoint_every: save ``checkpoint.msgpack/json`` every that many iterations (and always at the end);
            ``None``: about every 60 s of wall time.
        resume: continue from ``out_dir/checkpoint.*`` when present (otherwise start afresh); the result is
            bit-identical to an uninterrupted run with the same key. Raises ValueError if the checkpoint was written
            with another algorithm or config.
        progress: show a rich progress bar. csv: write ``progress.csv`` and ``learning_curve.png``.
        env_config: the env configuration text (YAML) to store with the policy, so it can be rebuilt.

    Returns:
        ``{"algo", "iterations", "env_steps", "total_time_s", "compile_time_s", "train_time_s",
        "env_steps_per_s" (steps of this session over its run time, compile excluded), "resumed_from_iteration",
        "final_metrics" (the last iteration's metrics), "out_dir"}``; JSON-ready.
    """
    start = time.perf_counter()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    total = int(learner.num_iterations)
    if total < 1:
        raise ValueError(f"learner.num_iterations: must be at least 1, got {total}")
    if chunk is not None and (int(chunk) != chunk or chunk < 1):
        raise ValueError(f"chunk: must be a positive integer or None, got {chunk!r}")
    if checkpoint_every is not None and (int(checkpoint_every) != checkpoint_every or checkpoint_every < 1):
        raise ValueError(f"checkpoint_every: must be a positive integer or None, got {checkpoint_every!r}")
    config = config_dict(learner.config)
    key = raw_key(jnp.asarray(key))

    init = jax.jit(learner.init)
    iteration, elapsed_before, resumed_from, steps_at_start = 0, 0.0, None, 0.0
    resumed_metrics: dict = {}
    checkpoint_file = out_dir / f"{CHECKPOINT_NAME}.json"
    if resume and checkpoint_file.exists():
        target = jax.eval_shape(learner.init, key, params)
        runner_state, meta = load_checkpoint(out_dir, CHECKPOINT_NAME, target)
        if meta.get("algo") != learner.name or meta.get("config") != config:
            raise ValueError(
                f"resume: {checkpoint_file} was written by {meta.get('algo')!r} with another config; use a new "
                "out_dir or the same settings"
            )
        runner_state = jax.tree.map(jnp.asarray, runner_state)
        iteration, elapsed_before = int(meta["iteration"]), float(meta.get("wall_time_s", 0.0))
        resumed_from, steps_at_start = iteration, float(meta.get("env_steps", 0))
        resumed_metrics = dict(meta.get("metrics") or {})
    else:
        runner_state = init(key, params)

    max_chunk = min(total, int(chunk) if chunk is not None else 1000)
    compile_start = time.perf_counter()
    if iteration < total:  # a finished run resumed has nothing to compile
        runner = _make_chunk_runner(learner, max_chunk)
        compiled = runner.lower(runner_state, params, jnp.int32(1)).compile()
    compile_s = time.perf_counter() - compile_start

    csv_path = out_dir / CSV_NAME
    names: list[str] = []
    if csv:
        metric_names = sorted(
            jax.eval_shape(lambda s: learner.update(s, params)[1], runner_state).keys() - {"env_steps"}
        )
        names = metric_names
        header = ["iteration", "env_steps", "wall_time_s", *names]
        old_header, rows = _read_csv_rows(csv_path, iteration) if resumed_from is not None else (None, [])
        if old_header is not None and old_header != header:
            rows = []
        _write_csv(csv_path, header, rows)

    bar = _Progress(progress, total, iteration, learner.name)
    run_start = time.perf_counter()
    # A resumed run that is already complete runs no iteration: it reports the checkpoint's last metrics.
    last_metrics: dict = resumed_metrics
    last_checkpoint_time = time.perf_counter()
    seconds_per_iteration = None
    try:
        while iteration < total:
            if chunk is not None:
                n = int(chunk)
            elif seconds_per_iteration is None:
                n = 1
            else:
                n = int(max(1, round(target_seconds_per_chunk / max(seconds_per_iteration, 1e-9))))
            n = min(n, max_chunk, total - iteration)
            if checkpoint_every is not None:
                next_checkpoint = (iteration // checkpoint_every + 1) * checkpoint_every
                n = min(n, next_checkpoint - iteration)
            t0 = time.perf_counter()
            runner_state, metrics = compiled(runner_state, params, jnp.int32(n))
            metrics = {name: np.asarray(values[:n]) for name, values in metrics.items()}
            dt = time.perf_counter() - t0
            per_iteration = dt / n
            seconds_per_iteration = (
                per_iteration if seconds_per_iteration is None else 0.5 * (seconds_per_iteration + per_iteration)
            )
            now = time.perf_counter()
            elapsed = elapsed_before + now - start
            if csv:
                rows = [_format_row(iteration + i + 1, elapsed, names, metrics, i) for i in range(n)]
                with csv_path.open("a", newline="") as file:
                    csv_lib.writer(file, lineterminator="\n").writerows(rows)
            iteration += n
            last_metrics = {name: float(values[-1]) for name, values in metrics.items()}
            rate = (last_metrics["env_steps"] - steps_at_start) / max(now - run_start, 1e-9)
            bar.update(
                iteration,
                f"{last_metrics['env_steps']:.3g} steps, {rate:,.0f} steps/s, return "
                f"{last_metrics.get('episode_return', math.nan):.4g}",
            )
            due = (
                iteration % checkpoint_every == 0
                if checkpoint_every is not None
                else now - last_checkpoint_time >= 60.0
            )
            if due or iteration >= total:
                _save_runner(out_dir, learner, config, runner_state, iteration, last_metrics, elapsed)
                last_checkpoint_time = time.perf_counter()
    finally:
        bar.stop()

    policy_params = learner.policy_params(runner_state)
    stats = find_obs_stats(policy_params)
    env_steps = int(round(last_metrics.get("env_steps", steps_at_start)))
    save_checkpoint(
        out_dir,
        POLICY_NAME,
        policy_params,
        {
            "algo": learner.name,
            "config": config,
            "env_config": env_config,
            "obs_size": int(env.observation_size),
            "action_size": int(env.action_size),
            "obs_normalizer": None if stats is None else json_ready(stats._asdict()),
            "iterations": iteration,
            "env_steps": env_steps,
        },
    )
    if csv:
        plot_learning_curve(csv_path, out_dir / CURVE_NAME)
    total_s = time.perf_counter() - start
    run_s = time.perf_counter() - run_start
    session_steps = last_metrics.get("env_steps", steps_at_start) - steps_at_start
    return {
        "algo": learner.name,
        "iterations": iteration,
        "env_steps": env_steps,
        "total_time_s": total_s,
        "compile_time_s": compile_s,
        "train_time_s": run_s,
        "env_steps_per_s": session_steps / max(run_s, 1e-9),
        "resumed_from_iteration": resumed_from,
        "final_metrics": last_metrics,
        "out_dir": str(out_dir),
    }


def _save_runner(out_dir, learner, config, runner_state, iteration, metrics, elapsed) -> None:
    save_checkpoint(
        out_dir,
        CHECKPOINT_NAME,
        runner_state,
        {
            "algo": learner.name,
            "config": config,
            "iteration": iteration,
            "num_iterations": int(learner.num_iterations),
            "env_steps": int(round(metrics.get("env_steps", 0.0))),
            "wall_time_s": elapsed,
            "metrics": metrics,
        },
    )


CURVE_PANELS = (
    ("episode_return", "return"),
    ("episode_rmse", "RMSE"),
    ("episode_cost", "cost (steps in violation)"),
    ("episode_length", "length (steps)"),
)


def plot_learning_curve(csv_path, png_path) -> None:
    """Plot ``progress.csv`` against env steps: return, RMSE, cost and length per episode, plus every ``*loss*``
    column, one panel each (the panels whose column is missing are left out); written atomically as a PNG."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    with Path(csv_path).open(newline="") as file:
        rows = list(csv_lib.DictReader(file))
    if not rows:
        return
    columns = rows[0].keys()
    panels = [(name, label) for name, label in CURVE_PANELS if name in columns]
    panels += [(name, name) for name in columns if "loss" in name]
    steps = np.array([float(row["env_steps"]) for row in rows])
    ncols = min(3, max(len(panels), 1))
    nrows = max(1, math.ceil(len(panels) / ncols))
    fig = Figure(figsize=(4.2 * ncols, 3.0 * nrows), layout="constrained")
    FigureCanvasAgg(fig)
    for i, (name, label) in enumerate(panels):
        ax = fig.add_subplot(nrows, ncols, i + 1)
        ax.plot(steps, [float(row[name]) for row in rows], lw=1.2)
        ax.set_xlabel("env steps")
        ax.set_title(label, fontsize=10)
        ax.grid(alpha=0.3)
    write_atomic(png_path, lambda file: fig.savefig(file, format="png", dpi=100))
