"""Shared fixtures: small analytic tetrahedral meshes."""

from __future__ import annotations

import pytest

from torchmorph import TetMesh
from torchmorph.mesh import box_mesh


def structured_cube(cells: int = 4, size: float = 1.0) -> TetMesh:
    """The cube [0, size]^3 as cells^3 Kuhn-split hexahedra; faces x0 … z1 as node sets."""
    return box_mesh(cells, size)


@pytest.fixture
def cube() -> TetMesh:
    return structured_cube(4)
