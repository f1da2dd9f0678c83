"""Analytic geometry of the three test cases (Ballarin et al. 2017, Section 2.3, Tables 1–3).

Axes: x chord-wise / along the hull, y vertical, z span-wise.
Everything here is plain NumPy and exact: the meshers build their surfaces from
these formulas, and every boundary node of a generated mesh is finally projected
onto them (:func:`project_to_profile`, :func:`wigley_half_breadth`).

Wing (cases A and B)
    NACA0012 profile with the closed trailing edge (last coefficient -0.1036),
    chord :data:`CHORD` = 1.01 m, leading edge at x = 0, trailing edge at
    x = 1.01, chord line y = 0; extruded from the root z = 0 to the tip
    z = :data:`SPAN` = 2π m.
Tunnel (case B)
    The box :data:`TUNNEL_BOUNDS` of 10 × 5 × 4π m, centred on the wing's
    mid-chord in x and on its chord line in y, the wing's root on the wall
    z = 0. The wing's coordinates are the same as in case A.
Hull (case C)
    Wigley hull of length :data:`HULL_LENGTH` = 2.5 m, beam B = 0.1 L and
    draft T = 0.0625 L (the classic Wigley proportions; the paper gives only
    the length), as a closed double body mirrored about its waterline y = 0:
    ``|z| = (B/2) (1 - (2x/L)^2) (1 - (y/T)^2)`` for ``|x| <= L/2, |y| <= T``,
    centred at the origin in the box :data:`HULL_BOX_BOUNDS` of 50 × 25 × 10 m
    (also centred at the origin). The draft is vertical (y) and the beam
    span-wise (z), so the paper's rotation about the z axis is a pitch of the
    hull about its own centre.
"""

from __future__ import annotations

import math

import numpy as np

from torchmorph.meshing import BOX_WALLS

__all__ = [
    "BOX_WALLS",
    "CHORD",
    "HULL_BEAM",
    "HULL_BOX_BOUNDS",
    "HULL_BOX_SIZE",
    "HULL_DRAFT",
    "HULL_LENGTH",
    "NACA_COEFFICIENTS",
    "NACA_THICKNESS",
    "SPAN",
    "TUNNEL_BOUNDS",
    "TUNNEL_SIZE",
    "TUNNEL_WALL_NAMES",
    "naca_half_thickness",
    "naca_profile",
    "project_to_profile",
    "wigley_half_breadth",
]

#: Chord length of the wing [m] (paper, Table 1).
CHORD = 1.01
#: Span of the wing, root z = 0 to tip z = SPAN [m] (paper, Table 1).
SPAN = 2.0 * math.pi
#: Maximum thickness of the NACA0012 profile as a fraction of the chord.
NACA_THICKNESS = 0.12
#: Coefficients of the 4-digit thickness polynomial with a closed trailing edge:
#: y_t = 5 t c (a0 sqrt(ξ) + a1 ξ + a2 ξ² + a3 ξ³ + a4 ξ⁴), ξ = x / c. They sum
#: to zero, so y_t(c) = 0 exactly.
NACA_COEFFICIENTS = (0.2969, -0.1260, -0.3516, 0.2843, -0.1036)

#: Wind-tunnel size (x, y, z) [m] (paper, Table 2).
TUNNEL_SIZE = (10.0, 5.0, 4.0 * math.pi)
#: Tunnel box as ((x0, y0, z0), (x1, y1, z1)): centred on the wing's mid-chord
#: in x and on the chord line in y; the wing's root lies on the wall z = 0.
TUNNEL_BOUNDS = (
    (CHORD / 2 - TUNNEL_SIZE[0] / 2, -TUNNEL_SIZE[1] / 2, 0.0),
    (CHORD / 2 + TUNNEL_SIZE[0] / 2, TUNNEL_SIZE[1] / 2, TUNNEL_SIZE[2]),
)
#: The box walls' node-set names and the paper's names for them (case B,
#: Section 2.3.2): top/bottom are the y walls and the paper's left/right are the
#: span-wise ends, as for the wing itself (clamped "left" side z = 0), which
#: leaves front/rear to the inflow/outflow walls x = x0, x1. The paper's
#: selection radii are R = 0.5 on top, bottom, front and rear and R = 0.25 on
#: left and right.
TUNNEL_WALL_NAMES = {
    "wall_x0": "front (inlet)",
    "wall_x1": "rear (outlet)",
    "wall_y0": "bottom",
    "wall_y1": "top",
    "wall_z0": "left (the wing's root side)",
    "wall_z1": "right",
}

#: Wigley hull length L [m] (paper, Table 3).
HULL_LENGTH = 2.5
#: Beam B = 0.1 L [m]; the classic Wigley value, the paper does not give it.
HULL_BEAM = 0.1 * HULL_LENGTH
#: Draft T = 0.0625 L [m]; the classic Wigley value, the paper does not give it.
HULL_DRAFT = 0.0625 * HULL_LENGTH
#: Size of the box around the hull (x, y, z) [m] (paper, Table 3).
HULL_BOX_SIZE = (50.0, 25.0, 10.0)
#: The box around the hull, centred at the origin like the hull.
HULL_BOX_BOUNDS = (
    tuple(-s / 2 for s in HULL_BOX_SIZE),
    tuple(s / 2 for s in HULL_BOX_SIZE),
)


def naca_half_thickness(x: np.ndarray | float) -> np.ndarray:
    """Half thickness y_t(x) of the closed-trailing-edge NACA0012 profile.

    Parameters
    ----------
    x : array, any shape, or float
        Chord-wise coordinate [m]; clipped to [0, CHORD].

    Returns
    -------
    array, same shape as ``x`` (a NumPy float for a float)
        ``5 t c (0.2969 √ξ - 0.1260 ξ - 0.3516 ξ² + 0.2843 ξ³ - 0.1036 ξ⁴)``,
        ξ = x / c, t = 0.12, c = 1.01; zero at both ends.
    """
    xi = np.clip(np.asarray(x, dtype=np.float64) / CHORD, 0.0, 1.0)
    a0, a1, a2, a3, a4 = NACA_COEFFICIENTS
    poly = a0 * np.sqrt(xi) + xi * (a1 + xi * (a2 + xi * (a3 + xi * a4)))
    return np.maximum(5.0 * NACA_THICKNESS * CHORD * poly, 0.0)


def naca_profile(num_points: int) -> tuple[np.ndarray, np.ndarray]:
    """Cosine-spaced stations of the upper profile, leading to trailing edge.

    Parameters
    ----------
    num_points : int
        Number of stations, >= 3, both ends included.

    Returns
    -------
    x, y : arrays, shape (num_points,)
        ``x = c (1 - cos θ) / 2`` for θ uniform in [0, π] and ``y = y_t(x)``;
        the lower profile is ``(x, -y)``. ``y[0] = y[-1] = 0``.
    """
    if num_points < 3:
        raise ValueError(f"num_points must be >= 3, got {num_points}")
    theta = np.linspace(0.0, math.pi, num_points)
    x = CHORD * (1.0 - np.cos(theta)) / 2.0
    x[0], x[-1] = 0.0, CHORD
    return x, naca_half_thickness(x)


_PROFILE_SAMPLES = 8192


def _profile_at(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    x = CHORD * (1.0 - np.cos(theta)) / 2.0
    return x, naca_half_thickness(x)


def project_to_profile(
    x: np.ndarray, y: np.ndarray, side: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Closest point of one side of the profile to each point (x, y).

    The profile side is parametrised by θ in [0, π], ``x = c (1 - cos θ)/2``;
    the nearest of 8192 samples is refined by golden-section search on its two
    neighbouring intervals, which puts the result within ~1e-12 m of the exact
    nearest point.

    Parameters
    ----------
    x, y : arrays, shape (K,)
        Points in the profile plane.
    side : array, shape (K,)
        +1 for the upper side (y = +y_t), -1 for the lower side (y = -y_t).

    Returns
    -------
    px, py : arrays, shape (K,)
        Points on the profile, ``py == side * naca_half_thickness(px)`` exactly.
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    side = np.where(np.asarray(side) < 0, -1.0, 1.0)
    if x.size == 0:
        return x.copy(), y.copy()
    yy = side * y  # mirror lower-side points onto the upper side
    samples = np.linspace(0.0, math.pi, _PROFILE_SAMPLES)
    sx, sy = _profile_at(samples)
    nearest = np.empty(x.size, dtype=np.int64)
    for start in range(0, x.size, 2048):  # bounded memory: 2048 × 8192 distances at a time
        stop = min(start + 2048, x.size)
        d2 = (x[start:stop, None] - sx[None, :]) ** 2 + (yy[start:stop, None] - sy[None, :]) ** 2
        nearest[start:stop] = np.argmin(d2, axis=1)
    lo = samples[np.maximum(nearest - 1, 0)]
    hi = samples[np.minimum(nearest + 1, _PROFILE_SAMPLES - 1)]

    def dist2(theta: np.ndarray) -> np.ndarray:
        px, py = _profile_at(theta)
        return (px - x) ** 2 + (py - yy) ** 2

    ratio = (math.sqrt(5.0) - 1.0) / 2.0
    a, b = lo, hi
    for _ in range(60):  # the bracket shrinks by 0.618 per step: 60 steps reach round-off
        c = b - ratio * (b - a)
        d = a + ratio * (b - a)
        left = dist2(c) < dist2(d)
        b = np.where(left, d, b)
        a = np.where(left, a, c)
    theta = (a + b) / 2.0
    # the ends of the parameter range (leading and trailing edge) are candidates too
    for end in (0.0, math.pi):
        end_theta = np.full_like(theta, end)
        theta = np.where(dist2(end_theta) < dist2(theta), end_theta, theta)
    px, py = _profile_at(theta)
    return px, side * py


def wigley_half_breadth(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Half breadth |z| of the Wigley double body at (x, y).

    Parameters
    ----------
    x, y : arrays, same shape
        Longitudinal and vertical coordinates [m]; clipped to the hull's
        rectangle ``|x| <= L/2, |y| <= T``.

    Returns
    -------
    array, same shape
        ``(B/2) (1 - (2x/L)^2) (1 - (y/T)^2)``, zero on the stem, stern and keels.
    """
    half_length = HULL_LENGTH / 2.0
    xc = np.clip(np.asarray(x, dtype=np.float64), -half_length, half_length)
    yc = np.clip(np.asarray(y, dtype=np.float64), -HULL_DRAFT, HULL_DRAFT)
    return (HULL_BEAM / 2.0) * (1.0 - (xc / half_length) ** 2) * (1.0 - (yc / HULL_DRAFT) ** 2)
