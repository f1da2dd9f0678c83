"""torch.func and torch.compile through the morphs: vmap over μ, jacrev / jacfwd with
respect to μ, and compiled forwards with no graph break (fullgraph=True).

A user's family maps one parameter value μ (a scalar, or a vector of P parameters)
to a displacement; ``vmap(lambda m: morph(family(m)))(mus)`` must equal the batched
forward ``morph(family(mus))``, and the Jacobians of the morphed coordinates with
respect to μ must equal central finite differences (float64, relative error <= 1e-6).
"""

from __future__ import annotations

import importlib.util
import shutil

import pytest
import torch
from _families import F64, KINDS, scalar_family, vector_family
from _families import build as build_morph
from torch.func import jacfwd, jacrev, vmap


def build(kind: str):
    """(morph, reference points of its inputs, reference points of its outputs)."""
    return build_morph(kind, idw_seed=5, num_controls=30, num_targets=40)


def relative_error(value: torch.Tensor, reference: torch.Tensor) -> float:
    return float((value - reference).norm() / reference.norm())


def central_differences(function, mu: torch.Tensor, step: float = 1e-5) -> torch.Tensor:
    """Jacobian d function / d mu by central differences; shape (*out, *mu.shape)."""
    flat = mu.detach().reshape(-1)
    columns = []
    for index in range(flat.numel()):
        plus, minus = flat.clone(), flat.clone()
        plus[index] += step
        minus[index] -= step
        columns.append(
            (function(plus.reshape(mu.shape)) - function(minus.reshape(mu.shape))) / (2 * step)
        )
    return torch.stack(columns, -1).reshape(*columns[0].shape, *mu.shape)


# --------------------------------------------------------------------------------------
# vmap
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", KINDS)
def test_vmap_over_scalar_mu_equals_batched_forward(kind):
    morph, inputs, _ = build(kind)
    family = scalar_family(inputs)
    mus = torch.linspace(-0.3, 0.4, 6, dtype=F64)
    with torch.no_grad():
        batched = morph(family(mus))
        mapped = vmap(lambda mu: morph(family(mu)))(mus)
    torch.testing.assert_close(mapped, batched, rtol=1e-13, atol=1e-15)


@pytest.mark.parametrize("kind", ("idw-dense", "morph-dense", "morph-matrix-free", "pod"))
def test_vmap_over_parameter_vectors_equals_batched_forward(kind):
    morph, inputs, _ = build(kind)
    family = vector_family(inputs)
    mus = torch.rand(5, 3, generator=torch.Generator().manual_seed(2), dtype=F64)
    mapped = vmap(lambda mu: morph(family(mu)))(mus)
    torch.testing.assert_close(mapped, morph(family(mus)), rtol=1e-13, atol=1e-15)


def test_vmap_keeps_the_finiteness_check():
    morph, inputs, _ = build("morph-dense")
    family = scalar_family(inputs)
    mus = torch.tensor([0.1, float("nan"), 0.2], dtype=F64)
    with pytest.raises(ValueError, match=r"boundary_displacement holds \d+ NaN"):
        morph(family(mus))
    with pytest.raises(ValueError, match=r"boundary_displacement holds \d+ NaN"):
        vmap(lambda mu: morph(family(mu)))(mus)


# --------------------------------------------------------------------------------------
# Jacobians with respect to μ
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("parameters", ("scalar", "vector"))
def test_jacobians_of_morphed_coordinates_match_finite_differences(kind, parameters):
    morph, inputs, outputs = build(kind)
    if parameters == "scalar":
        family, mu = scalar_family(inputs), torch.tensor(0.15, dtype=F64)
    else:
        family, mu = vector_family(inputs), torch.tensor([0.2, -0.1, 0.3], dtype=F64)

    def coordinates(value: torch.Tensor) -> torch.Tensor:
        return outputs + morph(family(value))

    numeric = central_differences(coordinates, mu)
    reverse = jacrev(coordinates)(mu)
    forward = jacfwd(coordinates)(mu)
    assert reverse.shape == forward.shape == (*outputs.shape, *mu.shape)
    assert relative_error(reverse, numeric) <= 1e-6
    assert relative_error(forward, numeric) <= 1e-6
    torch.testing.assert_close(forward, reverse, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("kind", ("morph-dense", "pod"))
def test_vmap_of_jacobians_equals_the_loop(kind):
    morph, inputs, _ = build(kind)
    family = vector_family(inputs)
    mus = torch.rand(4, 3, generator=torch.Generator().manual_seed(3), dtype=F64)
    jacobian = jacrev(lambda mu: morph(family(mu)))
    batched = vmap(jacobian)(mus)
    looped = torch.stack([jacobian(mu) for mu in mus])
    torch.testing.assert_close(batched, looped, rtol=1e-12, atol=1e-14)


def test_jacobian_agrees_with_autograd_of_a_batch():
    """The rows of jacrev over a scalar μ equal autograd's gradient of each output."""
    morph, inputs, outputs = build("morph-dense")
    family = scalar_family(inputs)
    mu = torch.tensor(0.25, dtype=F64)
    jacobian = jacrev(lambda value: morph(family(value)))(mu)
    probe = mu.clone().requires_grad_(True)
    weights = torch.linspace(-1.0, 1.0, outputs.numel(), dtype=F64).reshape(outputs.shape)
    (gradient,) = torch.autograd.grad((morph(family(probe)) * weights).sum(), probe)
    torch.testing.assert_close(gradient, (jacobian * weights).sum(), rtol=1e-12, atol=1e-14)


# --------------------------------------------------------------------------------------
# torch.compile
# --------------------------------------------------------------------------------------


def _inductor_available() -> bool:
    if importlib.util.find_spec("torch._inductor") is None:
        return False
    return any(shutil.which(name) for name in ("g++", "c++", "clang++"))


@pytest.fixture
def fresh_dynamo():
    torch._dynamo.reset()
    yield
    torch._dynamo.reset()


COMPILED = ("idw-dense", "morph-dense", "morph-selective", "pod")


@pytest.mark.parametrize("kind", COMPILED)
def test_compiled_forward_has_no_graph_break(kind, fresh_dynamo):
    """fullgraph=True raises on any graph break; aot_eager needs no C++ compiler."""
    morph, inputs, _ = build(kind)
    family = scalar_family(inputs)
    compiled = torch.compile(morph, fullgraph=True, backend="aot_eager")
    mus = torch.linspace(0.0, 0.3, 4, dtype=F64)
    with torch.no_grad():
        torch.testing.assert_close(
            compiled(family(mus)), morph(family(mus)), rtol=1e-13, atol=1e-15
        )
        torch.testing.assert_close(
            compiled(family(mus[1])), morph(family(mus[1])), rtol=1e-13, atol=1e-15
        )
    # and through the compiled graph, gradients to μ are autograd's
    mu = torch.tensor(0.2, dtype=F64, requires_grad=True)
    (compiled_gradient,) = torch.autograd.grad(compiled(family(mu)).square().sum(), mu)
    (eager_gradient,) = torch.autograd.grad(morph(family(mu)).square().sum(), mu)
    torch.testing.assert_close(compiled_gradient, eager_gradient, rtol=1e-12, atol=1e-15)


def test_compiled_forward_with_moved_points_has_no_graph_break(fresh_dynamo):
    morph, inputs, outputs = build("morph-dense")
    boundary = scalar_family(inputs)(torch.tensor(0.2, dtype=F64))
    moved = outputs + 0.01 * torch.sin(3.0 * outputs)
    compiled = torch.compile(
        lambda points: morph(boundary, points=points), fullgraph=True, backend="aot_eager"
    )
    torch.testing.assert_close(
        compiled(moved), morph(boundary, points=moved), rtol=1e-13, atol=1e-15
    )


@pytest.mark.slow
@pytest.mark.skipif(not _inductor_available(), reason="needs inductor and a C++ compiler")
@pytest.mark.parametrize("kind", ("idw-dense", "morph-dense", "pod"))
def test_inductor_compiled_forward_equals_eager(kind, fresh_dynamo):
    morph, inputs, _ = build(kind)
    family = scalar_family(inputs)
    compiled = torch.compile(morph, fullgraph=True)
    mus = torch.linspace(0.0, 0.3, 8, dtype=F64)
    with torch.no_grad():
        torch.testing.assert_close(
            compiled(family(mus)), morph(family(mus)), rtol=1e-12, atol=1e-14
        )


# --------------------------------------------------------------------------------------
# GPU
# --------------------------------------------------------------------------------------


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("kind", ("idw-dense", "idw-matrix-free", "morph-dense", "pod"))
def test_vmap_and_jacobians_on_cuda_match_cpu(kind):
    morph, inputs, _ = build(kind)
    family = scalar_family(inputs)
    mus = torch.linspace(-0.2, 0.3, 5, dtype=F64)
    expected = vmap(lambda mu: morph(family(mu)))(mus)
    expected_jacobian = jacfwd(lambda mu: morph(family(mu)))(mus[2])
    on_gpu = morph.to("cuda")
    gpu_family = scalar_family(inputs.to("cuda"))
    mus = mus.to("cuda")
    got = vmap(lambda mu: on_gpu(gpu_family(mu)))(mus)
    got_jacobian = jacfwd(lambda mu: on_gpu(gpu_family(mu)))(mus[2])
    torch.testing.assert_close(got.cpu(), expected, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(got_jacobian.cpu(), expected_jacobian, rtol=1e-10, atol=1e-12)
