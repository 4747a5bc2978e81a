"""The host driver of every JAX learner: compiled iterations in chunks, CSV, checkpoints, final policy, progress
reported through callbacks (``scg_algorithms.progress``).

A learner (``scg_algorithms.ppo.make_learner``, ``scg_algorithms.sac.make_learner``) is a ``Learner``: pure ``init`` and
``update`` functions over a runner state (a pytree holding everything: network and optimiser state, observation
statistics, env states, PRNG key). ``run_training`` compiles ``update`` repeated ``n`` times inside one
``lax.fori_loop`` (``n`` is a traced argument, so one compilation serves every chunk length), runs chunks of about a
second each so that progress is reported often, appends each iteration's metrics to ``progress.csv``, checkpoints
the runner state, and saves the final policy. Because every chunk runs the same compiled iteration, the result does
not depend on the chunking: a run resumed from a checkpoint is bit-identical to an uninterrupted one.

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
import time
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from scg_algorithms.base import parse_options
from scg_algorithms.progress import SILENT, Progress, Task, as_progress, running
from scg_algorithms.rl.checkpoint import load_checkpoint, load_metadata, save_checkpoint
from scg_algorithms.rl.counter import Count, count_value
from scg_algorithms.rl.curves import plot_learning_curve, rmse_label
from scg_algorithms.rl.normalization import RunningStats
from scg_jax import sharding
from scg_jax.files import write_atomic
from scg_jax.validation import FieldError

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
        collect: ``collect(runner_state, params) -> (collector_state, transitions)``: the data collection of the
            iteration ``update`` would run from ``runner_state`` alone (the env and the acting policy with the same
            key, nothing learned: ``collector_state`` is ``update``'s new ``collector``), for profiling where an
            iteration's time goes (``benchmarks/train.py``); None where a learner does not separate it.
    """

    name: str
    config: Any
    init: Callable
    update: Callable
    num_iterations: int
    steps_per_iteration: int
    policy_params: Callable
    make_policy: Callable
    collect: Callable | None = None


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


def init_while_compiling(init: Callable, key, params) -> tuple[Any, Callable[[], Any]]:
    """``init(key, params)`` compiled on a worker thread while the caller compiles its training loop.

    Returns ``(shapes, finish)``: the runner state's ``jax.ShapeDtypeStruct`` pytree, to lower the loop with, and
    ``finish() -> runner_state``, which waits for the compile and runs it. XLA compiles with Python's GIL released,
    so tracing and lowering the loop on the caller's thread meanwhile hides most of the init's compile (0.5-0.9 s of
    a cart-pole PPO's 4.6-5.0 s start on 2 CPU cores). The state is the one ``jax.jit(init)(key, params)`` returns.
    """
    lowered = jax.jit(init).lower(key, params)
    pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="scg-init-compile")
    compiling = pool.submit(lowered.compile)
    pool.shutdown(wait=False)  # the submitted compile still runs; the thread ends with it

    def finish():
        return compiling.result()(key, params)

    return lowered.out_info, finish


def _make_chunk_runner(update: Callable, max_chunk: int, state_shardings=None, mesh=None):
    """``run(runner_state, params, n) -> (runner_state, metrics (max_chunk, ...) per key)``: n iterations, n traced.

    ``update`` is the learner's ``update`` under ``jax.jit``, so the metric shapes and the loop body share one trace.
    With a ``mesh`` the runner state keeps the layout ``state_shardings`` (``scg_algorithms.rl.sharding``)
    from chunk to chunk, and params and metrics are replicated."""

    def run(runner_state, params, n):
        metric_shapes = jax.eval_shape(lambda s: update(s, params)[1], runner_state)
        # Each metric keeps its dtype and structure (a Count stays two exact uint32 words).
        buffer = jax.tree.map(lambda shape: jnp.zeros((max_chunk, *shape.shape), shape.dtype), metric_shapes)

        def body(i, carry):
            state, buffer = carry
            state, metrics = update(state, params)
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


ARGUMENT_WORDS = {"algo": "algo", "out_dir": "out_dir", "resume": "resume=True", "overwrite": "overwrite=True"}
"""How the folder rules' messages name the arguments; the command line passes its flags instead."""


def check_run_folder(out_dir, algo: str, resume: bool, overwrite: bool, names: Mapping[str, str] | None = None) -> None:
    """Refuse a folder that holds a run unless ``resume`` (its checkpoint is of ``algo``) or ``overwrite`` is given.

    Raises:
        FieldError: at ``resume`` (a checkpoint of another algorithm) or ``out_dir`` (a run without ``resume`` or
            ``overwrite``, or files but no checkpoint to resume); the message names the arguments as ``names``
            (``ARGUMENT_WORDS`` overridden).
    """
    words = {**ARGUMENT_WORDS, **dict(names or {})}
    out_dir = Path(out_dir)
    existing = existing_run_files(out_dir)
    if resume and (out_dir / f"{CHECKPOINT_NAME}.json").exists():
        saved = load_metadata(out_dir, CHECKPOINT_NAME).get("algo")
        if saved != algo:
            raise FieldError(
                "resume",
                f"{out_dir} holds a {saved} run, not {algo}; resume it with {words['algo']} {saved}, or train {algo} "
                f"into another {words['out_dir']} (or replace the run with {words['overwrite']})",
            )
    elif existing and not overwrite:
        what = "has no checkpoint to resume but holds" if resume else "already holds"
        advice = (
            f"pass {words['overwrite']} to replace it"
            if resume
            else f"pass {words['resume']} to continue it or {words['overwrite']} to replace it"
        )
        raise FieldError("out_dir", f"{out_dir} {what} a training run ({', '.join(existing)}); {advice}")


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
    """FieldError at ``resume`` naming what keeps the checkpoint ``meta`` (of ``learner``'s algorithm) from being
    continued with ``config`` and ``env_config``."""
    saved = dict(meta.get("config") or {})
    # A field added to the learner since the checkpoint was written counts at its default, the value that
    # reproduces the older code's behaviour (e.g. RARL's num_adversaries, always 1 before it was an option).
    defaults = config_dict(parse_options(type(learner.config), None, f"training.{learner.name}"))
    saved = {**{name: value for name, value in defaults.items() if name not in saved}, **saved}
    differences = config_differences(saved, config, ignore=("total_env_steps",))
    if differences:
        raise FieldError(
            "resume",
            f"{checkpoint_file} was written by {learner.name!r} with another config: {'; '.join(differences)}. Use "
            f"the same training.{learner.name} settings (only total_env_steps may be raised) or another folder",
        )
    saved_env, iteration = meta.get("env_config"), int(meta.get("iteration", 0))
    if saved_env is not None and env_config is not None:
        env_differences = config_differences(_env_section(saved_env), _env_section(env_config))
        if env_differences:
            raise FieldError(
                "resume",
                f"{checkpoint_file} was trained on another env: "
                f"{'; '.join('env.' + line for line in env_differences)}. Use the same env settings or another folder",
            )
    if iteration > learner.num_iterations:
        raise FieldError(
            "resume",
            f"{checkpoint_file} is at iteration {iteration} ({meta.get('env_steps')} env steps), beyond this budget "
            f"of {learner.num_iterations} iterations (training.{learner.name}.total_env_steps = "
            f"{config.get('total_env_steps')}); a resumed run's budget may be raised, not set below where it stands",
        )


@dataclasses.dataclass
class _Run:
    """Where one ``run_training`` call stands, on the host (mutable bookkeeping, not a pytree)."""

    learner: Learner
    env: Any
    params: Any
    out_dir: Path
    config: dict
    env_config: str | None
    mesh: Any
    distributed: bool
    main: bool  # the one process that writes files and reports progress
    progress: Progress
    csv: bool
    start: float  # perf_counter() when run_training was called
    runner_state: Any = None
    iteration: int = 0
    saved_iteration: int = 0  # the iteration the checkpoint on disk holds (when resumed) or will hold
    elapsed_before: float = 0.0  # wall time of the sessions before a resume
    resumed_from: int | None = None
    steps_at_start: int = 0
    last_metrics: dict = dataclasses.field(default_factory=dict)
    names: list = dataclasses.field(default_factory=list)  # the metric columns of progress.csv
    compile_s: float = 0.0
    run_start: float = 0.0  # perf_counter() after compiling
    # A fresh run's init, compiling beside the chunk runner (init_while_compiling); runner_state holds its shapes.
    finish_init: Callable | None = None

    # The learner's update under jax.jit: tracing it takes seconds, and progress.csv's columns and the chunk runner
    # share this one trace.
    update: Callable = dataclasses.field(init=False)

    def __post_init__(self):
        self.update = jax.jit(self.learner.update)

    @property
    def total(self) -> int:
        return int(self.learner.num_iterations)

    @property
    def csv_path(self) -> Path:
        return self.out_dir / CSV_NAME

    def elapsed(self) -> float:
        return self.elapsed_before + time.perf_counter() - self.start

    def interrupted(self, iteration: int) -> TrainingInterrupted:
        saved = self.out_dir / f"{CHECKPOINT_NAME}.msgpack"
        return TrainingInterrupted(self.out_dir, iteration, self.total, saved if saved.exists() else None)

    def save(self) -> None:
        """``checkpoint.*`` of the current runner state (gathered over the processes; written by process 0)."""
        state = sharding.to_host(self.runner_state) if self.distributed else self.runner_state
        if self.main:
            _save_runner(self.out_dir, self.learner, self.config, self.env_config, state, self.iteration,
                         self.last_metrics, self.elapsed())  # fmt: skip
        self.saved_iteration = self.iteration


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
    progress=None,
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
            unless ``resume`` or ``overwrite`` is given (``check_run_folder``).
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
        progress: a ``scg_algorithms.progress.Progress`` (or a function, its ``update``): the task
            ``"compiling <name>"``, then the task ``<name>`` counting iterations, updated after each compiled call
            with the last iteration's metrics plus ``steps_per_s``, ``elapsed_s`` and ``remaining_s``. None: silent.
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
            process 0 writes files and reports progress (``out_dir`` on a shared filesystem for ``resume``: every
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
    progress = as_progress(progress)
    _check_arguments(learner, chunk, checkpoint_every, checkpoint_seconds, resume, overwrite, mesh)
    distributed = mesh is not None and jax.process_count() > 1
    main = not distributed or sharding.is_main_process()
    run = _Run(learner, env, params, Path(out_dir), config_dict(learner.config), env_config, mesh, distributed, main,
               progress if main else SILENT, csv, start)  # fmt: skip
    _start_run(run, key, resume, overwrite)
    # Not bounded by the budget: a run resumed with a larger budget compiles the same chunk program as one run in one
    # go, so it repeats it bit for bit (two programs may round differently).
    max_chunk = int(chunk) if chunk is not None else 1000
    compiled = _compile(run, max_chunk)
    _open_csv(run)
    with running(run.progress, Task(learner.name, run.total, run.iteration, "iteration")):
        _run_chunks(run, compiled, max_chunk, chunk, checkpoint_every, checkpoint_seconds, target_seconds_per_chunk,
                    on_chunk)  # fmt: skip
    return _finish_run(run)


def _check_arguments(learner, chunk, checkpoint_every, checkpoint_seconds, resume, overwrite, mesh) -> None:
    total = int(learner.num_iterations)
    if total < 1:
        raise ValueError(f"learner.num_iterations: must be at least 1, got {total}")
    if chunk is not None and (int(chunk) != chunk or chunk < 1):
        raise ValueError(f"chunk: must be a positive integer or None, got {chunk!r}")
    if checkpoint_every is not None and (int(checkpoint_every) != checkpoint_every or checkpoint_every < 1):
        raise ValueError(f"checkpoint_every: must be a positive integer or None, got {checkpoint_every!r}")
    if not checkpoint_seconds > 0:
        raise ValueError(f"checkpoint_seconds: must be positive, got {checkpoint_seconds!r}")
    if resume and overwrite:
        raise ValueError("resume, overwrite: give one of them (continue the run in out_dir, or replace it)")
    if mesh is None:
        return
    if jax.process_count() > 1 and mesh.devices.size != jax.device_count():
        raise ValueError(
            f"mesh: a run over {jax.process_count()} processes needs a mesh over all {jax.device_count()} devices "
            f"(make_mesh('all'), devices: all), got {mesh.devices.size}"
        )
    num_envs = getattr(learner.config, "num_envs", None)
    if num_envs is not None:
        sharding.check_divisible(num_envs, mesh, f"training.{learner.name}.num_envs")


def _start_run(run: _Run, key, resume: bool, overwrite: bool) -> None:
    """Set-up: the folder rules, then the runner state, fresh or from the checkpoint, laid out over the mesh."""
    key = raw_key(jnp.asarray(key))
    out_dir = run.out_dir
    check_run_folder(out_dir, run.learner.name, resume, overwrite)
    if overwrite and run.main:
        for name in existing_run_files(out_dir):
            (out_dir / name).unlink(missing_ok=True)
    if run.distributed:  # every process has looked at the folder before process 0 changes it
        _barrier("scg_jax.run_training: folder checked")
    if run.main:
        out_dir.mkdir(parents=True, exist_ok=True)
    checkpoint_file = out_dir / f"{CHECKPOINT_NAME}.json"
    if resume and checkpoint_file.exists():
        _resume(run, checkpoint_file, key)
    elif run.mesh is None:
        run.runner_state, run.finish_init = init_while_compiling(run.learner.init, key, run.params)
    else:
        run.runner_state = jax.jit(run.learner.init)(key, run.params)
    if run.mesh is not None:
        from scg_algorithms.rl.sharding import shard_runner_state

        run.runner_state = shard_runner_state(run.runner_state, run.mesh)
        run.params = sharding.replicate(run.params, run.mesh)


def _resume(run: _Run, checkpoint_file: Path, key) -> None:
    """The runner state and counters of the checkpoint in ``run.out_dir`` (FieldError at ``resume`` when it cannot
    be continued)."""
    meta = load_metadata(run.out_dir, CHECKPOINT_NAME)
    _check_resumable(meta, checkpoint_file, run.learner, run.config, run.env_config)
    target = jax.eval_shape(run.learner.init, key, run.params)
    try:
        runner_state, meta = load_checkpoint(run.out_dir, CHECKPOINT_NAME, target)
    except ValueError as error:
        budget_changed = (meta.get("config") or {}).get("total_env_steps") != run.config.get("total_env_steps")
        hint = (
            " (the new total_env_steps changes the size of the state, e.g. a replay buffer clipped to the "
            "budget: keep buffer_size at most the old budget)"
            if budget_changed
            else ""
        )
        raise FieldError("resume", f"{error}{hint}") from None
    run.runner_state = jax.tree.map(jnp.asarray, runner_state)
    run.iteration = run.saved_iteration = run.resumed_from = int(meta["iteration"])
    run.elapsed_before = float(meta.get("wall_time_s", 0.0))
    run.steps_at_start = int(meta.get("env_steps", 0))
    # A resumed run that is already complete runs no iteration: it reports the checkpoint's last metrics.
    run.last_metrics = dict(meta.get("metrics") or {})


def _compile(run: _Run, max_chunk: int):
    """The chunk runner, compiled once for every chunk length (a finished run resumed has nothing to compile)."""
    if run.iteration >= run.total:
        return None
    compile_start = time.perf_counter()
    try:
        with running(run.progress, Task(f"compiling {run.learner.name}")):
            shardings = None if run.mesh is None else sharding.shardings_of(run.runner_state)
            runner = _make_chunk_runner(run.update, max_chunk, shardings, run.mesh)
            compiled = runner.lower(run.runner_state, run.params, _count(1, run.distributed)).compile()
            if run.finish_init is not None:
                run.runner_state, run.finish_init = run.finish_init(), None
    except KeyboardInterrupt:  # Ctrl-C while compiling: nothing new to save
        raise run.interrupted(run.iteration) from None
    run.compile_s = time.perf_counter() - compile_start
    return compiled


def _open_csv(run: _Run) -> None:
    """``progress.csv``'s header and, on a resume, the rows up to the checkpoint (a later chunk's are dropped)."""
    if not run.csv:
        return
    metrics = jax.eval_shape(lambda s: run.update(s, run.params)[1], run.runner_state)
    run.names = sorted(metrics.keys() - {"env_steps"})
    header = ["iteration", "env_steps", "wall_time_s", *run.names]
    resumed = run.resumed_from is not None and run.main
    old_header, rows = _read_csv_rows(run.csv_path, run.iteration) if resumed else (None, [])
    if old_header is not None and old_header != header:
        rows = []
    if run.main:
        _write_csv(run.csv_path, header, rows)


def _run_chunks(run: _Run, compiled, max_chunk, chunk, checkpoint_every, checkpoint_seconds, target_seconds,
                on_chunk) -> None:  # fmt: skip
    """The chunk loop: run, record (CSV, progress), checkpoint when due; on Ctrl-C save the last completed
    iteration and raise ``TrainingInterrupted``."""
    run.run_start = last_checkpoint_time = time.perf_counter()
    seconds_per_iteration = None
    try:
        while run.iteration < run.total:
            if chunk is not None:
                n = int(chunk)
            elif seconds_per_iteration is None:
                n = 1
            else:
                n = int(max(1, round(target_seconds / max(seconds_per_iteration, 1e-9))))
            n = min(n, max_chunk, run.total - run.iteration)
            if checkpoint_every is not None:
                n = min(n, (run.iteration // checkpoint_every + 1) * checkpoint_every - run.iteration)
            if run.distributed:  # every process runs the same chunk (its collectives pair up): process 0's decides
                n = int(_from_process_0(n))
            t0 = time.perf_counter()
            new_state, metrics = compiled(run.runner_state, run.params, _count(n, run.distributed))
            if run.distributed:  # one gather per chunk, a collective of every process
                metrics = sharding.to_host(metrics)
            metrics = _host_metrics(metrics, n)  # waits for the chunk
            per_iteration = (time.perf_counter() - t0) / n
            seconds_per_iteration = (
                per_iteration if seconds_per_iteration is None else 0.5 * (seconds_per_iteration + per_iteration)
            )
            _record_chunk(run, new_state, metrics, n)
            if checkpoint_every is not None:
                due = run.iteration % checkpoint_every == 0
            else:
                due = time.perf_counter() - last_checkpoint_time >= checkpoint_seconds
                if run.distributed:  # a gather every process must join: process 0's clock decides
                    due = bool(_from_process_0(due))
            if due or run.iteration >= run.total:
                run.save()
                last_checkpoint_time = time.perf_counter()
            if on_chunk is not None:
                on_chunk(run.iteration)
    except KeyboardInterrupt:
        raise _save_interrupted(run) from None


def _record_chunk(run: _Run, new_state, metrics: dict, n: int) -> None:
    """Append the chunk's CSV rows, take its state as done and report it."""
    elapsed = run.elapsed()
    if run.csv and run.main:
        rows = [_format_row(run.iteration + i + 1, elapsed, run.names, metrics, i) for i in range(n)]
        with run.csv_path.open("a", newline="") as file:
            csv_lib.writer(file, lineterminator="\n").writerows(rows)
    # Only now does the state count as done: an interrupt before this line saves the previous chunk's.
    run.runner_state, run.iteration = new_state, run.iteration + n
    run.last_metrics = {name: _scalar(values[-1]) for name, values in metrics.items()}
    rate = (run.last_metrics["env_steps"] - run.steps_at_start) / max(time.perf_counter() - run.run_start, 1e-9)
    remaining = (run.total - run.iteration) * run.learner.steps_per_iteration / max(rate, 1e-9)
    info = {**run.last_metrics, "steps_per_s": rate, "elapsed_s": elapsed, "remaining_s": remaining}
    run.progress.update(run.iteration, info)


def _save_interrupted(run: _Run) -> TrainingInterrupted:
    """After Ctrl-C: a checkpoint of the last completed iteration (one process) and ``progress.csv`` cut to it."""
    if run.distributed:  # saving would gather over processes that may not all have stopped: the last checkpoint stands
        return run.interrupted(run.saved_iteration)
    if run.iteration > run.saved_iteration:
        run.save()
    if run.csv and run.csv_path.exists():  # rows of a chunk that did not complete are dropped on resume anyway
        header, rows = _read_csv_rows(run.csv_path, run.saved_iteration)
        if header is not None:
            _write_csv(run.csv_path, header, rows)
    return run.interrupted(run.saved_iteration)


def _finish_run(run: _Run) -> dict:
    """Finalisation: ``policy.*`` and the learning curve (process 0), then the summary."""
    learner, env = run.learner, run.env
    policy_params = learner.policy_params(run.runner_state)
    if run.distributed:
        policy_params = sharding.to_host(policy_params)  # typed keys as raw data, as checkpoints store them
    stats = find_obs_stats(policy_params)
    env_steps = int(run.last_metrics.get("env_steps", run.steps_at_start))
    if run.main:
        save_checkpoint(run.out_dir, POLICY_NAME, policy_params, {
            "algo": learner.name, "config": run.config, "env_config": run.env_config, "system": env.system.name,
            "task": env.task, "obs_size": int(env.observation_size), "action_size": int(env.action_size),
            "obs_normalizer": None if stats is None else json_ready(stats._asdict()), "iterations": run.iteration,
            "env_steps": env_steps,
        })  # fmt: skip
        if run.csv:
            plot_learning_curve(run.csv_path, run.out_dir / CURVE_NAME, rmse_label=rmse_label(env, run.params),
                                ctrl_freq=float(env.ctrl_freq))  # fmt: skip
    if run.distributed:  # every process returns once the files are written (a caller may read them next)
        _barrier("scg_jax.run_training: files written")
    run_s = time.perf_counter() - run.run_start
    return json_ready({
        "algo": learner.name, "iterations": run.iteration, "env_steps": env_steps,
        "total_time_s": time.perf_counter() - run.start, "compile_time_s": run.compile_s, "train_time_s": run_s,
        "env_steps_per_s": (env_steps - run.steps_at_start) / max(run_s, 1e-9),
        "resumed_from_iteration": run.resumed_from, "final_metrics": run.last_metrics, "out_dir": str(run.out_dir),
    })  # fmt: skip


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
