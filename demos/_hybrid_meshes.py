"""gmsh meshes of the hybrid-mesh demo (``hybrid_wing.py``): the tunnel of case B around
the wing of case A with a prism boundary layer on the wing and tetrahedra elsewhere, and
the wing's section in a 2-D box with quads along the profile and triangles elsewhere.

Both are written as ``.msh`` files whose physical groups are the markers the demo reads
back with :func:`torchmorph.mesh.read_mesh`. gmsh runs in one thread with a fixed seed
(:func:`torchmorph.meshing.gmsh_model.gmsh_session`): the meshes are reproducible.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from data_gen.geometry import CHORD, SPAN, TUNNEL_BOUNDS, naca_half_thickness, naca_profile
from torchmorph.mesh import atomic_output
from torchmorph.meshing.gmsh_model import gmsh_session

__all__ = [
    "BOX_2D",
    "WALLS",
    "WING",
    "WING_EDGES",
    "layer_heights",
    "mesh_airfoil",
    "mesh_wing",
]

#: The wing's wall: the three gmsh surfaces it is made of.
WING = ("upper", "lower", "tip")
#: The tunnel's walls (case B's names: x inflow/outflow, y bottom/top, z the ends).
WALLS = ("wall_x0", "wall_x1", "wall_y0", "wall_y1", "wall_z0", "wall_z1")
#: ESIDW enrichment sets of the wing (Algorithm 2, step (ii)): gmsh's physical curves.
WING_EDGES = ("root_profile", "tip_profile", "leading_edge", "trailing_edge")
#: The 2-D box around the section, ((x0, y0), (x1, y1)) [m].
BOX_2D = ((-1.5, -2.0), (3.5, 2.0))

_FLAT = 1e-6  # nodes closer than this [m] to a plane lie on it
_GMSH_KINDS = {2: "triangle", 3: "quad", 4: "tetra", 5: "hexahedron", 6: "wedge", 7: "pyramid"}


def layer_heights(layers: int, first_height: float, growth: float) -> np.ndarray:
    """Distances from the wall of the tops of the layers, shape (layers,): the first layer
    ``first_height`` thick, each next one ``growth`` times thicker than the one below."""
    return np.cumsum(first_height * growth ** np.arange(layers))


def _profile_curves(occ, samples: int = 61) -> tuple[int, int]:
    """The NACA0012 profile in the plane z = 0 as two OpenCASCADE splines through
    ``samples`` cosine-spaced stations of each side, both from the trailing to the
    leading edge: (upper, lower), tangent to the sides at the sharp trailing edge and
    vertical at the leading edge (G1 there).

    Both sides start at the trailing edge: the lower side interpolated towards it with
    its end tangent prescribed overshoots it (by 7.5 mm, crossing y = 0 by 1.1 mm), and
    the boundary-layer curves extruded from it then cross.
    """
    x, y = naca_profile(samples)
    x, y = x[::-1], y[::-1]
    upper = [occ.addPoint(float(a), float(b), 0.0) for a, b in zip(x, y, strict=True)]
    lower = [upper[0]]
    lower += [occ.addPoint(float(a), float(-b), 0.0) for a, b in zip(x[1:-1], y[1:-1], strict=True)]
    lower.append(upper[-1])
    step = 1e-6 * CHORD
    slope = float((naca_half_thickness(CHORD) - naca_half_thickness(CHORD - step)) / step)
    upper_curve = occ.addSpline(upper, tangents=[-1.0, -slope, 0.0, 0.0, -1.0, 0.0])
    lower_curve = occ.addSpline(lower, tangents=[-1.0, slope, 0.0, 0.0, 1.0, 0.0])
    occ.remove([(0, tag) for tag in upper[1:-1] + lower[1:-1]])  # free vertices now
    return upper_curve, lower_curve


def _graded_size(gmsh, params: dict, span: float | None) -> None:
    """Background size ``min(h_far, h_near + grading * d)``, d the distance to the wing's
    bounding box (to the section's in 2-D, ``span`` None)."""
    half = float(naca_half_thickness(0.3 * CHORD))  # the thickest station
    terms = [f"max(0, max(-x, x - {CHORD!r}))^2", f"max(0, abs(y) - {half!r})^2"]
    if span is not None:
        terms.append(f"max(0, z - {span!r})^2")
    h_near, h_far, grading = (float(params[key]) for key in ("h_near", "h_far", "grading"))
    field = gmsh.model.mesh.field
    size = field.add("MathEval")
    distance = f"sqrt({' + '.join(terms)})"
    field.setString(size, "F", f"min({h_far!r}, {h_near!r} + {grading!r} * {distance})")
    field.setAsBackgroundMesh(size)
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)


def _element_counts(gmsh, dim: int) -> dict[str, int]:
    """Elements of dimension ``dim`` that gmsh made, by kind (meshio's names)."""
    counts: dict[str, int] = {}
    for element_type in gmsh.model.mesh.getElementTypes(dim):
        tags, _ = gmsh.model.mesh.getElementsByType(element_type)
        name = _GMSH_KINDS.get(int(element_type), f"gmsh type {element_type}")
        counts[name] = counts.get(name, 0) + len(tags)
    return counts


def _tunnel(geo, hole: int, inner: Sequence[int]) -> tuple[int, list[int]]:
    """The tunnel :data:`TUNNEL_BOUNDS` in gmsh's built-in kernel, the curve loop
    ``hole`` cut from its wall z = 0, the surfaces ``inner`` closing it inside; returns
    the volume and the tunnel's faces."""
    (x0, y0, z0), (x1, y1, z1) = TUNNEL_BOUNDS
    corners = [
        geo.addPoint(x, y, z) for z in (z0, z1) for x, y in ((x0, y0), (x1, y0), (x1, y1), (x0, y1))
    ]
    bottom = [geo.addLine(corners[i], corners[(i + 1) % 4]) for i in range(4)]
    top = [geo.addLine(corners[4 + i], corners[4 + (i + 1) % 4]) for i in range(4)]
    posts = [geo.addLine(corners[i], corners[4 + i]) for i in range(4)]
    faces = [
        geo.addPlaneSurface([geo.addCurveLoop(bottom), hole]),
        geo.addPlaneSurface([geo.addCurveLoop(top)]),
    ]
    for i in range(4):
        side = geo.addCurveLoop([bottom[i], posts[(i + 1) % 4], -top[i], -posts[i]])
        faces.append(geo.addPlaneSurface([side]))
    return geo.addVolume([geo.addSurfaceLoop([*inner, *faces])]), faces


def _walls_by_nodes(gmsh, skip: Sequence[int]) -> dict[str, list[int]]:
    """The surfaces whose nodes all lie on one wall of the tunnel, by wall (the layers'
    faces on the wall z = 0 among them)."""
    (x0, y0, z0), (x1, y1, z1) = TUNNEL_BOUNDS
    planes = ((0, x0), (0, x1), (1, y0), (1, y1), (2, z0), (2, z1))
    walls: dict[str, list[int]] = {}
    for _, tag in gmsh.model.getEntities(2):
        if tag in skip:
            continue
        _, coords, _ = gmsh.model.mesh.getNodes(2, tag, includeBoundary=True)
        coords = coords.reshape(-1, 3)
        for name, (axis, value) in zip(WALLS, planes, strict=True):
            if len(coords) and np.abs(coords[:, axis] - value).max() < _FLAT:
                walls.setdefault(name, []).append(tag)
    missing = [name for name in WALLS if name not in walls]
    if missing:
        raise RuntimeError(f"gmsh: no surface on the wall(s) {', '.join(missing)}")
    return walls


def mesh_wing(path: Path, params: dict, *, span: float = SPAN, seed: int = 0) -> dict[str, Any]:
    """Mesh the tunnel around the wing: prisms on the wing, tetrahedra elsewhere.

    Parameters
    ----------
    path : Path
        The ``.msh`` file to write (atomically), with physical groups: the volumes
        ``boundary_layer`` and ``core``, the surfaces :data:`WING` and :data:`WALLS`,
        the curves :data:`WING_EDGES`.
    params : dict
        ``SIZES[size]["wing"]``.
    span : float, keyword-only
        Span of the wing [m]; its root lies on the wall z = 0 of :data:`TUNNEL_BOUNDS`.
    seed : int, keyword-only
        gmsh's ``Mesh.RandomSeed`` (gmsh runs in one thread: the mesh is reproducible).

    Returns
    -------
    dict
        ``counts`` (elements of the volume by kind, as gmsh made them),
        ``wing_triangles`` (triangles on the wing), ``heights`` (the layers' tops above
        the wall [m], (layers,)) and ``seconds``.
    """
    start = time.perf_counter()
    heights = layer_heights(params["layers"], params["first_height"], params["growth"])
    with gmsh_session("hybrid_wing", seed=seed, verbose=False) as gmsh:
        occ, geo, mesh = gmsh.model.occ, gmsh.model.geo, gmsh.model.mesh
        upper, lower = _profile_curves(occ)
        profile = occ.addPlaneSurface([occ.addCurveLoop([upper, -lower])])
        extruded = occ.extrude([(2, profile)], 0.0, 0.0, span)
        occ.remove([(dim, tag) for dim, tag in extruded if dim == 3])
        occ.remove([(2, profile)])  # the root is a hole in the wall z = 0
        occ.synchronize()
        surfaces: dict[str, int] = {}
        for _, tag in gmsh.model.getEntities(2):
            box = gmsh.model.getBoundingBox(2, tag)
            if box[5] - box[2] < 1e-5:
                surfaces["tip"] = tag
            else:
                surfaces["upper" if occ.getCenterOfMass(2, tag)[1] > 0 else "lower"] = tag
        edges: dict[str, list[int]] = {}
        for _, tag in gmsh.model.getEntities(1):
            box = gmsh.model.getBoundingBox(1, tag)
            if box[5] - box[2] > 1e-5:  # along the span
                name = "leading_edge" if box[0] < CHORD / 2 else "trailing_edge"
                mesh.setTransfiniteCurve(tag, params["span_nodes"])
            else:
                name = "root_profile" if box[2] < span / 2 else "tip_profile"
                mesh.setTransfiniteCurve(tag, params["profile_nodes"], "Bump", params["bump"])
            edges.setdefault(name, []).append(tag)
        # structured sides: every triangle has an edge along z, so the extrusion normals
        # along the root lie in the plane z = 0 and the layers' root faces on the wall
        for name in ("upper", "lower"):
            mesh.setTransfiniteSurface(surfaces[name])
        _graded_size(gmsh, params, span)

        gmsh.option.setNumber("Geometry.ExtrudeReturnLateralEntities", 0)
        wing = [(2, surfaces[name]) for name in WING]
        layers = geo.extrudeBoundaryLayer(wing, [1] * len(heights), heights.tolist(), True)
        tops = [layers[i - 1] for i in range(1, len(layers)) if layers[i][0] == 3]
        prisms = [tag for dim, tag in layers if dim == 3]
        geo.synchronize()
        hole = geo.addCurveLoop([tag for _, tag in gmsh.model.getBoundary(tops)], reorient=True)
        core, _ = _tunnel(geo, hole, [tag for _, tag in tops])
        geo.synchronize()
        mesh.generate(3)
        counts = _element_counts(gmsh, 3)

        walls = _walls_by_nodes(gmsh, list(surfaces.values()))
        wing_triangles = sum(len(mesh.getElements(2, surfaces[name])[1][0]) for name in WING)
        for name in WING:
            gmsh.model.addPhysicalGroup(2, [surfaces[name]], name=name)
        for name in WALLS:
            gmsh.model.addPhysicalGroup(2, walls[name], name=name)
        for name in WING_EDGES:
            gmsh.model.addPhysicalGroup(1, edges[name], name=name)
        gmsh.model.addPhysicalGroup(3, prisms, name="boundary_layer")
        gmsh.model.addPhysicalGroup(3, [core], name="core")
        with atomic_output(path) as temporary:
            gmsh.write(str(temporary))
    return {
        "counts": counts,
        "wing_triangles": wing_triangles,
        "heights": heights,
        "seconds": time.perf_counter() - start,
    }


def mesh_airfoil(path: Path, params: dict, *, seed: int = 0) -> dict[str, Any]:
    """Mesh the box :data:`BOX_2D` around the wing's section: quads along the profile
    (gmsh's ``BoundaryLayer`` field, a fan at the trailing edge), triangles elsewhere.

    Writes ``path`` (``.msh``) with the physical groups ``fluid``, the curves ``airfoil``
    and ``walls`` and the points ``leading_edge`` and ``trailing_edge``. Returns
    ``counts`` (elements by kind as gmsh made them), ``heights`` (the quad layers'
    tops [m]) and ``seconds``.
    """
    start = time.perf_counter()
    heights = layer_heights(params["layers"], params["first_height"], params["growth"])
    (x0, y0), (x1, y1) = BOX_2D
    with gmsh_session("hybrid_airfoil", seed=seed, verbose=False) as gmsh:
        occ, field = gmsh.model.occ, gmsh.model.mesh.field
        upper, lower = _profile_curves(occ)
        section = occ.addPlaneSurface([occ.addCurveLoop([upper, -lower])])
        box = occ.addRectangle(x0, y0, 0.0, x1 - x0, y1 - y0)
        occ.cut([(2, box)], [(2, section)])
        occ.synchronize()
        profile, walls = [], []
        for _, tag in gmsh.model.getEntities(1):
            low, _, _, high, _, _ = gmsh.model.getBoundingBox(1, tag)
            (profile if low > -0.1 and high < CHORD + 0.1 else walls).append(tag)
        ends = {}
        for _, tag in gmsh.model.getEntities(0):
            x, y, _ = gmsh.model.getValue(0, tag, [])
            if abs(y) < _FLAT and min(abs(x), abs(x - CHORD)) < _FLAT:
                ends["leading_edge" if abs(x) < _FLAT else "trailing_edge"] = tag
        for tag in profile:
            gmsh.model.mesh.setTransfiniteCurve(
                tag, params["profile_nodes"], "Bump", params["bump"]
            )
        layer = field.add("BoundaryLayer")
        field.setNumbers(layer, "CurvesList", profile)
        field.setNumber(layer, "Size", params["first_height"])
        field.setNumber(layer, "Ratio", params["growth"])
        field.setNumber(layer, "Thickness", float(heights[-1]) * 1.0001)
        field.setNumber(layer, "Quads", 1)
        field.setNumbers(layer, "FanPointsList", [ends["trailing_edge"]])
        gmsh.option.setNumber("Mesh.BoundaryLayerFanElements", params["fan"])
        field.setAsBoundaryLayer(layer)
        _graded_size(gmsh, params, None)
        gmsh.model.mesh.generate(2)
        counts = _element_counts(gmsh, 2)
        gmsh.model.addPhysicalGroup(2, [tag for _, tag in gmsh.model.getEntities(2)], name="fluid")
        gmsh.model.addPhysicalGroup(1, profile, name="airfoil")
        gmsh.model.addPhysicalGroup(1, walls, name="walls")
        for name, tag in ends.items():
            gmsh.model.addPhysicalGroup(0, [tag], name=name)
        with atomic_output(path) as temporary:
            gmsh.write(str(temporary))
    return {"counts": counts, "heights": heights, "seconds": time.perf_counter() - start}
