"""RBF morphing (:class:`torchmorph.rbf.RBF`) against scipy's ``RBFInterpolator``.

One thread (torch and BLAS), float64; thin-plate spline with the linear polynomial
(``degree=1``, scipy's default for it). Controls: N_c points on the unit sphere (a
Fibonacci lattice, the surface of a body); targets: N_t points uniform in the shell
1.05 <= |x| <= 3 around it (the volume mesh); displacements a smooth field on the sphere.
Default N_c = 5,000 and N_t = 50,000 (the issue's counts).

Printed (markdown), wall times: the fits and first morphs timed once per round, in
``--rounds`` rounds (scipy, then ours matrix-free, then dense; medians over the rounds),
each configuration after a 256 MB buffer is written and freed (:func:`settle`); the later
morphs the median of ``--repeats``:

* scipy: ``RBFInterpolator(controls, d)`` (fit) and one evaluation at the targets;
* torchmorph, dense and matrix-free: building the module (the factorisation; in dense
  mode also the evaluation matrix ``[Φ_tc P_t]``), the first morph, fit plus first
  morph, later morphs (the factorisation reused: one solve and one product in dense
  mode, a solve and the kernel sum in blocks matrix-free), and the ratios of scipy's
  fit plus evaluation to ours;
* the largest difference of the morphed targets from scipy's;
* greedy reduction of the controls (:class:`~torchmorph.rbf.RBFErrorOracle` in
  :func:`~torchmorph.selection.greedy.greedy_selection`) to ``--tolerances``: the
  controls kept, the loop's time, and the error of an RBF refitted on them;
* greedy reduction on the paper's case A at size paper (``--case-a``, the default; the
  wing's boundary nodes with the displacement at μ*): controls kept, their share of the
  boundary nodes, the selection time, and the relative nodal error over the mesh of the
  reduced RBF morph against the RBF from every boundary node.

Below the table, the ratio of fit plus first morph in the process's CPU time: on a
shared machine, wall times of one-threaded code swing with the other load, CPU times
much less.

numba's kernels (the thin-plate spline's fused pass) are loaded from its cache by a tiny
morph before the timings: a one-time cost per process (about 0.3 s), as scipy's are
compiled ahead of time.

Run ``python benchmarks/rbf.py [--controls N] [--targets N] [--repeats R]`` (about 30 s
at the default counts on one core).
"""

from __future__ import annotations

import os

for _variable in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_variable] = "1"  # before numpy and scipy load their BLAS

import argparse  # noqa: E402
import math  # noqa: E402
import platform  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import scipy  # noqa: E402
import torch  # noqa: E402
from _timing import median_time, seconds  # noqa: E402
from scipy.interpolate import RBFInterpolator  # noqa: E402

from torchmorph.rbf import RBF, RBFErrorOracle  # noqa: E402
from torchmorph.selection.greedy import greedy_selection  # noqa: E402

MODES = ("matrix_free", "dense")


def sphere(count: int) -> np.ndarray:
    """A Fibonacci lattice of ``count`` points on the unit sphere."""
    index = np.arange(count) + 0.5
    polar = np.arccos(1 - 2 * index / count)
    azimuth = math.pi * (1 + 5**0.5) * index
    return np.stack(
        [np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)], 1
    )


def shell(count: int, seed: int = 0) -> np.ndarray:
    """``count`` points uniform in the shell 1.05 <= |x| <= 3."""
    rng = np.random.default_rng(seed)
    direction = rng.normal(size=(count, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    radius = (rng.uniform(1.05**3, 3.0**3, size=(count, 1))) ** (1 / 3)
    return direction * radius


def field(points: np.ndarray) -> np.ndarray:
    """A smooth displacement of the sphere: a bulge, a shear and a twist."""
    x, y, z = points.T
    return 0.05 * np.stack([np.sin(3 * x) + z * y, np.cos(2 * y) * x, z**2 - 0.3 * x], 1)


CPU_TIMES: dict[str, float] = {}


def settle() -> None:
    """Write and free 256 MB. After a large release (the dense module's 2 GB evaluation
    matrix, scipy's evaluation blocks) the next fresh allocation's page faults were slower
    for a while (a 200 MB system matrix: 0.5 s instead of 0.1 s); this takes that cost
    outside the timings, for every configuration alike."""
    np.ones(2**25).sum()


def timed(function, label: str = ""):
    """(result, wall seconds); the process's CPU seconds kept under ``label``."""
    start, cpu = time.perf_counter(), time.process_time()
    result = function()
    if label:
        CPU_TIMES[label] = time.process_time() - cpu
    return result, time.perf_counter() - start


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--controls", type=int, default=5000)
    parser.add_argument("--targets", type=int, default=50000)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument(
        "--rounds", type=int, default=3, help="rounds of the fits (medians reported)"
    )
    parser.add_argument("--tolerances", type=float, nargs="*", default=[1e-2, 1e-3, 1e-4])
    parser.add_argument(
        "--no-case-a", dest="case_a", action="store_false", help="skip the case-A table"
    )
    parser.add_argument(
        "--pygem",
        metavar="PATH",
        help="folder holding mathLab's pygem package (a checkout of github.com/mathLab/PyGeM; "
        "not on PyPI): time its RBF on the same clouds (one call, tens of seconds)",
    )
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    controls, targets = sphere(args.controls), shell(args.targets)
    values = field(controls)
    print(
        f"{platform.processor() or platform.machine()}, torch {torch.__version__}, "
        f"scipy {scipy.__version__}, 1 thread, float64, thin_plate_spline, degree=1, "
        f"{args.controls:,} controls x {args.targets:,} targets\n"
    )
    # numba's compiled kernels loaded once per process, outside the timings (scipy's are
    # compiled ahead of time)
    RBF(torch.from_numpy(controls[:20]), torch.from_numpy(targets[:5]))(
        torch.zeros(20, 3, dtype=torch.float64)
    )
    tensors = [torch.from_numpy(array) for array in (controls, targets, values)]
    # rounds of scipy, then each of our modes (the fits take seconds: each is timed once
    # per round, the medians over the rounds reported); every configuration starts after
    # settle(), so that none pays for the memory the one before it released
    runs: dict[str, list] = {name: [] for name in ("scipy", *MODES)}
    for _ in range(args.rounds):
        settle()
        interpolant, scipy_fit = timed(lambda: RBFInterpolator(controls, values), "scipy fit")
        reference, scipy_eval = timed(
            lambda interpolant=interpolant: interpolant(targets), "scipy eval"
        )
        runs["scipy"].append(
            (scipy_fit, scipy_eval, CPU_TIMES["scipy fit"] + CPU_TIMES["scipy eval"])
        )
        del interpolant
        for mode in MODES:
            settle()
            morph, build = timed(
                lambda mode=mode: RBF(tensors[0], tensors[1], mode=mode), f"{mode} fit"
            )
            moved, first = timed(lambda morph=morph: morph(tensors[2]), f"{mode} first")
            cpu = CPU_TIMES[f"{mode} fit"] + CPU_TIMES[f"{mode} first"]
            runs[mode].append((build, first, cpu, morph.fit_time, morph.solver, moved))
            del morph
    scipy_fit, scipy_eval, scipy_cpu = (
        statistics.median(run[k] for run in runs["scipy"]) for k in range(3)
    )
    scipy_total = statistics.median(run[0] + run[1] for run in runs["scipy"])
    rows = []
    for mode in MODES:
        settle()
        morph = RBF(tensors[0], tensors[1], mode=mode)
        later = median_time(lambda morph=morph: morph(tensors[2]), args.repeats)
        build, first, cpu, factorising = (
            statistics.median(run[k] for run in runs[mode]) for k in range(4)
        )
        total = statistics.median(run[0] + run[1] for run in runs[mode])
        difference = float(np.abs(runs[mode][-1][5].numpy() - reference).max())
        rows.append(
            (mode, runs[mode][-1][4], build, first, total, cpu, factorising, later, difference)
        )
        del morph
    print(
        f"Medians over {args.rounds} rounds (scipy, then each of ours, fit and first "
        "morph timed once per round):\n"
    )
    print("| | fit | first morph | fit + first morph | later morph | max diff. from scipy |")
    print("|---|---:|---:|---:|---:|---:|")
    print(
        f"| scipy `RBFInterpolator` | {seconds(scipy_fit)} | {seconds(scipy_eval)} | "
        f"{seconds(scipy_total)} | {seconds(scipy_eval)} | — |"
    )
    for mode, solver, build, first, total, _, factorising, later, difference in rows:
        fit = f"{seconds(build)} ({seconds(factorising)} factorising)"
        print(
            f"| torchmorph `RBF`, {mode} ({solver}) | {fit} | {seconds(first)} | "
            f"{seconds(total)} (**{scipy_total / total:.2f}x**) | "
            f"{seconds(later)} (**{scipy_eval / later:.1f}x**) | {difference:.1e} |"
        )
    print(
        "\nRatios: scipy's fit + evaluation over ours (fit + first morph), scipy's "
        "evaluation over one later morph."
    )
    for mode, *_, cpu, _, _, _ in rows:
        print(
            f"CPU time (the process's, insensitive to other load on the machine), {mode}: "
            f"scipy {scipy_cpu:.2f} s, ours {cpu:.2f} s for fit + first morph "
            f"(**{scipy_cpu / cpu:.2f}x**)"
        )
    if args.pygem:
        pygem_table(args.pygem, controls, targets, values, reference, rows)
    greedy_table(tensors[0], tensors[2], args.tolerances)
    if args.case_a:
        case_a_table((1e-2, 5e-3, 1e-3))


def greedy_rbf(points: torch.Tensor, values: torch.Tensor, tolerance: float):
    """(the greedy selection's result, its seconds): the selection loop with the RBF
    oracle over ``points`` (thin-plate spline, degree 1), from the polynomial's anchors."""
    start = time.perf_counter()
    oracle = RBFErrorOracle(points, values)
    result = greedy_selection(oracle, tolerance=tolerance, initial=oracle.anchors)
    return result, time.perf_counter() - start


def greedy_table(points: torch.Tensor, values: torch.Tensor, tolerances) -> None:
    """Greedy reduction of the controls: the selection loop with the RBF oracle, and the
    error of a thin-plate RBF refitted on the selected controls (at every candidate)."""
    print(
        f"\nGreedy reduction of the {points.shape[0]:,} controls (thin_plate_spline, "
        "degree=1; relative error max |s - d| / max |d| over the candidates):\n"
    )
    print("| tolerance | controls | loop time | scorings | error (oracle) | error (refit) |")
    print("|---:|---:|---:|---:|---:|---:|")
    for tolerance in tolerances:
        result, elapsed = greedy_rbf(points, values, tolerance)
        chosen = result.indices
        refit = RBF(points[chosen], points)(values[chosen])
        error = float((refit - values).norm(dim=-1).max() / values.norm(dim=-1).max())
        print(
            f"| {tolerance:g} | {chosen.numel():,} | {seconds(elapsed)} | {result.rounds} | "
            f"{result.error:.2e} | {error:.2e} |"
        )


def pygem_table(path, controls, targets, values, reference, rows) -> None:
    """mathLab's PyGeM RBF (thin-plate spline, radius 1, its linear polynomial) on the same
    clouds: one call (PyGeM solves the system again on every call), against ours."""
    import importlib
    import sys

    sys.path.insert(0, path)
    try:
        pygem = importlib.import_module("pygem")
        if not hasattr(pygem, "RBF"):
            raise ImportError(f"{pygem.__file__} is not mathLab's PyGeM")
    except ImportError as error:
        print(f"\nPyGeM: not available ({error})")
        return
    start = time.perf_counter()
    model = pygem.RBF(controls, controls + values, func="thin_plate_spline", radius=1.0)
    moved = model(targets) - targets
    call = time.perf_counter() - start
    difference = float(np.abs(moved - reference).max())
    print(
        f"\nPyGeM's RBF, one call (it fits on every call): {seconds(call)}, max diff. from "
        f"scipy {difference:.1e}\n"
    )
    print("| ours | fit + first morph | PyGeM / ours | later morph | PyGeM / ours |")
    print("|---|---:|---:|---:|---:|")
    for mode, _, _, _, total, _, _, later, _ in rows:
        print(
            f"| {mode} | {seconds(total)} | **{call / total:.1f}x** | "
            f"{seconds(later)} | **{call / later:.0f}x** |"
        )


def case_a_table(tolerances) -> None:
    """Greedy RBF on case A at size paper: the wing's boundary nodes, the displacement at
    μ*, the nodal error of the reduced morph against the RBF from every boundary node."""
    from torchmorph.paper import get_case, load_mesh

    spec = get_case("A")
    mesh = load_mesh(spec, size="paper")
    boundary, interior = mesh.boundary_nodes, mesh.interior_nodes
    controls, targets = mesh.points[boundary], mesh.points[interior]
    moving = torch.zeros(mesh.num_nodes, dtype=torch.bool)
    for name in spec.moving:
        moving[mesh.node_set(name)] = True
    mask = moving[boundary]
    displacement = torch.zeros_like(controls)
    mu = torch.tensor(spec.mu_star, dtype=controls.dtype)
    displacement[mask] = spec.displacement(controls[mask], mu)
    full = RBF(controls, targets)(displacement)
    norm = full.square().sum() + displacement.square().sum()
    print(
        f"\nGreedy RBF on case A at size paper (thin_plate_spline, degree=1; μ* = "
        f"{spec.mu_star}): {len(boundary):,} boundary nodes, {len(interior):,} interior "
        "nodes; nodal error = relative 2-norm over the mesh against the RBF from every "
        "boundary node:\n"
    )
    print("| tolerance | controls | share of boundary nodes | selection | nodal error |")
    print("|---:|---:|---:|---:|---:|")
    for tolerance in tolerances:
        result, elapsed = greedy_rbf(controls, displacement, tolerance)
        chosen = result.indices
        reduced = RBF(controls[chosen], targets)(displacement[chosen])
        error = float(torch.sqrt((reduced - full).square().sum() / norm))
        print(
            f"| {tolerance:g} | {chosen.numel():,} | {chosen.numel() / len(boundary):.1%} | "
            f"{seconds(elapsed)} | {error:.3%} |"
        )


if __name__ == "__main__":
    main()
