"""Tetrahedral meshes from CAD files (STEP, IGES, BREP) with gmsh's OpenCASCADE kernel.

The CAD counterpart of :func:`torchmorph.meshing.mesh_surfaces` (which
dispatches CAD files here; see there). The solids of each file are imported
with ``gmsh.model.occ.importShapes``, optionally cut out of a far-field box,
and meshed with gmsh's 3-D mesher (one thread, a fixed ``Mesh.RandomSeed``:
the same input gives the same mesh). gmsh places boundary nodes on the CAD
geometry itself, so no snapping is needed. Needs gmsh:
``pip install 'torchmorph[mesh]'``.
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any

import numpy as np

from torchmorph.meshing.gmsh_model import add_box, collect_tets, distance_threshold, gmsh_session
from torchmorph.meshing.surfaces import BOX_WALLS, CAD_FORMATS, WALL_NAMES, Surface

if TYPE_CHECKING:
    from torchmorph.mesh.tetmesh import TetMesh

__all__ = ["is_cad_file", "is_cad_input", "mesh_cad"]


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


def _import_bodies(gmsh, files):
    """Import every file's solids; per body its volumes and its faces (tag, centre, area)."""
    occ = gmsh.model.occ
    bodies = {}
    for name, path in files:
        try:
            shapes = occ.importShapes(str(path), highestDimOnly=True)
        except Exception as error:  # gmsh raises a bare Exception for an unreadable file
            raise ValueError(f"files: gmsh could not read {str(path)!r}: {error}") from error
        volumes = [tag for dim, tag in shapes if dim == 3]
        if not volumes:
            raise ValueError(
                f"files: {str(path)!r} holds no solid, only entities of dimension "
                f"{sorted({dim for dim, _ in shapes})} (IGES files often hold faces only); "
                "export the body as a solid, e.g. to STEP or BREP"
            )
        bodies[name] = volumes
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
    return result


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
    algorithm: int = 1,
    optimize: str = "",
    seed: int = 0,
    progress: bool = False,
    name: str | None = None,
) -> TetMesh:
    """A tetrahedral mesh of CAD solids (or of a box around them) with named node sets.

    Parameters
    ----------
    files : path, sequence of paths, or mapping name -> path
        ``.step``/``.stp``, ``.iges``/``.igs`` or ``.brep`` files, each with
        one or more solids (a body). Without ``box``/``bounds`` the solids are
        meshed; when one body's bounding box contains all the others, the
        others are cut out of it (bodies in a tunnel). Bodies must not touch
        or overlap each other.
    box, bounds
        The far-field box, as in :func:`torchmorph.meshing.mesh_surfaces`:
        the bodies are cut out of it (OpenCASCADE boolean).
    mesh_size : float, optional
        Target mesh size (default: the domain's bounding-box diagonal / 20).
    body_mesh_size, grading : float, optional
        Mesh size on the bodies, growing linearly with the distance from them
        to ``mesh_size`` over ``grading`` (default: the bodies' largest
        extent); needs a box.
    algorithm : int, default 1
        gmsh's ``Mesh.Algorithm3D`` (1 Delaunay, 4 Frontal, 10 HXT).
    optimize : str, default ""
        A gmsh optimiser run after meshing (e.g. ``"Netgen"``).
    seed : int, default 0
        gmsh's ``Mesh.RandomSeed``.
    progress : bool, default False
        Print the steps and the mesh's quality on stderr.
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
        solid, or bodies that touch (the boolean changes their faces).
    FileNotFoundError
        For a missing file.
    ImportError
        Without gmsh.
    """
    from torchmorph.mesh.quality import quality_report
    from torchmorph.mesh.tetmesh import TetMesh
    from torchmorph.meshing.surfaces import box_bounds

    start = time.perf_counter()
    files = _cad_files(files)
    if box is not None and bounds is not None:
        raise ValueError("box and bounds: give one of them, not both")
    if (body_mesh_size is not None or grading is not None) and box is None and bounds is None:
        raise ValueError("body_mesh_size and grading need a far field: give box or bounds")
    for label, value in (
        ("mesh_size", mesh_size),
        ("body_mesh_size", body_mesh_size),
        ("grading", grading),
    ):
        if value is not None and not (np.isfinite(value) and value > 0):
            raise ValueError(f"{label} must be a finite number > 0, got {value!r}")
    _import_gmsh()
    with gmsh_session("torchmorph_cad", seed=seed, verbose=False) as gmsh:
        occ = gmsh.model.occ
        bodies = _import_bodies(gmsh, files)
        if progress:
            for body, (volumes, faces, _) in bodies.items():
                print(
                    f"CAD: {body}: {len(volumes)} solid(s), {len(faces)} face(s)",
                    file=sys.stderr,
                    flush=True,
                )
        low = np.min([b[2][0] for b in bodies.values()], axis=0)
        high = np.max([b[2][1] for b in bodies.values()], axis=0)
        walls = None
        if box is not None:
            walls = box_bounds([SimpleNamespace(bounds=np.stack([low, high]))], box)
        elif bounds is not None:
            walls = np.asarray(bounds, dtype=np.float64)
            if walls.shape != (2, 3) or not np.isfinite(walls).all():
                raise ValueError(f"bounds must be finite, shape (2, 3), got {walls.tolist()}")
        if walls is not None:
            if "far_field" in bodies or any(body.startswith("wall_") for body in bodies):
                raise ValueError(
                    "files: far_field and wall_* are the box's names; name the file otherwise"
                )
            for body, (_, _, body_bounds) in bodies.items():
                if not ((walls[0] < body_bounds[0]).all() and (body_bounds[1] < walls[1]).all()):
                    raise ValueError(
                        f"bounds: the box {walls.tolist()} does not contain body {body!r} "
                        f"(bounds {body_bounds.tolist()})"
                    )
            container = [(3, add_box(occ, walls))]
            tools = [(3, v) for b in bodies.values() for v in b[0]]
        else:
            outer = [
                b
                for b, (_, _, o) in bodies.items()
                if all(
                    (o[0] < i[0]).all() and (i[1] < o[1]).all()
                    for c, (_, _, i) in bodies.items()
                    if c != b
                )
            ]
            container = [(3, v) for v in bodies[outer[0]][0]] if len(bodies) > 1 and outer else []
            tools = [
                (3, v) for b, (vs, _, _) in bodies.items() if outer and b != outer[0] for v in vs
            ]
        if container and tools:
            occ.cut(container, tools)
        occ.synchronize()
        domain = walls if walls is not None else np.stack([low, high])
        diagonal = float(np.linalg.norm(domain[1] - domain[0]))
        names = _match_faces(gmsh, bodies, walls, diagonal)
        size = float(mesh_size) if mesh_size is not None else diagonal / 20.0
        gmsh.option.setNumber("Mesh.MeshSizeMax", size)
        if body_mesh_size is not None:
            grading = float(grading) if grading is not None else float((high - low).max())
            body_faces = [tag for body in bodies for tag in names.get(body, [])]
            field = gmsh.model.mesh.field
            field.setAsBackgroundMesh(
                distance_threshold(field, body_faces, float(body_mesh_size), size, grading)
            )
            gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
            gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
        if progress:
            print(f"gmsh: meshing (size {size:.3g}) ...", file=sys.stderr, flush=True)
        points, tets, node_sets = collect_tets(gmsh, names, algorithm=algorithm, optimize=optimize)
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
    mesh = TetMesh(points, tets, node_sets, name=name or files[0][0])
    if progress:
        print(
            f"mesh: {mesh.num_nodes} nodes, {mesh.num_tets} tetrahedra, {quality_report(mesh)} "
            f"({time.perf_counter() - start:.1f} s in all)",
            file=sys.stderr,
            flush=True,
        )
    return mesh
