"""No import cycles between the modules of a package.

Imports inside functions count too: a lazy import hides a cycle from the interpreter, it does not remove it (the two
modules still need each other). Each package's import graph is read from the source with ``ast`` and must be
acyclic (no strongly connected component of more than one module).
"""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = {"scg_jax": "scg_jax", "scg_algorithms": "algorithms", "scg_cli": "cli", "scg_experiments": "experiments"}


def _modules(package: str, folder: str) -> dict[str, Path]:
    modules = {}
    for path in sorted((ROOT / folder).rglob("*.py")):
        parts = [package, *path.relative_to(ROOT / folder).with_suffix("").parts]
        if parts[-1] == "__init__":
            parts.pop()
        modules[".".join(parts)] = path
    return modules


def _imported(node, module: str, is_package: bool, modules) -> list[str]:
    """The modules of ``modules`` an import statement in ``module`` loads: ``from pkg import sub`` loads the submodule
    ``pkg.sub``, ``from pkg.mod import name`` loads ``pkg.mod``, ``import pkg.mod`` loads ``pkg.mod``."""
    if isinstance(node, ast.Import):
        names = [alias.name for alias in node.names]
    elif isinstance(node, ast.ImportFrom):
        base = node.module or ""
        if node.level:  # relative: from the package of ``module``
            anchor = module if is_package else module.rpartition(".")[0]
            for _ in range(node.level - 1):
                anchor = anchor.rpartition(".")[0]
            base = f"{anchor}.{base}" if base else anchor
        names = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else base for alias in node.names]
    else:
        return []
    found = []
    for name in names:
        while name not in modules and "." in name:
            name = name.rpartition(".")[0]
        if name in modules:
            found.append(name)
    return found


def import_graph(package: str, folder: str) -> dict[str, set[str]]:
    """``{module: modules of the same package it imports}``, counting imports anywhere in the module."""
    modules = _modules(package, folder)
    graph = {name: set() for name in modules}
    for name, path in modules.items():
        for node in ast.walk(ast.parse(path.read_text())):
            graph[name].update(_imported(node, name, path.name == "__init__.py", modules))
        graph[name].discard(name)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one node (Tarjan's algorithm, iterative)."""
    index, low, on_stack, stack, found = {}, {}, set(), [], []
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def test_the_cycle_finder_finds_a_cycle_and_only_cycles():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": {"d", "f"}, "f": {"e"}, "g": set()}
    assert sorted(cycles(graph)) == [["a", "b", "c"], ["e", "f"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_the_graph_counts_imports_inside_functions():
    graph = import_graph("scg_jax", "scg_jax")
    assert "scg_jax.symbolic" in graph["scg_jax.env"]  # imported inside Env.symbolic_model
    assert "scg_jax.validation" in graph["scg_jax.config"]  # ``from scg_jax import validation as V``


@pytest.mark.parametrize("package", PACKAGES)
def test_no_import_cycles_within_the_package(package):
    assert cycles(import_graph(package, PACKAGES[package])) == []
