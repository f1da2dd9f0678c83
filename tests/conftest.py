"""Shared fixtures: small analytic tetrahedral meshes."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchmorph import TetMesh


def structured_cube(cells: int = 4, size: float = 1.0) -> TetMesh:
    """A cube [0, size]^3 split into cells^3 hexahedra of 6 tets each.

    Node sets: the six faces ("x0", "x1", "y0", "y1", "z0", "z1").
    """
    ticks = np.linspace(0.0, size, cells + 1)
    x, y, z = np.meshgrid(ticks, ticks, ticks, indexing="ij")
    points = np.stack([x.ravel(), y.ravel(), z.ravel()], 1)
    index = np.arange((cells + 1) ** 3).reshape(cells + 1, cells + 1, cells + 1)
    corners = [index[i : cells + i, j : cells + j, k : cells + k].ravel()
               for i in (0, 1) for j in (0, 1) for k in (0, 1)]
    c000, c001, c010, c011, c100, c101, c110, c111 = corners
    # Kuhn (Freudenthal) split of each cube along its main diagonal c000-c111
    tets = np.concatenate([
        np.stack(t, 1) for t in (
            (c000, c100, c110, c111), (c000, c100, c101, c111), (c000, c010, c110, c111),
            (c000, c010, c011, c111), (c000, c001, c101, c111), (c000, c001, c011, c111),
        )
    ])
    sets = {}
    for axis, name in enumerate("xyz"):
        sets[f"{name}0"] = np.nonzero(points[:, axis] == 0.0)[0]
        sets[f"{name}1"] = np.nonzero(points[:, axis] == size)[0]
    return TetMesh(torch.from_numpy(points), torch.from_numpy(tets), sets, name="cube")


@pytest.fixture
def cube() -> TetMesh:
    return structured_cube(4)
