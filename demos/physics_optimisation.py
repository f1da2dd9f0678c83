"""The stiffest wing of fixed volume: a physics-driven shape optimisation through POD-ESIDW.

The NACA0012 wing of the paper's case A (chord 1.01 m, span L = 2π m) is clamped at
the root z = 0 and loaded at the tip (a force F along +y spread over the tip face by
area) or by a uniform lift (F spread over the upper surface by its planform area).
The design μ (K numbers) scales the profile's thickness along the span,

    t(s) = 1 + Σ_k μ_k b_k(s),   s = z / L,   b_k = C(K, k) s^k (1 - s)^(K-k), k = 1..K,

(Bernstein polynomials without b_0, so t(0) = 1 and μ -> t is one to one) and every
boundary node moves along y, y -> c(μ) t(s) y, with c(μ) chosen so that the volume
enclosed by the boundary, which is linear in the boundary's y coordinates
(V = ∮ y n_y dS), equals the reference volume exactly: the volume is held by an exact
normalisation, not a penalty. The interior follows by the morph: ESIDW (Algorithm 2
with the paper's case-A selection) reduced by POD (Algorithm 3) in the loop, full IDW
(every boundary node a control) to check. Every boundary field of the family is a
combination of the K + 1 fields y b_j(s), j = 0..K, that leaves the volume unchanged
(one linear condition), so the POD of ESIDW keeps K modes and equals full ESIDW to
round-off (with the default ε).

On the morphed mesh a linear-elasticity solve (demos/_elasticity.py: element matrices
V BᵀCB in torch from the morphed coordinates, a sparse LU in scipy with the adjoint in
the backward pass) gives the displacement u, and we minimise

    J(μ) = C(μ) / C(0) + weight · Σ_tets φ(V_deformed / V_reference),   C = fᵀu,

the compliance (the work of the load) over its initial value plus the validity
barrier (:func:`torchmorph.mesh.quality.validity_barrier`), by Adam with dJ/dμ from
autograd through the solver, the morph and the parametrisation. The demo

- checks dJ/dμ against central finite differences (fourth order, float64) at the
  start, and the compliance's gradient at the optimum (where the barrier's balances
  it; the barrier is only C¹, see :func:`gradient_error`), and compares dJ/dμ with the
  gradient through full ESIDW and through full IDW in place of the reduced morph,
- checks the torch stiffness matrix against scikit-fem's assembly
  (``ElementVector(ElementTetP1())``, ``linear_elasticity``) on the optimised mesh,
- verifies the optimum on the full IDW morph (objective below the start, no inverted
  tetrahedron, volume kept), and
- times the morph, the objective with its gradient and one iteration (objective,
  gradient and Adam step) with POD-ESIDW, full ESIDW and full IDW, taking turns.

Beam theory (a slender beam of thickness t, second moment ∝ t³, the same volume) puts
the material where the bending moment M is large, t ∝ M^(1/2): t ∝ (1 - s)^(1/2) under
the tip load, t ∝ 1 - s under the lift. The thinning tip is where the barrier ends
the run: the morph does not carry the boundary's y scaling linearly into the interior,
so tetrahedra near the surface shrink by more than the thickness does.
P1 tetrahedra (the default, fast) lock in bending with a few elements across the
thickness: C(0) under the 1 kN tip load is 4.7 J on the small mesh and 5.5 J on the
paper's, against F²L³/(3EI) = 16.7 J of Euler-Bernoulli beam theory (I = 7.09e-5 m⁴ of
the NACA0012 section). ``--element p2`` solves with straight-sided P2 tetrahedra (a
node on every edge, at its midpoint): 17.1 J and 16.9 J, the beam's value plus a little
shear, at some 30 times the cost of an iteration. On the small mesh the optimisation
ends alike with both: C/C(0) = 0.716 after 100 iterations with P1, 0.726 after 40 with
P2, both with the barrier holding the thinning tip.

Needs the ``fsi`` extra (scikit-fem, scipy)::

    python demos/physics_optimisation.py                        # paper-size mesh
    python demos/physics_optimisation.py --size small --out out/physics
    python demos/physics_optimisation.py --size small --element p2 --iterations 40
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import torch
from torch import Tensor, nn

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the demos' shared helpers

from _elasticity import (
    LagrangeSpace,
    SparseSolve,
    StiffnessPattern,
    element_stiffness,
    lame_parameters,
    require_solver,
)

from torchmorph._atomic import atomic_output
from torchmorph.mesh import TetMesh
from torchmorph.mesh.quality import (
    count_inverted,
    quality_summary,
    signed_volumes,
    validity_barrier,
)
from torchmorph.morph import MeshMorph
from torchmorph.paper import CASES, load_mesh
from torchmorph.pod import PODReducer

SPAN = 2.0 * math.pi
YOUNG = 70e9  # Pa, aluminium
POISSON = 0.33
#: Box of the POD training values of every μ_k.
TRAINING_BOX = (-0.8, 1.5)


# --------------------------------------------------------------------- design


def enclosed_volume_weights(mesh: TetMesh, nodes: Tensor) -> Tensor:
    """Weights w with ``Σ_i w_i y_i`` = the volume enclosed by the boundary, for nodes
    moved along y only.

    By the divergence theorem with the field (0, y, 0), ``V = ∮ y n_y dS``; on a flat
    triangle y is linear, so the integral is the mean of its corners' y times the
    triangle's area projected on the x-z plane (signed), which y does not change.

    Parameters
    ----------
    mesh : TetMesh
    nodes : Tensor, shape (N_b,)
        The boundary nodes, in the order of the returned weights.

    Returns
    -------
    Tensor, shape (N_b,)
    """
    faces = mesh.boundary_faces  # outward normals
    corners = mesh.points[faces]
    projected = torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    shares = (projected[:, 1] / 6.0).repeat_interleave(3)  # (1/2 |n_y A|) / 3 per corner
    weights = mesh.points.new_zeros(mesh.num_nodes).index_add(0, faces.reshape(-1), shares)
    return weights[nodes]


def bernstein_bumps(s: Tensor, num_bumps: int) -> Tensor:
    """``b_k(s) = C(K, k) s^k (1 − s)^(K−k)``, k = 1..K, shape (len(s), K): the Bernstein
    polynomials of degree K without ``b_0``, so that every one vanishes at the root."""
    k = torch.arange(1, num_bumps + 1, dtype=s.dtype, device=s.device)
    binomial = torch.tensor([math.comb(num_bumps, j) for j in range(1, num_bumps + 1)])
    binomial = binomial.to(dtype=s.dtype, device=s.device)
    return binomial * s[:, None] ** k * (1.0 - s[:, None]) ** (num_bumps - k)


class SpanwiseThickness(nn.Module):
    """Thickness of the wing's profile along the span, at fixed enclosed volume.

    ``forward(mu)`` maps K design parameters to the displacement of the boundary nodes:
    ``δy = (c(μ) t(s) − 1) y`` with ``t(s) = 1 + Σ_k μ_k b_k(s)``, ``b_k`` the
    Bernstein polynomials of degree K without ``b_0`` (so ``t(0) = 1``), ``s = z / L``,
    and ``c(μ) = V_0 / Σ_i w_i t(s_i) y_i`` (:func:`enclosed_volume_weights`), so the
    volume enclosed by the moved boundary equals the reference volume V_0 exactly.

    Parameters
    ----------
    points : Tensor, shape (N_b, 3)
        The boundary nodes' reference coordinates (x chord, y thickness, z span).
    volume_weights : Tensor, shape (N_b,)
        ``w`` of :func:`enclosed_volume_weights` for the same nodes.
    num_bumps : int
        K >= 1.
    span : float
        L, the span; the root is at z = 0.

    Notes
    -----
    Does not keep t(s) positive: a thickness through zero flattens and inverts the
    tetrahedra, which the validity barrier of the objective keeps away.
    """

    profile: Tensor
    bumps: Tensor
    volume_weights: Tensor

    def __init__(
        self, points: Tensor, volume_weights: Tensor, *, num_bumps: int, span: float = SPAN
    ) -> None:
        super().__init__()
        if num_bumps < 1:
            raise ValueError(f"num_bumps must be >= 1, got {num_bumps!r}")
        if volume_weights.shape != points.shape[:1]:
            raise ValueError(
                f"volume_weights must have shape ({points.shape[0]},), "
                f"got {tuple(volume_weights.shape)}"
            )
        bumps = bernstein_bumps((points[:, 2] / span).clamp(0.0, 1.0), num_bumps)
        self.register_buffer("profile", points[:, 1].clone())
        self.register_buffer("bumps", bumps)
        self.register_buffer("volume_weights", volume_weights.clone())
        self.span = float(span)

    @property
    def num_bumps(self) -> int:
        return int(self.bumps.shape[1])

    def thickness(self, mu: Tensor) -> Tensor:
        """t(s) at the boundary nodes, shape (N_b,) or (B, N_b)."""
        return 1.0 + mu @ self.bumps.mT

    def scale(self, mu: Tensor) -> Tensor:
        """c(μ), shape () or (B,): the factor that restores the enclosed volume."""
        weighted = self.volume_weights * self.profile
        return weighted.sum() / (self.thickness(mu) * weighted).sum(-1)

    def forward(self, mu: Tensor) -> Tensor:
        """Boundary displacement, shape (N_b, 3) for μ (K,), (B, N_b, 3) for μ (B, K)."""
        if mu.shape[-1:] != (self.num_bumps,) or mu.ndim not in (1, 2):
            count = self.num_bumps
            raise ValueError(
                f"mu must have shape ({count},) or (B, {count}), got {tuple(mu.shape)}"
            )
        factor = self.scale(mu)[..., None] * self.thickness(mu) - 1.0
        dy = factor * self.profile
        zeros = torch.zeros_like(dy)
        return torch.stack([zeros, dy, zeros], -1)

    def section_thickness(self, mu: Tensor, s: Tensor) -> Tensor:
        """The normalised thickness c(μ) t(s) at span fractions ``s`` (for plots)."""
        return self.scale(mu) * (1.0 + bernstein_bumps(s, self.num_bumps) @ mu)


# --------------------------------------------------------------------- physics


def nodal_load(
    mesh: TetMesh, space: LagrangeSpace, nodes: Tensor, force: float, *, projected: bool
) -> Tensor:
    """A total force ``force`` along +y on the boundary faces whose corners all lie in
    ``nodes``, spread by area (``projected``: by the area projected on the x-z plane, the
    planform, as a lift does) over the nodes of ``space`` that carry a constant traction
    (:meth:`LagrangeSpace.traction_nodes`), shape (space.num_nodes, 3)."""
    faces = mesh.boundary_faces
    member = torch.zeros(mesh.num_nodes, dtype=torch.bool, device=faces.device)
    member[nodes] = True
    faces = faces[member[faces].all(1)]
    corners = mesh.points[faces]
    normals = torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    areas = (normals[:, 1].abs() if projected else normals.norm(dim=1)) / 2.0
    shares = mesh.points.new_zeros(space.num_nodes).index_add(
        0, space.traction_nodes(faces).reshape(-1), (areas / 3.0).repeat_interleave(3)
    )
    load = mesh.points.new_zeros(space.num_nodes, 3)
    load[:, 1] = force * shares / shares.sum()
    return load


@dataclass
class Problem:
    """The wing's compliance on a morphed mesh, and the objective J of the module doc."""

    mesh: TetMesh
    family: SpanwiseThickness
    space: LagrangeSpace
    pattern: StiffnessPattern
    load: Tensor  # (n,): on the free degrees of freedom
    lame: tuple[float, float]
    threshold: float
    barrier_weight: float
    reference_compliance: float = 1.0

    def compliance(self, displacement: Tensor) -> Tensor:
        """C = fᵀu on the mesh moved by the nodal ``displacement`` (N, 3)."""
        points = self.mesh.points + displacement
        matrices = element_stiffness(points, self.mesh.tets, self.lame, order=self.space.order)
        values = self.pattern.assemble(matrices)
        solution = SparseSolve.apply(values, self.load, self.pattern)
        return self.load @ solution

    def terms(self, displacement: Tensor) -> dict[str, Tensor]:
        compliance = self.compliance(displacement)
        barrier = validity_barrier(self.mesh, displacement, threshold=self.threshold)
        objective = compliance / self.reference_compliance + self.barrier_weight * barrier
        return {"objective": objective, "compliance": compliance, "barrier": barrier}

    def objective(self, morph: Callable[[Tensor], Tensor], mu: Tensor) -> Tensor:
        return self.terms(morph(self.family(mu)))["objective"]


@dataclass
class History:
    objective: list[float] = field(default_factory=list)
    compliance: list[float] = field(default_factory=list)
    barrier: list[float] = field(default_factory=list)
    min_volume_ratio: list[float] = field(default_factory=list)
    inverted: list[int] = field(default_factory=list)
    mu: list[list[float]] = field(default_factory=list)
    iteration_seconds: list[float] = field(default_factory=list)


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
    print_every: int = 0,
    record: bool = True,
) -> tuple[Tensor, History]:
    """Minimise J from μ = 0 with Adam, one objective and gradient per iteration.

    The history holds every iterate's objective, compliance, barrier and validity
    (before its step), the last one included, and the wall time of each iteration
    (objective, gradient and step; the records are kept outside it); ``record=False``
    keeps the objective and the times only.
    """
    mesh = problem.mesh
    mu = mesh.points.new_zeros(problem.family.num_bumps, requires_grad=True)
    adam = torch.optim.Adam([mu], lr=learning_rate)
    history = History()
    for iteration in range(iterations + 1):
        start = time.perf_counter()
        displacement = morph(problem.family(mu))
        terms = problem.terms(displacement)
        elapsed = time.perf_counter() - start
        history.objective.append(float(terms["objective"].detach()))
        if record:
            history.compliance.append(float(terms["compliance"].detach()))
            history.barrier.append(float(terms["barrier"].detach()))
            history.min_volume_ratio.append(min_volume_ratio(mesh, displacement.detach()))
            history.inverted.append(count_inverted(mesh, displacement.detach()))
            history.mu.append(mu.detach().cpu().tolist())
            if print_every and (iteration % print_every == 0 or iteration == iterations):
                print(
                    f"  {iteration:4d}  J = {history.objective[-1]:.6f}  C/C0 = "
                    f"{history.compliance[-1] / problem.reference_compliance:.6f}  barrier = "
                    f"{history.barrier[-1]:.2e}  min V/V0 = {history.min_volume_ratio[-1]:.3f}"
                    f"  inverted = {history.inverted[-1]}"
                )
        if iteration == iterations:
            break
        start = time.perf_counter()
        adam.zero_grad()
        terms["objective"].backward()
        adam.step()
        history.iteration_seconds.append(elapsed + time.perf_counter() - start)
    return mu.detach(), history


# --------------------------------------------------------------------- checks


#: Central differences of fourth order: f'(μ) ≈ Σ c_j f(μ + j h) / h, j = ±1, ±2.
CENTRAL_STENCIL = ((-2, 1.0 / 12.0), (-1, -8.0 / 12.0), (1, 8.0 / 12.0), (2, -1.0 / 12.0))


def gradient_error(
    function: Callable[[Tensor], Tensor], mu: Tensor, step: float
) -> tuple[Tensor, float]:
    """The gradient of the scalar ``function`` at ``mu`` by autograd, and its relative
    error against central differences (2-norm of the difference over the 2-norm of the
    gradient).

    The differences are the fourth-order central ones,
    ``(f(μ − 2h e_k) − 8 f(μ − h e_k) + 8 f(μ + h e_k) − f(μ + 2h e_k)) / 12h``.

    Notes
    -----
    The step trades truncation, O(h⁴), against round-off, about ε_f / h: in float64
    the compliance of the thin wing carries a relative noise ε_f of about 1e-9 (the
    stiffness matrix's condition number, some 1e8, times the machine epsilon), so
    second-order differences cannot do better than about 1e-6 (at h = 1e-3), and
    fourth-order ones reach about 1e-7 at h = 1e-2. The validity barrier is only C¹ (its
    second derivative jumps where a volume ratio crosses the threshold), so differences
    of J are taken where no cell is near the threshold.
    """
    probe = mu.detach().clone().requires_grad_(True)
    (gradient,) = torch.autograd.grad(function(probe), probe)
    differences = torch.zeros_like(gradient)
    with torch.no_grad():
        for k in range(mu.numel()):
            for multiple, coefficient in CENTRAL_STENCIL:
                shifted = mu.clone()
                shifted[k] += multiple * step
                differences[k] += coefficient * function(shifted) / step
    return gradient, float((gradient - differences).norm() / gradient.norm())


def stiffness_against_skfem(problem: Problem, displacement: Tensor) -> float:
    """max |K_torch − K_skfem| / max |K_skfem| on the mesh moved by ``displacement``, over
    every degree of freedom (scikit-fem assembles the whole matrix; ours is restricted
    to the free ones, so both are compared there)."""
    from skfem import Basis, ElementTetP1, ElementTetP2, ElementVector, MeshTet, asm
    from skfem.models.elasticity import linear_elasticity

    points = (problem.mesh.points + displacement).detach().cpu()
    tets = problem.mesh.tets.cpu()
    order = problem.space.order
    element = ElementVector(ElementTetP1() if order == 1 else ElementTetP2())
    basis = Basis(MeshTet(points.numpy().T.copy(), tets.numpy().T.copy()), element)
    reference = asm(linear_elasticity(*problem.lame), basis).tocsr()
    ours_in_theirs = problem.space.skfem_numbering(basis)
    free = ours_in_theirs[problem.pattern.free_dofs.cpu().numpy()]
    reference = reference[free][:, free]
    with torch.no_grad():
        matrices = element_stiffness(points, tets, problem.lame, order=order)
        values = problem.pattern.assemble(matrices)
    ours = problem.pattern.to_scipy(values)
    return float(abs(ours - reference).max() / abs(reference).max())


# --------------------------------------------------------------------- timing


def timed_costs(
    problem: Problem,
    morphs: dict[str, Callable[[Tensor], Tensor]],
    mu: Tensor,
    *,
    repeats: int,
    learning_rate: float,
) -> dict[str, dict[str, float]]:
    """Median seconds, for each morph, of the morph alone (forward and gradient to μ
    through the family) and of the objective with its gradient, both at ``mu``, and of
    one iteration of the Adam loop run on from ``mu`` (objective, gradient, step).

    The morphs take turns, repeat by repeat, so that a load on a shared machine falls
    on each alike; one untimed round comes first.
    """
    weights = torch.ones(problem.mesh.num_nodes, 3, dtype=mu.dtype, device=mu.device)
    loops = {}
    for name in morphs:
        design = mu.clone().requires_grad_(True)
        loops[name] = (design, torch.optim.Adam([design], lr=learning_rate))
    samples: dict[str, dict[str, list[float]]] = {
        name: {"morph": [], "objective": [], "iteration": []} for name in morphs
    }
    for repeat in range(repeats + 1):
        for name, morph in morphs.items():
            probe = mu.clone().requires_grad_(True)
            design, adam = loops[name]
            start = time.perf_counter()
            torch.autograd.grad((morph(problem.family(probe)) * weights).sum(), probe)
            after_morph = time.perf_counter()
            torch.autograd.grad(problem.objective(morph, probe), probe)
            after_objective = time.perf_counter()
            adam.zero_grad()
            problem.objective(morph, design).backward()
            adam.step()
            after_iteration = time.perf_counter()
            if repeat:
                samples[name]["morph"].append(after_morph - start)
                samples[name]["objective"].append(after_objective - after_morph)
                samples[name]["iteration"].append(after_iteration - after_objective)
    return {
        name: {key: statistics.median(values) for key, values in costs.items()}
        for name, costs in samples.items()
    }


# --------------------------------------------------------------------- output


def plot(history: History, problem: Problem, mu: Tensor, path: Path, load: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    steps = range(len(history.objective))
    reference = problem.reference_compliance
    axes[0].plot(steps, history.objective, label="J")
    axes[0].plot(steps, [c / reference for c in history.compliance], "--", label="C / C(0)")
    axes[0].set(xlabel="iteration", ylabel="objective", title="objective")
    s = torch.linspace(0.0, 1.0, 101, dtype=mu.dtype)
    family = problem.family
    with torch.no_grad():
        start = family.section_thickness(torch.zeros_like(mu).cpu(), s)
        end = family.section_thickness(mu.cpu(), s)
    axes[1].plot(s, start, color="k", lw=0.8, label="start")
    axes[1].plot(s, end, label="optimum")
    # slender beam, second moment ∝ t³, same volume: t ∝ M(s)^(1/2), M the bending moment
    beam = 1.5 * (1.0 - s).sqrt() if load == "tip" else 2.0 * (1.0 - s)
    axes[1].plot(s, beam, ":", color="grey", label="beam theory, t ∝ M^(1/2)")
    axes[1].set(xlabel="span fraction s = z / L", ylabel="thickness c t(s)", title="thickness")
    axes[2].plot(steps, history.min_volume_ratio, label="POD-ESIDW")
    axes[2].axhline(0.0, color="k", lw=0.8)
    axes[2].axhline(
        problem.threshold, color="grey", lw=0.8, ls="--", label=f"threshold {problem.threshold:g}"
    )
    axes[2].set(xlabel="iteration", ylabel="min V / V0", title="smallest volume ratio")
    for axis in axes:
        axis.grid(alpha=0.3)
        axis.legend(fontsize=8)
    figure.suptitle(f"Case A wing: least compliance at fixed volume, {load} load, POD-ESIDW morph")
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
        help="mesh size (default: %(default)s)",
    )
    parser.add_argument(
        "--out",
        default="out/physics_optimisation",
        help="directory for the PNG of the history (default: %(default)s); '' writes nothing",
    )
    parser.add_argument(
        "--load",
        choices=("tip", "lift"),
        default="tip",
        help="tip force or uniform lift (default: %(default)s)",
    )
    parser.add_argument(
        "--element",
        choices=("p1", "p2"),
        default="p1",
        help="P1 or P2 (straight-sided) tetrahedra for the elasticity solve; P2 does not "
        "lock in bending but costs some 30 times more per iteration (default %(default)s)",
    )
    parser.add_argument(
        "--bumps", type=int, default=4, help="K, the thickness parameters (default %(default)s)"
    )
    parser.add_argument(
        "--iterations", type=int, default=100, help="Adam iterations (default %(default)s)"
    )
    parser.add_argument(
        "--lr", type=float, default=0.02, help="Adam's learning rate (default %(default)s)"
    )
    parser.add_argument(
        "--threshold",
        type=float,
        default=0.3,
        help="volume ratio under which the barrier starts (default %(default)s)",
    )
    parser.add_argument(
        "--barrier-weight",
        type=float,
        default=1.0,
        help="weight of the validity barrier (default %(default)s)",
    )
    parser.add_argument(
        "--train", type=int, default=20, help="POD training values (default %(default)s)"
    )
    parser.add_argument(
        "--energy-tolerance",
        type=float,
        default=1e-12,
        help="POD energy tolerance ε (default %(default)s)",
    )
    parser.add_argument(
        "--step", type=float, default=1e-2, help="finite-difference step in μ (default %(default)s)"
    )
    parser.add_argument(
        "--repeats",
        type=int,
        default=20,
        help="timed repeats of each cost (median; default %(default)s)",
    )
    parser.add_argument(
        "--seed", type=int, default=0, help="seed of the ESIDW selection and the training set"
    )
    parser.add_argument(
        "--threads", type=int, default=1, help="torch intra-op threads (default %(default)s)"
    )
    parser.add_argument("--quiet", action="store_true", help="print nothing")
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Run the demo; returns its numbers (history, checks, timings)."""
    args = parse(argv)
    require_solver()
    start = time.perf_counter()
    threads = torch.get_num_threads()
    torch.set_num_threads(args.threads)
    try:
        return _run(args, start)
    finally:
        torch.set_num_threads(threads)


def _run(args: argparse.Namespace, start: float) -> dict[str, Any]:
    say = (lambda *a, **k: None) if args.quiet else print

    # ------------------------------------------------------------------ set-up
    mesh = cast(TetMesh, load_mesh("wing", size=args.size).to(dtype=torch.float64))
    generator = torch.Generator().manual_seed(args.seed)
    esidw = MeshMorph(mesh, CASES["wing"].plan(), generator=generator)
    idw = MeshMorph(mesh)
    weights = enclosed_volume_weights(mesh, esidw.boundary_nodes)
    family = SpanwiseThickness(esidw.boundary_points, weights, num_bumps=args.bumps)
    low, high = TRAINING_BOX
    training = low + (high - low) * torch.rand(
        args.train, args.bumps, generator=generator, dtype=torch.float64
    )
    reducer = PODReducer(energy_tolerance=args.energy_tolerance)
    reducer.fit(esidw, family=family, parameters=training)

    space = LagrangeSpace.of(mesh, 2 if args.element == "p2" else 1)
    clamped = space.nodes_within(mesh.node_set("root"))
    pattern = StiffnessPattern.of(space.cells, space.num_nodes, clamped)
    projected = args.load == "lift"
    loaded = mesh.node_set("upper" if projected else "tip")
    load = nodal_load(mesh, space, loaded, 1.0e3, projected=projected)
    problem = Problem(
        mesh,
        family,
        space,
        pattern,
        load.reshape(-1)[pattern.free_dofs],
        lame_parameters(YOUNG, POISSON),
        args.threshold,
        args.barrier_weight,
    )
    zero = torch.zeros(args.bumps, dtype=torch.float64)
    with torch.no_grad():
        problem.reference_compliance = float(problem.compliance(torch.zeros_like(mesh.points)))
    setup = time.perf_counter() - start
    say(
        f"case A wing ({args.size}): {mesh.num_nodes} nodes, {mesh.num_tets} tets, "
        f"{args.element.upper()} elements, {pattern.size} free degrees of freedom "
        f"({pattern.nnz} stored entries); ESIDW "
        f"{esidw.num_controls} control points, IDW {idw.num_controls}; POD {reducer.num_modes_} "
        f"modes from {args.train} training values; {args.load} load, C(0) = "
        f"{problem.reference_compliance:.4e} J; set-up {setup:.2f} s"
    )

    # ------------------------------------------------------------------ gradients at the start
    def objective_with(morph: Callable[[Tensor], Tensor]) -> Callable[[Tensor], Tensor]:
        return lambda mu: problem.objective(morph, mu)

    gradient, fd_error_start = gradient_error(objective_with(reducer), zero, args.step)
    gradient_esidw, _ = gradient_error(objective_with(esidw), zero, args.step)
    gradient_idw, fd_error_idw = gradient_error(objective_with(idw), zero, args.step)
    versus_esidw = float((gradient - gradient_esidw).norm() / gradient_esidw.norm())
    versus_idw = float((gradient - gradient_idw).norm() / gradient_idw.norm())
    say(
        f"\ndJ/dμ at μ = 0 (POD-ESIDW): {[round(float(g), 6) for g in gradient]}\n"
        f"  vs central differences (h = {args.step:g}): relative error {fd_error_start:.1e}"
        f"\n  vs full ESIDW: {versus_esidw:.1e}; vs full IDW: {versus_idw:.1e} (IDW's own "
        f"against differences: {fd_error_idw:.1e})"
    )

    # ------------------------------------------------------------------ optimise
    say(f"\nAdam (lr {args.lr:g}), {args.iterations} iterations from μ = 0:")
    print_every = 0 if args.quiet else max(1, args.iterations // 10)
    mu, history = optimise(
        problem, reducer, iterations=args.iterations, learning_rate=args.lr, print_every=print_every
    )

    # at the optimum the barrier's gradient balances the compliance's: check the latter
    def relative_compliance(mu: Tensor) -> Tensor:
        return problem.compliance(reducer(family(mu))) / problem.reference_compliance

    _, fd_error_end = gradient_error(relative_compliance, mu, args.step)

    # ------------------------------------------------------------------ verify on full IDW
    with torch.no_grad():
        reduced = reducer(family(mu))
        full_esidw = esidw(family(mu))
        full = idw(family(mu))
        pod_error = float((reduced - full_esidw).norm() / full_esidw.norm())
        idw_start = {key: float(v) for key, v in problem.terms(idw(family(zero))).items()}
        idw_end = {key: float(v) for key, v in problem.terms(full).items()}
        volume_change = float(
            signed_volumes(mesh.points + full, mesh.tets).sum() / mesh.volumes.sum() - 1.0
        )
    skfem_difference = stiffness_against_skfem(problem, full)
    reference = problem.reference_compliance
    result: dict[str, Any] = {
        "mu": mu.tolist(),
        "history": history,
        "gradient": gradient.tolist(),
        "fd_error_start": fd_error_start,
        "fd_error_end": fd_error_end,
        "fd_error_idw": fd_error_idw,
        "gradient_vs_esidw": versus_esidw,
        "gradient_vs_idw": versus_idw,
        "objective_initial": history.objective[0],
        "objective_final": history.objective[-1],
        "compliance_initial": history.compliance[0],
        "compliance_final": history.compliance[-1],
        "inverted": history.inverted[-1],
        "min_volume_ratio": history.min_volume_ratio[-1],
        "pod_error": pod_error,
        "full_objective_initial": idw_start["objective"],
        "full_objective_final": idw_end["objective"],
        "full_compliance_initial": idw_start["compliance"],
        "full_compliance_final": idw_end["compliance"],
        "full_inverted": count_inverted(mesh, full),
        "full_min_volume_ratio": min_volume_ratio(mesh, full),
        "volume_change": volume_change,
        "stiffness_vs_skfem": skfem_difference,
        "num_modes": reducer.num_modes_,
        "num_controls": esidw.num_controls,
        "setup_s": setup,
    }
    say(
        f"\noptimum μ = {[round(v, 4) for v in result['mu']]}; there d(C/C(0))/dμ vs "
        f"differences {fd_error_end:.1e}; POD vs full ESIDW {pod_error:.1e}; volume change "
        f"on full IDW {volume_change:.1e}; stiffness vs scikit-fem {skfem_difference:.1e}"
    )
    columns = {
        "start": (idw_start, quality_summary(mesh)),
        "optimum, POD-ESIDW": (
            {"objective": history.objective[-1], "compliance": history.compliance[-1]},
            quality_summary(mesh, reduced),
        ),
        "optimum, full IDW": (idw_end, quality_summary(mesh, full)),
    }
    result["quality"] = {name: summary for name, (_, summary) in columns.items()}
    rows: list[tuple[str, Callable[[dict, dict], str]]] = [
        ("objective J", lambda terms, _: f"{terms['objective']:.4f}"),
        ("compliance C / C(0)", lambda terms, _: f"{terms['compliance'] / reference:.4f}"),
        ("inverted tets", lambda _, quality: f"{quality['num_inverted']}"),
        ("min V / V0", lambda _, quality: f"{quality['min_volume_ratio']:.3f}"),
        ("max Q (edge ratio)", lambda _, quality: f"{quality['max_edge_ratio']:.2f}"),
        ("min scaled Jacobian", lambda _, quality: f"{quality['min_scaled_jacobian']:.3f}"),
    ]
    say(f"\n  {'':22s}" + "".join(f"{name:>22s}" for name in columns))
    for label, cell in rows:
        say(f"  {label:22s}" + "".join(f"{cell(*column):>22s}" for column in columns.values()))

    # ------------------------------------------------------------------ timing
    morphs: dict[str, Callable[[Tensor], Tensor]] = {
        "POD-ESIDW": reducer,
        "ESIDW (full W)": esidw,
        f"IDW ({idw.num_controls} controls)": idw,
    }
    timings = timed_costs(problem, morphs, mu, repeats=args.repeats, learning_rate=args.lr)
    result["timings_s"] = timings
    base = timings["POD-ESIDW"]
    say(
        f"\ncosts at the optimum, median of {args.repeats} (the morphs taking turns): the "
        f"morph alone and the objective, each with its gradient to μ, and an iteration of "
        f"the loop (objective, gradient, Adam step); {torch.get_num_threads()} thread(s):"
    )
    say(
        f"  {'morph':24s} {'morph':>10s} {'objective':>10s} {'iteration':>10s} {'morph share':>12s}"
    )
    for name, costs in timings.items():
        say(
            f"  {name:24s} {costs['morph'] * 1e3:7.2f} ms {costs['objective'] * 1e3:7.2f} ms "
            f"{costs['iteration'] * 1e3:7.2f} ms {costs['morph'] / costs['objective']:11.1%}"
            f"   (morph {costs['morph'] / base['morph']:.1f}x POD, iteration "
            f"{costs['iteration'] / base['iteration']:.2f}x)"
        )

    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        path = out / "physics_optimisation.png"
        plot(history, problem, mu, path, args.load)
        result["figure"] = path
        say(f"\nwrote {path}")
    result["total_s"] = time.perf_counter() - start
    say(f"total run time {result['total_s']:.1f} s")
    return result


if __name__ == "__main__":
    main()
