"""Raw geometry kernels over the element kinds of :mod:`torchmorph.mesh.cells` (no
argument checks): simplex volumes, corner Jacobians and edge lengths, over
``points (..., N, D)`` and a block of cells ``nodes (M, n)``; batched over leading
dimensions of ``points`` and differentiable with respect to them."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchmorph.mesh.cells import TET_EDGES, CellKind

__all__ = [
    "corner_determinants",
    "edge_lengths_squared",
    "simplex_volumes",
    "tet_edge_lengths_squared",
    "tet_volumes",
]


def _gather(points: Tensor, nodes: Tensor) -> Tensor:
    """Coordinates of every node of every cell; points (..., N, D) -> (..., M, n, D)."""
    gathered = points.index_select(-2, nodes.reshape(-1))
    return gathered.unflatten(-2, tuple(nodes.shape))


def _determinant(vectors: Tensor) -> Tensor:
    """det of the D vectors in (..., D, D) (rows), for D = 2 or 3, without LU."""
    if vectors.shape[-1] == 2:
        return vectors[..., 0, 0] * vectors[..., 1, 1] - vectors[..., 0, 1] * vectors[..., 1, 0]
    cross = torch.linalg.cross(vectors[..., 1, :], vectors[..., 2, :], dim=-1)
    return (vectors[..., 0, :] * cross).sum(-1)


def simplex_volumes(points: Tensor, simplices: Tensor) -> Tensor:
    """Signed volumes (areas in 2-D) of simplices (S, D + 1); (..., N, D) -> (..., S)."""
    vertices = _gather(points, simplices)
    edges = vertices[..., 1:, :] - vertices[..., :1, :]
    return _determinant(edges) / math.factorial(points.shape[-1])


def tet_volumes(points: Tensor, tets: Tensor) -> Tensor:
    """Signed volumes of tetrahedra (M, 4); points (..., N, 3) -> (..., M)."""
    return simplex_volumes(points, tets)


def corner_determinants(points: Tensor, nodes: Tensor, kind: CellKind) -> Tensor:
    """det of the edge vectors of every corner frame of :attr:`CellKind.corner_frames`;
    (..., N, D) and a block (M, n) -> (..., M, corners)."""
    frames = torch.tensor(kind.corner_frames, device=nodes.device)
    vertices = _gather(points, nodes[:, frames.reshape(-1)]).unflatten(-2, tuple(frames.shape))
    return _determinant(vertices[..., 1:, :] - vertices[..., :1, :])


def scaled_corner_jacobians(points: Tensor, nodes: Tensor, kind: CellKind) -> Tensor:
    """Knupp's scaled Jacobian at every corner: the corner determinant divided by the
    lengths of its edges, times :attr:`CellKind.jacobian_scale` (1 for the ideal
    element); (..., M, corners)."""
    frames = torch.tensor(kind.corner_frames, device=nodes.device)
    vertices = _gather(points, nodes[:, frames.reshape(-1)]).unflatten(-2, tuple(frames.shape))
    vectors = vertices[..., 1:, :] - vertices[..., :1, :]
    lengths = torch.linalg.vector_norm(vectors, dim=-1).prod(-1)
    tiny = torch.finfo(points.dtype).tiny
    return kind.jacobian_scale * _determinant(vectors) / lengths.clamp_min(tiny)


def edge_lengths_squared(points: Tensor, nodes: Tensor, kind: CellKind) -> Tensor:
    """Squared lengths of the corner edges of every cell; (..., M, edges)."""
    edges = torch.tensor(kind.edges, device=nodes.device)
    vertices = _gather(points, nodes[:, edges.reshape(-1)]).unflatten(-2, tuple(edges.shape))
    vectors = vertices[..., 1, :] - vertices[..., 0, :]
    return (vectors * vectors).sum(-1)


def tet_edge_lengths_squared(points: Tensor, tets: Tensor) -> Tensor:
    """Squared lengths of the six edges (order of TET_EDGES); (..., N, 3) -> (..., M, 6)."""
    edges = torch.tensor(TET_EDGES, device=tets.device)
    vertices = _gather(points, tets[:, edges.reshape(-1)]).unflatten(-2, tuple(edges.shape))
    vectors = vertices[..., 1, :] - vertices[..., 0, :]
    return (vectors * vectors).sum(-1)
