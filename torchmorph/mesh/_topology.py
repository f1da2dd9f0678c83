"""Topology of a mesh of any element kinds: cell blocks checked on input, the orientation
of every cell, and the facets (faces in 3-D, edges in 2-D) matched across blocks — the
boundary is the facets used once, an interior facet is shared by exactly two cells on
opposite sides of it."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np
import torch
from torch import Tensor

from torchmorph.mesh._kernels import corner_determinants, edge_lengths_squared
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
    ``first``/``second``: for every interior facet, the global cells on its two sides
    (``first`` owns the copy whose outward normal is ``normal_nodes``'s);
    ``normal_nodes``: the corners of those copies, one (F_c, c) tensor per corner count,
    in the order of ``first``.
    """

    boundary: tuple[CellBlock, ...]
    first: Tensor
    second: Tensor
    normal_nodes: tuple[Tensor, ...]


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
            determinants = corner_determinants(exact, block.nodes, kind)
            longest = edge_lengths_squared(exact, block.nodes, kind).amax(-1).sqrt()
            bound = FLAT_CELL_TOLERANCE * longest**kind.dim
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


def _facet_copies(blocks, orientations):
    """Every facet of every cell, outward: per facet kind, (nodes (F, k), owner cells)."""
    copies: dict[str, list[tuple[Tensor, Tensor]]] = {}
    offset = 0
    for block, orientation in zip(blocks, orientations, strict=True):
        kind: CellKind = cell_kind(block.kind)
        count = block.nodes.shape[0]
        owners = torch.arange(offset, offset + count, device=block.nodes.device)
        mirrored = orientation < 0
        for facet_kind, local in kind.facets:
            nodes = block.nodes[:, list(local)]
            if bool(mirrored.any()):
                flipped = nodes[:, list(FACET_KINDS[facet_kind][1])]
                nodes = torch.where(mirrored[:, None], flipped, nodes)
            copies.setdefault(facet_kind, []).append((nodes, owners))
        offset += count
    return {
        k: (torch.cat([n for n, _ in v]), torch.cat([o for _, o in v])) for k, v in copies.items()
    }


def _sort_rows(rows: Tensor, num_nodes: int) -> tuple[Tensor, Tensor]:
    """Order of the rows (lexicographic) and, in that order, whether each row equals the
    next one."""
    width = rows.shape[1]
    if float(num_nodes) ** width < 2.0**62:
        keys = rows[:, 0].clone()
        for column in range(1, width):
            keys = keys * num_nodes + rows[:, column]
        keys, order = torch.sort(keys)
        return order, keys[1:] == keys[:-1]
    order = torch.arange(rows.shape[0], device=rows.device)
    for column in reversed(range(width)):
        order = order[torch.sort(rows[order, column], stable=True).indices]
    ordered = rows[order]
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
    or duplicated cells).
    """
    copies = _facet_copies(blocks, orientations)
    device = blocks[0].nodes.device
    by_corners: dict[int, list[tuple[str, Tensor, Tensor]]] = {}
    for facet_kind, (nodes, owners) in copies.items():
        by_corners.setdefault(FACET_KINDS[facet_kind][0], []).append((facet_kind, nodes, owners))
    boundary: dict[str, list[Tensor]] = {}
    firsts, seconds, normals = [], [], []
    for corners, groups in sorted(by_corners.items()):
        kinds = [k for k, _, _ in groups]
        corner_rows = torch.cat([n[:, :corners] for _, n, _ in groups])
        owners = torch.cat([o for _, _, o in groups])
        kind_ids = torch.cat(
            [torch.full((n.shape[0],), i, device=device) for i, (_, n, _) in enumerate(groups)]
        )
        starts = np.cumsum([0] + [n.shape[0] for _, n, _ in groups])
        order, same = _sort_rows(torch.sort(corner_rows, dim=1).values, num_nodes)
        if bool((same[1:] & same[:-1]).any()):
            count = int((same[1:] & same[:-1]).sum())
            raise ValueError(
                f"{argument}: {count} facet(s) belong to more than two cells "
                "(a non-manifold mesh or duplicated cells)"
            )
        true = torch.ones(1, dtype=torch.bool, device=device)
        single = order[torch.cat([true, ~same]) & torch.cat([~same, true])]
        for index, facet_kind in enumerate(kinds):
            rows = single[kind_ids[single] == index] - int(starts[index])
            boundary.setdefault(facet_kind, []).append(groups[index][1][rows])
        firsts.append(owners[order[:-1][same]])
        seconds.append(owners[order[1:][same]])
        normals.append(corner_rows[order[:-1][same]])
    return Facets(
        boundary=tuple(CellBlock(k, torch.cat(v)) for k, v in boundary.items()),
        first=torch.cat(firsts) if firsts else torch.empty(0, dtype=torch.long, device=device),
        second=torch.cat(seconds) if seconds else torch.empty(0, dtype=torch.long, device=device),
        normal_nodes=tuple(normals),
    )


def check_folds(
    points: Tensor, blocks: Sequence[CellBlock], facets: Facets, *, argument: str = "cells"
) -> None:
    """Raise ``ValueError`` if the two cells of an interior facet lie on the same side of it
    (a cell folded over its neighbour: an inverted reference cell that orientation alone
    cannot reveal)."""
    if facets.first.numel() == 0:
        return
    with torch.no_grad():
        exact = points.detach().to(torch.float64)
        centroids = torch.cat(
            [exact[b.nodes[:, : cell_kind(b.kind).corners]].mean(1) for b in blocks]
        )
        sides = []
        for corners in facets.normal_nodes:
            polygon = exact[corners]  # (F, c, D)
            if polygon.shape[-1] == 2:  # an edge (a, b) with the cell on its left
                edge = polygon[:, 1] - polygon[:, 0]
                normal = torch.stack([edge[:, 1], -edge[:, 0]], 1)
            else:  # Newell's normal of the polygon
                normal = torch.linalg.cross(polygon, polygon.roll(-1, 1), dim=-1).sum(1)
            sides.append((normal, polygon.mean(1)))
        normal = torch.cat([n for n, _ in sides])
        centre = torch.cat([c for _, c in sides])
        beyond = ((centroids[facets.second] - centre) * normal).sum(-1)
        folded = torch.nonzero(beyond <= 0).flatten()
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
