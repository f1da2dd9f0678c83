"""The RBF interpolation system: its factorisation (once per geometry) and its solves
(once per set of control values).

The interpolant is ``s(x) = Σ_k λ_k φ(|x − x_k|) + p(x)·β`` with, at the N controls,

    [Φ  P] [λ]   [d]
    [Pᵀ 0] [β] = [0]

(Φ the N × N kernel matrix, P the N × M monomials). Two factorisations:

``"cholesky"`` (the null-space method, when the polynomial degree is at least the kernel's
order, :data:`~torchmorph.rbf.kernels.MIN_DEGREE`): P = Q R (Householder), Z the last
N − M columns of Q; λ = Z γ with (Zᵀ Φ Z) γ = Zᵀ d, a symmetric positive definite
system (Wendland, *Scattered Data Approximation*, Thm. 8.21) factorised by Cholesky in
about half the time of an LU of the saddle matrix; then R β = Q₁ᵀ (d − Φ λ), with
``Q₁ᵀ Φ λ`` read from the stored block ``(Qᵀ Φ Q)[:M, M:] γ``.

``"lu"`` otherwise (or when Cholesky finds the projected matrix not positive definite
in floating point): an LU of the whole saddle matrix, as scipy's ``dgesv``.

Both are computed in float64 whatever the points' dtype.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.linalg.blas import dsymm, dsyr2k
from scipy.linalg.lapack import dpotrf, dpotrs
from torch import Tensor

from torchmorph.rbf.kernels import (
    MIN_DEGREE,
    kernel_matrix,
    kernel_matrix_upper,
    polynomial_matrix,
)

__all__ = ["FACTOR_NAMES", "KINDS", "factorise", "saddle_matrix", "solve"]

#: The buffers a factorisation is stored in (empty where its kind does not use them).
FACTOR_NAMES = ("qr", "tau", "factor", "coupling", "pivots")

#: The kinds of factorisation, in the order a module stores their index in.
KINDS = ("cholesky", "lu")


def saddle_matrix(
    controls: Tensor, kernel: str, scale: float, powers, shift: Tensor, poly_scale: Tensor
) -> Tensor:
    """The (N + M) × (N + M) matrix [[Φ, P], [Pᵀ, 0]] (differentiable in ``controls``)."""
    phi = kernel_matrix(controls, controls, kernel, scale)
    poly = polynomial_matrix(controls, powers, shift, poly_scale)
    count = poly.shape[1]
    lower = torch.cat([poly.T, poly.new_zeros(count, count)], dim=1)
    return torch.cat([torch.cat([phi, poly], dim=1), lower], dim=0)


def check_polynomial_rank(poly: Tensor, degree: int) -> tuple[Tensor, Tensor]:
    """Householder QR of the monomial matrix; ``ValueError`` naming ``controls`` when it
    does not have full column rank (the controls lie on a line or plane that the
    polynomial cannot be fitted on)."""
    qr, tau = torch.geqrf(poly)
    diagonal = torch.diagonal(qr[: poly.shape[1]]).abs()
    size = poly.shape[1]
    tolerance = max(poly.shape) * torch.finfo(poly.dtype).eps * float(diagonal.max())
    rank = int((diagonal > tolerance).sum())
    if rank < size:
        raise ValueError(
            f"controls: the monomials of degree={degree} at the controls have rank {rank} of "
            f"{size} (the controls lie on a lower-dimensional set); the system is singular, "
            "use a lower degree or controls that span the space"
        )
    return qr, tau


def block_reflector(qr: Tensor, tau: Tensor) -> tuple[Tensor, Tensor]:
    """``Q = H_1 … H_k = I − V T Vᵀ`` (LAPACK's ``dlarft``, forward and columnwise):
    V (N, k) unit lower trapezoidal from ``torch.geqrf``'s result, T (k, k) upper."""
    count = tau.shape[0]
    vectors = torch.tril(qr[:, :count], diagonal=-1)
    vectors.diagonal().fill_(1.0)
    triangle = qr.new_zeros(count, count)
    for column in range(count):
        triangle[column, column] = tau[column]
        if column:
            overlap = vectors[:, :column].T @ vectors[:, column]
            triangle[:column, column] = -tau[column] * (triangle[:column, :column] @ overlap)
    return vectors, triangle


def projected_blocks(
    controls: Tensor, kernel: str, scale: float, qr: Tensor, tau: Tensor
) -> tuple[Tensor, Tensor]:
    """The blocks ``(Qᵀ Φ Q)[k:, k:]`` (contiguous) and ``(Qᵀ Φ Q)[:k, k:]`` of the kernel
    matrix Φ of ``controls`` projected by Q from :func:`block_reflector`, k reflectors.

    ``Qᵀ Φ Q = Φ − V Yᵀ − Y Vᵀ`` with ``W = Φ V``, ``S = Tᵀ Vᵀ W T`` and
    ``Y = W T − V S / 2``, a symmetric rank-2k update in the index space of Φ, so its
    trailing block is ``Φ[k:, k:] − V[k:] Y[k:]ᵀ − Y[k:] V[k:]ᵀ``: Φ is computed by blocks
    (the trailing one written where the factorisation reads it), never whole.
    """
    count = tau.shape[0]
    vectors, triangle = block_reflector(qr, tau)
    head, tail = controls[:count], controls[count:]
    across = kernel_matrix(head, controls, kernel, scale)  # Φ[:k, :], (k, N)
    if _lapack(tail):  # one triangle of Φ[k:, k:] computed, read and updated
        trailing = kernel_matrix_upper(tail, kernel, scale)  # (N − k, N − k)
        # row-major upper = column-major lower: the triangle the BLAS calls and dpotrf read
        lower = trailing.numpy().T
        tail_product = torch.from_numpy(dsymm(1.0, lower, vectors[count:].numpy(), lower=1))
    else:
        trailing = kernel_matrix(tail, tail, kernel, scale)
        tail_product = trailing @ vectors[count:]
    product = torch.cat(
        [across @ vectors, across[:, count:].T @ vectors[:count] + tail_product]
    )  # W = Φ V
    inner = triangle.T @ (vectors.T @ product) @ triangle
    update = product @ triangle - 0.5 * (vectors @ inner)
    if _lapack(tail):  # − V Yᵀ − Y Vᵀ on the triangle, in place
        updated = dsyr2k(
            -1.0,
            vectors[count:].numpy(),
            update[count:].numpy(),
            beta=1.0,
            c=lower,
            lower=1,
            overwrite_c=1,
        )
        if not np.shares_memory(updated, lower):  # pragma: no cover - f2py copied it
            trailing = torch.from_numpy(np.ascontiguousarray(updated.T))
    else:
        stacked = torch.cat([vectors[count:], update[count:]], dim=1)
        swapped = torch.cat([update[count:], vectors[count:]], dim=1)
        trailing.addmm_(stacked, swapped.T, alpha=-1.0)  # − V Yᵀ − Y Vᵀ in one pass
    coupling = (
        across[:, count:] - vectors[:count] @ update[count:].T - update[:count] @ vectors[count:].T
    )
    return trailing, coupling


#: Order from which a float64 CPU Cholesky factorisation is scipy's rather than torch's:
#: below it torch's runs on torch's thread count (one in the partition-of-unity RBF's
#: loop over its patches), where OpenBLAS's own threads, waiting for a descheduled sibling
#: on a loaded machine, took 0.2 s instead of 2 ms at n = 314.
LAPACK_CHOLESKY_ORDER = 1000


def _lapack(matrix: Tensor) -> bool:
    """Whether a symmetric matrix with ``matrix``'s number of rows, dtype and device is
    factorised by scipy's LAPACK (:func:`cholesky`), which reads one triangle only."""
    return (
        matrix.device.type == "cpu"
        and matrix.dtype == torch.float64
        and matrix.shape[0] >= LAPACK_CHOLESKY_ORDER
    )


def cholesky(matrix: Tensor, *, overwrite: bool = False, clean: bool = True) -> tuple[Tensor, int]:
    """The lower Cholesky factor of a symmetric matrix and LAPACK's ``info`` (0: positive
    definite). float64 on the CPU from :data:`LAPACK_CHOLESKY_ORDER` on: scipy's LAPACK
    ``dpotrf`` in place on a contiguous copy (measured 1.75-1.80 s against 2.1-2.5 s for
    ``torch.linalg.cholesky_ex`` at n = 4,996, one thread, AMD EPYC: scipy's OpenBLAS
    against torch's MKL); otherwise torch's. ``overwrite``: a contiguous ``matrix`` may be
    factorised in place. ``clean=False``: the entries of ``matrix`` below the diagonal are
    zero already (:func:`~torchmorph.rbf.kernels.kernel_matrix_upper`), so LAPACK's
    factor is not cleaned there (its zeros kept, their pages never written)."""
    if _lapack(matrix):
        if matrix.is_contiguous():
            copy = matrix if overwrite else matrix.clone()
        else:
            copy = matrix.contiguous()
        # the row-major symmetric matrix read column-major is itself: no transposition
        factor, info = dpotrf(copy.numpy().T, lower=1, overwrite_a=1, clean=int(clean))
        return torch.from_numpy(factor), int(info)
    factor, info = torch.linalg.cholesky_ex(matrix)
    return factor, int(info)


class _LapackCholeskySolve(torch.autograd.Function):
    """``S⁻¹ B`` by scipy's LAPACK ``dpotrs`` on the stored lower factor (read in place
    when it is column-major; ``torch.cholesky_solve`` copied it, 0.28 s of a 0.29 s
    solve at n = 4,996); the backward pass is the same solve (S is symmetric)."""

    @staticmethod
    def forward(ctx, values, factor):  # type: ignore[override]
        ctx.save_for_backward(factor)
        return _dpotrs(values, factor)

    @staticmethod
    def backward(ctx, grad):  # type: ignore[override]
        (factor,) = ctx.saved_tensors
        return _dpotrs(grad, factor), None


def _dpotrs(values: Tensor, factor: Tensor) -> Tensor:
    array = factor.numpy()
    if not array.flags.f_contiguous:
        array = np.asfortranarray(array)
    solution, info = dpotrs(array, values.detach().numpy(), lower=1)
    if info != 0:  # pragma: no cover - LAPACK's argument checks
        raise RuntimeError(f"dpotrs failed with info={info}")
    return torch.from_numpy(np.ascontiguousarray(solution))


def cholesky_solve(values: Tensor, factor: Tensor) -> Tensor:
    """``(L Lᵀ)⁻¹ values`` for the lower factor L of :func:`cholesky`, differentiable in
    ``values``: scipy's LAPACK on the CPU in float64, else ``torch.cholesky_solve``."""
    if factor.device.type == "cpu" and factor.dtype == torch.float64 and values.shape[0]:
        if factor.requires_grad:
            return torch.cholesky_solve(values, factor)
        return _LapackCholeskySolve.apply(values, factor)
    return torch.cholesky_solve(values, factor)


def factorise(
    controls: Tensor,
    kernel: str,
    scale: float,
    degree: int,
    powers,
    shift: Tensor,
    poly_scale: Tensor,
) -> tuple[str, dict[str, Tensor]]:
    """Factorise the system of ``controls`` (float64, no gradient): the kind and its
    factors by :data:`FACTOR_NAMES`. ``ValueError`` naming ``controls`` if singular."""
    count = len(powers)
    size = controls.shape[0]
    empty = controls.new_zeros(0)
    factors = dict.fromkeys(FACTOR_NAMES, empty)
    factors["pivots"] = torch.zeros(0, dtype=torch.int32, device=controls.device)
    poly = polynomial_matrix(controls, powers, shift, poly_scale)
    qr = tau = None
    if count:
        qr, tau = check_polynomial_rank(poly, degree)
    if degree >= MIN_DEGREE.get(kernel, -1):
        if count:
            assert qr is not None and tau is not None
            projected, coupling = projected_blocks(controls, kernel, scale, qr, tau)
        elif _lapack(controls):  # N controls: a matrix of order N
            projected = kernel_matrix_upper(controls, kernel, scale)
        else:
            projected = kernel_matrix(controls, controls, kernel, scale)
        # LAPACK reads the upper triangle alone, and the entries below it are zero
        factor, info = cholesky(projected, overwrite=True, clean=not _lapack(projected))
        if info == 0:
            factors["factor"] = factor
            if count:
                assert qr is not None and tau is not None
                factors["qr"], factors["tau"] = qr, tau
                factors["coupling"] = coupling
            return "cholesky", factors
        del projected, factor
    matrix = saddle_matrix(controls, kernel, scale, powers, shift, poly_scale)
    lu, pivots, info = torch.linalg.lu_factor_ex(matrix)
    pivot_size = torch.diagonal(lu).abs()
    if int(info) != 0 or float(pivot_size.min()) <= size * torch.finfo(lu.dtype).eps * float(
        pivot_size.max()
    ):
        raise ValueError(
            "controls: the interpolation system is singular to working precision (nearly "
            "coincident controls, or a kernel too flat for them: a larger epsilon)"
        )
    factors["factor"], factors["pivots"] = lu, pivots
    return "lu", factors


def solve(kind: str, factors: dict[str, Tensor], values: Tensor) -> tuple[Tensor, Tensor]:
    """Coefficients (λ (N, S), β (M, S)) for control values (N, S), float64; differentiable
    in ``values``."""
    size = values.shape[0]
    factor = factors["factor"]
    if kind == "lu":
        count = factor.shape[0] - size
        padded = torch.cat([values, values.new_zeros(count, values.shape[1])], dim=0)
        solution = torch.linalg.lu_solve(factor, factors["pivots"], padded)
        return solution[:size], solution[size:]
    qr, tau = factors["qr"], factors["tau"]
    count = tau.shape[0]
    if not count:
        return cholesky_solve(values, factor), values.new_zeros(0, values.shape[1])
    rotated = torch.ormqr(qr, tau, values, left=True, transpose=True)
    gamma = cholesky_solve(rotated[count:], factor)
    weights = torch.ormqr(
        qr, tau, torch.cat([values.new_zeros(count, values.shape[1]), gamma]), left=True
    )
    upper = torch.triu(qr[:count, :count])
    rest = rotated[:count] - factors["coupling"] @ gamma
    return weights, torch.linalg.solve_triangular(upper, rest, upper=True)
