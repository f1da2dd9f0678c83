"""Rotation sweep: how far a body can turn before the morph folds a cell.

Three bodies turned by a growing angle, their meshes morphed four ways:

- **plain**: IDW in one shot (Algorithm 2 of Ballarin et al. 2017, every boundary node a
  control point);
- **steps**: the same in ``--steps`` increments along the rotation, each from the
  previous mesh (:func:`torchmorph.large_motions.morph_in_steps`);
- **rotations**: rotation-aware IDW in one shot (``MeshMorph(...)(d, rotations="fit")``,
  :mod:`torchmorph.idw.rotations`);
- **both**: rotation-aware and in steps;
- **rbf**: a thin-plate-spline RBF with the linear polynomial (``torchmorph.RBF``) from
  every boundary node, in one shot, for comparison;
- **stiffened**: IDW with near-wall stiffening (``torchmorph.idw.StiffenedIDW``: weights
  ``r^-4 + ℓ² r^-6``, ℓ a fifth of the moving body's largest extent), in one shot.

The bodies: the Wigley hull of the paper's case C pitched about its centre (the z axis;
0° to 90°, bow down), a 2-D NACA0012 section in a 16 × 8 chord box turned about its
quarter chord (meshed here with gmsh, triangles), and the wing of case A twisted about
its quarter-chord line by an angle growing linearly from the root (0 at the clamped root)
to the tip. For each angle: inverted cells, the smallest scaled Jacobian and the largest
edge ratio Q; then, per method, the first angle at which a cell folds (to 0.5° by
bisection from the sweep's first failing angle). Prints markdown tables and writes a
plot (``--plot``).

    python benchmarks/large_motions.py                 # paper-size meshes, a few minutes
    python benchmarks/large_motions.py --size small --step 15
"""

from __future__ import annotations

import argparse
import math
import platform
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from torchmorph import RBF, MeshMorph
from torchmorph.idw import StiffenedIDW
from torchmorph.large_motions import morph_in_steps
from torchmorph.mesh import Mesh, quality_summary

METHODS = ("plain", "steps", "rotations", "both", "rbf", "stiffened")

#: Near-wall stiffening of the "stiffened" method: the power q and ℓ as a share of the
#: moving body's largest extent.
STIFFENING_POWER, STIFFENING_SHARE = 6.0, 0.2


@dataclass
class Case:
    name: str
    mesh: Mesh
    moving: tuple[str, ...]
    turn: Callable[[Tensor, float], Tensor]  # (points, degrees) -> displacement
    angles: list[float]


def _rotation(points: Tensor, degrees: float, centre: tuple[float, float], axes=(0, 1)) -> Tensor:
    angle = math.radians(degrees)
    c, s = math.cos(angle), math.sin(angle)
    i, j = axes
    x, y = points[:, i] - centre[0], points[:, j] - centre[1]
    out = torch.zeros_like(points)
    out[:, i] = c * x - s * y - x
    out[:, j] = s * x + c * y - y
    return out


def airfoil_mesh(size: str) -> Mesh:
    """A NACA0012 section (chord 1.01 m, as the paper's wing) in the box
    [-7.5, 8.5] × [-4, 4], triangles graded from the profile; face sets ``airfoil`` and
    ``walls``."""
    from data_gen.geometry import CHORD, naca_half_thickness
    from torchmorph.meshing.gmsh_model import gmsh_session

    near, far = (0.03, 0.8) if size == "paper" else (0.08, 1.6)
    with gmsh_session("airfoil_sweep", seed=0, verbose=False) as gmsh:
        geo = gmsh.model.geo
        x = CHORD * 0.5 * (1 - np.cos(np.linspace(0, math.pi, 81)))
        y = naca_half_thickness(x)
        upper = [geo.addPoint(float(a), float(b), 0.0, near) for a, b in zip(x, y, strict=True)]
        lower = [upper[0]] + [
            geo.addPoint(float(a), float(-b), 0.0, near)
            for a, b in zip(x[1:-1], y[1:-1], strict=True)
        ]
        lower.append(upper[-1])
        curves = [geo.addSpline(upper), geo.addSpline(lower)]
        profile = geo.addCurveLoop([curves[0], -curves[1]])
        corners = [(-7.5, -4.0), (8.5, -4.0), (8.5, 4.0), (-7.5, 4.0)]
        box = [geo.addPoint(a, b, 0.0, far) for a, b in corners]
        walls = [geo.addLine(box[k], box[(k + 1) % 4]) for k in range(4)]
        outer = geo.addCurveLoop(walls)
        geo.addPlaneSurface([outer, profile])
        geo.synchronize()
        gmsh.model.mesh.generate(2)
        tags, coordinates, _ = gmsh.model.mesh.getNodes()
        order = np.argsort(tags)
        points = coordinates.reshape(-1, 3)[order, :2]
        index = {int(t): k for k, t in enumerate(tags[order])}
        _, _, nodes = gmsh.model.mesh.getElements(2)
        triangles = np.vectorize(index.get)(nodes[0].reshape(-1, 3).astype(np.int64))

        def lines(tags_1d):
            found = []
            for tag in tags_1d:
                _, _, edge_nodes = gmsh.model.mesh.getElements(1, tag)
                found.append(np.vectorize(index.get)(edge_nodes[0].reshape(-1, 2).astype(np.int64)))
            return np.concatenate(found)

        airfoil, box_lines = lines(curves), lines(walls)
    return Mesh(
        points,
        [("triangle", triangles)],
        face_sets={"airfoil": [("line", airfoil)], "walls": [("line", box_lines)]},
    )


def cases(size: str, step: float) -> list[Case]:
    from torchmorph.paper import load_mesh
    from torchmorph.paper.cases import hull_rotation

    def sweep(stop: float) -> list[float]:
        return [float(a) for a in np.arange(step, stop + 1e-9, step)]

    chord = 1.01
    span = 2 * math.pi

    def twist(points: Tensor, degrees: float) -> Tensor:
        angle = torch.deg2rad(torch.as_tensor(degrees, dtype=points.dtype)) * points[:, 2] / span
        c, s = torch.cos(angle), torch.sin(angle)
        x, y = points[:, 0] - 0.25 * chord, points[:, 1]
        out = torch.zeros_like(points)
        out[:, 0], out[:, 1] = c * x - s * y - x, s * x + c * y - y
        return out

    return [
        Case(
            "hull (case C), pitch",
            load_mesh("hull", size=size),
            ("hull",),
            lambda p, a: hull_rotation(p, torch.tensor(-a, dtype=p.dtype)),
            sweep(90.0),
        ),
        Case(
            "NACA0012 section, 2-D",
            airfoil_mesh(size),
            ("airfoil",),
            lambda p, a: _rotation(p, a, (0.25 * chord, 0.0)),
            sweep(90.0),
        ),
        Case(
            "wing (case A), tip twist",
            load_mesh("wing", size=size),
            ("upper", "lower", "tip", "leading_edge", "trailing_edge"),
            twist,
            sweep(45.0),
        ),
    ]


_RBF_CACHE: dict[int, RBF] = {}
_STIFFENED_CACHE: dict[int, StiffenedIDW] = {}


def stiffened(morph: MeshMorph, case: Case) -> StiffenedIDW:
    """IDW with near-wall stiffening from every boundary node, built once per mesh."""
    key = id(morph)
    if key not in _STIFFENED_CACHE:
        body = morph.points[case.mesh.node_set(case.moving[0])]
        for name in case.moving[1:]:
            body = torch.cat([body, morph.points[case.mesh.node_set(name)]])
        extent = float((body.amax(0) - body.amin(0)).max())
        _STIFFENED_CACHE[key] = StiffenedIDW(
            morph.points[morph.boundary_nodes],
            morph.points[morph.interior_nodes],
            stiffening_power=STIFFENING_POWER,
            stiffening_length=STIFFENING_SHARE * extent,
        )
    return _STIFFENED_CACHE[key]


def morph_once(morph: MeshMorph, case: Case, method: str, degrees: float, steps: int) -> Tensor:
    def path(t: float) -> Tensor:
        return morph.boundary_displacement(case.moving, lambda p: case.turn(p, t * degrees))

    if method == "rbf":  # the fit once per mesh, reused for every angle
        key = id(morph)
        if key not in _RBF_CACHE:
            _RBF_CACHE[key] = RBF(
                morph.points[morph.boundary_nodes], morph.points[morph.interior_nodes]
            )
        boundary = path(1.0)
        return morph.assemble(boundary, _RBF_CACHE[key](boundary))
    if method == "stiffened":
        boundary = path(1.0)
        return morph.assemble(boundary, stiffened(morph, case)(boundary))

    rotations = "fit" if method in ("rotations", "both") else None
    if method in ("steps", "both"):
        return morph_in_steps(morph, path, steps, rotations=rotations).displacement
    return morph(path(1.0), rotations=rotations)


def first_failure(
    morph: MeshMorph, case: Case, method: str, rows: list[dict], steps: int
) -> float | None:
    """The first angle at which a cell folds, to 0.5° by bisection from the sweep."""
    good, bad = 0.0, None
    for row in rows:
        if row[method]["num_inverted"] > 0:
            bad = row["angle"]
            break
        good = row["angle"]
    if bad is None:
        return None
    while bad - good > 0.5:
        middle = 0.5 * (good + bad)
        if morph.count_inverted(morph_once(morph, case, method, middle, steps)):
            bad = middle
        else:
            good = middle
    return bad


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", choices=("small", "paper"), default="paper")
    parser.add_argument("--step", type=float, default=5.0, help="angle step [degrees]")
    parser.add_argument("--steps", type=int, default=10, help="increments of 'steps'/'both'")
    parser.add_argument("--plot", default="docs/large_motions.png", help="'' for none")
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(
        f"torch {torch.__version__}, {platform.processor() or platform.machine()}, one "
        f"thread, float64, size {args.size}; {args.steps} increments for steps/both\n"
    )
    results = {}
    for case in cases(args.size, args.step):
        start = time.perf_counter()
        morph = MeshMorph(case.mesh)
        rows = []
        for angle in case.angles:
            row: dict = {"angle": angle}
            for method in METHODS:
                summary = quality_summary(
                    case.mesh, morph_once(morph, case, method, angle, args.steps)
                )
                row[method] = summary
            rows.append(row)
        firsts = {m: first_failure(morph, case, m, rows, args.steps) for m in METHODS}
        results[case.name] = (rows, firsts)
        print(
            f"### {case.name}: {case.mesh.num_nodes} nodes, {case.mesh.num_cells} cells, "
            f"{morph.num_boundary} boundary nodes ({time.perf_counter() - start:.0f} s)\n"
        )
        print("| angle | " + " | ".join(f"{m}: inverted / min SJ / max Q" for m in METHODS) + " |")
        print("|---:|" + "---:|" * len(METHODS))
        for row in rows:
            cells = [
                f"{row[m]['num_inverted']} / {row[m]['min_scaled_jacobian']:.3f} / "
                f"{row[m]['max_edge_ratio']:.1f}"
                for m in METHODS
            ]
            print(f"| {row['angle']:.0f}° | " + " | ".join(cells) + " |")
        print(
            "\nfirst angle with an inverted cell: "
            + ", ".join(f"{m} {_angle(a, case.angles[-1])}" for m, a in firsts.items())
            + "\n"
        )
    if args.plot:
        plot(results, Path(args.plot))
        print(f"wrote {args.plot}")


def _angle(first: float | None, last: float) -> str:
    return f"none up to {last:.0f}°" if first is None else f"{first:.1f}°"


def plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(2, len(results), figsize=(5.2 * len(results), 7.5))
    for column, (name, (rows, _)) in enumerate(results.items()):
        angles = [row["angle"] for row in rows]
        for method, style in zip(METHODS, ("o-", "s--", "^-", "D-", "x:", "v-."), strict=True):
            inverted = [row[method]["num_inverted"] for row in rows]
            jacobian = [row[method]["min_scaled_jacobian"] for row in rows]
            axes[0, column].plot(angles, inverted, style, ms=3, label=method)
            axes[1, column].plot(angles, jacobian, style, ms=3, label=method)
        axes[0, column].set(title=name, ylabel="inverted cells", yscale="symlog")
        axes[1, column].set(xlabel="angle [°]", ylabel="smallest scaled Jacobian")
        axes[1, column].axhline(0.0, color="k", lw=0.6)
        axes[0, column].legend(fontsize=8)
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=120)
    plt.close(figure)


if __name__ == "__main__":
    main()
