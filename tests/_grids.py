"""A Kuhn-split grid cube built independently of ``torchmorph.mesh.box_mesh``, for tests of
the library's mesh code (tests/mesh/test_mesh.py, tests/mesh/test_quality.py,
tests/mesh/test_io.py)."""

from __future__ import annotations

import itertools

import numpy as np


def kuhn_grid(n: int, size: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Cube [0, size]^3 in n^3 cells, each split into the 6 Kuhn tetrahedra.

    Half of the tetrahedra come out negatively oriented (odd permutations).
    """
    axis = np.linspace(0.0, size, n + 1)
    x, y, z = np.meshgrid(axis, axis, axis, indexing="ij")
    points = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    index = np.arange((n + 1) ** 3).reshape(n + 1, n + 1, n + 1)
    i, j, k = (a.ravel() for a in np.meshgrid(*[np.arange(n)] * 3, indexing="ij"))
    blocks = []
    for order in itertools.permutations(range(3)):
        corner = [0, 0, 0]
        path = [index[i, j, k]]
        for axis_number in order:
            corner[axis_number] = 1
            path.append(index[i + corner[0], j + corner[1], k + corner[2]])
        blocks.append(np.stack(path, axis=1))
    return points, np.concatenate(blocks)
