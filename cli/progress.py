"""The command line's side of ``scg_algorithms.progress``: what the library reports, drawn on the console.

On a terminal the open tasks are live rich bars (a pulsing bar while a task cannot be counted, e.g. compiling),
and a counted task leaves one line when it ends. When stdout is not a terminal (a log file, a pipe, CI) there is
nothing to redraw, so plain lines are printed instead: one when a task starts, then one at least every
``--progress-interval`` seconds while it runs (also while nothing is reported, e.g. during compilation or a long
host-side evaluation: a background thread keeps time) and one for its last count. Notes are printed as they come.
``command_progress`` keeps a task open for a command's whole run, so the lines keep coming between the library's
tasks too (building controllers, loading, writing).

Ctrl-C that Python swallowed: a ``KeyboardInterrupt`` raised while Python runs a callback of its own (a garbage
collector callback, as JAX installs one) is printed as "Exception ignored" and dropped, and the command would go on
as if nothing happened. ``catch_swallowed_interrupts`` records such an interrupt instead, and the next progress
callback (``start``, ``update`` or ``note``: the library calls them at least at every task, e.g. before writing
results) raises it again, so the command stops as on any other Ctrl-C.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import sys
import threading
import time
from collections.abc import Iterator

import numpy as np

from scg_algorithms.progress import SILENT, Progress, Task

_SWALLOWED_INTERRUPT = threading.Event()


@contextlib.contextmanager
def catch_swallowed_interrupts() -> Iterator[None]:
    """While the block runs, a ``KeyboardInterrupt`` that Python would print as "Exception ignored" and drop is
    recorded (silently) and raised again by the next progress callback (module docstring)."""
    previous = sys.unraisablehook

    def hook(unraisable):
        if unraisable.exc_type is not None and issubclass(unraisable.exc_type, KeyboardInterrupt):
            _SWALLOWED_INTERRUPT.set()
        else:
            previous(unraisable)

    _SWALLOWED_INTERRUPT.clear()
    sys.unraisablehook = hook
    try:
        yield
    finally:
        sys.unraisablehook = previous
        _SWALLOWED_INTERRUPT.clear()


def _raise_swallowed_interrupt() -> None:
    if _SWALLOWED_INTERRUPT.is_set():
        _SWALLOWED_INTERRUPT.clear()
        raise KeyboardInterrupt


def positive_seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not (np.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected a positive number of seconds, got {text!r}")
    return value


def add_progress_argument(parser: argparse.ArgumentParser) -> None:
    """``--progress-interval SECONDS`` (default 10)."""
    parser.add_argument(
        "--progress-interval",
        type=positive_seconds,
        default=10.0,
        metavar="SECONDS",
        help="when stdout is not a terminal, print a progress line at least every this many seconds (default: 10)",
    )


def format_seconds(seconds: float) -> str:
    """``m:ss`` or ``h:mm:ss``; ``?`` when unknown."""
    if not math.isfinite(seconds):
        return "?"
    seconds = int(round(seconds))
    hours, rest = divmod(seconds, 3600)
    return f"{hours}:{rest // 60:02d}:{rest % 60:02d}" if hours else f"{rest // 60}:{rest % 60:02d}"


def status_text(info) -> str:
    """What a training iteration's ``info`` says in a few words: env steps, their rate and the episode return."""
    if "env_steps" not in info:
        return ""
    return (
        f"{int(info['env_steps']):,} env steps, {info.get('steps_per_s', math.nan):,.0f} steps/s, return "
        f"{_number(info.get('episode_return')):.4g}"
    )


def _number(value) -> float:
    return math.nan if value is None else float(value)


class _Open:
    """A task that started and has not ended, with what was last reported about it."""

    def __init__(self, task: Task):
        self.task, self.completed, self.info = task, task.completed, {}
        self.started = time.perf_counter()
        self.bar = None  # the rich task id on a terminal

    def elapsed(self) -> float:
        return float(self.info.get("elapsed_s", time.perf_counter() - self.started))

    def remaining(self) -> float:
        if "remaining_s" in self.info:
            return float(self.info["remaining_s"])
        done_here = self.completed - self.task.completed
        if self.task.total is None or done_here <= 0:
            return math.nan
        return (time.perf_counter() - self.started) / done_here * (self.task.total - self.completed)

    def line(self) -> str:
        """``"ppo: iteration 2/8 (25.0%), 512 env steps, ..., elapsed 0:03, remaining 0:09"``."""
        task, parts = self.task, []
        if task.total is not None:
            fraction = 100.0 * self.completed / max(task.total, 1)
            parts.append(f"{task.unit} {self.completed}/{task.total} ({fraction:.1f}%)".strip())
        status = status_text(self.info)
        if status:
            parts.append(status)
        parts.append(f"elapsed {format_seconds(self.elapsed())}")
        if task.total is not None:
            parts.append(f"remaining {format_seconds(self.remaining())}")
        return f"{task.name}: {', '.join(parts)}"


class ConsoleProgress:
    """Draws a ``Progress`` on a rich ``console`` (module docstring); ``interval`` is the plain lines' period (s)."""

    def __init__(self, console, interval: float = 10.0):
        self.console, self.interval = console, float(interval)
        self.plain = not console.is_terminal
        self.open: list[_Open] = []
        self.lock = threading.Lock()
        self.last_print = -math.inf
        self.live = None  # rich.progress.Progress while a task is open on a terminal
        self.ticker: threading.Thread | None = None
        self.stop_ticker = threading.Event()

    def progress(self) -> Progress:
        """The callbacks to hand to the library."""
        return Progress(start=self.start, update=self.update, done=self.done, note=self.note)

    def note(self, text: str) -> None:
        _raise_swallowed_interrupt()
        with self.lock:
            self.console.print(text, markup=False, highlight=False, soft_wrap=True)

    def start(self, task: Task, announce: bool = True) -> None:
        """Open ``task``; when piped its first line is printed now, or (``announce=False``) only once ``interval``
        seconds pass without a line, so a command that fails at once prints nothing but its error."""
        _raise_swallowed_interrupt()
        with self.lock:
            entry = _Open(task)
            self.open.append(entry)
            if self.plain:
                if announce:
                    self._print(entry.line())
                else:
                    self.last_print = time.perf_counter()
                self._start_ticker()
            else:
                self._draw(entry)

    def update(self, completed: int, info) -> None:
        _raise_swallowed_interrupt()
        with self.lock:
            if not self.open:
                return
            entry = self.open[-1]
            entry.completed, entry.info = int(completed), dict(info)
            if not self.plain:
                self.live.update(entry.bar, completed=entry.completed, **self._fields(entry))
            elif time.perf_counter() - self.last_print >= self.interval or self._finished(entry):
                self._print(entry.line())

    def done(self) -> None:
        with self.lock:
            if not self.open:
                return
            entry = self.open.pop()
            if not self.plain:
                self.live.remove_task(entry.bar)
                if entry.task.total is not None:  # a counted task leaves its last line
                    self.live.console.print(entry.line(), markup=False, highlight=False, soft_wrap=True)
                if not self.open:
                    self.live.stop()
                    self.live = None
            elif not self.open:
                self.stop_ticker.set()
        if self.plain and not self.open and self.ticker is not None:
            self.ticker.join()
            self.ticker = None

    # ------------------------------------------------------------------------------------------ internals
    @staticmethod
    def _finished(entry: _Open) -> bool:
        return entry.task.total is not None and entry.completed >= entry.task.total

    def _print(self, line: str) -> None:
        self.console.print(line, markup=False, highlight=False, soft_wrap=True)
        self.last_print = time.perf_counter()

    def _start_ticker(self) -> None:
        if self.ticker is not None:
            return
        self.stop_ticker.clear()
        self.ticker = threading.Thread(target=self._tick, name="scg-jax progress", daemon=True)
        self.ticker.start()

    def _tick(self) -> None:
        """While a task is open: a line whenever ``interval`` seconds passed without one."""
        while not self.stop_ticker.wait(min(max(self.interval / 4, 0.05), 1.0)):
            with self.lock:
                if self.open and time.perf_counter() - self.last_print >= self.interval:
                    self._print(self.open[-1].line())

    @staticmethod
    def _fields(entry: _Open) -> dict:
        task = entry.task
        count = "" if task.total is None else f"{entry.completed}/{task.total} {task.unit}".strip()
        remaining = "" if task.total is None else f"remaining {format_seconds(entry.remaining())}"
        return {"count": count, "status": ", ".join(p for p in (status_text(entry.info), remaining) if p)}

    def _draw(self, entry: _Open) -> None:
        from rich.progress import BarColumn, Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

        if self.live is None:
            self.live = Progress(
                SpinnerColumn(),
                TextColumn("[bold]{task.description}"),
                BarColumn(),
                TextColumn("{task.fields[count]}"),
                TimeElapsedColumn(),
                TextColumn("{task.fields[status]}"),
                console=self.console,
            )
            self.live.start()
        entry.bar = self.live.add_task(
            entry.task.name, total=entry.task.total, completed=entry.task.completed, **self._fields(entry)
        )


def console_progress(console, interval: float = 10.0, enabled: bool = True) -> Progress:
    """A ``Progress`` drawn on ``console`` (``ConsoleProgress``), or a silent one when not ``enabled`` (e.g. every
    process of a ``--distributed`` job but process 0)."""
    return ConsoleProgress(console, interval).progress() if enabled else SILENT


@contextlib.contextmanager
def command_progress(console, name: str, interval: float = 10.0, enabled: bool = True) -> Iterator[Progress]:
    """The progress of a whole command: the task ``name`` is open while the block runs, so a piped command prints a
    line at least every ``interval`` seconds from here to its end, also while it builds envs and controllers, loads
    or writes files (where the library reports no task of its own); the library's tasks nest inside it. Its first
    line waits for the first interval (a usage error found at once prints only itself). Silent when not
    ``enabled``. The block's results are printed after it, once the task has ended."""
    if not enabled:
        yield SILENT
        return
    reporter = ConsoleProgress(console, interval)
    reporter.start(Task(name), announce=False)
    try:
        yield reporter.progress()
    finally:
        reporter.done()
