"""Tests of near-wall stiffening (torchmorph.idw.stiffened): the two-term weights
against their literal formula, the blend's limits, exactness, batches, gradients and
the state."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchmorph.idw import IDW
from torchmorph.idw.stiffened import StiffenedIDW, stiffening_blend


def literal(controls, targets, values, power, steep, length):
    """w_k = r_k^-p + ℓ^(q-p) r_k^-q, normalised, in NumPy float64."""
    c, t, v = (np.asarray(a, dtype=np.float64) for a in (controls, targets, values))
    r = np.sqrt(((t[:, None, :] - c[None, :, :]) ** 2).sum(-1))
    w = r**-power + length ** (steep - power) * r**-steep
    w /= w.sum(1, keepdims=True)
    return w, w @ v


@pytest.fixture
def cloud():
    generator = torch.Generator().manual_seed(3)
    controls = torch.rand(30, 3, generator=generator, dtype=torch.float64)
    targets = torch.rand(70, 3, generator=generator, dtype=torch.float64)
    displacements = torch.randn(30, 3, generator=generator, dtype=torch.float64)
    return controls, targets, displacements


@pytest.mark.parametrize("mode", ["dense", "matrix_free"])
@pytest.mark.parametrize(("steep", "length"), [(6.0, 0.05), (8.0, 0.3), (5.5, 2.0)])
def test_equals_the_two_term_formula(cloud, mode, steep, length):
    controls, targets, d = cloud
    morph = StiffenedIDW(
        controls, targets, stiffening_length=length, stiffening_power=steep, mode=mode
    )
    weights, expected = literal(controls, targets, d, 4.0, steep, length)
    assert np.abs(morph(d).numpy() - expected).max() <= 1e-13 * np.abs(expected).max()
    matrix = morph.weights_matrix()
    assert np.abs(matrix.numpy() - weights).max() <= 1e-13
    assert torch.allclose(matrix.sum(1), torch.ones(70, dtype=torch.float64), atol=1e-14)


def test_limits_of_the_length_are_plain_idw(cloud):
    controls, targets, d = cloud
    short = StiffenedIDW(controls, targets, stiffening_length=1e-9, stiffening_power=8.0)
    long = StiffenedIDW(controls, targets, stiffening_length=1e9, stiffening_power=8.0)
    assert torch.allclose(short(d), IDW(controls, targets, power=4.0)(d), atol=1e-12)
    assert torch.allclose(long(d), IDW(controls, targets, power=8.0)(d), atol=1e-12)
    assert float(short.blend.min()) > 1 - 1e-12
    assert float(long.blend.max()) < 1e-12


def test_near_the_wall_the_steep_term_dominates():
    """Targets much closer than ℓ to a control follow the power-q morph."""
    wall = torch.stack(
        torch.meshgrid(torch.linspace(0, 1, 11), torch.linspace(0, 1, 11), indexing="ij"), -1
    ).reshape(-1, 2)
    controls = torch.cat([wall, torch.zeros(121, 1)], 1).double()
    heights = torch.tensor([1e-3, 1e-2, 0.3, 3.0], dtype=torch.float64)
    targets = torch.tensor([[0.5, 0.5, 0.0]], dtype=torch.float64).repeat(4, 1)  # over a node
    targets[:, 2] = heights
    blend = stiffening_blend(
        controls, targets, power=4.0, stiffening_power=8.0, stiffening_length=0.1
    )
    assert float(blend[0]) < 1e-3 and float(blend[-1]) > 0.99
    assert bool((blend[1:] >= blend[:-1]).all())  # plain IDW takes over with distance


def test_exact_at_the_controls_and_batches_equal_loops(cloud):
    controls, targets, d = cloud
    targets = torch.cat([targets, controls[:5]])
    morph = StiffenedIDW(controls, targets, stiffening_length=0.2)
    batch = torch.stack([d, 2 * d, -d])
    out = morph(batch)
    assert torch.equal(out[:, -5:], batch[:, :5])
    for k in range(3):
        assert torch.allclose(out[k], morph(batch[k]), atol=1e-15, rtol=0)
    assert float(morph.blend[-5:].abs().max()) == 0.0


def test_gradients_to_displacements_and_positions():
    generator = torch.Generator().manual_seed(1)
    controls = torch.rand(6, 2, generator=generator, dtype=torch.float64)
    targets = torch.rand(5, 2, generator=generator, dtype=torch.float64)
    d = torch.randn(6, 2, generator=generator, dtype=torch.float64, requires_grad=True)
    morph = StiffenedIDW(controls, targets, stiffening_length=0.3, stiffening_power=7.0)
    assert torch.autograd.gradcheck(lambda x: morph(x), (d,))
    moved = controls.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda c: morph(d.detach(), controls=c), (moved,))


def test_state_round_trip_and_mismatch(cloud):
    controls, targets, d = cloud
    morph = StiffenedIDW(controls, targets, stiffening_length=0.2, stiffening_power=7.0)
    state = morph.state_dict()
    twin = StiffenedIDW(
        controls + 0.01, targets, stiffening_length=0.2, stiffening_power=7.0, mode="dense"
    )
    twin.load_state_dict(state)
    assert torch.allclose(twin(d), morph(d), atol=1e-14)
    other = StiffenedIDW(controls, targets, stiffening_length=0.3, stiffening_power=7.0)
    with pytest.raises(ValueError, match="stiffening_length"):
        other.load_state_dict(state)


@pytest.mark.parametrize(
    ("keywords", "message"),
    [
        ({"stiffening_length": 0.0}, "stiffening_length must be a finite number > 0"),
        ({"stiffening_length": float("inf")}, "stiffening_length must be a finite number > 0"),
        ({"stiffening_length": 0.1, "stiffening_power": 4.0}, "larger than power"),
        ({"stiffening_length": 0.1, "power": 0.0}, "power must be"),
        ({"stiffening_length": 0.1, "mode": "tree"}, "no tree mode"),
    ],
)
def test_bad_arguments(cloud, keywords, message):
    controls, targets, _ = cloud
    with pytest.raises(ValueError, match=message):
        StiffenedIDW(controls, targets, **keywords)
