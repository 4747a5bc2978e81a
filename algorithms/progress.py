"""How the library reports on long work: callbacks, in the style of brax's ``progress_fn``. It never prints.

``run_training``, ``train_run``, ``evaluate`` and the reproduction's results take a ``Progress``, a bundle of
four callbacks, each doing nothing unless given:

- ``start(task)``: a ``Task`` begins (compiling, training, evaluating), with its size when known.
- ``update(completed, info)``: the innermost task has ``completed`` units done (increasing); ``info`` is a dict of
  numbers about it, e.g. a training run's latest metrics (``env_steps``, ``episode_return``, ...) with
  ``steps_per_s``, ``elapsed_s`` and ``remaining_s``.
- ``done()``: the innermost task ended (normally or not). Tasks nest: an evaluation inside a training run.
- ``note(text)``: a line worth keeping (a GP-MPC round's result, a step's wall time).

The command line turns these into a bar on a terminal and plain lines when piped (``scg_cli.progress``); a plain
function is accepted where a ``Progress`` is, as ``update``.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Mapping
from typing import NamedTuple


class Task(NamedTuple):
    """What ``Progress.start`` announces.

    Attributes:
        name: what runs (``"ppo"``, ``"compiling ppo"``, ``"evaluating lqr on 16 episodes"``).
        total: units of work in all, or None when it cannot be counted (compiling, one jitted call).
        completed: units already done when it starts (a resumed run). unit: what is counted (``"iteration"``).
    """

    name: str
    total: int | None = None
    completed: int = 0
    unit: str = ""


def _ignore(*args) -> None:
    return None


class Progress(NamedTuple):
    """The callbacks (module docstring); leave out the ones you do not need."""

    start: Callable[[Task], None] = _ignore
    update: Callable[[int, Mapping[str, float]], None] = _ignore
    done: Callable[[], None] = _ignore
    note: Callable[[str], None] = _ignore


SILENT = Progress()


def as_progress(progress) -> Progress:
    """``progress`` as a ``Progress``: None (or False) reports nothing, a function becomes ``update``. ``TypeError``
    for anything else."""
    if progress is None or progress is False:
        return SILENT
    if isinstance(progress, Progress):
        return progress
    if callable(progress):
        return Progress(update=progress)
    raise TypeError(f"progress: expected a scg_algorithms.progress.Progress, a function or None, got {progress!r}")


@contextlib.contextmanager
def running(progress: Progress, task: Task):
    """``progress.start(task)``, the block, then ``progress.done()`` however the block ends."""
    progress.start(task)
    try:
        yield
    finally:
        progress.done()
