"""The layers point down: the CLI imports the algorithms, which import the environments, never the reverse."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ABOVE_ENV = {"scg_algorithms", "scg_cli", "algorithms", "cli"}


def _imported_modules(path: Path) -> set[str]:
    """Top-level names of every module ``path`` imports, lazily inside functions included."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names


def test_env_package_imports_nothing_above_it():
    offenders = {
        str(path.relative_to(ROOT)): sorted(_imported_modules(path) & ABOVE_ENV)
        for path in sorted((ROOT / "scg_jax").rglob("*.py"))
        if _imported_modules(path) & ABOVE_ENV
    }
    assert offenders == {}


def test_algorithms_do_not_import_the_cli():
    offenders = [
        str(path.relative_to(ROOT))
        for path in sorted((ROOT / "algorithms").rglob("*.py"))
        if _imported_modules(path) & {"scg_cli", "cli"}
    ]
    assert offenders == []


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
