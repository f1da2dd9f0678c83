"""The package's import structure: no cycle anywhere, the morphing core free of the
reproduction, the CLI and data_gen, IDW self-contained, one tet-topology table, no
library file much over 600 lines."""

from __future__ import annotations

import ast
from functools import cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LIBRARY = ROOT / "torchmorph"

#: The morphing core: the method of the paper and the meshes it works on.
CORE = (
    "torchmorph.idw",
    "torchmorph.ffd",
    "torchmorph.rbf",
    "torchmorph.selection",
    "torchmorph.morph",
    "torchmorph._morph_state",
    "torchmorph._morph_methods",
    "torchmorph.large_motions",
    "torchmorph.pod",
    "torchmorph.mesh",
)
#: What the core never reaches.
ABOVE_THE_CORE = (
    "torchmorph.paper",
    "torchmorph.cli",
    "torchmorph.meshing",
    "torchmorph.distributed",
    "data_gen",
)
#: The only library modules that may import data_gen (the paper's reproduction).
MAY_USE_DATA_GEN = ("torchmorph.paper",)
#: Shared helpers every subpackage may use.
SHARED = (
    "torchmorph._checks",
    "torchmorph._state",
    "torchmorph._atomic",
    "torchmorph._timing",
    "torchmorph._memory",
    "torchmorph._dense",
    "torchmorph._threads",
    "torchmorph._kernel_rows",
    "torchmorph._treecode",
    "torchmorph._treecode_jit",
)


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


@cache
def modules() -> dict[str, Path]:
    found = {module_name(path): path for path in LIBRARY.rglob("*.py")}
    found.update({module_name(path): path for path in (ROOT / "data_gen").rglob("*.py")})
    return found


def resolve(name: str) -> str | None:
    """The project module ``name`` denotes (a package denotes its ``__init__``)."""
    return name if name in modules() else None


@cache
def imports_of(module: str) -> frozenset[str]:
    """Project modules imported by ``module`` anywhere in it (lazy imports included);
    ``from package import name`` is an import of the submodule where ``name`` is one."""
    path = modules()[module]
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(parent + ([base] if base else []))
            for alias in node.names:
                target = resolve(f"{base}.{alias.name}") or resolve(base)
                if target:
                    found.add(target)
        elif isinstance(node, ast.Import):
            for alias in node.names:
                parts = alias.name.split(".")
                for end in range(len(parts), 0, -1):
                    target = resolve(".".join(parts[:end]))
                    if target:
                        found.add(target)
                        break
    found.discard(module)
    return frozenset(found)


def reachable(module: str) -> set[str]:
    seen, frontier = set(), [module]
    while frontier:
        for dependency in imports_of(frontier.pop()) - seen:
            seen.add(dependency)
            frontier.append(dependency)
    return seen


def inside(module: str, prefix: str) -> bool:
    return module == prefix or module.startswith(prefix + ".")


def test_the_graph_is_read():
    # a sanity check of the reader itself: known arrows are found
    assert "torchmorph.idw.module" in imports_of("torchmorph.morph")
    assert "torchmorph.mesh.model" in imports_of("torchmorph.mesh.quality")
    assert "torchmorph.cli.info" in imports_of("torchmorph.cli.main")


def test_no_import_cycle_anywhere():
    graph = {module: imports_of(module) for module in modules()}
    state: dict[str, int] = {}

    def visit(module: str, path: tuple[str, ...]) -> None:
        state[module] = 1
        for dependency in sorted(graph[module]):
            if state.get(dependency) == 1:
                cycle = path[path.index(dependency) :] + (dependency,)
                pytest.fail("import cycle: " + " -> ".join(cycle))
            if dependency not in state:
                visit(dependency, (*path, dependency))
        state[module] = 2

    for module in sorted(graph):
        if module not in state:
            visit(module, (module,))


@pytest.mark.parametrize("core", CORE)
def test_the_core_reaches_nothing_above_it(core):
    for module in [m for m in modules() if inside(m, core)]:
        for other in reachable(module):
            assert not any(inside(other, above) for above in ABOVE_THE_CORE), (module, other)


def test_only_the_reproduction_imports_data_gen():
    for module in modules():
        if not module.startswith("torchmorph") or any(inside(module, m) for m in MAY_USE_DATA_GEN):
            continue
        assert not any(inside(m, "data_gen") for m in imports_of(module)), module


def test_data_gen_imports_only_public_names():
    for module in [m for m in modules() if inside(m, "data_gen")]:
        for other in imports_of(module):
            if other.startswith("torchmorph"):
                assert not any(part.startswith("_") for part in other.split(".")), (module, other)


def test_idw_stays_inside_idw():
    for module in [m for m in modules() if inside(m, "torchmorph.idw")]:
        for other in imports_of(module):
            assert inside(other, "torchmorph.idw") or other in SHARED, (module, other)


def test_ffd_stays_inside_ffd():
    for module in [m for m in modules() if inside(m, "torchmorph.ffd")]:
        for other in imports_of(module):
            assert inside(other, "torchmorph.ffd") or other in SHARED, (module, other)


def test_rbf_stays_inside_rbf():
    for module in [m for m in modules() if inside(m, "torchmorph.rbf")]:
        for other in imports_of(module):
            assert inside(other, "torchmorph.rbf") or other in SHARED, (module, other)


def test_one_tet_edge_table():
    table = "(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)"
    holders = [
        str(path.relative_to(ROOT))
        for path in [*LIBRARY.rglob("*.py"), *(ROOT / "data_gen").rglob("*.py")]
        if table in path.read_text()
    ]
    assert holders == ["torchmorph/mesh/cells.py"]


@pytest.mark.parametrize(
    "module", sorted(str(p.relative_to(LIBRARY)) for p in LIBRARY.rglob("*.py"))
)
def test_library_files_stay_small(module):
    """About 600 lines at most (docstrings included), so that a module stays one concept."""
    lines = (LIBRARY / module).read_text().count("\n")
    assert lines <= 630, f"{module} has {lines} lines"
