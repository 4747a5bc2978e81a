"""The command line's progress display (``scg_cli.progress``): plain lines when piped, at least one every
``--progress-interval`` seconds while a task runs, even when the library reports nothing (compiling)."""

from __future__ import annotations

import io
import time

from rich.console import Console

from scg_algorithms.progress import Task
from scg_cli import main
from scg_cli.progress import ConsoleProgress, format_seconds


def _piped(interval: float):
    stream = io.StringIO()
    return ConsoleProgress(Console(file=stream, force_terminal=False, width=200), interval), stream


def test_a_counted_task_prints_its_count_status_and_times():
    reporter, stream = _piped(3600.0)
    progress = reporter.progress()
    progress.start(Task("ppo", 4, 1, "iteration"))
    info = {"env_steps": 512, "steps_per_s": 1234.4, "episode_return": 1.5, "elapsed_s": 3.0, "remaining_s": 62.0}
    progress.update(2, info)  # within the interval: not printed
    progress.update(4, {**info, "env_steps": 1024, "remaining_s": 0.0})  # the last count always is
    progress.note("a note")
    progress.done()
    assert stream.getvalue().splitlines() == [
        "ppo: iteration 1/4 (25.0%), elapsed 0:00, remaining ?",
        "ppo: iteration 4/4 (100.0%), 1,024 env steps, 1,234 steps/s, return 1.5, elapsed 0:03, remaining 0:00",
        "a note",
    ]
    assert [format_seconds(s) for s in (0.4, 61, 3725, float("nan"))] == ["0:00", "1:01", "1:02:05", "?"]


def test_piped_output_gets_a_line_every_interval_while_nothing_is_reported():
    """A task that reports nothing (compiling) still gets lines: one at its start, then one per interval."""
    reporter, stream = _piped(0.05)
    progress = reporter.progress()
    progress.start(Task("compiling ppo"))
    deadline = time.monotonic() + 30.0
    while len(stream.getvalue().splitlines()) < 3 and time.monotonic() < deadline:
        time.sleep(0.01)
    progress.done()
    lines = stream.getvalue().splitlines()
    assert len(lines) >= 3 and all(line.startswith("compiling ppo: elapsed ") for line in lines)
    assert reporter.ticker is None  # the timekeeping thread ends with the last task
    count = len(stream.getvalue().splitlines())
    time.sleep(0.2)
    assert len(stream.getvalue().splitlines()) == count  # and prints nothing after it


def test_on_a_terminal_a_counted_task_leaves_its_last_line():
    stream = io.StringIO()
    progress = ConsoleProgress(Console(file=stream, force_terminal=True, width=200), 10.0).progress()
    progress.start(Task("lqr", 3, 0, "step"))
    progress.start(Task("compiling"))  # tasks nest
    progress.done()
    progress.update(3, {})
    progress.done()
    assert "lqr: step 3/3 (100.0%), elapsed" in stream.getvalue()


def test_a_piped_eval_reports_the_evaluation(tmp_path, capsys):
    argv = ["eval", "--system", "cartpole", "--controller", "lqr", "--episodes", "4", "--episode-len", "1"]
    assert main([*argv, "--progress-interval", "0.05", "--out", str(tmp_path / "e.json")]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("evaluating lqr on 4 episodes: elapsed 0:0")
