"""Every code block of the README and of ``docs/*.md`` runs as a reader would run it.

Python blocks run one by one, each in a fresh namespace: a reader copies one block, so each imports and builds what
it uses (``test_every_python_block_names_only_what_it_defines`` checks this for the blocks not run here too).

Bash blocks run line by line in a model of the reader's shell (``_Shell``), in the page's order: the working folder
and ``PATH`` carry from line to line and block to block. The README starts in a fresh shell, without the virtual
environment on ``PATH``; each page of ``docs/`` starts in the shell the README leaves (its set-up line activated the
environment). Every program must be found in that state, as bash would find it (``scg-jax`` alone only after
``source .venv/bin/activate``), or the test fails with bash's ``command not found``. ``python3 -m venv .venv``
links ``.venv`` to the environment running the tests, where CI installed the package, so ``.venv/bin/scg-jax`` is the
installed entry point. An ``scg-jax`` line runs through that entry point's function, ``scg_cli.main``, in this
process (it must exit 0); ``scg-jax reproduce`` runs with the reproduction itself replaced by a recorder
(``tests/test_experiments.py`` runs it at the tiny profile; the main job trains for minutes). Other programs are
found but not run: the installation, lint and test commands are what CI itself runs (``.ci/run``), and the benchmark
scripts are long measurements.

Blocks run in a temporary folder holding a link to ``configs/``, so relative paths in the examples work. A page's
examples may write only under ``results/`` (ignored by git), or in a temporary folder they make: nothing else is
left in the folder where the reader ran them.

Markers, on the first line of a block:
- ``# not run: REASON`` — never run here (an optional extra that the test install does not have); the reason
  is required, so a skipped block always says why.
- ``# slow`` — run only when the slow tests are selected (a block that trains for a while); ``-m "not slow"``
  skips it.
"""

from __future__ import annotations

import ast
import builtins
import os
import re
import shlex
import shutil
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOC_FILES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
FENCE = re.compile(r"^```(\w+)[^\n]*\n(.*?)^```", re.MULTILINE | re.DOTALL)
VENV = Path(sys.prefix)
# What a page's examples may leave in the folder they ran in: the link to configs/, the environment the README's
# set-up line made, and results/ (ignored by git).
ALLOWED_OUTPUTS = {"configs", ".venv", "results"}


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


class _Shell:
    """The reader's bash while following one page: the working folder (``cwd``) and ``PATH`` (module docstring)."""

    def __init__(self, cwd: Path, activated: bool, monkeypatch):
        self.cwd, self.monkeypatch = cwd, monkeypatch
        # A fresh shell: whatever environment the tests run in is not on the reader's PATH.
        self.path = [p for p in os.environ.get("PATH", "").split(os.pathsep) if p and not _inside(Path(p), VENV)]
        if activated:
            self.run_line("python3 -m venv .venv && source .venv/bin/activate", "the README's set-up")

    def run_line(self, line: str, where: str) -> int:
        """Run the commands of one line (``a && b``); returns how many ``scg-jax`` commands ran."""
        ran = 0
        for command in line.split("&&"):
            words = shlex.split(command, comments=True)
            while words and re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*=.*", words[0]):
                words = words[1:]  # VAR=value before a command: the variable is for that command alone
            if words:
                ran += self._run(words, f"{where}: {command.strip()}")
        return ran

    def _run(self, words: list[str], where: str) -> int:
        program, args = words[0], words[1:]
        if program in ("source", ".") and args == [".venv/bin/activate"]:
            activate = self.cwd / ".venv" / "bin" / "activate"
            assert activate.is_file(), f"{where}: bash: .venv/bin/activate: No such file or directory"
            self.path.insert(0, str(self.cwd / ".venv" / "bin"))
            return 0
        found = self._which(program)
        assert found is not None, f"{where}: bash: {program}: command not found"
        if Path(program).name == "python3" and args[:2] == ["-m", "venv"]:
            target = self.cwd / args[2]
            assert sys.prefix != sys.base_prefix, "the docs' shell needs the tests to run in a virtual environment"
            if not target.exists():
                target.symlink_to(VENV, target_is_directory=True)  # the environment CI installed the package into
            return 0
        if Path(program).name == "scg-jax":
            assert found.resolve() == (VENV / "bin" / "scg-jax").resolve(), f"{where}: {found} is another scg-jax"
            self._scg_jax(args, where)
            return 1
        return 0  # installation, lint, tests, benchmarks: found, not run here (module docstring)

    def _which(self, program: str) -> Path | None:
        if "/" in program:
            path = self.cwd / program
            return path if path.is_file() and os.access(path, os.X_OK) else None
        found = shutil.which(program, path=os.pathsep.join(self.path))
        return None if found is None else Path(found)

    def _scg_jax(self, args: list[str], where: str) -> None:
        import scg_experiments
        from scg_cli import main

        calls = []
        if args[:1] == ["reproduce"]:
            self.monkeypatch.setattr(scg_experiments, "reproduce", lambda *a, **k: calls.append(a))
        status = main(args)
        assert status == 0, f"{where} exited with {status}"
        assert len(calls) == (args[:1] == ["reproduce"]), f"{where}: the reproduction was not reached"


def _inside(path: Path, folder: Path) -> bool:
    try:
        path.resolve().relative_to(folder.resolve())
    except ValueError:
        return False
    return True


def _run_file(path: Path, tmp_path: Path, monkeypatch, slow: bool) -> int:
    (tmp_path / "configs").symlink_to(ROOT / "configs")
    monkeypatch.chdir(tmp_path)
    shell = _Shell(tmp_path, activated=path.name != "README.md", monkeypatch=monkeypatch)
    ran = 0
    for language, code, line in code_blocks(path):
        marker = _marker(code)
        if marker == "not run" or (marker == "slow" and not slow):
            continue
        where = f"{path.relative_to(ROOT)}:{line}"
        if language == "python":
            exec(compile(code, where, "exec"), {"__name__": f"doc_{path.stem}_{line}"})
            ran += 1
        elif language == "bash":
            for offset, command in enumerate(code.splitlines()):
                ran += shell.run_line(command, f"{path.relative_to(ROOT)}:{line + offset}")
    left = sorted(p.name for p in tmp_path.iterdir() if p.name not in ALLOWED_OUTPUTS)
    assert not left, f"{path.name}'s examples left {left} in the folder they ran in; write under results/"
    return ran


def _doc_id(path: Path) -> str:
    return str(path.relative_to(ROOT))


def _slow_selected(config) -> bool:
    """Whether this run includes the ``slow`` tests (CI does; ``-m "not slow"`` leaves them out)."""
    return "not slow" not in (config.getoption("markexpr") or "")


@pytest.mark.parametrize("path", DOC_FILES, ids=_doc_id)
def test_doc_examples_run(path, tmp_path, monkeypatch, request):
    """Every block not marked ``# not run`` runs without error; ``# slow`` blocks only when slow tests are selected.

    One test per file runs the whole page once: a separate slow variant would run the fast blocks twice.
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


def _free_names(code: str) -> set[str]:
    """Names a block reads that it neither imports, defines nor gets from the builtins: a NameError when it runs
    alone (a static check, so it covers the blocks marked ``# not run`` and ``# slow`` too)."""
    tree = ast.parse(code)
    defined, loaded = set(dir(builtins)), set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import | ast.ImportFrom):
            defined.update((alias.asname or alias.name).split(".")[0] for alias in node.names)
        elif isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            defined.add(node.name)
        elif isinstance(node, ast.arg):
            defined.add(node.arg)
        elif isinstance(node, ast.ExceptHandler) and node.name:
            defined.add(node.name)
        elif isinstance(node, ast.Name):
            (loaded if isinstance(node.ctx, ast.Load) else defined).add(node.id)
    return loaded - defined


def test_every_python_block_names_only_what_it_defines():
    """A reader copies one block: each Python block imports and builds everything it uses."""
    assert _free_names("import jax\nx = jax.numpy.ones(2)\nprint(x, y)\n") == {"y"}  # the check itself
    missing = [
        f"{path.relative_to(ROOT)}:{line}: {', '.join(sorted(free))}"
        for path in DOC_FILES
        for language, code, line in code_blocks(path)
        if language == "python" and (free := _free_names(code))
    ]
    assert not missing, "blocks that use names an earlier block defined:\n" + "\n".join(missing)
