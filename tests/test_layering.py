"""The core's import structure: no cycles, nothing from the reproduction or data_gen,
one tet-topology table, no library file much over 600 lines."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

LIBRARY = Path(__file__).resolve().parents[1] / "torchmorph"
CORE = ("idw", "selection", "morph", "pod", "mesh", "quality", "io")


def imports_of(module: str) -> set[str]:
    """torchmorph modules (and top-level packages) imported by ``module``, anywhere in it."""
    tree = ast.parse((LIBRARY / f"{module}.py").read_text())
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            name = node.module or ""
            if node.level:
                found.update([name] if name else [alias.name for alias in node.names])
            elif name.startswith("torchmorph."):
                found.add(name.split(".")[1])
            else:
                found.add(name.split(".")[0])
        elif isinstance(node, ast.Import):
            found.update(alias.name.split(".")[0] for alias in node.names)
    return found


def library_graph() -> dict[str, set[str]]:
    modules = {path.stem for path in LIBRARY.glob("*.py")} - {"__init__"}
    return {module: imports_of(module) & modules for module in modules}


def test_core_never_imports_the_reproduction_or_data_gen():
    graph = library_graph()
    for module in CORE:
        reachable, frontier = set(), [module]
        while frontier:
            for dependency in graph[frontier.pop()] - reachable:
                reachable.add(dependency)
                frontier.append(dependency)
        assert "paper" not in reachable, module
        assert "data_gen" not in imports_of(module), module


def test_no_import_cycle_in_the_library():
    graph = library_graph()

    def visit(module: str, path: tuple[str, ...]) -> None:
        for dependency in graph[module]:
            assert dependency not in path, " -> ".join((*path, dependency))
            visit(dependency, (*path, dependency))

    for module in CORE:
        visit(module, (module,))


def test_one_tet_edge_table():
    table = "(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)"
    holders = [path.name for path in LIBRARY.glob("*.py") if table in path.read_text()]
    holders += [
        path.name
        for path in (LIBRARY.parent / "data_gen").glob("*.py")
        if table in path.read_text()
    ]
    assert [name for name in holders if name != "paper.py"] == ["_tet.py"]


@pytest.mark.parametrize(
    "module", sorted(str(path.relative_to(LIBRARY))[:-3] for path in LIBRARY.rglob("*.py"))
)
def test_library_files_stay_small(module):
    """About 600 lines at most (docstrings included), so that a module stays one concept."""
    lines = (LIBRARY / f"{module}.py").read_text().count("\n")
    assert lines <= 630, f"{module}.py has {lines} lines"
