"""Every code block of the README and of ``docs/*.md`` runs as written, in order, as one tutorial per file.

Python blocks of one file share a namespace, so a later block may use what an earlier one defined, as a reader
would in one session. Bash blocks run line by line when a line is an ``scg-jax`` command (other shell lines,
such as the README's set-up commands that CI itself runs, are not repeated here). Blocks run in a temporary
folder holding a link to ``configs/``, so relative paths in the examples work and outputs stay out of the
checkout.

Markers, on the first line of a block:
- ``# not run: REASON`` — never run here (an optional extra that the test install does not have); the reason
  is required, so a skipped block always says why.
- ``# slow`` — run only when the slow tests are selected (a block that trains for a while); ``-m "not slow"``
  skips it.
"""

from __future__ import annotations

import os
import re
import shlex
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOC_FILES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
FENCE = re.compile(r"^```(\w+)[^\n]*\n(.*?)^```", re.MULTILINE | re.DOTALL)


def code_blocks(path: Path) -> list[tuple[str, str, int]]:
    """``(language, code, first line number)`` of every fenced block in ``path``."""
    text = path.read_text()
    return [(m.group(1), m.group(2), text.count("\n", 0, m.start()) + 2) for m in FENCE.finditer(text)]


def _marker(code: str) -> str | None:
    first = code.lstrip().splitlines()[0] if code.strip() else ""
    if first.startswith("# not run"):
        if not first.startswith("# not run:") or not first.split(":", 1)[1].strip():
            raise AssertionError(f"a '# not run' marker needs a reason: {first!r}")
        return "not run"
    if first.strip() == "# slow":
        return "slow"
    return None


def _run_cli_line(line: str) -> None:
    from scg_cli import main

    argv = shlex.split(line)
    assert argv[0] == "scg-jax"
    status = main(argv[1:])
    assert status == 0, f"{line!r} exited with {status}"


def _run_file(path: Path, tmp_path: Path, monkeypatch, slow: bool) -> int:
    (tmp_path / "configs").symlink_to(ROOT / "configs")
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": f"doc_{path.stem}"}
    ran = 0
    for language, code, line in code_blocks(path):
        marker = _marker(code)
        if marker == "not run" or (marker == "slow" and not slow):
            continue
        where = f"{path.relative_to(ROOT)}:{line}"
        if language == "python":
            exec(compile(code, where, "exec"), namespace)
            ran += 1
        elif language == "bash":
            for command in code.splitlines():
                command = command.split(" #", 1)[0].strip()
                if command.startswith("scg-jax "):
                    _run_cli_line(command)
                    ran += 1
    return ran


def _doc_id(path: Path) -> str:
    return str(path.relative_to(ROOT))


def _slow_selected(config) -> bool:
    """Whether this run includes the ``slow`` tests (CI does; ``-m "not slow"`` leaves them out)."""
    return "not slow" not in (config.getoption("markexpr") or "")


@pytest.mark.parametrize("path", DOC_FILES, ids=_doc_id)
def test_doc_examples_run(path, tmp_path, monkeypatch, request):
    """Every block not marked ``# not run`` runs without error; ``# slow`` blocks only when slow tests are selected.

    One test per file runs the whole tutorial once: a separate slow variant would run the fast blocks twice.
    """
    monkeypatch.setattr(sys, "argv", ["doc-example"])
    os.environ.setdefault("MPLBACKEND", "Agg")
    _run_file(path, tmp_path, monkeypatch, slow=_slow_selected(request.config))


def test_every_doc_has_examples_and_markers_have_reasons():
    """Each reference page carries runnable examples, and every skip marker says why (checked by ``_marker``)."""
    for path in DOC_FILES:
        blocks = code_blocks(path)
        for _, code, _ in blocks:
            _marker(code)
        if path.parent.name == "docs":
            assert any(lang in ("python", "bash") for lang, _, _ in blocks), f"{path.name} has no example"
