"""``scg-jax sweep``: the grid as tasks, per-task results kept as they finish, resume, one retry, and the same
table on a local Ray instance (2 CPUs, one of whose workers is killed mid-sweep) as in this process."""

import csv
import json
import os
from pathlib import Path

import jax
import pytest

import scg_jax
from scg_algorithms.evaluation import evaluate
from scg_algorithms.lqr import make_lqr
from scg_cli import main
from scg_cli.sweep import METRICS, evaluate_task, parse_grid, plan_tasks, run_sweep
from scg_jax.config import dump_config, load_config

CONFIG = load_config(
    {
        "env": {
            "system": "cartpole",
            "episode_len_sec": 0.5,
            "disturbances": {"action": [{"type": "white_noise", "std": 0.0}]},
        }
    }
)
GRID = [("env.disturbances.action[0].std", [0.0, 0.2])]
EPISODES = 2


def quiet(line):
    pass


def fake_task(config_text, overrides, task, episodes):
    """A stand-in evaluation: numbers determined by the task, no JAX (tests of the sweep machinery)."""
    level = next(iter(task["grid"].values()))
    return {"summary": {name: 10.0 * level + task["seed"] + i for i, name in enumerate(METRICS)}}


def _table(folder: Path) -> list[dict]:
    with (folder / "results.csv").open() as file:
        return list(csv.DictReader(file))


def test_grid_parsing_and_task_plan():
    assert parse_grid("disturbances.action[0].std=[0, 0.05, 0.1]") == ("env.disturbances.action[0].std", [0, 0.05, 0.1])
    assert parse_grid("controllers.lqr.r=[1,2]")[0] == "controllers.lqr.r"
    tasks = plan_tasks([("env.a", [1, 2]), ("env.b", ["x"])], range(3), ["lqr", "pid"])
    assert len(tasks) == 2 * 1 * 3 * 2 and len({t["id"] for t in tasks}) == len(tasks)
    assert tasks[0]["grid"] == {"env.a": 1, "env.b": "x"} and tasks[-1]["grid"] == {"env.a": 2, "env.b": "x"}


def test_bad_grid_names_the_option(tmp_path, capsys):
    config = tmp_path / "c.yaml"
    config.write_text(dump_config(CONFIG))
    base = ["sweep", "--config", str(config), "--controllers", "lqr", "--out", str(tmp_path / "s")]
    assert main([*base, "--grid", "ctrl_freq=7"]) == 2
    assert "argument --grid: env.ctrl_freq: expected a non-empty list" in capsys.readouterr().err
    assert main([*base, "--grid", "ctrl_freq=[50, -1]"]) == 2
    assert "argument --grid: env.ctrl_freq" in capsys.readouterr().err
    assert not (tmp_path / "s").exists()


def test_an_interrupted_sweep_keeps_finished_tasks_and_resumes_the_rest(tmp_path):
    calls = []

    def interrupted(*args):
        if len(calls) == 3:
            raise KeyboardInterrupt  # Ctrl-C (or the machine going away) in the middle of the sweep
        calls.append(args[2]["id"])
        return fake_task(*args)

    with pytest.raises(KeyboardInterrupt):
        run_sweep("", GRID, range(3), ["a"], tmp_path, task_fn=interrupted, report=quiet)
    assert len(list((tmp_path / "tasks").iterdir())) == 3
    resumed_calls = []

    def counting(*args):
        resumed_calls.append(args[2]["id"])
        return fake_task(*args)

    summary = run_sweep("", GRID, range(3), ["a"], tmp_path, task_fn=counting, report=quiet)
    assert summary["resumed"] == 3 and summary["ran"] == 3 and not summary["failed"]
    assert set(resumed_calls).isdisjoint(calls) and len(resumed_calls) == 3
    full = run_sweep("", GRID, range(3), ["a"], tmp_path / "full", task_fn=fake_task, report=quiet)
    assert _table(tmp_path) == _table(tmp_path / "full")
    assert [row["rmse"] for row in full["rows"]] == [0.0, 1.0, 2.0, 2.0, 3.0, 4.0]


def test_a_failing_task_is_retried_once_then_reported(tmp_path):
    attempts: dict = {}

    def flaky(*args):
        task = args[2]
        attempts[task["id"]] = attempts.get(task["id"], 0) + 1
        if task["seed"] == 0 and attempts[task["id"]] == 1:
            raise RuntimeError("transient")
        if task["seed"] == 1:
            raise FloatingPointError("always")
        return fake_task(*args)

    lines = []
    summary = run_sweep("", GRID[:1], range(2), ["a"], tmp_path, task_fn=flaky, report=lines.append)
    assert sorted(attempts.values()) == [2, 2, 2, 2]  # every failure retried exactly once
    rows = {(row["seed"], row["env.disturbances.action[0].std"]): row for row in summary["rows"]}
    assert rows[0, 0.0]["status"] == "ok" and rows[0, 0.2]["status"] == "ok"
    assert rows[1, 0.0]["status"] == "failed" and rows[1, 0.0]["error"] == "FloatingPointError: always"
    assert len(summary["failed"]) == 2
    stored = json.loads((tmp_path / "tasks" / f"{rows[0, 0.0]['task']}.json").read_text())
    assert stored["attempts"] == 2
    assert sum(line.startswith("failed") for line in lines) == 6 and any("retrying 4" in line for line in lines)
    assert json.loads((tmp_path / "results.json").read_text()) == summary["rows"]


@pytest.fixture(scope="module")
def in_process(tmp_path_factory):
    folder = tmp_path_factory.mktemp("sweep_local")
    summary = run_sweep(dump_config(CONFIG), GRID, range(1), ["lqr"], folder, episodes=EPISODES, report=quiet)
    return folder, summary


def test_in_process_sweep_rows_are_the_evaluations(in_process):
    folder, summary = in_process
    assert not summary["failed"] and len(summary["rows"]) == 2
    assert (folder / "results.png").stat().st_size > 0
    env = scg_jax.make("cartpole", episode_len_sec=0.5, disturbances={"action": [{"type": "white_noise", "std": 0.2}]})
    params = env.default_params
    direct = evaluate(env, params, make_lqr(env, params), jax.random.key(0), EPISODES, measure_time=False)
    row = summary["rows"][1]
    assert row["rmse"] == pytest.approx(direct.summary["rmse"], rel=1e-6)
    assert summary["rows"][0]["rmse"] < row["rmse"]  # the disturbance does disturb


def test_ray_sweep_with_a_killed_worker_gives_the_in_process_table(in_process, tmp_path):
    ray = pytest.importorskip("ray")
    folder, summary = in_process
    marker = tmp_path / "killed"

    def kill_first_worker(config_text, overrides, task, episodes):
        if task["grid"]["env.disturbances.action[0].std"] == 0.2 and not marker.exists():
            marker.write_text(str(os.getpid()))
            os._exit(1)  # the worker process dies mid-sweep
        return evaluate_task(config_text, overrides, task, episodes)

    lines = []
    out = tmp_path / "ray"
    ray_summary = run_sweep(
        dump_config(CONFIG), GRID, range(1), ["lqr"], out, episodes=EPISODES, ray="local", ray_cpus=2,
        task_fn=kill_first_worker, report=lines.append,
    )  # fmt: skip
    assert not ray.is_initialized()
    assert marker.exists() and any("failed" in line for line in lines)
    assert not ray_summary["failed"]
    assert _table(out) == _table(folder)
    attempts = sorted(json.loads(p.read_text())["attempts"] for p in (out / "tasks").iterdir())
    assert attempts == [1, 2]
