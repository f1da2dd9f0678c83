"""The one-dimensional bases of free-form deformation: Bernstein polynomials (Sederberg
and Parry 1986, the basis of PyGeM's ``FFD`` and SU2's ``BEZIER`` blending) and clamped
uniform B-splines (Cox–de Boor's recurrence; the knot vector of SU2's ``BSPLINE_UNIFORM``).

Each basis is evaluated at local coordinates ``s`` in [0, 1] and returns one column per
control point of the axis; a lattice's basis is the tensor product of one such matrix
per axis (:func:`torchmorph.ffd.functional.ffd_bases`). Both are evaluated by stable
recurrences in torch operations, so they run on any device, in float32 or float64, and
are differentiable in ``s``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = [
    "bernstein_basis",
    "bspline_basis",
    "clamped_uniform_knots",
    "greville_abscissae",
]


def _check_count(count: int, name: str, minimum: int, what: str) -> int:
    if isinstance(count, bool) or not isinstance(count, int) or count < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum} {what}, got {count!r}")
    return count


def _check_coordinates(s: Tensor) -> None:
    if not isinstance(s, Tensor):
        raise TypeError(f"s must be a torch.Tensor, got {type(s).__name__}")
    if s.ndim != 1 or not s.is_floating_point():
        raise ValueError(
            f"s must be a 1-D floating-point tensor, got shape {tuple(s.shape)} and dtype {s.dtype}"
        )


def bernstein_basis(s: Tensor, count: int) -> Tensor:
    """The ``count`` Bernstein polynomials of degree n = count − 1 at ``s``.

    ``B_i(s) = C(n, i) s^i (1 − s)^(n − i)``, i = 0 … n (Sederberg and Parry 1986,
    eq. 1; PyGeM's ``FFD.T``).

    Parameters
    ----------
    s : Tensor, shape (M,)
        Local coordinates, normally in [0, 1].
    count : int
        Number of control points on the axis, >= 1.

    Returns
    -------
    Tensor, shape (M, count)
        Row m holds ``B_0(s_m) … B_n(s_m)``; rows sum to 1 (partition of unity).

    Notes
    -----
    Evaluated by de Casteljau's recurrence ``B^k_i = (1 − s) B^(k−1)_i + s B^(k−1)_(i−1)``
    rather than by powers and binomial coefficients: no cancellation, no ``0 ** 0``, and
    a gradient that is finite at s = 0 and s = 1.
    """
    _check_coordinates(s)
    count = _check_count(count, "count", 1, "(control points on the axis)")
    column = s[:, None]
    values = torch.ones_like(column)
    for _ in range(count - 1):
        values = F.pad((1 - column) * values, (0, 1)) + F.pad(column * values, (1, 0))
    return values


def clamped_uniform_knots(count: int, degree: int) -> list[float]:
    """The clamped (open) uniform knot vector of ``count`` B-splines of ``degree`` on [0, 1].

    ``degree + 1`` zeros, the interior knots ``i / (count − degree)`` for
    i = 1 … count − degree − 1, and ``degree + 1`` ones: ``count + degree + 1`` knots.
    Clamping makes the curve interpolate its end control points, so the lattice corners
    (and, in a volume, its faces) move exactly with their control points.
    """
    degree = _check_count(degree, "degree", 1, "(the B-spline degree)")
    count = _check_count(count, "count", degree + 1, f"(control points for degree {degree})")
    spans = count - degree
    interior = [i / spans for i in range(1, spans)]
    return [0.0] * (degree + 1) + interior + [1.0] * (degree + 1)


def greville_abscissae(count: int, degree: int) -> list[float]:
    """The Greville abscissae ``ξ_i = (t_(i+1) + … + t_(i+degree)) / degree`` of the
    clamped uniform knot vector: the parameter positions of the ``count`` control points.

    With control points there, the B-spline map reproduces every affine function (linear
    precision, de Boor, *A Practical Guide to Splines*, ch. IX). For ``degree = count − 1``
    (the Bernstein case) they are the uniform ``i / (count − 1)``.
    """
    knots = clamped_uniform_knots(count, degree)
    return [sum(knots[i + 1 : i + degree + 1]) / degree for i in range(count)]


def _inverse(width: float) -> float:
    """1 / width, and 0 for the zero width of a repeated knot (the recurrence's 0/0 := 0)."""
    return 1.0 / width if width > 0 else 0.0


def bspline_basis(s: Tensor, count: int, degree: int = 3) -> Tensor:
    """The ``count`` clamped uniform B-splines of ``degree`` at ``s``.

    Parameters
    ----------
    s : Tensor, shape (M,)
        Local coordinates in [0, 1] (the closed interval: s = 1 belongs to the last span).
    count : int
        Number of control points on the axis, >= degree + 1.
    degree : int
        Polynomial degree, >= 1 (3: cubic, C² across knots).

    Returns
    -------
    Tensor, shape (M, count)
        Row m holds ``N_(0,p)(s_m) … N_(count−1,p)(s_m)`` on the knots of
        :func:`clamped_uniform_knots`: at most ``degree + 1`` non-zero entries per row,
        non-negative, summing to 1.

    Notes
    -----
    The Cox–de Boor recurrence (de Boor 1972) over all functions at once:
    ``N_(i,k) = (s − t_i)/(t_(i+k) − t_i) N_(i,k−1) + (t_(i+k+1) − s)/(t_(i+k+1) − t_(i+1))
    N_(i+1,k−1)``, a term with a zero-width denominator taken as 0. With
    ``count = degree + 1`` the knots are those of a single Bézier segment and the basis
    equals :func:`bernstein_basis`.
    """
    _check_coordinates(s)
    knots = clamped_uniform_knots(count, degree)
    spans = count - degree
    # the one non-zero degree-0 function: the span [t_j, t_j+1) holding s, [.., 1] for s = 1
    with torch.no_grad():
        span = torch.clamp(torch.floor(s * spans), 0, spans - 1).long() + degree
    values = F.one_hot(span, len(knots) - 1).to(s.dtype)
    t = torch.tensor(knots, dtype=s.dtype, device=s.device)
    column = s[:, None]
    for k in range(1, degree + 1):
        width = len(knots) - 1 - k  # functions of degree k
        left = [_inverse(knots[i + k] - knots[i]) for i in range(width)]
        right = [_inverse(knots[i + k + 1] - knots[i + 1]) for i in range(width)]
        left_t = torch.tensor(left, dtype=s.dtype, device=s.device)
        right_t = torch.tensor(right, dtype=s.dtype, device=s.device)
        values = (column - t[:width]) * left_t * values[:, :width] + (
            t[k + 1 : k + 1 + width] - column
        ) * right_t * values[:, 1 : width + 1]
    return values
