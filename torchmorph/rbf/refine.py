"""The global RBF fit by preconditioned Krylov iterations: flexible GMRES (Saad, *Iterative
Methods for Sparse Linear Systems*, 2nd ed., §9.4.1) on several right-hand sides at once,
for :class:`~torchmorph.rbf.PartitionRBF` with a ``tolerance``; and its kernel sums,
exact or by the treecode (:class:`KernelSums`).

The system is the interpolation system of the whole fit, ``[Φ P; Pᵀ 0] [λ; β] = [d; 0]``
(symmetric, indefinite with the polynomial), applied by kernel sums and never stored;
the preconditioner is the partition of unity's own two levels (the coarse fit, then the
patches' local fits of what it leaves), so each iteration costs one product with the
kernel matrix and one pass over the patches. :class:`GlobalSolve` differentiates the
solution as ``A⁻¹ b`` (the transposed system is the same system, solved again; with the
treecode's products, symmetric to its error), not through the iterations. The fit
itself is :class:`GlobalFit`, :class:`~torchmorph.rbf.PartitionRBF`'s base.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from torch import Tensor

from torchmorph._treecode import TreeCode, tree_sum
from torchmorph.rbf import _parallel
from torchmorph.rbf._parallel import kernel_sum
from torchmorph.rbf.kernels import fused, polynomial_matrix
from torchmorph.rbf.system import FACTOR_NAMES, KINDS, solve

__all__ = [
    "MAX_TREECODE_DEGREE",
    "SAMPLED_TARGETS",
    "SUMMATIONS",
    "TREECODE_PAIRS",
    "GlobalFit",
    "GlobalSolve",
    "KernelSums",
    "control_degree",
    "fgmres",
    "global_solver",
    "treecode_degree",
    "uses_treecode",
]

#: How :class:`~torchmorph.rbf.PartitionRBF`'s global fit sums the kernel over the
#: controls (``summation=``): ``"auto"`` (the treecode from :data:`TREECODE_PAIRS`
#: pairs), ``"exact"``, ``"treecode"``.
SUMMATIONS = ("auto", "exact", "treecode")

#: ``summation="auto"`` takes the treecode from this many target-control pairs up. On the
#: wing in a box at tolerance 1e-4 (two threads; first and later morph): 10⁴ × 10⁵ took
#: 3.1 and 3.0 s with exact sums, 3.0 and 2.7 s with the treecode; 3·10⁴ × 10⁵ 9.7 and
#: 9.2 s against 6.4 and 6.2 s; 10⁴ × 10⁶ 11.9 and 11.8 s against 8.6 and 6.3 s.
TREECODE_PAIRS = 10**9

#: The highest interpolation degree :func:`treecode_degree` gives.
MAX_TREECODE_DEGREE = 16


#: Targets at which the treecode's sums are checked against exact ones on every call.
SAMPLED_TARGETS = 32

Operator = Callable[[Tensor], Tensor]


def fgmres(
    apply: Operator,
    precondition: Operator,
    rhs: Tensor,
    start: Tensor,
    *,
    tolerance: float,
    max_iterations: int,
    restart: int = 40,
) -> tuple[Tensor, int, Tensor, Tensor]:
    """Solve ``apply(x) = rhs`` for each column of ``rhs`` (n, S), from ``start``, by
    right-preconditioned flexible GMRES restarted every ``restart`` iterations, until
    ``|rhs − apply(x)| <= tolerance |rhs|`` in every column or ``max_iterations`` products.

    The columns run their own Arnoldi processes side by side (one ``apply`` and one
    ``precondition`` of all the columns per iteration); a column already converged, or
    all zero, takes a zero direction. The small least-squares problem of each column is
    updated by Givens rotations (elementwise arithmetic, so that a solve repeats to the
    bit, which LAPACK's least squares does not on copies of the same data). Returns the
    solution, the iterations made, the relative residual of each column and the residual
    ``rhs − apply(solution)`` itself (recomputed, not the recurrence's)."""
    scale = torch.linalg.vector_norm(rhs, dim=0)
    goal = tolerance * scale
    solution = start.clone()
    residual = rhs - apply(solution)
    done = 0
    while True:
        norms = torch.linalg.vector_norm(residual, dim=0)
        active = norms > goal
        if not bool(active.any()) or done >= max_iterations:
            break
        beta = torch.where(active, norms, torch.ones_like(norms))
        basis = [residual * (active / beta)]
        directions: list[Tensor] = []
        steps = min(restart, max_iterations - done)
        columns = rhs.shape[1]
        upper = rhs.new_zeros(columns, steps, steps)  # R of the Hessenberg matrix's QR
        cosines = rhs.new_zeros(columns, steps)
        sines = rhs.new_zeros(columns, steps)
        first = rhs.new_zeros(columns, steps + 1)  # Qᵀ (β e₁)
        first[:, 0] = torch.where(active, norms, torch.zeros_like(norms))
        made = 0
        for step in range(steps):
            direction = precondition(basis[step])
            directions.append(direction)
            vector = apply(direction)
            column = rhs.new_zeros(columns, step + 2)
            for index in range(step + 1):  # modified Gram-Schmidt, column by column
                projection = (basis[index] * vector).sum(dim=0)
                column[:, index] = projection
                vector = vector - basis[index] * projection
            length = torch.linalg.vector_norm(vector, dim=0)
            column[:, step + 1] = length
            safe = torch.where(length > 0, length, torch.ones_like(length))
            basis.append(vector / safe)
            done += 1
            made = step + 1
            for index in range(step):  # the earlier Givens rotations, then a new one
                above, below = column[:, index].clone(), column[:, index + 1].clone()
                column[:, index] = cosines[:, index] * above + sines[:, index] * below
                column[:, index + 1] = -sines[:, index] * above + cosines[:, index] * below
            radius = torch.hypot(column[:, step], column[:, step + 1])
            nonzero = radius > 0
            safe_radius = torch.where(nonzero, radius, torch.ones_like(radius))
            cosines[:, step] = torch.where(nonzero, column[:, step] / safe_radius, 1.0)
            sines[:, step] = torch.where(nonzero, column[:, step + 1] / safe_radius, 0.0)
            column[:, step] = radius
            upper[:, : step + 1, step] = column[:, : step + 1]
            first[:, step + 1] = -sines[:, step] * first[:, step]
            first[:, step] = cosines[:, step] * first[:, step]
            estimate = first[:, step + 1].abs()
            if bool(((estimate <= goal) | ~active).all()) or bool((length == 0).all()):
                break
        coefficients = rhs.new_zeros(columns, made)
        for index in reversed(range(made)):  # back substitution in R y = Qᵀ β e₁
            known = (upper[:, index, index + 1 : made] * coefficients[:, index + 1 :]).sum(dim=1)
            pivot = upper[:, index, index]
            safe_pivot = torch.where(pivot != 0, pivot, torch.ones_like(pivot))
            coefficients[:, index] = torch.where(
                pivot != 0, (first[:, index] - known) / safe_pivot, 0.0
            )
        for index, direction in enumerate(directions):
            solution = solution + direction * coefficients[:, index]
        residual = rhs - apply(solution)
    safe_scale = torch.where(scale > 0, scale, torch.ones_like(scale))
    return solution, done, torch.linalg.vector_norm(residual, dim=0) / safe_scale, residual


class GlobalSolve(torch.autograd.Function):
    """``x = A⁻¹ b`` by :func:`fgmres` (A symmetric), differentiable in ``b``: the backward
    pass solves ``A g' = g`` with the same operator and preconditioner. ``solver`` is
    a callable ``(b, start) -> x``; ``start`` the first guess (not differentiated)."""

    @staticmethod
    def forward(ctx, rhs, start, solver):  # type: ignore[override]
        ctx.solver = solver
        return solver(rhs, start)

    @staticmethod
    def backward(ctx, grad):  # type: ignore[override]
        return ctx.solver(grad, torch.zeros_like(grad)), None, None


def global_solver(
    apply: Operator, precondition: Operator, owner: Any, name: str
) -> Callable[[Tensor, Tensor], Tensor]:
    """A solver ``(b, start) -> x`` for :class:`GlobalSolve`: :func:`fgmres` to
    ``owner.tolerance`` in at most ``owner.max_iterations``, recording the iterations and
    the relative residuals in ``owner.last_iterations_`` and ``owner.last_residual_``
    (and the residual itself in the solver's ``residual``, for a caller that needs no
    gradient through it); a solve that stops short warns (``RuntimeWarning``, naming
    ``name``)."""

    def solver(rhs: Tensor, start: Tensor) -> Tensor:
        with torch.no_grad():
            solution, owner.last_iterations_, owner.last_residual_, solver.residual = fgmres(  # type: ignore[attr-defined]
                apply, precondition, rhs, start,
                tolerance=owner.tolerance, max_iterations=owner.max_iterations,
            )  # fmt: skip
        if bool((owner.last_residual_ > owner.tolerance).any()):
            warnings.warn(
                f"{name}: the global fit stopped at max_iterations={owner.max_iterations} "
                f"with a relative residual of {float(owner.last_residual_.max()):.3g} > "
                f"tolerance={owner.tolerance:g}",
                RuntimeWarning,
                stacklevel=2,
            )
        return solution

    return solver


def treecode_degree(tolerance: float) -> int:
    """The degree of the treecode at the targets for a tolerance: 8 for 1e-4 and one more
    per tenth, between 4 and :data:`MAX_TREECODE_DEGREE`. Measured on the wing in a box
    of ``benchmarks/rbf_scale.py`` (3·10⁴ controls, 10⁵ targets, tolerance 1e-4; the
    morph's error against the exact sums' at the sampled targets): 5.2e-4 at degree 6,
    2.4e-4 at 7, 7.5e-6 at 8. The sampled check of every call
    (:meth:`KernelSums.sampled_error`) measures what it gives on yours.

    The preconditioner's sums take two degrees fewer (an inexact preconditioner costs
    iterations, not accuracy; degree 6 left them at 5-6 there), the sums at the
    controls :func:`control_degree`."""
    wanted = 8 + math.ceil(math.log10(1e-4 / tolerance) - 1e-9)
    return int(min(max(wanted, 4), MAX_TREECODE_DEGREE))


def control_degree(tolerance: float) -> int:
    """The degree of the treecode at the controls (the iterations' products): one more
    than :func:`treecode_degree`, and at least 9. The iterations multiply its error by
    the interpolation matrix's condition number and stall when that is not small: on the
    wing in a box, 17 iterations at degree 8 and 6 at 9 or 10 with 10⁵ controls, 72 at
    degree 6 and 5 at 8 with 3·10⁴ (tolerance 1e-4)."""
    return int(min(max(treecode_degree(tolerance) + 1, 9), MAX_TREECODE_DEGREE))


def uses_treecode(summation: str, kernel: str, points: Tensor, pairs: int) -> bool:
    """Whether kernel sums over ``pairs`` target-control pairs take the treecode:
    ``"treecode"`` always, ``"auto"`` for the thin-plate spline on the CPU (numba
    installed) from :data:`TREECODE_PAIRS` pairs up, ``"exact"`` never."""
    if summation == "exact" or pairs == 0:
        return False
    if summation == "treecode":
        return True
    return fused(kernel, points.double()) and pairs >= TREECODE_PAIRS


class KernelSums:
    """``Σ_j φ(ε|x − y_j|) λ_j`` over the controls y, at the controls and at the targets,
    for :class:`~torchmorph.rbf.PartitionRBF`'s global fit: exact (the fused pass or torch
    blocks, :func:`~torchmorph.rbf._parallel.kernel_sum`) or by the treecode
    (:mod:`~torchmorph._treecode`, built here once per pair of point sets), each set
    of targets decided by :func:`uses_treecode`; and the coarse fit's sums at the
    controls for the preconditioner (:meth:`coarse_at_controls`).

    With the treecode at the targets, :meth:`sampled_error` compares its sums with exact
    ones at :data:`SAMPLED_TARGETS` targets spread through them, and the targets that
    coincide with a control are listed (``coincident``: target and control indices) so
    that the morph can give them the control's displacement exactly.
    """

    def __init__(
        self,
        controls: Tensor,
        targets: Tensor,
        coarse: Tensor,
        *,
        kernel: str,
        scale: float,
        block_bytes: int | None,
        summation: str,
        tolerance: float,
    ) -> None:
        self.controls, self.targets, self.coarse = controls, targets, coarse
        self.kernel, self.scale, self.block_bytes = kernel, scale, block_bytes
        degree = treecode_degree(tolerance)
        points = controls.detach().cpu().numpy()
        count = controls.shape[0]
        self.control_tree = (
            TreeCode(points, points, scale, control_degree(tolerance))
            if uses_treecode(summation, kernel, controls, count * count)
            else None
        )
        self.target_tree = (
            TreeCode(points, targets.detach().cpu().numpy(), scale, degree)
            if uses_treecode(summation, kernel, controls, count * targets.shape[0])
            else None
        )
        self.coarse_tree = (
            TreeCode(coarse.detach().cpu().numpy(), points, scale, max(degree - 2, 4))
            if uses_treecode(summation, kernel, controls, count * coarse.shape[0])
            else None
        )
        self.coincident: tuple[Tensor, Tensor] | None = None
        self.samples = torch.zeros(0, dtype=torch.int64)
        if self.target_tree is not None:
            from scipy.spatial import cKDTree

            distance, nearest = cKDTree(points).query(targets.detach().cpu().numpy(), k=1)
            hit = np.flatnonzero(distance == 0)
            device = targets.device
            self.coincident = (
                torch.from_numpy(hit).to(device),
                torch.from_numpy(nearest[hit]).to(device),
            )
            spread = np.linspace(0, targets.shape[0] - 1, min(SAMPLED_TARGETS, targets.shape[0]))
            self.samples = torch.from_numpy(np.unique(spread.round().astype(np.int64))).to(device)

    def _exact(self, points: Tensor, weights: Tensor, threads: int) -> Tensor:
        return kernel_sum(
            points, self.controls, weights, self.kernel, self.scale, self.block_bytes, threads
        )

    def at_controls(self, weights: Tensor, threads: int) -> Tensor:
        if self.control_tree is None:
            return self._exact(self.controls, weights, threads)
        return tree_sum(self.control_tree, weights, threads)

    def coarse_at_controls(self, weights: Tensor, threads: int) -> Tensor:
        """``Σ_k φ(ε|x − c_k|) weights_k`` over the coarse controls c, at the controls x
        (the preconditioner's)."""
        if self.coarse_tree is None:
            return kernel_sum(
                self.controls, self.coarse, weights, self.kernel, self.scale, self.block_bytes,
                threads,
            )  # fmt: skip
        return tree_sum(self.coarse_tree, weights, threads)

    def at_targets(self, weights: Tensor, threads: int) -> Tensor:
        if self.target_tree is None:
            return self._exact(self.targets, weights, threads)
        return tree_sum(self.target_tree, weights, threads)

    def sampled_error(self, weights: Tensor, sums: Tensor, values: Tensor, threads: int) -> float:
        """With the treecode at the targets: ‖sums − exact‖ / ‖values − sums + exact‖ over
        the sampled targets (``sums`` the treecode's kernel sums at every target,
        ``values`` the morph there), the relative error of the morph the treecode makes;
        0 without it."""
        if self.target_tree is None or not self.samples.numel():
            return 0.0
        with torch.no_grad():
            exact = self._exact(self.targets[self.samples], weights.detach(), threads)
            approximate = sums.detach()[self.samples]
            reference = values.detach()[self.samples] - approximate + exact
            scale = float(torch.linalg.vector_norm(reference))
            error = float(torch.linalg.vector_norm(approximate - exact))
        return error / scale if scale > 0 else error


class GlobalFit:
    """The global fit of :class:`~torchmorph.rbf.PartitionRBF` with a ``tolerance`` (its
    base: these methods use the partition's coarse factorisation, patches and blend)."""

    _sums: KernelSums | None  # made on the first call, dropped on a move or a load

    def _global(
        self: Any, values: Tensor, controls: Tensor, targets: Tensor, threads: int
    ) -> Tensor:
        """The global fit of ``values`` (:mod:`~torchmorph.rbf.refine`) at the targets, its
        last residual at the controls blended by the patches."""
        size, coarse = controls.shape[0], controls[self.coarse_indices]
        kind = KINDS[int(self.coarse_solver)]
        factors = {name: self._buffers[f"coarse_{name}"] for name in FACTOR_NAMES}
        poly = polynomial_matrix(controls, self.powers, self.coarse_shift, self.coarse_scale)
        basis, triangle = torch.linalg.qr(poly)  # P = QR: Pᵀλ = 0 is Qᵀλ = 0
        if self._sums is None:
            self._sums = KernelSums(
                controls, targets, coarse, kernel=self.kernel, scale=self.scale,
                block_bytes=self.block_bytes, summation=self.summation,
                tolerance=self.tolerance,  # type: ignore[arg-type]
            )  # fmt: skip
        sums = self._sums

        def apply(solution: Tensor) -> Tensor:  # [Φ P; Pᵀ 0] [λ; β]
            weights, tail = solution[:size], solution[size:]
            return torch.cat([sums.at_controls(weights, threads) + poly @ tail, poly.T @ weights])

        def precondition(vector: Tensor) -> Tensor:  # the coarse fit, then the patches
            weights, tail = solve(kind, factors, vector[self.coarse_indices])  # type: ignore[arg-type]
            fitted = sums.coarse_at_controls(weights, threads)
            if self.powers:
                fitted = fitted + poly @ tail  # the coarse fit's tail (its shift and scale)
            rest = vector[:size] - fitted
            local = self._local_coefficients(rest)
            local = local.index_add(0, self.coarse_indices, weights)
            local = local - basis @ (basis.T @ local)  # the coefficients' moments vanish
            if self.powers:  # the moment rows' residual s: + Q R⁻ᵀ s, whose moments are s
                moments = torch.linalg.solve_triangular(triangle.T, vector[size:], upper=False)
                local = local + basis @ moments
            return torch.cat([local, tail])

        with torch.no_grad():  # the coarse fit
            weights, tail = solve(kind, factors, values.detach()[self.coarse_indices])  # type: ignore[arg-type]
            start = torch.cat(
                [values.new_zeros(values.shape).index_add(0, self.coarse_indices, weights), tail]
            )
        rhs = torch.cat([values, values.new_zeros(len(self.powers), values.shape[1])])
        solver = global_solver(apply, precondition, self, "PartitionRBF")
        solution = GlobalSolve.apply(rhs, start, solver)
        weights, tail = solution[:size], solution[size:]
        if torch.is_grad_enabled() and solution.requires_grad:
            residual = values - sums.at_controls(weights, threads) - poly @ tail
        else:  # the solve's own last residual, the same sums
            residual = solver.residual[:size]  # type: ignore[attr-defined]
        summed = sums.at_targets(weights, threads)
        value = (
            summed
            + polynomial_matrix(targets, self.powers, self.coarse_shift, self.coarse_scale) @ tail
        )
        with _parallel.one_torch_thread():
            value = value + self._blend(residual, controls, targets, threads)
        self.last_treecode_error_ = sums.sampled_error(weights, summed, value, threads)
        if self.last_treecode_error_ > self.tolerance:  # type: ignore[operator]
            warnings.warn(
                f"PartitionRBF: the treecode's sums were {self.last_treecode_error_:.3g} off "
                f"the exact ones at the sampled targets, > tolerance={self.tolerance:g}; "
                "summation='exact' sums exactly",
                RuntimeWarning,
                stacklevel=3,
            )
        if sums.coincident is not None and sums.coincident[0].numel():
            on, control = sums.coincident
            value = value.index_put((on,), values[control])  # exact at the controls
        return value

    def _local_coefficients(self: Any, values: Tensor) -> Tensor:
        """Each control's coefficient from its own cell's patch's local fit of ``values``
        (the restricted additive Schwarz step of the preconditioner)."""
        layout, members = self._layout(), self.patch_member_offsets.tolist()
        solvers = self.patch_solver.tolist()
        out = values.new_zeros(values.shape)
        with _parallel.one_torch_thread():
            for index in range(self.num_patches):
                held = self._buffers["patch_members"][members[index] : members[index + 1]]  # type: ignore[index]
                weights, _ = solve(
                    KINDS[solvers[index]], self._patch_factors(index, layout), values[held]
                )
                own = self.patch_owner[held] == index
                out[held[own]] = weights[own]
        return out
