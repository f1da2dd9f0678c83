"""Tetrahedral meshes: :class:`TetMesh`, the :class:`~torchmorph.mesh.Mesh` of one block
of linear tetrahedra (the paper's meshes), and :func:`box_mesh`.

A mesh is plain data — ``points (N, 3)``, ``tets (M, 4)`` and named node sets —
checked once on construction. Topological quantities (boundary faces, boundary
and interior nodes, edges) and geometric ones (volumes, the mass matrix of
:mod:`torchmorph.mesh.quality`) are derived on first use and cached.

Why a subclass and not a second model: everything in torchmorph takes a
:class:`~torchmorph.mesh.Mesh`, so there is one model and one API, and a ``TetMesh``
goes wherever a ``Mesh`` does. It stays for what is tetrahedral only (``tets``,
``boundary_faces``, ``edges``, :func:`box_mesh`, the flat-tetrahedron bound), which the
paper's meshes, saved 0.1.0 states and existing code use;
:func:`~torchmorph.mesh.read_mesh` returns one for a file holding one block of linear
tetrahedra.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor

from torchmorph._checks import as_points
from torchmorph.mesh._kernels import tet_edge_lengths_squared, tet_volumes
from torchmorph.mesh.cells import TET_EDGES, TET_OUTWARD_FACES
from torchmorph.mesh.model import CellBlock, Mesh

__all__ = ["FLAT_TET_TOLERANCE", "TetMesh", "box_mesh"]

#: A tetrahedron is rejected as flat when ``|V| <= FLAT_TET_TOLERANCE * L**3``,
#: ``L`` its longest edge. The bound is relative to the element's own size, so
#: it does not depend on the units, on the extent of the mesh or on how graded
#: it is (boundary-layer elements much smaller than the domain pass). A regular
#: tetrahedron has ``V ≈ 0.118 L**3`` and float64 round-off in the volume is
#: about ``1e-16 L**3``: the threshold lies far from both.
FLAT_TET_TOLERANCE = 1e-12

# Largest node count for which a face (i < j < k) fits one int64 key i*N² + j*N + k.
_MAX_NODES_FOR_FACE_KEYS = 2_000_000


class TetMesh(Mesh):
    """A conforming tetrahedral mesh with named node sets: the :class:`Mesh` of one block
    of linear tetrahedra, with the checks and quantities of tetrahedra.

    Parameters
    ----------
    points : Tensor or array, shape (N, 3)
        Node coordinates. Tensors keep their dtype and device; NumPy arrays and
        sequences become float64 tensors.
    tets : Tensor or array, shape (M, 4), integer
        Vertex indices of the tetrahedra. Negatively oriented tetrahedra are
        reoriented (their last two vertices swapped) so that every signed
        volume is > 0; the order of the tetrahedra is kept, so cell data stay
        aligned. The input is not modified.
    node_sets : mapping of str to index array, optional
        Named groups of nodes (``"root"``, ``"tip"``, ``"wall_top"`` …), each
        given as indices or a boolean mask of length N; stored as sorted unique
        int64 tensors on the points' device.
    face_sets, groups : optional, keyword-only
        As in :class:`Mesh` (triangle face sets).
    name : str, optional, keyword-only
        A label for printing and file names.

    Raises
    ------
    ValueError
        For points that are not (N, 3), empty, or hold NaN/inf; tets that are
        not (M, 4) integers, empty, or index outside ``[0, N)``; flat
        tetrahedra (``|V| <= FLAT_TET_TOLERANCE * L**3``, ``L`` the longest
        edge); node sets with non-string names or indices outside ``[0, N)``.

    Notes
    -----
    ``points`` and ``tets`` are copied (a tensor that requires grad keeps its
    autograd link through the copy), so editing the caller's arrays afterwards
    does not change the mesh. Nodes that belong to no tetrahedron are allowed; they are
    not on the boundary and so count among :attr:`interior_nodes`. Faces shared by more
    than two tetrahedra (a non-manifold or duplicated input) and tetrahedra
    folded over a neighbour (inverted reference elements: the two tetrahedra of
    an interior face on the same side of it) raise ``ValueError``.

    Overlapping tetrahedra that share no face are detected where they share a
    node: the solid angles of the tetrahedra at a node may add up to at most one
    sphere (4π), and to exactly 4π at a node off the boundary. Not detected: two
    parts of the mesh that overlap without sharing a node (e.g. two separate
    blocks pushed into each other) — check the boundary surface for
    self-intersections if your input may have them.
    """

    def __init__(
        self,
        points: Tensor | np.ndarray | Sequence,
        tets: Tensor | np.ndarray | Sequence,
        node_sets: Mapping[str, Tensor | np.ndarray | Sequence] | None = None,
        *,
        face_sets: Mapping[str, Any] | None = None,
        groups: Mapping[str, Sequence[str]] | None = None,
        name: str | None = None,
    ) -> None:
        dtype = None if isinstance(points, Tensor) else torch.float64
        given_points, given_tets = points, tets
        points = as_points(points, "points", dtype=dtype)
        if points is given_points:  # a copy: later in-place edits by the caller cannot
            points = points.clone()  # make the cached topology and geometry stale
        tets = _as_tets(tets, points.shape[0]).to(points.device)
        if tets is given_tets:
            tets = tets.clone()
        tets = _orient(points, tets)
        boundary_faces = _checked_faces(points, tets)
        _check_interior_solid_angles(points, tets, boundary_faces)
        orientation = torch.ones(tets.shape[0], dtype=torch.int8, device=tets.device)
        self._setup(
            points, (CellBlock("tetra", tets),), (orientation,), node_sets, face_sets, groups, name
        )
        self._topology["boundary_faces"] = boundary_faces

    # ------------------------------------------------------------------ data

    @property
    def tets(self) -> Tensor:
        """Vertex indices, shape (M, 4), int64, positively oriented."""
        return self._blocks[0].nodes

    @property
    def num_tets(self) -> int:
        """Number of tetrahedra M."""
        return int(self._blocks[0].nodes.shape[0])

    # ------------------------------------------------------------------ topology

    @property
    def boundary_faces(self) -> Tensor:
        """Faces that belong to exactly one tetrahedron, shape (F, 3), int64.

        Each face is ordered so that its right-hand normal points out of the
        mesh. Faces are sorted by their (sorted) vertex triples.
        """
        return self._cached_topology(
            "boundary_faces", lambda: _face_structure(self.tets, self.num_nodes)[0]
        )

    @property
    def boundary_facets(self) -> tuple[CellBlock, ...]:
        """:attr:`boundary_faces` as one block of triangles (see :class:`Mesh`)."""
        return (CellBlock("triangle", self.boundary_faces),)

    @property
    def edges(self) -> Tensor:
        """Unique undirected edges ``(i, j)`` with ``i < j``, shape (E, 2), int64, sorted."""
        return self._cached_topology("edges", lambda: self._find_edges()[0])

    @property
    def tet_edges(self) -> Tensor:
        """Edge numbers of every tetrahedron, shape (M, 6), int64.

        Row ``k`` holds the indices into :attr:`edges` of the edges
        ``(0,1), (0,2), (0,3), (1,2), (1,3), (2,3)`` of tetrahedron ``k``.
        """
        return self._cached_topology("tet_edges", lambda: self._find_edges()[1])

    def _find_edges(self) -> tuple[Tensor, Tensor]:
        if "edges" in self._topology and "tet_edges" in self._topology:
            return self._topology["edges"], self._topology["tet_edges"]
        tets = self.tets
        first = tets[:, [i for i, _ in TET_EDGES]]
        second = tets[:, [j for _, j in TET_EDGES]]
        n = self.num_nodes
        keys = torch.minimum(first, second) * n + torch.maximum(first, second)
        unique, inverse = torch.unique(keys.reshape(-1), sorted=True, return_inverse=True)
        edges = torch.stack([unique // n, unique % n], dim=1)
        self._topology["edges"] = edges
        self._topology["tet_edges"] = inverse.reshape(-1, 6)
        return edges, self._topology["tet_edges"]

    # ------------------------------------------------------------------ geometry

    @property
    def volumes(self) -> Tensor:
        """Signed volumes of the tetrahedra, shape (M,), in the points' dtype.

        All > 0 for a constructed mesh; a mesh from :meth:`deformed` may have
        negative ones (inverted tetrahedra).
        """
        return self._cached_geometry("volumes", lambda: tet_volumes(self._points, self.tets))

    def __repr__(self) -> str:
        sets = ", ".join(self.markers) or "none"
        label = f"{self.name!r}, " if self.name else ""
        return (
            f"TetMesh({label}nodes={self.num_nodes}, tets={self.num_tets}, "
            f"node_sets=[{sets}], dtype={self.dtype}, device={self.device})"
        )


# ---------------------------------------------------------------------- helpers


def _as_tets(tets: Tensor | np.ndarray | Sequence, num_nodes: int) -> Tensor:
    if not isinstance(tets, Tensor):
        array = np.asarray(tets)
        if array.size == 0:
            array = array.astype(np.int64)
        if array.dtype.kind not in "iu":
            raise ValueError(f"tets must hold integer vertex indices, got dtype {array.dtype}")
        tets = torch.from_numpy(np.ascontiguousarray(array.astype(np.int64)))
    if tets.is_floating_point() or tets.is_complex() or tets.dtype == torch.bool:
        raise ValueError(f"tets must hold integer vertex indices, got dtype {tets.dtype}")
    if tets.ndim != 2 or tets.shape[1] != 4:
        raise ValueError(f"tets must have shape (M, 4), got {tuple(tets.shape)}")
    if tets.shape[0] == 0:
        raise ValueError("tets is empty: at least one tetrahedron is needed")
    tets = tets.long()
    low, high = int(tets.min()), int(tets.max())
    if low < 0 or high >= num_nodes:
        raise ValueError(
            f"tets holds vertex indices outside [0, {num_nodes}): min {low}, max {high}"
        )
    return tets


def _orient(points: Tensor, tets: Tensor) -> Tensor:
    """Reject flat tetrahedra and swap the last two vertices of negative ones."""
    with torch.no_grad():
        exact = points.detach().to(torch.float64)
        volumes = tet_volumes(exact, tets)
        # Every edge is at most the bounding-box diagonal, so only tetrahedra below
        # the bound for that length can be flat: measure their edges alone.
        diagonal = float(torch.linalg.vector_norm(exact.amax(0) - exact.amin(0)))
        candidates = torch.nonzero(volumes.abs() <= FLAT_TET_TOLERANCE * diagonal**3).flatten()
        if candidates.numel() > 0:
            longest = tet_edge_lengths_squared(exact, tets[candidates]).amax(-1) ** 1.5
            flat = candidates[volumes[candidates].abs() <= FLAT_TET_TOLERANCE * longest]
        else:
            flat = candidates
        if flat.numel() > 0:
            shown = ", ".join(str(i) for i in flat[:5].tolist())
            more = ", ..." if flat.numel() > 5 else ""
            raise ValueError(
                f"tets: {flat.numel()} tetrahedra have zero volume "
                f"(|V| <= {FLAT_TET_TOLERANCE:g} * longest_edge**3), at indices {shown}{more}"
            )
        negative = volumes < 0
        if bool(negative.any()):
            swapped = torch.where(negative[:, None], tets[:, [3, 2]], tets[:, 2:])
            tets = torch.cat([tets[:, :2], swapped], dim=1)
    return tets


def _face_structure(tets: Tensor, num_nodes: int) -> tuple[Tensor, Tensor, Tensor]:
    """Boundary faces and the interior face pairs of a tetrahedral mesh.

    Returns the faces that belong to one tetrahedron (F, 3), outward oriented,
    and for every face shared by two tetrahedra the positions ``first`` and
    ``second`` of its two copies in the (4M, 3) array of outward faces (face
    ``k`` of tet ``t`` is position ``4 t + k``; vertex ``k`` is opposite it).

    Raises
    ------
    ValueError
        If a face belongs to more than two tetrahedra (a non-manifold mesh or
        duplicated tetrahedra).
    """
    device = tets.device
    faces = tets[:, torch.tensor(TET_OUTWARD_FACES, device=device)].reshape(-1, 3)
    ordered = torch.sort(faces, dim=1).values
    if num_nodes <= _MAX_NODES_FOR_FACE_KEYS:
        keys = (ordered[:, 0] * num_nodes + ordered[:, 1]) * num_nodes + ordered[:, 2]
        keys, order = torch.sort(keys)
        same = keys[1:] == keys[:-1]
    else:  # lexicographic order by three stable sorts
        order = torch.arange(faces.shape[0], device=device)
        for column in (2, 1, 0):
            order = order[torch.sort(ordered[order, column], stable=True).indices]
        rows = ordered[order]
        same = (rows[1:] == rows[:-1]).all(1)
    shared_thrice = same[1:] & same[:-1]
    if bool(shared_thrice.any()):
        count = int(shared_thrice.sum())
        raise ValueError(
            f"tets: {count} face(s) belong to more than two tetrahedra "
            "(a non-manifold mesh or duplicated tetrahedra)"
        )
    true = torch.ones(1, dtype=torch.bool, device=device)
    single = torch.cat([true, ~same]) & torch.cat([~same, true])
    return faces[order[single]], order[:-1][same], order[1:][same]


def _checked_faces(points: Tensor, tets: Tensor) -> Tensor:
    """Boundary faces, after checking that no reference tetrahedron is folded.

    In a valid (positively oriented) mesh the two tetrahedra of an interior face
    lie on opposite sides of it: the vertex of the second opposite the face is on
    the outward side of the face as seen from the first. A tetrahedron folded over
    its neighbour (an inverted reference element that orientation alone cannot
    reveal) puts both on the same side.
    """
    boundary, first, second = _face_structure(tets, points.shape[0])
    if first.numel() == 0:
        return boundary
    with torch.no_grad():
        exact = points.detach().to(torch.float64)
        outward = tets[:, torch.tensor(TET_OUTWARD_FACES, device=tets.device)].reshape(-1, 3)
        opposite = tets[second // 4, second % 4]
        sides = tet_volumes(exact, torch.cat([outward[first], opposite[:, None]], 1))
        folded = torch.nonzero(sides <= 0).flatten()
    if folded.numel() > 0:
        pairs = ", ".join(
            f"({int(first[k]) // 4}, {int(second[k]) // 4})" for k in folded[:5].tolist()
        )
        more = ", ..." if folded.numel() > 5 else ""
        raise ValueError(
            f"tets: {folded.numel()} interior face(s) have both of their tetrahedra on the same "
            f"side (inverted, folded reference tetrahedra), e.g. tetrahedra {pairs}{more}"
        )
    return boundary


_SOLID_ANGLE_TOLERANCE = 1e-8
"""Relative tolerance of the full-sphere check of the solid angles at interior nodes."""


def _check_interior_solid_angles(points: Tensor, tets: Tensor, boundary_faces: Tensor) -> None:
    """Raise ``ValueError`` if the tetrahedra around a node cover more than one sphere
    (4π: overlapping tetrahedra), or those around an interior node less (a gap)."""
    if tets.numel() == 0:
        return
    with torch.no_grad():
        exact = points.detach().to(torch.float64)
        vertices = exact[tets]  # (M, 4, 3)
        angles = []
        for corner in range(4):
            others = [k for k in range(4) if k != corner]
            u, v, w = (vertices[:, k] - vertices[:, corner] for k in others)
            lu, lv, lw = u.norm(dim=1), v.norm(dim=1), w.norm(dim=1)
            triple = (u * torch.linalg.cross(v, w, dim=1)).sum(1).abs()
            below = lu * lv * lw + (u * v).sum(1) * lw + (u * w).sum(1) * lv + (v * w).sum(1) * lu
            angles.append(2.0 * torch.atan2(triple, below))  # Van Oosterom–Strackee
        total = exact.new_zeros(points.shape[0]).index_add_(
            0, tets.reshape(-1), torch.stack(angles, 1).reshape(-1)
        )
        interior = torch.zeros(points.shape[0], dtype=torch.bool, device=tets.device)
        interior[tets.reshape(-1)] = True
        interior[boundary_faces.reshape(-1)] = False
        sphere = 4.0 * torch.pi
        over = total > sphere * (1.0 + _SOLID_ANGLE_TOLERANCE)  # anywhere: overlap
        under = interior & (total < sphere * (1.0 - _SOLID_ANGLE_TOLERANCE))
        wrong = torch.nonzero(over | under).flatten()
    if wrong.numel() > 0:
        node = int(wrong[0])
        raise ValueError(
            f"tets: the tetrahedra around {wrong.numel()} node(s) cover more than one sphere "
            f"(overlapping tetrahedra) or, at an interior node, less (a gap), e.g. node "
            f"{node}: solid angle "
            f"{float(total[node]) / sphere:.6g} x 4π"
        )


def box_mesh(
    cells: int | Sequence[int] = 4,
    size: float | Sequence[float] = 1.0,
    *,
    origin: Sequence[float] = (0.0, 0.0, 0.0),
) -> TetMesh:
    """A structured tetrahedral mesh of a box, for examples and tests.

    The box ``origin + [0, size_x] × [0, size_y] × [0, size_z]`` is split into
    ``cells`` hexahedra per axis, each cut into 6 tetrahedra around its main
    diagonal (Kuhn split; conforming across cells).

    Parameters
    ----------
    cells : int or (3,) ints
        Number of cells along each axis (>= 1).
    size : float or (3,) floats
        Edge lengths of the box (> 0).
    origin : (3,) floats
        The corner with the smallest coordinates.

    Returns
    -------
    TetMesh
        ``(nx+1)(ny+1)(nz+1)`` nodes, ``6 nx ny nz`` tetrahedra (float64), with
        the six faces as node sets ``"x0", "x1", "y0", "y1", "z0", "z1"``.
    """
    counts = np.broadcast_to(np.asarray(cells), (3,)).astype(np.int64)
    lengths = np.broadcast_to(np.asarray(size, dtype=np.float64), (3,))
    if (counts < 1).any():
        raise ValueError(f"cells must be >= 1 along every axis, got {tuple(counts)}")
    if not np.isfinite(lengths).all() or (lengths <= 0).any():
        raise ValueError(f"size must be finite and > 0 along every axis, got {tuple(lengths)}")
    nx, ny, nz = (int(c) for c in counts)
    ticks = [np.arange(n + 1) / n for n in (nx, ny, nz)]
    grid = np.meshgrid(*ticks, indexing="ij")
    unit = np.stack([g.ravel() for g in grid], 1)
    points = np.asarray(origin, dtype=np.float64) + unit * lengths
    index = np.arange(unit.shape[0]).reshape(nx + 1, ny + 1, nz + 1)
    corner = {
        (i, j, k): index[i : nx + i, j : ny + j, k : nz + k].ravel()
        for i in (0, 1)
        for j in (0, 1)
        for k in (0, 1)
    }
    paths = (
        ((1, 0, 0), (1, 1, 0)),
        ((1, 0, 0), (1, 0, 1)),
        ((0, 1, 0), (1, 1, 0)),
        ((0, 1, 0), (0, 1, 1)),
        ((0, 0, 1), (1, 0, 1)),
        ((0, 0, 1), (0, 1, 1)),
    )
    tets = np.concatenate(
        [
            np.stack([corner[(0, 0, 0)], corner[a], corner[b], corner[(1, 1, 1)]], 1)
            for a, b in paths
        ]
    )
    node_sets = {}
    for axis, name in enumerate("xyz"):
        node_sets[f"{name}0"] = np.nonzero(unit[:, axis] == 0.0)[0]
        node_sets[f"{name}1"] = np.nonzero(unit[:, axis] == 1.0)[0]
    return TetMesh(points, tets, node_sets, name="box")
