"""Results are written whole or not at all: a temporary file in the target folder, then an atomic rename.

``check_output_dir`` and ``check_output_file`` check an output location before any work, so a run never computes
for minutes and then fails to save.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path


@contextlib.contextmanager
def replacing(path, suffix: str = ".tmp") -> Iterator[Path]:
    """A temporary file beside ``path`` to write, renamed over ``path`` (mode 0644) when the block ends.

    For writers that need a file name (an external encoder): ``with replacing(path, ".mp4") as tmp: encode(tmp)``.
    If the block raises, ``path`` is left as it was and the temporary file is removed. ``suffix`` is the temporary
    file's ending (some writers choose the format by it).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=suffix)
    os.close(fd)
    try:
        yield Path(tmp)
        os.chmod(tmp, 0o644)  # mkstemp creates 0600; results are meant to be read by others
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def write_atomic(path, write: Callable) -> None:
    """Call ``write(binary_file)`` on a temporary file beside ``path``, then rename it over ``path`` (mode 0644).

    If ``write`` raises, ``path`` is left as it was and the temporary file is removed.
    """
    with replacing(path) as tmp, open(tmp, "wb") as file:
        write(file)
        file.flush()
        os.fsync(file.fileno())


def write_json(path, data) -> None:
    """``data`` as indented JSON, written atomically."""
    write_atomic(path, lambda file: file.write((json.dumps(data, indent=2) + "\n").encode()))


def check_output_dir(path) -> Path:
    """Check, before any work, that results can be written into the folder ``path``; return it as a ``Path``.

    The folder and any missing parents are allowed not to exist yet (the writers create them, like ``mkdir -p``);
    nothing is created here, so a run refused later leaves no empty folder behind. Refused: a file (not a folder)
    at ``path`` or at one of its parents, and a nearest existing folder that cannot be written.

    Raises:
        ValueError: one line naming the location and the reason, e.g. ``cannot write results to 'out/run':
            'out' is a file, not a folder``.
    """
    path = Path(path)
    _check_folder(path, path)
    return path


def _check_folder(folder: Path, target: Path) -> None:
    """``check_output_dir`` of ``folder``, naming ``target`` (the folder or a file in it) in messages."""
    path = target
    existing = folder
    while not existing.exists():
        if existing.is_symlink():  # a dangling link: writing through it would fail later
            raise ValueError(f"cannot write results to {str(path)!r}: {str(existing)!r} is a broken link")
        existing = existing.parent
    if not existing.is_dir():
        raise ValueError(f"cannot write results to {str(path)!r}: {str(existing)!r} is a file, not a folder")
    try:  # os.access ignores ACLs and read-only mounts; creating a file is the real test
        fd, probe = tempfile.mkstemp(dir=existing, prefix=".scg-jax-write-check.")
    except OSError as error:
        reason = error.strerror or type(error).__name__
        raise ValueError(
            f"cannot write results to {str(path)!r}: {str(existing)!r} is not writable ({reason})"
        ) from None
    os.close(fd)
    os.unlink(probe)


def check_output_file(path) -> Path:
    """``check_output_dir`` of the file's folder, and ``path`` itself is not a folder; returns ``path``."""
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"cannot write results to {str(path)!r}: it is a folder, expected a file name")
    _check_folder(path.parent, path)
    return path
