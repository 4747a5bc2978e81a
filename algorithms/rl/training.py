"""The host driver of every JAX learner: compiled iterations in chunks, progress, CSV, checkpoints, final policy.

A learner (``scg_algorithms.ppo.make_learner``, ``scg_algorithms.sac.make_learner``) is a ``Learner``: pure ``init`` and
``update`` functions over a runner state (a pytree holding everything: network and optimiser state, observation
statistics, env states, PRNG key). ``run_training`` compiles ``update`` repeated ``n`` times inside one
``lax.fori_loop`` (``n`` is a traced argument, so one compilation serves every chunk length), runs chunks of about a
second each so the progress bar moves, appends each iteration's metrics to ``progress.csv``, checkpoints the runner
state, and saves the final policy. Because every chunk runs the same compiled iteration, the result does not depend
on the chunking: a run resumed from a checkpoint is bit-identical to an uninterrupted one.

Files written in ``out_dir``:

- ``progress.csv``: one row per iteration: ``iteration``, ``env_steps``, ``wall_time_s`` then the learner's metrics
  (``episode_*`` are ``nan`` until the first episode has ended: there is nothing to average yet).
- ``checkpoint.msgpack`` / ``checkpoint.json``: the runner state and where it stands (``resume=True`` reads them).
- ``policy.msgpack`` / ``policy.json``: what ``scg_algorithms.rl.policy.load_policy`` needs (algo, config, env config
  text, observation normaliser).
- ``learning_curve.png``: ``plot_learning_curve`` of the CSV.
"""

from __future__ import annotations

import csv as csv_lib
import dataclasses
import io
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from scg_algorithms.rl.checkpoint import load_checkpoint, load_metadata, save_checkpoint
from scg_algorithms.rl.counter import Count, count_value
from scg_algorithms.rl.normalization import RunningStats
from scg_jax.files import write_atomic

CSV_NAME = "progress.csv"
CHECKPOINT_NAME = "checkpoint"
POLICY_NAME = "policy"
CURVE_NAME = "learning_curve.png"
RUN_FILES = (
    f"{CHECKPOINT_NAME}.json",
    f"{CHECKPOINT_NAME}.msgpack",
    f"{POLICY_NAME}.json",
    f"{POLICY_NAME}.msgpack",
    CSV_NAME,
    CURVE_NAME,
    "metrics.json",
)
"""The files of a training run in its folder (``metrics.json`` is the CLI's); ``overwrite=True`` removes these."""


class Learner(NamedTuple):
    """A learning algorithm as pure functions (see the module docstring).

    Attributes:
        name: ``"ppo"`` or ``"sac"`` (the package ``scg_algorithms.<name>`` that rebuilds it).
        config: the frozen hyperparameter dataclass (``scg_algorithms.<name>.Config``).
        init: ``init(key, params) -> runner_state``; ``params`` unbatched ``EnvParams``.
        update: ``update(runner_state, params) -> (runner_state, metrics)``, one iteration; ``metrics`` a dict of
            scalars (or ``scg_algorithms.rl.counter.Count``s, exact integers) with at least ``env_steps`` (total so far,
            a ``Count``), ``episode_return``, ``episode_cost``, ``episode_rmse`` (means over the episodes finished
            in the iteration, the previous value when none did, NaN before the first) and the losses.
        num_iterations: iterations in the budget (``total_env_steps`` over the env steps per iteration).
        steps_per_iteration: env steps per iteration (all copies together).
        policy_params: ``policy_params(runner_state) -> pytree``: network parameters and observation statistics.
        make_policy: ``make_policy(policy_params) -> policy(obs, key)``: the action in [-1, 1] for ``obs``
            (obs_size,) or (B, obs_size); deterministic (the mean) when ``key`` is None, sampled otherwise.
    """

    name: str
    config: Any
    init: Callable
    update: Callable
    num_iterations: int
    steps_per_iteration: int
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
        return json_ready(np.asarray(value).tolist())
    if isinstance(value, float) and not math.isfinite(value):
        return None  # NaN (no episode finished yet) is not JSON: null
    return value


def find_obs_stats(policy_params) -> RunningStats | None:
    """The first ``RunningStats`` inside ``policy_params`` (the observation normaliser), or None."""
    found = [
        leaf
        for leaf in jax.tree.leaves(policy_params, is_leaf=lambda x: isinstance(x, RunningStats))
        if isinstance(leaf, RunningStats)
    ]
    return found[0] if found else None


def _make_chunk_runner(learner: Learner, max_chunk: int, state_shardings=None, mesh=None):
    """``run(runner_state, params, n) -> (runner_state, metrics (max_chunk, ...) per key)``: n iterations, n traced.

    With a ``mesh`` the runner state keeps the layout ``state_shardings`` (``scg_algorithms.rl.sharding``)
    from chunk to chunk, and params and metrics are replicated."""

    def run(runner_state, params, n):
        metric_shapes = jax.eval_shape(lambda s: learner.update(s, params)[1], runner_state)
        # Each metric keeps its dtype and structure (a Count stays two exact uint32 words).
        buffer = jax.tree.map(lambda shape: jnp.zeros((max_chunk, *shape.shape), shape.dtype), metric_shapes)

        def body(i, carry):
            state, buffer = carry
            state, metrics = learner.update(state, params)
            buffer = jax.tree.map(lambda stored, value: stored.at[i].set(value), buffer, metrics)
            return state, buffer

        return jax.lax.fori_loop(0, n, body, (runner_state, buffer))

    if mesh is not None:
        from scg_jax.sharding import replicated

        whole = replicated(mesh)
        return jax.jit(run, in_shardings=(state_shardings, whole, whole), out_shardings=(state_shardings, whole))
    return jax.jit(run)


def _host_metrics(metrics: dict, n: int) -> dict[str, np.ndarray]:
    """The first ``n`` entries of each metric as numpy arrays; ``Count``s as exact ``uint64``."""
    out = {}
    for name, value in metrics.items():
        if isinstance(value, Count):
            out[name] = np.asarray(count_value(Count(np.asarray(value.hi)[:n], np.asarray(value.lo)[:n])))
        else:
            out[name] = np.asarray(value)[:n]
    return out


def _count(n: int, distributed: bool):
    """The chunk length argument: a host integer over several processes (the same value on each, replicated by
    ``jit``; a device array would sit on one process's device), a device scalar otherwise."""
    return np.int32(n) if distributed else jnp.int32(n)


def _from_process_0(value):
    """Process 0's ``value`` (an int or bool) on every process (``broadcast_one_to_all``, a collective): decisions
    taken from a process's own clock (chunk length, checkpoint due) must be the same everywhere, or the processes'
    collectives would not pair up."""
    from jax.experimental import multihost_utils

    return multihost_utils.broadcast_one_to_all(np.asarray(value, dtype=np.int64)).item()


def _barrier(name: str) -> None:
    """Wait until every process has reached the barrier ``name``."""
    from jax.experimental import multihost_utils

    multihost_utils.sync_global_devices(name)


def _scalar(value):
    """A metric entry as a Python int (integer dtypes: exact) or float."""
    return int(value) if np.issubdtype(np.asarray(value).dtype, np.integer) else float(value)


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
    row = [iteration, int(metrics["env_steps"][index]), f"{elapsed:.3f}"]
    for name in names:
        value = _scalar(metrics[name][index])
        row.append(str(value) if isinstance(value, int) else f"{value:.7g}")  # NaN is written "nan"
    return row


def _format_seconds(seconds: float) -> str:
    seconds = int(round(seconds))
    hours, rest = divmod(seconds, 3600)
    return f"{hours}:{rest // 60:02d}:{rest % 60:02d}" if hours else f"{rest // 60}:{rest % 60:02d}"


class _Progress:
    """Progress of a run: a rich bar on a terminal, a plain line every ``seconds`` otherwise (a log file or a pipe
    sees output while the run goes, not only at its end), nothing when disabled."""

    def __init__(self, enabled: bool, total: int, completed: int, name: str, seconds: float, stream=None):
        self.bar, self.plain, self.total, self.name, self.seconds = None, False, total, name, seconds
        self.stream = sys.stdout if stream is None else stream
        self.last_print = -math.inf
        if not enabled:
            return
        if not self.stream.isatty():
            self.plain = True
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

    def update(self, completed: int, status: str, elapsed: float, remaining: float) -> None:
        if self.bar is not None:
            self.bar.update(self.task, completed=completed, status=status)
        elif self.plain:
            now = time.perf_counter()
            if now - self.last_print >= self.seconds or completed >= self.total:
                self.last_print = now
                line = (
                    f"{self.name}: iteration {completed}/{self.total} ({100.0 * completed / self.total:.1f}%), "
                    f"{status}, elapsed {_format_seconds(elapsed)}, remaining {_format_seconds(remaining)}"
                )
                print(line, file=self.stream, flush=True)

    def stop(self) -> None:
        if self.bar is not None:
            self.bar.stop()
            self.bar = None


class TrainingInterrupted(KeyboardInterrupt):
    """``run_training`` was interrupted (Ctrl-C) and saved what it had.

    Attributes:
        out_dir: the run's folder. iteration: the last completed iteration, saved in ``checkpoint.*`` (resumable
            with ``resume=True``). num_iterations: the budget. checkpoint: path of ``checkpoint.msgpack``, or None
            when no iteration had completed (nothing to save).
    """

    def __init__(self, out_dir: Path, iteration: int, num_iterations: int, checkpoint: Path | None):
        super().__init__(f"training interrupted at iteration {iteration}/{num_iterations}")
        self.out_dir, self.iteration, self.num_iterations = out_dir, iteration, num_iterations
        self.checkpoint = checkpoint


def existing_run_files(out_dir) -> list[str]:
    """The ``RUN_FILES`` present in ``out_dir`` (empty when it holds no run or does not exist)."""
    out_dir = Path(out_dir)
    return [name for name in RUN_FILES if (out_dir / name).exists()]


_MISSING = object()


def config_differences(saved: dict, current: dict, ignore: tuple[str, ...] = ()) -> list[str]:
    """``"key: <saved> in the checkpoint, <current> now"`` for each top-level key whose value differs."""
    differences = []
    for name in sorted(saved.keys() | current.keys()):
        if name in ignore:
            continue
        old, new = saved.get(name, _MISSING), current.get(name, _MISSING)
        if old != new:
            show = lambda v: "(absent)" if v is _MISSING else repr(v)  # noqa: E731
            differences.append(f"{name}: {show(old)} in the checkpoint, {show(new)} now")
    return differences


def _env_section(config_text: str) -> dict:
    """The ``env`` mapping of a stored config text (the whole text under ``"(text)"`` if it is not such YAML)."""
    import yaml

    try:
        section = (yaml.safe_load(config_text) or {}).get("env")
    except (yaml.YAMLError, AttributeError):
        section = None
    return section if isinstance(section, dict) else {"(text)": config_text}


def _check_resumable(meta: dict, checkpoint_file: Path, learner: Learner, config: dict, env_config) -> None:
    """ValueError naming what keeps the checkpoint ``meta`` from being continued by ``learner`` with ``config``."""
    saved_algo = meta.get("algo")
    if saved_algo != learner.name:
        raise ValueError(
            f"resume: {checkpoint_file} is a {saved_algo!r} run, not {learner.name!r}; resume it with algo "
            f"{saved_algo!r}, or train {learner.name!r} into another folder"
        )
    differences = config_differences(meta.get("config") or {}, config, ignore=("total_env_steps",))
    if differences:
        raise ValueError(
            f"resume: {checkpoint_file} was written by {saved_algo!r} with another config: {'; '.join(differences)}. "
            f"Use the same training.{learner.name} settings (only total_env_steps may be raised) or another folder"
        )
    saved_env, iteration = meta.get("env_config"), int(meta.get("iteration", 0))
    if saved_env is not None and env_config is not None:
        env_differences = config_differences(_env_section(saved_env), _env_section(env_config))
        if env_differences:
            raise ValueError(
                f"resume: {checkpoint_file} was trained on another env: "
                f"{'; '.join('env.' + line for line in env_differences)}. Use the same env settings or another folder"
            )
    if iteration > learner.num_iterations:
        raise ValueError(
            f"resume: {checkpoint_file} is at iteration {iteration} ({meta.get('env_steps')} env steps), beyond "
            f"this budget of {learner.num_iterations} iterations (training.{learner.name}.total_env_steps = "
            f"{config.get('total_env_steps')}); a resumed run's budget may be raised, not set below where it stands"
        )


def run_training(
    learner: Learner,
    env,
    params,
    key,
    out_dir,
    *,
    chunk: int | None = None,
    checkpoint_every: int | None = None,
    checkpoint_seconds: float = 60.0,
    resume: bool = False,
    overwrite: bool = False,
    progress: bool = True,
    progress_seconds: float = 10.0,
    csv: bool = True,
    env_config: str | None = None,
    target_seconds_per_chunk: float = 1.0,
    on_chunk: Callable[[int], None] | None = None,
    mesh=None,
) -> dict:
    """Train ``learner`` for its ``num_iterations`` on ``env`` with ``params``, writing results to ``out_dir``.

    Args:
        learner: a ``Learner``. env: the ``scg_jax.Env`` it was made for. params: unbatched ``EnvParams`` of the
            training plant (randomisation and disturbances as configured in ``env``/``params``).
        key: PRNG key (raw or typed); the whole run is determined by it.
        out_dir: output folder (created). A folder that already holds a run (any of ``RUN_FILES``) is refused
            unless ``resume`` or ``overwrite`` is given.
        chunk: iterations per compiled call; ``None`` adapts it so that a call takes about
            ``target_seconds_per_chunk`` (results do not depend on it).
        checkpoint_every: save ``checkpoint.msgpack/json`` every that many iterations; ``None``: every
            ``checkpoint_seconds`` of wall time (the first one after that long too). Always at the end, and on
            Ctrl-C.
        resume: continue from ``out_dir/checkpoint.*`` (start afresh in an empty folder); the result is
            bit-identical to an uninterrupted run with the same key. The algorithm, its config and the env config
            must be the checkpoint's, except ``total_env_steps``, which may be raised to extend a run (PPO's
            decaying step size then follows the new budget's schedule from where the run stands). Raises
            ValueError naming the settings that differ.
        overwrite: remove a previous run's files from ``out_dir`` and start afresh (excludes ``resume``).
        progress: show progress: a rich bar on a terminal, else a plain line every ``progress_seconds``.
        csv: write ``progress.csv`` and ``learning_curve.png``.
        env_config: the env configuration text (YAML) to store with the policy, so it can be rebuilt.
        on_chunk: called with the iteration count after each compiled call has been recorded (CSV rows written);
            an exception it raises stops the run (KeyboardInterrupt: as Ctrl-C).
        mesh: ``scg_jax.sharding.make_mesh(devices)``: the env copies of the runner state are laid out over its
            devices, networks and optimiser state replicated, and ``jit`` partitions collection and updates (the
            gradient is the full batch's mean, all-reduced by the compiler). ``None``: one device. Several processes
            (``scg_jax.sharding.initialize_distributed``): the mesh must hold every process's devices
            (``make_mesh("all")``); every process calls ``run_training`` with the same arguments and steps the copies
            on its own devices; the metrics are gathered once per chunk, the chunk lengths and checkpoint times are
            process 0's (broadcast), the runner state is gathered to every process for a checkpoint, and only
            process 0 writes files and shows progress (``out_dir`` on a shared filesystem for ``resume``: every
            process reads the checkpoint). On Ctrl-C a multi-process run saves nothing new (the other processes
            may not take part in a gather): its last periodic checkpoint stands.

    Returns:
        ``{"algo", "iterations", "env_steps", "total_time_s", "compile_time_s", "train_time_s",
        "env_steps_per_s" (steps of this session over its run time, compile excluded), "resumed_from_iteration",
        "final_metrics" (the last iteration's metrics), "out_dir"}``; JSON-ready.

    Raises:
        ValueError: bad arguments, a folder holding a run without ``resume``/``overwrite``, a checkpoint that
            cannot be continued. TrainingInterrupted (a KeyboardInterrupt): Ctrl-C, after saving a checkpoint of
            the last completed iteration.
    """
    start = time.perf_counter()
    out_dir = Path(out_dir)
    total = int(learner.num_iterations)
    if total < 1:
        raise ValueError(f"learner.num_iterations: must be at least 1, got {total}")
    if chunk is not None and (int(chunk) != chunk or chunk < 1):
        raise ValueError(f"chunk: must be a positive integer or None, got {chunk!r}")
    if checkpoint_every is not None and (int(checkpoint_every) != checkpoint_every or checkpoint_every < 1):
        raise ValueError(f"checkpoint_every: must be a positive integer or None, got {checkpoint_every!r}")
    if not checkpoint_seconds > 0:
        raise ValueError(f"checkpoint_seconds: must be positive, got {checkpoint_seconds!r}")
    if not progress_seconds >= 0:
        raise ValueError(f"progress_seconds: must be >= 0, got {progress_seconds!r}")
    if resume and overwrite:
        raise ValueError("resume, overwrite: give one of them (continue the run in out_dir, or replace it)")
    distributed = mesh is not None and jax.process_count() > 1
    if mesh is not None:
        from scg_jax import sharding

        if distributed and mesh.devices.size != jax.device_count():
            raise ValueError(
                f"mesh: a run over {jax.process_count()} processes needs a mesh over all {jax.device_count()} devices "
                f"(make_mesh('all'), devices: all), got {mesh.devices.size}"
            )
        num_envs = getattr(learner.config, "num_envs", None)
        if num_envs is not None:
            sharding.check_divisible(num_envs, mesh, f"training.{learner.name}.num_envs")
    config = config_dict(learner.config)
    key = raw_key(jnp.asarray(key))

    checkpoint_file = out_dir / f"{CHECKPOINT_NAME}.json"
    main = not distributed or sharding.is_main_process()  # the one process that writes files
    existing = existing_run_files(out_dir)
    if existing and overwrite:
        for name in existing if main else ():
            (out_dir / name).unlink(missing_ok=True)
    elif existing and not (resume and checkpoint_file.exists()):
        action = "has no checkpoint to resume" if resume else "already holds a training run"
        raise ValueError(
            f"out_dir: {out_dir} {action} ({', '.join(existing)}); "
            + ("use overwrite to replace it" if resume else "use resume to continue it or overwrite to replace it")
        )
    if distributed:  # every process has looked at the folder before process 0 changes it
        _barrier("scg_jax.run_training: folder checked")
    if main:
        out_dir.mkdir(parents=True, exist_ok=True)

    init = jax.jit(learner.init)
    iteration, elapsed_before, resumed_from, steps_at_start = 0, 0.0, None, 0
    resumed_metrics: dict = {}
    if resume and checkpoint_file.exists():
        meta = load_metadata(out_dir, CHECKPOINT_NAME)
        _check_resumable(meta, checkpoint_file, learner, config, env_config)
        target = jax.eval_shape(learner.init, key, params)
        try:
            runner_state, meta = load_checkpoint(out_dir, CHECKPOINT_NAME, target)
        except ValueError as error:
            budget_changed = (meta.get("config") or {}).get("total_env_steps") != config.get("total_env_steps")
            hint = (
                " (the new total_env_steps changes the size of the state, e.g. a replay buffer clipped to the "
                "budget: keep buffer_size at most the old budget)"
                if budget_changed
                else ""
            )
            raise ValueError(f"resume: {error}{hint}") from None
        runner_state = jax.tree.map(jnp.asarray, runner_state)
        iteration, elapsed_before = int(meta["iteration"]), float(meta.get("wall_time_s", 0.0))
        resumed_from, steps_at_start = iteration, int(meta.get("env_steps", 0))
        resumed_metrics = dict(meta.get("metrics") or {})
    else:
        runner_state = init(key, params)
    if mesh is not None:
        from scg_algorithms.rl.sharding import shard_runner_state

        runner_state = shard_runner_state(runner_state, mesh)
        params = sharding.replicate(params, mesh)

    max_chunk = min(total, int(chunk) if chunk is not None else 1000)
    compile_start = time.perf_counter()
    try:
        if iteration < total:  # a finished run resumed has nothing to compile
            shardings = None if mesh is None else sharding.shardings_of(runner_state)
            runner = _make_chunk_runner(learner, max_chunk, shardings, mesh)
            compiled = runner.lower(runner_state, params, _count(1, distributed)).compile()
    except KeyboardInterrupt:  # Ctrl-C while compiling: nothing new to save
        saved = out_dir / f"{CHECKPOINT_NAME}.msgpack"
        raise TrainingInterrupted(out_dir, iteration, total, saved if saved.exists() else None) from None
    compile_s = time.perf_counter() - compile_start

    csv_path = out_dir / CSV_NAME
    names: list[str] = []
    if csv:
        metric_names = sorted(
            jax.eval_shape(lambda s: learner.update(s, params)[1], runner_state).keys() - {"env_steps"}
        )
        names = metric_names
        header = ["iteration", "env_steps", "wall_time_s", *names]
        old_header, rows = _read_csv_rows(csv_path, iteration) if resumed_from is not None and main else (None, [])
        if old_header is not None and old_header != header:
            rows = []
        if main:
            _write_csv(csv_path, header, rows)

    bar = _Progress(progress and main, total, iteration, learner.name, progress_seconds)
    run_start = time.perf_counter()
    # A resumed run that is already complete runs no iteration: it reports the checkpoint's last metrics.
    last_metrics: dict = resumed_metrics
    last_checkpoint_time = time.perf_counter()
    saved_iteration = iteration  # the iteration the checkpoint on disk holds (when resumed) or will hold
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
            if distributed:  # every process runs the same chunk (its collectives pair up): process 0's timing decides
                n = int(_from_process_0(n))
            t0 = time.perf_counter()
            new_state, metrics = compiled(runner_state, params, _count(n, distributed))
            if distributed:  # one gather per chunk, a collective of every process
                metrics = sharding.to_host(metrics)
            metrics = _host_metrics(metrics, n)  # waits for the chunk
            dt = time.perf_counter() - t0
            per_iteration = dt / n
            seconds_per_iteration = (
                per_iteration if seconds_per_iteration is None else 0.5 * (seconds_per_iteration + per_iteration)
            )
            now = time.perf_counter()
            elapsed = elapsed_before + now - start
            if csv and main:
                rows = [_format_row(iteration + i + 1, elapsed, names, metrics, i) for i in range(n)]
                with csv_path.open("a", newline="") as file:
                    csv_lib.writer(file, lineterminator="\n").writerows(rows)
            # Only now does the state count as done: an interrupt before this line saves the previous chunk's.
            runner_state, iteration = new_state, iteration + n
            last_metrics = {name: _scalar(values[-1]) for name, values in metrics.items()}
            rate = (last_metrics["env_steps"] - steps_at_start) / max(now - run_start, 1e-9)
            remaining = (total - iteration) * learner.steps_per_iteration / max(rate, 1e-9)
            bar.update(
                iteration,
                f"{last_metrics['env_steps']:,} env steps, {rate:,.0f} steps/s, return "
                f"{last_metrics.get('episode_return', math.nan):.4g}",
                elapsed,
                remaining,
            )
            due = (
                iteration % checkpoint_every == 0
                if checkpoint_every is not None
                else now - last_checkpoint_time >= checkpoint_seconds
            )
            if distributed and checkpoint_every is None:  # a gather every process must join: process 0's clock decides
                due = bool(_from_process_0(due))
            if due or iteration >= total:
                state_to_save = sharding.to_host(runner_state) if distributed else runner_state
                if main:
                    _save_runner(out_dir, learner, config, env_config, state_to_save, iteration, last_metrics, elapsed)
                saved_iteration, last_checkpoint_time = iteration, time.perf_counter()
            if on_chunk is not None:
                on_chunk(iteration)
    except KeyboardInterrupt:
        bar.stop()
        if distributed:  # saving would gather over processes that may not all have stopped: the last checkpoint stands
            saved = out_dir / f"{CHECKPOINT_NAME}.msgpack"
            raise TrainingInterrupted(out_dir, saved_iteration, total, saved if saved.exists() else None) from None
        if iteration > saved_iteration:
            elapsed = elapsed_before + time.perf_counter() - start
            _save_runner(out_dir, learner, config, env_config, runner_state, iteration, last_metrics, elapsed)
            saved_iteration = iteration
        if csv and csv_path.exists():  # rows of a chunk that did not complete are dropped on resume anyway
            header, rows = _read_csv_rows(csv_path, saved_iteration)
            if header is not None:
                _write_csv(csv_path, header, rows)
        saved = out_dir / f"{CHECKPOINT_NAME}.msgpack"
        raise TrainingInterrupted(out_dir, saved_iteration, total, saved if saved.exists() else None) from None
    finally:
        bar.stop()

    policy_params = learner.policy_params(runner_state)
    if distributed:
        policy_params = sharding.to_host(policy_params)  # typed keys as raw data, as checkpoints store them
    stats = find_obs_stats(policy_params)
    env_steps = int(last_metrics.get("env_steps", steps_at_start))
    if main:
        save_checkpoint(
            out_dir,
            POLICY_NAME,
            policy_params,
            {
                "algo": learner.name,
                "config": config,
                "env_config": env_config,
                "system": env.system.name,
                "task": env.task,
                "obs_size": int(env.observation_size),
                "action_size": int(env.action_size),
                "obs_normalizer": None if stats is None else json_ready(stats._asdict()),
                "iterations": iteration,
                "env_steps": env_steps,
            },
        )
        if csv:
            plot_learning_curve(
                csv_path, out_dir / CURVE_NAME, rmse_label=rmse_label(env, params), ctrl_freq=float(env.ctrl_freq)
            )
    if distributed:  # every process returns once the files are written (a caller may read them next)
        _barrier("scg_jax.run_training: files written")
    total_s = time.perf_counter() - start
    run_s = time.perf_counter() - run_start
    session_steps = env_steps - steps_at_start
    return json_ready(
        {
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
    )


def _save_runner(out_dir, learner, config, env_config, runner_state, iteration, metrics, elapsed) -> None:
    save_checkpoint(
        out_dir,
        CHECKPOINT_NAME,
        runner_state,
        {
            "algo": learner.name,
            "config": config,
            "env_config": env_config,
            "iteration": iteration,
            "num_iterations": int(learner.num_iterations),
            "env_steps": int(metrics.get("env_steps", 0)),
            "wall_time_s": elapsed,
            "metrics": json_ready(metrics),
        },
    )


# Position entries of each system's state (m): a RMSE weighted only on these is a distance.
_POSITION_INDICES = {"cartpole": (0,), "quadrotor_1d": (0,), "quadrotor_2d": (0, 2), "quadrotor_3d": (0, 2, 4)}


def rmse_label(env, params) -> str:
    """Axis label of the episode RMSE: ``"RMSE (m)"`` when ``params.mse_weight`` weighs only positions with 1
    (the quadrotors' default), otherwise a weighted full-state error of mixed units (the cart-pole's default)."""
    weights = np.asarray(params.mse_weight)
    weighted = set(np.flatnonzero(weights).tolist())
    positions = set(_POSITION_INDICES.get(env.system.name, ()))
    if weighted and weighted <= positions and np.all(weights[list(weighted)] == 1.0):
        return "RMSE (m)"
    return "RMSE (weighted state error, mixed units)"


CURVE_PANELS = (
    ("episode_return", "return (sum of rewards)"),
    ("episode_rmse", None),  # the label comes from rmse_label
    ("episode_cost", "cost (steps in violation)"),
    ("episode_length", "length (control steps)"),
)


def plot_learning_curve(
    csv_path, png_path, rmse_label: str = "RMSE (weighted state error)", ctrl_freq: float | None = None
) -> None:
    """Plot ``progress.csv`` against env steps: return, RMSE, cost and length per episode, plus every ``*loss*``
    column, one panel each (the panels whose column is missing are left out); written atomically as a PNG.

    With ``ctrl_freq`` (Hz) and the ``episode_cost`` and ``episode_length`` columns, one more panel plots the
    fraction of steps in violation (episode cost over episode length) against seconds of simulated training data
    (``env_steps / ctrl_freq``, log scale), the x-axis of the paper's constraint figure.

    ``nan`` entries (no episode had ended yet) are left out of the lines rather than drawn as 0.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    with Path(csv_path).open(newline="") as file:
        rows = list(csv_lib.DictReader(file))
    if not rows:
        return
    columns = rows[0].keys()
    panels = [(name, label or rmse_label) for name, label in CURVE_PANELS if name in columns]
    panels += [(name, name) for name in columns if "loss" in name]
    steps = np.array([float(row["env_steps"]) for row in rows])
    violation_panel = ctrl_freq is not None and {"episode_cost", "episode_length"} <= set(columns)
    num_panels = len(panels) + int(violation_panel)
    ncols = min(3, max(num_panels, 1))
    nrows = max(1, math.ceil(num_panels / ncols))
    fig = Figure(figsize=(4.2 * ncols, 3.0 * nrows), layout="constrained")
    FigureCanvasAgg(fig)
    for i, (name, label) in enumerate(panels):
        ax = fig.add_subplot(nrows, ncols, i + 1)
        values = np.array([float(row[name]) if row[name] != "" else math.nan for row in rows])
        ax.plot(steps, values, lw=1.2)
        ax.set_xlabel("env steps")
        ax.set_ylabel(label, fontsize=9)
        ax.set_title(label, fontsize=10)
        ax.grid(alpha=0.3)
    if violation_panel:
        ax = fig.add_subplot(nrows, ncols, len(panels) + 1)
        cost, length = (np.array([float(row[n]) if row[n] != "" else math.nan for row in rows]) for n in
                        ("episode_cost", "episode_length"))  # fmt: skip
        ax.plot(steps / ctrl_freq, cost / length, lw=1.2)
        ax.set_xscale("log")
        ax.set_xlabel("simulated training data (s)")
        ax.set_title("fraction of steps in violation", fontsize=10)
        ax.grid(alpha=0.3)
    write_atomic(png_path, lambda file: fig.savefig(file, format="png", dpi=100))
