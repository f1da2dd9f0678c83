"""The functional core of free-form deformation: the box's local coordinates, the
per-axis basis matrices of the points inside it, and the lattice sum

    d(x) = Σ_(i,j,k) B_i(s) B_j(t) B_k(u) d_ijk,     (s, t, u) = Rᵀ (x − origin) / lengths,

of Sederberg and Parry (1986, eq. 1), written for displacements: ``d_ijk`` is the
displacement of control point (i, j, k) in physical units and ``d(x)`` the displacement
of a point x inside the box; a point outside the box does not move.

:func:`ffd_bases` computes what depends on the points only (once),
:func:`~torchmorph.ffd.lattice.lattice_sum` what depends on the displacements (every
call), :func:`ffd_apply` both. The :class:`~torchmorph.ffd.FFD` module keeps the bases
as buffers.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, Literal

import numpy as np
import torch
from torch import Tensor

from torchmorph._checks import (
    as_points,
    check_choice,
    check_finite,
    check_float_dtype,
    check_same_device_dtype,
)
from torchmorph.ffd.basis import bernstein_basis, bspline_basis, greville_abscissae
from torchmorph.ffd.lattice import lattice_sum

__all__ = [
    "BASES",
    "BOUNDARY_ULPS",
    "DEFAULT_DEGREE",
    "Basis",
    "control_coordinates",
    "ffd_apply",
    "ffd_bases",
    "local_coordinates",
]

Basis = Literal["bernstein", "bspline"]
BASES: tuple[Basis, ...] = ("bernstein", "bspline")
DEFAULT_DEGREE = 3
"""Degree of the B-spline basis when none is given (cubic: C² across the knots)."""
BOUNDARY_ULPS = 4
"""A point is inside the box when each local coordinate lies in [0, 1] widened by this
many units of the dtype's rounding (``torch.finfo(dtype).eps``): a point on a face of the
box is inside even when ``(x − origin) / lengths`` rounds to 1 + 1 ulp."""

BASIS_BLOCK_ROWS = 2**15
"""Points per block of the basis recurrences: their temporaries stay in cache (a million
points in one block spends most of its time allocating them)."""

AXES = "xyz"


# --------------------------------------------------------------------------- #
# checks of the box
# --------------------------------------------------------------------------- #
def dim_of_points(points: Any) -> int:
    """D of points of shape (N, D), D = 2 or 3; ``ValueError`` naming ``points`` otherwise."""
    shape = getattr(points, "shape", None)
    if shape is None:
        shape = np.shape(points)
    if len(shape) != 2 or shape[1] not in (2, 3):
        raise ValueError(f"points must have shape (N, 2) or (N, 3), got {tuple(shape)}")
    return int(shape[1])


def as_vector(value: Any, name: str, points: Tensor) -> Tensor:
    """``value`` as a finite (D,) tensor on the points' device and dtype. A tensor must
    already be on them; a sequence or array is converted."""
    dim = points.shape[1]
    if isinstance(value, Tensor):
        check_float_dtype(value, name)
        check_same_device_dtype(points, "points", value, name)
    else:
        array = np.asarray(value)
        if array.dtype.kind not in "fiu":
            raise ValueError(f"{name} must hold numbers, got {value!r}")
        value = torch.as_tensor(array.astype(np.float64), device=points.device).to(points.dtype)
    if value.shape != (dim,):
        raise ValueError(
            f"{name} must have shape ({dim},) for points in {dim}-D, got {tuple(value.shape)}"
        )
    check_finite(value, name)
    return value


def check_lengths(lengths: Tensor) -> Tensor:
    if bool((lengths <= 0).any()):
        raise ValueError(f"lengths must be > 0 along every axis, got {lengths.tolist()}")
    return lengths


def check_rotation(rotation: Any, points: Tensor) -> Tensor:
    """The (D, D) orthogonal matrix whose columns are the box's axes (identity for None)."""
    dim = points.shape[1]
    if rotation is None:
        return torch.eye(dim, dtype=points.dtype, device=points.device)
    if isinstance(rotation, Tensor):
        check_float_dtype(rotation, "rotation")
        check_same_device_dtype(points, "points", rotation, "rotation")
    else:
        array = np.asarray(rotation, dtype=np.float64)
        rotation = torch.as_tensor(array, device=points.device).to(points.dtype)
    if rotation.shape != (dim, dim):
        raise ValueError(
            f"rotation must have shape ({dim}, {dim}) for points in {dim}-D, "
            f"got {tuple(rotation.shape)}"
        )
    check_finite(rotation, "rotation")
    identity = torch.eye(dim, dtype=rotation.dtype, device=rotation.device)
    defect = float((rotation.detach().T @ rotation.detach() - identity).abs().max())
    if defect > 1e3 * torch.finfo(rotation.dtype).eps:
        raise ValueError(
            "rotation must be orthogonal (its columns the box's unit axes): "
            f"max |RᵀR − I| = {defect:.3g}"
        )
    return rotation


def check_shape(
    shape: Any, dim: int, basis: Basis, degree: int | None, name: str = "shape"
) -> tuple[int, ...]:
    """The lattice sizes (n_1 … n_D): >= 2 for Bernstein, >= degree + 1 for B-splines.
    ``name`` is the argument they come from, for the messages."""
    names = ", ".join(f"n_{axis}" for axis in AXES[:dim])
    try:
        sizes = tuple(shape)
    except TypeError:
        sizes = None
    if sizes is None or len(sizes) != dim:
        raise ValueError(
            f"{name} must hold {dim} lattice sizes ({names}) for points in {dim}-D, got {shape!r}"
        )
    minimum = 2 if basis == "bernstein" else int(degree or DEFAULT_DEGREE) + 1
    what = "a Bernstein basis" if basis == "bernstein" else f"a B-spline basis of degree {degree}"
    for axis, size in enumerate(sizes):
        if isinstance(size, (bool, np.bool_)) or not isinstance(size, (int, np.integer)):
            raise ValueError(f"{name}[{axis}] must be an integer, got {size!r}")
        if size < minimum:
            raise ValueError(f"{name}[{axis}] must be >= {minimum} for {what}, got {size}")
    return tuple(int(size) for size in sizes)


def check_degree(basis: Basis, degree: int | None) -> int | None:
    """The B-spline degree (default 3); None for the Bernstein basis, whose degree is
    shape[k] − 1 on each axis."""
    if basis == "bernstein":
        if degree is not None:
            raise ValueError(
                "degree: the Bernstein basis has degree shape[k] - 1 on each axis; "
                f"leave degree=None (got {degree!r})"
            )
        return None
    if degree is None:
        return DEFAULT_DEGREE
    if isinstance(degree, (bool, np.bool_)) or not isinstance(degree, (int, np.integer)):
        raise ValueError(f"degree must be an integer >= 1, got {degree!r}")
    if degree < 1:
        raise ValueError(f"degree must be an integer >= 1, got {degree!r}")
    return int(degree)


def check_box(
    points: Tensor | np.ndarray | Sequence,
    origin: Any,
    lengths: Any,
    shape: Any,
    basis: str,
    degree: int | None,
    rotation: Any,
) -> tuple[Tensor, Tensor, Tensor, tuple[int, ...], Basis, int | None, Tensor]:
    """Every argument of a box checked, in the order a user reads them."""
    points = as_points(points, "points", dim=dim_of_points(points))
    origin = as_vector(origin, "origin", points)
    lengths = check_lengths(as_vector(lengths, "lengths", points))
    basis = check_choice(basis, "basis", BASES)
    degree = check_degree(basis, degree)
    sizes = check_shape(shape, points.shape[1], basis, degree)
    return points, origin, lengths, sizes, basis, degree, check_rotation(rotation, points)


# --------------------------------------------------------------------------- #
# geometry
# --------------------------------------------------------------------------- #
def local_coordinates(
    points: Tensor, origin: Tensor, lengths: Tensor, rotation: Tensor | None = None
) -> Tensor:
    """``Rᵀ (x − origin) / lengths`` row by row: shape (N, D), the box being [0, 1]^D.

    ``rotation`` (D, D) has the box's unit axes as columns (PyGeM's
    ``FFD.rotation_matrix``); None for an axis-aligned box.
    """
    relative = points - origin
    if rotation is not None:
        relative = relative @ rotation
    return relative / lengths


def control_coordinates(count: int, basis: Basis, degree: int | None = None) -> list[float]:
    """Local positions in [0, 1] of the ``count`` control points of one axis: uniform
    ``i / (count − 1)`` for Bernstein, the Greville abscissae for B-splines (where an
    affine displacement field is reproduced exactly)."""
    if basis == "bernstein":
        return [i / (count - 1) for i in range(count)]
    return greville_abscissae(count, degree or DEFAULT_DEGREE)


def axis_basis(s: Tensor, count: int, basis: Basis, degree: int | None) -> Tensor:
    """The (M, count) basis matrix of one axis at local coordinates ``s`` (M,), evaluated
    :data:`BASIS_BLOCK_ROWS` points at a time."""

    def evaluate(part: Tensor) -> Tensor:
        if basis == "bernstein":
            return bernstein_basis(part, count)
        return bspline_basis(part, count, degree or DEFAULT_DEGREE)

    if s.shape[0] <= BASIS_BLOCK_ROWS:
        return evaluate(s)
    starts = range(0, s.shape[0], BASIS_BLOCK_ROWS)
    if torch.is_grad_enabled() and s.requires_grad:
        return torch.cat([evaluate(s[start : start + BASIS_BLOCK_ROWS]) for start in starts])
    values = s.new_empty(s.shape[0], count)
    for start in starts:
        values[start : start + BASIS_BLOCK_ROWS] = evaluate(s[start : start + BASIS_BLOCK_ROWS])
    return values


def ffd_bases(
    points: Tensor,
    *,
    origin: Tensor | Sequence[float],
    lengths: Tensor | Sequence[float],
    shape: Sequence[int],
    basis: Basis = "bernstein",
    degree: int | None = None,
    rotation: Tensor | None = None,
) -> tuple[Tensor, list[Tensor]]:
    """The points inside the box and their basis matrix on each axis.

    Parameters
    ----------
    points : Tensor, shape (N, D)
        D = 2 or 3.
    origin : Tensor or sequence, shape (D,)
        The corner of the box at control point (0, …, 0).
    lengths : Tensor or sequence, shape (D,)
        Edge lengths of the box along its axes, > 0.
    shape : sequence of D ints
        Control points per axis (n_1 … n_D).
    basis : {"bernstein", "bspline"}
    degree : int, optional
        B-spline degree (default 3); must be None for Bernstein.
    rotation : Tensor, shape (D, D), optional
        Orthogonal matrix whose columns are the box's axes; None: axis-aligned.

    Returns
    -------
    inside : Tensor, shape (N_in,), int64
        Indices of the points in the closed box (each local coordinate in [0, 1], widened
        by :data:`BOUNDARY_ULPS` units of rounding), ascending.
    bases : list of D Tensors, shapes (N_in, n_k)
        ``bases[k][p, i]`` is the i-th basis function of axis k at point ``inside[p]``;
        local coordinates are clamped to [0, 1] first. Differentiable in ``points``.

    Raises
    ------
    ValueError
        Naming the argument: points not (N, 2) or (N, 3) or not finite, origin or
        lengths of the wrong shape or not finite, lengths <= 0, a shape entry too small
        for the basis, an unknown basis, a rotation that is not orthogonal.
    """
    points, origin_t, lengths_t, sizes, basis, degree, rotation_t = check_box(
        points, origin, lengths, shape, basis, degree, rotation
    )
    local = local_coordinates(points, origin_t, lengths_t, rotation_t)
    slack = BOUNDARY_ULPS * torch.finfo(points.dtype).eps
    with torch.no_grad():
        mask = ((local >= -slack) & (local <= 1 + slack)).all(dim=1)
        inside = torch.nonzero(mask).flatten()
    local = local[inside].clamp(0.0, 1.0)
    bases = [axis_basis(local[:, k], size, basis, degree) for k, size in enumerate(sizes)]
    return inside, bases


# --------------------------------------------------------------------------- #
# displacements of the points
# --------------------------------------------------------------------------- #
def scatter_inside(moved: Tensor, inside: Tensor, count: int) -> Tensor:
    """(..., N_in, D) displacements of the inside points spread to all ``count`` points,
    zero outside (differentiable in ``moved``).

    The copy runs over rows of the (N_in, batch · D) layout :func:`lattice_sum` computes
    in (a row per point, whole batches at once), 1.5× faster than a scatter along the
    point axis of (batch, N, D); a batched result is therefore a view of a
    (N, batch, D) buffer, not contiguous.
    """
    if inside.numel() == count:  # every point inside: ``inside`` is 0 … count − 1
        return moved
    lead, dim = moved.shape[:-2], moved.shape[-1]
    batch = math.prod(lead)
    rows = moved.reshape(batch, inside.numel(), dim).permute(1, 0, 2)
    full = rows.new_zeros(count, *rows.shape[1:]).index_copy(0, inside, rows)
    return full.permute(1, 0, 2).reshape(*lead, count, dim)


def check_displacements(displacements: Any, sizes: tuple[int, ...]) -> None:
    """Displacements of shape (..., n_1, …, n_D, D), floating and finite."""
    dim = len(sizes)
    if not isinstance(displacements, Tensor):
        raise TypeError(f"displacements must be a torch.Tensor, got {type(displacements).__name__}")
    expected = (*sizes, dim)
    if displacements.ndim < dim + 1 or tuple(displacements.shape[-dim - 1 :]) != expected:
        lattice = " x ".join(str(size) for size in sizes)
        raise ValueError(
            f"displacements must have shape (..., {', '.join(map(str, expected))}) for a "
            f"{lattice} lattice in {dim}-D, got {tuple(displacements.shape)}"
        )
    check_float_dtype(displacements, "displacements")
    check_finite(displacements, "displacements")


def ffd_apply(
    *,
    points: Tensor,
    displacements: Tensor,
    origin: Tensor | Sequence[float],
    lengths: Tensor | Sequence[float],
    basis: Basis = "bernstein",
    degree: int | None = None,
    rotation: Tensor | None = None,
    block_bytes: int | None = None,
) -> Tensor:
    """Displacements of ``points`` under the lattice displacements (one call: bases, then sum).

    Parameters
    ----------
    points : Tensor, shape (N, D)
    displacements : Tensor, shape (..., n_1, …, n_D, D)
        Control-point displacements in physical units; the lattice shape is read from it.
    origin, lengths, basis, degree, rotation
        The box, as in :func:`ffd_bases`.
    block_bytes : int, optional
        As in :func:`lattice_sum`.

    Returns
    -------
    Tensor, shape (..., N, D)
        Zero for the points outside the box. Differentiable in ``displacements`` and
        ``points`` (and in ``origin``, ``lengths``, ``rotation`` given as tensors).
    """
    dim = dim_of_points(points)
    if not isinstance(displacements, Tensor):
        raise TypeError(f"displacements must be a torch.Tensor, got {type(displacements).__name__}")
    if displacements.ndim < dim + 1 or displacements.shape[-1] != dim:
        names = ", ".join(f"n_{axis}" for axis in AXES[:dim])
        raise ValueError(
            f"displacements must have shape (..., {names}, {dim}) for points in {dim}-D, "
            f"got {tuple(displacements.shape)}"
        )
    basis = check_choice(basis, "basis", BASES)
    degree = check_degree(basis, degree)
    lattice = displacements.shape[-dim - 1 : -1]
    shape = check_shape(lattice, dim, basis, degree, "displacements' lattice shape")
    inside, bases = ffd_bases(
        points,
        origin=origin,
        lengths=lengths,
        shape=shape,
        basis=basis,
        degree=degree,
        rotation=rotation,
    )
    check_displacements(displacements, shape)
    check_same_device_dtype(bases[0], "points", displacements, "displacements")
    moved = lattice_sum(bases, displacements, block_bytes=block_bytes)
    return scatter_inside(moved, inside, points.shape[0])
