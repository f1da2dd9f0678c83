"""Shared fixtures: small analytic tetrahedral meshes, one torch thread, and a temporary home.

The tests never write into the user's home: before anything is collected, ``HOME`` and
matplotlib's configuration point into one temporary directory (gmsh writes ``~/.fltk``
and ``~/.gmsh-options`` there), removed at the end of the session; the mesh cache
(``TORCHMORPH_CACHE``) and numba's cache live in the repository's ignored
``.cache/tests``, so that meshes and kernels are built once, not on every run.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import torch

# Without a CUDA device, Triton kernels run in Triton's interpreter (on the CPU). The
# switch must be set before triton is first imported: its own helpers (tl.sum, tl.max
# ...) are compiled or interpreted from then on.
if not torch.cuda.is_available():
    os.environ.setdefault("TRITON_INTERPRET", "1")

import pytest

from torchmorph import TetMesh
from torchmorph.mesh import box_mesh

#: Environment variables pointed into the session's temporary directory (name -> subfolder).
ISOLATED = {
    "HOME": "home",
    "MPLCONFIGDIR": "config/matplotlib",
    "XDG_CACHE_HOME": "cache",
    "XDG_CONFIG_HOME": "config",
}
#: Caches kept between sessions, in the repository's ignored ``.cache/tests`` (name ->
#: subfolder): generated meshes and numba's compiled kernels are built once, not per run.
PERSISTENT = {"TORCHMORPH_CACHE": "meshes", "NUMBA_CACHE_DIR": "numba"}
PERSISTENT_ROOT = Path(__file__).resolve().parents[1] / ".cache" / "tests"
_saved: dict[str, str | None] = {}
_root: Path | None = None
_paths: dict[str, Path] = {}


def pytest_configure(config):
    """Point home, caches and configuration into a temporary directory (before collection)."""
    global _root
    _root = Path(tempfile.mkdtemp(prefix="torchmorph-tests-"))
    _paths.update({name: _root / folder for name, folder in ISOLATED.items()})
    _paths.update({name: PERSISTENT_ROOT / folder for name, folder in PERSISTENT.items()})
    for name, path in _paths.items():
        _saved[name] = os.environ.get(name)
        path.mkdir(parents=True, exist_ok=True)
        os.environ[name] = str(path)


def pytest_unconfigure(config):
    for name, value in _saved.items():
        if value is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = value
    if _root is not None:
        shutil.rmtree(_root, ignore_errors=True)


@pytest.fixture(scope="session", autouse=True)
def temporary_home() -> Path:
    """The session's temporary directory holding HOME and the caches (see the module doc)."""
    assert _root is not None
    for name, path in _paths.items():
        assert os.environ[name] == str(path), f"{name} was changed during the session"
    return _root


def structured_cube(cells: int = 4, size: float = 1.0) -> TetMesh:
    """The cube [0, size]^3 as cells^3 Kuhn-split hexahedra; faces x0 … z1 as node sets."""
    return box_mesh(cells, size)


@pytest.fixture
def cube() -> TetMesh:
    return structured_cube(4)


@pytest.fixture
def one_thread():
    """Run the test with one torch thread, restoring the count after it.

    The small meshes gain nothing from threads, and a shared CPU makes them much slower.
    """
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def write_cad(path: Path, build=None) -> Path:
    """Write the OpenCASCADE model made by ``build(occ)`` to a CAD file with gmsh.

    The format follows the extension: ``.step``, ``.iges`` (faces only), ``.brep``.

    The default model is a box [-1, 1]^2 x [-0.5, 0.5] with a cylindrical hole of
    radius 0.4 along z: 7 CAD faces.
    """
    import gmsh

    def holed_box(occ):
        box = occ.addBox(-1, -1, -0.5, 2, 2, 1)
        occ.cut([(3, box)], [(3, occ.addCylinder(0, 0, -0.5, 0, 0, 1, 0.4))])

    gmsh.initialize(readConfigFiles=False, interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("cad")
        (build or holed_box)(gmsh.model.occ)
        gmsh.model.occ.synchronize()
        gmsh.write(str(path))
    finally:
        gmsh.finalize()
    return path
