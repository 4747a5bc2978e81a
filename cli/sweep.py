"""``scg-jax sweep``: a grid of config values x seeds x controllers, each point one evaluation task.

A robustness figure needs the same evaluation repeated over disturbance levels, seeds and methods: independent
tasks. ``run_sweep`` runs them in this process (the default) or as Ray tasks on a cluster (``--ray auto|ADDRESS``,
or ``--ray local`` for a Ray instance started on this machine; the optional extra ``scg-jax[ray]``):

- each task's result is written to ``OUT/tasks/<task id>.json`` (atomically) as soon as it finishes, so a sweep
  that is interrupted, or whose worker dies, keeps everything that finished, and running it again resumes: tasks
  whose file exists are not run again;
- a task that fails (an exception, or on Ray a worker that died) is reported and retried once; a task that fails
  twice is listed in the table with ``status: failed`` and its error (and runs again on the next resume);
- all tasks are collected into ``OUT/results.csv`` and ``OUT/results.json`` (one row per task, written whole) and
  ``OUT/results.png`` (each metric against the first grid key, mean and std over seeds, one line per controller).

A task is ``(overrides, seed, controller)``: the config with the ``--set`` and grid overrides applied, evaluated
with ``scg_algorithms.evaluation.evaluate`` on ``--episodes`` episodes with ``jax.random.key(seed)``. The same
task gives the same numbers wherever it runs (CPU), so a Ray sweep's table equals the in-process one.
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import io
import itertools
import json
import math
import time
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path

from scg_cli.common import OUT_CHECKED, UsageError, positive_int
from scg_jax.files import write_atomic, write_json

TASKS_FOLDER = "tasks"
METRICS = ("rmse", "rmse_std", "failure_rate", "constraint_violation_steps", "return", "length", "crash_rate")
"""The summary metrics of each task that go into the table (compute times are left out: they are not numbers of
the experiment and differ from run to run)."""
PLOT_METRICS = ("rmse", "failure_rate", "return")
TOP_LEVEL = ("env", "controllers", "training", "devices")


# --------------------------------------------------------------------------------------------- the grid
def parse_grid(text: str) -> tuple[str, list]:
    """``"KEY=[v1, v2, ...]"`` -> ``(dotted path, values)``; a KEY without a top-level section is under ``env``."""
    import yaml

    key, sep, values_text = text.partition("=")
    key = key.strip()
    if not sep or not key:
        raise UsageError(f"argument --grid: expected KEY=[v1,v2,...], got {text!r}")
    if key.split(".")[0].split("[")[0] not in TOP_LEVEL:
        key = f"env.{key}"
    try:
        values = yaml.safe_load(values_text)
    except yaml.YAMLError as error:
        raise UsageError(f"argument --grid: {key}: the values are not YAML ({error})") from None
    if not isinstance(values, list) or not values:
        raise UsageError(f"argument --grid: {key}: expected a non-empty list [v1,v2,...], got {values_text.strip()!r}")
    return key, values


def task_id(task: dict) -> str:
    """A short stable name of a task (a hash of its overrides, seed and controller)."""
    text = json.dumps([task["grid"], task["seed"], task["controller"]], sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def plan_tasks(grid: Sequence[tuple[str, list]], seeds: Sequence[int], controllers: Sequence[str]) -> list[dict]:
    """Every ``(grid point, controller, seed)``, grid points outermost, seeds innermost (tasks that follow each other
    share the env and controller), in a fixed order."""
    keys = [key for key, _ in grid]
    tasks = []
    for point in itertools.product(*(values for _, values in grid)):
        for controller in controllers:
            for seed in seeds:
                task = {"grid": dict(zip(keys, point, strict=True)), "seed": int(seed), "controller": controller}
                tasks.append({**task, "id": task_id(task)})
    return tasks


def task_overrides(task: dict) -> list[str]:
    """The grid point as ``--set``-style overrides (values as JSON, which is YAML)."""
    return [f"{key}={json.dumps(value)}" for key, value in task["grid"].items()]


# --------------------------------------------------------------------------------------------- one task
_BUILT: dict = {}


def evaluate_task(config_text: str, overrides: Sequence[str], task: dict, episodes: int) -> dict:
    """Run one task: ``{"summary": {METRICS...}, "run_s": seconds}``; raises whatever the evaluation raises."""
    import jax

    from scg_algorithms.evaluation import evaluate
    from scg_cli.evaluate import _build_controller
    from scg_jax.config import load_config, make_from_config

    # Tasks that differ only in the seed share the env and controller, hence one compiled closed loop.
    cache_key = json.dumps([config_text, list(overrides), task["grid"], task["controller"]], sort_keys=True)
    if cache_key not in _BUILT:
        cfg = load_config(config_text, [*overrides, *task_overrides(task)])
        env, params = make_from_config(cfg)
        _BUILT.clear()  # one entry: a sweep runs its tasks grid point by grid point
        _BUILT[cache_key] = (env, params, _build_controller(task["controller"], env, params, cfg, 1.0))
    env, params, controller = _BUILT[cache_key]
    start = time.perf_counter()
    evaluation = evaluate(env, params, controller, jax.random.key(task["seed"]), episodes, measure_time=False)
    summary = {name: evaluation.summary[name] for name in METRICS}
    return {"summary": _json_floats(summary), "run_s": time.perf_counter() - start}


def _json_floats(values: dict) -> dict:
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in values.items()}


# --------------------------------------------------------------------------------------------- executors
def _run_local(task_fn, jobs, on_done):
    for task, args in jobs:
        try:
            on_done(task, task_fn(*args), None)
        except Exception as error:  # noqa: BLE001 - any failure of a task is reported and retried
            on_done(task, None, _describe(error))


def _run_ray(task_fn, jobs, on_done, address: str, num_cpus: int | None):
    try:
        import ray
    except ImportError:
        raise UsageError("argument --ray: Ray is not installed; pip install 'scg-jax[ray]'") from None
    started = False
    if not ray.is_initialized():
        if address == "local":
            ray.init(num_cpus=num_cpus, include_dashboard=False, log_to_driver=False)
        else:
            ray.init(address=address, include_dashboard=False, log_to_driver=False)
        started = True
    try:
        # max_retries=0: a retry is this module's decision (once, reported), for exceptions and dead workers alike.
        remote = ray.remote(max_retries=0, num_cpus=1)(task_fn)
        pending = {remote.remote(*args): task for task, args in jobs}
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            task = pending.pop(done[0])
            try:
                on_done(task, ray.get(done[0]), None)
            except Exception as error:  # noqa: BLE001 - RayTaskError, WorkerCrashedError, ...
                on_done(task, None, _describe(error))
    finally:
        if started:
            ray.shutdown()


def _describe(error: BaseException) -> str:
    text = "".join(traceback.format_exception_only(type(error), error)).strip()
    return text.splitlines()[-1] if text else type(error).__name__


# --------------------------------------------------------------------------------------------- the sweep
def run_sweep(
    config_text: str,
    grid: Sequence[tuple[str, list]],
    seeds: Sequence[int],
    controllers: Sequence[str],
    out_dir,
    *,
    episodes: int = 8,
    overrides: Sequence[str] = (),
    ray: str | None = None,
    ray_cpus: int | None = None,
    task_fn: Callable = evaluate_task,
    report: Callable[[str], None] = print,
) -> dict:
    """Run every task not finished yet in ``out_dir``, retry failures once, and write the table and plot.

    Args:
        config_text: the config (YAML text). grid: ``[(dotted key, values)]``. seeds, controllers: the other axes.
        out_dir: the sweep's folder (``tasks/``, ``results.*``). episodes: per task.
        overrides: ``--set``-style overrides applied before each grid point's.
        ray: ``None`` (in this process), ``"local"`` (a Ray instance on this machine with ``ray_cpus`` CPUs),
            ``"auto"`` or an address (an existing cluster).
        task_fn: ``task_fn(config_text, overrides, task, episodes) -> {"summary": {...}, ...}``.
        report: receives one line per finished, failed or retried task.

    Returns:
        ``{"tasks", "ran", "resumed", "failed" (ids), "rows" (the table)}``.
    """
    out_dir = Path(out_dir)
    tasks = plan_tasks(grid, seeds, controllers)
    folder = out_dir / TASKS_FOLDER
    results: dict[str, dict] = {}
    for task in tasks:
        path = folder / f"{task['id']}.json"
        if path.exists():
            stored = json.loads(path.read_text())
            if stored.get("task") == _task_key(task) and stored.get("episodes") == episodes:
                results[task["id"]] = stored
    resumed = len(results)
    if resumed:
        report(f"resuming: {resumed} of {len(tasks)} tasks already finished in {folder}")

    attempts: dict[str, int] = {}
    errors: dict[str, str] = {}

    def on_done(task, result, error):
        attempts[task["id"]] = attempts.get(task["id"], 0) + 1
        label = f"{task['controller']} seed {task['seed']} {task['grid']}"
        if error is None:
            record = {"task": _task_key(task), "episodes": episodes, "attempts": attempts[task["id"]], **result}
            write_json(folder / f"{task['id']}.json", record)  # kept even if the sweep stops right after
            results[task["id"]] = record
            errors.pop(task["id"], None)
            report(f"done   {label} ({len(results)}/{len(tasks)})")
        else:
            errors[task["id"]] = error
            report(f"failed {label} (attempt {attempts[task['id']]}): {error}")

    def run(batch):
        jobs = [(task, (config_text, list(overrides), task, episodes)) for task in batch]
        if ray is None:
            _run_local(task_fn, jobs, on_done)
        else:
            _run_ray(task_fn, jobs, on_done, ray, ray_cpus)

    todo = [task for task in tasks if task["id"] not in results]
    run(todo)
    retry = [task for task in todo if task["id"] in errors]
    if retry:
        report(f"retrying {len(retry)} failed task(s) once")
        run(retry)

    rows = [_row(task, results.get(task["id"]), errors.get(task["id"])) for task in tasks]
    _write_table(out_dir, rows, [key for key, _ in grid])
    failed = [task["id"] for task in tasks if task["id"] not in results]
    return {"tasks": len(tasks), "ran": len(todo), "resumed": resumed, "failed": failed, "rows": rows}


def _task_key(task: dict) -> dict:
    return {"grid": task["grid"], "seed": task["seed"], "controller": task["controller"]}


def _row(task: dict, result: dict | None, error: str | None) -> dict:
    row = {"task": task["id"], "controller": task["controller"], "seed": task["seed"], **task["grid"]}
    if result is None:
        return {**row, "status": "failed", **{name: None for name in METRICS}, "error": error}
    return {**row, "status": "ok", **result["summary"], "error": None}


def _write_table(out_dir: Path, rows: list[dict], grid_keys: list[str]) -> None:
    columns = list(rows[0]) if rows else []
    text = io.StringIO()
    writer = csv.DictWriter(text, columns, lineterminator="\n")
    writer.writeheader()
    writer.writerows(
        {k: ("" if v is None else json.dumps(v) if isinstance(v, list | dict) else v) for k, v in r.items()}
        for r in rows
    )
    write_atomic(out_dir / "results.csv", lambda file: file.write(text.getvalue().encode()))
    write_json(out_dir / "results.json", rows)
    if rows and grid_keys:
        plot_sweep(rows, grid_keys[0], out_dir / "results.png")


def plot_sweep(rows: list[dict], key: str, png_path) -> None:
    """Each of ``PLOT_METRICS`` against the grid key ``key``: mean over seeds (and any other grid keys) with a
    band of one std, one line per controller; failed tasks left out. Written atomically."""
    import numpy as np
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(4.2 * len(PLOT_METRICS), 3.2), layout="constrained")
    FigureCanvasAgg(fig)
    controllers = list(dict.fromkeys(row["controller"] for row in rows))
    levels = list(dict.fromkeys(json.dumps(row[key]) for row in rows))
    numeric = all(isinstance(json.loads(level), int | float) for level in levels)
    for i, metric in enumerate(PLOT_METRICS):
        ax = fig.add_subplot(1, len(PLOT_METRICS), i + 1)
        for controller in controllers:
            means, stds = [], []
            for level in levels:
                values = [
                    row[metric]
                    for row in rows
                    if row["controller"] == controller and json.dumps(row[key]) == level and row[metric] is not None
                ]
                means.append(np.mean(values) if values else np.nan)
                stds.append(np.std(values) if values else np.nan)
            x = [json.loads(level) for level in levels] if numeric else np.arange(len(levels))
            means, stds = np.asarray(means), np.asarray(stds)
            ax.plot(x, means, marker="o", label=controller)
            ax.fill_between(x, means - stds, means + stds, alpha=0.2)
        if not numeric:
            ax.set_xticks(np.arange(len(levels)), levels, fontsize=7)
        ax.set_xlabel(key, fontsize=9)
        ax.set_title(metric, fontsize=10)
        ax.grid(alpha=0.3)
        if i == 0:
            ax.legend(fontsize=8)
    write_atomic(png_path, lambda file: fig.savefig(file, format="png", dpi=100))


# --------------------------------------------------------------------------------------------- command line
def add_sweep_parser(subparsers) -> argparse.ArgumentParser:
    parser = subparsers.add_parser(
        "sweep",
        help="evaluate controllers over a grid of config values and seeds, in-process or on Ray; one table",
        description=(
            "Run every (grid point, seed, controller) as an evaluation task, in this process or on a Ray cluster "
            "(--ray), store each result as it finishes, retry a failed task once, resume what is missing when run "
            "again, and write OUT/results.csv, results.json and results.png."
        ),
    )
    parser.add_argument("--config", type=Path, required=True, metavar="FILE", help="YAML config file")
    parser.add_argument(
        "--grid",
        action="append",
        default=[],
        required=True,
        metavar="KEY=[V1,V2,...]",
        help="a config path (under env unless it starts with env/controllers/training) and its values; repeatable, "
        "the grid is the product, e.g. 'env.disturbances.action[0].std=[0,0.05,0.1]'",
    )
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override for every task")
    parser.add_argument("--seeds", type=positive_int, default=3, help="seeds 0..N-1 (default: 3)")
    parser.add_argument(
        "--controllers", required=True, metavar="A,B,...", help="controller names or trained policy folders"
    )
    parser.add_argument("--episodes", type=positive_int, default=8, help="episodes per task (default: 8)")
    parser.add_argument("--out", type=Path, required=True, metavar="DIR", help=f"sweep folder{OUT_CHECKED}")
    parser.add_argument(
        "--ray",
        metavar="local|auto|ADDRESS",
        help="run the tasks on Ray: 'local' starts an instance here, 'auto' or HOST:PORT joins a cluster",
    )
    parser.add_argument("--ray-cpus", type=positive_int, help="CPUs of a --ray local instance (default: all)")
    return parser


def run_sweep_command(args: argparse.Namespace, console) -> int:
    from scg_cli.common import check_output
    from scg_jax.config import dump_config, load_config, make_from_config
    from scg_jax.validation import FieldError

    check_output(args.out, "dir")
    grid = [parse_grid(text) for text in args.grid]
    controllers = [item.strip() for item in args.controllers.split(",") if item.strip()]
    if not controllers or len(set(controllers)) != len(controllers):
        raise UsageError(f"argument --controllers: expected distinct names or folders, got {args.controllers!r}")
    if args.ray_cpus is not None and args.ray != "local":
        raise UsageError("argument --ray-cpus: only with --ray local")
    try:
        cfg = load_config(args.config, list(args.set))
        for task in plan_tasks(grid, [0], controllers[:1]):  # every grid point is a valid config before any run
            make_from_config(load_config(cfg, task_overrides(task)))
    except FieldError as error:
        raise UsageError(f"argument --grid: {error}") from None
    except (ValueError, OSError) as error:
        raise UsageError(str(error)) from None
    summary = run_sweep(
        dump_config(cfg),
        grid,
        range(args.seeds),
        controllers,
        args.out,
        episodes=args.episodes,
        ray=args.ray,
        ray_cpus=args.ray_cpus,
        report=lambda line: console.print(line, markup=False, highlight=False),
    )
    console.print(
        f"{summary['tasks']} tasks: {summary['ran']} run, {summary['resumed']} resumed, {len(summary['failed'])} "
        f"failed; wrote {args.out}/results.csv, results.json, results.png"
    )
    return 1 if summary["failed"] else 0
