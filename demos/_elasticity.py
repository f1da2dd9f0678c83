"""Linear elasticity with P1 tetrahedra in torch, differentiable in the node coordinates.

The finite-element solve of demos/physics_optimisation.py (not part of the library):

- :func:`p1_gradients`: volumes and shape-function gradients of every tetrahedron from
  the (morphed) node coordinates;
- :func:`element_stiffness`: ``K_e = V_e B_eᵀ C B_e`` (Voigt strains, isotropic C);
- :class:`StiffnessPattern`: the fixed sparsity of the assembled matrix with clamped
  degrees of freedom removed, and the scatter of element entries onto it;
- :class:`SparseSolve`: ``u = K⁻¹ f`` by a sparse LU factorisation (scipy), with the
  adjoint in the backward pass: ``λ = K⁻ᵀ ū``, ``∂/∂f = λ`` and
  ``∂/∂K_ij = −λ_i u_j`` on the stored entries only (exact, one more triangular solve
  pair, no second factorisation).

Degrees of freedom are interleaved, ``3 · node + component``, as scikit-fem numbers
those of ``ElementVector(ElementTetP1())``; the tests compare the assembled matrix with
scikit-fem's ``linear_elasticity`` form entry by entry.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "SparseSolve",
    "StiffnessPattern",
    "elasticity_matrix",
    "element_stiffness",
    "lame_parameters",
    "p1_gradients",
    "require_solver",
    "strain_selection",
]

FSI_HINT = (
    "the physics demos need the 'fsi' extra (scikit-fem, with scipy): pip install 'torchmorph[fsi]'"
)


def require_solver() -> None:
    """Raise ImportError, naming the ``fsi`` extra, when scipy or scikit-fem is missing."""
    for name in ("scipy.sparse.linalg", "skfem"):
        try:
            __import__(name)
        except ImportError as error:
            raise ImportError(f"{name} is not importable ({error}); {FSI_HINT}") from error


def lame_parameters(young: float, poisson: float) -> tuple[float, float]:
    """Lamé's (λ, μ) from Young's modulus E and Poisson's ratio ν (the same as
    ``skfem.models.elasticity.lame_parameters``)."""
    if not young > 0.0:
        raise ValueError(f"young must be positive, got {young!r}")
    if not -1.0 < poisson < 0.5:
        raise ValueError(f"poisson must lie in (-1, 0.5), got {poisson!r}")
    first = young * poisson / ((1.0 + poisson) * (1.0 - 2.0 * poisson))
    shear = young / (2.0 * (1.0 + poisson))
    return first, shear


def p1_gradients(points: Tensor, tets: Tensor) -> tuple[Tensor, Tensor]:
    """Volumes and gradients of the four P1 shape functions of every tetrahedron.

    Parameters
    ----------
    points : Tensor, shape (N, 3)
        Node coordinates; both results are differentiable with respect to them.
    tets : Tensor, shape (M, 4), int64

    Returns
    -------
    volumes : Tensor, shape (M,)
        Signed volumes (positive for the mesh's orientation).
    gradients : Tensor, shape (M, 4, 3)
        ``gradients[m, a] = ∇φ_a`` on tetrahedron m, constant there.

    Notes
    -----
    With the edge matrix ``E`` (rows ``x_a − x_0``, a = 1..3), the barycentric
    coordinates are ``ξ = E⁻ᵀ (x − x_0)``, so ``∇φ_a`` is row a of ``E⁻¹ᵀ`` and
    ``∇φ_0 = −Σ_a ∇φ_a``. Inverted or flat tetrahedra give negative or infinite
    values; nothing here checks for them.
    """
    corners = points[tets]  # (M, 4, 3)
    edges = corners[:, 1:] - corners[:, :1]  # (M, 3, 3)
    volumes = torch.linalg.det(edges) / 6.0
    rest = torch.linalg.inv(edges).mT  # (M, 3, 3): ∇φ_1..3 as rows
    gradients = torch.cat([-rest.sum(1, keepdim=True), rest], 1)
    return volumes, gradients


#: Voigt strain rows (ε_xx, ε_yy, ε_zz, 2ε_yz, 2ε_xz, 2ε_xy) as ``Σ S[r, i, k] ∂_k u_i``.
VOIGT_PAIRS = ((0, 0), (1, 1), (2, 2), (1, 2), (0, 2), (0, 1))


def strain_selection(dtype: torch.dtype, device: torch.device | None = None) -> Tensor:
    """S, shape (6, 3, 3): Voigt strain row r = Σ_ik S[r, i, k] ∂_k u_i."""
    selection = torch.zeros(6, 3, 3, dtype=dtype, device=device)
    for row, (i, k) in enumerate(VOIGT_PAIRS):
        selection[row, i, k] = 1.0
        selection[row, k, i] = 1.0
    return selection


def elasticity_matrix(
    lame: tuple[float, float], dtype: torch.dtype, device: torch.device | None = None
) -> Tensor:
    """C, shape (6, 6), of isotropic linear elasticity in Voigt form (engineering shear
    strains): ``λ`` on the normal block, ``2μ`` and ``μ`` on the diagonal."""
    first, shear = lame
    matrix = torch.zeros(6, 6, dtype=dtype, device=device)
    matrix[:3, :3] = first
    diagonal = torch.tensor([2.0 * shear] * 3 + [shear] * 3, dtype=dtype, device=device)
    return matrix + torch.diag(diagonal)


def element_stiffness(points: Tensor, tets: Tensor, lame: tuple[float, float]) -> Tensor:
    """Element stiffness matrices of isotropic linear elasticity, P1 tetrahedra.

    ``K_e = |V_e| B_eᵀ C B_e``: the bilinear form ``∫ 2μ ε(u):ε(v) + λ div u div v`` on
    one tetrahedron, with B_e (6 × 12) the strain of each corner's displacement,
    ``B_e[r, 3 a + i] = Σ_k S[r, i, k] ∂_k φ_a`` (:func:`strain_selection`), and C of
    :func:`elasticity_matrix`.

    Parameters
    ----------
    points : Tensor, shape (N, 3)
    tets : Tensor, shape (M, 4)
    lame : (float, float)
        Lamé's λ and μ (:func:`lame_parameters`).

    Returns
    -------
    Tensor, shape (M, 12, 12)
        Rows and columns ``3 a + i`` (corner a, component i); differentiable in
        ``points``.
    """
    volumes, gradients = p1_gradients(points, tets)
    selection = strain_selection(points.dtype, points.device)
    strain = torch.einsum("rik,mak->mrai", selection, gradients).reshape(-1, 6, 12)
    material = elasticity_matrix(lame, points.dtype, points.device)
    return volumes.abs()[:, None, None] * (strain.mT @ (material @ strain))


@dataclass(frozen=True)
class StiffnessPattern:
    """The assembled stiffness matrix's sparsity on the free degrees of freedom.

    Built once from the connectivity; :meth:`assemble` then turns element matrices into
    the stored values (differentiably), in compressed-column order.

    Attributes
    ----------
    free_dofs : Tensor (n,)
        Global degrees of freedom ``3 · node + component`` kept (not clamped).
    row_indices, column_pointers : ndarray
        CSC structure of the n × n matrix (``scipy.sparse.csc_matrix`` arguments).
    rows, columns : Tensor (nnz,)
        Row and column of each stored value.
    element_entries, positions : Tensor (E,)
        Which entries of the flattened element matrices are kept, and where each adds.
    """

    free_dofs: Tensor
    row_indices: np.ndarray
    column_pointers: np.ndarray
    rows: Tensor
    columns: Tensor
    element_entries: Tensor
    positions: Tensor

    @property
    def size(self) -> int:
        return int(self.free_dofs.numel())

    @property
    def nnz(self) -> int:
        return int(self.rows.numel())

    @classmethod
    def of(cls, tets: Tensor, num_nodes: int, clamped_nodes: Tensor) -> StiffnessPattern:
        """Pattern of the tetrahedra ``tets`` (M, 4) with every component of
        ``clamped_nodes`` fixed to zero (their rows and columns removed)."""
        tets_np = tets.detach().cpu().numpy().astype(np.int64)
        dofs = (3 * tets_np[:, :, None] + np.arange(3)).reshape(-1, 12)  # (M, 12)
        free = np.ones(3 * num_nodes, dtype=bool)
        clamped = clamped_nodes.detach().cpu().numpy().astype(np.int64)
        free[(3 * clamped[:, None] + np.arange(3)).reshape(-1)] = False
        numbering = np.full(3 * num_nodes, -1, dtype=np.int64)
        numbering[free] = np.arange(int(free.sum()))
        size = int(free.sum())
        local = numbering[dofs]
        entry_rows = np.repeat(local, 12, axis=1).reshape(-1)  # entry (m, 12 r + c)
        entry_columns = np.tile(local, (1, 12)).reshape(-1)
        kept = (entry_rows >= 0) & (entry_columns >= 0)
        keys = entry_columns[kept] * size + entry_rows[kept]  # column-major: CSC order
        unique, positions = np.unique(keys, return_inverse=True)
        columns, rows = np.divmod(unique, size)
        pointers = np.searchsorted(columns, np.arange(size + 1))
        device = tets.device
        return cls(
            free_dofs=torch.from_numpy(np.flatnonzero(free)).to(device),
            row_indices=rows.astype(np.int32),
            column_pointers=pointers.astype(np.int32),
            rows=torch.from_numpy(rows).to(device),
            columns=torch.from_numpy(columns).to(device),
            element_entries=torch.from_numpy(np.flatnonzero(kept)).to(device),
            positions=torch.from_numpy(positions.reshape(-1)).to(device),
        )

    def assemble(self, element_matrices: Tensor) -> Tensor:
        """Stored values (nnz,) of Σ_e K_e on the free degrees of freedom."""
        entries = element_matrices.reshape(-1)[self.element_entries]
        return entries.new_zeros(self.nnz).index_add(0, self.positions, entries)

    def to_scipy(self, values: Tensor) -> Any:
        """The matrix as a ``scipy.sparse.csc_matrix`` (values detached)."""
        import scipy.sparse

        data = values.detach().cpu().numpy()
        return scipy.sparse.csc_matrix(
            (data, self.row_indices, self.column_pointers), shape=(self.size, self.size)
        )


class SparseSolve(torch.autograd.Function):
    """``u = K⁻¹ f`` for a sparse K given by its stored values on a pattern.

    ``SparseSolve.apply(values, rhs, pattern)``: values (nnz,) in the order of
    ``pattern.rows`` / ``pattern.columns``, rhs (n,); returns u (n,). Forward factorises
    K once (``scipy.sparse.linalg.splu``); backward solves the adjoint system with the
    same factors, ``Kᵀ λ = ū``, and returns ``∂/∂values = −λ[rows] u[columns]``,
    ``∂/∂rhs = λ``. First derivatives only (no double backward); CPU arrays through
    NumPy, so a CUDA input is copied to the host and back.
    """

    @staticmethod
    def forward(ctx: Any, values: Tensor, rhs: Tensor, pattern: StiffnessPattern) -> Tensor:
        from scipy.sparse.linalg import splu

        # K is symmetric positive definite: a symmetric fill-reducing order and the
        # diagonal as pivots (no row exchanges needed)
        factor = splu(
            pattern.to_scipy(values),
            permc_spec="MMD_AT_PLUS_A",
            diag_pivot_thresh=0.0,
            options={"SymmetricMode": True},
        )
        solution = factor.solve(rhs.detach().cpu().numpy())
        if not np.all(np.isfinite(solution)):
            raise FloatingPointError("the stiffness matrix is singular (the solve gave inf/NaN)")
        result = torch.from_numpy(solution).to(device=rhs.device, dtype=rhs.dtype)
        ctx.factor = factor
        ctx.pattern = pattern
        ctx.save_for_backward(result)
        return result

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, grad_solution: Tensor) -> tuple[Tensor, Tensor, None]:
        (solution,) = ctx.saved_tensors
        pattern: StiffnessPattern = ctx.pattern
        adjoint = ctx.factor.solve(grad_solution.detach().cpu().numpy(), trans="T")
        multiplier = torch.from_numpy(adjoint).to(solution)
        grad_values = -multiplier[pattern.rows] * solution[pattern.columns]
        return grad_values, multiplier, None
