"""Topology of a mesh of any element kinds: cell blocks checked on input, the orientation
of every cell, and the facets (faces in 3-D, edges in 2-D) matched across blocks — the
boundary is the facets used once, an interior facet is shared by exactly two cells on
opposite sides of it, and a quadrilateral face against two triangles (a non-conforming
interface, which would read as boundary) is an error."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np
import torch
from torch import Tensor

from torchmorph.mesh.cells import FACET_KINDS, CellKind, cell_kind

__all__ = ["CellBlock", "Facets", "as_cell_blocks", "cell_orientations", "match_facets"]

#: A cell is flat when ``|V| <= FLAT_CELL_TOLERANCE * L**D``, ``L`` its longest edge: a
#: bound relative to the cell's own size, independent of units and grading (a regular
#: tetrahedron has ``V ≈ 0.118 L³``; float64 round-off in V is about ``1e-16 L³``).
FLAT_CELL_TOLERANCE = 1e-12

_MAX_FIRST = 5  # indices shown in a message


class CellBlock(NamedTuple):
    """Cells of one kind: ``kind`` (meshio's name) and ``nodes`` (M, n), int64."""

    kind: str
    nodes: Tensor


class Facets(NamedTuple):
    """The facets of a mesh, matched.

    ``boundary``: the facets used once, by facet kind, outward, sorted by their corners;
    ``first``/``second``: for every interior facet, the global cells on its two sides;
    ``first_corners``/``second_corners``: the corners of each side's outward copy of the
    facet (in the cell's order, flipped for a mirrored cell), one (F_c, c) tensor per
    corner count, in the order of ``first`` (int32 node ids where they fit).
    """

    boundary: tuple[CellBlock, ...]
    first: Tensor
    second: Tensor
    first_corners: tuple[Tensor, ...]
    second_corners: tuple[Tensor, ...]


def _shown(indices: Tensor) -> str:
    text = ", ".join(str(int(i)) for i in indices[:_MAX_FIRST].tolist())
    return text + (", ..." if indices.numel() > _MAX_FIRST else "")


def as_cell_blocks(
    cells: Any, num_nodes: int, device: torch.device, *, argument: str = "cells"
) -> tuple[CellBlock, ...]:
    """Cell blocks from a mapping ``kind -> (M, n) array``, a sequence of ``(kind, array)``
    pairs or of meshio ``CellBlock``s; checked (known kinds, integer indices in
    ``[0, num_nodes)``, one topological dimension, at least one cell)."""
    if isinstance(cells, Mapping):
        items = list(cells.items())
    elif isinstance(cells, Sequence) and not isinstance(cells, (str, bytes)):
        items = []
        for position, item in enumerate(cells):
            if hasattr(item, "type") and hasattr(item, "data"):  # a meshio CellBlock
                items.append((item.type, item.data))
            elif isinstance(item, (tuple, list)) and len(item) == 2:
                items.append((item[0], item[1]))
            else:
                raise TypeError(
                    f"{argument}[{position}] must be a (kind, array) pair, got "
                    f"{type(item).__name__}"
                )
    else:
        raise TypeError(
            f"{argument} must be a mapping of cell kinds to arrays or a sequence of "
            f"(kind, array) pairs, got {type(cells).__name__}"
        )
    blocks = []
    for position, (name, value) in enumerate(items):
        kind = cell_kind(name, argument=f"{argument}[{position}]")
        where = f"{argument}[{position}] ({name})"
        if not isinstance(value, Tensor):
            array = np.asarray(value)
            if array.size == 0:
                array = array.astype(np.int64).reshape(0, kind.num_nodes)
            if array.dtype.kind not in "iu":
                raise ValueError(f"{where} must hold integer node indices, got dtype {array.dtype}")
            value = torch.from_numpy(np.ascontiguousarray(array.astype(np.int64)))
        if value.is_floating_point() or value.is_complex() or value.dtype == torch.bool:
            raise ValueError(f"{where} must hold integer node indices, got dtype {value.dtype}")
        if value.ndim != 2 or value.shape[1] != kind.num_nodes:
            raise ValueError(
                f"{where} must have shape (M, {kind.num_nodes}), got {tuple(value.shape)}"
            )
        value = value.to(device=device, dtype=torch.int64)
        if value.numel():
            low, high = int(value.min()), int(value.max())
            if low < 0 or high >= num_nodes:
                raise ValueError(
                    f"{where} holds node indices outside [0, {num_nodes}): min {low}, max {high}"
                )
        blocks.append(CellBlock(kind.name, value))
    dims = {cell_kind(block.kind).dim for block in blocks}
    if len(dims) > 1:
        raise ValueError(
            f"{argument}: cells of dimension 2 and 3 in one mesh ("
            + ", ".join(sorted({b.kind for b in blocks}))
            + "): a mesh holds the cells of its domain; give boundary elements as face sets"
        )
    if not blocks or sum(block.nodes.shape[0] for block in blocks) == 0:
        raise ValueError(f"{argument} is empty: at least one cell is needed")
    return tuple(blocks)


def cell_orientations(
    points: Tensor, blocks: Sequence[CellBlock], *, argument: str = "cells"
) -> tuple[Tensor, ...]:
    """The orientation of every cell (int8, +1 or -1 per block), after checking that no
    reference cell is flat and none is inverted at some corners only (corner Jacobians of
    both signs: a folded or tangled cell)."""
    result = []
    with torch.no_grad():
        exact = points.detach().to(torch.float64)
        for position, block in enumerate(blocks):
            kind = cell_kind(block.kind)
            if block.nodes.shape[0] == 0:
                result.append(torch.ones(0, dtype=torch.int8, device=block.nodes.device))
                continue
            # the corners once per cell (D columns of (M, c)), then frame by frame from them
            # (no (M, frames, D, D) temporaries); a simplex's frames all give its volume
            corners = exact[block.nodes[:, : kind.corners]].permute(2, 1, 0).contiguous()
            frames = kind.corner_frames[:1] if kind.is_simplex else kind.corner_frames
            columns, longest = [], None
            for frame in frames:
                vectors = [corners[:, k] - corners[:, frame[0]] for k in frame[1:]]
                columns.append(_determinant(vectors))
                for vector in vectors:  # the frames' edges hold the longest edge (or, for a
                    squared = vector.square().sum(0)  # simplex, one at least half as long)
                    longest = squared if longest is None else torch.maximum(longest, squared)
            determinants = torch.stack(columns, -1)
            assert longest is not None  # every kind has a frame, every frame edges
            bound = FLAT_CELL_TOLERANCE * longest ** (kind.dim / 2)
            total = determinants.sum(-1)
            flat = torch.nonzero(total.abs() <= bound * determinants.shape[-1]).flatten()
            where = f"{argument}[{position}] ({block.kind})"
            if flat.numel():
                raise ValueError(
                    f"{where}: {flat.numel()} cell(s) are flat (zero volume), at indices "
                    f"{_shown(flat)}"
                )
            sign = torch.sign(total)
            mixed = torch.nonzero(((determinants * sign[:, None]) <= bound[:, None]).any(-1))
            mixed = mixed.flatten()
            if mixed.numel():
                raise ValueError(
                    f"{where}: {mixed.numel()} reference cell(s) are inverted at some corners "
                    f"(corner Jacobians of both signs: folded or tangled cells), at indices "
                    f"{_shown(mixed)}"
                )
            result.append(sign.to(torch.int8))
    return tuple(result)


def _determinant(vectors: list[Tensor]) -> Tensor:
    """det of D vectors, each (D, M) (one row per coordinate), for D = 2 or 3."""
    if len(vectors) == 2:
        (a0, a1), (b0, b1) = vectors
        return a0 * b1 - a1 * b0
    (a0, a1, a2), (b0, b1, b2), (c0, c1, c2) = vectors
    return a0 * (b1 * c2 - b2 * c1) - a1 * (b0 * c2 - b2 * c0) + a2 * (b0 * c1 - b1 * c0)


def _facet_copies(
    blocks: Sequence[CellBlock], orientations: Sequence[Tensor], index_dtype: torch.dtype
) -> dict[str, tuple[Tensor, Tensor]]:
    """Every facet of every cell, outward: per facet kind, (nodes (F, k) of
    ``index_dtype``, owner cells)."""
    copies: dict[str, list[tuple[Tensor, Tensor]]] = {}
    offset = 0
    for block, orientation in zip(blocks, orientations, strict=True):
        kind: CellKind = cell_kind(block.kind)
        count = block.nodes.shape[0]
        owners = torch.arange(offset, offset + count, device=block.nodes.device)
        mirrored = orientation < 0
        cell_nodes = block.nodes.to(index_dtype)
        for facet_kind, local in kind.facets:
            nodes = cell_nodes[:, list(local)]
            if bool(mirrored.any()):
                flipped = nodes[:, list(FACET_KINDS[facet_kind][1])]
                nodes = torch.where(mirrored[:, None], flipped, nodes)
            copies.setdefault(facet_kind, []).append((nodes, owners))
        offset += count
    return {
        k: (torch.cat([n for n, _ in v]), torch.cat([o for _, o in v])) for k, v in copies.items()
    }


#: Compare-exchange networks that sort 2, 3 or 4 columns.
_NETWORKS = {2: ((0, 1),), 3: ((0, 1), (1, 2), (0, 1)), 4: ((0, 1), (2, 3), (0, 2), (1, 3), (1, 2))}


def _sorted_columns(rows: Tensor) -> list[Tensor]:
    """Every row's entries in ascending order, as columns (a sorting network: a few
    elementwise minima and maxima, several times faster than ``torch.sort`` along a
    short row)."""
    columns = list(rows.unbind(1))
    for a, b in _NETWORKS[len(columns)]:
        columns[a], columns[b] = (
            torch.minimum(columns[a], columns[b]),
            torch.maximum(columns[a], columns[b]),
        )
    return columns


def _sort_rows(columns: list[Tensor], num_nodes: int) -> tuple[Tensor, Tensor]:
    """Order of the sorted-corner rows (given as columns; by their first three corners, the
    smallest ones, which fix a facet of a valid mesh) and, in that order, whether each
    row equals the next one (all corners compared)."""
    width = len(columns)
    keyed = min(width, 3)
    if float(num_nodes) ** keyed < 2.0**62:
        keys = columns[0].to(torch.int64)
        for column in columns[1:keyed]:
            keys = keys * num_nodes + column
        keys, order = torch.sort(keys)
        same = keys[1:] == keys[:-1]
        for column in columns[keyed:]:
            last = column[order]
            same &= last[1:] == last[:-1]
        return order, same
    order = torch.arange(columns[0].shape[0], device=columns[0].device)
    for column in reversed(columns):
        order = order[torch.sort(column[order], stable=True).indices]
    ordered = torch.stack(columns, 1)[order]
    return order, (ordered[1:] == ordered[:-1]).all(1)


def match_facets(
    blocks: Sequence[CellBlock],
    orientations: Sequence[Tensor],
    num_nodes: int,
    *,
    argument: str = "cells",
) -> Facets:
    """Match the facets of all blocks by their corners (see :class:`Facets`).

    Raises ``ValueError`` if a facet belongs to more than two cells (a non-manifold mesh
    or duplicated cells), or if a quadrilateral face lies against two triangular faces
    (see :func:`_check_split_quads`).
    """
    # node ids in int32 where they fit: the sort's passes read half the bytes
    index_dtype = torch.int32 if num_nodes < 2**31 else torch.int64
    copies = _facet_copies(blocks, orientations, index_dtype)
    device = blocks[0].nodes.device
    by_corners: dict[int, list[tuple[str, Tensor, Tensor]]] = {}
    for facet_kind, (nodes, owners) in copies.items():
        by_corners.setdefault(FACET_KINDS[facet_kind][0], []).append((facet_kind, nodes, owners))
    boundary: dict[str, list[Tensor]] = {}
    single_corners: dict[int, tuple[Tensor, Tensor]] = {}  # boundary corners, owners
    firsts, seconds, first_corners, second_corners = [], [], [], []
    for corners, groups in sorted(by_corners.items()):
        kinds = [k for k, _, _ in groups]
        corner_rows = torch.cat([n[:, :corners] for _, n, _ in groups])
        owners = torch.cat([o for _, _, o in groups])
        kind_ids = torch.cat(
            [torch.full((n.shape[0],), i, device=device) for i, (_, n, _) in enumerate(groups)]
        )
        starts = np.cumsum([0] + [n.shape[0] for _, n, _ in groups])
        order, same = _sort_rows(_sorted_columns(corner_rows), num_nodes)
        if bool((same[1:] & same[:-1]).any()):
            count = int((same[1:] & same[:-1]).sum())
            raise ValueError(
                f"{argument}: {count} facet(s) belong to more than two cells "
                "(a non-manifold mesh or duplicated cells)"
            )
        true = torch.ones(1, dtype=torch.bool, device=device)
        single = order[torch.cat([true, ~same]) & torch.cat([~same, true])]
        single_corners[corners] = (corner_rows[single], owners[single])
        for index, facet_kind in enumerate(kinds):
            rows = single[kind_ids[single] == index] - int(starts[index])
            boundary.setdefault(facet_kind, []).append(groups[index][1][rows].long())
        first, second = order[:-1][same], order[1:][same]
        firsts.append(owners[first])
        seconds.append(owners[second])
        first_corners.append(corner_rows[first])
        second_corners.append(corner_rows[second])
    quads, triangles = single_corners.get(4), single_corners.get(3)
    if quads is not None and triangles is not None and quads[0].numel() and triangles[0].numel():
        _check_split_quads(quads, triangles, blocks, num_nodes, argument)
    return Facets(
        boundary=tuple(CellBlock(k, torch.cat(v)) for k, v in boundary.items()),
        first=torch.cat(firsts) if firsts else torch.empty(0, dtype=torch.long, device=device),
        second=torch.cat(seconds) if seconds else torch.empty(0, dtype=torch.long, device=device),
        first_corners=tuple(first_corners),
        second_corners=tuple(second_corners),
    )


#: The two triangles along each diagonal of a quad (corners in cyclic order): 0-2, 1-3.
_QUAD_HALVES = (((0, 1, 2), (0, 2, 3)), ((1, 2, 3), (1, 3, 0)))


def _check_split_quads(
    quads: tuple[Tensor, Tensor],
    triangles: tuple[Tensor, Tensor],
    blocks: Sequence[CellBlock],
    num_nodes: int,
    argument: str,
) -> None:
    """Raise ``ValueError`` if a boundary quad's two halves along one of its diagonals are
    both boundary triangles: a quadrilateral face of one cell against two triangular faces
    of its neighbours, an interface the facets cannot match (it would read as boundary).

    ``quads`` and ``triangles``: the corners (F, 4) / (F, 3) of the facets used once, in
    cyclic order, and their owner cells (global). Sorts ``4 Q + T`` rows once.
    """
    quad_corners, quad_owners = quads
    triangle_corners, triangle_owners = triangles
    count = quad_corners.shape[0]
    halves = [quad_corners[:, list(half)] for pair in _QUAD_HALVES for half in pair]
    rows = torch.cat([*halves, triangle_corners])  # (4 Q + T, 3): four halves, then triangles
    order, same = _sort_rows(_sorted_columns(rows), num_nodes)
    # runs of equal rows in sorted order: a half is a boundary triangle when its run holds one
    run = torch.cat([same.new_zeros(1, dtype=torch.long), torch.cumsum(~same, 0)])
    is_triangle = order >= 4 * count
    triangle_of_run = torch.full((rows.shape[0],), -1, dtype=torch.long, device=rows.device)
    triangle_of_run[run[is_triangle]] = order[is_triangle] - 4 * count
    matched = torch.empty(rows.shape[0], dtype=torch.long, device=rows.device)
    matched[order] = triangle_of_run[run]
    against = matched[: 4 * count].reshape(4, count)  # the triangle on each half, or -1
    split = (against >= 0).reshape(2, 2, count).all(1)  # (diagonal, quad)
    bad = torch.nonzero(split.any(0)).flatten()
    if not bad.numel():
        return
    quad = int(bad[0])
    diagonal = 0 if bool(split[0, quad]) else 1
    faces = [int(against[2 * diagonal + k, quad]) for k in range(2)]
    first_corner = quad_corners[quad, diagonal]
    nodes = quad_corners[quad].tolist()
    raise ValueError(
        f"{argument}: {bad.numel()} quadrilateral face(s) lie against two triangular faces "
        f"split along a diagonal (a non-conforming interface: it would read as boundary and "
        f"its nodes be held fixed), e.g. the quad face with corners {nodes} of "
        f"{_cell_name(int(quad_owners[quad]), blocks, argument)} against the triangles of "
        + " and ".join(_cell_name(int(triangle_owners[f]), blocks, argument) for f in faces)
        + f", split along its diagonal {int(first_corner)}-"
        f"{int(quad_corners[quad, diagonal + 2])}; insert pyramids between the quad faces and "
        "the triangles, or split the cells with quad faces along that diagonal (hexahedra "
        "into wedges or tetrahedra)"
    )


def _cell_name(cell: int, blocks: Sequence[CellBlock], argument: str) -> str:
    """``"cell 5 of cells[1] (wedge)"`` for the global cell index ``cell``."""
    for position, block in enumerate(blocks):
        if cell < block.nodes.shape[0]:
            return f"cell {cell} of {argument}[{position}] ({block.kind})"
        cell -= block.nodes.shape[0]
    raise IndexError(cell)


def check_folds(facets: Facets, *, argument: str = "cells") -> None:
    """Raise ``ValueError`` if the two cells of an interior facet lie on the same side of it
    (a cell folded over its neighbour, or an inverted reference cell that reads as a
    mirrored one: orientation alone cannot reveal either).

    Each side's copy of the facet is outward for its cell (mirrored cells' copies are
    flipped), so two cells on opposite sides list the facet's corners in opposite cyclic
    orders; the same order puts both cells on one side. A combinatorial test: no
    coordinates are read.
    """
    parts = []
    for first, second in zip(facets.first_corners, facets.second_corners, strict=True):
        if first.shape[1] == 2:  # an edge: opposite sides read it (a, b) and (b, a)
            parts.append((first[:, 0] != second[:, 1]) | (first[:, 1] != second[:, 0]))
            continue
        width = first.shape[1]
        rows = torch.arange(first.shape[0], device=first.device)
        lowest_first = first.argmin(1)
        lowest_second = second.argmin(1)
        after = first[rows, (lowest_first + 1) % width]  # the corner after the smallest
        before = second[rows, (lowest_second - 1) % width]  # the corner before it
        parts.append(after != before)
    folded = torch.nonzero(torch.cat(parts)).flatten() if parts else torch.empty(0)
    if folded.numel():
        pairs = ", ".join(
            f"({int(facets.first[k])}, {int(facets.second[k])})"
            for k in folded[:_MAX_FIRST].tolist()
        )
        more = ", ..." if folded.numel() > _MAX_FIRST else ""
        raise ValueError(
            f"{argument}: {folded.numel()} interior facet(s) have both of their cells on the "
            f"same side (inverted, folded reference cells), e.g. cells {pairs}{more}"
        )
