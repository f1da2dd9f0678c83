"""Independent references for the FFD tests: PyGeM's formula written out in NumPy loops."""

from __future__ import annotations

import math

import numpy as np
from scipy.interpolate import BSpline

from torchmorph.ffd import clamped_uniform_knots


def bernstein(count: int, s: float) -> np.ndarray:
    degree = count - 1
    return np.array([math.comb(degree, i) * s**i * (1 - s) ** (degree - i) for i in range(count)])


def bspline(count: int, s: float, degree: int) -> np.ndarray:
    knots = np.array(clamped_uniform_knots(count, degree))
    return BSpline.design_matrix(np.array([s]), knots, degree).toarray()[0]


def pygem_ffd(points, origin, lengths, mu, rotation=None, basis="bernstein", degree=3):
    """Moved points by PyGeM's ``FFD.__call__``: local coordinates in the rotated box,
    the closed unit box as inside, ``shift = Σ_ijk B_i B_j B_k μ_ijk`` over every lattice
    index in explicit loops, ``x' = x + R (lengths ⊙ shift)``. ``mu`` (n_1, …, n_D, D) is
    normalised by the box lengths and along the box axes, as PyGeM's ``array_mu_*``."""
    points = np.asarray(points, dtype=np.float64)
    dim = points.shape[1]
    rotation = np.eye(dim) if rotation is None else np.asarray(rotation)
    local = (points - origin) @ rotation / lengths
    sizes = mu.shape[:-1]
    moved = points.copy()
    for p, s in enumerate(local):
        if not ((s >= 0) & (s <= 1)).all():
            continue
        if basis == "bernstein":
            factors = [bernstein(size, float(x)) for size, x in zip(sizes, s, strict=True)]
        else:
            factors = [bspline(size, float(x), degree) for size, x in zip(sizes, s, strict=True)]
        shift = np.zeros(dim)
        for index in np.ndindex(*sizes):
            weight = 1.0
            for axis, i in enumerate(index):
                weight *= factors[axis][i]
            shift += weight * mu[index]
        moved[p] = points[p] + rotation @ (lengths * shift)
    return moved


def rotation_matrix(angles_degrees) -> np.ndarray:
    """PyGeM's ``angles2matrix``: R = R_x R_y R_z for rotations about x, y, z (degrees)."""
    x, y, z = np.radians(angles_degrees)
    rx = np.array([[1, 0, 0], [0, math.cos(x), -math.sin(x)], [0, math.sin(x), math.cos(x)]])
    ry = np.array([[math.cos(y), 0, math.sin(y)], [0, 1, 0], [-math.sin(y), 0, math.cos(y)]])
    rz = np.array([[math.cos(z), -math.sin(z), 0], [math.sin(z), math.cos(z), 0], [0, 0, 1]])
    return rx @ ry @ rz


def rotation_2d(angle_degrees: float) -> np.ndarray:
    """The counter-clockwise rotation of the plane by ``angle_degrees``."""
    angle = math.radians(angle_degrees)
    return np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
