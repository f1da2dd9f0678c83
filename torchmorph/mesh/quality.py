"""Mesh quality and validity for every element kind (the quality measure of Ballarin et
al. 2017, Section 2.3, and the standard measures of non-simplicial cells).

Per cell, for a :class:`~torchmorph.mesh.Mesh` of any kinds, optionally moved by a
displacement (N, D) or a batch (B, N, D):

- :func:`cell_volumes` — signed volume (area in 2-D) from the kind's fixed
  decomposition into simplices, times the cell's orientation (positive when valid);
- :func:`scaled_jacobian` — the smallest scaled Jacobian over the corners (1 for the
  ideal element, <= 0 at an inverted corner), the standard measure for non-simplices;
- :func:`cell_edge_ratio` — longest / shortest corner edge (the paper's Q for
  tetrahedra);
- :func:`inverted`, :func:`count_inverted` — a cell is inverted when a corner Jacobian
  or its volume is <= 0 (for a simplex both say: signed volume <= 0);
- :func:`quality_summary`, :func:`quality_by_kind`, :func:`quality_report`;
- :func:`validity_barrier` — a smooth penalty that keeps the simplices of every cell from
  collapsing, for shape optimisation.

The tetrahedron kernels :func:`signed_volumes` and :func:`edge_ratio` take ``points
(N, 3)`` and ``tets (M, 4)`` directly. Quadratic cells are measured on their corners:
a mid-side node moved so far that the curved element folds is not detected. The error
norms (mass matrix, relative errors) are in :mod:`torchmorph.mesh.norms`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from torchmorph._checks import check_choice, check_finite, check_float_dtype
from torchmorph.mesh._kernels import (
    corner_determinants,
    edge_lengths_squared,
    scaled_corner_jacobians,
    simplex_volumes,
    tet_edge_lengths_squared,
    tet_volumes,
)
from torchmorph.mesh.cells import cell_kind
from torchmorph.mesh.model import CellBlock, Mesh

__all__ = [
    "cell_edge_ratio",
    "cell_volumes",
    "count_inverted",
    "edge_ratio",
    "inverted",
    "inverted_cells",
    "quality_by_kind",
    "quality_report",
    "quality_summary",
    "scaled_jacobian",
    "signed_volumes",
    "validity_barrier",
]

# --------------------------------------------------------------------------- checks


def _check_geometry(points: Tensor, tets: Tensor) -> tuple[Tensor, Tensor]:
    """Validate ``points (..., N, 3)`` and ``tets (M, 4)`` for the kernels."""
    if not isinstance(points, Tensor):
        raise TypeError(f"points must be a torch.Tensor, got {type(points).__name__}")
    if not isinstance(tets, Tensor):
        raise TypeError(f"tets must be a torch.Tensor, got {type(tets).__name__}")
    if points.ndim < 2 or points.shape[-1] != 3:
        raise ValueError(f"points must have shape (N, 3) or (B, N, 3), got {tuple(points.shape)}")
    check_float_dtype(points, "points")
    if tets.ndim != 2 or tets.shape[1] != 4:
        raise ValueError(f"tets must have shape (M, 4), got {tuple(tets.shape)}")
    if tets.is_floating_point() or tets.dtype == torch.bool or tets.is_complex():
        raise ValueError(f"tets must hold integer vertex indices, got dtype {tets.dtype}")
    tets = tets.to(device=points.device, dtype=torch.int64)
    num_nodes = points.shape[-2]
    if tets.numel() > 0:
        low, high = int(tets.min()), int(tets.max())
        if low < 0 or high >= num_nodes:
            raise ValueError(
                f"tets holds vertex indices outside [0, {num_nodes}): min {low}, max {high}"
            )
    return points, tets


def check_mesh(mesh: Mesh) -> None:
    if not isinstance(mesh, Mesh):
        raise TypeError(f"mesh must be a torchmorph Mesh, got {type(mesh).__name__}")


def check_field(
    mesh: Mesh, value: Tensor, *, batched: bool = True, name: str = "displacement"
) -> Tensor:
    """Validate a nodal field (N, D) (or (B, N, D) when ``batched``) for ``mesh``."""
    if not isinstance(value, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    n, dim = mesh.num_nodes, mesh.dim
    allowed = (2, 3) if batched else (2,)
    if value.ndim not in allowed or value.shape[-2:] != (n, dim):
        shapes = f"({n}, {dim}) or (B, {n}, {dim})" if batched else f"({n}, {dim})"
        raise ValueError(
            f"{name} must have shape {shapes} for a mesh of {n} nodes in {dim}-D, got "
            f"{tuple(value.shape)}"
        )
    check_float_dtype(value, name)
    if value.device != mesh.points.device:
        raise ValueError(
            f"{name} is on device {value.device} but the mesh is on {mesh.points.device}"
        )
    check_finite(value, name)
    return value


def _points(mesh: Mesh, displacement: Tensor | None, *, batched: bool = True) -> Tensor:
    check_mesh(mesh)
    if displacement is None:
        return mesh.points
    return mesh.points + check_field(mesh, displacement, batched=batched)


# --------------------------------------------------------------------------- tetrahedra


def signed_volumes(points: Tensor, tets: Tensor) -> Tensor:
    """Signed volume of every tetrahedron.

    ``V = det(b - a, c - a, d - a) / 6`` for a tetrahedron ``(a, b, c, d)``:
    positive when ``d`` lies on the side of ``(b - a) x (c - a)``.

    Parameters
    ----------
    points : Tensor, shape (N, 3) or (B, N, 3)
        Node coordinates (a batch of deformed configurations is allowed).
    tets : Tensor, shape (M, 4), integer
        Vertex indices of the tetrahedra.

    Returns
    -------
    Tensor, shape (M,) or (B, M)
        Signed volumes in the dtype of ``points``; differentiable with respect
        to ``points``.

    Raises
    ------
    ValueError
        For wrong shapes or dtypes, or indices outside ``[0, N)``.
    """
    points, tets = _check_geometry(points, tets)
    return tet_volumes(points, tets)


def edge_ratio(points: Tensor, tets: Tensor) -> Tensor:
    """Quality ``Q`` of every tetrahedron: longest edge / shortest edge (Ballarin et al.
    2017, Section 2.3.1).

    ``Q >= 1``; 1 for a regular tetrahedron. The measure does not see the
    orientation: an inverted tetrahedron can have a good ``Q`` (use
    :func:`inverted`). For cells of any kind: :func:`cell_edge_ratio`.

    Parameters
    ----------
    points : Tensor, shape (N, 3) or (B, N, 3)
        Node coordinates.
    tets : Tensor, shape (M, 4), integer
        Vertex indices of the tetrahedra.

    Returns
    -------
    Tensor, shape (M,) or (B, M)
        Edge ratios; ``inf`` for a tetrahedron with a zero-length edge.
    """
    points, tets = _check_geometry(points, tets)
    lengths_squared = tet_edge_lengths_squared(points, tets)
    return torch.sqrt(lengths_squared.amax(-1) / lengths_squared.amin(-1))


# --------------------------------------------------------------------------- any kind


def _per_block(function, points: Tensor, blocks: Sequence[CellBlock], orientations) -> Tensor:
    parts = [
        function(points, block.nodes, cell_kind(block.kind), orientation)
        for block, orientation in zip(blocks, orientations, strict=True)
    ]
    return torch.cat(parts, dim=-1)


def _oriented_volumes(points, nodes, kind, orientation) -> Tensor:
    local = torch.tensor(kind.simplices, device=nodes.device)
    volumes = simplex_volumes(points, nodes[:, local].reshape(-1, local.shape[1]))
    volumes = volumes.unflatten(-1, (nodes.shape[0], local.shape[0])).sum(-1)
    return volumes * orientation.to(volumes.dtype)


def _min_scaled_jacobian(points, nodes, kind, orientation) -> Tensor:
    jacobians = scaled_corner_jacobians(points, nodes, kind)
    return (jacobians * orientation[:, None]).amin(-1)


def _edge_ratio(points, nodes, kind, orientation) -> Tensor:
    lengths = edge_lengths_squared(points, nodes, kind)
    return torch.sqrt(lengths.amax(-1) / lengths.amin(-1))


def inverted_cells(points: Tensor, blocks: Sequence[CellBlock], orientations) -> Tensor:
    """Mask of inverted cells (a corner Jacobian or the volume <= 0 after orientation) for
    raw cell blocks; points (..., N, D) -> (..., M). :func:`inverted` takes a mesh."""

    def inverted_block(points, nodes, kind, orientation):
        determinants = corner_determinants(points, nodes, kind) * orientation[:, None]
        bad = (determinants <= 0).any(-1)
        if not kind.is_simplex:
            bad = bad | (_oriented_volumes(points, nodes, kind, orientation) <= 0)
        return bad

    with torch.no_grad():
        return _per_block(inverted_block, points.detach(), blocks, orientations)


def cell_volumes(mesh: Mesh, displacement: Tensor | None = None) -> Tensor:
    """Volume (area in 2-D) of every cell, from its kind's simplices, positive for a valid
    cell whatever its node order; cells numbered across blocks in order.

    Parameters
    ----------
    mesh : Mesh
    displacement : Tensor, shape (N, D) or (B, N, D), optional

    Returns
    -------
    Tensor, shape (M,) or (B, M); differentiable with respect to ``displacement``.
    """
    points = _points(mesh, displacement)
    return _per_block(_oriented_volumes, points, mesh.cells, mesh.orientation)


def scaled_jacobian(mesh: Mesh, displacement: Tensor | None = None) -> Tensor:
    """Smallest scaled Jacobian over the corners of every cell (Knupp): the corner
    determinant over the product of its edge lengths, scaled so that the ideal element
    has 1; <= 0 where a corner is inverted. Shape (M,) or (B, M)."""
    points = _points(mesh, displacement)
    return _per_block(_min_scaled_jacobian, points, mesh.cells, mesh.orientation)


def cell_edge_ratio(mesh: Mesh, displacement: Tensor | None = None) -> Tensor:
    """Longest / shortest corner edge of every cell (the paper's Q for tetrahedra); shape
    (M,) or (B, M). Blind to orientation: read it with :func:`inverted`."""
    points = _points(mesh, displacement)
    return _per_block(_edge_ratio, points, mesh.cells, mesh.orientation)


def inverted(mesh: Mesh, displacement: Tensor | None = None) -> Tensor:
    """Mask of the cells that a displacement inverts (or, without one, that ``mesh`` —
    e.g. from :meth:`Mesh.deformed` — holds).

    A cell is inverted when a corner Jacobian (after the cell's orientation) or its
    volume is <= 0; for a tetrahedron, when its signed volume is <= 0.

    Parameters
    ----------
    mesh : Mesh
    displacement : Tensor, shape (N, D) or (B, N, D), optional

    Returns
    -------
    Tensor of bool, shape (M,) or (B, M)
    """
    return inverted_cells(_points(mesh, displacement), mesh.cells, mesh.orientation)


def count_inverted(mesh: Mesh, displacement: Tensor | None = None) -> int:
    """Number of inverted cells (:func:`inverted`) for one displacement (N, D), or of
    ``mesh`` itself; for a batch use ``inverted(mesh, d).sum(-1)``."""
    points = _points(mesh, displacement, batched=False)
    return int(inverted_cells(points, mesh.cells, mesh.orientation).sum())


def _summary(points, reference, blocks, orientations, count_key: str) -> dict[str, float | int]:
    with torch.no_grad():
        volumes = _per_block(_oriented_volumes, points, blocks, orientations)
        ratio = volumes / _per_block(_oriented_volumes, reference, blocks, orientations)
        q = _per_block(_edge_ratio, points, blocks, orientations)
        jacobian = _per_block(_min_scaled_jacobian, points, blocks, orientations)
        bad = inverted_cells(points, blocks, orientations)
        return {
            count_key: int(volumes.shape[-1]),
            "max_edge_ratio": float(q.max()),
            "mean_edge_ratio": float(q.mean()),
            "min_scaled_jacobian": float(jacobian.min()),
            "min_volume": float(volumes.min()),
            "min_volume_ratio": float(ratio.min()),
            "num_inverted": int(bad.sum()),
        }


def quality_summary(mesh: Mesh, displacement: Tensor | None = None) -> dict[str, float | int]:
    """Quality figures of a mesh, or of a mesh moved by a displacement (N, D).

    Returns
    -------
    dict
        ``num_cells`` (``num_tets`` for a tetrahedral mesh), ``max_edge_ratio`` and
        ``mean_edge_ratio`` (Q), ``min_scaled_jacobian``, ``min_volume`` (smallest
        oriented volume), ``min_volume_ratio`` (smallest moved / reference volume; 1.0
        without a displacement) and ``num_inverted``.

    Notes
    -----
    ``Q`` is finite for inverted cells; always read it together with ``num_inverted``.
    """
    points = _points(mesh, displacement, batched=False).detach()
    key = "num_tets" if mesh.is_tetrahedral else "num_cells"
    return _summary(points, mesh.points.detach(), mesh.cells, mesh.orientation, key)


def quality_by_kind(
    mesh: Mesh, displacement: Tensor | None = None
) -> dict[str, dict[str, float | int]]:
    """:func:`quality_summary` for each cell kind of the mesh (blocks of one kind together),
    with ``num_cells`` as the count."""
    points = _points(mesh, displacement, batched=False).detach()
    reference = mesh.points.detach()
    result = {}
    for kind in mesh.cell_counts:
        chosen = [
            (block, orientation)
            for block, orientation in zip(mesh.cells, mesh.orientation, strict=True)
            if block.kind == kind
        ]
        blocks, orientations = zip(*chosen, strict=True)
        result[kind] = _summary(points, reference, blocks, orientations, "num_cells")
    return result


def quality_report(mesh: Mesh) -> str:
    """One line: the cells by kind, Q (max/mean edge ratio), the smallest scaled Jacobian
    and volume, the inverted cells."""
    summary = quality_summary(mesh)
    kinds = ", ".join(f"{count} {kind}" for kind, count in mesh.cell_counts.items())
    return (
        f"{kinds}; quality Q max {summary['max_edge_ratio']:.4g}, mean "
        f"{summary['mean_edge_ratio']:.4g} (edge ratio, 1 is best); min scaled Jacobian "
        f"{summary['min_scaled_jacobian']:.4g}; min volume {summary['min_volume']:.4g}; "
        f"inverted {summary['num_inverted']}"
    )


# --------------------------------------------------------------------------- barrier


def validity_barrier(
    mesh: Mesh,
    displacement: Tensor,
    *,
    threshold: float = 0.1,
    reduction: Literal["sum", "mean", "none"] = "sum",
) -> Tensor:
    """Smooth penalty on cells that shrink towards inversion.

    With ``r = V_deformed / V_reference`` the volume ratio of every simplex of the cells'
    fixed decomposition (the tetrahedra themselves for a tetrahedral mesh), the penalty
    is

        φ(r) = ((threshold - r) / threshold)²   if r < threshold,
        φ(r) = 0                                otherwise,

    summed over the simplices of each cell. ``φ`` is C¹ (value and slope vanish at
    ``r = threshold``), equals 1 for a flattened simplex (``r = 0``) and keeps growing,
    finitely, for inverted ones (``r < 0``), so a gradient-based optimiser that has
    inverted cells is pushed back rather than stopped by an infinite barrier (a
    ``-log r`` barrier would be undefined there).

    Parameters
    ----------
    mesh : Mesh
        The reference mesh.
    displacement : Tensor, shape (N, D) or (B, N, D)
        Nodal displacement; the penalty is differentiable with respect to it.
    threshold : float, keyword-only
        Volume ratio in (0, 1] below which the penalty starts.
    reduction : {"sum", "mean", "none"}, keyword-only
        Sum or mean over the cells, or the per-cell values.

    Returns
    -------
    Tensor, shape () / (B,) for "sum" and "mean", (M,) / (B, M) for "none"

    Notes
    -----
    A smooth surrogate, not a count: it is positive for cells that are valid but shrunk
    below ``threshold``. The exact number of inverted cells is :func:`count_inverted`.
    """
    check_mesh(mesh)
    threshold = float(threshold)
    if not np.isfinite(threshold) or not 0.0 < threshold <= 1.0:
        raise ValueError(f"threshold must lie in (0, 1], got {threshold!r}")
    check_choice(reduction, "reduction", ("sum", "mean", "none"))
    displacement = check_field(mesh, displacement, batched=True)
    simplices, owners = mesh.simplices
    volumes = simplex_volumes(mesh.points + displacement, simplices)
    reference = simplex_volumes(mesh.points.detach(), simplices).to(volumes.dtype)
    shortfall = torch.clamp(threshold - volumes / reference, min=0.0) / threshold
    penalty = shortfall * shortfall
    per_cell = penalty.new_zeros(*penalty.shape[:-1], mesh.num_cells).index_add(-1, owners, penalty)
    if reduction == "sum":
        return per_cell.sum(-1)
    if reduction == "mean":
        return per_cell.mean(-1)
    return per_cell
