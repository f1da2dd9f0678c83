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

import math
from collections.abc import Callable
from itertools import combinations_with_replacement

import torch
from torch import Tensor

__all__ = [
    "KERNELS",
    "MIN_DEGREE",
    "SCALE_INVARIANT",
    "WENDLAND",
    "kernel_matrix",
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


def kernel_matrix(points: Tensor, centres: Tensor, kernel: str, scale: float) -> Tensor:
    """φ(scale · |points_i − centres_j|), shape (N, M), from direct coordinate differences.

    Parameters
    ----------
    points : Tensor, shape (N, D)
    centres : Tensor, shape (M, D)
    kernel : str
        A key of :data:`KERNELS`.
    scale : float
        ``epsilon`` for scipy's kernels, ``1 / support_radius`` for Wendland's.
    """
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


def binomial_count(dim: int, degree: int) -> int:
    """How many monomials :func:`monomial_powers` gives (0 for degree -1)."""
    return math.comb(degree + dim, dim) if degree >= 0 else 0
