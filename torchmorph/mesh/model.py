"""Meshes of any element kinds, 2-D and 3-D: :class:`Mesh`.

A mesh is plain data — ``points (N, D)``, cell blocks by kind (any kinds of
:data:`torchmorph.mesh.cells.CELL_KINDS` of one dimension D, linear or quadratic),
named node sets, named face sets (facets, where a file's markers are faces) and groups
of markers — checked once on construction. The boundary is the facets used once across
all blocks; a quadratic cell's mid-side and face nodes are nodes like any other (those
of boundary facets are boundary nodes). Topology and geometry are derived on first use
and cached. :class:`~torchmorph.mesh.TetMesh` is the tetrahedral special case.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor

from torchmorph._checks import as_index, as_points, check_finite, check_float_dtype
from torchmorph.mesh._kernels import simplex_volumes
from torchmorph.mesh._topology import (
    CellBlock,
    Facets,
    as_cell_blocks,
    cell_orientations,
    check_folds,
    match_facets,
)
from torchmorph.mesh.cells import FACET_KINDS, cell_kind

__all__ = ["CellBlock", "Mesh"]


class Mesh:
    """A conforming mesh of any element kinds with named markers.

    Parameters
    ----------
    points : Tensor or array, shape (N, D), D = 2 or 3
        Node coordinates. Tensors keep their dtype and device; NumPy arrays and
        sequences become float64 tensors.
    cells : mapping of kind to array, or sequence of (kind, array) pairs
        The cell blocks, in order (several blocks of one kind are kept apart), kinds as
        meshio names them (``"tetra"``, ``"wedge"``, ``"hexahedron20"``, ``"quad"`` …)
        with meshio's node order; all of topological dimension D. meshio ``CellBlock``
        objects are accepted too.
    node_sets : mapping of str to index array, optional
        Named groups of nodes (indices or boolean masks of length N).
    face_sets : mapping of str to cell blocks, optional
        Named sets of facets (``"triangle"``/``"quad"`` and their quadratic kinds in 3-D,
        ``"line"``/``"line3"`` in 2-D), as a mapping or sequence like ``cells``. Their
        nodes are markers too (:meth:`node_set`).
    groups : mapping of str to sequence of str, optional
        Named groups of markers (OpenFOAM's ``inGroups``): the group's nodes are the
        union of its members'.
    name : str, optional, keyword-only
        A label for printing and file names.

    Raises
    ------
    ValueError
        For points that are not (N, D) with D the cells' dimension, or hold NaN/inf; an
        unknown cell kind (named); cells of two dimensions; indices outside ``[0, N)``;
        flat cells; reference cells inverted at some corners or folded over a neighbour;
        facets shared by more than two cells; a quadrilateral face against two triangular
        faces split along its diagonal (a non-conforming interface, which would read as
        boundary); markers with bad names, indices or kinds, or a name used twice.

    Notes
    -----
    The node order of every cell is kept as given, so a mesh written back is the mesh
    read: a cell given in mirrored order is valid, with orientation −1
    (:attr:`orientation`), and its facets are flipped so that :attr:`boundary_facets`
    point outward. Quadratic cells are measured on their corners (see
    :mod:`torchmorph.mesh.cells`). Not detected: parts of the mesh that overlap without
    sharing a facet, and other non-conforming interfaces (hanging nodes: a face or edge
    against several smaller ones; a quad against a single triangle on three of its
    corners), whose facets read as boundary.
    """

    def __init__(
        self,
        points: Tensor | np.ndarray | Sequence,
        cells: Any,
        node_sets: Mapping[str, Any] | None = None,
        face_sets: Mapping[str, Any] | None = None,
        *,
        groups: Mapping[str, Sequence[str]] | None = None,
        name: str | None = None,
    ) -> None:
        dtype = None if isinstance(points, Tensor) else torch.float64
        given = points
        dim = _points_dim(points)
        points = as_points(points, "points", dim=dim, dtype=dtype)
        if points is given:
            points = points.clone()
        blocks = as_cell_blocks(cells, points.shape[0], points.device)
        kind_dim = cell_kind(blocks[0].kind).dim
        if kind_dim != dim:
            raise ValueError(
                f"points must have shape (N, {kind_dim}) for cells of dimension {kind_dim} "
                f"({', '.join(sorted({b.kind for b in blocks}))}), got {tuple(points.shape)}; "
                "a planar mesh keeps its two in-plane coordinates"
            )
        orientation = cell_orientations(points, blocks)
        facets = match_facets(blocks, orientation, points.shape[0])
        check_folds(facets)
        self._setup(points, blocks, orientation, node_sets, face_sets, groups, name)
        self._topology["facets"] = facets

    def _setup(self, points, blocks, orientation, node_sets, face_sets, groups, name) -> None:
        if name is not None and not isinstance(name, str):
            raise TypeError(f"name must be a string or None, got {type(name).__name__}")
        num_nodes = points.shape[0]
        self._points = points
        self._blocks = tuple(blocks)
        self._orientation = tuple(orientation)
        self._node_sets = _as_node_sets(node_sets, num_nodes, points.device)
        self._face_sets = _as_face_sets(face_sets, num_nodes, points.device, points.shape[1])
        self._groups = _as_groups(groups, set(self._node_sets) | set(self._face_sets))
        clash = set(self._node_sets) & set(self._face_sets)
        if clash:
            raise ValueError(
                f"node_sets and face_sets: the name(s) {', '.join(sorted(clash))} are used by "
                "both; give each marker one name"
            )
        self.name = name
        self._topology: dict[str, Any] = {}
        self._geometry: dict[str, Any] = {}

    @classmethod
    def from_checked(
        cls,
        points: Tensor,
        cells: Sequence[CellBlock],
        orientation: Sequence[Tensor],
        node_sets: Mapping[str, Tensor] | None = None,
        *,
        name: str | None = None,
    ) -> Mesh:
        """A mesh from parts that were checked before (a module's stored reference mesh):
        the cells and their orientation are taken as they are, not validated again."""
        mesh = Mesh.__new__(Mesh)
        mesh._setup(points, tuple(cells), tuple(orientation), node_sets, None, None, name)
        return mesh

    @classmethod
    def _from_parts(cls, template: Mesh, points: Tensor, **changes: Any) -> Mesh:
        """A copy of ``template`` with other points (topology shared), not re-validated."""
        mesh = cls.__new__(cls)
        mesh.__dict__.update(template.__dict__)
        mesh._points = points
        mesh._geometry = {}
        mesh.__dict__.update(changes)
        return mesh

    # ------------------------------------------------------------------ data

    @property
    def points(self) -> Tensor:
        """Node coordinates, shape (N, D)."""
        return self._points

    @property
    def dim(self) -> int:
        """The dimension D (2 or 3) of the points and of the cells."""
        return int(self._points.shape[1])

    @property
    def cells(self) -> tuple[CellBlock, ...]:
        """The cell blocks ``(kind, nodes (M_k, n_k))``, in the order given."""
        return self._blocks

    @property
    def orientation(self) -> tuple[Tensor, ...]:
        """Per block, the orientation of every cell (int8: +1, or −1 for mirrored order)."""
        return self._orientation

    @property
    def cell_counts(self) -> dict[str, int]:
        """Number of cells of each kind (blocks of one kind added up)."""
        counts: dict[str, int] = {}
        for block in self._blocks:
            counts[block.kind] = counts.get(block.kind, 0) + int(block.nodes.shape[0])
        return counts

    @property
    def num_cells(self) -> int:
        return sum(int(block.nodes.shape[0]) for block in self._blocks)

    @property
    def num_nodes(self) -> int:
        return int(self._points.shape[0])

    @property
    def device(self) -> torch.device:
        return self._points.device

    @property
    def dtype(self) -> torch.dtype:
        return self._points.dtype

    @property
    def is_tetrahedral(self) -> bool:
        """Whether every cell is a linear tetrahedron."""
        return all(block.kind == "tetra" for block in self._blocks)

    @property
    def tets(self) -> Tensor:
        """The cells as positively oriented tetrahedra (M, 4), for a tetrahedral mesh.

        Raises
        ------
        ValueError
            If the mesh holds cells of other kinds (use :attr:`cells`).
        """
        if not self.is_tetrahedral:
            kinds = ", ".join(sorted(self.cell_counts))
            raise ValueError(
                f"tets: this mesh holds {kinds} cells, not only linear tetrahedra; use "
                "mesh.cells (the quality functions take any mesh)"
            )

        def build() -> Tensor:
            parts = []
            for block, orientation in zip(self._blocks, self._orientation, strict=True):
                swapped = block.nodes[:, [0, 1, 3, 2]]
                parts.append(torch.where(orientation[:, None] < 0, swapped, block.nodes))
            return torch.cat(parts)

        return self._cached_topology("tets", build)

    # ------------------------------------------------------------------ markers

    @property
    def node_sets(self) -> dict[str, Tensor]:
        """The named node sets given (a copy of the mapping; the tensors are shared)."""
        return dict(self._node_sets)

    @property
    def face_sets(self) -> dict[str, tuple[CellBlock, ...]]:
        """The named face sets given, as facet blocks."""
        return dict(self._face_sets)

    @property
    def groups(self) -> dict[str, tuple[str, ...]]:
        """The named groups of markers."""
        return dict(self._groups)

    @property
    def markers(self) -> tuple[str, ...]:
        """Every name :meth:`node_set` knows: node sets, face sets, then groups."""
        return (*self._node_sets, *self._face_sets, *self._groups)

    def node_set(self, name: str) -> Tensor:
        """Nodes of the marker ``name``, shape (K,), sorted unique int64: a node set, the
        nodes of a face set, or the union over a group's members.

        Raises
        ------
        ValueError
            If no marker has that name (the message lists the known ones).
        """
        if isinstance(name, str):
            if name in self._node_sets:
                return self._node_sets[name]
            if name in self._face_sets:
                key = "face_set_nodes:" + name
                return self._cached_topology(
                    key, lambda: _facet_nodes(self._face_sets[name], self.device)
                )
            if name in self._groups:
                return self.nodes_of(self._groups[name])
        known = ", ".join(self.markers) or "(none)"
        raise ValueError(f"unknown marker {name!r}; known: {known}")

    def nodes_of(self, names: str | Sequence[str]) -> Tensor:
        """Sorted unique union of one or several markers, shape (K,), int64."""
        names = [names] if isinstance(names, str) else list(names)
        parts = [self.node_set(n) for n in names]
        if not parts:
            return torch.empty(0, dtype=torch.int64, device=self.device)
        return torch.unique(torch.cat(parts), sorted=True)

    # ------------------------------------------------------------------ topology

    def _cached_topology(self, key: str, build: Callable[[], Any]) -> Any:
        value = self._topology.get(key)
        if value is None:
            value = build()
            self._topology[key] = value
        return value

    def _cached_geometry(self, key: str, build: Callable[[], Any], *, always: bool = False) -> Any:
        """Memoise a quantity derived from the points (not while they require grad, unless
        ``always``: quantities built from detached points)."""
        if key in self._geometry:
            return self._geometry[key]
        value = build()
        if always or not self._points.requires_grad:
            self._geometry[key] = value
        return value

    def _facets(self) -> Facets:
        return self._cached_topology(
            "facets", lambda: match_facets(self._blocks, self._orientation, self.num_nodes)
        )

    @property
    def boundary_facets(self) -> tuple[CellBlock, ...]:
        """The facets used by one cell (faces in 3-D, edges in 2-D), by facet kind,
        oriented outward, each block sorted by its corners."""
        return self._facets().boundary

    @property
    def boundary_nodes(self) -> Tensor:
        """Nodes of the boundary facets (mid-side and face nodes included), sorted int64."""
        return self._cached_topology(
            "boundary_nodes", lambda: _facet_nodes(self.boundary_facets, self.device)
        )

    @property
    def interior_nodes(self) -> Tensor:
        """All nodes not on the boundary, sorted int64 (nodes of no cell included)."""

        def build() -> Tensor:
            on_boundary = torch.zeros(self.num_nodes, dtype=torch.bool, device=self.device)
            on_boundary[self.boundary_nodes] = True
            return torch.nonzero(~on_boundary).flatten()

        return self._cached_topology("interior_nodes", build)

    @property
    def simplices(self) -> tuple[Tensor, Tensor]:
        """The fixed decomposition of every cell's corners into positively oriented simplices
        (tetrahedra in 3-D, triangles in 2-D): ``(simplices (S, D + 1), cell of each (S,))``,
        cells numbered across blocks in order."""

        def build() -> tuple[Tensor, Tensor]:
            parts, owners, offset = [], [], 0
            for block, orientation in zip(self._blocks, self._orientation, strict=True):
                kind = cell_kind(block.kind)
                count = block.nodes.shape[0]
                local = torch.tensor(kind.simplices, device=self.device)  # (s, D + 1)
                simplices = block.nodes[:, local]  # (M, s, D + 1)
                swapped = simplices[..., [1, 0, *range(2, local.shape[1])]]
                mirrored = (orientation < 0)[:, None, None]
                parts.append(torch.where(mirrored, swapped, simplices).reshape(-1, local.shape[1]))
                cells = torch.arange(offset, offset + count, device=self.device)
                owners.append(cells.repeat_interleave(local.shape[0]))
                offset += count
            return torch.cat(parts), torch.cat(owners)

        return self._cached_topology("simplices", build)

    # ------------------------------------------------------------------ geometry

    @property
    def volumes(self) -> Tensor:
        """Volume (area in 2-D) of every cell from its simplices, shape (M,), positive for
        a constructed mesh; a mesh from :meth:`deformed` may have some <= 0."""

        def build() -> Tensor:
            simplices, owners = self.simplices
            volumes = simplex_volumes(self._points, simplices)
            return volumes.new_zeros(self.num_cells).index_add(0, owners, volumes)

        return self._cached_geometry("volumes", build)

    @property
    def bounding_box(self) -> Tensor:
        """Lower and upper corners, shape (2, D)."""
        points = self._points.detach()
        return torch.stack([points.amin(0), points.amax(0)])

    # ------------------------------------------------------------------ new meshes

    def deformed(self, displacement: Tensor) -> Mesh:
        """The mesh moved by a nodal displacement (N, D): same cells and markers, points
        ``points + displacement`` (autograd history kept). Not re-validated: its volumes
        may be <= 0, which is how inverted cells are found."""
        if isinstance(displacement, np.ndarray):
            displacement = torch.from_numpy(displacement)
        if not isinstance(displacement, Tensor):
            raise TypeError(
                f"displacement must be a torch.Tensor, got {type(displacement).__name__}"
            )
        if displacement.shape != self._points.shape:
            raise ValueError(
                f"displacement must have shape {tuple(self._points.shape)}, "
                f"got {tuple(displacement.shape)}"
            )
        check_float_dtype(displacement, "displacement")
        if displacement.device != self.device:
            raise ValueError(
                f"displacement is on device {displacement.device} but the mesh is on {self.device}"
            )
        check_finite(displacement, "displacement")
        return type(self)._from_parts(self, self._points + displacement)

    def with_node_sets(self, node_sets: Mapping[str, Any]) -> Mesh:
        """A copy with more named node sets (names not yet markers), topology shared."""
        added = _as_node_sets(node_sets, self.num_nodes, self.device)
        clash = set(added) & set(self.markers)
        if clash:
            raise ValueError(f"node_sets: {', '.join(sorted(clash))} name markers already")
        mesh = type(self)._from_parts(self, self._points, _node_sets={**self._node_sets, **added})
        mesh._geometry = self._geometry
        return mesh

    def to(
        self, device: torch.device | str | None = None, dtype: torch.dtype | None = None
    ) -> Mesh:
        """A copy on another device and/or with another floating dtype for the points."""
        if dtype is not None and not dtype.is_floating_point:
            raise ValueError(f"dtype must be a floating-point dtype, got {dtype}")
        points = self._points.to(device=device, dtype=dtype)
        target = points.device
        return type(self)._from_parts(
            self,
            points,
            _blocks=tuple(CellBlock(b.kind, b.nodes.to(target)) for b in self._blocks),
            _orientation=tuple(o.to(target) for o in self._orientation),
            _node_sets={k: v.to(target) for k, v in self._node_sets.items()},
            _face_sets={
                k: tuple(CellBlock(b.kind, b.nodes.to(target)) for b in v)
                for k, v in self._face_sets.items()
            },
            _topology=_moved(self._topology, target),
        )

    def __repr__(self) -> str:
        counts = ", ".join(f"{kind}={count}" for kind, count in self.cell_counts.items())
        markers = ", ".join(self.markers) or "none"
        label = f"{self.name!r}, " if self.name else ""
        return (
            f"{type(self).__name__}({label}dim={self.dim}, nodes={self.num_nodes}, {counts}, "
            f"markers=[{markers}], dtype={self.dtype}, device={self.device})"
        )


# ---------------------------------------------------------------------- helpers


def _points_dim(points: Any) -> int:
    shape = getattr(points, "shape", None)
    if shape is None:
        shape = np.shape(points)
    return int(shape[1]) if len(shape) == 2 and shape[1] in (2, 3) else 3


def _moved(value: Any, device: torch.device) -> Any:
    if isinstance(value, Tensor):
        return value.to(device)
    if isinstance(value, tuple) and hasattr(value, "_fields"):
        return type(value)(*(_moved(v, device) for v in value))
    if isinstance(value, (tuple, list)):
        return type(value)(_moved(v, device) for v in value)
    if isinstance(value, dict):
        return {k: _moved(v, device) for k, v in value.items()}
    return value


def _facet_nodes(blocks: Sequence[CellBlock], device: torch.device) -> Tensor:
    if not blocks:
        return torch.empty(0, dtype=torch.int64, device=device)
    return torch.unique(torch.cat([block.nodes.reshape(-1) for block in blocks]), sorted=True)


def _check_name(name: Any, argument: str) -> None:
    if not isinstance(name, str) or not name:
        raise ValueError(f"{argument}: names must be non-empty strings, got {name!r}")


def _as_node_sets(node_sets: Any, num_nodes: int, device: torch.device) -> dict[str, Tensor]:
    if node_sets is None:
        return {}
    if not isinstance(node_sets, Mapping):
        raise TypeError(
            f"node_sets must be a mapping of names to node indices, got {type(node_sets).__name__}"
        )
    result: dict[str, Tensor] = {}
    for key, value in node_sets.items():
        _check_name(key, "node_sets")
        indices = as_index(value, f"node_sets[{key!r}]", size=num_nodes)
        result[key] = torch.unique(indices.to(device), sorted=True)
    return result


def _as_face_sets(
    face_sets: Any, num_nodes: int, device: torch.device, dim: int
) -> dict[str, tuple[CellBlock, ...]]:
    if face_sets is None:
        return {}
    if not isinstance(face_sets, Mapping):
        raise TypeError(
            f"face_sets must be a mapping of names to facet blocks, got {type(face_sets).__name__}"
        )
    allowed = {k for k, (corners, _, _) in FACET_KINDS.items() if (corners == 2) == (dim == 2)}
    result: dict[str, tuple[CellBlock, ...]] = {}
    for key, value in face_sets.items():
        _check_name(key, "face_sets")
        argument = f"face_sets[{key!r}]"
        blocks = []
        # (kind, nodes) pairs, or meshio CellBlocks
        items: list[Any] = list(value.items()) if isinstance(value, Mapping) else list(value)
        for position, item in enumerate(items):
            kind, nodes = (item.type, item.data) if hasattr(item, "type") else item
            if kind not in allowed:
                raise ValueError(
                    f"{argument}[{position}]: facet kind {kind!r} is not a facet of a "
                    f"{dim}-D mesh; expected one of {', '.join(sorted(allowed))}"
                )
            nodes = as_index(np.asarray(nodes).reshape(-1), argument, size=num_nodes)
            width = {"line": 2, "line3": 3, "triangle": 3, "triangle6": 6, "quad": 4}
            width |= {"quad8": 8, "quad9": 9}
            blocks.append(CellBlock(kind, nodes.reshape(-1, width[kind]).to(device)))
        result[key] = tuple(blocks)
    return result


def _as_groups(groups: Any, known: set[str]) -> dict[str, tuple[str, ...]]:
    if groups is None:
        return {}
    if not isinstance(groups, Mapping):
        raise TypeError(
            f"groups must be a mapping of names to marker names, got {type(groups).__name__}"
        )
    result: dict[str, tuple[str, ...]] = {}
    for key, members in groups.items():
        _check_name(key, "groups")
        if key in known:
            raise ValueError(f"groups[{key!r}]: the name is a node or face set's already")
        members = (members,) if isinstance(members, str) else tuple(members)
        unknown = [m for m in members if m not in known and m not in groups]
        if unknown:
            raise ValueError(
                f"groups[{key!r}]: unknown member marker(s) {', '.join(map(repr, unknown))}"
            )
        result[key] = members
    return result
