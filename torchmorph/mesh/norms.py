"""Error norms over a mesh of any element kinds: the mass matrix and the relative errors of
Ballarin et al. (2017, Section 2.3) in the L2(Ω) norm and in the nodal ℓ2 norm."""

from __future__ import annotations

import warnings
from typing import Literal

import torch
from torch import Tensor

from torchmorph._checks import check_choice
from torchmorph.mesh._kernels import simplex_volumes
from torchmorph.mesh.cells import cell_kind
from torchmorph.mesh.model import Mesh
from torchmorph.mesh.quality import check_field, check_mesh

__all__ = ["ERROR_NORMS", "mass_matrix", "relative_l2_error", "relative_nodal_error"]

#: Norms of :func:`relative_l2_error`: ``"mass"`` (L2(Ω) through :func:`mass_matrix`,
#: the default) and ``"nodal"`` (ℓ2 over the nodes, the paper's Ω_h = {x_i}).
ERROR_NORMS = ("mass", "nodal")


def _assemble_mass_matrix(mesh: Mesh) -> Tensor:
    """The mass matrix as a coalesced float64 sparse COO tensor (N, N)."""
    n, device = mesh.num_nodes, mesh.device
    points = mesh.points.detach().to(torch.float64)
    rows, cols, values = [], [], []
    for block, orientation in zip(mesh.cells, mesh.orientation, strict=True):
        kind = cell_kind(block.kind)
        local = torch.tensor(kind.simplices, device=device)
        simplices = block.nodes[:, local].reshape(-1, local.shape[1])
        volumes = simplex_volumes(points, simplices).reshape(block.nodes.shape[0], -1).sum(-1)
        volumes = volumes * orientation.to(torch.float64)
        if kind.is_simplex:  # consistent P1: |K| / ((D + 1)(D + 2)) (1 + δ_ij)
            corners = kind.corners
            scale = volumes / ((corners) * (corners + 1))
            nodes = block.nodes
            rows.append(nodes[:, :, None].expand(-1, corners, corners).reshape(-1))
            cols.append(nodes[:, None, :].expand(-1, corners, corners).reshape(-1))
            weights = 1.0 + torch.eye(corners, dtype=torch.float64, device=device)
            values.append((scale[:, None, None] * weights).reshape(-1))
        else:  # lumped: the cell's volume shared equally by all its nodes
            nodes = block.nodes.reshape(-1)
            rows.append(nodes)
            cols.append(nodes)
            values.append((volumes / kind.num_nodes).repeat_interleave(kind.num_nodes))
    diagonal = torch.arange(n, device=device)  # the pattern holds every diagonal entry
    indices = torch.stack([torch.cat([*rows, diagonal]), torch.cat([*cols, diagonal])])
    entries = torch.cat([*values, torch.zeros(n, dtype=torch.float64, device=device)])
    return torch.sparse_coo_tensor(indices, entries, (n, n), check_invariants=True).coalesce()


def mass_matrix(mesh: Mesh) -> Tensor:
    """Mass matrix of the reference mesh.

    Linear simplices (tetrahedra, triangles) contribute the consistent P1 matrix,
    ``M_ij = |K| (1 + δ_ij) / ((D + 1)(D + 2))`` (``|K|/20`` per edge, ``|K|/10`` on the
    diagonal for a tetrahedron), so that ``u^T M u = ∫_Ω u_h²`` for the piecewise linear
    interpolant ``u_h``. Every other kind (pyramids, wedges, hexahedra, quads and all
    quadratic kinds) contributes a lumped matrix: its volume shared equally by all of
    its nodes, mid-side and face nodes included. Either way the sum of all entries is
    the mesh volume.

    Parameters
    ----------
    mesh : Mesh
        The reference mesh.

    Returns
    -------
    Tensor, sparse COO (coalesced), shape (N, N), float64
        On the mesh's device. Cached on the mesh: later calls return the same tensor.

    Notes
    -----
    The pattern holds the diagonal and the pairs of nodes of a simplex; nodes that
    belong to no cell have a zero row.
    """
    check_mesh(mesh)
    return mesh._cached_geometry("mass_matrix", lambda: _assemble_mass_matrix(mesh), always=True)


def relative_l2_error(
    mesh: Mesh,
    d: Tensor,
    d_ref: Tensor,
    *,
    norm: Literal["mass", "nodal"] = "mass",
) -> Tensor:
    """Relative error ``||d - d_ref|| / ||d_ref||`` of a nodal vector field.

    Two norms, both "L2" in some sense, and they can differ several-fold:

    - ``norm="mass"`` (default): the L2(Ω) norm ``||u||_M² = Σ_c u_c^T M u_c`` summed over
      the D components ``c``, ``M`` the :func:`mass_matrix` of the reference mesh. Each
      node weighs as much as the volume around it, so on a graded fluid mesh the large
      far-field elements dominate.
    - ``norm="nodal"``: the plain ℓ2 norm of all ``D N`` nodal values, every node
      weighing the same (:func:`relative_nodal_error`). This is the most literal
      reading of the error "in L2(Ω_h)" of Ballarin et al. (2017, Section 2.3),
      who define Ω_h as the set of mesh nodes {x_i}.

    Parameters
    ----------
    mesh : Mesh
        The reference mesh (``M`` is built on it).
    d : Tensor, shape (N, D) or (B, N, D)
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
        of shape (N, D) / (B, N, D), or a reference with zero norm.
    """
    check_mesh(mesh)
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
    check_field(mesh, d.detach(), name="d")
    check_field(mesh, d_ref.detach(), name="d_ref")
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
            # (B, N, D) -> (N, D B): one sparse product for every field and component.
            b, dim = field.shape[0], field.shape[2]
            columns = field.permute(1, 0, 2).reshape(mesh.num_nodes, dim * b)
            product = torch.sparse.mm(matrix, columns)
            return (columns * product).sum(0).reshape(b, dim).sum(1)

        error_sq = m_norm_squared(error)
        ref_sq = m_norm_squared(ref64)

    zero = ref_sq.detach() <= 0
    if bool(zero.any()):
        where = "" if not batched else f" (batch entries {_first_indices(zero)})"
        raise ValueError(f"d_ref has zero {norm} norm{where}: the relative error is undefined")
    result = torch.sqrt(error_sq.clamp_min(0.0) / ref_sq)
    return result if batched else result[0]


def relative_nodal_error(mesh: Mesh, d: Tensor, d_ref: Tensor) -> Tensor:
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
