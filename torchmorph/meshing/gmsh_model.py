"""A deterministic gmsh session and the steps every gmsh mesher here shares: a box, a
size field graded by distance from surfaces, a coarse triangulation of surfaces (for
estimates), and the 3-D mesh collected as arrays with named node sets. Used by
:mod:`torchmorph.meshing.cad` and by the paper's mesh builders (``data_gen``). Needs
gmsh: ``pip install 'torchmorph[mesh]'``."""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator, Mapping, Sequence
from types import ModuleType

import numpy as np

__all__ = [
    "add_box",
    "collect_tets",
    "distance_threshold",
    "gmsh_session",
    "graded_options",
    "surface_triangles",
]


@contextlib.contextmanager
def gmsh_session(name: str, *, seed: int, verbose: bool, threads: int = 1) -> Iterator[ModuleType]:
    """A fresh gmsh model with deterministic settings (``threads`` threads, one by default,
    and ``Mesh.RandomSeed``); yields the ``gmsh`` module. gmsh is finalised after use
    unless the caller had initialised it (then only the model is removed)."""
    import gmsh

    started = not gmsh.isInitialized()
    if started:
        gmsh.initialize(readConfigFiles=False, interruptible=False)
    try:
        gmsh.model.add(name)
        gmsh.option.setNumber("General.Terminal", 1 if verbose else 0)
        gmsh.option.setNumber("General.Verbosity", 5 if verbose else 0)
        gmsh.option.setNumber("General.NumThreads", threads)
        gmsh.option.setNumber("Mesh.RandomSeed", seed)
        yield gmsh
    finally:
        if started:
            gmsh.finalize()
        else:
            with contextlib.suppress(Exception):
                gmsh.model.remove()


def add_box(occ, bounds: Sequence[Sequence[float]]) -> int:
    """An OpenCASCADE box from ``bounds = (low corner, high corner)``; its volume tag."""
    (x0, y0, z0), (x1, y1, z1) = bounds
    return occ.addBox(x0, y0, z0, x1 - x0, y1 - y0, z1 - z0)


def distance_threshold(
    field, surfaces: Sequence[int], size_min: float, size_max: float, distance: float
) -> int:
    """A size field growing linearly from ``size_min`` on ``surfaces`` to ``size_max`` at
    ``distance`` from them; its field tag (``field`` is ``gmsh.model.mesh.field``)."""
    dist = field.add("Distance")
    field.setNumbers(dist, "SurfacesList", list(surfaces))
    field.setNumber(dist, "Sampling", 100)
    threshold = field.add("Threshold")
    field.setNumber(threshold, "InField", dist)
    field.setNumber(threshold, "SizeMin", size_min)
    field.setNumber(threshold, "SizeMax", size_max)
    field.setNumber(threshold, "DistMin", 0.0)
    field.setNumber(threshold, "DistMax", distance)
    return threshold


def graded_options(gmsh) -> None:
    """Sizes from the background field alone, integrated along curves to 1e-5.

    Sizes extended from the boundary or taken from the CAD points or the curvature would
    override the field; integrating it along the curves to gmsh's default precision
    (1e-9) takes about three times longer for no visible difference.
    """
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
    gmsh.option.setNumber("Mesh.LcIntegrationPrecision", 1e-5)


def surface_triangles(
    gmsh, surfaces: Sequence[int], size: float, bounds: Sequence[Sequence[float]]
) -> tuple[np.ndarray, np.ndarray]:
    """A coarse triangulation of ``surfaces``: vertices (V, 3), triangles (F, 3).

    Surfaces inside ``bounds`` (the low and high corners) are meshed at ``size``, the
    rest as coarsely as their curves allow; the model's mesh and the field are removed
    again afterwards.
    """
    field = gmsh.model.mesh.field
    (x0, y0, z0), (x1, y1, z1) = bounds
    region = field.add("Box")
    for key, value in zip(
        ("VIn", "VOut", "XMin", "YMin", "ZMin", "XMax", "YMax", "ZMax"),
        (size, 1e22, x0 - size, y0 - size, z0 - size, x1 + size, y1 + size, z1 + size),
        strict=True,
    ):
        field.setNumber(region, key, float(value))
    field.setAsBackgroundMesh(region)
    try:
        gmsh.model.mesh.generate(2)
        node_tags, coords, _ = gmsh.model.mesh.getNodes()
        index = np.full(int(node_tags.max()) + 1, -1, dtype=np.int64)
        index[node_tags.astype(np.int64)] = np.arange(len(node_tags))
        triangles = []
        for tag in surfaces:
            types, _, nodes = gmsh.model.mesh.getElements(2, tag)
            triangles += [n for t, n in zip(types, nodes, strict=True) if t == 2]
        faces = index[np.concatenate(triangles).astype(np.int64)].reshape(-1, 3)
        return coords.reshape(-1, 3).astype(np.float64), faces
    finally:
        gmsh.model.mesh.clear()
        field.remove(region)


def collect_tets(
    gmsh,
    names: Mapping[str, Sequence[int]],
    *,
    algorithm: int,
    optimize: str,
    progress: Callable[[str], None] | None = None,
) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """Mesh the model in 3-D and return it as arrays.

    Parameters
    ----------
    gmsh : module
        From :func:`gmsh_session`, with the geometry built and synchronised.
    names : mapping of str to surface tags
        Node sets to collect: the nodes of these surfaces (their boundary included).
    algorithm : int
        gmsh's ``Mesh.Algorithm3D``.
    optimize : str
        gmsh's optimiser to run after meshing (``""`` for none).
    progress : callable, optional
        Called with a line after each dimension is meshed (curves, surfaces, volumes).

    Returns
    -------
    points (N, 3) float64, tets (M, 4) int64 (gmsh's orientation), node sets by name
    (sorted unique int64); nodes used by no tetrahedron are dropped and the rest
    renumbered in order.
    """
    gmsh.option.setNumber("Mesh.Algorithm3D", algorithm)
    if progress is None:
        gmsh.model.mesh.generate(3)
    else:
        for dim, what in ((1, "curves"), (2, "surfaces"), (3, "volumes")):
            gmsh.model.mesh.generate(dim)
            kind = {1: 1, 2: 2, 3: 4}[dim]  # lines, triangles, tetrahedra
            count = sum(len(tags) for tags in gmsh.model.mesh.getElementsByType(kind)[:1])
            elements = {1: "segments", 2: "triangles", 3: "tetrahedra"}[dim]
            progress(f"gmsh: meshed the {what}: {count:,} {elements}")
    if optimize:
        gmsh.model.mesh.optimize(optimize)
        if progress is not None:
            progress(f"gmsh: optimised ({optimize})")
    node_tags, coords, _ = gmsh.model.mesh.getNodes()
    index = np.full(int(node_tags.max()) + 1, -1, dtype=np.int64)
    index[node_tags.astype(np.int64)] = np.arange(len(node_tags))
    points = coords.reshape(-1, 3).astype(np.float64)
    _, tet_nodes = gmsh.model.mesh.getElementsByType(4)
    tets = index[tet_nodes.astype(np.int64)].reshape(-1, 4)
    patches = {}
    for name, tags in names.items():
        nodes = [gmsh.model.mesh.getNodes(2, tag, includeBoundary=True)[0] for tag in tags]
        patches[name] = np.unique(index[np.concatenate(nodes).astype(np.int64)])
    used = np.zeros(len(points), dtype=bool)
    used[tets.ravel()] = True
    new_index = np.cumsum(used) - 1
    patches = {name: np.unique(new_index[nodes[used[nodes]]]) for name, nodes in patches.items()}
    return points[used], new_index[tets], patches
