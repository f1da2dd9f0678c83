"""Partitioned fluid–structure interaction on the paper's wing: the morph inside the loop.

The elastic NACA0012 wing of case A (linear elasticity, P1 tetrahedra, clamped at the
root) sits in the tunnel of case B (potential flow, P1 on the fluid tetrahedra), both
solved with scikit-fem. One coupling iteration (block Gauss–Seidel, Dirichlet–Neumann):

1. fluid solve on the current (morphed) fluid mesh → Bernoulli pressure on the wing;
2. transfer: the wing-face forces onto the structure's surface nodes (conservative map);
3. structural solve → displacement of the wing;
4. transfer: the wing surface displacement onto the fluid mesh's wing nodes;
5. **torchmorph moves the fluid mesh**: the tunnel walls stay, the wing nodes take their
   displacement exactly, the interior follows by POD-ESIDW (Algorithm 3 of Ballarin et
   al. 2017 on the ESIDW selection of their section 2.3.2), or by ESIDW or full IDW
   (Algorithm 2) for comparison;

with Aitken's dynamic relaxation of the interface displacement, until the relative
change of the wing displacement falls below ``--tolerance``. The flow has no
circulation (no wake, no Kutta condition), so its load on the wing is a moment rather
than a lift: Munk's moment, nose up for a positive angle of attack, which twists the
wing, raising the angle and with it the moment. That static aeroelastic feedback is
what the coupling captures and a one-way analysis (the structure under the load of the
undeformed fluid mesh, the first iteration here) misses; the demo reports by how much.

The POD reducer is trained offline on the fluid-mesh morphs of the structure's
responses to the flow load at several angles of attack and to a few unit loads (tip
forces and torque, pressure on either face): the online morph costs two small products
per iteration. The table gives each part's share of an iteration for POD-ESIDW, ESIDW
and IDW, the coupled answer of each (they should agree: the morph moves only the fluid
mesh's interior), the cell validity of the morphed fluid mesh, and pictures of the
convergence and of a section of the deformed fluid mesh.

    pip install -e '.[mesh,fsi,plot]'
    python demos/fsi.py                       # paper-size meshes
    python demos/fsi.py --size small --out out/fsi
"""

from __future__ import annotations

import argparse
import copy
import math
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the demos' shared helpers

from _common import set_threads, synchronise

from torchmorph.mesh import TetMesh, count_inverted, signed_volumes
from torchmorph.morph import MeshMorph
from torchmorph.paper import get_case, load_mesh
from torchmorph.pod import PODReducer

WALLS = ("wall_x0", "wall_x1", "wall_y0", "wall_y1", "wall_z0", "wall_z1")
MORPHS = ("pod-esidw", "esidw", "idw")
PARTS = ("fluid", "transfer", "structure", "morph")


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        description="Partitioned FSI: potential flow around the paper's wing (case B) "
        "coupled to its linear elasticity (case A), the fluid mesh moved by torchmorph."
    )
    parser.add_argument("--size", choices=("small", "paper"), default="paper")
    parser.add_argument("--speed", type=float, default=30.0, help="free stream |U∞| [m/s]")
    parser.add_argument("--alpha", type=float, default=5.0, help="angle of attack [degrees]")
    parser.add_argument("--density", type=float, default=1.2, help="fluid density [kg/m³]")
    parser.add_argument(
        "--young", type=float, default=1.0e8, help="Young's modulus of the wing [Pa]"
    )
    parser.add_argument("--poisson", type=float, default=0.3, help="Poisson's ratio")
    parser.add_argument(
        "--tolerance",
        type=float,
        default=1e-6,
        help="convergence: |d_new - d| / |d_new| of the wing displacement (default 1e-6)",
    )
    parser.add_argument("--max-iterations", type=int, default=40)
    parser.add_argument(
        "--relaxation", type=float, default=0.5, help="Aitken's first relaxation factor"
    )
    parser.add_argument(
        "--morphs",
        default=",".join(MORPHS),
        help="comma-separated morphs to couple with, the first is the main one "
        "(default: %(default)s)",
    )
    parser.add_argument("--energy-tolerance", type=float, default=1e-8, help="POD ε (eq. 12)")
    parser.add_argument("--device", default="cpu", help="device of the morph (cpu or cuda)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the ESIDW selection")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--out", default="out/fsi", help="pictures go here ('' for none)")
    parser.add_argument("--quiet", action="store_true")
    return parser


def _check(args: argparse.Namespace) -> list[str]:
    morphs = [name.strip() for name in args.morphs.split(",") if name.strip()]
    unknown = [name for name in morphs if name not in MORPHS]
    if not morphs or unknown:
        raise SystemExit(f"--morphs: expected names among {', '.join(MORPHS)}, got {args.morphs!r}")
    for name in ("speed", "density", "young", "tolerance"):
        value = getattr(args, name)
        if not (math.isfinite(value) and value > 0):
            raise SystemExit(f"--{name}: must be a positive number, got {value}")
    if not -0.5 < args.poisson < 0.5:
        raise SystemExit(f"--poisson: must lie in (-0.5, 0.5), got {args.poisson}")
    if args.max_iterations < 1:
        raise SystemExit(f"--max-iterations: must be at least 1, got {args.max_iterations}")
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        raise SystemExit("--device cuda asked for, but torch sees no CUDA device")
    return morphs


# ---------------------------------------------------------------------- the problem


@dataclass
class Interface:
    """The two meshes, their solvers and the maps between their wing surfaces."""

    fluid: TetMesh
    wing: TetMesh
    flow: Any  # _fsi_solvers.PotentialFlow
    structure: Any  # _fsi_solvers.Elasticity
    to_fluid: Any  # SurfaceMap: structure nodes -> fluid wing nodes
    to_structure: Any  # SurfaceMap: structure nodes -> fluid wing-face centroids
    fluid_wing_nodes: np.ndarray  # fluid node ids that follow the wing
    tip_le: int  # structure node ids of the tip's leading and trailing edges
    tip_te: int
    tip_nodes: np.ndarray

    def tip(self, displacement: np.ndarray) -> tuple[float, float]:
        """Tip deflection (mean vertical displacement of the tip face) [m] and twist [°],
        positive nose up."""
        chord = float(self.wing.points[self.tip_te, 0] - self.wing.points[self.tip_le, 0])
        rise = displacement[self.tip_le, 1] - displacement[self.tip_te, 1]
        return float(displacement[self.tip_nodes, 1].mean()), math.degrees(math.atan2(rise, chord))


def build_interface(args: argparse.Namespace) -> Interface:
    from _fsi_solvers import Elasticity, PotentialFlow, SurfaceMap

    fluid = load_mesh("fluid-wing", size=args.size)
    wing = load_mesh("wing", size=args.size)
    points = fluid.points.numpy()
    faces = fluid.boundary_faces.numpy()
    on_wall = np.zeros(len(faces), dtype=bool)
    for name in WALLS:
        member = np.zeros(fluid.num_nodes, dtype=bool)
        member[fluid.node_set(name).numpy()] = True
        on_wall |= member[faces].all(axis=1)
    alpha = math.radians(args.alpha)
    velocity = args.speed * np.array([math.cos(alpha), math.sin(alpha), 0.0])
    flow = PotentialFlow(
        fluid.tets.numpy(),
        faces[on_wall],
        faces[~on_wall],
        fluid.num_nodes,
        velocity=velocity,
        density=args.density,
    )

    wing_points = wing.points.numpy()
    root = wing.node_set("root").numpy()
    structure = Elasticity(
        wing_points, wing.tets.numpy(), root, young=args.young, poisson=args.poisson
    )
    wing_faces = wing.boundary_faces.numpy()
    clamped = np.zeros(wing.num_nodes, dtype=bool)
    clamped[root] = True
    surface = wing_faces[~clamped[wing_faces].all(axis=1)]  # the wetted faces

    # the fluid's wing nodes, except those on the root wall (they stay on the wall)
    follows = np.zeros(fluid.num_nodes, dtype=bool)
    follows[fluid.node_set("wing").numpy()] = True
    follows[fluid.node_set("wall_z0").numpy()] = False
    fluid_wing_nodes = np.flatnonzero(follows)
    to_fluid = SurfaceMap(wing_points, surface, points[fluid_wing_nodes], num_nodes=wing.num_nodes)
    to_structure = SurfaceMap(
        wing_points, surface, points[flow.wing_faces].mean(axis=1), num_nodes=wing.num_nodes
    )
    tip = wing.node_set("tip").numpy()
    return Interface(
        fluid=fluid,
        wing=wing,
        flow=flow,
        structure=structure,
        to_fluid=to_fluid,
        to_structure=to_structure,
        fluid_wing_nodes=fluid_wing_nodes,
        tip_le=int(tip[np.argmin(wing_points[tip, 0])]),
        tip_te=int(tip[np.argmax(wing_points[tip, 0])]),
        tip_nodes=tip,
    )


class FluidMeshMotion:
    """Wing displacement (structure nodes) -> fluid node displacement, by one morph."""

    def __init__(self, interface: Interface, morph: Any, boundary_nodes: Tensor, device) -> None:
        self.interface = interface
        self.morph = morph
        self.device = device
        boundary = boundary_nodes.cpu().numpy()
        rows = np.searchsorted(boundary, interface.fluid_wing_nodes)
        if not np.array_equal(boundary[rows], interface.fluid_wing_nodes):
            raise RuntimeError("the fluid's wing nodes are not boundary nodes of the morph")
        self.rows = torch.as_tensor(rows, device=device)
        self.num_boundary = len(boundary)
        # the POD reducer writes straight into the NumPy array the fluid solver reads
        # (out= on a tensor that shares its memory): no copy on the way out
        self.buffer: np.ndarray | None = None
        if isinstance(morph, PODReducer) and torch.device(device).type == "cpu":
            self.buffer = np.zeros((interface.fluid.num_nodes, 3))
            self._out = torch.from_numpy(self.buffer)

    def boundary(self, wing_displacement: np.ndarray) -> Tensor:
        """(N_b, 3) boundary displacement of the fluid mesh: the wing's, walls fixed."""
        moved = self.interface.to_fluid.interpolate(wing_displacement)
        out = torch.zeros(self.num_boundary, 3, dtype=torch.float64, device=self.device)
        out[self.rows] = torch.as_tensor(moved, device=self.device)  # no copy of `moved`
        return out

    def __call__(self, boundary: Tensor) -> np.ndarray:
        """The fluid nodes' displacement (N, 3): a view of the morph's output on the CPU
        (``Tensor.numpy`` shares memory), or the reducer's own buffer."""
        with torch.no_grad():
            if self.buffer is not None:
                self.morph(boundary, out=self._out)
                return self.buffer
            displacement = self.morph(boundary)
        synchronise(self.device)
        return displacement.cpu().numpy()


def make_morphs(
    interface: Interface, names: Sequence[str], args: argparse.Namespace, say
) -> dict[str, FluidMeshMotion]:
    """The fluid-mesh morphs asked for; the POD reducer trained on structural responses."""
    device = torch.device(args.device)
    fluid = interface.fluid
    morphs: dict[str, FluidMeshMotion] = {}
    esidw = None
    if "esidw" in names or "pod-esidw" in names:
        generator = torch.Generator().manual_seed(args.seed)
        esidw = MeshMorph(fluid, get_case("fluid-wing").plan(), generator=generator)
        esidw = esidw.to(device)
        say(
            f"ESIDW: {esidw.num_controls} control points of {esidw.num_boundary} boundary "
            f"nodes ({esidw.selection_time:.2f} s selection, {esidw.assembly_time:.2f} s W)"
        )
    if "esidw" in names:
        morphs["esidw"] = FluidMeshMotion(interface, esidw, esidw.boundary_nodes, device)
    if "pod-esidw" in names:
        assert esidw is not None
        motion = FluidMeshMotion(interface, esidw, esidw.boundary_nodes, device)
        start = time.perf_counter()
        snapshots = torch.stack([motion.boundary(d) for d in training_responses(interface)])
        reducer = PODReducer(energy_tolerance=args.energy_tolerance).fit(esidw, snapshots)
        say(
            f"POD-ESIDW: {reducer.num_modes_} modes from {len(snapshots)} structural responses "
            f"({time.perf_counter() - start:.2f} s offline)"
        )
        morphs["pod-esidw"] = FluidMeshMotion(interface, reducer, esidw.boundary_nodes, device)
    if "idw" in names:
        idw = MeshMorph(fluid).to(device)
        say(f"IDW: all {idw.num_boundary} boundary nodes ({idw.assembly_time:.2f} s)")
        morphs["idw"] = FluidMeshMotion(interface, idw, idw.boundary_nodes, device)
    return {name: morphs[name] for name in names}


def training_responses(interface: Interface) -> list[np.ndarray]:
    """Wing displacements that span the coupled ones: the responses to the flow load at
    several angles of attack (the Bernoulli load is quadratic in U∞, so three angles
    span every angle on a fixed mesh) and to unit loads that the twisting adds (tip
    forces and a tip torque, uniform pressure on the upper or lower face)."""
    flow, structure, wing = interface.flow, interface.structure, interface.wing
    reference = interface.fluid.points.numpy()
    speed = float(np.linalg.norm(flow.velocity))
    responses = []
    for degrees in (-10.0, -5.0, 0.0, 5.0, 10.0):
        alpha = math.radians(degrees)
        flow_at = copy.copy(flow)  # the same mesh and faces, another free stream
        flow_at.velocity = speed * np.array([math.cos(alpha), math.sin(alpha), 0.0])
        forces = interface.to_structure.spread(flow_at.solve(reference).forces)
        responses.append(structure.solve(forces))
    points = wing.points.numpy()
    tip = interface.tip_nodes
    centre = points[tip].mean(axis=0)
    for direction in np.eye(3)[:2]:  # tip forces along x and y
        forces = np.zeros_like(points)
        forces[tip] = direction / len(tip)
        responses.append(structure.solve(forces))
    forces = np.zeros_like(points)  # a tip torque about the span
    arm = points[tip] - centre
    forces[tip] = np.stack([-arm[:, 1], arm[:, 0], 0 * arm[:, 0]], axis=1)
    responses.append(structure.solve(forces))
    for name in ("upper", "lower"):
        member = np.zeros(wing.num_nodes, dtype=bool)
        member[wing.node_set(name).numpy()] = True
        faces = wing.boundary_faces.numpy()
        faces = faces[member[faces].all(axis=1)]
        a, b, c = (points[faces[:, k]] for k in range(3))
        normals = 0.5 * np.cross(b - a, c - a)
        forces = np.zeros_like(points)
        for k in range(3):
            np.add.at(forces, faces[:, k], -normals / 3.0)
        responses.append(structure.solve(forces))
    return [r / max(np.abs(r).max(), 1e-300) for r in responses]


# ---------------------------------------------------------------------- the coupling


@dataclass
class Coupling:
    """The history and cost of one coupled solve."""

    morph: str
    residual: list[float] = field(default_factory=list)
    deflection: list[float] = field(default_factory=list)
    twist: list[float] = field(default_factory=list)
    omega: list[float] = field(default_factory=list)
    seconds: dict[str, list[float]] = field(default_factory=lambda: {p: [] for p in PARTS})
    converged: bool = False
    wing_displacement: np.ndarray | None = None
    fluid_displacement: np.ndarray | None = None
    one_way: tuple[float, float] = (0.0, 0.0)

    @property
    def iterations(self) -> int:
        return len(self.residual)

    def per_iteration(self) -> dict[str, float]:
        """Median seconds of each part over the iterations after the first."""
        times = {p: v[1:] if len(v) > 1 else v for p, v in self.seconds.items()}
        out = {p: float(np.median(v)) for p, v in times.items()}
        out["total"] = sum(out.values())
        return out


def couple(
    interface: Interface,
    motion: FluidMeshMotion,
    name: str,
    *,
    tolerance: float,
    max_iterations: int,
    relaxation: float,
    say,
) -> Coupling:
    """Block Gauss–Seidel with Aitken relaxation of the wing displacement, from rest."""
    from _fsi_solvers import Aitken

    reference = interface.fluid.points.numpy()
    structure = interface.structure
    record = Coupling(morph=name)
    aitken = Aitken(relaxation)
    wing_displacement = np.zeros((interface.wing.num_nodes, 3))
    fluid_displacement = np.zeros_like(reference)
    potential = None
    for iteration in range(max_iterations):
        start = time.perf_counter()
        solution = interface.flow.solve(reference + fluid_displacement, guess=potential)
        potential = solution.potential
        fluid_done = time.perf_counter()
        forces = interface.to_structure.spread(solution.forces)
        transfer_done = time.perf_counter()
        response = structure.solve(forces)
        structure_done = time.perf_counter()
        if iteration == 0:
            record.one_way = interface.tip(response)
        residual = response - wing_displacement
        size = float(np.linalg.norm(response))
        relative = float(np.linalg.norm(residual)) / max(size, 1e-300)
        omega = aitken.step(residual)
        wing_displacement = wing_displacement + omega * residual
        deflection, twist = interface.tip(response)
        record.residual.append(relative)
        record.deflection.append(deflection)
        record.twist.append(twist)
        record.omega.append(omega)
        move_start = time.perf_counter()
        boundary = motion.boundary(wing_displacement)
        interface_done = time.perf_counter()
        fluid_displacement = motion(boundary)
        morph_done = time.perf_counter()
        seconds = record.seconds
        seconds["fluid"].append(fluid_done - start)
        seconds["transfer"].append(transfer_done - fluid_done + interface_done - move_start)
        seconds["structure"].append(structure_done - transfer_done)
        seconds["morph"].append(morph_done - interface_done)
        say(
            f"  {name:>9s} {iteration:3d}  residual {relative:9.2e}  ω {omega:6.3f}  "
            f"tip deflection {deflection * 1e3:8.3f} mm  twist {twist:7.4f}°"
        )
        if relative < tolerance:
            record.converged = True
            break
    record.wing_displacement = wing_displacement
    record.fluid_displacement = fluid_displacement
    return record


# ---------------------------------------------------------------------- reporting


def _validity(interface: Interface, displacement: np.ndarray) -> tuple[int, float]:
    fluid = interface.fluid
    moved = torch.as_tensor(displacement)
    inverted = count_inverted(fluid, moved)
    ratio = signed_volumes(fluid.points + moved, fluid.tets) / fluid.volumes
    return int(inverted), float(ratio.min())


def _table(records: dict[str, Coupling], say) -> None:
    say(
        f"\n{'morph':>10s} {'iter':>5s} {'fluid':>9s} {'transfer':>9s} {'structure':>10s} "
        f"{'morph':>9s} {'total':>9s} {'morph share':>12s}   (median seconds per iteration)"
    )
    for name, record in records.items():
        t = record.per_iteration()
        say(
            f"{name:>10s} {record.iterations:5d} {t['fluid']:9.4f} {t['transfer']:9.4f} "
            f"{t['structure']:10.4f} {t['morph']:9.5f} {t['total']:9.4f} "
            f"{100 * t['morph'] / t['total']:11.2f} %"
        )


def section(
    points: np.ndarray, tets: np.ndarray, displacement: np.ndarray, level: float
) -> tuple[list[np.ndarray], np.ndarray]:
    """The cut of the tetrahedra by the plane z = ``level`` (reference mesh), drawn at the
    displaced positions: one x–y polygon (3 or 4 corners) per cut tet, and the mean
    |displacement| of its corners."""
    height = points[tets, 2] - level  # (M, 4)
    crossing = (height.min(axis=1) < 0) & (height.max(axis=1) > 0)
    pairs = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
    polygons, values = [], []
    moved = points + displacement
    for tet, h in zip(tets[crossing], height[crossing], strict=True):
        corners, sizes = [], []
        for i, j in pairs:
            if (h[i] < 0) != (h[j] < 0):
                t = h[i] / (h[i] - h[j])
                corners.append((1 - t) * moved[tet[i], :2] + t * moved[tet[j], :2])
                sizes.append(
                    np.linalg.norm((1 - t) * displacement[tet[i]] + t * displacement[tet[j]])
                )
        corners_array = np.array(corners)
        centre = corners_array.mean(axis=0)
        angle = np.arctan2(*(corners_array - centre).T[::-1])
        polygons.append(corners_array[np.argsort(angle)])
        values.append(float(np.mean(sizes)))
    return polygons, np.array(values)


def _plot(interface: Interface, records: dict[str, Coupling], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    figure, axes = plt.subplots(1, 3, figsize=(17, 4.6))
    for name, record in records.items():
        steps = range(1, record.iterations + 1)
        axes[0].semilogy(steps, record.residual, marker="o", ms=3, label=name)
        axes[1].plot(steps, record.twist, marker="o", ms=3, label=f"{name}: twist")
    main = next(iter(records.values()))
    axes[0].set(xlabel="coupling iteration", ylabel="|d̃ − d| / |d̃|", title="interface residual")
    axes[0].legend()
    axes[1].axhline(main.one_way[1], color="k", ls=":", label="one-way twist")
    axes[1].set(xlabel="coupling iteration", ylabel="tip twist [°]", title="tip twist")
    twin = axes[1].twinx()
    twin.plot(
        range(1, main.iterations + 1),
        [1e3 * d for d in main.deflection],
        "C3--",
        label=f"{main.morph}: deflection",
    )
    twin.set_ylabel("tip deflection [mm]", color="C3")
    axes[1].legend(loc="center right")

    # a section of the deformed fluid mesh near the tip, coloured by |displacement|
    fluid = interface.fluid
    level = 0.9 * float(interface.wing.points[:, 2].max())
    polygons, values = section(
        fluid.points.numpy(), fluid.tets.numpy(), main.fluid_displacement, level
    )
    cells = PolyCollection(polygons, array=1e3 * values, cmap="viridis", edgecolors="0.25")
    cells.set_linewidth(0.25)
    axes[2].add_collection(cells)
    figure.colorbar(cells, ax=axes[2], label="|displacement| [mm]")
    axes[2].set(
        xlim=(-0.5, 1.5),
        ylim=(-0.55, 0.55),
        aspect="equal",
        xlabel="x [m]",
        ylabel="y [m]",
        title=f"deformed fluid mesh at z = {level:.2f} m ({main.morph})",
    )
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=130)
    plt.close(figure)


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Run the demo with command-line arguments ``argv``; returns the results."""
    args = _parser().parse_args(argv)
    names = _check(args)
    try:
        import skfem  # noqa: F401
    except ImportError:
        raise SystemExit(
            "demos/fsi.py needs scikit-fem, the fsi extra: pip install -e '.[fsi]'"
        ) from None
    set_threads(args.threads)
    say = (lambda *a, **k: None) if args.quiet else print
    start = time.perf_counter()
    interface = build_interface(args)
    say(
        f"fluid: {interface.fluid.num_nodes} nodes, {interface.fluid.num_tets} tets; wing: "
        f"{interface.wing.num_nodes} nodes, {interface.wing.num_tets} tets; surface gap "
        f"between the meshes ≤ {1e3 * interface.to_fluid.gaps.max():.2f} mm"
    )
    say(
        f"flow {args.speed:g} m/s at α = {args.alpha:g}°, ρ = {args.density:g} kg/m³; wing "
        f"E = {args.young:.3g} Pa, ν = {args.poisson:g}"
    )
    morphs = make_morphs(interface, names, args, say)
    setup = time.perf_counter() - start
    records: dict[str, Coupling] = {}
    for name, motion in morphs.items():
        records[name] = couple(
            interface,
            motion,
            name,
            tolerance=args.tolerance,
            max_iterations=args.max_iterations,
            relaxation=args.relaxation,
            say=say,
        )
    _table(records, say)
    main_record = records[names[0]]
    one_deflection, one_twist = main_record.one_way
    deflection, twist = main_record.deflection[-1], main_record.twist[-1]
    inverted, min_ratio = _validity(interface, main_record.fluid_displacement)
    say(
        f"\none-way (undeformed fluid mesh): tip deflection {1e3 * one_deflection:.3f} mm, "
        f"twist {one_twist:.4f}°\ncoupled ({names[0]}): tip deflection {1e3 * deflection:.3f} "
        f"mm, twist {twist:.4f}° — the coupling raises the twist by "
        f"{100 * (twist / one_twist - 1):.1f} %\nfluid mesh after the morph: {inverted} "
        f"inverted tets, smallest volume ratio {min_ratio:.3f}"
    )
    agreement = {
        name: abs(record.twist[-1] - twist) / abs(twist) for name, record in records.items()
    }
    for name, value in agreement.items():
        say(f"  coupled twist with {name}: {records[name].twist[-1]:.5f}° ({value:.1e} apart)")
    if args.out:
        path = Path(args.out) / "fsi.png"
        _plot(interface, records, path)
        say(f"wrote {path}")
    share = {
        name: record.per_iteration()["morph"] / record.per_iteration()["total"]
        for name, record in records.items()
    }
    return {
        "records": records,
        "converged": all(r.converged for r in records.values()),
        "one_way": main_record.one_way,
        "coupled": (deflection, twist),
        "agreement": agreement,
        "inverted": inverted,
        "min_volume_ratio": min_ratio,
        "morph_share": share,
        "setup_seconds": setup,
        "max_gap": float(interface.to_fluid.gaps.max()),
    }


if __name__ == "__main__":
    main()
