"""Mesh quality and error measures (the quality measure of Ballarin et al. 2017, Section 2.3).

Pure functions over ``points (N, 3)`` / ``tets (M, 4)`` and a few that take a
:class:`~torchmorph.mesh.TetMesh`:

- :func:`signed_volumes`, :func:`edge_ratio` — per-tetrahedron geometry;
- :func:`inverted`, :func:`count_inverted`, :func:`quality_summary` — what a
  displacement does to the mesh;
- :func:`mass_matrix`, :func:`relative_l2_error`, :func:`relative_nodal_error`
  — the relative errors of Ballarin et al. (2017, Section 2.3) in the P1
  mass-matrix norm and in the nodal ℓ2 norm;
- :func:`validity_barrier` — a smooth penalty that keeps tetrahedra from
  collapsing, for use in shape optimisation.

Every function is vectorised over the tetrahedra; the geometric ones accept a
batch of point sets ``(B, N, 3)`` and are differentiable with respect to the
points (and hence to a displacement).
"""

from __future__ import annotations

import warnings
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from torchmorph._checks import check_choice, check_finite, check_float_dtype
from torchmorph.mesh._cells import TET_EDGES, tet_edge_lengths_squared, tet_volumes  # noqa: F401
from torchmorph.mesh.model import TetMesh

__all__ = [
    "ERROR_NORMS",
    "count_inverted",
    "edge_ratio",
    "inverted",
    "mass_matrix",
    "quality_report",
    "quality_summary",
    "relative_l2_error",
    "relative_nodal_error",
    "signed_volumes",
    "validity_barrier",
]

# --------------------------------------------------------------------------- kernels

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


def _check_mesh(mesh: TetMesh) -> None:
    if not isinstance(mesh, TetMesh):
        raise TypeError(f"mesh must be a TetMesh, got {type(mesh).__name__}")


def _check_displacement(
    mesh: TetMesh, value: Tensor, *, batched: bool = True, name: str = "displacement"
) -> Tensor:
    """Validate a nodal field (N, 3) (or (B, N, 3) when ``batched``) for ``mesh``."""
    if not isinstance(value, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    n = mesh.num_nodes
    allowed = (2, 3) if batched else (2,)
    if value.ndim not in allowed or value.shape[-2:] != (n, 3):
        shapes = f"({n}, 3) or (B, {n}, 3)" if batched else f"({n}, 3)"
        raise ValueError(
            f"{name} must have shape {shapes} for a mesh of {n} nodes, got {tuple(value.shape)}"
        )
    check_float_dtype(value, name)
    if value.device != mesh.points.device:
        raise ValueError(
            f"{name} is on device {value.device} but the mesh is on {mesh.points.device}"
        )
    check_finite(value, name)
    return value


# --------------------------------------------------------------------------- geometry


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
    """Quality ``Q`` of every tetrahedron: longest edge / shortest edge (Ballarin et al. 2017, Section 2.3.1).

    ``Q >= 1``; 1 for a regular tetrahedron. The measure does not see the
    orientation: an inverted tetrahedron can have a good ``Q`` (use
    :func:`inverted`).

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
    longest = lengths_squared.amax(-1)
    shortest = lengths_squared.amin(-1)
    return torch.sqrt(longest / shortest)


# --------------------------------------------------------------------------- inversions


def _deformed_points(mesh: TetMesh, displacement: Tensor | None, *, batched: bool) -> Tensor:
    if displacement is None:
        return mesh.points
    displacement = _check_displacement(mesh, displacement, batched=batched)
    return mesh.points + displacement


def inverted(mesh: TetMesh, displacement: Tensor | None = None) -> Tensor:
    """Mask of the tetrahedra that a displacement inverts.

    A tetrahedron is inverted when its signed volume in the deformed
    configuration ``points + displacement`` is ``<= 0`` (the reference mesh is
    positively oriented, so a sign change is what is detected; flattened
    tetrahedra count as inverted).

    Parameters
    ----------
    mesh : TetMesh
        The reference mesh.
    displacement : Tensor, shape (N, 3) or (B, N, 3), optional
        Nodal displacement; None checks the mesh itself (for a mesh returned
        by :meth:`TetMesh.deformed`).

    Returns
    -------
    Tensor of bool, shape (M,) or (B, M)
    """
    _check_mesh(mesh)
    points = _deformed_points(mesh, displacement, batched=True)
    with torch.no_grad():
        return tet_volumes(points, mesh.tets) <= 0


def count_inverted(mesh: TetMesh, displacement: Tensor | None = None) -> int:
    """Number of tetrahedra whose signed volume becomes ``<= 0`` (inverted by the morph).

    Parameters
    ----------
    mesh : TetMesh
        The reference mesh.
    displacement : Tensor, shape (N, 3), optional
        Nodal displacement; None counts the inverted tetrahedra of ``mesh``
        itself. For a batch use ``inverted(mesh, d).sum(-1)``.

    Returns
    -------
    int
    """
    _check_mesh(mesh)
    points = _deformed_points(mesh, displacement, batched=False)
    with torch.no_grad():
        return int((tet_volumes(points, mesh.tets) <= 0).sum())


def quality_summary(mesh: TetMesh, displacement: Tensor | None = None) -> dict[str, float | int]:
    """Quality figures of a mesh, or of a mesh moved by a displacement.

    Parameters
    ----------
    mesh : TetMesh
        The reference mesh.
    displacement : Tensor, shape (N, 3), optional
        Nodal displacement; None summarises ``mesh`` itself.

    Returns
    -------
    dict
        ``num_tets`` (int), ``max_edge_ratio`` and ``mean_edge_ratio`` (float,
        the edge-ratio quality ``Q``), ``min_volume`` (float, smallest
        signed volume), ``min_volume_ratio`` (float, smallest deformed /
        reference volume; 1.0 without a displacement) and ``num_inverted``
        (int, tetrahedra with signed volume ``<= 0``).

    Notes
    -----
    ``Q`` is finite for inverted tetrahedra; always read it together with
    ``num_inverted``.
    """
    _check_mesh(mesh)
    points = _deformed_points(mesh, displacement, batched=False)
    with torch.no_grad():
        points = points.detach()
        volumes = tet_volumes(points, mesh.tets)
        lengths_squared = tet_edge_lengths_squared(points, mesh.tets)
        q = torch.sqrt(lengths_squared.amax(-1) / lengths_squared.amin(-1))
        ratio = volumes / mesh.volumes.detach().to(volumes.dtype)
        return {
            "num_tets": mesh.num_tets,
            "max_edge_ratio": float(q.max()),
            "mean_edge_ratio": float(q.mean()),
            "min_volume": float(volumes.min()),
            "min_volume_ratio": float(ratio.min()),
            "num_inverted": int((volumes <= 0).sum()),
        }


# --------------------------------------------------------------------------- mass matrix


def _assemble_mass_matrix(mesh: TetMesh) -> Tensor:
    """P1 mass matrix of ``mesh`` as a coalesced float64 sparse COO tensor (N, N)."""
    n = mesh.num_nodes
    tets = mesh.tets
    volumes = tet_volumes(mesh.points.detach().to(torch.float64), tets).abs()
    # M_K = |K| / 20 * (1 + delta_ij): |K|/20 on each of the six edges, |K|/10 on
    # the four diagonal entries. Sum per unique edge and per node.
    edges = mesh.edges
    off_diagonal = torch.zeros(edges.shape[0], dtype=torch.float64, device=tets.device)
    off_diagonal.index_add_(0, mesh.tet_edges.reshape(-1), (volumes / 20.0).repeat_interleave(6))
    diagonal = torch.zeros(n, dtype=torch.float64, device=tets.device)
    diagonal.index_add_(0, tets.reshape(-1), (volumes / 10.0).repeat_interleave(4))
    nodes = torch.arange(n, device=tets.device)
    rows = torch.cat([edges[:, 0], edges[:, 1], nodes])
    cols = torch.cat([edges[:, 1], edges[:, 0], nodes])
    values = torch.cat([off_diagonal, off_diagonal, diagonal])
    order = torch.argsort(rows * n + cols)
    return torch.sparse_coo_tensor(
        torch.stack([rows[order], cols[order]]),
        values[order],
        (n, n),
        is_coalesced=True,
        check_invariants=False,
    )


def mass_matrix(mesh: TetMesh) -> Tensor:
    """P1 (linear tetrahedron) mass matrix of the reference mesh.

    Element ``K`` contributes ``M_ij = |K| / 20 * (1 + δ_ij)`` for its four
    vertices ``i, j``, so that ``u^T M u = ∫_Ω u_h²`` for the piecewise linear
    interpolant ``u_h`` of nodal values ``u`` (exact for P1 fields), and the
    sum of all entries is the mesh volume.

    Parameters
    ----------
    mesh : TetMesh
        The reference mesh.

    Returns
    -------
    Tensor, sparse COO (coalesced), shape (N, N), float64
        On the mesh's device. Cached on the mesh: later calls return the same
        tensor.

    Notes
    -----
    The pattern holds the diagonal and the mesh edges (both directions); nodes
    that belong to no tetrahedron have a zero row.
    """
    _check_mesh(mesh)
    # Cached with the mesh's geometric quantities (the cache belongs to TetMesh).
    return mesh._cached_geometry("mass_matrix", lambda: _assemble_mass_matrix(mesh), always=True)


#: Norms of :func:`relative_l2_error`: ``"mass"`` (L2(Ω) of the P1 interpolant,
#: the default) and ``"nodal"`` (ℓ2 over the nodes, the paper's Ω_h = {x_i}).
ERROR_NORMS = ("mass", "nodal")


def relative_l2_error(
    mesh: TetMesh,
    d: Tensor,
    d_ref: Tensor,
    *,
    norm: Literal["mass", "nodal"] = "mass",
) -> Tensor:
    """Relative error ``||d - d_ref|| / ||d_ref||`` of a nodal vector field.

    Two norms, both "L2" in some sense, and they can differ several-fold:

    - ``norm="mass"`` (default): the L2(Ω) norm of the piecewise-linear (P1)
      interpolant, ``||u||_M² = Σ_c u_c^T M u_c`` summed over the three
      components ``c``, ``M`` the :func:`mass_matrix` of the reference mesh.
      Each node weighs as much as the volume around it, so on a graded fluid
      mesh the large far-field elements dominate.
    - ``norm="nodal"``: the plain ℓ2 norm of all ``3N`` nodal values, every node
      weighing the same (:func:`relative_nodal_error`). This is the most literal
      reading of the error "in L2(Ω_h)" of Ballarin et al. (2017, Section 2.3),
      who define Ω_h as the set of mesh nodes {x_i}.

    Parameters
    ----------
    mesh : TetMesh
        The reference mesh (``M`` is built on it).
    d : Tensor, shape (N, 3) or (B, N, 3)
        Approximate displacement field(s).
    d_ref : Tensor, same shape as ``d``
        Reference field(s).
    norm : {"mass", "nodal"}, keyword-only
        Which norm (see above). ``"l2"``, the old spelling of ``"mass"``, still
        works but warns (DeprecationWarning).

    Returns
    -------
    Tensor, shape () or (B,), float64
        Differentiable with respect to ``d`` and ``d_ref``.

    Raises
    ------
    ValueError
        For an unknown ``norm``, ``d`` and ``d_ref`` of different shapes or not
        of shape (N, 3) / (B, N, 3), or a reference with zero norm.
    """
    _check_mesh(mesh)
    if norm == "l2":
        warnings.warn(
            "relative_l2_error(norm='l2') is deprecated: the mass-matrix norm is "
            "norm='mass' (the default); the nodal norm is norm='nodal'",
            DeprecationWarning,
            stacklevel=2,
        )
        norm = "mass"
    check_choice(norm, "norm", ERROR_NORMS)
    for value, name in ((d, "d"), (d_ref, "d_ref")):
        if not isinstance(value, Tensor):
            raise TypeError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    if d.shape != d_ref.shape:
        raise ValueError(
            f"d and d_ref must have the same shape, got {tuple(d.shape)} and {tuple(d_ref.shape)}"
        )
    _check_displacement(mesh, d.detach(), name="d")
    _check_displacement(mesh, d_ref.detach(), name="d_ref")
    batched = d.ndim == 3
    d64 = d.to(torch.float64)
    ref64 = d_ref.to(torch.float64)
    if not batched:
        d64, ref64 = d64[None], ref64[None]
    error = d64 - ref64

    if norm == "nodal":
        error_sq = (error * error).sum(dim=(1, 2))
        ref_sq = (ref64 * ref64).sum(dim=(1, 2))
    else:
        matrix = mass_matrix(mesh)

        def m_norm_squared(field: Tensor) -> Tensor:
            # (B, N, 3) -> (N, 3B): one sparse product for every field and component.
            b = field.shape[0]
            columns = field.permute(1, 0, 2).reshape(mesh.num_nodes, 3 * b)
            product = torch.sparse.mm(matrix, columns)
            return (columns * product).sum(0).reshape(b, 3).sum(1)

        error_sq = m_norm_squared(error)
        ref_sq = m_norm_squared(ref64)

    zero = ref_sq.detach() <= 0
    if bool(zero.any()):
        where = "" if not batched else f" (batch entries {_first_indices(zero)})"
        raise ValueError(f"d_ref has zero {norm} norm{where}: the relative error is undefined")
    result = torch.sqrt(error_sq.clamp_min(0.0) / ref_sq)
    return result if batched else result[0]


def relative_nodal_error(mesh: TetMesh, d: Tensor, d_ref: Tensor) -> Tensor:
    """Relative error in the nodal ℓ2 norm, every node weighing the same.

    ``sqrt(Σ_i |d_i - d_ref,i|² / Σ_i |d_ref,i|²)`` over all nodes: the error
    "in L2(Ω_h)", Ω_h = {x_i}, of Ballarin et al. (2017, Section 2.3) read
    literally. Same as ``relative_l2_error(mesh, d, d_ref, norm="nodal")``;
    shapes, dtype and errors as :func:`relative_l2_error`.
    """
    return relative_l2_error(mesh, d, d_ref, norm="nodal")


def _first_indices(mask: Tensor, limit: int = 5) -> str:
    indices = torch.nonzero(mask).flatten().tolist()
    text = ", ".join(str(i) for i in indices[:limit])
    return text + (", ..." if len(indices) > limit else "")


# --------------------------------------------------------------------------- barrier


def validity_barrier(
    mesh: TetMesh,
    displacement: Tensor,
    *,
    threshold: float = 0.1,
    reduction: Literal["sum", "mean", "none"] = "sum",
) -> Tensor:
    """Smooth penalty on tetrahedra that shrink towards inversion.

    With ``r = V_deformed / V_reference`` the volume ratio of a tetrahedron,
    the penalty is

        φ(r) = ((threshold - r) / threshold)²   if r < threshold,
        φ(r) = 0                                otherwise.

    ``φ`` is C¹ (value and slope vanish at ``r = threshold``), equals 1 for a
    flattened tetrahedron (``r = 0``) and keeps growing, finitely, for
    inverted ones (``r < 0``), so a gradient-based optimiser that has inverted
    tetrahedra is pushed back rather than stopped by an infinite barrier (a
    ``-log r`` barrier would be undefined there). Summed over the mesh it
    reads roughly as "number of collapsed tetrahedra".

    Parameters
    ----------
    mesh : TetMesh
        The reference mesh (volumes > 0).
    displacement : Tensor, shape (N, 3) or (B, N, 3)
        Nodal displacement; the penalty is differentiable with respect to it.
    threshold : float, keyword-only
        Volume ratio in (0, 1] below which the penalty starts.
    reduction : {"sum", "mean", "none"}, keyword-only
        Sum or mean over the tetrahedra, or the per-tetrahedron values.

    Returns
    -------
    Tensor, shape () / (B,) for "sum" and "mean", (M,) / (B, M) for "none"

    Notes
    -----
    The penalty is a smooth surrogate, not a count: it is positive for
    tetrahedra that are valid but shrunk below ``threshold`` and does not say
    how many are inverted. The exact number is :func:`count_inverted`.
    """
    _check_mesh(mesh)
    threshold = float(threshold)
    if not np.isfinite(threshold) or not 0.0 < threshold <= 1.0:
        raise ValueError(f"threshold must lie in (0, 1], got {threshold!r}")
    check_choice(reduction, "reduction", ("sum", "mean", "none"))
    displacement = _check_displacement(mesh, displacement, batched=True)
    volumes = tet_volumes(mesh.points + displacement, mesh.tets)
    ratio = volumes / mesh.volumes.detach().to(volumes.dtype)
    shortfall = torch.clamp(threshold - ratio, min=0.0) / threshold
    penalty = shortfall * shortfall
    if reduction == "sum":
        return penalty.sum(-1)
    if reduction == "mean":
        return penalty.mean(-1)
    return penalty


def quality_report(mesh: TetMesh) -> str:
    """One line: the quality Q (max/mean edge ratio), the smallest volume, inverted tets."""
    summary = quality_summary(mesh)
    return (
        f"quality Q max {summary['max_edge_ratio']:.4g}, mean {summary['mean_edge_ratio']:.4g}"
        f" (edge ratio, 1 is best); min volume {summary['min_volume']:.4g}; inverted "
        f"{summary['num_inverted']}"
    )
