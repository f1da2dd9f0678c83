"""Hybrid meshes morphed: prism and quad boundary layers on the NACA0012 wing of case A.

Ballarin et al. (2017) morph tetrahedral meshes and note that SIDW/ESIDW "can be applied
to any dimension and to arbitrary meshes". This demo morphs the kind of mesh a flow
solver wants near a wall:

1. **3-D.** The NACA0012 wing of case A (chord 1.01 m, span 2π m) stands on the wall
   z = 0 of case B's tunnel (10 × 5 × 4π m), its root profile bounding a hole in that
   wall. gmsh meshes the wing's upper and lower surfaces with structured triangles
   (clustered towards the leading and trailing edges) and its flat tip with free ones,
   extrudes a prism boundary layer from them (``gmsh.model.geo.extrudeBoundaryLayer``,
   a few layers with geometric growth) and fills the rest of the tunnel with
   tetrahedra graded away from the wing. The ``.msh`` file is read back as a
   :class:`torchmorph.mesh.Mesh` of wedge and tetra blocks with gmsh's physical groups
   as markers: the wing's ``upper``, ``lower`` and ``tip`` surfaces, the walls
   ``wall_x0`` … ``wall_z1`` and the enrichment curves ``root_profile``,
   ``tip_profile``, ``leading_edge``, ``trailing_edge``. The wing is bent by case A's
   law δy = μ z² (μ = 0.01, the paper's μ*, and 0.05, the top of case B's range), the
   walls fixed, by IDW from every boundary node and by ESIDW with case B's radii
   (0.5 m on the walls, 0.25 m on the z walls, 0.05 m on the wing, the end profiles and
   edges enriched). A sweep of the wing's radius shows how far the wall that carries
   the layers may be thinned before its first prisms fold.
2. **2-D.** The wing's section in a 5 × 4 m box: gmsh's 2-D ``BoundaryLayer`` field
   puts quads along the profile (a fan of quads at the sharp trailing edge), triangles
   fill the rest; read as a planar ``Mesh`` (points (N, 2)). The section is turned
   rigidly about its quarter chord to an angle of attack of 5° and 20° by IDW and
   ESIDW (the profile thinned at twice the first quad's height, the walls at twice their
   mesh size, the leading and trailing edges enriched).

Printed for every morph: the controls, the times to build (selection + assembly of W)
and to morph, the relative error of ESIDW against IDW (nodal and mass norms), the
quality per element kind before and after (``quality_by_kind``: edge ratio Q, smallest
scaled Jacobian, smallest volume ratio, inverted cells) and where inverted cells lie
(prism layer, span, chord). ``OUT`` receives ``wing.msh`` and ``airfoil.msh``, VTU files
of the reference and deformed meshes (point data ``displacement``; cell data
``prism_layer`` and ``inverted``) and ``hybrid_wing.png`` (sections of the 3-D mesh and
the 2-D mesh, cells coloured by kind, before and after).

Usage::

    python demos/hybrid_wing.py                  # 'paper' size: ~120k cells in 3-D
    python demos/hybrid_wing.py --size small     # seconds
    python demos/hybrid_wing.py [--out DIR] [--seed 0] [--device cuda] [--repeats 3]

Needs gmsh and matplotlib (``pip install 'torchmorph[mesh,plot]'``).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the demos' shared helpers

from _common import median_seconds
from _hybrid_meshes import WALLS, WING, WING_EDGES, mesh_airfoil, mesh_wing

from data_gen.geometry import CHORD, SPAN
from torchmorph import IDW, MeshMorph
from torchmorph.mesh import (
    Mesh,
    atomic_output,
    inverted,
    quality_by_kind,
    read_mesh,
    relative_l2_error,
    write_mesh,
)
from torchmorph.mesh.cells import cell_kind
from torchmorph.selection import SelectionPlan

#: Bending parameters μ of δy = μ z²: the paper's μ* and the top of case B's range.
BENDING = (0.01, 0.05)
#: Angles of attack [degrees] of the section, turned nose up about its quarter chord.
ANGLES = (5.0, 20.0)
#: ESIDW radii [m] in 3-D, case B's: R on the x and y walls, R / 2 on the z walls, R / 10
#: on the wing; and the wing radii of the sweep.
WALL_RADIUS = 0.5
WING_RADIUS = 0.05
WING_RADII = (0.05, 0.1, 0.2, 0.4)
#: Mesh parameters per size. ``wing``: nodes on each side of a profile (``bump``: gmsh's
#: Bump coefficient, their clustering towards both edges) and along the span, the prism
#: layers (number, first height [m], growth), the tetrahedra's size near the wing and
#: far from it [m] and its growth per metre of distance from the wing. ``airfoil``: the
#: same for the section, quads instead of prisms, and the quads of the trailing-edge fan.
SIZES: dict[str, dict[str, dict[str, Any]]] = {
    "small": {
        "wing": {
            "profile_nodes": 21,
            "bump": 0.5,
            "span_nodes": 31,
            "layers": 4,
            "first_height": 0.004,
            "growth": 1.3,
            "h_near": 0.2,
            "h_far": 2.0,
            "grading": 0.35,
        },
        "airfoil": {
            "profile_nodes": 41,
            "bump": 0.25,
            "layers": 6,
            "first_height": 0.002,
            "growth": 1.3,
            "h_near": 0.03,
            "h_far": 0.5,
            "grading": 0.3,
            "fan": 5,
        },
    },
    "paper": {
        "wing": {
            "profile_nodes": 41,
            "bump": 0.5,
            "span_nodes": 61,
            "layers": 8,
            "first_height": 0.002,
            "growth": 1.25,
            "h_near": 0.1,
            "h_far": 1.2,
            "grading": 0.25,
        },
        "airfoil": {
            "profile_nodes": 101,
            "bump": 0.25,
            "layers": 10,
            "first_height": 0.0005,
            "growth": 1.25,
            "h_near": 0.012,
            "h_far": 0.3,
            "grading": 0.2,
            "fan": 7,
        },
    },
}

# ------------------------------------------------------------------------------ laws


def bending(mu: float) -> Callable[[Tensor], Tensor]:
    """Case A's law on points (n, 3): ``δ(x, y, z) = (0, μ z², 0)``."""

    def law(points: Tensor) -> Tensor:
        displacement = torch.zeros_like(points)
        displacement[:, 1] = mu * points[:, 2] ** 2
        return displacement

    return law


def rotation(degrees: float, centre: Sequence[float] = (CHORD / 4, 0.0)) -> Callable:
    """A rigid turn of points (n, 2) about ``centre`` (the quarter chord) to an angle of
    attack of ``degrees``, nose up (clockwise): ``δ(p) = R (p - c) + c - p``."""
    angle = -math.radians(degrees)
    matrix = ((math.cos(angle), -math.sin(angle)), (math.sin(angle), math.cos(angle)))

    def law(points: Tensor) -> Tensor:
        relative = points - points.new_tensor(centre)
        return relative @ points.new_tensor(matrix).T - relative

    return law


# ------------------------------------------------------------------------------ cells


def _triangle_keys(triangles: Tensor, num_nodes: int) -> Tensor:
    """One int64 per triangle (k, 3), the same whatever the order of its nodes."""
    ordered = torch.sort(triangles.cpu(), dim=1).values
    return (ordered[:, 0] * num_nodes + ordered[:, 1]) * num_nodes + ordered[:, 2]


def prism_layers(mesh: Mesh, wall: Sequence[str]) -> Tensor:
    """The layer of every cell in the prism columns standing on the face sets ``wall``,
    shape (M,), cells numbered across blocks.

    A wedge whose triangle (nodes 0-2 or 3-5) is a triangle of ``wall`` is in layer 1; a
    wedge sharing its other triangle with a wedge of layer k, in layer k + 1. Every other
    cell (tetrahedra, wedges in no column) gets 0. So a mesh of L layers on T wall
    triangles has T wedges in each of the layers 1 … L and no wedge of layer 0.
    """
    num_nodes = mesh.num_nodes
    wall_triangles = [
        block.nodes for name in wall for block in mesh.face_sets[name] if block.kind == "triangle"
    ]
    frontier = _triangle_keys(torch.cat(wall_triangles), num_nodes)
    starts = np.cumsum([0] + [int(block.nodes.shape[0]) for block in mesh.cells])
    wedge_cells = torch.cat(
        [
            torch.arange(int(starts[k]), int(starts[k + 1]))
            for k, block in enumerate(mesh.cells)
            if block.kind == "wedge"
        ]
    )
    wedges = torch.cat([block.nodes for block in mesh.cells if block.kind == "wedge"])
    first, second = (
        _triangle_keys(wedges[:, :3], num_nodes),
        _triangle_keys(wedges[:, 3:], num_nodes),
    )
    level = torch.zeros(wedges.shape[0], dtype=torch.int64)
    layer = 1
    while frontier.numel():
        free = level == 0
        from_first = free & torch.isin(first, frontier)
        from_second = free & torch.isin(second, frontier) & ~from_first
        level[from_first | from_second] = layer
        frontier = torch.cat([second[from_first], first[from_second]])
        layer += 1
    layers = torch.zeros(mesh.num_cells, dtype=torch.int64)
    layers[wedge_cells] = level
    return layers


def cell_kinds(mesh: Mesh) -> np.ndarray:
    """The kind of every cell, cells numbered across blocks, shape (M,)."""
    return np.concatenate([np.full(int(block.nodes.shape[0]), block.kind) for block in mesh.cells])


def cell_centres(mesh: Mesh) -> np.ndarray:
    """Mean of the corners of every cell, shape (M, D)."""
    points = mesh.points.detach().cpu().numpy()
    return np.concatenate(
        [
            points[block.nodes[:, : cell_kind(block.kind).corners].cpu().numpy()].mean(1)
            for block in mesh.cells
        ]
    )


def where_inverted(
    mesh: Mesh,
    field: Tensor,
    layers: Tensor | None = None,
    markers: Sequence[str] = (),
) -> dict[str, Any]:
    """The cells that ``field`` inverts, by kind: their count, the ranges of their
    centres (x as x / c, y and, in 3-D, z), the prism layers they are in (wedges, with
    ``layers`` from :func:`prism_layers`) and how many touch each of ``markers`` (those
    touched). Empty when no cell is inverted."""
    bad = inverted(mesh, field).cpu().numpy()
    if not bad.any():
        return {}
    kinds, centres = cell_kinds(mesh), cell_centres(mesh)
    touching = {}
    for name in markers:
        on_marker = np.zeros(mesh.num_nodes, dtype=bool)
        on_marker[mesh.node_set(name).cpu().numpy()] = True
        touching[name] = np.concatenate(
            [on_marker[block.nodes.cpu().numpy()].any(1) for block in mesh.cells]
        )
    where = {}
    for kind in np.unique(kinds[bad]):
        chosen = bad & (kinds == kind)
        low, high = centres[chosen].min(0), centres[chosen].max(0)
        entry: dict[str, Any] = {
            "count": int(chosen.sum()),
            "x_over_chord": (float(low[0] / CHORD), float(high[0] / CHORD)),
            "y": (float(low[1]), float(high[1])),
        }
        if mesh.dim == 3:
            entry["z"] = (float(low[2]), float(high[2]))
        if layers is not None and kind == "wedge":
            values, counts = np.unique(layers.numpy()[chosen], return_counts=True)
            entry["layers"] = {int(v): int(c) for v, c in zip(values, counts, strict=True)}
        entry["touching"] = {
            name: int((chosen & mask).sum())
            for name, mask in touching.items()
            if (chosen & mask).any()
        }
        where[str(kind)] = entry
    return where


def describe(where: dict[str, Any]) -> str:
    """One line for :func:`where_inverted`'s result."""
    parts = []
    for kind, entry in where.items():
        details = []
        if "layers" in entry:
            details.append("layer " + ", ".join(f"{k}: {v}" for k, v in entry["layers"].items()))
        low, high = entry["x_over_chord"]
        details.append(f"x/c {low:.2f}-{high:.2f}")
        details.append(f"y {entry['y'][0]:.2f}-{entry['y'][1]:.2f} m")
        if "z" in entry:
            details.append(f"z {entry['z'][0]:.2f}-{entry['z'][1]:.2f} m")
        if entry["touching"]:
            details.append(
                "touching " + ", ".join(f"{k} {v}" for k, v in entry["touching"].items())
            )
        parts.append(f"{entry['count']} {kind} ({'; '.join(details)})")
    return ", ".join(parts) or "none"


# ------------------------------------------------------------------------------ morphs


def wing_plan(wing_radius: float = WING_RADIUS, wall_radius: float = WALL_RADIUS) -> SelectionPlan:
    """ESIDW in the tunnel (case B's set-up): the wing at ``wing_radius``, the x and y
    walls at ``wall_radius``, the z walls at half of it, :data:`WING_EDGES` enriched; a
    node of the wing and of a wall (the root profile) belongs to the wing."""
    return SelectionPlan(
        {
            WING: wing_radius,
            ("wall_x0", "wall_x1", "wall_y0", "wall_y1"): wall_radius,
            ("wall_z0", "wall_z1"): wall_radius / 2,
        },
        enrich=WING_EDGES,
        overlap="first",
    )


def airfoil_plan(profile_radius: float, box_radius: float) -> SelectionPlan:
    """ESIDW in the 2-D box: the profile and the walls at their radii, the leading and
    trailing edges enriched."""
    return SelectionPlan(
        {"airfoil": profile_radius, "walls": box_radius},
        enrich=("leading_edge", "trailing_edge"),
        overlap="first",
    )


def _warm_up(device: torch.device) -> None:
    """One small IDW in 2-D and 3-D, so that loading the compiled kernels is not counted
    in the first build time."""
    for dim in (2, 3):
        generator = torch.Generator().manual_seed(0)
        controls = torch.rand(8, dim, generator=generator, dtype=torch.float64).to(device)
        targets = torch.rand(32, dim, generator=generator, dtype=torch.float64).to(device)
        IDW(controls, targets)(torch.ones_like(controls))


def build(mesh: Mesh, plan: SelectionPlan | None, seed: int) -> tuple[MeshMorph, float]:
    """A morph of ``mesh`` (IDW without a plan) and the seconds it took to build."""
    start = time.perf_counter()
    morph = MeshMorph(mesh, plan, generator=torch.Generator().manual_seed(seed))
    return morph, time.perf_counter() - start


def apply(
    morph: MeshMorph, moving: Sequence[str], law: Callable, repeats: int
) -> tuple[Tensor, float]:
    """The nodal field of ``law`` on the markers ``moving`` (the rest fixed) and the
    median time of the morph itself."""
    boundary = morph.boundary_displacement(list(moving), law)
    with torch.no_grad():
        field = morph(boundary)
        seconds = median_seconds(lambda: morph(boundary), repeats, morph.points.device)
    return field, seconds


def run_case(
    mesh: Mesh,
    plans: dict[str, SelectionPlan | None],
    moving: Sequence[str],
    laws: dict[str, Callable],
    *,
    layers: Tensor | None,
    markers: Sequence[str],
    seed: int,
    repeats: int,
    progress: Callable,
) -> dict[str, Any]:
    """Build every morph of ``plans`` (``"IDW"`` first: the reference of the errors),
    apply it for every law and collect controls, times, errors, quality by kind and
    the inverted cells (:func:`where_inverted`, with ``layers`` and ``markers``)."""
    rows, fields, where = [], {}, {}
    quality = [
        {"state": "reference", "kind": kind, **summary}
        for kind, summary in quality_by_kind(mesh).items()
    ]
    for method, plan in progress(list(plans.items()), desc=f"{mesh.name}: morphs"):
        morph, built = build(mesh, plan, seed)
        for label, law in laws.items():
            field, seconds = apply(morph, moving, law, repeats)
            fields[method, label] = field
            reference = fields["IDW", label]
            where[method, label] = where_inverted(mesh, field, layers, markers)
            rows.append(
                {
                    "method": method,
                    "law": label,
                    "controls": morph.num_controls,
                    "boundary": morph.num_boundary,
                    "control_nodes": morph.control_nodes,
                    "build_s": built,
                    "morph_s": seconds,
                    "error_nodal": float(relative_l2_error(mesh, field, reference, norm="nodal")),
                    "error_mass": float(relative_l2_error(mesh, field, reference, norm="mass")),
                    "inverted": sum(entry["count"] for entry in where[method, label].values()),
                }
            )
            quality += [
                {"state": f"{method} {label}", "kind": kind, **summary}
                for kind, summary in quality_by_kind(mesh, field).items()
            ]
    return {"rows": rows, "quality": quality, "fields": fields, "where": where}


def radius_sweep(
    mesh: Mesh,
    laws: dict[str, Callable],
    reference: dict,
    layers: Tensor,
    *,
    seed: int,
    progress: Callable,
) -> list[dict[str, Any]]:
    """ESIDW with the wing thinned at each radius of :data:`WING_RADII`: controls (on
    the wing), nodal error against IDW (``reference[("IDW", law)]``) and inverted cells."""
    wing_nodes = mesh.nodes_of(WING)
    rows = []
    for radius in progress(WING_RADII, desc="wing radius sweep"):
        morph, _ = build(mesh, wing_plan(radius), seed)
        for label, law in laws.items():
            field, _ = apply(morph, WING, law, 1)
            rows.append(
                {
                    "wing_radius": radius,
                    "law": label,
                    "controls": morph.num_controls,
                    "wing_controls": int(torch.isin(morph.control_nodes, wing_nodes).sum()),
                    "error_nodal": float(
                        relative_l2_error(mesh, field, reference["IDW", label], norm="nodal")
                    ),
                    "where": where_inverted(mesh, field, layers, (*WING, *WALLS)),
                }
            )
    return rows


# ------------------------------------------------------------------------------ tables


def _table(say: Callable, title: str, headers: Sequence[str], rows: Sequence[Sequence]) -> None:
    text = [[str(cell) for cell in row] for row in rows]
    widths = [max(len(h), *(len(row[i]) for row in text)) for i, h in enumerate(headers)]
    say(f"\n{title}")
    for row in [list(headers), *text]:  # the last column (text) aligned left
        cells = [c.rjust(w) for c, w in zip(row[:-1], widths, strict=False)]
        say("  ".join([*cells, row[-1]]).rstrip())


def print_morphs(say: Callable, title: str, rows: list[dict]) -> None:
    """The morphs: controls, times, errors against IDW, inverted cells."""
    _table(
        say,
        title,
        ("method", "law", "controls", "build s", "morph ms", "err nodal", "err mass", "inverted"),
        [
            (
                row["method"],
                row["law"],
                f"{row['controls']}/{row['boundary']}",
                f"{row['build_s']:.2f}",
                f"{row['morph_s'] * 1e3:.2f}",
                "-" if row["method"] == "IDW" else f"{row['error_nodal']:.2e}",
                "-" if row["method"] == "IDW" else f"{row['error_mass']:.2e}",
                row["inverted"],
            )
            for row in rows
        ],
    )


def print_quality(say: Callable, title: str, rows: list[dict]) -> None:
    """Quality by element kind, before (``reference``) and after every morph."""
    _table(
        say,
        title,
        ("state", "kind", "cells", "Q max", "Q mean", "min SJ", "min vol ratio", "inverted"),
        [
            (
                row["state"],
                row["kind"],
                row["num_cells"],
                f"{row['max_edge_ratio']:.3g}",
                f"{row['mean_edge_ratio']:.3g}",
                f"{row['min_scaled_jacobian']:.3f}",
                f"{row['min_volume_ratio']:.3f}",
                row["num_inverted"],
            )
            for row in rows
        ],
    )


def print_sweep(say: Callable, rows: list[dict], wing_nodes: int) -> None:
    """The wing-radius sweep: controls, error and inverted cells per radius and law."""

    def prisms(where: dict) -> str:
        entry = where.get("wedge")
        if entry is None:
            return "0"
        low, high = entry["z"]
        return f"{entry['count']} ({entry['layers'].get(1, 0)}; z {low:.2f}-{high:.2f} m)"

    _table(
        say,
        f"ESIDW with the wing thinned at radius R (walls as above; {wing_nodes} wing nodes):",
        ("R wing", "law", "controls", "on wing", "err nodal", "tets inv.", "prisms inv. (layer 1)"),
        [
            (
                f"{row['wing_radius']:g}",
                row["law"],
                row["controls"],
                row["wing_controls"],
                f"{row['error_nodal']:.2e}",
                row["where"].get("tetra", {"count": 0})["count"],
                prisms(row["where"]),
            )
            for row in rows
        ],
    )


# ------------------------------------------------------------------------------ picture

_COLOURS = {
    "wedge": "tab:orange",
    "quad": "tab:orange",
    "tetra": "tab:blue",
    "triangle": "tab:blue",
}


def section(mesh: Mesh, points: np.ndarray, z: float) -> tuple[list[np.ndarray], np.ndarray]:
    """The cut of the cells by the plane z = ``z``: one polygon (k, 2) per cut cell (the
    cut of a convex cell is convex: its edge crossings sorted by angle about their mean)
    and the indices of the cut cells (numbered across blocks)."""
    side = points[:, 2] - z
    side[side == 0] = 1e-12  # a node on the plane counts as just above it
    polygons, cells, start = [], [], 0
    for block in mesh.cells:
        kind = cell_kind(block.kind)
        nodes = block.nodes.cpu().numpy()
        edges = np.array(kind.edges)
        height = side[nodes[:, : kind.corners]]
        cut = np.flatnonzero((height.min(1) < 0) & (height.max(1) > 0))
        a, b = points[nodes[cut][:, edges[:, 0]]], points[nodes[cut][:, edges[:, 1]]]
        low, high = side[nodes[cut][:, edges[:, 0]]], side[nodes[cut][:, edges[:, 1]]]
        crosses = low * high < 0
        share = np.where(crosses, low / np.where(crosses, low - high, 1.0), 0.0)
        hits = a + share[..., None] * (b - a)
        for row in range(len(cut)):
            corners = hits[row, crosses[row], :2]
            offset = corners - corners.mean(0)
            polygons.append(corners[np.argsort(np.arctan2(offset[:, 1], offset[:, 0]))])
        cells.append(start + cut)
        start += int(nodes.shape[0])
    return polygons, np.concatenate(cells)


def _draw(axis, polygons, kinds, bad, title: str, centre, half) -> None:
    from matplotlib.collections import PolyCollection

    colours = ["crimson" if b else _COLOURS[k] for k, b in zip(kinds, bad, strict=True)]
    axis.add_collection(
        PolyCollection(polygons, facecolors=colours, edgecolors="k", linewidths=0.15, alpha=0.85)
    )
    axis.set_xlim(centre[0] - half[0], centre[0] + half[0])
    axis.set_ylim(centre[1] - half[1], centre[1] + half[1])
    axis.set_aspect("equal")
    axis.set_title(title, fontsize=9)
    axis.set_xlabel("x [m]")
    axis.set_ylabel("y [m]")


def plot(path: Path, wing: dict, airfoil: dict) -> None:
    """Top: the 3-D mesh cut at mid-span (reference; bent at μ = 0.05 by ESIDW) and cut
    where ESIDW inverts a prism at μ = 0.05, around it (at the trailing edge, mid-span,
    if none is). Bottom: the 2-D mesh (reference; turned to the larger angle by ESIDW;
    its trailing edge). Prisms and quads orange, tetrahedra and triangles blue, inverted
    cells red."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    figure, axes = plt.subplots(2, 3, figsize=(15, 7.5), constrained_layout=True)
    mesh = wing["mesh"].to("cpu")
    mu, label = BENDING[-1], f"μ={BENDING[-1]:g}"
    field = wing["fields"]["ESIDW", label].cpu()
    reference = mesh.points.numpy()
    moved = reference + field.numpy()
    kinds, bad = cell_kinds(mesh), inverted(mesh, field).numpy()
    middle = wing["span"] / 2
    wedges = np.flatnonzero(bad & (kinds == "wedge"))
    if wedges.size:
        focus = cell_centres(mesh)[wedges[0]]
        cut_at, zoom = float(focus[2]), (float(focus[0]), float(focus[1]))
        where = f"z = {cut_at:.2f} m, an inverted prism"
    else:
        cut_at, zoom, where = middle, (CHORD, 0.0), f"z = {middle:.2f} m, trailing edge"
    panels = (
        (reference, middle, (0.5, 0.0), (0.75, 0.38), f"3-D, z = {middle:.2f} m: reference"),
        (moved, middle, (0.5, mu * middle**2), (0.75, 0.38), f"3-D bent by ESIDW, {label}"),
        (moved, cut_at, (zoom[0], zoom[1] + mu * cut_at**2), (0.1, 0.05), f"{label}: {where}"),
    )
    for axis, (points, z, centre, half, title) in zip(axes[0], panels, strict=True):
        polygons, cells = section(mesh, points, z)
        shown = bad[cells] if points is moved else np.zeros(len(cells), dtype=bool)
        _draw(axis, polygons, kinds[cells], shown, title, centre, half)

    mesh2 = airfoil["mesh"].to("cpu")
    angle = f"{ANGLES[-1]:g}°"
    field2 = airfoil["fields"]["ESIDW", angle].cpu()
    reference2 = mesh2.points.numpy()
    moved2 = reference2 + field2.numpy()
    kinds2, bad2 = cell_kinds(mesh2), inverted(mesh2, field2).numpy()
    trailing = rotation(ANGLES[-1])(torch.tensor([[CHORD, 0.0]], dtype=torch.float64))[0]
    panels2 = (
        (reference2, (0.5, 0.0), (0.8, 0.45), "2-D: reference"),
        (moved2, (0.5, 0.0), (0.8, 0.45), f"2-D turned by ESIDW to {angle}"),
        (
            moved2,
            (CHORD + float(trailing[0]), float(trailing[1])),
            (0.1, 0.07),
            f"{angle}: trailing edge",
        ),
    )
    for axis, (points, centre, half, title) in zip(axes[1], panels2, strict=True):
        polygons = [
            points[nodes[: cell_kind(block.kind).corners]]
            for block in mesh2.cells
            for nodes in block.nodes.numpy()
        ]
        shown = bad2 if points is moved2 else np.zeros(len(polygons), dtype=bool)
        _draw(axis, polygons, kinds2, shown, title, centre, half)
    handles = [
        Patch(color=_COLOURS["wedge"], label="prisms (3-D), quads (2-D)"),
        Patch(color=_COLOURS["tetra"], label="tetrahedra (3-D), triangles (2-D)"),
        Patch(color="crimson", label="inverted"),
    ]
    figure.legend(handles=handles, loc="outside lower center", ncol=3)
    with atomic_output(path) as temporary:
        figure.savefig(temporary, dpi=110)
    plt.close(figure)


# ------------------------------------------------------------------------------ main


def _progress_bars(show: bool) -> Callable:
    from tqdm.auto import tqdm

    def progress(items, desc: str):
        return tqdm(items, desc=desc, disable=not show, leave=False)

    return progress


def _write_files(out: Path, wing: dict, airfoil: dict, progress: Callable) -> list[Path]:
    """The VTU files: reference meshes with the ESIDW field of the first law and the
    control points, deformed meshes with their field and their inverted cells."""
    outputs = []
    for case, prefix, labels, units in (
        (wing, "wing", [f"μ={mu:g}" for mu in BENDING], [f"mu{mu:g}" for mu in BENDING]),
        (airfoil, "airfoil", [f"{a:g}°" for a in ANGLES], [f"{a:g}deg" for a in ANGLES]),
    ):
        mesh = case["mesh"].to("cpu")
        cells = {"prism_layer": case["layers"]} if "layers" in case else {}
        controls = next(r for r in case["rows"] if r["method"] == "ESIDW")["control_nodes"]
        flag = torch.zeros(mesh.num_nodes, dtype=torch.uint8)
        flag[controls.cpu()] = 1
        first = case["fields"]["ESIDW", labels[0]].cpu()
        outputs.append(
            (
                out / f"{prefix}_reference.vtu",
                mesh,
                {"displacement": first, "control_point": flag},
                cells,
            )
        )
        for method in ("IDW", "ESIDW"):
            for label, unit in zip(labels, units, strict=True):
                field = case["fields"][method, label].cpu()
                bad = inverted(mesh, field).to(torch.uint8)
                outputs.append(
                    (
                        out / f"{prefix}_{method.lower()}_{unit}.vtu",
                        mesh.deformed(field),
                        {"displacement": field},
                        {**cells, "inverted": bad},
                    )
                )
    for path, mesh, point_data, cell_data in progress(outputs, desc="VTU files"):
        write_mesh(path, mesh, point_data=point_data, cell_data=cell_data)
    return [path for path, *_ in outputs]


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Run the demo with command-line arguments ``argv`` (default ``sys.argv[1:]``).

    Returns
    -------
    dict
        ``wing`` and ``airfoil``: the mesh, what gmsh made (``made``), the morph
        ``rows``, the ``quality`` rows, the ``fields`` by (method, law), the inverted
        cells by (method, law) (``where``); the wing also its ``layers``, ``span`` and
        the radius ``sweep``. ``files``: the files written; ``params``: the sizes used.
    """
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--size",
        choices=tuple(SIZES),
        default="paper",
        help="'paper' (default: 8 prism layers, ~120k cells in 3-D; under a minute) or 'small' "
        "(4 layers, ~20k cells; seconds)",
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=Path("out/hybrid_wing"),
        help="output directory (default %(default)s)",
    )
    parser.add_argument("--seed", type=int, default=0, help="gmsh's and the selection's seed")
    parser.add_argument("--device", default="cpu", help="torch device of the morphs (default cpu)")
    parser.add_argument("--repeats", type=int, default=3, help="timed repeats of each morph")
    parser.add_argument("--quiet", action="store_true", help="no tables or progress bars")
    args = parser.parse_args(argv)
    say = (lambda *a: None) if args.quiet else print
    progress = _progress_bars(not args.quiet)
    device = torch.device(args.device)
    params = SIZES[args.size]
    args.out.mkdir(parents=True, exist_ok=True)
    _warm_up(device)

    # ---------------------------------------------------------------- 3-D
    wing_file = args.out / "wing.msh"
    made = mesh_wing(wing_file, params["wing"], seed=args.seed)
    start = time.perf_counter()
    mesh = read_mesh(wing_file)
    read_s = time.perf_counter() - start
    layers = prism_layers(mesh, WING)
    say(
        f"3-D: gmsh made {made['counts']} in {made['seconds']:.2f} s; read back "
        f"{mesh.cell_counts}, {mesh.num_nodes} nodes ({mesh.boundary_nodes.numel()} on the "
        f"boundary, {mesh.nodes_of(WING).numel()} on the wing) in {read_s:.2f} s; "
        f"{int(layers.max())} prism layers on {made['wing_triangles']} wing triangles, tops at "
        f"{', '.join(f'{h * 1e3:.1f}' for h in made['heights'])} mm"
    )
    mesh = mesh.to(device)
    laws = {f"μ={mu:g}": bending(mu) for mu in BENDING}
    plans = {"IDW": None, "ESIDW": wing_plan()}
    wing = run_case(
        mesh,
        plans,
        WING,
        laws,
        layers=layers,
        markers=(*WING, *WALLS),
        seed=args.seed,
        repeats=args.repeats,
        progress=progress,
    )
    sweep = radius_sweep(mesh, laws, wing["fields"], layers, seed=args.seed, progress=progress)
    wing.update(mesh=mesh, made=made, layers=layers, span=SPAN, sweep=sweep)
    print_morphs(say, "3-D wing bent by δy = μ z², walls fixed:", wing["rows"])
    print_quality(say, "3-D quality by kind (SJ: scaled Jacobian):", wing["quality"])
    for (method, label), where in wing["where"].items():
        if where:
            say(f"  {method} {label}: inverted {describe(where)}")
    print_sweep(say, sweep, mesh.nodes_of(WING).numel())

    # ---------------------------------------------------------------- 2-D
    airfoil_file = args.out / "airfoil.msh"
    section_params = params["airfoil"]
    made2 = mesh_airfoil(airfoil_file, section_params, seed=args.seed)
    mesh2 = read_mesh(airfoil_file)
    say(
        f"\n2-D: gmsh made {made2['counts']} in {made2['seconds']:.2f} s; read back "
        f"{mesh2.cell_counts}, points {tuple(mesh2.points.shape)} "
        f"({mesh2.boundary_nodes.numel()} on the boundary)"
    )
    mesh2 = mesh2.to(device)
    turns = {f"{angle:g}°": rotation(angle) for angle in ANGLES}
    airfoil = run_case(
        mesh2,
        # the profile thinned at twice the first quad's height, the walls at twice their size
        {
            "IDW": None,
            "ESIDW": airfoil_plan(2 * section_params["first_height"], 2 * section_params["h_far"]),
        },
        ("airfoil",),
        turns,
        layers=None,
        markers=("airfoil", "walls"),
        seed=args.seed,
        repeats=args.repeats,
        progress=progress,
    )
    airfoil.update(mesh=mesh2, made=made2)
    print_morphs(say, "2-D section turned about its quarter chord:", airfoil["rows"])
    print_quality(say, "2-D quality by kind:", airfoil["quality"])
    for (method, label), where in airfoil["where"].items():
        if where:
            say(f"  {method} {label}: inverted {describe(where)}")

    # ---------------------------------------------------------------- files
    files = [wing_file, airfoil_file, *_write_files(args.out, wing, airfoil, progress)]
    picture = args.out / "hybrid_wing.png"
    plot(picture, wing, airfoil)
    files.append(picture)
    say("\nwrote " + ", ".join(str(path) for path in files))
    return {"wing": wing, "airfoil": airfoil, "files": files, "params": params}


if __name__ == "__main__":
    main()
