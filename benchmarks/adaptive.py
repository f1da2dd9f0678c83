"""Benchmark of the error-driven selection against SIDW/ESIDW on the paper's three cases.

For cases A, B and C at size paper (the meshes of ``data_gen``, cached after the first
build), with the paper's displacement at μ* and the relative nodal error over the whole
mesh against full IDW (every boundary node a control; the measure of the paper's
tables):

1. ESIDW as the reproduction runs it (``CaseSpec.plan``, seed 0): controls, error,
   selection time; then the adaptive selection (:class:`torchmorph.selection.AdaptivePlan`
   with its defaults: the stratified start) with ESIDW's error as its tolerance:
   controls and selection time (the median of 3 runs), also in units of one full IDW
   evaluation (matrix-free, fused kernels, every boundary node to every interior node,
   one displacement: the median of 3).
2. Error at equal control counts: the adaptive selection with ESIDW's count as its
   budget (and a tolerance it cannot reach).
3. Controls needed for 1 % and 0.1 % nodal error: SIDW and ESIDW from a sweep of the
   case's radii (every region's radius times a factor from 4 down to 1/16; the fewest
   controls of the sweep that reach the error), and the adaptive selection with that
   tolerance.

Case C's rotation is not linear in μ: the adaptive rows are driven by μ* alone, as the
errors are measured; a last table drives C by the POD training family (50 angles in D)
and gives the worst error over it.

Everything runs on one thread (torch and numba). Run
``python benchmarks/adaptive.py`` (the first run longer: meshing); ``--cases A C`` for
fewer cases, ``--tolerances 0.01`` to leave out 0.1 %, ``--start empty`` for the selection
from no control (``AdaptivePlan(start=None)``). Measured on 2 shared cores, after the
meshes are cached: the whole run about 2 minutes (case B's equal-count and 0.1 % rows
15 and 20 s of it); with ``--start empty`` about 10 minutes (case B's 0.1 % row 5
minutes, its equal-count run 2, case C's 0.1 % row 2).
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("NUMBA_NUM_THREADS", "1")

import argparse
import time

import torch
from _timing import median_time

from torchmorph.idw import idw_apply
from torchmorph.paper import get_case, load_mesh
from torchmorph.selection import AdaptivePlan, select_adaptive

SWEEP_FACTORS = (4.0, 2.83, 2.0, 1.41, 1.0, 0.71, 0.5, 0.35, 0.25, 0.18, 0.125, 0.088, 0.0625)


class Case:
    """A case's mesh, boundary displacement at μ* and full-IDW reference."""

    def __init__(self, letter: str, start: str | None = "stratified") -> None:
        self.start = start  # AdaptivePlan's start (None: from no control)
        self.spec = get_case(letter)
        self.mesh = load_mesh(self.spec, size="paper")
        mesh = self.mesh
        self.boundary = mesh.boundary_nodes
        self.interior = mesh.interior_nodes
        self.boundary_points = mesh.points[self.boundary]
        self.interior_points = mesh.points[self.interior]
        self.displacement = self.family(torch.tensor(self.spec.mu_star, dtype=mesh.dtype))
        self.reference = self.apply(torch.arange(len(self.boundary)), self.displacement)
        self.full_s = median_time(
            lambda: self.apply(torch.arange(len(self.boundary)), self.displacement), 3
        )

    def family(self, mu: torch.Tensor) -> torch.Tensor:
        """Boundary displacement (N_b, 3) or (B, N_b, 3), rows as ``boundary``."""
        points = self.boundary_points
        moving = torch.zeros(self.mesh.num_nodes, dtype=torch.bool)
        for name in self.spec.moving:
            moving[self.mesh.node_set(name)] = True
        mask = moving[self.boundary]
        values = self.spec.displacement(points[mask], mu)
        out = values.new_zeros(*values.shape[:-2], len(self.boundary), 3)
        out[..., mask, :] = values
        return out

    def apply(self, rows: torch.Tensor, displacement: torch.Tensor) -> torch.Tensor:
        """Interior field of IDW from the boundary rows ``rows``."""
        return idw_apply(
            controls=self.boundary_points[rows],
            targets=self.interior_points,
            displacements=displacement[..., rows, :],
        )

    def error(self, rows: torch.Tensor, displacement=None, reference=None) -> float:
        """Relative nodal error over the whole mesh (worst over a batch)."""
        displacement = self.displacement if displacement is None else displacement
        reference = self.reference if reference is None else reference
        field = self.apply(rows, displacement)
        error = (field - reference).square().sum((-1, -2))
        norm = reference.square().sum((-1, -2)) + displacement.square().sum((-1, -2))
        return float(torch.sqrt(error / norm).max())

    def rows(self, nodes: torch.Tensor) -> torch.Tensor:
        return torch.searchsorted(self.boundary, nodes.to(self.boundary.device))

    def geometric(self, factor: float, *, enrich: bool) -> tuple[int, float, float]:
        """(controls, error, selection seconds) of SIDW / ESIDW at ``factor`` R."""
        plan = self.spec.plan(self.spec.radius * factor, enrich=enrich)
        start = time.perf_counter()
        nodes = plan.select(self.mesh, generator=torch.Generator().manual_seed(0))
        seconds = time.perf_counter() - start
        rows = self.rows(nodes)
        return len(rows), self.error(rows), seconds

    def adaptive(self, tolerance: float, budget: int | None = None, family=None, repeats=1):
        """(controls, error at μ*, selection seconds, plan) of the adaptive selection
        (the median time of ``repeats`` runs); the rows it selected are ``plan.rows_``."""
        family = self.displacement if family is None else family
        plan = AdaptivePlan(tolerance, family, max_controls=budget, start=self.start)
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            nodes = plan.select(self.mesh)
            times.append(time.perf_counter() - start)
        seconds = sorted(times)[len(times) // 2]
        rows = plan.rows_ = self.rows(nodes)
        return len(rows), self.error(rows), seconds, plan


def fewest(points: list[tuple[int, float, float]], tolerance: float) -> str:
    within = [controls for controls, error, _ in points if error <= tolerance]
    return f"{min(within):,}" if within else "not reached"


def warm_up(case: Case) -> None:
    """Load the kernels a selection uses (numba's cache: the weights, scores, picks,
    sums and the curve's keys) before anything is timed."""
    rows = torch.arange(0, len(case.boundary), max(1, len(case.boundary) // 200))
    select_adaptive(
        case.boundary_points[rows],
        case.interior_points[:100],
        case.displacement[rows],
        tolerance=0.01,
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="+", default=["A", "B", "C"])
    parser.add_argument(
        "--tolerances",
        nargs="*",
        type=float,
        default=[0.01, 0.001],
        help="nodal errors of the controls-needed table (default 0.01 0.001)",
    )
    parser.add_argument(
        "--no-family", action="store_true", help="skip case C driven by its training family"
    )
    parser.add_argument(
        "--start",
        choices=["stratified", "empty"],
        default="stratified",
        help="the adaptive selection's start (default: the stratified start)",
    )
    args = parser.parse_args()
    start = "stratified" if args.start == "stratified" else None
    torch.set_num_threads(1)
    try:
        import numba

        numba.set_num_threads(1)
    except ImportError:
        pass

    first, equal, needed = [], [], []
    cases = {}
    for letter in args.cases:
        case = cases[letter] = Case(letter, start)
        warm_up(case)
        n_b, n_i = len(case.boundary), len(case.interior)
        controls, error, esidw_s = case.geometric(1.0, enrich=True)
        a_controls, a_error, a_s, plan = case.adaptive(error, repeats=3)
        first.append(
            f"| {letter} | {n_b:,} / {n_i:,} | {case.full_s * 1e3:,.1f} ms | {controls:,} | "
            f"{100 * error:.2f} % | {esidw_s:.2f} s | {a_controls:,} "
            f"({a_controls / controls:.0%}) | {100 * a_error:.2f} % | {a_s:.2f} s | "
            f"{a_s / case.full_s:,.0f} | {plan.result_.rounds} | {plan.sampled_targets_:,} |"
        )
        print(first[-1], flush=True)
        _, b_error, b_s, _ = case.adaptive(1e-9, budget=controls)
        equal.append(
            f"| {letter} | {controls:,} | {100 * error:.2f} % | {100 * b_error:.3f} % "
            f"({b_error / error:.2f}×) | {b_s:.2f} s |"
        )
        print(equal[-1], flush=True)
        sweeps = {
            enrich: [case.geometric(f, enrich=enrich) for f in SWEEP_FACTORS]
            for enrich in (False, True)
        }
        for tolerance in args.tolerances:
            t_controls, t_error, t_s, _ = case.adaptive(
                tolerance, repeats=1 if letter == "B" else 3
            )
            needed.append(
                f"| {letter} | {100 * tolerance:g} % | {fewest(sweeps[False], tolerance)} | "
                f"{fewest(sweeps[True], tolerance)} | {t_controls:,} ({100 * t_error:.3f} %) | "
                f"{t_s:.2f} s ({t_s / case.full_s:,.0f} full IDW) |"
            )
            print(needed[-1], flush=True)

    print("\n### ESIDW and the adaptive selection at ESIDW's error (μ*)\n")
    print(
        "| case | N_b / N_int | full IDW eval. | ESIDW controls | ESIDW error | ESIDW "
        "selection | adaptive controls | adaptive error | adaptive selection | in full IDW "
        "evals | scorings | sampled targets |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    print("\n".join(first))
    print("\n### Error at equal control counts (ESIDW's)\n")
    print("| case | controls | ESIDW error | adaptive error | adaptive selection |")
    print("|---|---|---|---|---|")
    print("\n".join(equal))
    print("\n### Controls needed for a nodal error (fewest of the radius sweep for SIDW/ESIDW)\n")
    print("| case | error | SIDW | ESIDW | adaptive (error reached) | adaptive selection |")
    print("|---|---|---|---|---|---|")
    print("\n".join(needed))

    if "C" in cases and not args.no_family:
        case = cases["C"]
        parameters = case.spec.training_parameters(0, dtype=case.mesh.dtype)
        family = case.family(parameters)
        reference = case.apply(torch.arange(len(case.boundary)), family)
        nodes = case.spec.plan().select(case.mesh, generator=torch.Generator().manual_seed(0))
        rows = case.rows(nodes)
        controls, worst = len(rows), case.error(rows, family, reference)
        a_controls, _, a_s, plan = case.adaptive(worst, family=family)
        a_worst = case.error(plan.rows_, family, reference)
        print("\n### Case C driven by the POD training family (50 angles in D)\n")
        print("| method | controls | worst error over the family | selection |")
        print("|---|---|---|---|")
        print(f"| ESIDW | {controls:,} | {100 * worst:.2f} % | |")
        print(f"| adaptive | {a_controls:,} | {100 * a_worst:.2f} % | {a_s:.2f} s |")


if __name__ == "__main__":
    main()
