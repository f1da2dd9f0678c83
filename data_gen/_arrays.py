"""Plain NumPy tetrahedral-mesh helpers shared by the meshers.

The builders work on NumPy arrays and wrap the result in
:class:`torchmorph.mesh.TetMesh` at the very end; volumes and edge ratios are
torchmorph's own (:func:`torchmorph.mesh.signed_volumes`, :func:`torchmorph.mesh.edge_ratio`),
so importing data_gen imports torch.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np
import torch

from torchmorph import mesh as tm

__all__ = [
    "MeshArrays",
    "boundary_faces",
    "compact",
    "edge_ratio",
    "mesh_figures",
    "orient",
    "signed_volumes",
    "untangle",
]

# Faces of a positively oriented tetrahedron (a, b, c, d), normals pointing out.
_OUTWARD_FACES = np.array([(1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1)])
_TET_EDGES = np.array(list(itertools.combinations(range(4), 2)))  # every pair of vertices


@dataclass
class MeshArrays:
    """A generated mesh as NumPy arrays.

    Attributes
    ----------
    points : array, shape (N, 3), float64
    tets : array, shape (M, 4), int64, every signed volume > 0
    node_sets : dict of str to array, shape (K,), int64, sorted unique
    info : dict
        Build metadata: case, size, mesher, parameters, build seconds.
    """

    points: np.ndarray
    tets: np.ndarray
    node_sets: dict[str, np.ndarray]
    info: dict = field(default_factory=dict)


def signed_volumes(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed volumes, shape (M,) (:func:`torchmorph.mesh.signed_volumes` on arrays)."""
    return tm.signed_volumes(_tensor(points), _tensor(tets)).numpy()


def _tensor(array: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(array))


def orient(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Copy of ``tets`` with the last two vertices of negative tetrahedra swapped."""
    tets = np.array(tets, dtype=np.int64, copy=True)
    negative = signed_volumes(points, tets) < 0
    tets[negative, 2], tets[negative, 3] = tets[negative, 3], tets[negative, 2].copy()
    return tets


def boundary_faces(tets: np.ndarray) -> np.ndarray:
    """Faces that belong to exactly one tetrahedron, shape (F, 3).

    For positively oriented ``tets`` the faces are oriented with their normal
    pointing out of the mesh.
    """
    faces = tets[:, _OUTWARD_FACES].reshape(-1, 3)
    keys = np.sort(faces, axis=1)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    return faces[counts[inverse.ravel()] == 1]


def compact(
    points: np.ndarray, tets: np.ndarray, node_sets: dict[str, np.ndarray]
) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """Drop nodes used by no tetrahedron and renumber (order kept)."""
    used = np.zeros(len(points), dtype=bool)
    used[tets.ravel()] = True
    new_index = np.cumsum(used) - 1
    sets = {name: np.unique(new_index[nodes[used[nodes]]]) for name, nodes in node_sets.items()}
    return points[used], new_index[tets], sets


def edge_ratio(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Mesh quality Q per tetrahedron: longest / shortest edge (Ballarin et al. 2017,
    Section 2.3.1), shape (M,) (:func:`torchmorph.mesh.edge_ratio` on arrays)."""
    return tm.edge_ratio(_tensor(points), _tensor(tets)).numpy()


def mesh_figures(points: np.ndarray, tets: np.ndarray) -> dict[str, float | int]:
    """The paper's Table 1–3 figures of a mesh.

    Returns
    -------
    dict
        ``tets``, ``nodes``, ``interior``, ``boundary`` (node counts) and
        ``max_q``, ``mean_q`` (edge ratio, :func:`edge_ratio`).
    """
    boundary = np.unique(boundary_faces(tets))
    q = edge_ratio(points, tets)
    return {
        "tets": len(tets),
        "nodes": len(points),
        "interior": int(len(points) - len(boundary)),
        "boundary": len(boundary),
        "max_q": float(q.max()),
        "mean_q": float(q.mean()),
    }


def untangle(
    points: np.ndarray,
    tets: np.ndarray,
    fixed: np.ndarray,
    *,
    min_volume: np.ndarray | float = 0.0,
    max_sweeps: int = 50,
) -> tuple[np.ndarray, int]:
    """Repair inverted tetrahedra by moving their free nodes, one at a time.

    Each sweep visits the free nodes of the bad tetrahedra (volume <=
    ``min_volume``) and moves each to the best of a few points between where
    it is and the mean of its edge neighbours, best meaning the largest
    smallest volume of the tetrahedra around it (volumes relative to their
    ``min_volume``); a move is kept only if it improves that value, so good
    elements never turn bad. When a sweep stalls, the neighbours of the
    visited nodes join the next one.

    Parameters
    ----------
    points : array, shape (N, 3)
    tets : int array, shape (M, 4), positively oriented before the damage
    fixed : bool array, shape (N,)
        Nodes that must not move (the boundary).
    min_volume : float or array, shape (M,)
        A tetrahedron counts as bad at or below this volume.
    max_sweeps : int

    Returns
    -------
    points : array, shape (N, 3)
        Repaired copy.
    bad : int
        Tetrahedra still at or below ``min_volume`` (0 on success).
    """
    points = np.array(points, dtype=np.float64, copy=True)
    min_volume = np.broadcast_to(np.asarray(min_volume, dtype=np.float64), (len(tets),))
    scale = np.maximum(np.abs(min_volume), np.finfo(np.float64).tiny)
    order = np.argsort(tets.ravel(), kind="stable")
    offsets = np.concatenate([[0], np.cumsum(np.bincount(tets.ravel(), minlength=len(points)))])
    tet_of = order // 4
    edges = np.unique(np.sort(tets[:, _TET_EDGES].reshape(-1, 2), axis=1), axis=0)
    neighbours: list[list[int]] = [[] for _ in range(len(points))]
    for a, b in edges:
        neighbours[a].append(b)
        neighbours[b].append(a)

    def worst(node_tets: np.ndarray) -> float:
        return float(
            np.min(
                (signed_volumes(points, tets[node_tets]) - min_volume[node_tets]) / scale[node_tets]
            )
        )

    bad = signed_volumes(points, tets) <= min_volume
    rings = 0
    for _ in range(max_sweeps):
        if not bad.any():
            return points, 0
        active = np.zeros(len(points), dtype=bool)
        active[tets[bad].ravel()] = True
        for _ in range(rings):
            grown = active[edges[:, 0]] | active[edges[:, 1]]
            active[edges[grown].ravel()] = True
        improved = False
        for node in np.flatnonzero(active & ~fixed):
            node_tets = tet_of[offsets[node] : offsets[node + 1]]
            start = points[node].copy()
            best_value, best_point = worst(node_tets), start
            # directions: to the neighbours' mean, and up the volume gradient of the
            # worst tetrahedron around the node (the normal of its opposite face)
            values = (signed_volumes(points, tets[node_tets]) - min_volume[node_tets]) / scale[
                node_tets
            ]
            worst_tet = tets[node_tets[np.argmin(values)]]
            others = worst_tet[worst_tet != node]
            position = int(np.flatnonzero(worst_tet == node)[0])
            normal = np.cross(
                points[others[1]] - points[others[0]], points[others[2]] - points[others[0]]
            )
            sign = 1.0 if position % 2 else -1.0  # (b, c, d) vs (a, c, d) orientation parity
            gradient = sign * normal / (np.linalg.norm(normal) + 1e-300)
            reach = np.linalg.norm(points[neighbours[node]] - start, axis=1).min()
            directions = [points[neighbours[node]].mean(axis=0) - start, gradient * reach]
            for direction in directions:
                for t in (1.0, 0.5, 0.25, 0.1, 0.03):
                    points[node] = start + t * direction
                    value = worst(node_tets)
                    if value > best_value:
                        best_value, best_point = value, points[node].copy()
            points[node] = best_point
            improved |= best_point is not start
        bad = signed_volumes(points, tets) <= min_volume
        rings = 0 if improved else rings + 1
    return points, int(bad.sum())
