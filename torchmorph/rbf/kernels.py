"""Radial basis functions as scipy's :class:`~scipy.interpolate.RBFInterpolator` defines
them, plus Wendland's compactly supported functions, and the matrices built from them.

Every kernel is written as a function of the *squared* scaled distance ``s = r²``
(``r = epsilon · |x − y|`` for scipy's kernels, ``r = |x − y| / support_radius`` for
Wendland's), so that a pairwise block is differences, squares and one function, never a
square root that a kernel does not need. At ``s = 0`` a kernel returns its value at
the origin through a mask, so that gradients stay finite where a target meets a control
(``sqrt`` and ``log`` have infinite slopes there; the kernels themselves do not, except
``linear``, whose gradient at the origin is taken as 0).
"""

from __future__ import annotations

from collections.abc import Callable
from itertools import combinations_with_replacement

import numpy as np
import torch
from torch import Tensor

from torchmorph.rbf import _numba

__all__ = [
    "KERNELS",
    "MIN_DEGREE",
    "SCALE_INVARIANT",
    "WENDLAND",
    "fused",
    "kernel_matrix",
    "kernel_matrix_upper",
    "monomial_powers",
    "polynomial_matrix",
    "polynomial_scaling",
]


def _thin_plate_spline(s: Tensor) -> Tensor:
    return 0.5 * s * torch.log(s)  # r² log r


def _linear(s: Tensor) -> Tensor:
    return -torch.sqrt(s)


def _cubic(s: Tensor) -> Tensor:
    return s * torch.sqrt(s)


def _quintic(s: Tensor) -> Tensor:
    return -(s * s) * torch.sqrt(s)


def _multiquadric(s: Tensor) -> Tensor:
    return -torch.sqrt(1.0 + s)


def _inverse_multiquadric(s: Tensor) -> Tensor:
    return torch.rsqrt(1.0 + s)


def _inverse_quadratic(s: Tensor) -> Tensor:
    return 1.0 / (1.0 + s)


def _gaussian(s: Tensor) -> Tensor:
    return torch.exp(-s)


def _wendland_c0(s: Tensor) -> Tensor:
    rest = torch.clamp(1.0 - torch.sqrt(s), min=0.0)
    return rest * rest  # (1 − r)₊²


def _wendland_c2(s: Tensor) -> Tensor:
    r = torch.sqrt(s)
    rest = torch.clamp(1.0 - r, min=0.0)
    return rest**4 * (4.0 * r + 1.0)  # (1 − r)₊⁴ (4r + 1)


def _wendland_c4(s: Tensor) -> Tensor:
    r = torch.sqrt(s)
    rest = torch.clamp(1.0 - r, min=0.0)
    return rest**6 * (35.0 * s + 18.0 * r + 3.0) / 3.0  # (1 − r)₊⁶ (35r² + 18r + 3) / 3


#: name -> (φ as a function of s = r², φ(0)).
KERNELS: dict[str, tuple[Callable[[Tensor], Tensor], float]] = {
    "thin_plate_spline": (_thin_plate_spline, 0.0),
    "linear": (_linear, 0.0),
    "cubic": (_cubic, 0.0),
    "quintic": (_quintic, 0.0),
    "multiquadric": (_multiquadric, -1.0),
    "inverse_multiquadric": (_inverse_multiquadric, 1.0),
    "inverse_quadratic": (_inverse_quadratic, 1.0),
    "gaussian": (_gaussian, 1.0),
    "wendland_c0": (_wendland_c0, 1.0),
    "wendland_c2": (_wendland_c2, 1.0),
    "wendland_c4": (_wendland_c4, 1.0),
}

#: Kernels whose scale needs no ``epsilon`` (scipy's ``_SCALE_INVARIANT``: default 1).
SCALE_INVARIANT = ("linear", "thin_plate_spline", "cubic", "quintic")

#: Wendland's functions (positive definite in up to 3 dimensions; zero beyond
#: ``support_radius``).
WENDLAND = ("wendland_c0", "wendland_c2", "wendland_c4")

#: The lowest polynomial degree with which a conditionally positive definite kernel is
#: uniquely solvable (scipy's ``_NAME_TO_MIN_DEGREE``, from Fasshauer, *Meshfree
#: Approximation Methods with MATLAB*, ch. 8); the others are positive definite (-1).
MIN_DEGREE = {
    "multiquadric": 0,
    "linear": 0,
    "thin_plate_spline": 1,
    "cubic": 1,
    "quintic": 2,
}


def _thin_plate_spline_(s: Tensor, scratch: Tensor) -> None:
    torch.log(s.clamp_min_(torch.finfo(s.dtype).tiny), out=scratch)
    s.mul_(scratch).mul_(0.5)  # at s = 0: tiny · log(tiny) / 2, about -4e-306 (float64)


def _wendland_(s: Tensor, scratch: Tensor, kernel: str) -> None:
    s.sqrt_()  # r
    torch.sub(1.0, s, out=scratch).clamp_min_(0.0)  # (1 − r)₊
    if kernel == "wendland_c0":
        torch.square(scratch, out=s)
    elif kernel == "wendland_c2":
        s.mul_(4.0).add_(1.0).mul_(scratch.square_().square_())
    else:
        polynomial = (s * 35.0).add_(18.0).mul_(s).add_(3.0).div_(3.0)
        torch.mul(polynomial, scratch.pow_(6), out=s)


#: In-place forms of the kernels, for blocks that need no gradient: φ(s) written over s.
_IN_PLACE: dict[str, Callable[[Tensor, Tensor], object]] = {
    "thin_plate_spline": _thin_plate_spline_,
    "linear": lambda s, _: s.sqrt_().neg_(),
    "cubic": lambda s, scratch: s.mul_(torch.sqrt(s, out=scratch)),
    "quintic": lambda s, scratch: torch.neg(torch.sqrt(s, out=scratch).mul_(s).mul_(s), out=s),
    "multiquadric": lambda s, _: s.add_(1.0).sqrt_().neg_(),
    "inverse_multiquadric": lambda s, _: s.add_(1.0).rsqrt_(),
    "inverse_quadratic": lambda s, _: s.add_(1.0).reciprocal_(),
    "gaussian": lambda s, _: s.neg_().exp_(),
    "wendland_c0": lambda s, scratch: _wendland_(s, scratch, "wendland_c0"),
    "wendland_c2": lambda s, scratch: _wendland_(s, scratch, "wendland_c2"),
    "wendland_c4": lambda s, scratch: _wendland_(s, scratch, "wendland_c4"),
}

#: Entries of one in-place block of :func:`kernel_matrix` (256 KiB of float64: L2-sized).
IN_PLACE_BLOCK = 32768


def kernel_matrix(
    points: Tensor, centres: Tensor, kernel: str, scale: float, *, out: Tensor | None = None
) -> Tensor:
    """φ(scale · |points_i − centres_j|), shape (N, M), from direct coordinate differences.

    Parameters
    ----------
    points : Tensor, shape (N, D)
    centres : Tensor, shape (M, D)
    kernel : str
        A key of :data:`KERNELS`.
    scale : float
        ``epsilon`` for scipy's kernels, ``1 / support_radius`` for Wendland's.
    out : Tensor, shape (N, M), optional
        Where to write (a contiguous tensor of the points' dtype), when no gradient is
        needed.

    Notes
    -----
    Without gradients, blocks of rows of :data:`IN_PLACE_BLOCK` entries are computed in
    place (differences, squares and the kernel written over one cache-sized block);
    with gradients, the masked functions of :data:`KERNELS`.
    """
    needs_grad = torch.is_grad_enabled() and (points.requires_grad or centres.requires_grad)
    if not needs_grad:
        return _kernel_matrix_in_place(points, centres, kernel, scale, out)
    function, at_zero = KERNELS[kernel]
    squared = torch.zeros(
        points.shape[0], centres.shape[0], dtype=points.dtype, device=points.device
    )
    for axis in range(points.shape[1]):
        difference = points[:, axis, None] - centres[None, :, axis]
        squared = squared + difference * difference
    if scale != 1.0:
        squared = squared * (scale * scale)
    positive = squared > 0
    values = function(torch.where(positive, squared, torch.ones_like(squared)))
    return torch.where(positive, values, torch.full_like(values, at_zero))


def kernel_matrix_upper(points: Tensor, kernel: str, scale: float) -> Tensor:
    """The upper triangle (diagonal included) of the kernel matrix of ``points`` with
    themselves, zeros below (no gradient), for a routine that reads one triangle. Where
    the fused kernels run, only that triangle is computed and written, into pages the
    system zeroes on first use: half the work and half the memory touched."""
    if fused(kernel, points):
        size = points.shape[0]
        out = torch.from_numpy(np.zeros((size, size)))  # calloc: untouched pages stay free
        return _numba.tps_upper(points.detach(), scale, out)
    return kernel_matrix(points.detach(), points.detach(), kernel, scale).triu_()


def fused(kernel: str, points: Tensor) -> bool:
    """Whether the fused numba kernels of :mod:`torchmorph.rbf._numba` compute this
    kernel's blocks: the thin-plate spline, float64, on the CPU, numba installed (the
    other kernels and cases run the torch blocks)."""
    return (
        kernel == "thin_plate_spline"
        and points.device.type == "cpu"
        and points.dtype == torch.float64
        and _numba.available()
    )


def _kernel_matrix_in_place(
    points: Tensor, centres: Tensor, kernel: str, scale: float, out: Tensor | None
) -> Tensor:
    points, centres = points.detach(), centres.detach()
    rows_total, columns = points.shape[0], centres.shape[0]
    if out is None:
        out = torch.empty(rows_total, columns, dtype=points.dtype, device=points.device)
    if not rows_total or not columns:
        return out
    if fused(kernel, points):
        return _numba.tps_rows(points, centres, scale, out)
    rows = max(1, IN_PLACE_BLOCK // columns)
    if points.device.type == "cuda":
        rows = max(rows, (64 << 20) // (points.element_size() * columns))
    point_axes = [points[:, axis, None].contiguous() for axis in range(points.shape[1])]
    centre_axes = [centres[None, :, axis].contiguous() for axis in range(points.shape[1])]
    scratch_all = torch.empty(
        min(rows, rows_total), columns, dtype=points.dtype, device=points.device
    )
    in_place = _IN_PLACE[kernel]
    factor = scale * scale
    for start in range(0, rows_total, rows):
        stop = min(start + rows, rows_total)
        block, scratch = out[start:stop], scratch_all[: stop - start]
        torch.sub(point_axes[0][start:stop], centre_axes[0], out=block)
        block.square_()
        for axis in range(1, len(point_axes)):
            torch.sub(point_axes[axis][start:stop], centre_axes[axis], out=scratch)
            block.addcmul_(scratch, scratch)
        if factor != 1.0:
            block.mul_(factor)
        in_place(block, scratch)
    return out


def monomial_powers(dim: int, degree: int) -> list[tuple[int, ...]]:
    """Exponents of the monomials of degree <= ``degree`` in ``dim`` variables, in scipy's
    order (constant, then x, y, z, then the quadratic terms …); none for degree -1."""
    powers = []
    for total in range(degree + 1):
        for combination in combinations_with_replacement(range(dim), total):
            exponent = [0] * dim
            for variable in combination:
                exponent[variable] += 1
            powers.append(tuple(exponent))
    return powers


def polynomial_scaling(controls: Tensor) -> tuple[Tensor, Tensor]:
    """scipy's ``shift`` and ``scale`` of the polynomial's variables: the centre and the
    half extent of the controls' bounding box per axis (an extent of 0 scaled by 1), so
    that the monomials are evaluated in [-1, 1]^D."""
    low, high = controls.min(dim=0).values, controls.max(dim=0).values
    shift = (high + low) / 2
    scale = (high - low) / 2
    return shift, torch.where(scale == 0, torch.ones_like(scale), scale)


def polynomial_matrix(
    points: Tensor, powers: list[tuple[int, ...]], shift: Tensor, scale: Tensor
) -> Tensor:
    """The monomials at ``(points − shift) / scale``, shape (N, len(powers))."""
    local = (points - shift) / scale
    columns = []
    for exponent in powers:
        column = torch.ones_like(local[:, 0])
        for axis, power in enumerate(exponent):
            if power:
                column = column * local[:, axis] ** power
        columns.append(column)
    if not columns:
        return local.new_zeros(points.shape[0], 0)
    return torch.stack(columns, dim=1)
