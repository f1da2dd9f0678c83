"""Tetrahedra of fTetWild's output: orientation, and boundary nodes moved onto the input
surfaces without inverting a tetrahedron (:func:`torchmorph.meshing.mesh_surfaces`)."""

from __future__ import annotations

import numpy as np

__all__ = ["boundary_nodes", "edge_lengths_at_nodes", "orient", "signed_volumes", "snap"]


def orient(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Tets with the last two vertices swapped where the signed volume is negative."""
    tets = np.array(tets, dtype=np.int64, copy=True)
    flip = signed_volumes(points, tets) < 0
    tets[flip, 2], tets[flip, 3] = tets[flip, 3].copy(), tets[flip, 2].copy()
    return tets


def signed_volumes(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    a, b, c, d = (points[tets[:, k]] for k in range(4))
    return np.einsum("ij,ij->i", b - a, np.cross(c - a, d - a)) / 6.0


def snap(points, tets, nodes, targets, *, sweeps: int = 30):
    """Move ``nodes`` to ``targets``, backing moves off where a tetrahedron would invert.

    Returns the moved points and the number of nodes not moved all the way.
    """
    original = points[nodes].copy()
    fraction = np.ones(len(nodes))
    position = np.full(len(points), -1)
    position[nodes] = np.arange(len(nodes))
    longest = np.sqrt(
        np.max(
            [
                np.sum((points[tets[:, i]] - points[tets[:, j]]) ** 2, axis=1)
                for i in range(4)
                for j in range(i + 1, 4)
            ],
            axis=0,
        )
    )
    minimum = 1e-8 * longest**3
    for _ in range(sweeps):
        points[nodes] = original + fraction[:, None] * (targets - original)
        bad = signed_volumes(points, tets) <= minimum
        if not bad.any():
            break
        culprits = np.unique(position[tets[bad]])
        culprits = culprits[culprits >= 0]
        if culprits.size == 0:
            break
        fraction[culprits] = np.where(fraction[culprits] > 1e-3, fraction[culprits] / 2, 0.0)
    return points, int((fraction < 1).sum())


def edge_lengths_at_nodes(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    pairs = tets[:, [0, 1, 0, 2, 0, 3, 1, 2, 1, 3, 2, 3]].reshape(-1, 2)
    lengths = np.linalg.norm(points[pairs[:, 0]] - points[pairs[:, 1]], axis=1)
    shortest = np.full(len(points), np.inf)
    np.minimum.at(shortest, pairs[:, 0], lengths)
    np.minimum.at(shortest, pairs[:, 1], lengths)
    return shortest


def boundary_nodes(tets: np.ndarray) -> np.ndarray:
    faces = np.sort(tets[:, [1, 2, 3, 0, 3, 2, 0, 1, 3, 0, 2, 1]].reshape(-1, 3), axis=1)
    unique, counts = np.unique(faces, axis=0, return_counts=True)
    return np.unique(unique[counts == 1])
