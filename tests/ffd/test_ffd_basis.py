"""The one-dimensional bases of FFD: Bernstein polynomials against their closed form,
clamped uniform B-splines against SciPy's design matrix, and the properties the lattice
relies on (partition of unity, linear precision at the Greville abscissae)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.interpolate import BSpline
from torch.autograd import gradcheck

from torchmorph.ffd import (
    bernstein_basis,
    bspline_basis,
    clamped_uniform_knots,
    control_coordinates,
    greville_abscissae,
)

F64 = torch.float64


def coordinates(count: int = 57, seed: int = 0) -> torch.Tensor:
    """Random points of [0, 1], the ends and every knot of the lattices tested."""
    generator = torch.Generator().manual_seed(seed)
    knots = torch.tensor([i / d for d in range(1, 8) for i in range(d + 1)], dtype=F64)
    return torch.cat([torch.rand(count, generator=generator, dtype=F64), knots])


@pytest.mark.parametrize("count", [1, 2, 3, 5, 10])
def test_bernstein_equals_its_closed_form(count):
    s = coordinates()
    degree = count - 1
    reference = np.array(
        [
            [math.comb(degree, i) * x**i * (1 - x) ** (degree - i) for i in range(count)]
            for x in s.tolist()
        ]
    )
    torch.testing.assert_close(bernstein_basis(s, count), torch.from_numpy(reference))


@pytest.mark.parametrize(
    ("count", "degree"), [(2, 1), (6, 1), (3, 2), (7, 2), (4, 3), (10, 3), (9, 5)]
)
def test_bspline_equals_scipy_design_matrix(count, degree):
    s = coordinates()
    knots = np.array(clamped_uniform_knots(count, degree))
    reference = BSpline.design_matrix(s.numpy(), knots, degree).toarray()
    torch.testing.assert_close(
        bspline_basis(s, count, degree), torch.from_numpy(reference), rtol=0, atol=1e-14
    )


def test_clamped_uniform_knots():
    assert clamped_uniform_knots(4, 3) == [0.0] * 4 + [1.0] * 4
    assert clamped_uniform_knots(6, 2) == [0.0, 0.0, 0.0, 0.25, 0.5, 0.75, 1.0, 1.0, 1.0]


@pytest.mark.parametrize("count", [2, 4, 7])
def test_bspline_of_a_single_segment_is_bernstein(count):
    s = coordinates()
    torch.testing.assert_close(
        bspline_basis(s, count, count - 1), bernstein_basis(s, count), rtol=0, atol=1e-15
    )


@pytest.mark.parametrize(
    "evaluate",
    [
        lambda s: bernstein_basis(s, 8),
        lambda s: bspline_basis(s, 8, 3),
        lambda s: bspline_basis(s, 5, 2),
    ],
)
def test_partition_of_unity_and_non_negative(evaluate):
    values = evaluate(coordinates())
    assert (values >= 0).all()
    torch.testing.assert_close(
        values.sum(1), torch.ones(values.shape[0], dtype=F64), rtol=0, atol=1e-15
    )


def test_bspline_support_is_local():
    values = bspline_basis(coordinates(), 10, 3)
    assert ((values > 0).sum(1) <= 4).all()


@pytest.mark.parametrize(("count", "degree"), [(5, 4), (6, 3), (9, 3), (7, 2), (4, 1)])
def test_linear_precision_at_greville_abscissae(count, degree):
    s = coordinates()
    greville = torch.tensor(greville_abscissae(count, degree), dtype=F64)
    torch.testing.assert_close(bspline_basis(s, count, degree) @ greville, s, rtol=0, atol=1e-15)


def test_control_coordinates():
    assert control_coordinates(5, "bernstein") == [0.0, 0.25, 0.5, 0.75, 1.0]
    np.testing.assert_allclose(greville_abscissae(5, 4), [0.0, 0.25, 0.5, 0.75, 1.0])
    np.testing.assert_allclose(
        control_coordinates(6, "bspline", 3), [0.0, 1 / 9, 1 / 3, 2 / 3, 8 / 9, 1.0]
    )


def test_ends_interpolate():
    ends = torch.tensor([0.0, 1.0], dtype=F64)
    for values in (bernstein_basis(ends, 6), bspline_basis(ends, 9, 3)):
        expected = torch.zeros_like(values)
        expected[0, 0] = expected[1, -1] = 1.0
        assert torch.equal(values, expected)


@pytest.mark.parametrize(
    "evaluate",
    [
        lambda s: bernstein_basis(s, 6),
        lambda s: bspline_basis(s, 7, 3),
        lambda s: bspline_basis(s, 6, 2),
    ],
)
def test_bases_are_differentiable_in_s(evaluate):
    s = torch.tensor([0.0, 0.013, 0.25, 0.4, 0.61, 0.999, 1.0], dtype=F64, requires_grad=True)
    assert gradcheck(evaluate, (s,))
    (gradient,) = torch.autograd.grad(evaluate(s)[:, 1].sum(), s)
    assert torch.isfinite(gradient).all() and (gradient != 0).any()


def test_float32_matches_float64():
    s = coordinates()
    torch.testing.assert_close(
        bspline_basis(s.float(), 9, 3).double(), bspline_basis(s, 9, 3), rtol=0, atol=1e-6
    )
    torch.testing.assert_close(
        bernstein_basis(s.float(), 9).double(), bernstein_basis(s, 9), rtol=0, atol=1e-6
    )


def test_errors_name_the_argument():
    s = coordinates()
    with pytest.raises(
        ValueError, match=r"count must be an integer >= 4 \(control points for degree 3\), got 3"
    ):
        bspline_basis(s, 3, 3)
    with pytest.raises(ValueError, match="degree must be an integer >= 1"):
        bspline_basis(s, 3, 0)
    with pytest.raises(ValueError, match="count must be an integer >= 1"):
        bernstein_basis(s, 0)
    with pytest.raises(
        ValueError, match=r"s must be a 1-D floating-point tensor, got shape \(3, 1\)"
    ):
        bernstein_basis(torch.zeros(3, 1), 3)
    with pytest.raises(TypeError, match="s must be a torch.Tensor"):
        bernstein_basis([0.5], 3)
