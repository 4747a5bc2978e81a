"""The layers point down: the CLI imports the algorithms, which import the environments, never the reverse."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# Each layer's folder and the packages it must not import: cli -> experiments -> algorithms -> scg_jax.
LAYERS = {
    "scg_jax": {"scg_algorithms", "scg_experiments", "scg_cli", "algorithms", "experiments", "cli"},
    "algorithms": {"scg_experiments", "scg_cli", "experiments", "cli"},
    "experiments": {"scg_cli", "cli"},
}
TERMINAL_UI = {"rich"}  # only the command line draws


def _imported_modules(path: Path) -> set[str]:
    """Top-level names of every module ``path`` imports, lazily inside functions included."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names


def _offenders(folder: str, forbidden: set[str]) -> dict[str, list[str]]:
    found = {str(path.relative_to(ROOT)): sorted(_imported_modules(path) & forbidden)
             for path in sorted((ROOT / folder).rglob("*.py"))}  # fmt: skip
    return {path: names for path, names in found.items() if names}


@pytest.mark.parametrize("folder", LAYERS)
def test_each_layer_imports_nothing_above_it(folder):
    assert _offenders(folder, LAYERS[folder]) == {}


@pytest.mark.parametrize("folder", LAYERS)
def test_only_the_command_line_imports_a_terminal_ui(folder):
    assert _offenders(folder, TERMINAL_UI) == {}


def test_the_layer_checks_see_the_imports_they_forbid(tmp_path):
    """The AST scan finds top-level, aliased, dotted and function-local imports (a check that sees nothing passes)."""
    source = tmp_path / "sample.py"
    source.write_text("import rich.console as c\nfrom scg_cli.train import x\ndef f():\n    import scg_experiments\n")
    assert _imported_modules(source) == {"rich", "scg_cli", "scg_experiments"}
    assert _offenders("cli", TERMINAL_UI)  # the CLI does draw with rich


def test_importing_the_library_loads_no_terminal_ui_and_nothing_above():
    code = (
        "import sys, scg_jax, scg_algorithms, scg_experiments, scg_algorithms.runs, scg_algorithms.evaluation; "
        "print(sorted(m for m in sys.modules if m.split('.')[0] in {'rich', 'scg_cli'}))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    assert out.stdout.strip() == "[]"


def test_importing_the_env_package_loads_no_algorithm():
    code = (
        "import sys, scg_jax; print(sorted(m for m in sys.modules if m.split('.')[0] in {'scg_algorithms', 'scg_cli'}))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    assert out.stdout.strip() == "[]"


def test_every_package_folder_is_installed_under_its_import_name():
    """pyproject lists every folder with an ``__init__.py`` (algorithms/ as scg_algorithms, cli/ as scg_cli)."""
    import tomllib

    setuptools = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    import_name = {folder: name for name, folder in setuptools["package-dir"].items()}
    folders = sorted(p.parent.relative_to(ROOT) for top in ("scg_jax", "algorithms", "cli", "experiments")
                     for p in (ROOT / top).rglob("__init__.py"))  # fmt: skip
    expected = sorted(".".join([import_name.get(f.parts[0], f.parts[0]), *f.parts[1:]]) for f in folders)
    assert sorted(setuptools["packages"]) == expected
    import scg_algorithms
    import scg_cli

    assert Path(scg_algorithms.__file__).parent == ROOT / "algorithms"
    assert Path(scg_cli.__file__).parent == ROOT / "cli"
