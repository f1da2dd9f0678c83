"""Benchmark of control-point selection (Algorithm 1, SPEC.md §2) and of its effect on IDW.

Two tables, printed as markdown:

1. Selection time against the number of candidates (10^3 .. 10^6 points on the unit
   sphere, R chosen so that about 2.5 % of them are selected): the KD-tree
   implementation (:func:`torchmorph.selection.select_control_points`, three
   strategies) and the plain O(N^2) transcription of the pseudocode kept in
   ``tests/test_selection.py`` (up to ``--max-reference`` candidates).
2. A problem of the size of the paper's case B (fluid wing in a tunnel): about 14k
   boundary points (tunnel walls plus a NACA0012 wing surface) and 22k interior
   targets, morphed by ``δy = μ z²`` on the wing (walls fixed). Full IDW (every
   boundary point a control) against ESIDW with the paper's per-region radii:
   control count, selection, assembly and morph times, and the relative nodal
   error of the interior displacement against full IDW.

Run ``python benchmarks/selection.py`` (about 2-3 minutes on 2 cores; ``--quick`` for a
smaller run). Times are medians of repeats.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import scipy
import torch

from torchmorph.idw import IDW
from torchmorph.selection import Region, SelectionPlan, select_control_points

# the plain reference lives with the tests, where it is checked against the library
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_selection import reference_sidw

# Selections per unit sphere at radius R with the default a, b: about 9.4 / R^2.
SPHERE_SELECTION_CONSTANT = 9.4


def median_time(function, repeats: int) -> tuple[float, object]:
    """Median wall time of ``repeats`` calls and the last result."""
    times, result = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        result = function()
        times.append(time.perf_counter() - start)
    return statistics.median(times), result


def sphere_points(count: int, seed: int = 0) -> np.ndarray:
    points = np.random.default_rng(seed).normal(size=(count, 3))
    return points / np.linalg.norm(points, axis=1, keepdims=True)


def selection_scaling(sizes, fraction: float, repeats: int, max_reference: int) -> list[str]:
    rows = [
        (
            "| candidates | R | selected (random) | random [s] | centroid [s] | farthest [s] "
            "| plain reference, random [s] | speed-up |"
        ),
        "|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    print("\n".join(rows), flush=True)
    for count in sizes:
        points = sphere_points(count)
        radius = float(np.sqrt(SPHERE_SELECTION_CONSTANT / (fraction * count)))
        reps = repeats if count < 10**6 else max(1, min(repeats, 3))
        times = {}
        selected = None
        for strategy in ("random", "centroid", "farthest"):
            times[strategy], result = median_time(
                lambda points=points, radius=radius, strategy=strategy: select_control_points(
                    points, radius, strategy=strategy, generator=torch.Generator().manual_seed(0)
                ),
                reps,
            )
            if strategy == "random":
                selected = result
        if count <= max_reference:
            start = int(selected[0])
            reference_time, expected = median_time(
                lambda points=points, radius=radius, start=start, count=count: reference_sidw(
                    points, radius, 0.8, 1.3, start, "random", _generator_after_start(count)
                ),
                max(1, reps // 2),
            )
            assert expected == selected.tolist(), "fast and plain selections differ"
            reference = f"{reference_time:.3f}"
            speedup = f"{reference_time / times['random']:.1f}×"
        else:
            reference, speedup = "–", "–"
        rows.append(
            f"| {count:,} | {radius:.4f} | {len(selected):,} | {times['random']:.3f} "
            f"| {times['centroid']:.3f} | {times['farthest']:.3f} | {reference} | {speedup} |"
        )
        print(rows[-1], flush=True)
    return rows


def _generator_after_start(count: int) -> torch.Generator:
    """The generator state after the library has drawn its random start point."""
    generator = torch.Generator().manual_seed(0)
    torch.randint(count, (1,), generator=generator)
    return generator


# --------------------------------------------------------------------------------------
# case-B-sized synthetic problem
# --------------------------------------------------------------------------------------

CHORD, SPAN = 1.01, 2 * np.pi
BOX = np.array([10.0, 5.0, 4 * np.pi])
WING_X, WING_Y = 3.0, 2.5  # leading edge position in the tunnel


def naca0012_half_thickness(x: np.ndarray) -> np.ndarray:
    t = np.clip(x / CHORD, 0.0, 1.0)
    return (
        0.6
        * CHORD
        * (0.2969 * np.sqrt(t) - 0.1260 * t - 0.3516 * t**2 + 0.2843 * t**3 - 0.1036 * t**4)
    )  # closed trailing edge


def inside_wing(points: np.ndarray) -> np.ndarray:
    x = points[:, 0] - WING_X
    return (
        (x >= 0)
        & (x <= CHORD)
        & (points[:, 2] <= SPAN)
        & (np.abs(points[:, 1] - WING_Y) < naca0012_half_thickness(x))
    )


class PointCloud:
    """Points with named node sets: what :class:`SelectionPlan` needs of a mesh."""

    def __init__(self, points: np.ndarray, sets: dict[str, np.ndarray], boundary: np.ndarray):
        self.points = torch.from_numpy(points)
        self.boundary_nodes = torch.from_numpy(boundary)
        self.sets = {name: torch.from_numpy(np.sort(ids)) for name, ids in sets.items()}

    def node_set(self, name: str) -> torch.Tensor:
        if name not in self.sets:
            raise ValueError(f"unknown node set {name!r}; known: {', '.join(sorted(self.sets))}")
        return self.sets[name]


def case_b_cloud(
    wall_count: int, wing_stations: tuple[int, int], interior_count: int, seed: int = 0
) -> tuple[PointCloud, np.ndarray]:
    """Tunnel walls (random points), wing surface (structured), interior targets."""
    rng = np.random.default_rng(seed)
    blocks, sets = [], {}

    def add(name, block):
        offset = sum(len(b) for b in blocks)
        blocks.append(block)
        sets[name] = np.arange(offset, offset + len(block))

    # walls, points in proportion to their area
    walls = {
        "bottom": (1, 0.0),
        "top": (1, BOX[1]),
        "front": (0, 0.0),
        "rear": (0, BOX[0]),
        "root_wall": (2, 0.0),
        "far_wall": (2, BOX[2]),
    }
    areas = {name: np.prod(np.delete(BOX, axis)) for name, (axis, _) in walls.items()}
    total_area = sum(areas.values())
    for name, (axis, value) in walls.items():
        block = rng.random((int(wall_count * areas[name] / total_area), 3)) * BOX
        block[:, axis] = value
        if name == "root_wall":  # no wall inside the wing's root section
            block = block[~inside_wing(block + [0, 0, 1e-9])]
        add(name, block)

    # wing: cosine-spaced stations around the section, uniform along the span
    chordwise, spanwise = wing_stations
    t = 0.5 * (1 - np.cos(np.linspace(0.0, np.pi, chordwise)))  # 0 .. 1, both ends
    x = t * CHORD
    z = np.linspace(0.0, SPAN, spanwise)
    half = naca0012_half_thickness(x)
    for name, sign, columns in (
        ("upper", 1.0, slice(1, -1)),
        ("lower", -1.0, slice(1, -1)),
        ("leading_edge", 0.0, slice(0, 1)),
        ("trailing_edge", 0.0, slice(-1, None)),
    ):
        xx, zz = np.meshgrid(x[columns], z[1:], indexing="ij")
        yy = sign * np.repeat(half[columns, None], len(z) - 1, axis=1)
        add(name, np.stack([xx.ravel() + WING_X, yy.ravel() + WING_Y, zz.ravel()], 1))
    section = np.concatenate([np.stack([x, half], 1), np.stack([x[1:-1], -half[1:-1]], 1)])
    add(
        "root_profile",
        np.column_stack([section[:, 0] + WING_X, section[:, 1] + WING_Y, np.zeros(len(section))]),
    )
    # tip cap: the section shrunk towards its camber line
    cap = [
        np.column_stack(
            [section[:, 0] + WING_X, s * section[:, 1] + WING_Y, np.full(len(section), SPAN)]
        )
        for s in np.linspace(1, 0, 6)[:-1]
    ]
    add("tip", np.concatenate(cap))

    boundary = np.concatenate(blocks)
    # interior: half uniform in the tunnel, half clustered around the wing
    uniform = rng.random((interior_count, 3)) * BOX
    near = np.column_stack(
        [
            rng.uniform(WING_X - 0.5, WING_X + CHORD + 1.0, interior_count),
            WING_Y + rng.normal(0.0, 0.4, interior_count),
            rng.uniform(0.0, SPAN + 0.5, interior_count),
        ]
    )
    interior = np.concatenate([uniform[: interior_count // 2], near])
    interior = interior[~inside_wing(interior) & np.all((interior > 0) & (interior < BOX), 1)]
    interior = interior[:interior_count]
    points = np.concatenate([boundary, interior])
    cloud = PointCloud(points, sets, np.arange(len(boundary)))
    return cloud, np.arange(len(boundary), len(points))


def case_b_plan(enrich: bool = True) -> SelectionPlan:
    """The paper's case-B selection: box R 0.5 / 0.25, wing R 0.05, ESIDW enrichment."""
    return SelectionPlan(
        [
            Region(("top", "bottom", "front", "rear"), 0.5),
            Region(("root_wall", "far_wall"), 0.25),
            Region(
                ("upper", "lower", "leading_edge", "trailing_edge", "root_profile", "tip"), 0.05
            ),
        ],
        enrich=["root_profile", "leading_edge", "trailing_edge"] if enrich else (),
    )


def case_b(wall_count, wing_stations, interior_count, repeats, dtype) -> list[str]:
    cloud, interior = case_b_cloud(wall_count, wing_stations, interior_count)
    points = cloud.points.to(dtype)
    boundary = cloud.boundary_nodes
    wing = torch.cat(
        [
            cloud.node_set(name)
            for name in ("upper", "lower", "leading_edge", "trailing_edge", "root_profile", "tip")
        ]
    )
    displacement = torch.zeros_like(points)
    displacement[wing, 1] = 0.01 * points[wing, 2] ** 2  # δy = μ z², μ = 0.01
    targets = points[interior]

    rows = [
        (
            f"Synthetic case-B-sized cloud: {boundary.numel():,} boundary points "
            f"({wing.numel():,} on the wing), {interior.size:,} interior targets, {dtype}."
        ),
        "",
        (
            "| method | control points | selection [s] | assembly of W [s] | morph [s] "
            "| rel. error vs IDW |"
        ),
        "|---|---:|---:|---:|---:|---:|",
    ]
    print("\n".join(rows), flush=True)
    methods = [("IDW", boundary, None)]
    for method, plan in (("SIDW", case_b_plan(enrich=False)), ("ESIDW", case_b_plan())):
        seconds, selected = median_time(
            lambda plan=plan: plan.select(cloud, generator=torch.Generator().manual_seed(0)),
            repeats,
        )
        methods.append((method, selected, seconds))
    # methods interleaved within each repeat, so that all see the same background load
    assembly_times = {method: [] for method, _, _ in methods}
    morph_times = {method: [] for method, _, _ in methods}
    results = {}
    for _ in range(repeats):
        for method, controls, _ in methods:
            start = time.perf_counter()
            idw = IDW(points[controls], targets, mode="dense")
            assembly_times[method].append(time.perf_counter() - start)
            morph_time, results[method] = median_time(
                lambda idw=idw, d=displacement[controls]: idw(d), 3
            )
            morph_times[method].append(morph_time)
            idw = None  # free W before the next assembly
    reference = results["IDW"]
    for method, controls, select_seconds in methods:
        error = (
            "–"
            if method == "IDW"
            else f"{float((results[method] - reference).norm() / reference.norm()):.2%}"
        )
        selection = "–" if select_seconds is None else f"{select_seconds:.3f}"
        rows.append(
            f"| {method} | {controls.numel():,} | {selection} "
            f"| {statistics.median(assembly_times[method]):.2f} "
            f"| {statistics.median(morph_times[method]):.4f} | {error} |"
        )
        print(rows[-1], flush=True)
    return rows


def cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smaller sizes, fewer repeats")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument(
        "--max-reference",
        type=int,
        default=10**5,
        help="largest candidate count timed with the plain reference",
    )
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    args = parser.parse_args()
    sizes = (10**3, 10**4, 10**5) if args.quick else (10**3, 10**4, 10**5, 10**6)
    repeats = 2 if args.quick else args.repeats
    machine = (
        f"{cpu_name()}, {os.cpu_count()} cores, {torch.get_num_threads()} torch "
        f"threads; Python {platform.python_version()}, torch {torch.__version__}, "
        f"numpy {np.__version__}, scipy {scipy.__version__}"
    )
    print(f"Machine: {machine}")
    print("Load average (1, 5, 15 min) at start: {:.1f}, {:.1f}, {:.1f}\n".format(*os.getloadavg()))
    print("### Selection time against candidate count (unit sphere, ~2.5 % selected)\n")
    selection_scaling(sizes, 0.025, repeats, args.max_reference)
    print("\n### Case-B-sized problem: full IDW against ESIDW\n")
    if args.quick:
        case_b(3000, (24, 80), 6000, 2, getattr(torch, args.dtype))
    else:
        case_b(6000, (30, 130), 22000, args.repeats, getattr(torch, args.dtype))
    print("\nLoad average at the end: {:.1f}, {:.1f}, {:.1f}".format(*os.getloadavg()))


if __name__ == "__main__":
    main()
