"""Flexible GMRES (:func:`torchmorph.rbf.refine.fgmres`): the solution of a dense system
against LAPACK's, several columns at once (one already solved), a preconditioner that
changes from step to step, restarts, and a solve that repeats to the bit."""

from __future__ import annotations

import torch

from torchmorph.rbf.refine import fgmres

F64 = torch.float64


def system(size: int = 120, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    matrix = torch.randn(size, size, dtype=F64, generator=generator) / size**0.5
    matrix += 3 * torch.eye(size, dtype=F64)
    rhs = torch.randn(size, 3, dtype=F64, generator=generator)
    return matrix, rhs


def test_the_solution_of_a_nonsymmetric_system_column_by_column():
    matrix, rhs = system()
    rhs[:, 1] = 0  # an all-zero column stays zero
    solution, iterations, residual, _ = fgmres(
        lambda x: matrix @ x, lambda x: x, rhs, torch.zeros_like(rhs),
        tolerance=1e-12, max_iterations=200,
    )  # fmt: skip
    torch.testing.assert_close(solution, torch.linalg.solve(matrix, rhs), rtol=0, atol=1e-10)
    assert 1 <= iterations < 120
    assert (residual <= 1e-12).all() and residual[1] == 0


def test_restarts_and_a_changing_preconditioner_still_converge():
    matrix, rhs = system(seed=1)
    diagonal = matrix.diagonal()
    calls = []

    def precondition(vector):  # Jacobi on even calls, nothing on odd ones: not one operator
        calls.append(1)
        return vector / diagonal[:, None] if len(calls) % 2 else vector

    solution, iterations, residual, _ = fgmres(
        lambda x: matrix @ x, precondition, rhs, torch.zeros_like(rhs),
        tolerance=1e-11, max_iterations=300, restart=5,
    )  # fmt: skip
    assert iterations > 5  # at least one restart
    assert (residual <= 1e-11).all()
    torch.testing.assert_close(solution, torch.linalg.solve(matrix, rhs), rtol=0, atol=1e-9)


def test_a_stopped_solve_reports_its_residual_and_repeats_to_the_bit():
    matrix, rhs = system(seed=2)

    def run():
        return fgmres(
            lambda x: matrix @ x, lambda x: x, rhs.clone(), torch.zeros_like(rhs),
            tolerance=1e-14, max_iterations=3,
        )  # fmt: skip

    runs = [run() for _ in range(3)]
    solution, iterations, residual, vector = runs[0]
    assert iterations == 3
    torch.testing.assert_close(vector, rhs - matrix @ solution, rtol=0, atol=1e-13)
    true = torch.linalg.vector_norm(rhs - matrix @ solution, dim=0) / rhs.norm(dim=0)
    torch.testing.assert_close(residual, true, rtol=1e-12, atol=0)
    assert (residual > 1e-14).all()
    for other, *_ in runs[1:]:
        assert torch.equal(other, solution)


def test_a_start_that_solves_it_takes_no_iteration():
    matrix, rhs = system(seed=3)
    exact = torch.linalg.solve(matrix, rhs)
    _, iterations, residual, _ = fgmres(
        lambda x: matrix @ x, lambda x: x, matrix @ exact, exact,
        tolerance=1e-8, max_iterations=10,
    )  # fmt: skip
    assert iterations == 0 and (residual <= 1e-8).all()
