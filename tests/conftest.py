"""Shared fixtures: small analytic tetrahedral meshes, and one torch thread."""

from __future__ import annotations

import os

import torch

# Without a CUDA device, Triton kernels run in Triton's interpreter (on the CPU). The
# switch must be set before triton is first imported: its own helpers (tl.sum, tl.max
# ...) are compiled or interpreted from then on.
if not torch.cuda.is_available():
    os.environ.setdefault("TRITON_INTERPRET", "1")

import pytest  # noqa: E402

from torchmorph import TetMesh  # noqa: E402
from torchmorph.mesh import box_mesh  # noqa: E402


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
