"""Gradient-based shape optimisation through a POD-ESIDW morph (case A, the structural wing).

The NACA0012 wing of the paper's case A (chord 1.01 m, span L = 2π m, clamped at the
root z = 0) is deformed by a three-parameter family on every boundary node, with
s = z / L the span fraction:

    bending   δy = μ1 s² + μ2 s³                              (metres at the tip)
    twist     rotation of each section about its quarter chord by θ(s) = μ3 s
              (μ3 = the tip twist in degrees, trailing edge up for μ3 > 0)

The interior follows by POD-ESIDW (Algorithm 2 with the paper's ESIDW selection,
reduced by Algorithm 3). We look for the parameters that bring

- the tip's vertical deflection (the centre of mass of the outermost segment of the
  wing, every node of it — interior ones too — moved by the morph) to ``--deflection``,
- the tip twist (chord line of the tip profile) to ``--twist`` degrees,

while keeping every tetrahedron valid. The two targets fix μ1 + μ2 and μ3 but leave a
one-parameter family of bendings; most of them (the smallest parameters among them
in particular) invert tets of the ESIDW morph, whose few control points leave the
thin wing's interior loosely held. The validity barrier
(:func:`torchmorph.mesh.quality.validity_barrier`) in the objective picks a valid one:

    J(μ) = ((deflection - target) / 0.05 m)² + ((twist - target) / 1°)²
           + weight · Σ_tets φ(V_deformed / V_reference)

minimised by Adam from μ = 0 with gradients through the reduced morph. The same
optimisation without the barrier is run beside it (it ends with inverted tets), and
the optimum is checked against the full ESIDW morph (no POD). The costs of one
evaluation (the morph alone, and the whole objective, with the gradient to μ) and of
one iteration of the loop are timed for the POD morph, the full ESIDW morph and full
IDW (every boundary node a control point).

(L-BFGS with a strong-Wolfe line search stalls on this objective: the barrier is zero
on valid meshes, so from a valid point the fit's gradient leads straight into the
region of inverted tets, and the line search gives up there. Adam's small steps follow
the edge of the barrier instead.)

    python demos/shape_optimisation.py                       # paper-size mesh
    python demos/shape_optimisation.py --size small --out out/shape
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the demos' shared helpers

from _common import median_seconds, synchronise

from torchmorph._atomic import atomic_output
from torchmorph.mesh import TetMesh
from torchmorph.mesh.quality import count_inverted, signed_volumes, validity_barrier
from torchmorph.morph import MeshMorph
from torchmorph.paper import CASES, load_mesh
from torchmorph.pod import PODReducer

CHORD = 1.01
SPAN = 2.0 * math.pi
TWIST_AXIS = 0.25 * CHORD  # the quarter chord, x; the sections' axes lie on y = 0
#: Parameter box of the POD training set: μ1, μ2 in metres, μ3 in degrees.
TRAINING_BOX = ((-1.0, 5.0), (-4.0, 2.0), (-10.0, 10.0))
DEFLECTION_SCALE = 0.05  # m
TWIST_SCALE = 1.0  # degree


def wing_family(boundary_points: Tensor) -> Callable[[Tensor], Tensor]:
    """Bending and twist of the wing's boundary nodes.

    Returns ``family(mu)``: μ of shape (3,) or (B, 3) -> (N_b, 3) or (B, N_b, 3).
    """
    x, y, z = boundary_points.unbind(-1)
    s = z / SPAN
    arm = x - TWIST_AXIS

    def family(mu: Tensor) -> Tensor:
        bend_2, bend_3, tip_twist = (mu[..., k, None] for k in range(3))
        theta = torch.deg2rad(tip_twist) * s
        cos, sin = torch.cos(theta), torch.sin(theta)
        dx = (cos - 1.0) * arm - sin * y
        dy = sin * arm + (cos - 1.0) * y + bend_2 * s**2 + bend_3 * s**3
        return torch.stack([dx, dy, torch.zeros_like(dx)], -1)

    return family


@dataclass
class TipMeasures:
    """Differentiable measures of the wing tip on a nodal displacement field."""

    centroid_weights: Tensor  # (N,): mass weights of the tip segment's nodes
    leading_edge: int  # node ids of the tip profile's leading and trailing edge
    trailing_edge: int
    reference_chord: Tensor  # (3,)

    @classmethod
    def of(cls, mesh: TetMesh, segment: float) -> TipMeasures:
        points, tets = mesh.points, mesh.tets
        volumes = mesh.volumes
        centres_z = points[tets, 2].mean(1)
        in_tip = centres_z > SPAN - segment
        weights = torch.zeros(mesh.num_nodes, dtype=points.dtype, device=points.device)
        weights.index_add_(
            0, tets[in_tip].reshape(-1), (volumes[in_tip] / 4.0).repeat_interleave(4)
        )
        weights = weights / weights.sum()
        profile = mesh.node_set("tip_profile")
        chordwise = points[profile, 0]
        leading, trailing = int(profile[chordwise.argmin()]), int(profile[chordwise.argmax()])
        return cls(weights, leading, trailing, points[trailing] - points[leading])

    def deflection(self, displacement: Tensor) -> Tensor:
        """Vertical displacement of the tip segment's centre of mass, () or (B,)."""
        return torch.einsum("n,...n->...", self.centroid_weights, displacement[..., 1])

    def twist(self, displacement: Tensor) -> Tensor:
        """Rotation of the tip chord in the x-y plane, degrees, () or (B,)."""
        chord = (
            self.reference_chord
            + displacement[..., self.trailing_edge, :]
            - displacement[..., self.leading_edge, :]
        )
        angle = torch.atan2(chord[..., 1], chord[..., 0])
        reference = torch.atan2(self.reference_chord[1], self.reference_chord[0])
        return torch.rad2deg(angle - reference)


@dataclass
class Problem:
    mesh: TetMesh
    family: Callable[[Tensor], Tensor]
    tip: TipMeasures
    deflection_target: float
    twist_target: float
    threshold: float
    barrier_weight: float

    def terms(self, displacement: Tensor) -> dict[str, Tensor]:
        deflection = self.tip.deflection(displacement)
        twist = self.tip.twist(displacement)
        barrier = validity_barrier(self.mesh, displacement, threshold=self.threshold)
        fit = ((deflection - self.deflection_target) / DEFLECTION_SCALE).square() + (
            (twist - self.twist_target) / TWIST_SCALE
        ).square()
        return {"fit": fit, "barrier": barrier, "deflection": deflection, "twist": twist}

    def objective(
        self, morph: Callable[[Tensor], Tensor], mu: Tensor, barrier_weight: float | None = None
    ) -> tuple[Tensor, dict[str, Tensor]]:
        weight = self.barrier_weight if barrier_weight is None else barrier_weight
        terms = self.terms(morph(self.family(mu)))
        return terms["fit"] + weight * terms["barrier"], terms


@dataclass
class History:
    objective: list[float] = field(default_factory=list)
    fit: list[float] = field(default_factory=list)
    barrier: list[float] = field(default_factory=list)
    deflection: list[float] = field(default_factory=list)
    twist: list[float] = field(default_factory=list)
    min_volume_ratio: list[float] = field(default_factory=list)
    inverted: list[int] = field(default_factory=list)
    mu: list[list[float]] = field(default_factory=list)
    evaluations: int = 0
    seconds: float = 0.0


def min_volume_ratio(mesh: TetMesh, displacement: Tensor) -> float:
    with torch.no_grad():
        volumes = signed_volumes(mesh.points + displacement, mesh.tets)
        return float((volumes / mesh.volumes).min())


def optimise(
    problem: Problem,
    morph: Callable[[Tensor], Tensor],
    *,
    iterations: int,
    learning_rate: float,
    barrier_weight: float | None = None,
    tolerance: float = 1e-7,
    print_every: int = 0,
    label: str = "",
) -> tuple[Tensor, History]:
    """Minimise the objective from μ = 0 with Adam (one evaluation per iteration).

    Stops after ``iterations`` steps or when the objective falls below ``tolerance``
    times its initial value. The history holds the objective, the tip measures and the
    mesh validity at every iterate (before its step), the last one included.
    """
    mesh = problem.mesh
    weight = problem.barrier_weight if barrier_weight is None else barrier_weight
    mu = torch.zeros(3, dtype=mesh.dtype, device=mesh.points.device, requires_grad=True)
    adam = torch.optim.Adam([mu], lr=learning_rate)
    history = History()

    def show(iteration: int) -> None:
        m = history.mu[-1]
        print(
            f"{label}{iteration:5d}  J = {history.objective[-1]:11.4e}  fit = "
            f"{history.fit[-1]:10.3e}  barrier = {history.barrier[-1]:9.3e}  deflection = "
            f"{history.deflection[-1]:7.4f} m  twist = {history.twist[-1]:7.3f}°  "
            f"min V/V0 = {history.min_volume_ratio[-1]:6.3f}  inverted = "
            f"{history.inverted[-1]:3d}  μ = ({m[0]:.4f}, {m[1]:.4f}, {m[2]:.4f})"
        )

    start = time.perf_counter()
    for iteration in range(iterations + 1):
        displacement = morph(problem.family(mu))
        terms = problem.terms(displacement)
        value = terms["fit"] + weight * terms["barrier"]
        history.objective.append(float(value.detach()))
        for name in ("fit", "barrier", "deflection", "twist"):
            getattr(history, name).append(float(terms[name].detach()))
        history.min_volume_ratio.append(min_volume_ratio(mesh, displacement.detach()))
        history.inverted.append(count_inverted(mesh, displacement.detach()))
        history.mu.append(mu.detach().cpu().tolist())
        last = iteration == iterations or history.objective[-1] <= tolerance * history.objective[0]
        if print_every and (iteration < 10 or iteration % print_every == 0 or last):
            show(iteration)
        if last:
            break
        adam.zero_grad()
        value.backward()
        adam.step()
        history.evaluations += 1
    history.seconds = time.perf_counter() - start
    return mu.detach(), history


def plot(histories: dict[str, History], problem: Problem, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    styles = ("-", "--", ":")
    for (name, history), colour in zip(histories.items(), ("C0", "C3"), strict=False):
        steps = range(len(history.objective))
        axes[0].semilogy(
            steps, [max(v, 1e-300) for v in history.objective], color=colour, label=name
        )
        for values, style in zip(zip(*history.mu, strict=True), styles, strict=True):
            axes[1].plot(steps, values, style, color=colour)
        axes[1].plot([], [], color=colour, label=name)
        axes[2].plot(steps, history.min_volume_ratio, color=colour, label=name)
    for k, style in enumerate(styles):
        unit = "°" if k == 2 else "m"
        axes[1].plot([], [], style, color="k", label=f"μ{k + 1} ({unit})")
    axes[0].set(xlabel="iteration", ylabel="objective J", title="objective")
    axes[1].set(xlabel="iteration", ylabel="parameter", title="bending μ1 s² + μ2 s³, tip twist μ3")
    axes[2].axhline(0.0, color="k", lw=0.8)
    axes[2].axhline(
        problem.threshold,
        color="grey",
        lw=0.8,
        ls="--",
        label=f"barrier threshold {problem.threshold:g}",
    )
    axes[2].set(xlabel="iteration", ylabel="min V / V0", title="smallest volume ratio")
    for axis in axes:
        axis.grid(alpha=0.3)
        axis.legend(fontsize=8)
    figure.suptitle(
        f"Case A wing: tip deflection {problem.deflection_target:g} m and twist "
        f"{problem.twist_target:g}° through POD-ESIDW"
    )
    figure.tight_layout()
    with atomic_output(path) as temporary:
        figure.savefig(temporary, dpi=120)
    plt.close(figure)


def parse(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--size",
        choices=("small", "paper"),
        default="paper",
        help="mesh size (default: %(default)s; case A is small either way)",
    )
    parser.add_argument(
        "--out",
        default="out/shape_optimisation",
        help="directory for the PNG of the history (default: %(default)s); '' writes nothing",
    )
    parser.add_argument("--device", default="cpu", help="cpu, cuda, cuda:1, ... (default cpu)")
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float64")
    parser.add_argument(
        "--iterations", type=int, default=1500, help="most Adam iterations (default %(default)s)"
    )
    parser.add_argument(
        "--lr", type=float, default=0.05, help="Adam's learning rate (default %(default)s)"
    )
    parser.add_argument(
        "--tolerance",
        type=float,
        default=1e-7,
        help="stop when the objective is below this fraction of its initial "
        "value (default %(default)s)",
    )
    parser.add_argument(
        "--deflection",
        type=float,
        default=1.0,
        help="target tip deflection in m (default %(default)s)",
    )
    parser.add_argument(
        "--twist", type=float, default=5.0, help="target tip twist in degrees (default %(default)s)"
    )
    parser.add_argument(
        "--threshold",
        type=float,
        default=0.2,
        help="volume ratio under which the barrier starts (default %(default)s)",
    )
    parser.add_argument(
        "--barrier-weight",
        type=float,
        default=10.0,
        help="weight of the validity barrier (default %(default)s)",
    )
    parser.add_argument(
        "--segment",
        type=float,
        default=0.2,
        help="length of the tip segment whose centre of mass is the tip "
        "position, m (default %(default)s)",
    )
    parser.add_argument(
        "--train",
        type=int,
        default=100,
        help="POD training values (default: the paper's 100 for case A)",
    )
    parser.add_argument(
        "--energy-tolerance",
        type=float,
        default=1e-8,
        help="POD energy tolerance ε (default %(default)s)",
    )
    parser.add_argument(
        "--seed", type=int, default=0, help="seed of the ESIDW selection and the training set"
    )
    parser.add_argument(
        "--repeats",
        type=int,
        default=20,
        help="timed repeats of each evaluation cost (median; default %(default)s)",
    )
    parser.add_argument(
        "--print-every",
        type=int,
        default=10,
        help="print every n-th iteration (and the first ten and the last; default %(default)s)",
    )
    parser.add_argument(
        "--no-compare",
        action="store_true",
        help="skip the run without barrier and the full-morph timings",
    )
    parser.add_argument(
        "--threads",
        type=int,
        default=1,
        help="torch intra-op threads (default 1: the problem is small, and "
        "more threads only wait for each other on a busy machine)",
    )
    parser.add_argument("--quiet", action="store_true", help="print nothing")
    return parser.parse_args(argv)


def timed_costs(
    problem: Problem,
    morphs: dict[str, Callable[[Tensor], Tensor]],
    mu: Tensor,
    repeats: int,
    device: torch.device,
) -> dict[str, dict[str, float]]:
    """Median seconds of (a) the morph alone, forward and backward, and (b) the whole
    objective and its gradient, at ``mu``, for each morph."""
    costs = {}
    for name, morph in morphs.items():
        probe = mu.clone().requires_grad_(True)
        weights = torch.ones(problem.mesh.num_nodes, 3, dtype=mu.dtype, device=mu.device)

        def morph_only(morph=morph, probe=probe, weights=weights):
            value = (morph(problem.family(probe)) * weights).sum()
            gradient = torch.autograd.grad(value, probe)
            synchronise(device)
            return gradient

        def objective(morph=morph, probe=probe):
            value, _ = problem.objective(morph, probe)
            gradient = torch.autograd.grad(value, probe)
            synchronise(device)
            return gradient

        costs[name] = {
            "morph": median_seconds(morph_only, repeats),
            "objective": median_seconds(objective, repeats),
        }
    return costs


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Run the demo; returns its numbers (histories, optimum, checks, timings)."""
    args = parse(argv)
    start = time.perf_counter()
    threads = torch.get_num_threads()
    torch.set_num_threads(args.threads)
    try:
        return _run(args, start)
    finally:
        torch.set_num_threads(threads)


def _run(args: argparse.Namespace, start: float) -> dict[str, Any]:
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device cuda asked for, but torch sees no CUDA device")
    dtype = getattr(torch, args.dtype)
    verbose = not args.quiet
    say = print if verbose else (lambda *a, **k: None)

    # ------------------------------------------------------------------ offline
    spec = CASES["wing"]
    reference = load_mesh("wing", size=args.size)
    generator = torch.Generator().manual_seed(args.seed)
    esidw = MeshMorph(reference, spec.plan(), generator=generator)  # selection on the CPU
    mesh = reference.to(device=device, dtype=dtype)
    esidw = esidw.to(device=device, dtype=dtype)
    family = wing_family(esidw.boundary_points)
    low = torch.tensor([bounds[0] for bounds in TRAINING_BOX], dtype=dtype)
    high = torch.tensor([bounds[1] for bounds in TRAINING_BOX], dtype=dtype)
    training = low + (high - low) * torch.rand(args.train, 3, generator=generator, dtype=dtype)
    reducer = PODReducer(energy_tolerance=args.energy_tolerance)
    reducer.fit(esidw, family=family, parameters=training.to(device))
    setup = time.perf_counter() - start
    say(
        f"case A wing ({args.size}): {mesh.num_nodes} nodes, {mesh.num_tets} tets, "
        f"{esidw.num_boundary} boundary nodes; ESIDW {esidw.num_controls} control points; "
        f"POD {reducer.num_modes_} modes from {args.train} training values "
        f"(ε = {args.energy_tolerance:g}); set-up {setup:.2f} s on {device}"
    )

    tip = TipMeasures.of(mesh, args.segment)
    problem = Problem(
        mesh, family, tip, args.deflection, args.twist, args.threshold, args.barrier_weight
    )

    # ------------------------------------------------------------------ optimise
    say(
        f"\ntargets: tip deflection {args.deflection:g} m, tip twist {args.twist:g}°; Adam "
        f"(lr {args.lr:g}) from μ = 0, barrier threshold {args.threshold:g}, weight "
        f"{args.barrier_weight:g}"
    )
    print_every = 0 if args.quiet else max(1, args.print_every)
    mu, history = optimise(
        problem,
        reducer,
        iterations=args.iterations,
        learning_rate=args.lr,
        tolerance=args.tolerance,
        print_every=print_every,
    )
    histories = {"with barrier": history}
    with torch.no_grad():
        reduced = reducer(family(mu))
        full = esidw(family(mu))
        final = {key: float(value) for key, value in problem.terms(reduced).items()}
        checked = {key: float(value) for key, value in problem.terms(full).items()}
        pod_error = float((reduced - full).norm() / full.norm())
    result: dict[str, Any] = {
        "mu": mu.cpu().tolist(),
        "history": history,
        "objective_initial": history.objective[0],
        "objective_final": history.objective[-1],
        "iterations": len(history.objective) - 1,
        "optimisation_s": history.seconds,
        "deflection": final["deflection"],
        "twist": final["twist"],
        "barrier": final["barrier"],
        "inverted": count_inverted(mesh, reduced),
        "min_volume_ratio": min_volume_ratio(mesh, reduced),
        "full_deflection": checked["deflection"],
        "full_twist": checked["twist"],
        "full_inverted": count_inverted(mesh, full),
        "full_min_volume_ratio": min_volume_ratio(mesh, full),
        "pod_error": pod_error,
        "num_modes": reducer.num_modes_,
        "num_controls": esidw.num_controls,
        "setup_s": setup,
    }
    decrease = result["objective_initial"] / max(result["objective_final"], 1e-300)
    say(
        f"\noptimum μ = ({mu[0]:.4f} m, {mu[1]:.4f} m, {mu[2]:.4f}°) after "
        f"{result['iterations']} iterations in {history.seconds:.2f} s; objective "
        f"{result['objective_initial']:.3e} -> {result['objective_final']:.3e} "
        f"({decrease:.1e}x smaller)"
    )
    say(
        f"POD-ESIDW at the optimum: deflection {final['deflection']:.5f} m (target "
        f"{args.deflection:g}), twist {final['twist']:.4f}° (target {args.twist:g}), "
        f"inverted tets {result['inverted']}, min V/V0 {result['min_volume_ratio']:.3f}"
    )
    say(
        f"full ESIDW at the optimum: deflection {checked['deflection']:.5f} m, twist "
        f"{checked['twist']:.4f}°, inverted tets {result['full_inverted']}, min V/V0 "
        f"{result['full_min_volume_ratio']:.3f}; POD vs ESIDW relative error "
        f"{pod_error:.1e}"
    )

    # ------------------------------------------------------------------ comparisons
    if not args.no_compare:
        free_mu, free = optimise(
            problem,
            reducer,
            iterations=args.iterations,
            learning_rate=args.lr,
            tolerance=args.tolerance,
            barrier_weight=0.0,
        )
        histories["without barrier"] = free
        with torch.no_grad():
            free_field = reducer(family(free_mu))
        result["unconstrained_mu"] = free_mu.cpu().tolist()
        result["unconstrained_inverted"] = count_inverted(mesh, free_field)
        result["unconstrained_history"] = free
        say(
            f"\nthe same optimisation without the barrier: μ = ({free_mu[0]:.4f} m, "
            f"{free_mu[1]:.4f} m, {free_mu[2]:.4f}°) after {len(free.objective) - 1} "
            f"iterations, fit {free.fit[-1]:.1e}, {result['unconstrained_inverted']} "
            f"inverted tets (min V/V0 {free.min_volume_ratio[-1]:.3f})"
        )

        idw = MeshMorph(reference).to(device=device, dtype=dtype)
        morphs = {
            "POD-ESIDW": reducer,
            "ESIDW (full W)": esidw,
            f"IDW ({idw.num_controls} controls)": idw,
        }
        costs = timed_costs(problem, morphs, mu, args.repeats, device)
        # the same loop, a fixed number of iterations, with each morph
        loop_iterations = min(100, args.iterations)
        per_iteration = {}
        for name, morph in morphs.items():
            _, timed = optimise(
                problem, morph, iterations=loop_iterations, learning_rate=args.lr, tolerance=0.0
            )
            per_iteration[name] = timed.seconds / loop_iterations
        result["costs_s"] = costs
        result["iteration_s"] = per_iteration
        base = costs["POD-ESIDW"]
        say(
            f"\ncost per evaluation, median of {args.repeats} (forward + gradient to μ), "
            f"and per iteration of the loop above ({loop_iterations} iterations; the "
            f"objective, its gradient, Adam and the validity count), on {device}:"
        )
        say(f"  {'morph':28s} {'morph alone':>12s} {'objective':>12s} {'iteration':>12s}")
        for name in morphs:
            say(
                f"  {name:28s} {costs[name]['morph'] * 1e3:9.3f} ms "
                f"{costs[name]['objective'] * 1e3:9.3f} ms "
                f"{per_iteration[name] * 1e3:9.3f} ms   "
                f"(morph {costs[name]['morph'] / base['morph']:.1f}x POD)"
            )

    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        path = out / "shape_optimisation.png"
        plot(histories, problem, path)
        result["figure"] = path
        say(f"\nwrote {path}")
    result["total_s"] = time.perf_counter() - start
    say(f"total run time {result['total_s']:.1f} s")
    return result


if __name__ == "__main__":
    main()
