"""Builders of the three test meshes of Ballarin et al. (2017, Section 2.3), and
the one table of their names.

``build(case, size, mesher)`` makes (or loads from the cache) one of

- ``"wing"`` (``"A"``): the NACA0012 structural wing, chord 1.01 m, span 2π m;
- ``"fluid_wing"`` (``"B"``): the 10 × 5 × 4π m tunnel around that wing, its
  root on the wall z = 0 (fluid mesh only: the wing is a hole);
- ``"hull"`` (``"C"``): the 50 × 25 × 10 m box around a Wigley double body of
  length 2.5 m (fluid mesh only),

as a :class:`torchmorph.mesh.TetMesh` with named boundary node sets. The
geometry and its axes are described in :mod:`data_gen.geometry`; the node sets
in :func:`wing`, :func:`fluid_wing` and :func:`hull`.

Sizes: ``"small"`` (about a thousand to a few thousand nodes, for tests) and
``"paper"`` (node counts near the paper's Tables 1–3, see
:data:`PAPER_MESHES`). Meshers: ``"gmsh"`` (default, deterministic, exact CAD
surfaces) and ``"pytetwild"`` (fTetWild on a triangulated surface, boundary
nodes then projected onto the exact surfaces; not bit-reproducible, so the
cache is what makes repeated runs see the same mesh).

The "paper" presets with gmsh 4.15 give (the paper's figures in brackets;
Q = longest / shortest edge, max / mean):

- A: 9,626 tets (8,850), 2,631 nodes (2,463) = 805 interior (797) + 1,826
  boundary (1,666); Q 6.83 / 2.17 (not given); 100 nodes on the leading and on
  the trailing edge, 54 on each end profile, so that ESIDW keeps about as many
  control points as the paper's 390;
- B: 160,199 tets (169,598), 33,984 nodes (36,036) = 20,025 (21,910) + 13,959
  (14,126); Q 3.76 / 1.52 (4.31 / 1.48);
- C: 29,710 tets (30,265), 7,018 nodes (7,186) = 3,173 (3,322) + 3,845
  (3,864); Q 3.55 / 1.69 (2.47 / 1.62).
"""

from __future__ import annotations

import copy
import time
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING

import numpy as np

from data_gen import cache as _cache
from data_gen._arrays import (
    MeshArrays,
    boundary_faces,
    mesh_figures,
    orient,
    signed_volumes,
    untangle,
)
from data_gen._surfaces import finish_hull, finish_wing
from data_gen.geometry import (
    CHORD,
    HULL_BOX_BOUNDS,
    HULL_DRAFT,
    HULL_LENGTH,
    SPAN,
    TUNNEL_BOUNDS,
    naca_half_thickness,
    wigley_half_breadth,
)

if TYPE_CHECKING:
    from torchmorph.mesh import TetMesh

__all__ = [
    "CASES",
    "CASE_ALIASES",
    "LARGE_PARAMETERS",
    "MESHERS",
    "PAPER_MESHES",
    "PARAMETERS",
    "SIZES",
    "build",
    "build_arrays",
    "cache_path",
    "canonical_case",
    "fluid_wing",
    "hull",
    "mesh_figures",
    "wing",
]

CASES = ("wing", "fluid_wing", "hull")
SIZES = ("small", "paper", "large")
MESHERS = ("gmsh", "pytetwild")
#: Every accepted spelling of a case name (after lower-casing and stripping):
#: the letters of the paper's sections, and hyphens for underscores.
CASE_ALIASES = {
    "a": "wing",
    "b": "fluid_wing",
    "c": "hull",
    "fluid-wing": "fluid_wing",
    "fluidwing": "fluid_wing",
}
# fTetWild's output differs from run to run; a mesh that fails its checks after the
# projection onto the exact surfaces is made again, at most this many times in all
_TETWILD_ATTEMPTS = 3

#: The paper's meshes (Tables 1–3 and Section 2.3): tetrahedra, nodes, interior
#: and boundary nodes, and the edge-ratio quality Q where the paper gives it
#: (None where it does not).
PAPER_MESHES = {
    "wing": {
        "tets": 8850,
        "nodes": 2463,
        "interior": 797,
        "boundary": 1666,
        "max_q": None,
        "mean_q": None,
    },
    "fluid_wing": {
        "tets": 169598,
        "nodes": 36036,
        "interior": 21910,
        "boundary": 14126,
        "max_q": 4.31,
        "mean_q": 1.48,
    },
    "hull": {
        "tets": 30265,
        "nodes": 7186,
        "interior": 3322,
        "boundary": 3864,
        "max_q": 2.47,
        "mean_q": 1.62,
    },
}

#: Meshing parameters per case, mesher and size. Lengths in metres; every key
#: starting with ``h_`` is a mesh size and is multiplied by ``mesh_scale``.
#: gmsh: ``h_surface``/``h_volume`` (wing surface / inside the wing),
#: ``h_body``/``h_wall``/``h_far`` (size on the body, on the box walls, far
#: from both), ``grading_*`` (distance over which the size grows from the body
#: or wall size to ``h_far``), ``h_min``, ``edge_nodes``/``profile_nodes``
#: (wing: node counts on the leading and trailing edge lines and on each side
#: of each end profile, the ESIDW enrichment sets; not scaled by
#: ``mesh_scale``), ``algorithm`` (gmsh ``Mesh.Algorithm3D``:
#: 1 Delaunay, 4 Frontal), ``optimize`` (a gmsh optimiser run after meshing, or
#: ""). pytetwild: ``h_body``, ``h_far``, ``h_wall``, ``grading_*`` likewise
#: (through a background sizing field; fTetWild's surfaces come out coarser
#: than its target, so its sizes are smaller than gmsh's for similar counts),
#: ``profile_points``/``span_points``/``hull_points`` (resolution of the input
#: surface), ``epsilon`` (fTetWild's envelope relative to the bounding-box
#: diagonal), ``stop_energy`` and ``iterations`` (fTetWild's optimisation target
#: and its maximum number of passes).
PARAMETERS: dict[str, dict[str, dict[str, dict]]] = {
    "wing": {
        "gmsh": {
            "small": {
                "profile_points": 121,
                "h_surface": 0.12,
                "h_volume": 0.045,
                "h_min": 0.03,
                "algorithm": 4,
                "optimize": "",
            },
            "paper": {
                "profile_points": 121,
                "h_surface": 0.105,
                "h_volume": 0.046,
                "h_min": 0.03,
                "edge_nodes": 100,
                "profile_nodes": 28,
                "algorithm": 4,
                "optimize": "",
            },
        },
        "pytetwild": {
            "small": {
                "profile_points": 41,
                "span_points": 21,
                "h_body": 0.2,
                "epsilon": 1e-3,
                "stop_energy": 10.0,
                "iterations": 20,
            },
            "paper": {
                "profile_points": 81,
                "span_points": 61,
                "h_body": 0.1,
                "epsilon": 1e-3,
                "stop_energy": 10.0,
                "iterations": 40,
            },
        },
    },
    "fluid_wing": {
        "gmsh": {
            "small": {
                "profile_points": 121,
                "h_body": 0.12,
                "h_wall": 1.0,
                "h_far": 2.0,
                "grading_body": 2.5,
                "grading_wall": 2.0,
                "h_min": 0.03,
                "algorithm": 1,
                "optimize": "Netgen",
            },
            "paper": {
                "profile_points": 121,
                "h_body": 0.042,
                "h_wall": 0.3,
                "h_far": 0.6,
                "grading_body": 2.5,
                "grading_wall": 2.0,
                "h_min": 0.015,
                "algorithm": 1,
                "optimize": "Netgen",
            },
        },
        "pytetwild": {
            "small": {
                "profile_points": 41,
                "span_points": 21,
                "h_body": 0.2,
                "h_far": 2.0,
                "grading_body": 3.0,
                "epsilon": 5e-4,
                "stop_energy": 10.0,
                "iterations": 20,
            },
            "paper": {
                "profile_points": 81,
                "span_points": 61,
                "h_body": 0.04,
                "h_wall": 0.25,
                "h_far": 1.0,
                "grading_body": 2.5,
                "grading_wall": 1.5,
                "epsilon": 3e-4,
                "stop_energy": 10.0,
                "iterations": 40,
            },
        },
    },
    "hull": {
        "gmsh": {
            "small": {
                "h_body": 0.06,
                "h_wall": 4.0,
                "h_far": 8.0,
                "grading_body": 12.0,
                "grading_wall": 3.0,
                "h_min": 0.005,
                "algorithm": 1,
                "optimize": "Netgen",
            },
            "paper": {
                "h_body": 0.028,
                "h_wall": 1.7,
                "h_far": 5.0,
                "grading_body": 10.0,
                "grading_wall": 3.0,
                "h_min": 0.005,
                "algorithm": 1,
                "optimize": "Netgen",
            },
        },
        "pytetwild": {
            "small": {
                "hull_points": 25,
                "h_body": 0.05,
                "h_far": 8.0,
                "grading_body": 12.0,
                "epsilon": 2.5e-4,
                "stop_energy": 10.0,
                "iterations": 20,
            },
            "paper": {
                "hull_points": 41,
                "h_body": 0.02,
                "h_wall": 1.3,
                "h_far": 7.0,
                "grading_body": 10.0,
                "grading_wall": 2.0,
                "epsilon": 1.5e-4,
                "stop_energy": 10.0,
                "iterations": 40,
            },
        },
    },
}


#: The ``"large"`` size (about 10^6 nodes, for scaling studies; gmsh only): the
#: ``"paper"`` presets with every mesh size divided by about 3.3 (fluid wing) and
#: 6.7 (hull, whose paper mesh is 5x smaller), gmsh's Delaunay and no optimiser
#: pass (Netgen's takes longer than the meshing itself at this size). Merged into
#: :data:`PARAMETERS` below. Never built by the test suite.
LARGE_PARAMETERS: dict[str, dict] = {
    "fluid_wing": {
        "profile_points": 241,
        "h_body": 0.0127,
        "h_wall": 0.09,
        "h_far": 0.18,
        "grading_body": 2.5,
        "grading_wall": 2.0,
        "h_min": 0.0045,
        "algorithm": 1,
        "optimize": "",
    },
    "hull": {
        "h_body": 0.0042,
        "h_wall": 0.26,
        "h_far": 0.75,
        "grading_body": 10.0,
        "grading_wall": 3.0,
        "h_min": 0.0008,
        "algorithm": 1,
        "optimize": "",
    },
}
for _case, _large in LARGE_PARAMETERS.items():
    PARAMETERS[_case]["gmsh"]["large"] = _large


def canonical_case(case: str) -> str:
    """``"wing"``, ``"fluid_wing"`` or ``"hull"`` for any spelling of a case.

    Accepts the names in :data:`CASES`, ``"fluid-wing"``/``"fluidwing"`` and the
    letters A, B, C, in any case and with surrounding spaces (:data:`CASE_ALIASES`).
    This is the one table of case names: the data_gen CLI, the reproduction
    (:mod:`torchmorph.paper`) and ``torchmorph reproduce`` all go through it.
    """
    if not isinstance(case, str):
        raise TypeError(f"case must be a string, got {type(case).__name__}")
    name = CASE_ALIASES.get(case.strip().lower(), case.strip().lower())
    if name not in CASES:
        raise ValueError(f"case must be one of {', '.join(CASES)} (or A, B, C), got {case!r}")
    return name


def _resolve(case: str, size: str, mesher: str, mesh_scale: float, seed: int) -> tuple[str, dict]:
    case = canonical_case(case)
    if size not in SIZES:
        raise ValueError(f"size must be one of {', '.join(SIZES)}, got {size!r}")
    if mesher not in MESHERS:
        raise ValueError(f"mesher must be one of {', '.join(MESHERS)}, got {mesher!r}")
    if not (isinstance(mesh_scale, (int, float)) and mesh_scale > 0 and np.isfinite(mesh_scale)):
        raise ValueError(f"mesh_scale must be a positive number, got {mesh_scale!r}")
    if size not in PARAMETERS[case][mesher]:
        sizes = ", ".join(PARAMETERS[case][mesher])
        raise ValueError(
            f"size {size!r} is not defined for case {case!r} with mesher "
            f"{mesher!r}; its sizes: {sizes}"
        )
    params = copy.deepcopy(PARAMETERS[case][mesher][size])
    for key in params:
        if key.startswith("h_"):
            params[key] = float(params[key]) * float(mesh_scale)
    record = {"case": case, "mesher": mesher, "params": params, "seed": int(seed)}
    return case, record


def cache_path(
    case: str,
    size: str = "small",
    mesher: str = "gmsh",
    *,
    mesh_scale: float = 1.0,
    seed: int = 1,
    cache_dir: str | Path | None = None,
) -> Path:
    """The file a mesh is cached in (it may not exist yet); arguments as :func:`build`."""
    case, record = _resolve(case, size, mesher, mesh_scale, seed)
    directory = (
        Path(cache_dir).expanduser() if cache_dir is not None else _cache.default_cache_dir()
    )
    return directory / f"{case}-{size}-{mesher}-{_cache.cache_key(record)}.npz"


def _generate(case: str, mesher: str, params: dict, *, seed: int, verbose: bool):
    backend: ModuleType
    if mesher == "gmsh":
        from data_gen import _gmsh as backend
    else:
        from data_gen import _tetwild as backend
    if case == "wing":
        return backend.mesh_wing(params, seed=seed, verbose=verbose)
    if case == "fluid_wing":
        return backend.mesh_fluid_wing(params, seed=seed, verbose=verbose)
    return backend.mesh_hull(params, seed=seed, verbose=verbose)


def _finish(
    case: str,
    mesher: str,
    points: np.ndarray,
    tets: np.ndarray,
    patches: dict,
    epsilon: float | None = None,
):
    """Orient, project the boundary onto the exact surfaces, name the node sets, check."""
    tets = orient(points, tets)
    approximate = tets if mesher == "pytetwild" else None  # surface only near the sharp edges
    if case == "wing":
        points, sets = finish_wing(points, patches, tets=approximate)
    elif case == "fluid_wing":
        points, sets = finish_wing(points, patches, tunnel_bounds=TUNNEL_BOUNDS, tets=approximate)
    else:
        points, sets = finish_hull(points, patches, box_bounds=HULL_BOX_BOUNDS, tets=approximate)
    # a tetrahedron is bad when |V| <= 1e-10 L^3, L its longest edge (TetMesh rejects <= 1e-12)
    longest = np.sqrt(
        np.max(
            [
                np.sum((points[tets[:, i]] - points[tets[:, j]]) ** 2, axis=1)
                for i in range(4)
                for j in range(i + 1, 4)
            ],
            axis=0,
        )
    )
    min_volume = 1e-10 * longest**3
    bad = int(np.sum(signed_volumes(points, tets) <= min_volume))
    repaired = 0
    if bad:
        # projecting the boundary can fold a thin element over: move interior nodes back
        boundary_mask = np.zeros(len(points), dtype=bool)
        boundary_mask[boundary_faces(tets).ravel()] = True
        points, remaining = untangle(points, tets, boundary_mask, min_volume=min_volume)
        repaired, bad = bad - remaining, remaining
    if bad:
        raise RuntimeError(
            f"{case} ({mesher}): {bad} of {len(tets)} tetrahedra are inverted or flat after "
            "projecting the boundary nodes onto the exact surface; try another mesh size "
            "(mesh_scale) or the other mesher"
        )
    boundary = np.unique(boundary_faces(tets))
    tagged = np.unique(np.concatenate(list(sets.values())))
    if not np.array_equal(boundary, tagged):
        missing = np.setdiff1d(boundary, tagged)
        extra = np.setdiff1d(tagged, boundary)
        raise RuntimeError(
            f"{case} ({mesher}): boundary tagging failed: {len(missing)} boundary nodes in no "
            f"node set, {len(extra)} tagged nodes not on the boundary"
        )
    empty = [name for name, nodes in sets.items() if len(nodes) == 0]
    if empty:
        raise RuntimeError(f"{case} ({mesher}): empty node sets: {', '.join(empty)}")
    if case in ("fluid_wing", "hull") and epsilon is not None:
        _check_body_is_a_hole(case, points, epsilon)
    return points, tets, sets, repaired


def _check_body_is_a_hole(case: str, points: np.ndarray, epsilon: float) -> None:
    """No fluid node strictly inside the exact wing (case B) or hull (case C), except
    within their ends thinner than fTetWild's envelope (``epsilon`` times the domain's
    diagonal), which fTetWild may cut off; fTetWild differs from run to run, so a mesh
    that fails is made again."""
    x, y, z = points.T
    if case == "fluid_wing":
        inside = (x > 1e-6) & (x < CHORD - 1e-6) & (z > 1e-6) & (z < SPAN - 1e-6)
        distance, thickness = np.abs(y[inside]), naca_half_thickness(x[inside])
        body = "wing"
    else:
        inside = (np.abs(x) < HULL_LENGTH / 2.0 - 1e-6) & (np.abs(y) < HULL_DRAFT - 1e-6)
        distance, thickness = np.abs(z[inside]), wigley_half_breadth(x[inside], y[inside])
        body = "hull"
    envelope = epsilon * np.linalg.norm(np.ptp(points, axis=0))
    wrong = int(np.sum((distance < thickness - 1e-9) & (thickness > envelope)))
    if wrong:
        raise RuntimeError(
            f"{case} (pytetwild): {wrong} fluid nodes lie inside the {body} where it is "
            f"thicker than fTetWild's envelope ({envelope:.3g})"
        )


def build_arrays(
    case: str,
    size: str = "small",
    mesher: str = "gmsh",
    *,
    mesh_scale: float = 1.0,
    seed: int = 1,
    cache_dir: str | Path | None = None,
    cache: bool = True,
    verbose: bool = False,
) -> MeshArrays:
    """Like :func:`build`, but return NumPy arrays (:class:`MeshArrays`), not a TetMesh."""
    case, record = _resolve(case, size, mesher, mesh_scale, seed)
    path = cache_path(case, size, mesher, mesh_scale=mesh_scale, seed=seed, cache_dir=cache_dir)
    cached = _cache.load_or_none(path) if cache else None  # a corrupt entry: rebuilt
    if cached is not None:
        if verbose:
            print(f"[data_gen] {case} ({size}, {mesher}): cached {path}")
        return cached
    if verbose:
        print(f"[data_gen] {case} ({size}, {mesher}): meshing with {record['params']}")
    start = time.perf_counter()
    attempts = 1 if mesher == "gmsh" else _TETWILD_ATTEMPTS
    for attempt in range(1, attempts + 1):
        points, tets, patches = _generate(
            case, mesher, record["params"], seed=seed, verbose=verbose
        )
        try:
            epsilon = record["params"].get("epsilon") if mesher == "pytetwild" else None
            points, tets, sets, repaired = _finish(case, mesher, points, tets, patches, epsilon)
            break
        except RuntimeError as error:  # fTetWild differs from run to run: try again
            if attempt == attempts:
                raise
            if verbose:
                print(f"[data_gen] attempt {attempt} failed ({error}); meshing again")
    seconds = time.perf_counter() - start
    info = {
        **record,
        "size": size,
        "mesh_scale": float(mesh_scale),
        "build_seconds": seconds,
        "figures": mesh_figures(points, tets),
        "repaired_tets": repaired,
        "attempts": attempt,
    }
    mesh = MeshArrays(points=points, tets=tets, node_sets=sets, info=info)
    if verbose:
        print(f"[data_gen] {case} ({size}, {mesher}): {info['figures']} in {seconds:.2f} s")
    if cache and _cache.save(path, mesh) and verbose:  # a failed write only warns
        print(f"[data_gen] saved {path}")
    return mesh


def build(
    case: str,
    size: str = "small",
    mesher: str = "gmsh",
    *,
    mesh_scale: float = 1.0,
    seed: int = 1,
    cache_dir: str | Path | None = None,
    cache: bool = True,
    verbose: bool = False,
) -> TetMesh:
    """Build (or load from the cache) one of the paper's test meshes.

    Parameters
    ----------
    case : {"wing", "fluid_wing", "hull"} or {"A", "B", "C"}
        The test case (Ballarin et al. 2017, Section 2.3; Tables 1–3).
    size : {"small", "paper", "large"}
        ``"small"``: a coarse mesh for tests, built in seconds. ``"paper"``:
        node counts near the paper's (:data:`PAPER_MESHES`). ``"large"``: about
        10^6 nodes, for scaling studies (fluid wing and hull with gmsh only; see
        :data:`LARGE_PARAMETERS`).
    mesher : {"gmsh", "pytetwild"}
        ``"gmsh"`` (default): OpenCASCADE geometry, deterministic.
        ``"pytetwild"``: fTetWild on a triangulated surface; not reproducible
        from run to run (use the cache), slower, and coarse at the bodies'
        thinnest sharp ends (see :mod:`data_gen._tetwild`).
    mesh_scale : float, keyword-only
        Multiplies every mesh size of the preset (2.0: about 8× fewer
        tetrahedra).
    seed : int, keyword-only
        gmsh's ``Mesh.RandomSeed`` (part of the cache key).
    cache_dir : str or Path, optional, keyword-only
        Cache directory; default ``$TORCHMORPH_CACHE`` or
        ``~/.cache/torchmorph/meshes``.
    cache : bool, keyword-only
        Read and write the cache (default). ``False`` always meshes anew and
        writes nothing.
    verbose : bool, keyword-only
        Print progress (and gmsh's own log).

    Returns
    -------
    TetMesh
        Named ``"<case>-<size>-<mesher>"``; every boundary node belongs to at
        least one node set and lies exactly on the analytic surface.

    Raises
    ------
    ValueError
        For an unknown case, size or mesher, or a non-positive ``mesh_scale``.
    ImportError
        If the chosen mesher is not installed (``pip install gmsh`` /
        ``pip install pytetwild``).
    RuntimeError
        If a generated mesh fails its checks (an inverted tetrahedron after
        projecting the boundary, an untagged boundary node, an empty node set).
    """
    from torchmorph.mesh import TetMesh

    mesh = build_arrays(
        case,
        size,
        mesher,
        mesh_scale=mesh_scale,
        seed=seed,
        cache_dir=cache_dir,
        cache=cache,
        verbose=verbose,
    )
    name = f"{canonical_case(case)}-{size}-{mesher}"
    return TetMesh(mesh.points, mesh.tets, mesh.node_sets, name=name)


def wing(size: str = "small", mesher: str = "gmsh", **options) -> TetMesh:
    """Case A, the NACA0012 structural wing (Table 1); options as :func:`build`.

    Node sets: ``root`` (end face z = 0, clamped), ``tip`` (z = 2π),
    ``upper``, ``lower`` (the two sides), ``root_profile``, ``tip_profile``
    (the end profiles), ``leading_edge`` (x = 0, y = 0), ``trailing_edge``
    (x = 1.01, y = 0) and ``wing`` (every boundary node). Sets share the nodes
    of the curves between them.
    """
    return build("wing", size, mesher, **options)


def fluid_wing(size: str = "small", mesher: str = "gmsh", **options) -> TetMesh:
    """Case B, the tunnel around the wing (Table 2); options as :func:`build`.

    Node sets: the walls ``wall_x0``, ``wall_x1`` (the paper's front/inlet and
    rear/outlet), ``wall_y0``, ``wall_y1`` (bottom, top), ``wall_z0``,
    ``wall_z1`` (the paper's left, with the wing's root, and right; see
    :data:`data_gen.geometry.TUNNEL_WALL_NAMES`), and the wing's ``wing``
    (upper, lower and tip), ``upper``, ``lower``, ``tip``, ``tip_profile``,
    ``root_profile`` (where the wing meets ``wall_z0``), ``leading_edge``,
    ``trailing_edge``.
    """
    return build("fluid_wing", size, mesher, **options)


def hull(size: str = "small", mesher: str = "gmsh", **options) -> TetMesh:
    """Case C, the box around the Wigley hull (Table 3); options as :func:`build`.

    Node sets: the walls ``wall_x0`` … ``wall_z1``, ``hull`` (the whole hull),
    ``starboard`` (z >= 0), ``port`` (z <= 0), the sharp edges ``stem``
    (x = L/2), ``stern`` (x = -L/2), ``keel`` (y = -T), ``keel_top`` (y = +T,
    the mirror image of the keel: the body is a double body) and their union
    ``hull_edges`` (the paper's "edge of the hull"). The hull is centred at the
    origin, so the paper's rotation about the z axis is a pitch about its centre.
    """
    return build("hull", size, mesher, **options)
