"""A swept, tapered wing like the ONERA M6, as a CAD solid built with gmsh's OpenCASCADE kernel.

The ONERA M6 (a public STEP file, not shipped here) is a semi-span wing of 1.196 m, root
chord 0.806 m, taper ratio 0.562, leading edge swept by 30 degrees, symmetric ONERA D
sections (about 10 % thick). This wing has the same planform with NACA 0010 sections
(sharp trailing edge): two closed spline sections (root in the plane y = 0, tip at
y = span) joined by ``addThruSections`` into one ruled solid of 4 CAD faces (upper and
lower skin, root and tip caps) and volume 0.0329 -- what the meshing tests and the
benchmark need: a curved, thin, swept body about 1 m across.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

SPAN = 1.196
ROOT_CHORD = 0.806
TAPER = 0.562
SWEEP_DEGREES = 30.0
THICKNESS = 0.10


def _section(occ, chord: float, x0: float, y: float, z0: float, points: int) -> int:
    """A closed NACA 00xx section of ``chord`` with its leading edge at (x0, y, z0); a wire."""
    beta = np.linspace(0.0, math.pi, points)
    x = 0.5 * (1 - np.cos(beta))  # clustered at both ends
    half = (
        5
        * THICKNESS
        * (0.2969 * np.sqrt(x) - 0.1260 * x - 0.3516 * x**2 + 0.2843 * x**3 - 0.1036 * x**4)
    )
    half[-1] = 0.0  # a sharp trailing edge
    upper = [
        occ.addPoint(x0 + chord * a, y, z0 + chord * b)
        for a, b in zip(x[::-1], half[::-1], strict=True)
    ]
    lower = [
        occ.addPoint(x0 + chord * a, y, z0 - chord * b)
        for a, b in zip(x[1:-1], half[1:-1], strict=True)
    ]
    trailing = upper[0]
    upper_curve = occ.addSpline(upper)  # TE -> LE over the top
    lower_curve = occ.addSpline([upper[-1], *lower, trailing])  # LE -> TE underneath
    wire = occ.addWire([upper_curve, lower_curve])
    occ.remove([(0, tag) for tag in upper[1:-1] + lower])  # free interpolation points
    return wire


def build_wing(occ, *, scale: float = 1.0, offset=(0.0, 0.0, 0.0), points: int = 41) -> int:
    """Add the wing to an OpenCASCADE model (``gmsh.model.occ``); its volume tag.

    ``scale`` multiplies every length, ``offset`` translates the root's leading edge.
    """
    dx, dy, dz = (float(v) for v in offset)
    root = _section(occ, scale * ROOT_CHORD, dx, dy, dz, points)
    sweep = math.tan(math.radians(SWEEP_DEGREES)) * SPAN
    tip_chord = scale * ROOT_CHORD * TAPER
    tip = _section(occ, tip_chord, dx + scale * sweep, dy + scale * SPAN, dz, points)
    shapes = occ.addThruSections([root, tip], makeSolid=True, makeRuled=True)
    return next(tag for dim, tag in shapes if dim == 3)


def write_wing(path: Path, *, metres: bool = False, **options) -> Path:
    """Write :func:`build_wing`'s solid to a CAD file (``.step`` or ``.brep``) with gmsh.

    gmsh writes STEP lengths in millimetres (the numbers as built); ``metres=True``
    declares the same numbers as metres, as most aerodynamic STEP files (the M6's) do.
    """
    import gmsh

    started = not gmsh.isInitialized()
    if started:
        gmsh.initialize(readConfigFiles=False, interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("wing")
        build_wing(gmsh.model.occ, **options)
        gmsh.model.occ.synchronize()
        gmsh.write(str(path))
        gmsh.model.remove()
    finally:
        if started:
            gmsh.finalize()
    if metres:
        text = Path(path).read_text()
        assert "SI_UNIT(.MILLI.,.METRE.)" in text
        Path(path).write_text(text.replace("SI_UNIT(.MILLI.,.METRE.)", "SI_UNIT($,.METRE.)"))
    return Path(path)
