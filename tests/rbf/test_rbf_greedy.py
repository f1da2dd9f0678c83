"""The RBF error oracle of the greedy selection loop: its bordered factor equals a
Cholesky factorisation from scratch, its interpolant equals the RBF refitted on the
selected controls (and scipy's), prefixes and changed tails are followed, and the loop
reaches its tolerance with it."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.interpolate import RBFInterpolator

from torchmorph.rbf import RBF
from torchmorph.rbf.greedy import BLOCK_COLUMNS, RBFErrorOracle
from torchmorph.rbf.kernels import kernel_matrix
from torchmorph.selection.greedy import ErrorOracle, greedy_selection

pytestmark = pytest.mark.usefixtures("one_thread")

CASES = [("thin_plate_spline", None, 1), ("cubic", None, 1), ("gaussian", 3.0, -1)]


def candidates(count=120, seed=0):
    return torch.from_numpy(np.random.default_rng(seed).uniform(size=(count, 3)))


def family(points, members=3):
    x, y, z = points.T
    return torch.stack(
        [
            0.1 * torch.stack([torch.sin(3 * x + k), y * z, torch.cos(2 * x) * k], 1)
            for k in range(members)
        ]
    )


def selection(oracle, extra):
    rest = [i for i in extra if i not in oracle.anchors.tolist()]
    return torch.cat([oracle.anchors, torch.tensor(rest, dtype=torch.int64)])


@pytest.mark.parametrize(("kernel", "epsilon", "degree"), CASES)
def test_the_interpolant_equals_a_refit_from_scratch(kernel, epsilon, degree):
    points = candidates()
    fields = family(points)
    oracle = RBFErrorOracle(points, fields, kernel=kernel, epsilon=epsilon, degree=degree)
    assert isinstance(oracle, ErrorOracle)
    long = selection(oracle, [5, 17, 40, 99, 110, 63, 7, 8, 9, 21])
    short = long[: oracle.anchors.numel() + 3]
    changed = torch.cat([short, torch.tensor([100, 101, 102])])
    for selected in (long, short, changed):  # a prefix, then another tail
        refit = torch.stack(
            [
                RBF(points[selected], points, kernel=kernel, epsilon=epsilon, degree=degree)(
                    member[selected]
                )
                for member in fields
            ]
        )
        torch.testing.assert_close(oracle.interpolate(selected), refit, rtol=0, atol=1e-12)
    scipy = RBFInterpolator(
        points[changed].numpy(),
        fields[0][changed].numpy(),
        kernel=kernel,
        epsilon=epsilon or 1.0,
        degree=degree,
    )(points.numpy())
    np.testing.assert_allclose(oracle.interpolate(changed)[0].numpy(), scipy, rtol=0, atol=1e-12)


@pytest.mark.parametrize(("kernel", "epsilon", "degree"), CASES)
def test_the_bordered_factor_equals_cholesky_from_scratch(kernel, epsilon, degree):
    points = candidates(60)
    oracle = RBFErrorOracle(points, family(points), kernel=kernel, epsilon=epsilon, degree=degree)
    selected = selection(oracle, [3, 9, 27, 31, 44, 50, 12, *range(13, 27), *range(32, 40)])
    anchors_count = oracle.anchors.numel()
    assert selected.numel() - 3 - (anchors_count + 2) > BLOCK_COLUMNS
    oracle.factor(selected[: anchors_count + 2])  # then grown by bordered updates:
    oracle.factor(selected[:-3])  # a block of more than BLOCK_COLUMNS controls at once
    factor = oracle.factor(selected)  # and a few, one packed solve each
    anchors, rest = selected[: oracle.anchors.numel()], selected[oracle.anchors.numel() :]
    scale = epsilon or 1.0
    phi = kernel_matrix(points[rest], points[rest], kernel, scale)
    if anchors.numel():  # the Schur complement of the anchors' saddle block, directly
        from torchmorph.rbf.kernels import monomial_powers, polynomial_matrix, polynomial_scaling

        shift, poly_scale = polynomial_scaling(points)
        poly = polynomial_matrix(points, monomial_powers(3, degree), shift, poly_scale)
        border = torch.cat([kernel_matrix(points, points[anchors], kernel, scale), poly], 1)
        block = torch.cat(
            [border[anchors], torch.cat([poly[anchors].T, torch.zeros(4, 4, dtype=poly.dtype)], 1)]
        )
        phi = phi - border[rest] @ torch.linalg.solve(block, border[rest].T)
    torch.testing.assert_close(factor, torch.linalg.cholesky(phi), rtol=0, atol=1e-12)


def test_errors_and_scores():
    points = candidates()
    fields = family(points)
    oracle = RBFErrorOracle(points, fields)
    selected = selection(oracle, [5, 17, 40, 99])
    errors, scores = oracle.scores(selected)
    moved = oracle.interpolate(selected)
    expected = ((moved - fields).norm(dim=-1).amax(dim=1)) / fields.norm(dim=-1).amax(dim=1)
    torch.testing.assert_close(errors, expected, rtol=1e-12, atol=0)
    torch.testing.assert_close(oracle.errors(selected), errors, rtol=0, atol=0)
    assert scores.shape == (120,) and float(scores[selected].abs().max()) < 1e-10
    assert int(scores.argmax()) not in selected.tolist()


def test_the_greedy_loop_reaches_its_tolerance():
    points = candidates(200)
    fields = family(points, members=2)
    oracle = RBFErrorOracle(points, fields)
    result = greedy_selection(oracle, tolerance=1e-3, initial=oracle.anchors)
    assert result.converged and result.reason == "tolerance"
    assert result.indices[:4].tolist() == oracle.anchors.tolist()
    selected = result.indices
    refit = torch.stack([RBF(points[selected], points)(member[selected]) for member in fields])
    error = ((refit - fields).norm(dim=-1).amax(dim=1) / fields.norm(dim=-1).amax(dim=1)).max()
    assert float(error) <= 1e-3
    assert abs(float(error) - result.error) < 1e-12
    budget = greedy_selection(oracle, tolerance=1e-9, max_controls=30, initial=oracle.anchors)
    assert budget.reason == "budget" and budget.indices.numel() == 30


def test_oracle_arguments_are_named():
    points = candidates(20)
    with pytest.raises(
        ValueError, match="^degree must be at least 1 for kernel='thin_plate_spline'"
    ):
        RBFErrorOracle(points, family(points), degree=0)
    with pytest.raises(
        ValueError, match=r"^displacements must have shape \(20, 3\) or \(F, 20, 3\)"
    ):
        RBFErrorOracle(points, torch.zeros(19, 3, dtype=torch.float64))
    oracle = RBFErrorOracle(points, family(points))
    with pytest.raises(ValueError, match="^selected must start with the oracle's 4 anchors"):
        oracle.errors(
            torch.tensor([0, 1, 2, 3, 4])
            if oracle.anchors.tolist() != [0, 1, 2, 3]
            else torch.tensor([5])
        )
