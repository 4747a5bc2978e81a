"""The command line's progress display (``scg_cli.progress``): plain lines when piped, at least one every
``--progress-interval`` seconds while a task runs, even when the library reports nothing (compiling), and from a
command's start to its end; Ctrl-C in ``compare`` and ``eval`` (status 130, one line). The piped train is
``tests/test_cli_train.py``'s."""

from __future__ import annotations

import io
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from rich.console import Console

from scg_algorithms.progress import Task
from scg_cli.progress import ConsoleProgress, catch_swallowed_interrupts, format_seconds


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


class _InterruptedWhenCollected:
    """Raises Ctrl-C's exception where Python swallows it: in ``__del__``, as in JAX's garbage-collector callback."""

    def __del__(self):
        raise KeyboardInterrupt


def test_a_swallowed_ctrl_c_is_raised_at_the_next_progress_callback_and_prints_nothing(capsys):
    progress = ConsoleProgress(Console(file=io.StringIO()), interval=60.0).progress()
    hook = sys.unraisablehook
    with catch_swallowed_interrupts():
        progress.start(Task("work", total=3))
        progress.update(1, {})
        _InterruptedWhenCollected()  # collected at once: Python hands its exception to sys.unraisablehook
        with pytest.raises(KeyboardInterrupt):
            progress.update(2, {})
        progress.update(3, {})  # raised once, then forgotten
    assert capsys.readouterr().err == ""  # no "Exception ignored" lines
    assert sys.unraisablehook is hook  # outside the block Python reports such exceptions as before


def test_on_a_terminal_a_counted_task_leaves_its_last_line():
    stream = io.StringIO()
    progress = ConsoleProgress(Console(file=stream, force_terminal=True, width=200), 10.0).progress()
    progress.start(Task("lqr", 3, 0, "step"))
    progress.start(Task("compiling"))  # tasks nest
    progress.done()
    progress.update(3, {})
    progress.done()
    assert "lqr: step 3/3 (100.0%), elapsed" in stream.getvalue()


# ----------------------------------------------------------------------------------------------- as a user runs them
# Piped through the installed entry point. The interval is small; a line may come a little late on a loaded machine
# (the thread that keeps time waits for the CPU like everything else), hence the slack. Without the command's own task
# the first lines came only when the harness started evaluating, after building every controller (20 s before).
INTERVAL = 0.25
SLACK = 2.0
PROGRESS_LINE = re.compile(r"^[^:]+: .*elapsed \d+:\d\d")


class _Piped:
    """``scg-jax ARGS`` with stdout and stderr piped; a thread timestamps each stdout line as it arrives."""

    def __init__(self, args, cwd):
        self.process = subprocess.Popen(
            [str(Path(sys.prefix) / "bin" / "scg-jax"), *args],
            cwd=cwd,
            # Compiled afresh, as a user's first run is: a persistent cache's executables would make XLA log a
            # version-compatibility warning on stderr, which these tests require to be empty.
            env={key: value for key, value in os.environ.items() if key != "JAX_COMPILATION_CACHE_DIR"},
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            # Ctrl-C as in a terminal: a test run started in the background (``pytest &`` in a script) ignores
            # SIGINT, the child would inherit that, and Python would then not raise KeyboardInterrupt at all.
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
        )
        self.lines: list[tuple[float, str]] = []
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()

    def _read(self):
        for line in self.process.stdout:
            self.lines.append((time.monotonic(), line.rstrip("\n")))

    def wait_for(self, condition, timeout=300.0):
        deadline = time.monotonic() + timeout
        while not condition([text for _, text in self.lines]):
            assert self.process.poll() is None, f"ended early: {self.lines} {self.process.stderr.read()}"
            assert time.monotonic() < deadline, f"timed out: {self.lines}"
            time.sleep(0.01)

    def finish(self, timeout=300.0) -> tuple[int, list[tuple[float, str]], str]:
        status = self.process.wait(timeout)
        self.reader.join(timeout)
        return status, self.lines, self.process.stderr.read()


def _gaps(lines) -> list[float]:
    return [b - a for (a, _), (b, _) in zip(lines, lines[1:], strict=False)]


def test_piped_compare_prints_every_interval_from_its_start_and_ctrl_c_exits_130(tmp_path):
    """The first line is the command's own (before the env and the controller are built), then one at least every
    --progress-interval seconds through building, compiling and evaluating (host-side, step by step); Ctrl-C during
    the evaluation: status 130, one line, no traceback."""
    (tmp_path / "configs").symlink_to(Path(__file__).resolve().parents[1] / "configs")
    # 20 s episodes: the evaluation takes about 7 s on an idle 2-core machine, so Ctrl-C, sent at its second progress
    # line, lands inside it (with 3 s episodes it took 1 s and could end before the signal came: status 0).
    args = ["compare", "--config", "configs/cartpole_stabilization.yaml", "--set", "env.episode_len_sec=20",
            "--controllers", "nonlinear_mpc", "--episodes", "3", "--progress-interval", str(INTERVAL)]  # fmt: skip
    run = _Piped(args, tmp_path)
    run.wait_for(lambda lines: sum(line.startswith("evaluating nonlinear_mpc") for line in lines) >= 2)
    run.process.send_signal(signal.SIGINT)
    status, lines, err = run.finish()
    assert status == 130 and err == "", err
    texts = [text for _, text in lines]
    assert texts[0].startswith("compare nonlinear_mpc: elapsed 0:0")
    assert all(PROGRESS_LINE.match(text) for text in texts[:-1]), texts
    assert texts[-1] == "interrupted; nothing written"
    assert max(_gaps(lines[:-1])) <= INTERVAL + SLACK, list(zip(_gaps(lines), texts[1:], strict=True))


def test_piped_eval_prints_every_interval_through_compilation_evaluation_and_writing(tmp_path):
    """A JAX controller: the closed loop is one jitted call (compiled, then run), then the files are written; a line
    at least every interval from the command's own first line to the table."""
    out = tmp_path / "e.json"
    args = ["eval", "--system", "cartpole", "--controller", "lqr", "--episodes", "4", "--episode-len", "1",
            "--progress-interval", str(INTERVAL), "--out", str(out)]  # fmt: skip
    status, lines, err = _Piped(args, tmp_path).finish()
    assert status == 0 and err == "", err
    texts = [text for _, text in lines]
    table = next(i for i, text in enumerate(texts) if not PROGRESS_LINE.match(text))
    assert texts[0].startswith("eval lqr: elapsed 0:0") and table > 2
    assert any(t.startswith("evaluating lqr on 4 episodes") for t in texts[:table])
    assert any(t.startswith(f"writing {out}") for t in texts[:table])
    assert max(_gaps(lines[:table])) <= INTERVAL + SLACK, list(zip(_gaps(lines), texts[1:], strict=False))
    assert out.is_file() and out.with_suffix(".png").is_file() and any(t.startswith("wrote ") for t in texts[table:])


def test_piped_eval_ctrl_c_after_the_first_progress_line_exits_130_with_one_line(tmp_path):
    out = tmp_path / "e.json"
    args = ["eval", "--system", "cartpole", "--controller", "lqr", "--episodes", "4",
            "--progress-interval", str(INTERVAL), "--out", str(out)]  # fmt: skip
    for _ in range(3):
        run = _Piped(args, tmp_path)
        run.wait_for(lambda lines: len(lines) >= 1)
        run.process.send_signal(signal.SIGINT)
        status, lines, err = run.finish()
        if not (status == 0 and out.is_file()):
            break
        # The whole eval takes about 1.5 s: on a loaded machine it can end, its files written, before the signal is
        # sent. That is not the case under test, so run it again (a signal that is ignored fails all three runs).
        for path in tmp_path.iterdir():
            path.unlink()
    texts = [text for _, text in lines]
    assert status == 130 and err == "" and "Traceback" not in " ".join(texts), err
    assert texts[0].startswith("eval lqr: elapsed 0:0") and texts[-1] == "interrupted; nothing written"
    assert all(PROGRESS_LINE.match(text) for text in texts[:-1]), texts
    assert not any(tmp_path.iterdir())
