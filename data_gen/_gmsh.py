"""Meshing with gmsh's OpenCASCADE kernel (the default mesher).

The wing is the NACA0012 profile as two interpolating splines (upper and lower
side, tangent-continuous at the leading edge, meeting at a sharp trailing
edge) extruded along z; the tunnel is a box with the wing cut out. The Wigley
hull is exact: each side, ``z = ±(B/2) g(x) h(y)`` with g and h quadratic, is a
bi-quadratic Bézier patch (3 × 3 control points, all zero in z but the middle
one, 2B). Node sets come from the gmsh surfaces each node lies on.

Meshing is deterministic: one thread, a fixed ``Mesh.RandomSeed``.
"""

from __future__ import annotations

from data_gen.geometry import (
    BOX_WALLS,
    CHORD,
    HULL_BEAM,
    HULL_BOX_BOUNDS,
    HULL_DRAFT,
    HULL_LENGTH,
    SPAN,
    TUNNEL_BOUNDS,
    naca_half_thickness,
    naca_profile,
)
from torchmorph.meshing.gmsh_model import add_box, collect_tets, distance_threshold, gmsh_session

__all__ = ["mesh_fluid_wing", "mesh_hull", "mesh_wing"]

_FLAT = 1e-5  # a surface whose bounding box is thinner than this [m] is planar (OCC pads by 1e-7)


def _profile_splines(occ, num_points: int) -> int:
    """The wing's profile face in the plane z = 0; returns its surface tag."""
    x, y = naca_profile(num_points)
    x, y = x[::-1], y[::-1]  # both sides from the trailing to the leading edge
    upper = [occ.addPoint(float(a), float(b), 0.0) for a, b in zip(x, y, strict=True)]
    trailing, leading = upper[0], upper[-1]
    lower = [trailing]
    lower += [occ.addPoint(float(a), float(-b), 0.0) for a, b in zip(x[1:-1], y[1:-1], strict=True)]
    lower.append(leading)
    # end tangents: along the sides at the sharp TE, vertical at the leading edge (G1 there).
    # Both splines start at the TE: the lower side interpolated towards the TE with its end
    # tangent prescribed overshoots it (x = 1.012 c) and crosses the chord line there.
    h = 1e-6 * CHORD
    slope = float((naca_half_thickness(CHORD) - naca_half_thickness(CHORD - h)) / h)
    upper_curve = occ.addSpline(upper, tangents=[-1.0, -slope, 0.0, 0.0, -1.0, 0.0])
    lower_curve = occ.addSpline(lower, tangents=[-1.0, slope, 0.0, 0.0, 1.0, 0.0])
    loop = occ.addCurveLoop([upper_curve, -lower_curve])
    face = occ.addPlaneSurface([loop])
    # the interpolation points are free vertices now: remove them
    occ.remove([(0, tag) for tag in upper[1:-1] + lower[1:-1]])
    return face


def _wing_volume(occ, num_points: int) -> int:
    face = _profile_splines(occ, num_points)
    extruded = occ.extrude([(2, face)], 0.0, 0.0, SPAN)
    return next(tag for dim, tag in extruded if dim == 3)


def _classify_surfaces(gmsh, bounds, body: str) -> dict[str, list[int]]:
    """Name every surface: box walls by plane, end faces by z, sides by centre."""
    names: dict[str, list[int]] = {}
    for _, tag in gmsh.model.getEntities(2):
        lo = gmsh.model.getBoundingBox(2, tag)
        box = (lo[:3], lo[3:])
        name = None
        if bounds is not None:
            for wall, axis, side in BOX_WALLS:
                if (
                    box[1][axis] - box[0][axis] < _FLAT
                    and abs(box[0][axis] - bounds[side][axis]) < _FLAT
                ):
                    name = wall
        if name is None:
            centre = gmsh.model.occ.getCenterOfMass(2, tag)
            if body == "wing":
                if box[1][2] - box[0][2] < _FLAT:
                    name = "root" if centre[2] < SPAN / 2 else "tip"
                else:
                    name = "upper" if centre[1] > 0 else "lower"
            else:
                name = "starboard" if centre[2] > 0 else "port"
        names.setdefault(name, []).append(tag)
    return names


def _edge_nodes(gmsh, params: dict) -> None:
    """Fixed node counts on the wing's sharp edges (ESIDW's enrichment sets).

    ``edge_nodes``: nodes on the leading and on the trailing edge line (along
    z); ``profile_nodes``: nodes on each side (upper, lower) of the two end
    profiles. Absent keys leave gmsh's own sizes.
    """
    for _, tag in gmsh.model.getEntities(1):
        box = gmsh.model.getBoundingBox(1, tag)
        along_z = box[5] - box[2] > _FLAT and box[3] - box[0] < _FLAT
        count = params.get("edge_nodes" if along_z else "profile_nodes")
        if count:
            gmsh.model.mesh.setTransfiniteCurve(tag, int(count))
    if params.get("edge_nodes") or params.get("profile_nodes"):
        # the surfaces keep their own size instead of growing from the finer edges;
        # the volume is meshed afterwards with the usual sizes
        gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
        gmsh.model.mesh.generate(2)
        gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 1)


def mesh_wing(params: dict, *, seed: int, verbose: bool):
    """Case A: the wing alone. Returns (points, tets, patches)."""
    with gmsh_session("torchmorph_wing", seed=seed, verbose=verbose) as gmsh:
        occ = gmsh.model.occ
        volume = _wing_volume(occ, params["profile_points"])
        occ.synchronize()
        names = _classify_surfaces(gmsh, None, "wing")
        gmsh.option.setNumber("Mesh.MeshSizeMax", params["h_surface"])
        gmsh.option.setNumber("Mesh.MeshSizeMin", params["h_min"])
        gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
        # a finer size inside the volume only: the thin wing gets interior nodes
        field = gmsh.model.mesh.field
        constant = field.add("MathEval")
        field.setString(constant, "F", repr(float(params["h_volume"])))
        restrict = field.add("Restrict")
        field.setNumber(restrict, "InField", constant)
        field.setNumbers(restrict, "VolumesList", [volume])
        field.setNumber(restrict, "IncludeBoundary", 0)
        field.setAsBackgroundMesh(restrict)
        _edge_nodes(gmsh, params)
        return collect_tets(gmsh, names, algorithm=params["algorithm"], optimize=params["optimize"])


def _graded_fields(gmsh, names, body_patches, bounds, params) -> None:
    """Mesh size growing linearly with the distance from the body and from the walls.

    The size is ``min(h_far, h_body + (h_far - h_body) d_body / grading_body,
    h_wall + (h_far - h_wall) d_wall / grading_wall)``. The distance to the
    body comes from a sampled Distance field, the distance to the box walls
    from a closed formula (a Distance field on the large walls makes the 1-D
    meshing several times slower).
    """
    field = gmsh.model.mesh.field
    body = [tag for name in body_patches for tag in names.get(name, [])]
    near_body = distance_threshold(
        field, body, params["h_body"], params["h_far"], params["grading_body"]
    )
    (x0, y0, z0), (x1, y1, z1) = bounds
    wall_distance = (
        f"min(min(min(x - ({x0!r}), ({x1!r}) - x), min(y - ({y0!r}), ({y1!r}) - y)),"
        f" min(z - ({z0!r}), ({z1!r}) - z))"
    )
    h_wall, h_far = float(params["h_wall"]), float(params["h_far"])
    rate = (h_far - h_wall) / float(params["grading_wall"])
    near_walls = field.add("MathEval")
    field.setString(
        near_walls, "F", f"min({h_far!r}, {h_wall!r} + {rate!r} * max(0, {wall_distance}))"
    )
    smallest = field.add("Min")
    field.setNumbers(smallest, "FieldsList", [near_body, near_walls])
    field.setAsBackgroundMesh(smallest)
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
    gmsh.option.setNumber("Mesh.MeshSizeMin", params["h_min"])
    # integrating the size field along the curves to 1e-9 (the default) triples the time
    gmsh.option.setNumber("Mesh.LcIntegrationPrecision", 1e-5)


def mesh_fluid_wing(params: dict, *, seed: int, verbose: bool):
    """Case B: the tunnel around the wing. Returns (points, tets, patches)."""
    with gmsh_session("torchmorph_fluid_wing", seed=seed, verbose=verbose) as gmsh:
        occ = gmsh.model.occ
        wing = _wing_volume(occ, params["profile_points"])
        box = add_box(occ, TUNNEL_BOUNDS)
        occ.cut([(3, box)], [(3, wing)])
        occ.synchronize()
        names = _classify_surfaces(gmsh, TUNNEL_BOUNDS, "wing")
        if "root" in names:
            raise RuntimeError("gmsh kept the wing's root face inside the tunnel")
        _graded_fields(gmsh, names, ("upper", "lower", "tip"), TUNNEL_BOUNDS, params)
        return collect_tets(gmsh, names, algorithm=params["algorithm"], optimize=params["optimize"])


def _wigley_volume(occ) -> int:
    """The Wigley double body as two exact Bézier patches sewn into a volume."""
    half_length = HULL_LENGTH / 2.0
    xs = (-half_length, 0.0, half_length)
    ys = (-HULL_DRAFT, 0.0, HULL_DRAFT)
    patches = []
    for side in (1.0, -1.0):
        control = []
        for j in range(3):
            for i in range(3):
                z = side * 2.0 * HULL_BEAM if (i, j) == (1, 1) else 0.0
                control.append(occ.addPoint(xs[i], ys[j], z))
        patches.append(occ.addBezierSurface(control, 3))
        occ.remove([(0, tag) for tag in control])  # control points are free vertices
    shell = occ.addSurfaceLoop(patches, sewing=True)
    volume = occ.addVolume([shell])
    occ.remove([(2, tag) for tag in patches], recursive=True)  # sewing made copies
    return volume


def mesh_hull(params: dict, *, seed: int, verbose: bool):
    """Case C: the box around the hull. Returns (points, tets, patches)."""
    with gmsh_session("torchmorph_hull", seed=seed, verbose=verbose) as gmsh:
        occ = gmsh.model.occ
        hull = _wigley_volume(occ)
        box = add_box(occ, HULL_BOX_BOUNDS)
        occ.cut([(3, box)], [(3, hull)])
        occ.synchronize()
        names = _classify_surfaces(gmsh, HULL_BOX_BOUNDS, "hull")
        _graded_fields(gmsh, names, ("starboard", "port"), HULL_BOX_BOUNDS, params)
        return collect_tets(gmsh, names, algorithm=params["algorithm"], optimize=params["optimize"])
