"""Figures of the paper's cases: sections of the reference and morphed meshes."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from torch import Tensor

from torchmorph._atomic import atomic_output
from torchmorph.mesh.cells import TET_EDGES
from torchmorph.morph import MeshMorph
from torchmorph.paper.cases import HULL_CENTRE

if TYPE_CHECKING:
    from torchmorph.paper.experiments import CaseContext

__all__ = ["plane_section", "plot_case", "plot_one_mode_bound"]

_TET_EDGES = np.asarray(TET_EDGES)


def plane_section(
    points: np.ndarray | Tensor,
    tets: np.ndarray | Tensor,
    axis: int,
    value: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Cut a tetrahedral mesh by the plane ``x[axis] = value``.

    Parameters
    ----------
    points : array, shape (N, 3)
    tets : array, shape (M, 4)
    axis : int
        0, 1 or 2.
    value : float
        Position of the plane. Nodes exactly on the plane count as lying on its
        positive side.

    Returns
    -------
    cut : array of int, shape (K,)
        Indices of the tetrahedra the plane crosses.
    first, second : arrays of int, shape (K, 4)
        End nodes of the (up to four) crossed edges of each cut tetrahedron, in
        polygon order; a triangle repeats its last vertex.
    weight : array of float, shape (K, 4)
        Position along each edge: the polygon's vertices are
        ``(1 - weight) * x[first] + weight * x[second]`` for the reference points
        ``x`` — and, applied to moved points, follow the mesh as it deforms.
    """
    points = points.detach().cpu().numpy() if isinstance(points, Tensor) else np.asarray(points)
    tets = tets.detach().cpu().numpy() if isinstance(tets, Tensor) else np.asarray(tets)
    side = points[:, axis] - value
    side = np.where(side == 0.0, np.finfo(np.float64).tiny, side)
    per_tet = side[tets]
    cut = np.flatnonzero((per_tet.min(1) < 0) & (per_tet.max(1) > 0))
    corners = tets[cut]
    sides = per_tet[cut]
    first = corners[:, _TET_EDGES[:, 0]]
    second = corners[:, _TET_EDGES[:, 1]]
    s_first = sides[:, _TET_EDGES[:, 0]]
    s_second = sides[:, _TET_EDGES[:, 1]]
    crossed = s_first * s_second < 0
    weight = np.where(crossed, s_first / np.where(crossed, s_first - s_second, 1.0), 0.0)
    vertices = (1 - weight)[..., None] * points[first] + weight[..., None] * points[second]
    plane_axes = [i for i in range(3) if i != axis]
    flat = vertices[..., plane_axes]
    centre = (flat * crossed[..., None]).sum(1) / crossed.sum(1, keepdims=True)
    angle = np.arctan2(flat[..., 1] - centre[:, 1:2], flat[..., 0] - centre[:, 0:1])
    angle = np.where(crossed, angle, np.inf)
    order = np.argsort(angle, axis=1)[:, :4]
    take = np.take_along_axis
    first, second, weight = (take(a, order, 1) for a in (first, second, weight))
    count = crossed.sum(1)
    triangle = count == 3
    for array in (first, second, weight):
        array[triangle, 3] = array[triangle, 2]
    return cut, first, second, weight


def _section_polygons(points: np.ndarray, first, second, weight, plane_axes) -> np.ndarray:
    vertices = (1 - weight)[..., None] * points[first] + weight[..., None] * points[second]
    return vertices[..., plane_axes]


def plot_case(
    context: CaseContext,
    fields: dict[str, Tensor],
    morphs: dict[str, MeshMorph],
    path: str | Path,
) -> Path:
    """PNG of the reference and ESIDW-deformed geometry at μ*.

    Every panel with a colour scale has its own colour bar. Wing cases (A, B):
    the mesh section at mid-span (z = π), reference and ESIDW-deformed; the
    deformed section is coloured by ESIDW's difference from full IDW, since the
    displacement itself, δy = μ z², is the same everywhere on a span section;
    and a side view (z–y) of the wing's boundary nodes coloured by the
    displacement. Case B adds the whole tunnel section coloured by the
    displacement (2 × 2 panels). Hull (C): the section z = 0 (the hull's centre
    plane) coloured by the displacement, and a zoom on the bow coloured by
    ESIDW's difference from IDW, with the hull's profile before and after the
    rotation.
    """
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        from matplotlib.collections import PolyCollection
    except ImportError as missing:  # pragma: no cover - matplotlib is a test dependency
        raise ImportError("plots need matplotlib: pip install 'torchmorph[plot]'") from missing

    spec, mesh = context.spec, context.mesh
    points = mesh.points.detach().cpu().numpy()
    tets = mesh.tets.cpu().numpy()
    displacement = fields["ESIDW"].detach().cpu().numpy()
    difference = displacement - fields["IDW"].detach().cpu().numpy()
    moved = points + displacement
    magnitude = np.linalg.norm(displacement, axis=1)
    error = np.linalg.norm(difference, axis=1)
    hull = spec.key == "hull"
    fluid = spec.key == "fluid-wing"
    labels = ("x [m]", "y [m]")
    if hull:
        axis, value, plane_axes = 2, 1e-6, (0, 1)
        window = ((-2.5, 2.5), (-1.2, 1.2))
    else:  # mid-span of the wing (span 2π from the root z = 0)
        axis, value, plane_axes = 2, math.pi, (0, 1)
        window = ((-0.5, 1.5), (-0.45, 0.6)) if fluid else ((-0.1, 1.1), (-0.2, 0.35))
    _, first, second, weight = plane_section(points, tets, axis, value)

    def on_section(nodal: np.ndarray) -> np.ndarray:
        return ((1 - weight) * nodal[first] + weight * nodal[second]).mean(1)

    reference = _section_polygons(points, first, second, weight, list(plane_axes))
    deformed = _section_polygons(moved, first, second, weight, list(plane_axes))
    where = f"z = {value:.3g} m" if not hull else "z = 0 (hull centre plane)"
    mu_text = f"{spec.parameter}* = {spec.mu_star:g}{spec.unit}"

    if fluid:
        figure, grid = plt.subplots(2, 2, figsize=(13, 8.5), constrained_layout=True)
        axes = list(grid.ravel())
    elif hull:
        figure, grid = plt.subplots(1, 3, figsize=(17, 4.8), constrained_layout=True)
        axes = list(grid)
    else:
        figure, grid = plt.subplots(1, 3, figsize=(16, 4.4), constrained_layout=True)
        axes = list(grid)

    def section_panel(ax, polygons, colour, title, limits, label=None, scale=1.0):
        if colour is not None:  # the reference section underneath, faint, to show the motion
            ax.add_collection(
                PolyCollection(
                    list(reference), linewidths=0.3, facecolors="none", edgecolors="0.75", zorder=0
                )
            )
        collection = PolyCollection(list(polygons), linewidths=0.3, edgecolors="0.35")
        if colour is None:
            collection.set_facecolor("white")
        else:
            colour = colour * scale
            collection.set_array(colour)
            collection.set_cmap("viridis")
            # the colour scale spans what the panel shows, not the whole section
            centre = np.asarray(polygons).mean(1)
            shown = (
                (centre[:, 0] >= limits[0][0])
                & (centre[:, 0] <= limits[0][1])
                & (centre[:, 1] >= limits[1][0])
                & (centre[:, 1] <= limits[1][1])
            )
            visible = colour[shown] if shown.any() else colour
            top = float(visible.max()) if visible.size else 1.0
            collection.set_clim(0.0, top if top > 0 else 1.0)
            collection.set_alpha(0.85)
        ax.add_collection(collection)
        ax.set_xlim(*limits[0])
        ax.set_ylim(*limits[1])
        ax.set_aspect("equal")
        ax.set_xlabel(labels[0])
        ax.set_ylabel(labels[1])
        ax.set_title(title, fontsize=10)
        if colour is not None:
            figure.colorbar(collection, ax=ax, shrink=0.85, label=label)
        return collection

    section_panel(axes[0], reference, None, f"reference mesh, section {where}", window)
    if hull:
        section_panel(
            axes[1],
            deformed,
            on_section(magnitude),
            f"ESIDW deformed, {mu_text} (grey: reference)",
            window,
            "|displacement| [m]",
        )
        hull_points = points[mesh.node_set("hull").cpu().numpy()]
        (x0, y0), (x1, y1) = hull_points[:, :2].min(0), hull_points[:, :2].max(0)
        outline = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1], [x0, y0]])
        angle = math.radians(spec.mu_star)
        rotation = np.array(
            [[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]]
        )
        centre = np.asarray(HULL_CENTRE[:2])
        rotated = (outline - centre) @ rotation.T + centre
        bow = ((x1 - 0.6, x1 + 0.5), (-0.45, 0.4))
        ax = axes[2]
        section_panel(
            ax,
            deformed,
            on_section(error),
            f"bow: ESIDW − IDW at {mu_text}",
            bow,
            "|ESIDW − IDW| [mm]",
            1e3,
        )
        for target in (axes[1], ax):
            target.plot(*outline.T, "--", color="0.3", lw=1.0, label="hull profile, reference")
            target.plot(
                *rotated.T,
                "-",
                color="C3",
                lw=1.2,
                label=f"hull profile rotated by {spec.mu_star:g}°",
            )
        axes[1].plot([centre[0]], [centre[1]], "k+", ms=8, label="rotation centre")
        ax.legend(loc="lower left", fontsize=7)
    else:
        if fluid:
            box = mesh.points[mesh.nodes_of([f"wall_{a}{s}" for a in "xy" for s in "01"])]
            low, high = box.amin(0).tolist(), box.amax(0).tolist()
            tunnel = ((low[0], high[0]), (low[1], high[1]))
            axes[0].set_xlim(*tunnel[0])
            axes[0].set_ylim(*tunnel[1])
            section_panel(
                axes[1],
                deformed,
                on_section(magnitude),
                f"ESIDW deformed, {mu_text}, whole tunnel",
                tunnel,
                "|displacement| [m]",
            )
            zoom = ((-0.3, 1.3), (-0.3, 0.45))
            section_panel(
                axes[2],
                deformed,
                on_section(error),
                f"near the wing: ESIDW − IDW at {mu_text}",
                zoom,
                "|ESIDW − IDW| [mm]",
                1e3,
            )
        else:
            section_panel(
                axes[1],
                deformed,
                on_section(error),
                f"ESIDW − IDW at {mu_text} (grey: reference)",
                window,
                "|ESIDW − IDW| [mm]",
                1e3,
            )
        ax = axes[-1]
        wing = mesh.node_set("wing").cpu().numpy()
        wing = wing[:: max(1, len(wing) // 3000)]  # enough dots to see the shape
        ax.plot(points[wing, 2], points[wing, 1], ".", ms=1.5, color="0.7", label="reference")
        dots = ax.scatter(
            moved[wing, 2],
            moved[wing, 1],
            s=2,
            c=magnitude[wing],
            cmap="viridis",
            label=f"deformed, {mu_text}",
        )
        figure.colorbar(dots, ax=ax, shrink=0.85, label="|displacement| [m]")
        ax.axvline(value, color="C3", lw=0.8, ls="--", label="section")
        ax.set_xlabel("z (span) [m]")
        ax.set_ylabel("y [m]")
        ax.set_title("side view of the wing (boundary nodes)", fontsize=10)
        ax.legend(loc="upper left", fontsize=8, markerscale=4)
    variant = "" if spec.variant == "paper" else f", variant {spec.variant}"
    figure.suptitle(
        f"Case {spec.letter}: {spec.title} ({context.size} mesh, {mesh.num_nodes:,} nodes{variant})"
    )
    path = Path(path)
    with atomic_output(path) as temporary:
        figure.savefig(temporary, dpi=100, format="png")
    plt.close(figure)
    return path


def plot_one_mode_bound(sweep: dict, path: str | Path, *, title: str = "") -> Path:
    """Error of POD with 1 and 2 modes against the rotation angle (case C, Fig. 16).

    With the hull rotated by μ, the boundary displacement is
    ``(cos μ - 1) u + sin μ v`` for fixed fields u, v, and their IDW images are
    (nearly) orthogonal with equal norms: the field at μ points in the direction
    at angle μ/2 of their plane. One POD mode fixes one direction φ, so its
    relative error is ``|sin(μ/2 - φ)|`` whatever the mesh or the norm; over
    D = [-36°, 0] the best φ = -9° leaves sin 9° = 15.6 % at both ends. The
    dashed curve is that formula, φ taken from the measured minimum.

    Parameters
    ----------
    sweep : dict
        :func:`~torchmorph.paper.pod_parameter_sweep`'s output (``"mu"`` and
        ``"error_nodal"`` with ``"POD-IDW, 1 mode"`` etc.).
    path : str or Path
        The PNG to write.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    mu = np.asarray(sweep["mu"], dtype=float)
    figure, axes = plt.subplots(1, 2, figsize=(11, 4.2), constrained_layout=True)
    for ax, norm, name in (
        (axes[0], "error_nodal", "nodal ℓ2 norm (the paper's reading)"),
        (axes[1], "error", "P1 mass-matrix norm"),
    ):
        for label, values in sweep[norm].items():
            if "mode" not in label:
                continue
            values = np.asarray(values, dtype=float)
            style = "-" if "1 mode" in label else ":"
            ax.semilogy(mu, np.maximum(values, 1e-17), style, marker=".", ms=3, label=label)
        one = np.asarray(sweep[norm]["POD-IDW, 1 mode"], dtype=float)
        phi = math.radians(float(mu[np.argmin(one)])) / 2.0
        bound = np.abs(np.sin(np.radians(mu) / 2.0 - phi))
        ax.semilogy(mu, np.maximum(bound, 1e-17), "k--", lw=1.0, label="|sin(μ/2 − φ)|, one mode")
        ax.axhline(
            math.sin(math.radians(9.0)),
            color="0.5",
            lw=0.8,
            label="sin 9° = 15.6 %: best worst case",
        )
        ax.set_ylim(1e-17, 1.0)
        ax.set_xlabel("rotation angle μ [°]")
        ax.set_ylabel("relative error against IDW")
        ax.set_title(name, fontsize=10)
        ax.legend(fontsize=7, loc="lower left")
    figure.suptitle(title or "Case C: POD with 1 and 2 modes over D = [−36°, 0°]")
    path = Path(path)
    with atomic_output(path) as temporary:
        figure.savefig(temporary, dpi=100, format="png")
    plt.close(figure)
    return path
