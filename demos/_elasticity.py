"""Linear elasticity with P1 tetrahedra in torch, differentiable in the node coordinates.

The finite-element solve of demos/physics_optimisation.py (not part of the library):

- :func:`p1_gradients`: volumes and shape-function gradients of every tetrahedron from
  the (morphed) node coordinates;
- :func:`shape_gradients`: the same for P2 (straight-sided, mid-edge nodes at the
  edges' midpoints) at the points of a degree-2 quadrature;
- :func:`element_stiffness`: ``K_e = |V_e| Σ_q w_q B_qᵀ C B_q`` (Voigt strains,
  isotropic C), P1 or P2;
- :class:`LagrangeSpace`: the nodes of P1 or P2 elements (the mesh's nodes, then its
  edges), the nodes on a clamped set and those that carry a traction;
- :class:`StiffnessPattern`: the fixed sparsity of the assembled matrix with clamped
  degrees of freedom removed, and the scatter of element entries onto it;
- :class:`SparseSolve`: ``u = K⁻¹ f`` by a sparse LU factorisation (scipy), with the
  adjoint in the backward pass: ``λ = K⁻ᵀ ū``, ``∂/∂f = λ`` and
  ``∂/∂K_ij = −λ_i u_j`` on the stored entries only (exact, one more triangular solve
  pair, no second factorisation).

Degrees of freedom are interleaved, ``3 · node + component``, as scikit-fem numbers
those of ``ElementVector(ElementTetP1())``; the P2 nodes are the corners, then the
edges (``num_nodes + edge``). The tests compare the assembled matrices with scikit-fem's
``linear_elasticity`` form (P1 and P2) entry by entry.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "LagrangeSpace",
    "SparseSolve",
    "StiffnessPattern",
    "elasticity_matrix",
    "element_stiffness",
    "lame_parameters",
    "p1_gradients",
    "quadratic_cells",
    "require_solver",
    "shape_gradients",
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


#: The edges of a tetrahedron by its corners, in the order of ``TetMesh.tet_edges``; the
#: local nodes 4..9 of a quadratic tetrahedron are their midpoints, in this order.
TET_EDGE_CORNERS = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))
#: Degree-2 quadrature on a tetrahedron (exact for the P2 stiffness of a straight-sided
#: one): the barycentric points (a, b, b, b) and their permutations, each of weight 1/4.
QUADRATURE_A, QUADRATURE_B = 0.5854101966249685, 0.1381966011250105


def shape_gradients(points: Tensor, tets: Tensor, *, order: int) -> tuple[Tensor, Tensor, Tensor]:
    """Gradients of the Lagrange shape functions of degree ``order`` (1 or 2) at the
    quadrature points of every (straight-sided) tetrahedron.

    Parameters
    ----------
    points : Tensor, shape (N, 3)
        The corners' coordinates (the mid-edge nodes of P2 are the edges' midpoints).
    tets : Tensor, shape (M, 4)
    order : {1, 2}

    Returns
    -------
    volumes : Tensor, shape (M,)
    gradients : Tensor, shape (M, Q, n, 3)
        n = 4 (P1, Q = 1) or 10 (P2, Q = 4): corners first, then the mid-edge nodes in
        the order of :data:`TET_EDGE_CORNERS`.
    weights : Tensor, shape (Q,)
        Quadrature weights, summing to 1 (multiply by the volume).

    Notes
    -----
    With the barycentric coordinates λ_i (gradients ``g_i`` from :func:`p1_gradients`),
    the P2 functions are ``λ_i (2 λ_i − 1)`` at corner i, gradient ``(4 λ_i − 1) g_i``,
    and ``4 λ_i λ_j`` at edge (i, j), gradient ``4 (λ_i g_j + λ_j g_i)``.
    """
    volumes, corner_gradients = p1_gradients(points, tets)
    if order == 1:
        weights = corner_gradients.new_ones(1)
        return volumes, corner_gradients[:, None], weights
    if order != 2:
        raise ValueError(f"order must be 1 or 2, got {order!r}")
    barycentric = torch.full((4, 4), QUADRATURE_B, dtype=points.dtype, device=points.device)
    barycentric.fill_diagonal_(QUADRATURE_A)  # (Q, 4): point q, coordinate i
    corner = (4.0 * barycentric - 1.0)[None, :, :, None] * corner_gradients[:, None]
    first = [i for i, _ in TET_EDGE_CORNERS]
    second = [j for _, j in TET_EDGE_CORNERS]
    edge = 4.0 * (
        barycentric[None, :, first, None] * corner_gradients[:, None, second]
        + barycentric[None, :, second, None] * corner_gradients[:, None, first]
    )
    weights = barycentric.new_full((4,), 0.25)
    return volumes, torch.cat([corner, edge], 2), weights


def quadratic_cells(tets: Tensor, tet_edges: Tensor, num_nodes: int) -> Tensor:
    """The ten nodes of every P2 tetrahedron, shape (M, 10): the corners, then
    ``num_nodes + e`` for its edges e (``TetMesh.tet_edges``), in the order of
    :data:`TET_EDGE_CORNERS`."""
    return torch.cat([tets, num_nodes + tet_edges], 1)


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


def element_stiffness(
    points: Tensor, tets: Tensor, lame: tuple[float, float], *, order: int = 1
) -> Tensor:
    """Element stiffness matrices of isotropic linear elasticity, P1 or P2 tetrahedra.

    ``K_e = |V_e| Σ_q w_q B_qᵀ C B_q``: the bilinear form ``∫ 2μ ε(u):ε(v) + λ div u
    div v`` on one tetrahedron by the quadrature of :func:`shape_gradients` (exact: one
    point for P1, four for P2), with B_q (6 × 3n) the strain of each node's
    displacement, ``B_q[r, 3 a + i] = Σ_k S[r, i, k] ∂_k φ_a`` (:func:`strain_selection`),
    and C of :func:`elasticity_matrix`.

    Parameters
    ----------
    points : Tensor, shape (N, 3)
        The corners' coordinates.
    tets : Tensor, shape (M, 4)
    lame : (float, float)
        Lamé's λ and μ (:func:`lame_parameters`).
    order : {1, 2}
        P1 (4 nodes) or straight-sided P2 (10 nodes, :func:`quadratic_cells`).

    Returns
    -------
    Tensor, shape (M, 3n, 3n)
        Rows and columns ``3 a + i`` (local node a, component i); differentiable in
        ``points``.
    """
    volumes, gradients, weights = shape_gradients(points, tets, order=order)
    nodes = gradients.shape[2]
    selection = strain_selection(points.dtype, points.device)
    strain = torch.einsum("rik,mqak->mqrai", selection, gradients).reshape(
        *gradients.shape[:2], 6, 3 * nodes
    )
    material = elasticity_matrix(lame, points.dtype, points.device)
    weighted = weights[:, None, None] * (material @ strain)  # (M, Q, 6, 3n)
    products = (strain.mT @ weighted).sum(1)
    return volumes.abs()[:, None, None] * products


@dataclass(frozen=True)
class LagrangeSpace:
    """The nodes of P1 or P2 (straight-sided) vector Lagrange elements on a tetrahedral
    mesh: the mesh's nodes, then for P2 one node on each edge (``num_vertices + e``).

    Attributes
    ----------
    order : int
        1 or 2.
    cells : Tensor (M, 4) or (M, 10)
        The nodes of every element (:func:`quadratic_cells` for P2).
    num_nodes : int
        Nodes in all.
    num_vertices : int
        The mesh's nodes.
    edges : Tensor (E, 2)
        The mesh's edges, ``i < j``, sorted (``TetMesh.edges``).
    """

    order: int
    cells: Tensor
    num_nodes: int
    num_vertices: int
    edges: Tensor

    @classmethod
    def of(cls, mesh: Any, order: int) -> LagrangeSpace:
        """The space of degree ``order`` on the TetMesh ``mesh``."""
        if order not in (1, 2):
            raise ValueError(f"order must be 1 or 2, got {order!r}")
        vertices = mesh.num_nodes
        edges = mesh.edges
        if order == 1:
            return cls(1, mesh.tets, vertices, vertices, edges)
        cells = quadratic_cells(mesh.tets, mesh.tet_edges, vertices)
        return cls(2, cells, vertices + edges.shape[0], vertices, edges)

    def edge_numbers(self, first: Tensor, second: Tensor) -> Tensor:
        """The numbers in :attr:`edges` of the edges ``(first[k], second[k])``."""
        low, high = torch.minimum(first, second), torch.maximum(first, second)
        keys = self.edges[:, 0] * self.num_vertices + self.edges[:, 1]
        return torch.searchsorted(keys, low * self.num_vertices + high)

    def nodes_within(self, vertices: Tensor) -> Tensor:
        """The space's nodes on the closure of a vertex set: the vertices and, for P2,
        the edges whose two ends both lie in it."""
        if self.order == 1:
            return vertices
        member = torch.zeros(self.num_vertices, dtype=torch.bool, device=vertices.device)
        member[vertices] = True
        inside = torch.nonzero(member[self.edges].all(1)).flatten()
        return torch.cat([vertices, self.num_vertices + inside])

    def traction_nodes(self, faces: Tensor) -> Tensor:
        """The nodes that share a constant traction on each flat triangle ``faces``
        (F, 3), a third of the force each: its corners (P1) or its mid-edge nodes (P2;
        the corners' shares of the consistent load are zero), shape (F, 3)."""
        if self.order == 1:
            return faces
        pairs = ((0, 1), (1, 2), (0, 2))
        numbers = [self.edge_numbers(faces[:, i], faces[:, j]) for i, j in pairs]
        return self.num_vertices + torch.stack(numbers, 1)

    def skfem_numbering(self, basis: Any) -> np.ndarray:
        """scikit-fem's number of each of our degrees of freedom ``3 · node + i`` in the
        ``ElementVector`` basis of the same order on the same mesh, shape (3 n,)."""
        numbering = [basis.nodal_dofs.T]
        if self.order == 2:
            theirs = {
                tuple(edge): k for k, edge in enumerate(np.sort(basis.mesh.edges.T, 1).tolist())
            }
            rows = [theirs[tuple(edge)] for edge in self.edges.tolist()]
            numbering.append(basis.edge_dofs.T[rows])
        return np.concatenate(numbering).reshape(-1)


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
    def of(cls, cells: Tensor, num_nodes: int, clamped_nodes: Tensor) -> StiffnessPattern:
        """Pattern of the elements ``cells`` (M, n): n nodes each, 4 for P1 and 10 for
        P2 (:func:`quadratic_cells`), ``num_nodes`` in all, with every component of
        ``clamped_nodes`` fixed to zero (their rows and columns removed)."""
        cells_np = cells.detach().cpu().numpy().astype(np.int64)
        width = 3 * cells_np.shape[1]
        dofs = (3 * cells_np[:, :, None] + np.arange(3)).reshape(-1, width)  # (M, 3n)
        free = np.ones(3 * num_nodes, dtype=bool)
        clamped = clamped_nodes.detach().cpu().numpy().astype(np.int64)
        free[(3 * clamped[:, None] + np.arange(3)).reshape(-1)] = False
        numbering = np.full(3 * num_nodes, -1, dtype=np.int64)
        numbering[free] = np.arange(int(free.sum()))
        size = int(free.sum())
        local = numbering[dofs]
        entry_rows = np.repeat(local, width, axis=1).reshape(-1)  # entry (m, 3n r + c)
        entry_columns = np.tile(local, (1, width)).reshape(-1)
        kept = (entry_rows >= 0) & (entry_columns >= 0)
        keys = entry_columns[kept] * size + entry_rows[kept]  # column-major: CSC order
        unique, positions = np.unique(keys, return_inverse=True)
        columns, rows = np.divmod(unique, size)
        pointers = np.searchsorted(columns, np.arange(size + 1))
        device = cells.device
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
    """``u = K⁻¹ f`` for a sparse, symmetric positive definite K given by its stored
    values on a pattern (the factorisation pivots on the diagonal, without row exchanges).

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
