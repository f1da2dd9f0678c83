"""The tetrahedron's topology and the geometry kernels every module shares.

One table of the six edges and one of the four faces (outward for a positively
oriented tetrahedron), used by :mod:`torchmorph.mesh`, :mod:`torchmorph.mesh.quality`
and the mesh builders in ``data_gen``; and the raw per-tetrahedron kernels (no
argument checks) over ``points (..., N, 3)`` and ``tets (M, 4)``.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["TET_EDGES", "TET_OUTWARD_FACES", "tet_edge_lengths_squared", "tet_volumes"]

#: The six edges of a tetrahedron as pairs of local vertex numbers.
TET_EDGES: tuple[tuple[int, int], ...] = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))

#: The four faces, face k opposite vertex k, oriented outward when the tetrahedron's
#: signed volume is positive.
TET_OUTWARD_FACES: tuple[tuple[int, int, int], ...] = ((1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1))


def tet_vertices(points: Tensor, tets: Tensor) -> Tensor:
    """Vertex coordinates of every tetrahedron; points (..., N, 3) -> (..., M, 4, 3)."""
    gathered = points.index_select(-2, tets.reshape(-1))
    return gathered.unflatten(-2, (tets.shape[0], 4))


def tet_volumes(points: Tensor, tets: Tensor) -> Tensor:
    """Signed volumes without argument checks; points (..., N, 3) -> (..., M)."""
    vertices = tet_vertices(points, tets)
    edges = vertices[..., 1:, :] - vertices[..., :1, :]
    normal = torch.linalg.cross(edges[..., 0, :], edges[..., 1, :], dim=-1)
    return (normal * edges[..., 2, :]).sum(-1) / 6.0


def tet_edge_lengths_squared(points: Tensor, tets: Tensor) -> Tensor:
    """Squared lengths of the six edges (order of TET_EDGES); (..., N, 3) -> (..., M, 6)."""
    vertices = tet_vertices(points, tets)
    vectors = torch.stack([vertices[..., j, :] - vertices[..., i, :] for i, j in TET_EDGES], -2)
    return (vectors * vectors).sum(-1)
