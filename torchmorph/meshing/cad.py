"""Tetrahedral meshes from CAD files (STEP, IGES, BREP) with gmsh's OpenCASCADE kernel.

The CAD counterpart of :func:`torchmorph.meshing.mesh_surfaces` (which
dispatches CAD files here; see there). The solids of each file are imported
with ``gmsh.model.occ.importShapes``, optionally cut out of a far-field box,
and meshed with gmsh's 3-D mesher (HXT by default; one thread and a fixed
``Mesh.RandomSeed``: the same input gives the same mesh). gmsh places boundary
nodes on the CAD geometry itself, so no snapping is needed.

Before meshing, solids that overlap, touch or nest are refused (OpenCASCADE's
distance between solids and their intersection; a body inside another only as
a hole in the outer file, without a box), and the number of tetrahedra is
estimated (:mod:`torchmorph.meshing.estimate`) and refused above
``max_elements``. Coordinates are those of the file's length unit
(:mod:`torchmorph.meshing.cad_units`). Needs gmsh: ``pip install
'torchmorph[mesh]'``.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any

import numpy as np

from torchmorph.meshing.cad_units import MILLIMETRES, UNIT_NAMES, file_unit
from torchmorph.meshing.checks import (
    TOUCH_TOLERANCE,
    Progress,
    check_max_elements,
    check_size,
    check_threads,
    far_offset,
)
from torchmorph.meshing.estimate import MAX_ELEMENTS, check_budget, estimate_tets
from torchmorph.meshing.gmsh_model import (
    add_box,
    collect_tets,
    distance_threshold,
    gmsh_session,
    graded_options,
    surface_triangles,
)
from torchmorph.meshing.surfaces import BOX_WALLS, CAD_FORMATS, WALL_NAMES, Surface

if TYPE_CHECKING:
    from torchmorph.mesh import TetMesh

__all__ = ["ALGORITHM_3D", "is_cad_file", "is_cad_input", "mesh_cad"]

#: gmsh's 3-D algorithm by default: HXT, 2-4x faster than Delaunay (1) on graded meshes
#: and deterministic on one thread.
ALGORITHM_3D = 10


_GMSH_EXTRA = "pip install 'torchmorph[mesh]'"


def is_cad_file(item: Any) -> bool:
    """Whether ``item`` is a path with a CAD extension (:data:`CAD_FORMATS`)."""
    return isinstance(item, (str, os.PathLike)) and Path(item).suffix.lower() in CAD_FORMATS


def is_cad_input(surfaces: Any) -> bool:
    """Whether ``surfaces`` are CAD files (all of them); mixing them with triangle surfaces is refused."""
    items = [surfaces] if isinstance(surfaces, (str, os.PathLike, Surface)) else surfaces
    items = list(items.values() if isinstance(items, Mapping) else items)
    cad = [is_cad_file(item) for item in items]
    if any(cad) and not all(cad):
        raise ValueError(
            f"surfaces: CAD files ({', '.join(CAD_FORMATS)}, meshed with gmsh) and triangle "
            "surfaces (meshed with fTetWild) cannot be meshed together; convert one kind"
        )
    return bool(cad) and all(cad)


def _import_gmsh():
    try:
        import gmsh
    except ImportError as error:
        raise ImportError(f"meshing CAD files needs gmsh: {_GMSH_EXTRA}") from error
    return gmsh


def _cad_files(files: Any) -> list[tuple[str, Path]]:
    """(name, path) of every file, checked: CAD extension, existing, names unique."""
    if isinstance(files, (str, os.PathLike)):
        files = [files]
    items = list(files.items()) if isinstance(files, Mapping) else [(None, f) for f in files]
    if not items:
        raise ValueError("files: give at least one CAD file")
    result = []
    for name, item in items:
        path = Path(item)
        if path.suffix.lower() not in CAD_FORMATS:
            raise ValueError(
                f"files: unsupported CAD file extension {path.suffix or '(none)'!r} in "
                f"{str(path)!r}; supported: {', '.join(CAD_FORMATS)}"
            )
        if not path.is_file():
            raise FileNotFoundError(f"files: CAD file {str(path)!r} does not exist")
        result.append((name or path.stem, path))
    names = [name for name, _ in result]
    for duplicate in sorted({n for n in names if names.count(n) > 1}):
        raise ValueError(
            f"files: two files are named {duplicate!r}; name them "
            "(a mapping name -> file, or NAME=FILE on the command line)"
        )
    return result


def _import_bodies(gmsh, files, progress):
    """Import every file's solids, moved by ``-offset`` when far from the origin
    (:func:`far_offset`); per body its volumes, faces (tag, centre, area) and bounds, the
    offset, and the millimetres per length unit of the first file (see :func:`_mesh_cad`)."""
    occ = gmsh.model.occ
    bodies, units = {}, []
    previous = gmsh.option.getString("Geometry.OCCTargetUnit")
    for name, path in files:
        unit = file_unit(path)
        units.append(unit)
        # OpenCASCADE's own unit, set explicitly: another import may have left it changed
        gmsh.option.setString("Geometry.OCCTargetUnit", "MM")
        try:
            shapes = occ.importShapes(str(path), highestDimOnly=True)
        except Exception as error:  # gmsh raises a bare Exception for an unreadable file
            raise ValueError(f"files: gmsh could not read {str(path)!r}: {error}") from error
        finally:
            gmsh.option.setString("Geometry.OCCTargetUnit", previous)
        volumes = [tag for dim, tag in shapes if dim == 3]
        if not volumes:
            raise ValueError(
                f"files: {str(path)!r} holds no solid, only entities of dimension "
                f"{sorted({dim for dim, _ in shapes})} (IGES files often hold faces only); "
                "export the body as a solid, e.g. to STEP or BREP"
            )
        bodies[name] = volumes
        first = units[0] or "MM"
        if unit is None:
            said = "no length unit: its numbers"
        elif unit == first:
            said = f"lengths in {UNIT_NAMES[unit]}, as in the file"
        else:
            said = f"lengths converted from {UNIT_NAMES[unit]} to {UNIT_NAMES[first]}"
        progress(f"CAD: {name}: {len(volumes)} solid(s) ({said})")
    scale = MILLIMETRES[units[0] or "MM"]
    boxes = np.array([occ.getBoundingBox(3, v) for vs in bodies.values() for v in vs])
    offset = far_offset(boxes[:, :3].min(axis=0), boxes[:, 3:].max(axis=0))
    if offset.any():
        occ.translate([(3, v) for vs in bodies.values() for v in vs], *(-offset))
        progress(f"CAD: meshed about the bodies' centre {(offset / scale).tolist()}, moved back")
    occ.synchronize()
    result = {}
    for name, volumes in bodies.items():
        boundary = gmsh.model.getBoundary([(3, v) for v in volumes], combined=True, oriented=False)
        faces = [
            (tag, np.array(occ.getCenterOfMass(2, tag)), occ.getMass(2, tag)) for _, tag in boundary
        ]
        boxes = np.array([gmsh.model.getBoundingBox(3, v) for v in volumes])
        bounds = np.stack([boxes[:, :3].min(axis=0), boxes[:, 3:].max(axis=0)])
        result[name] = (volumes, faces, bounds)
    return result, offset, scale


def _solid(bodies, name: str, index: int) -> str:
    count = len(bodies[name][0])
    return repr(name) if count == 1 else f"{name!r} (solid {index + 1} of {count})"


def _common_volume(occ, first: int, second: int) -> float:
    """The volume two solids share (OpenCASCADE's intersection of copies of them)."""
    common, _ = occ.intersect(occ.copy([(3, first)]), occ.copy([(3, second)]))
    volume = sum(occ.getMass(3, tag) for dim, tag in common if dim == 3)
    occ.remove(common, recursive=True)
    return volume


def _check_contacts(gmsh, bodies, container: str | None, tolerance: float, scale: float) -> None:
    """Refuse solids that overlap, touch, or lie inside one another (see the module doc);
    lengths in messages divided by ``scale``."""
    occ = gmsh.model.occ
    solids = [(name, k, v) for name, b in bodies.items() for k, v in enumerate(b[0])]
    boxes = {v: np.array(occ.getBoundingBox(3, v)) for _, _, v in solids}
    for i, (name_a, k_a, a) in enumerate(solids):
        for name_b, k_b, b in solids[i + 1 :]:
            box_a, box_b = boxes[a], boxes[b]
            if (box_a[:3] > box_b[3:] + tolerance).any() or (
                box_b[:3] > box_a[3:] + tolerance
            ).any():
                continue
            if occ.getDistance(3, a, 3, b)[0] > tolerance:
                continue
            first, second = _solid(bodies, name_a, k_a), _solid(bodies, name_b, k_b)
            common = _common_volume(occ, a, b)
            volume_a, volume_b = occ.getMass(3, a), occ.getMass(3, b)
            if common <= 1e-9 * min(volume_a, volume_b):
                raise ValueError(
                    f"files: bodies {first} and {second} touch (closer than "
                    f"{tolerance / scale:.2g}): "
                    "bodies must be apart, a gap of zero thickness cannot be meshed; fuse "
                    "them into one solid in the CAD tool, or move them apart"
                )
            if abs(common - volume_b) <= 1e-6 * volume_b:
                (hole, outer), (hole_tag, outer_tag) = (second, first), (b, a)
                hole_body, outer_body = name_b, name_a
            elif abs(common - volume_a) <= 1e-6 * volume_a:
                (hole, outer), (hole_tag, outer_tag) = (first, second), (a, b)
                hole_body, outer_body = name_a, name_b
            else:
                raise ValueError(
                    f"files: bodies {first} and {second} overlap (common volume "
                    f"{common / scale**3:.4g}): "
                    "bodies must be disjoint; fuse them into one solid in the CAD tool, or "
                    "move them apart"
                )
            if container is None or outer_body != container or hole_body == container:
                raise ValueError(
                    f"files: body {hole} lies inside body {outer}: a body inside another is a "
                    "hole only without box/bounds and in a file of its own, the outer body's "
                    "file holding all the others (bodies in a tunnel)"
                )
            faces = gmsh.model.getBoundary([(3, outer_tag)], oriented=False)
            if min(occ.getDistance(2, tag, 3, hole_tag)[0] for _, tag in faces) <= tolerance:
                raise ValueError(
                    f"files: body {hole} touches the inside of body {outer} (closer than "
                    f"{tolerance / scale:.2g}): a hole must not touch the wall around it"
                )


def _match_faces(gmsh, bodies, bounds, diagonal: float, tolerance: float = 1e-9):
    """Name every surface of the model after the boolean: box wall or body face."""
    occ = gmsh.model.occ
    names: dict[str, list[int]] = {}
    faces = [
        (name, k, centre, area)
        for name, b in bodies.items()
        for k, (_, centre, area) in enumerate(b[1])
    ]
    for _, tag in gmsh.model.getEntities(2):
        centre, area = np.array(occ.getCenterOfMass(2, tag)), occ.getMass(2, tag)
        wall = None
        if bounds is not None:  # the bodies are strictly inside: a centre on a wall is a wall's
            for label, axis, side in BOX_WALLS:
                if abs(centre[axis] - bounds[side][axis]) <= tolerance * diagonal:
                    wall = label
        if wall is not None:
            names.setdefault(wall, []).append(tag)
            names.setdefault("far_field", []).append(tag)
            continue
        # a body's face, unchanged by the boolean: the same centre and area
        distance = [
            np.linalg.norm(centre - c) / diagonal + abs(area - a) / max(area, a)
            for _, _, c, a in faces
        ]
        best = int(np.argmin(distance))
        if distance[best] > tolerance:
            raise ValueError(
                f"files: gmsh's boolean changed CAD surface {tag} (centre {centre.tolist()}): "
                "do the bodies touch or overlap each other?"
            )
        body, k, _, _ = faces[best]
        names.setdefault(body, []).append(tag)
        if len(bodies[body][1]) > 1:
            names[f"{body}_face{k}"] = [tag]
    return names


def _edge_curves(gmsh, names, bodies) -> dict[str, list[int]]:
    """Per body with several faces: its curves shared by two of its faces (no seams)."""
    edges = {}
    for body in bodies:
        faces = set(names.get(body, []))
        if len(bodies[body][1]) < 2:
            continue
        curves = gmsh.model.getBoundary(
            [(2, t) for t in sorted(faces)], combined=False, oriented=False
        )
        tags = sorted({abs(tag) for _, tag in curves})
        shared = [t for t in tags if len(set(gmsh.model.getAdjacencies(1, t)[0]) & faces) >= 2]
        if shared:
            edges[f"{body}_edges"] = shared
    return edges


def mesh_cad(
    files: Any,
    *,
    box: float | Sequence[float] | None = None,
    bounds: Any = None,
    mesh_size: float | None = None,
    body_mesh_size: float | None = None,
    grading: float | None = None,
    algorithm: int = ALGORITHM_3D,
    optimize: str = "",
    seed: int = 0,
    threads: int | None = None,
    max_elements: int | None = MAX_ELEMENTS,
    progress: bool = False,
    name: str | None = None,
) -> TetMesh:
    """A tetrahedral mesh of CAD solids (or of a box around them) with named node sets.

    Parameters
    ----------
    files : path, sequence of paths, or mapping name -> path
        ``.step``/``.stp``, ``.iges``/``.igs`` or ``.brep`` files, each with
        one or more solids (a body), read in the file's own length unit (a STEP
        file in metres gives a mesh in metres; OpenCASCADE alone would convert
        it to millimetres). Without ``box``/``bounds`` the solids are meshed;
        when one body's bounding box contains all the others, the others are
        cut out of it (bodies in a tunnel): the only case where a body may lie
        inside another. Otherwise solids, of one file or of several, must not
        touch or overlap each other.
    box, bounds
        The far-field box, as in :func:`torchmorph.meshing.mesh_surfaces`:
        the bodies are cut out of it (OpenCASCADE boolean). Bodies must lie
        strictly inside it, not touching its walls.
    mesh_size : float, optional
        Target mesh size (default: the domain's bounding-box diagonal / 20); at
        most the domain's largest extent.
    body_mesh_size, grading : float, optional
        Mesh size on the bodies (at most their largest extent), growing
        linearly with the distance from them to ``mesh_size`` over ``grading``
        (default: the bodies' largest extent); needs a box.
    algorithm : int, default 10
        gmsh's ``Mesh.Algorithm3D`` (1 Delaunay, 4 Frontal, 10 HXT: the fastest,
        deterministic on one thread).
    optimize : str, default ""
        A gmsh optimiser run after meshing (e.g. ``"Netgen"``).
    seed : int, default 0
        gmsh's ``Mesh.RandomSeed``.
    threads : int, optional
        gmsh's threads (default 1: the same input gives the same mesh).
    max_elements : int or None, default :data:`MAX_ELEMENTS`
        Refuse to mesh when the estimated number of tetrahedra
        (:func:`~torchmorph.meshing.estimate.estimate_tets`) is larger; None: no limit.
    progress : bool, default False
        Print the steps, the estimate, the elapsed time and the mesh's quality on stderr.
    name : str, optional
        The mesh's name (default: the first body's).

    Returns
    -------
    TetMesh
        Node sets: one per file (its stem or mapping name), with a box
        ``far_field`` and ``wall_x0`` … ``wall_z1``, and for a body of several
        CAD faces ``<body>_face<k>`` (face ``k`` in the file's order) and
        ``<body>_edges`` (nodes on the CAD curves between two of its faces).

    Raises
    ------
    ValueError
        For a bad file or argument (named in the message), a file without a
        solid, solids that overlap, touch (closer than 1e-6 of their bounding
        box's diagonal) or lie inside one another (but for the tunnel above),
        or an estimated mesh larger than ``max_elements`` (the message names the
        size to raise).
    FileNotFoundError
        For a missing file.
    ImportError
        Without gmsh.

    Notes
    -----
    Bodies far from the origin (farther than their bounding box's diagonal) are
    meshed about their centre and moved back. Touching along an edge or at a
    point with no common volume is detected by OpenCASCADE's distance (0).
    """
    return _mesh_cad(
        files,
        box=box,
        bounds=bounds,
        sizes=(mesh_size, body_mesh_size, grading),
        labels=("mesh_size", "body_mesh_size", "grading"),
        algorithm=algorithm,
        optimize=optimize,
        seed=seed,
        threads=threads,
        max_elements=max_elements,
        progress=progress,
        name=name,
    )


def _domain_walls(bodies, box, bounds, offset: np.ndarray, scale: float):
    """The far-field box (or None) and the bodies' bounds (2, 3); coordinates in messages
    moved back by ``offset`` and divided by ``scale``."""
    from torchmorph.meshing.surfaces import box_bounds

    low = np.min([b[2][0] for b in bodies.values()], axis=0)
    high = np.max([b[2][1] for b in bodies.values()], axis=0)
    walls = None
    if box is not None:
        walls = box_bounds([SimpleNamespace(bounds=np.stack([low, high]))], box)
    elif bounds is not None:
        walls = bounds
    if walls is not None:
        if "far_field" in bodies or any(body.startswith("wall_") for body in bodies):
            raise ValueError(
                "files: far_field and wall_* are the box's names; name the file otherwise"
            )
        for body, (_, _, body_bounds) in bodies.items():
            if not ((walls[0] < body_bounds[0]).all() and (body_bounds[1] < walls[1]).all()):
                raise ValueError(
                    f"bounds: the box {((walls + offset) / scale).tolist()} does not contain "
                    f"body {body!r} (bounds {((body_bounds + offset) / scale).tolist()}); "
                    "bodies must lie strictly inside the box, not touching its walls"
                )
    return walls, np.stack([low, high])


def _mesh_cad(
    files,
    *,
    box,
    bounds,
    sizes,
    labels,
    algorithm,
    optimize,
    seed,
    threads,
    max_elements,
    progress,
    name,
):
    """:func:`mesh_cad`, with the sizes' names in messages given by ``labels``.

    The model is in OpenCASCADE's millimetres; lengths the caller gives or gets (sizes,
    bounds, points, messages) are in the first file's unit: ``scale`` millimetres.
    """
    from torchmorph.mesh import TetMesh
    from torchmorph.mesh.quality import quality_report

    report = Progress(progress)
    files = _cad_files(files)
    if box is not None and bounds is not None:
        raise ValueError("box and bounds: give one of them, not both")
    mesh_size, body_mesh_size, grading = (
        check_size(label, value) for label, value in zip(labels, sizes, strict=True)
    )
    if (body_mesh_size is not None or grading is not None) and box is None and bounds is None:
        raise ValueError(f"{labels[1]} and {labels[2]} need a far field: give box or bounds")
    threads, max_elements = check_threads(threads), check_max_elements(max_elements)
    if bounds is not None:
        bounds = np.asarray(bounds, dtype=np.float64)
        if bounds.shape != (2, 3) or not np.isfinite(bounds).all():
            raise ValueError(f"bounds must be finite, shape (2, 3), got {bounds.tolist()}")
    _import_gmsh()
    with gmsh_session("torchmorph_cad", seed=seed, verbose=False, threads=threads) as gmsh:
        occ = gmsh.model.occ
        bodies, offset, scale = _import_bodies(gmsh, files, report)
        walls, (low, high) = _domain_walls(
            bodies, box, None if bounds is None else bounds * scale - offset, offset, scale
        )
        outer = [
            b
            for b, (_, _, o) in bodies.items()
            if all(
                (o[0] < i[0]).all() and (i[1] < o[1]).all()
                for c, (_, _, i) in bodies.items()
                if c != b
            )
        ]
        container = outer[0] if walls is None and len(bodies) > 1 and outer else None
        report("CAD: checking that the bodies do not overlap or touch")
        tolerance = TOUCH_TOLERANCE * float(np.linalg.norm(high - low))
        _check_contacts(gmsh, bodies, container, tolerance, scale)
        if walls is not None:
            occ.cut([(3, add_box(occ, walls))], [(3, v) for b in bodies.values() for v in b[0]])
        elif container is not None:
            occ.cut(
                [(3, v) for v in bodies[container][0]],
                [(3, v) for b, (vs, _, _) in bodies.items() if b != container for v in vs],
            )
        occ.synchronize()
        domain = walls if walls is not None else np.stack([low, high])
        diagonal = float(np.linalg.norm(domain[1] - domain[0]))
        names = _match_faces(gmsh, bodies, walls, diagonal)
        # sizes in the file's unit, as the caller gave them
        extent = float((domain[1] - domain[0]).max()) / scale
        size = check_size(labels[0], mesh_size, extent=extent) or diagonal / 20.0 / scale
        body_extent = float((high - low).max()) / scale
        check_size(labels[1], body_mesh_size, extent=body_extent, what="the bodies'")
        grading = grading if grading is not None else body_extent
        body_faces = [tag for body in bodies for tag in names.get(body, [])]
        volume = sum(occ.getMass(3, tag) for _, tag in gmsh.model.getEntities(3)) / scale**3
        mesher = "gmsh-hxt" if algorithm == 10 else "gmsh"
        if body_mesh_size is not None and body_mesh_size < size:
            vertices, triangles = surface_triangles(
                gmsh, body_faces, body_extent * scale / 16, (low, high)
            )
            estimate = estimate_tets(
                volume=volume,
                size=size,
                body_size=body_mesh_size,
                grading=grading,
                bounds=walls / scale,
                body_vertices=vertices / scale,
                body_faces=triangles,
                body_area=sum(occ.getMass(2, tag) for tag in body_faces) / scale**2,
                mesher=mesher,
                labels=labels,
            )
        else:
            estimate = estimate_tets(volume=volume, size=size, mesher=mesher, labels=labels)
        limit = "no limit" if max_elements is None else f"max_elements {max_elements:,}"
        report(f"estimate: about {estimate.total:,.0f} tetrahedra ({limit})")
        check_budget(estimate, max_elements)
        gmsh.option.setNumber("Mesh.MeshSizeMax", size * scale)
        if body_mesh_size is not None:
            field = gmsh.model.mesh.field
            threshold = distance_threshold(
                field, body_faces, body_mesh_size * scale, size * scale, grading * scale
            )
            field.setAsBackgroundMesh(threshold)
            graded_options(gmsh)
        on_bodies = "" if body_mesh_size is None else f", {body_mesh_size:.3g} on the bodies"
        report(f"gmsh: meshing (size {size:.3g}{on_bodies}) ...")
        points, tets, node_sets = collect_tets(
            gmsh,
            names,
            algorithm=algorithm,
            optimize=optimize,
            progress=report if progress else None,
        )
        # nodes on the CAD curves: gmsh's coordinates are the mesh's, bit for bit
        lookup = {point.tobytes(): i for i, point in enumerate(points)}
        for label, curves in _edge_curves(gmsh, names, bodies).items():
            coords = [gmsh.model.mesh.getNodes(1, t, includeBoundary=True)[1] for t in curves]
            ids = [lookup.get(p.tobytes(), -1) for p in np.concatenate(coords).reshape(-1, 3)]
            node_sets[label] = np.unique([i for i in ids if i >= 0]).astype(np.int64)
    if len(tets) == 0:
        raise RuntimeError("gmsh returned no tetrahedra")
    order = list(bodies) + (["far_field", *WALL_NAMES] if walls is not None else [])
    for body, (_, faces, _) in bodies.items():
        order += [f"{body}_face{k}" for k in range(len(faces))] + [f"{body}_edges"]
    node_sets = {k: node_sets[k] for k in order if k in node_sets and node_sets[k].size}
    if offset.any():
        points = points + offset
    mesh = TetMesh(
        points / scale if scale != 1 else points, tets, node_sets, name=name or files[0][0]
    )
    if progress:
        report(f"mesh: {mesh.num_nodes} nodes, {mesh.num_tets} tetrahedra, {quality_report(mesh)}")
    return mesh
