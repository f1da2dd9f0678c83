"""Greedy RBF reduction: the error oracle of RBF interpolation for
:func:`torchmorph.selection.greedy.greedy_selection`, with a factorisation that grows by
one bordered (Schur complement) update per added control, O(k²), and is never computed
again from scratch.

The system. With the polynomial tail, order the selected controls as the M *anchors*
(a set on which the M monomials are unisolvent, chosen once by a pivoted QR of Pᵀ) and
then the others, in the order they were added. With ``A = [[Φ₀₀, P₀], [P₀ᵀ, 0]]`` (the
anchors' 2M × 2M saddle block, factorised once by LU) and ``b(x) = [φ(x, anchors);
p(x)]``, the Schur complement of A in the saddle matrix of the selected controls is

    S_pq = φ(x_p, x_q) − b(x_p)ᵀ A⁻¹ b(x_q)

(for the anchors' polynomial reproduction, the Gram matrix of the kernel that
vanishes on the anchors), symmetric positive definite for a kernel with degree at
least its order. Its Cholesky factor L grows by a bordered update: for a new control
p, ``l = L⁻¹ S[order, p]`` and the new diagonal ``√(S_pp − lᵀl)`` (for b controls
added at once, the block form: X = L⁻¹ S[order, new] and the Cholesky factor of
``S[new, new] − XᵀX``). A prefix of the order keeps the leading block of L, so the
loop's halving prefixes cost nothing.

The solve for control values d: ``y = A⁻¹ [d₀; 0]``, ``λ_r = S⁻¹ (d_r − B_r y)``,
``[λ₀; β] = y − A⁻¹ B_rᵀ λ_r``; the interpolant at every candidate is
``b(x)ᵀ [λ₀; β] + Φ(x, rest) λ_r`` (the kernel columns of the selected controls at the
candidates are kept, one column added per control).
"""

from __future__ import annotations

import numpy as np
import scipy.linalg
import torch
from scipy.linalg.blas import dtpsv
from scipy.linalg.lapack import dpotrf
from torch import Tensor

from torchmorph._checks import as_index, as_points, check_float_dtype
from torchmorph.rbf.functional import check_distinct, check_options, dim_of
from torchmorph.rbf.kernels import (
    MIN_DEGREE,
    kernel_matrix,
    monomial_powers,
    polynomial_matrix,
    polynomial_scaling,
)

__all__ = ["BLOCK_COLUMNS", "RBFErrorOracle"]

#: Controls added at once beyond which their rows of L are found by one BLAS-3 solve on L
#: unpacked (one copy of L) rather than by packed solves per control (one pass over L
#: each): at k = 2,000 a packed solve takes about 0.6 ms and the copy 20 ms.
BLOCK_COLUMNS = 16


class RBFErrorOracle:
    """The error of RBF interpolation on a family of control fields, for
    :func:`~torchmorph.selection.greedy.greedy_selection`: "add the controls with the
    largest interpolation error", with an incrementally updated factorisation.

    Parameters
    ----------
    points : Tensor, shape (N, D)
        The candidate controls (e.g. every boundary node), pairwise distinct.
    displacements : Tensor, shape (N, D) or (F, N, D)
        The displacement fields at the candidates (a family of F fields).
    kernel, epsilon, degree, support_radius
        As :class:`~torchmorph.rbf.RBF`. The degree must be at least the kernel's order
        (:data:`~torchmorph.rbf.kernels.MIN_DEGREE`) so that the Schur complement is
        positive definite.

    Attributes
    ----------
    points : Tensor, shape (N, D)
    anchors : Tensor, shape (M,), int64
        The candidates that carry the polynomial (M monomials; none for degree -1). Pass
        ``initial=oracle.anchors`` to ``greedy_selection``: every selection must start
        with them.

    Notes
    -----
    The error of a member is ``max_i |s(x_i) − d_i| / max_i |d_i|`` over the
    candidates (Euclidean norms of the D components), the score of a candidate its
    largest relative error over the family. Computations are in float64.
    """

    def __init__(
        self,
        points: Tensor,
        displacements: Tensor,
        *,
        kernel: str = "thin_plate_spline",
        epsilon: float | None = None,
        degree: int = 1,
        support_radius: float | None = None,
    ) -> None:
        points = as_points(points, "points", dim=dim_of(points))
        count, dim = points.shape
        if not isinstance(displacements, Tensor):
            raise TypeError(
                f"displacements must be a torch.Tensor, got {type(displacements).__name__}"
            )
        check_float_dtype(displacements, "displacements")
        family = displacements[None] if displacements.ndim == 2 else displacements
        if family.ndim != 3 or family.shape[1:] != (count, dim):
            raise ValueError(
                f"displacements must have shape ({count}, {dim}) or (F, {count}, {dim}), got "
                f"{tuple(displacements.shape)}"
            )
        kernel, _, degree, _, scale = check_options(
            kernel, epsilon, degree, support_radius, count, dim
        )
        if degree < MIN_DEGREE.get(kernel, -1):
            raise ValueError(
                f"degree must be at least {MIN_DEGREE[kernel]} for kernel={kernel!r} here "
                f"(the Schur complement of a lower degree need not be positive definite), "
                f"got {degree}"
            )
        check_distinct(points)
        self.points = points
        self.kernel, self.scale = kernel, scale
        work = points.detach().double()
        self._work = work
        shift, poly_scale = polynomial_scaling(work)
        poly = polynomial_matrix(work, monomial_powers(dim, degree), shift, poly_scale)
        monomials = poly.shape[1]
        if monomials:  # the anchors: a pivoted QR of Pᵀ picks well-conditioned ones
            pivots = scipy.linalg.qr(poly.T.cpu().numpy(), pivoting=True, mode="r")[1]
            anchors = torch.from_numpy(np.sort(pivots[:monomials]).astype(np.int64))
        else:
            anchors = torch.zeros(0, dtype=torch.int64)
        self.anchors = anchors
        anchor_kernel = kernel_matrix(work, work[anchors], kernel, scale)  # (N, M)
        self._border = torch.cat([anchor_kernel, poly], dim=1)  # b(x)ᵀ, (N, 2M)
        if monomials:
            block = torch.cat(
                [
                    torch.cat([anchor_kernel[anchors], poly[anchors]], dim=1),
                    torch.cat([poly[anchors].T, poly.new_zeros(monomials, monomials)], dim=1),
                ]
            )
            self._block = torch.linalg.lu_factor(block)
            self._reduced = torch.linalg.lu_solve(*self._block, self._border.T)  # A⁻¹ b, (2M, N)
        values = family.detach().double().permute(1, 0, 2).reshape(count, -1)  # (N, F·D)
        self._values = values
        self._family, self._dim = family.shape[0], dim
        norms = family.detach().double().norm(dim=-1).amax(dim=1)  # (F,)
        self._norms = torch.where(norms > 0, norms, torch.ones_like(norms))
        self._order: list[int] = []
        self._packed = np.zeros(0)  # the rows of L, one after another
        self._columns = work.new_zeros(count, 0)  # φ(candidates, rest in order)

    # --------------------------------------------------------------- factor
    def _schur(self, rows: Tensor, columns: Tensor) -> Tensor:
        """S[rows, columns]."""
        phi = kernel_matrix(self._work[rows], self._work[columns], self.kernel, self.scale)
        if self.anchors.numel():
            phi = phi - self._border[rows] @ self._reduced[:, columns]
        return phi

    def _extend(self, candidates: list[int]) -> None:
        """The bordered (block) update of L for more controls: with C = S[order, new] and
        X = L⁻¹ C (one pass over the stored rows of L for all new controls, O(k² b)), the
        new rows are ``[Xᵀ, L_b]`` with ``L_b`` the Cholesky factor of
        ``S[new, new] − Xᵀ X``. The rows of L are stored one after another, so that the
        leading k × k block is the first k(k + 1)/2 entries."""
        size, count = len(self._order), len(candidates)
        needed = size + count
        if needed > self._columns.shape[1]:
            capacity = max(16, 2 * needed)
            packed = np.zeros(capacity * (capacity + 1) // 2)
            packed[: self._packed.size] = self._packed
            self._packed = packed
            columns = self._columns.new_zeros(self._columns.shape[0], capacity)
            columns[:, :size] = self._columns[:, :size]
            self._columns = columns
        new = torch.tensor(candidates, dtype=torch.int64)
        block = self._schur(new, new).cpu().numpy()
        rows = np.zeros((count, size))
        if size:
            border = self._schur(torch.tensor(self._order, dtype=torch.int64), new)
            rows = self._forward(border.cpu().numpy(), size)
            block = block - rows @ rows.T
        corner, info = dpotrf(np.asfortranarray(block), lower=1, clean=1)
        if info != 0:
            bad = candidates[min(int(info), count) - 1]
            raise ValueError(
                f"selected: adding candidate {bad} makes the system singular to working precision"
            )
        for offset in range(count):
            index = size + offset
            start = index * (index + 1) // 2
            self._packed[start : start + size] = rows[offset]
            self._packed[start + size : start + index + 1] = corner[offset, : offset + 1]
        self._columns[:, size:needed] = kernel_matrix(
            self._work, self._work[new], self.kernel, self.scale
        )
        self._order.extend(candidates)

    def _forward(self, border: np.ndarray, size: int) -> np.ndarray:
        """``(L⁻¹ border)ᵀ`` for the leading ``size`` rows of L, shape (b, size): a few
        columns by packed solves (BLAS ``dtpsv``, no copy of L), many by one BLAS-3
        triangular solve on L unpacked (one O(k²) copy, then cache-blocked)."""
        if border.shape[1] <= BLOCK_COLUMNS:
            return np.stack(
                [
                    dtpsv(size, self._packed, border[:, column], lower=0, trans=1)
                    for column in range(border.shape[1])
                ]
            )
        lower = self._lower(size).cpu().numpy()
        return scipy.linalg.solve_triangular(lower, border, lower=True, check_finite=False).T

    def _solve(self, values: Tensor, size: int) -> Tensor:
        """``(L Lᵀ)⁻¹ values`` for the first ``size`` controls: two packed triangular
        solves per column on the stored rows (no dense copy of L)."""
        array = values.detach().cpu().numpy()
        solution = np.empty_like(array)
        for column in range(array.shape[1]):
            forward = dtpsv(size, self._packed, array[:, column], lower=0, trans=1)
            solution[:, column] = dtpsv(size, self._packed, forward, lower=0, trans=0)
        return torch.from_numpy(solution).to(values.device)

    def _lower(self, size: int) -> Tensor:
        """L for the first ``size`` controls, as a dense (size, size) tensor."""
        rows, columns = np.tril_indices(size)
        dense = np.zeros((size, size))
        dense[rows, columns] = self._packed[: size * (size + 1) // 2]
        return torch.from_numpy(dense).to(self._work.device)

    def _sync(self, selected: Tensor) -> int:
        """Make the factor that of ``selected`` (anchors first): keep the common prefix,
        extend by bordered updates. Returns the number of non-anchor controls."""
        indices = as_index(selected, "selected", size=self.points.shape[0]).tolist()
        anchors = self.anchors.tolist()
        if sorted(indices[: len(anchors)]) != anchors:
            raise ValueError(
                f"selected must start with the oracle's {len(anchors)} anchors (pass "
                "initial=oracle.anchors to greedy_selection)"
            )
        rest = indices[len(anchors) :]
        common = 0
        while common < min(len(rest), len(self._order)) and rest[common] == self._order[common]:
            common += 1
        if common < len(rest):  # another tail: the common prefix's factor is kept
            del self._order[common:]
        # else a prefix of the stored order: the leading block of L is its factor, and the
        # longer factor stays for the loop's next, longer selection
        if common < len(rest):
            self._extend(rest[common:])
        return len(rest)

    def factor(self, selected: Tensor) -> Tensor:
        """The Cholesky factor of the Schur complement for ``selected``, shape (k, k)."""
        return self._lower(self._sync(selected))

    # --------------------------------------------------------------- values
    def interpolate(self, selected: Tensor) -> Tensor:
        """The interpolant at every candidate, shape (F, N, D), from the controls
        ``selected`` (anchors first)."""
        size = self._sync(selected)
        values = self._values
        order = torch.tensor(self._order[:size], dtype=torch.int64)
        weights = self._rest_weights(values, order, size)
        result = self._anchor_part + self._columns[:, :size] @ weights
        return result.reshape(values.shape[0], self._family, self._dim).permute(1, 0, 2)

    def _rest_weights(self, values: Tensor, order: Tensor, size: int) -> Tensor:
        """λ_r (k, S); the anchors' part ``b(x)ᵀ [λ₀; β]`` at every candidate is left in
        ``self._anchor_part`` (N, S)."""
        if not self.anchors.numel():
            self._anchor_part = values.new_zeros(values.shape)
            if not size:
                return values.new_zeros(0, values.shape[1])
            return self._solve(values[order], size)
        monomials = self.anchors.numel()
        padded = torch.cat([values[self.anchors], values.new_zeros(monomials, values.shape[1])])
        anchor_solution = torch.linalg.lu_solve(*self._block, padded)
        weights = values.new_zeros(0, values.shape[1])
        if size:
            rhs = values[order] - self._border[order] @ anchor_solution
            weights = self._solve(rhs, size)
            anchor_solution = anchor_solution - self._reduced[:, order] @ weights
        self._anchor_part = self._border @ anchor_solution
        return weights

    def _relative(self, selected: Tensor) -> Tensor:
        """Relative error of every candidate for every member, shape (F, N)."""
        size = self._sync(selected)
        order = torch.tensor(self._order[:size], dtype=torch.int64)
        weights = self._rest_weights(self._values, order, size)
        result = self._anchor_part + self._columns[:, :size] @ weights
        residual = (result - self._values).reshape(-1, self._family, self._dim)
        return residual.norm(dim=-1).T / self._norms[:, None]

    def errors(self, selected: Tensor) -> Tensor:
        """Relative error of each member, shape (F,)."""
        return self._relative(selected).amax(dim=1)

    def scores(self, selected: Tensor) -> tuple[Tensor, Tensor]:
        """``(errors (F,), scores (N,))``: a candidate's score is its largest relative
        interpolation error over the family (0 at the selected controls)."""
        relative = self._relative(selected)
        return relative.amax(dim=1), relative.amax(dim=0)
