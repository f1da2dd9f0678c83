"""The maths of POD-reduced morphing as plain functions over dense tensors.

Ballarin, D'Amario, Perotto and Rozza (2017), section 3: the POD basis of a set of
snapshots (eqs. 9–12, :func:`pod_basis`), the online matrix of the orthogonal
projection onto it (:func:`projection_matrix`), and the matrices of the paper's own
online system (eq. 16, :func:`paper_matrices`). :class:`torchmorph.pod.PODReducer` is
the estimator built on them.

Layout. A displacement field on M points of dimension D (2 or 3) is a tensor (M, D);
flattened it is the component-interleaved vector of length D·M (x1, y1, z1, x2, ...).
The POD basis ``Z`` (3·N_int × N in the paper, whose meshes are 3-D) is stored as
``modes`` of shape (N, N_int, D): ``modes[l]`` is the l-th mode as a displacement
field. ``W`` acts on each component separately (the operator on flattened fields is
W ⊗ I_D); no Kronecker matrix is ever formed.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from torchmorph._checks import check_choice, check_finite, check_float_dtype

__all__ = [
    "check_energy_tolerance",
    "check_num_modes",
    "paper_matrices",
    "pod_basis",
    "projection_matrix",
]


# --------------------------------------------------------------------------------------
# functional core
# --------------------------------------------------------------------------------------


def _num_modes_for_energy(energies: Tensor, energy_tolerance: float) -> int:
    """Smallest N with sum_{i>N} σ_i² <= ε sum_i σ_i² (paper eq. 12), from the σ_i²."""
    energy = energies.double()
    total = float(energy.sum())
    # tail[N] = sum_{i>N} σ_i², summed from the small end for accuracy
    tail = torch.flip(torch.cumsum(torch.flip(energy, (0,)), 0), (0,))
    tail = torch.cat([tail[1:], tail.new_zeros(1)])
    below = torch.nonzero(tail <= energy_tolerance * total).flatten()
    return int(below[0]) + 1


def _numerical_rank(singular_values: Tensor, shape: tuple[int, int], dtype: torch.dtype) -> int:
    """Number of singular values above σ_1 · sqrt(m·n) · eps(dtype)."""
    if singular_values.numel() == 0 or float(singular_values[0]) == 0.0:
        return 0
    eps = torch.finfo(dtype).eps
    tolerance = float(singular_values[0]) * math.sqrt(shape[0] * shape[1]) * eps
    return int((singular_values > tolerance).sum())


_CORRELATION_MIN_ASPECT = 4
"""The method of snapshots is tried when the snapshots' length is at least this many
times their number (a 20 × 66,000 matrix: the correlation matrix is 20 × 20)."""

_SAFE_SQUARES = (1e-250, 1e250)
"""Largest squared snapshot norm for which the snapshots are used unscaled."""

_SUBSPACE_TOLERANCE = 1e-10
"""Largest error of the kept modes' span (float64 outputs; float32 outputs allow their
own eps) for which the method of snapshots is used rather than the thin SVD."""


def _kept_modes(
    energies: Tensor, energy_tolerance: float, num_modes: int | None, count: int
) -> int:
    if num_modes is None:
        return _num_modes_for_energy(energies, energy_tolerance)
    if num_modes > count:
        raise ValueError(f"num_modes={num_modes} exceeds the number of snapshots ({count})")
    return num_modes


def _check_rank(
    num_modes: int | None, singular_values: Tensor, shape: tuple[int, int], dtype: torch.dtype
) -> None:
    if num_modes is None:
        return
    rank = _numerical_rank(singular_values, shape, dtype)
    if num_modes > rank:
        raise ValueError(
            f"num_modes={num_modes} exceeds the numerical rank {rank} of the snapshots "
            f"(singular values {singular_values[:num_modes].tolist()})"
        )


def _svd_basis(
    matrix: Tensor, energy_tolerance: float, num_modes: int | None, dtype: torch.dtype
) -> tuple[Tensor, Tensor]:
    """Thin SVD of the (scaled, float64) n × D·M matrix Uᵀ: rows of modes, all σ."""
    _, singular_values, vh = torch.linalg.svd(matrix, full_matrices=False)
    kept = _kept_modes(singular_values.square(), energy_tolerance, num_modes, matrix.shape[0])
    _check_rank(num_modes, singular_values, (matrix.shape[0], matrix.shape[1]), dtype)
    return vh[:kept], singular_values


def _correlation_basis(
    matrix: Tensor,
    correlation: Tensor,
    energy_tolerance: float,
    num_modes: int | None,
    dtype: torch.dtype,
) -> tuple[Tensor, Tensor] | None:
    """Method of snapshots on the float64 n × D·M matrix Uᵀ and its correlation
    matrix UᵀU, or None where it would lose accuracy on the kept modes.

    The eigen-decomposition UᵀU = V Σ² Vᵀ gives the modes as Σ⁻¹ Vᵀ Uᵀ at the cost of
    two passes over U, but squares the condition number: the span of the first N
    modes is accurate to about eps · σ_1² / (σ_N² − σ_{N+1}²). Where that exceeds the
    tolerance, None is returned (the caller runs the thin SVD). The modes are
    re-orthonormalised by a QR factorisation (D·M × N, cheap for few modes).
    """
    count = matrix.shape[0]
    eigenvalues, vectors = torch.linalg.eigh(correlation)
    eigenvalues = eigenvalues.flip(0).clamp_min(0.0)
    kept = _kept_modes(eigenvalues, energy_tolerance, num_modes, count)
    following = float(eigenvalues[kept]) if kept < count else 0.0
    gap = float(eigenvalues[kept - 1]) - following
    tolerance = max(_SUBSPACE_TOLERANCE, torch.finfo(dtype).eps)
    if gap <= 0.0 or torch.finfo(torch.float64).eps * float(eigenvalues[0]) > tolerance * gap:
        return None
    singular_values = eigenvalues.sqrt()
    _check_rank(num_modes, singular_values, (matrix.shape[0], matrix.shape[1]), dtype)
    leading = vectors[:, count - kept :].flip(1)  # (n, N), descending
    rough = (leading.mT @ matrix) / singular_values[:kept].unsqueeze(1)  # (N, D·M)
    basis, triangle = torch.linalg.qr(rough.mT)  # (D·M, N): orthonormal columns
    signs = torch.sign(triangle.diagonal())  # QR may flip a column: keep each mode's sign
    basis = basis * torch.where(signs == 0, 1.0, signs)
    return basis.mT, singular_values


def pod_basis(
    snapshots: Tensor,
    *,
    energy_tolerance: float = 1e-5,
    num_modes: int | None = None,
    method: Literal["auto", "svd", "correlation"] = "auto",
) -> tuple[Tensor, Tensor, Tensor]:
    """POD basis of a set of displacement fields (the paper's section 3, eqs. 9–12).

    Parameters
    ----------
    snapshots : Tensor, shape (n, M, D)
        ``n`` fields on ``M`` points of dimension D, the columns of the snapshot
        matrix ``U`` (each flattened component-interleaved to length D·M).
    energy_tolerance : float
        ε in (0, 1): N is the smallest number of modes with
        ``sum_{i>N} σ_i² <= ε · sum_i σ_i²``. Ignored when ``num_modes`` is given.
    num_modes : int, optional
        Keep exactly this many modes.
    method : {"auto", "svd", "correlation"}
        ``"svd"``: thin SVD of Uᵀ. ``"correlation"``: the method of snapshots
        (eigen-decomposition of the n × n correlation matrix, then a Rayleigh–Ritz
        step), falling back to the SVD when it would lose accuracy on the kept
        modes (see Notes). ``"auto"`` (default): ``"correlation"`` when D·M >= 4n.

    Returns
    -------
    modes : Tensor, shape (N, M, D)
        Orthonormal modes (the first N left singular vectors of U), in the
        snapshots' dtype.
    singular_values : Tensor, shape (min(n, D·M),)
        All singular values of U, descending (float64 arithmetic, snapshots' dtype).
    energy_captured : Tensor, shape (min(n, D·M),)
        ``energy_captured[k] = sum_{i<=k+1} σ_i² / sum_i σ_i²``: the energy fraction
        kept by k + 1 modes.

    Raises
    ------
    ValueError
        If the snapshots are not (n, M, D), are half precision, hold NaN/inf, are
        all zero, if ε is outside (0, 1), or ``num_modes`` exceeds the number of
        snapshots or their numerical rank (singular values above
        σ_1 · sqrt(D·M·n) · eps).

    Notes
    -----
    Computed in float64 whatever the input dtype. Snapshots whose squared norms
    leave [1e-250, 1e250] are first divided by a power of two near their largest
    entry (exactly), so that norms from 1e-300 to 1e300 neither underflow nor
    overflow when squared; the singular values are scaled back.

    The correlation route squares the condition number: the span of the N kept
    modes is accurate to about eps · σ_1² / (σ_N² − σ_{N+1}²). It is used only
    where that is below 1e-10 (float64 snapshots) or float32's eps (float32
    snapshots); otherwise the thin SVD runs. At case-B size (20 × 66,000) it takes
    a few milliseconds against about 0.1 s for the SVD. Its singular values are
    those of the correlation matrix: σ_i is accurate to about eps · σ_1² / σ_i, so
    values below about 1e-7 · σ_1 are rounding noise (use ``method="svd"`` to
    resolve them). The signs of the modes are arbitrary.
    """
    if not isinstance(snapshots, Tensor):
        raise TypeError(f"snapshots must be a torch.Tensor, got {type(snapshots).__name__}")
    if snapshots.ndim != 3 or 0 in (snapshots.shape[0], snapshots.shape[2]):
        raise ValueError(
            f"snapshots must have shape (n, M, D) with n >= 1, got {tuple(snapshots.shape)}"
        )
    check_float_dtype(snapshots, "snapshots")
    energy_tolerance = check_energy_tolerance(energy_tolerance)
    num_modes = check_num_modes(num_modes)
    check_choice(method, "method", ("auto", "svd", "correlation"))
    count, num_points, dim = snapshots.shape
    length = dim * num_points

    # U^T = V Σ Z^T: the rows of Vh are the modes, already in the (N, M·D) layout
    snapshots = snapshots.detach()
    # the layout first (a strided copy is fastest in the narrower dtype), then float64
    work = snapshots.contiguous().reshape(count, length).to(torch.float64)
    correlation = work @ work.mT
    largest = float(correlation.diagonal().max())  # the largest squared snapshot norm
    extent = 1.0
    if not math.isfinite(largest) or not (_SAFE_SQUARES[0] <= largest <= _SAFE_SQUARES[1]):
        # NaN/inf entries, all zero, or squares outside float64's comfortable range:
        # divide by a power of two near the largest entry (exact) and start again
        check_finite(snapshots, "snapshots")
        low, high = torch.aminmax(snapshots)
        if max(-float(low), float(high)) == 0.0:
            raise ValueError("snapshots are all zero: there is no displacement to reduce")
        extent = 2.0 ** math.frexp(max(-float(low), float(high)))[1]
        work = snapshots.reshape(count, length).to(torch.float64, copy=True)
        work = work.div_(extent)
        correlation = work @ work.mT
    result = None
    if method == "correlation" or (method == "auto" and length >= _CORRELATION_MIN_ASPECT * count):
        result = _correlation_basis(work, correlation, energy_tolerance, num_modes, snapshots.dtype)
    if result is None:
        result = _svd_basis(work, energy_tolerance, num_modes, snapshots.dtype)
    rows, scaled_values = result
    kept = rows.shape[0]
    energy = scaled_values.square()
    energy_captured = torch.cumsum(energy, 0) / energy.sum()
    modes = rows.reshape(kept, num_points, dim).to(snapshots.dtype).contiguous()
    return (
        modes,
        (scaled_values * extent).to(snapshots.dtype),
        energy_captured.to(snapshots.dtype),
    )


def _fields_as_columns(fields: Tensor) -> Tensor:
    """(N, M, D) -> (M, D·N): the N fields' components side by side, one row per point."""
    count, num_points, dim = fields.shape
    return fields.permute(1, 0, 2).reshape(num_points, dim * count)


def _columns_as_fields(columns: Tensor, count: int) -> Tensor:
    """Inverse of :func:`_fields_as_columns`: (M, D·N) -> (N, M, D), contiguous."""
    num_points = columns.shape[0]
    return columns.reshape(num_points, count, -1).permute(1, 0, 2).contiguous()


def _check_modes_weights(modes: Tensor, weights: Tensor) -> None:
    if modes.ndim != 3 or modes.shape[-1] == 0:
        raise ValueError(f"modes must have shape (N, N_int, D), got {tuple(modes.shape)}")
    if weights.ndim != 2 or weights.shape[0] != modes.shape[1]:
        raise ValueError(
            f"weights must have shape ({modes.shape[1]}, N_sel) to match modes "
            f"{tuple(modes.shape)}, got {tuple(weights.shape)}"
        )


def projection_matrix(modes: Tensor, weights: Tensor) -> Tensor:
    """Online matrix of the ``projection`` variant: P = Zᵀ (W ⊗ I_D) (section 3 of the paper, Algorithm 3, step (e)).

    Parameters
    ----------
    modes : Tensor, shape (N, N_int, D)
        Orthonormal POD modes (``Z``).
    weights : Tensor, shape (N_int, N_sel)
        The (S)IDW matrix ``W``.

    Returns
    -------
    Tensor, shape (N, N_sel, D)
        ``P[l, k, c] = sum_i modes[l, i, c] · W[i, k]``, so that for a control
        displacement ``d`` (N_sel, D) the coefficients are
        ``β = P.reshape(N, -1) @ d.reshape(-1) = Zᵀ vec(W d)``: the orthogonal
        projection of the full morph onto the POD space.

    Notes
    -----
    One GEMM, (D·N × N_int) · (N_int × N_sel): W is streamed once for all D·N
    columns (mat-vecs per column would stream it D·N times).
    """
    _check_modes_weights(modes, weights)
    fields = _fields_as_columns(modes.to(weights.dtype))  # (N_int, D·N)
    columns = (fields.mT @ weights).mT  # (N_sel, D·N)
    return _columns_as_fields(columns, modes.shape[0])


def _pseudo_inverse_apply(weights: Tensor, columns: Tensor) -> Tensor:
    """W⁺ @ columns (minimum-norm least squares), float64."""
    weights = weights.double()
    columns = columns.double()
    if weights.device.type == "cpu":
        # rank-revealing complete orthogonal factorisation; minimum-norm solution
        return torch.linalg.lstsq(weights, columns, driver="gelsy").solution
    return torch.linalg.pinv(weights) @ columns


def paper_matrices(modes: Tensor, weights: Tensor) -> tuple[Tensor, Tensor]:
    """Online matrices of the paper's variant (the paper's eq. 16).

    The paper writes the control displacement as the least-squares preimage of
    the interior field, ``d_sel ≈ W⁺ Z β`` (eq. 15), and computes β from the
    normal equations of that system:

        Zᵀ (W⁺)ᵀ W⁺ Z β = Zᵀ (W⁺)ᵀ d_sel.                      (16)

    Parameters
    ----------
    modes : Tensor, shape (N, N_int, D)
        Orthonormal POD modes (``Z``).
    weights : Tensor, shape (N_int, N_sel)
        The (S)IDW matrix ``W``; ``W⁺`` (N_sel × N_int) is its Moore–Penrose
        pseudo-inverse, applied per component.

    Returns
    -------
    system_matrix : Tensor, shape (N, N)
        ``A = Zᵀ (W⁺)ᵀ W⁺ Z`` (symmetric positive definite).
    rhs_matrix : Tensor, shape (N, N_sel, D)
        ``B = Zᵀ (W⁺)ᵀ`` in the displacement layout: the right-hand side of (16)
        is ``B.reshape(N, -1) @ d_sel.reshape(-1)``.

    Notes
    -----
    ``W⁺ Z`` is computed without forming W⁺ (minimum-norm least squares with a
    rank-revealing QR, LAPACK ``gelsy``, in float64; on other devices through
    ``torch.linalg.pinv``). This costs O(N_int · N_sel · min(N_int, N_sel)) — the
    dominant offline cost of the paper's method (minutes at case-B size) and the
    reason ``projection`` is the default. Results are returned in ``weights``'
    dtype. When W has full rank and the field lies in the POD space, (16) gives
    the exact coefficients; otherwise it weights the error by (W⁺)ᵀW⁺ and is never
    more accurate (in the Euclidean norm of the interior field) than the
    projection.
    """
    _check_modes_weights(modes, weights)
    count = modes.shape[0]
    preimage = _pseudo_inverse_apply(weights, _fields_as_columns(modes))  # (N_sel, D·N)
    rhs = _columns_as_fields(preimage, count)  # (N, N_sel, D) = Z^T (W^+)^T
    flat = rhs.reshape(count, -1)
    system = flat @ flat.mT
    system = 0.5 * (system + system.mT)
    return system.to(weights.dtype), rhs.to(weights.dtype)


# --------------------------------------------------------------------------------------
# argument checks
# --------------------------------------------------------------------------------------


def check_energy_tolerance(value: float) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"energy_tolerance must be a number in (0, 1), got {value!r}") from None
    if not (0.0 < number < 1.0):
        raise ValueError(f"energy_tolerance must be in (0, 1), got {value!r}")
    return number


def check_num_modes(value: int | None) -> int | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"num_modes must be a positive integer or None, got {value!r}")
    return int(value)
