"""The functional core of RBF morphing: option checks, the evaluation of an interpolant in
blocks of targets, and :func:`rbf_interpolate`, the one-shot (differentiable) morph.

The interpolant (scipy's :class:`~scipy.interpolate.RBFInterpolator` without smoothing)
is ``s(x) = Σ_k λ_k φ(r_k) + p(x)·β``, ``r_k = epsilon · |x − x_k|`` (Wendland:
``|x − x_k| / support_radius``), ``p`` the monomials of degree <= ``degree`` in the
shifted and scaled coordinates of :func:`~torchmorph.rbf.kernels.polynomial_scaling`,
with ``Φ λ + P β = d`` and ``Pᵀ λ = 0`` at the controls (see
:mod:`torchmorph.rbf.system`).
"""

from __future__ import annotations

import math
import numbers

import torch
from torch import Tensor

from torchmorph._checks import (
    as_points,
    check_choice,
    check_positive,
    check_same_device_dtype,
    check_vectors,
)
from torchmorph.rbf import _numba
from torchmorph.rbf.kernels import (
    KERNELS,
    SCALE_INVARIANT,
    WENDLAND,
    fused,
    kernel_matrix,
    monomial_powers,
    polynomial_matrix,
    polynomial_scaling,
)
from torchmorph.rbf.system import saddle_matrix

__all__ = [
    "DEFAULT_BLOCK_BYTES",
    "DEFAULT_CUDA_BLOCK_BYTES",
    "check_distinct",
    "check_options",
    "dim_of",
    "evaluate",
    "rbf_interpolate",
]

#: Byte budget of one block of pairwise temporaries (targets × controls) on the CPU.
DEFAULT_BLOCK_BYTES = 4 << 20
#: The same on CUDA.
DEFAULT_CUDA_BLOCK_BYTES = 256 << 20


def check_options(
    kernel: str,
    epsilon: float | None,
    degree: int,
    support_radius: float | None,
    num_controls: int,
    dim: int,
) -> tuple[str, float, int, float | None, float]:
    """Validate the hyper-parameters: ``(kernel, epsilon, degree, support_radius, scale)``
    with ``scale`` the factor of the distance (``epsilon`` or ``1 / support_radius``).

    Raises ``ValueError`` naming the argument: an unknown kernel; epsilon not > 0, missing
    for a kernel that is not scale invariant, or given with a Wendland kernel;
    support_radius missing or not > 0 with a Wendland kernel, or given with another;
    degree not an integer >= -1; fewer controls than the polynomial has monomials.
    """
    kernel = check_choice(kernel, "kernel", tuple(KERNELS))
    if kernel in WENDLAND:
        if support_radius is None:
            raise ValueError(f"support_radius must be given for kernel={kernel!r}")
        support_radius = check_positive(support_radius, "support_radius")
        if epsilon is not None:
            raise ValueError(
                f"epsilon must be None for kernel={kernel!r}: its scale is support_radius"
            )
        epsilon, scale = 1.0, 1.0 / support_radius
    else:
        if support_radius is not None:
            raise ValueError(
                f"support_radius is only for the Wendland kernels, not kernel={kernel!r}"
            )
        if epsilon is None:
            if kernel not in SCALE_INVARIANT:
                raise ValueError(
                    f"epsilon must be given for kernel={kernel!r} (only "
                    f"{', '.join(SCALE_INVARIANT)} default to 1)"
                )
            epsilon = 1.0
        epsilon = check_positive(epsilon, "epsilon")
        scale = epsilon
    if isinstance(degree, bool) or not isinstance(degree, numbers.Integral) or degree < -1:
        raise ValueError(f"degree must be an integer >= -1 (-1: no polynomial), got {degree!r}")
    degree = int(degree)
    needed = math.comb(degree + dim, dim) if degree >= 0 else 0
    if num_controls < needed:
        raise ValueError(
            f"controls: degree={degree} in {dim}-D needs at least {needed} controls, "
            f"got {num_controls}"
        )
    return kernel, epsilon, degree, support_radius, scale


def check_distinct(controls: Tensor) -> None:
    """``ValueError`` naming ``controls`` and two indices if two controls coincide (their
    rows of the kernel matrix are equal: the system is singular)."""
    plain = controls.detach()
    unique, inverse, counts = torch.unique(plain, dim=0, return_inverse=True, return_counts=True)
    if unique.shape[0] == plain.shape[0]:
        return
    repeated = int(torch.nonzero(counts > 1)[0, 0])
    first, second = torch.nonzero(inverse == repeated)[:2, 0].tolist()
    raise ValueError(
        f"controls: points {first} and {second} coincide, so the interpolation system is "
        "singular; remove the duplicates"
    )


def dim_of(points) -> int:
    """The dimension a point array claims (its last axis) when it is 2 or 3, else 3, so
    that :func:`~torchmorph._checks.as_points` reports a bad shape against (N, 3)."""
    shape = getattr(points, "shape", None)
    if shape is not None and len(shape) == 2 and shape[1] in (2, 3):
        return int(shape[1])
    return 3


def block_rows(num_controls: int, block_bytes: int | None, device: torch.device) -> int:
    """Targets per block so that one (rows × controls) float64 temporary fits the budget."""
    if block_bytes is None:
        block_bytes = DEFAULT_CUDA_BLOCK_BYTES if device.type == "cuda" else DEFAULT_BLOCK_BYTES
    return max(1, block_bytes // (8 * max(1, num_controls)))


def evaluate(
    targets: Tensor,
    controls: Tensor,
    weights: Tensor,
    poly_coefficients: Tensor,
    *,
    kernel: str,
    scale: float,
    powers,
    shift: Tensor,
    poly_scale: Tensor,
    block_bytes: int | None = None,
) -> Tensor:
    """``Σ_k λ_k φ(scale |x − x_k|) + p(x)·β`` at the targets, in blocks of targets.

    Parameters
    ----------
    targets : Tensor, shape (N_t, D)
    controls : Tensor, shape (N_c, D)
    weights : Tensor, shape (N_c, S)
        λ.
    poly_coefficients : Tensor, shape (M, S)
        β.

    Returns
    -------
    Tensor, shape (N_t, S)
    """
    geometry_grad = torch.is_grad_enabled() and (targets.requires_grad or controls.requires_grad)
    if not geometry_grad and fused(kernel, controls) and targets.shape[0]:
        value = _FusedApply.apply(targets, controls, scale, weights)
        if powers:
            value += polynomial_matrix(targets, powers, shift, poly_scale) @ poly_coefficients
        return value
    rows = block_rows(controls.shape[0], block_bytes, targets.device)
    parts = []
    for start in range(0, targets.shape[0], rows):
        block = targets[start : start + rows]
        value = kernel_matrix(block, controls, kernel, scale) @ weights
        if powers:
            value = value + polynomial_matrix(block, powers, shift, poly_scale) @ poly_coefficients
        parts.append(value)
    if not parts:
        return weights.new_zeros(0, weights.shape[1])
    return torch.cat(parts) if len(parts) > 1 else parts[0]


class _FusedApply(torch.autograd.Function):
    """``Φ(targets, controls) @ weights`` by the fused kernel, differentiable in the
    weights: the backward pass is the same kernel with the roles swapped,
    ``Φ(controls, targets) @ grad`` (Φ is symmetric in its two point sets)."""

    @staticmethod
    def forward(ctx, targets, controls, scale, weights):  # type: ignore[override]
        ctx.save_for_backward(targets, controls)
        ctx.scale = scale
        return _numba.tps_apply(targets, controls, scale, weights)

    @staticmethod
    def backward(ctx, grad):  # type: ignore[override]
        targets, controls = ctx.saved_tensors
        weights_grad = None
        if ctx.needs_input_grad[3]:
            weights_grad = _numba.tps_apply(controls, targets, ctx.scale, grad.contiguous())
        return None, None, None, weights_grad


def columns_of(displacements: Tensor) -> Tensor:
    """(N, D) or (B, N, D) -> (N, B·D): the value columns of one solve."""
    if displacements.ndim == 2:
        return displacements
    batch, count, dim = displacements.shape
    return displacements.permute(1, 0, 2).reshape(count, batch * dim)


def from_columns(values: Tensor, displacements: Tensor) -> Tensor:
    """The inverse of :func:`columns_of` for N_t rows, shaped as ``displacements``."""
    if displacements.ndim == 2:
        return values
    batch, _, dim = displacements.shape
    return values.reshape(values.shape[0], batch, dim).permute(1, 0, 2)


def rbf_interpolate(
    *,
    controls: Tensor,
    targets: Tensor,
    displacements: Tensor,
    kernel: str = "thin_plate_spline",
    epsilon: float | None = None,
    degree: int = 1,
    support_radius: float | None = None,
    block_bytes: int | None = None,
) -> Tensor:
    """Interpolate control displacements to the targets with an RBF, in one call.

    The system is assembled and solved (``torch.linalg.solve`` of the saddle matrix, in
    float64) on every call, differentiably in the displacements and in both point sets.
    To morph many times with the same geometry, build :class:`~torchmorph.rbf.RBF` once.

    Parameters
    ----------
    controls : Tensor, shape (N_c, D)
    targets : Tensor, shape (N_t, D)
    displacements : Tensor, shape (N_c, D) or (B, N_c, D)
    kernel, epsilon, degree, support_radius
        As :class:`~torchmorph.rbf.RBF`.
    block_bytes : int, optional
        Byte budget of one block of pairwise temporaries.

    Returns
    -------
    Tensor, shape (N_t, D) or (B, N_t, D), the dtype of the displacements.
    """
    controls = as_points(controls, "controls", dim=dim_of(controls))
    dim = controls.shape[1]
    targets = as_points(targets, "targets", dim=dim, allow_empty=True)
    check_same_device_dtype(controls, "controls", targets, "targets")
    check_vectors(displacements, "displacements", controls.shape[0], dim=dim, what="control points")
    check_same_device_dtype(controls, "controls", displacements, "displacements")
    kernel, _, degree, _, scale = check_options(
        kernel, epsilon, degree, support_radius, controls.shape[0], dim
    )
    check_distinct(controls)
    powers = monomial_powers(dim, degree)
    work_controls, work_targets = controls.double(), targets.double()
    shift, poly_scale = polynomial_scaling(work_controls.detach())
    matrix = saddle_matrix(work_controls, kernel, scale, powers, shift, poly_scale)
    values = columns_of(displacements).double()
    padded = torch.cat([values, values.new_zeros(len(powers), values.shape[1])])
    solution = torch.linalg.solve(matrix, padded)
    size = controls.shape[0]
    result = evaluate(
        work_targets,
        work_controls,
        solution[:size],
        solution[size:],
        kernel=kernel,
        scale=scale,
        powers=powers,
        shift=shift,
        poly_scale=poly_scale,
        block_bytes=block_bytes,
    )
    return from_columns(result, displacements).to(displacements.dtype)
