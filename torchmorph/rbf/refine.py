"""The global RBF fit by preconditioned Krylov iterations: flexible GMRES (Saad, *Iterative
Methods for Sparse Linear Systems*, 2nd ed., §9.4.1) on several right-hand sides at once,
for :class:`~torchmorph.rbf.PartitionRBF` with a ``tolerance``.

The system is the interpolation system of the whole fit, ``[Φ P; Pᵀ 0] [λ; β] = [d; 0]``
(symmetric, indefinite with the polynomial), applied by kernel sums and never stored;
the preconditioner is the partition of unity's own two levels (the coarse fit, then the
patches' local fits of what it leaves), so each iteration costs one product with the
kernel matrix and one pass over the patches. :class:`GlobalSolve` differentiates the
solution as ``A⁻¹ b`` (the transposed system is the same system, solved again), not
through the iterations.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

__all__ = ["GlobalSolve", "fgmres", "global_solver"]

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
) -> tuple[Tensor, int, Tensor]:
    """Solve ``apply(x) = rhs`` for each column of ``rhs`` (n, S), from ``start``, by
    right-preconditioned flexible GMRES restarted every ``restart`` iterations, until
    ``|rhs − apply(x)| <= tolerance |rhs|`` in every column or ``max_iterations`` products.

    The columns run their own Arnoldi processes side by side (one ``apply`` and one
    ``precondition`` of all the columns per iteration); a column already converged, or
    all zero, takes a zero direction. The small least-squares problem of each column is
    updated by Givens rotations (elementwise arithmetic, so that a solve repeats to the
    bit, which LAPACK's least squares does not on copies of the same data). Returns the
    solution, the iterations made and the relative residual of each column (recomputed,
    not the recurrence's)."""
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
    return solution, done, torch.linalg.vector_norm(residual, dim=0) / safe_scale


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
    the relative residuals in ``owner.last_iterations_`` and ``owner.last_residual_``;
    a solve that stops short warns (``RuntimeWarning``, naming ``name``)."""

    def solver(rhs: Tensor, start: Tensor) -> Tensor:
        with torch.no_grad():
            solution, owner.last_iterations_, owner.last_residual_ = fgmres(
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
