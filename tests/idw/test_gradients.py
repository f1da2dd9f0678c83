"""Gradients through the morphs, checked against central finite differences (float64,
relative error <= 1e-6) and ``torch.autograd.gradcheck``.

Covered here (tests/idw/test_idw.py, tests/test_morph.py and tests/pod/test_pod.py hold the
gradients with respect to displacements and IDW positions):

- a parametrized family μ -> boundary displacement through IDW (dense and
  matrix-free), the Algorithm 2 morph (dense, matrix-free, selective) and the POD
  online phase, for one parameter, a vector of parameters and a batch of them;
- moved reference points through ``MeshMorph.forward(points=)`` in both IDW modes;
- the validity barrier composed with the morph, and its gradient on inverted tets.
"""

from __future__ import annotations

import pytest
import torch
from _families import F64, KINDS, scalar_family, vector_family
from _families import build as build_morph
from torch.autograd import gradcheck

from torchmorph.mesh import TetMesh, box_mesh
from torchmorph.mesh.quality import signed_volumes, validity_barrier
from torchmorph.morph import MeshMorph


def build(kind: str):
    """(morph, reference points of its inputs, reference points of its outputs)."""
    return build_morph(kind, idw_seed=11, num_controls=25, num_targets=30)


def output_weights(shape, seed: int = 0) -> torch.Tensor:
    return torch.randn(shape, generator=torch.Generator().manual_seed(seed), dtype=F64)


def finite_difference_gradient(objective, value: torch.Tensor, step: float = 1e-5):
    """Central differences of a scalar ``objective`` at ``value`` (any shape)."""
    flat = value.detach().reshape(-1)
    gradient = torch.empty_like(flat)
    for index in range(flat.numel()):
        plus, minus = flat.clone(), flat.clone()
        plus[index] += step
        minus[index] -= step
        gradient[index] = (
            objective(plus.reshape(value.shape)) - objective(minus.reshape(value.shape))
        ) / (2 * step)
    return gradient.reshape(value.shape)


def autograd_gradient(objective, value: torch.Tensor) -> torch.Tensor:
    value = value.detach().clone().requires_grad_(True)
    (gradient,) = torch.autograd.grad(objective(value), value)
    return gradient


def relative_error(value: torch.Tensor, reference: torch.Tensor) -> float:
    return float((value - reference).norm() / reference.norm())


# --------------------------------------------------------------------------------------
# parametrized families through every morph
# --------------------------------------------------------------------------------------

PARAMETERS = {
    "scalar": (scalar_family, torch.tensor(0.2, dtype=F64)),
    "vector": (vector_family, torch.tensor([0.3, -0.2, 0.4], dtype=F64)),
    "batch": (vector_family, torch.tensor([[0.3, -0.2, 0.4], [0.1, 0.2, -0.5]], dtype=F64)),
}


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("parameters", tuple(PARAMETERS))
def test_gradient_with_respect_to_mu_matches_finite_differences(kind, parameters):
    morph, inputs, outputs = build(kind)
    make_family, mu = PARAMETERS[parameters]
    family = make_family(inputs)
    batch = mu.shape[:1] if parameters == "batch" else ()
    weights = output_weights((*batch, *outputs.shape))

    def objective(value: torch.Tensor) -> torch.Tensor:
        return (weights * morph(family(value))).sum()

    assert (
        relative_error(autograd_gradient(objective, mu), finite_difference_gradient(objective, mu))
        <= 1e-6
    )


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("parameters", tuple(PARAMETERS))
def test_gradcheck_with_respect_to_mu(kind, parameters):
    morph, inputs, _ = build(kind)
    make_family, mu = PARAMETERS[parameters]
    family = make_family(inputs)
    # a batch (many outputs) and matrix-free backward passes (which recompute the
    # tiles) take the fast check: one random projection of the Jacobian
    assert gradcheck(
        lambda value: morph(family(value)),
        (mu.clone().requires_grad_(True),),
        fast_mode=parameters == "batch" or "matrix-free" in kind,
    )


def test_gradcheck_of_pod_morph_parameters_with_a_vector_family():
    reducer, _, _ = build("pod")
    for name in ("vector", "batch"):
        mu = PARAMETERS[name][1].clone().requires_grad_(True)
        assert gradcheck(reducer.morph_parameters, (mu,), fast_mode=name == "batch")


def test_batched_gradient_is_the_sum_of_the_single_ones():
    morph, inputs, outputs = build("morph-dense")
    family = vector_family(inputs)
    mus = PARAMETERS["batch"][1]
    weights = output_weights(outputs.shape)
    batched = autograd_gradient(lambda value: (weights * morph(family(value))).sum(), mus)
    for row, mu in enumerate(mus):
        single = autograd_gradient(lambda value: (weights * morph(family(value))).sum(), mu)
        torch.testing.assert_close(batched[row], single, rtol=1e-12, atol=1e-14)


# --------------------------------------------------------------------------------------
# moved reference points through the mesh morph
# --------------------------------------------------------------------------------------


def small_morph(mode: str) -> tuple[MeshMorph, torch.Tensor]:
    mesh = box_mesh(2)
    morph = MeshMorph(mesh, mode=mode, block_bytes=1000)
    boundary = scalar_family(morph.boundary_points)(torch.tensor(0.3, dtype=F64))
    return morph, boundary


@pytest.mark.parametrize("mode", ("dense", "matrix_free"))
def test_gradcheck_with_respect_to_points(mode):
    morph, boundary = small_morph(mode)
    points = morph.points.clone().requires_grad_(True)
    assert gradcheck(
        lambda moved: morph(boundary, points=moved), (points,), fast_mode=mode == "matrix_free"
    )


@pytest.mark.parametrize("mode", ("dense", "matrix_free"))
def test_gradient_with_respect_to_points_matches_finite_differences(mode):
    morph, boundary = small_morph(mode)
    weights = output_weights(morph.points.shape, seed=4)

    def objective(points: torch.Tensor) -> torch.Tensor:
        return (weights * morph(boundary, points=points)).sum()

    assert (
        relative_error(
            autograd_gradient(objective, morph.points),
            finite_difference_gradient(objective, morph.points),
        )
        <= 1e-6
    )


def test_point_gradients_agree_between_dense_and_matrix_free():
    dense, boundary = small_morph("dense")
    free, _ = small_morph("matrix_free")
    weights = output_weights(dense.points.shape, seed=5)
    gradients = [
        autograd_gradient(lambda p, m=m: (weights * m(boundary, points=p)).sum(), dense.points)
        for m in (dense, free)
    ]
    torch.testing.assert_close(gradients[1], gradients[0], rtol=1e-10, atol=1e-13)


@pytest.mark.parametrize("mode", ("dense", "matrix_free"))
def test_gradcheck_with_respect_to_mu_and_points_together(mode):
    morph, _ = small_morph(mode)
    family = scalar_family(morph.boundary_points)
    mu = torch.tensor(0.3, dtype=F64, requires_grad=True)
    points = morph.points.clone().requires_grad_(True)
    assert gradcheck(lambda value, moved: morph(family(value), points=moved), (mu, points))


# --------------------------------------------------------------------------------------
# the validity barrier as a penalty on the morph
# --------------------------------------------------------------------------------------


def test_barrier_of_the_morph_matches_finite_differences():
    morph, inputs, _ = build("morph-dense")
    mesh = morph.reference_mesh()
    family = vector_family(inputs)
    mu = torch.tensor([-1.5, 1.2, 0.4], dtype=F64)  # squeezes the cube: penalty active

    def objective(value: torch.Tensor) -> torch.Tensor:
        return validity_barrier(mesh, morph(family(value)), threshold=0.9)

    assert float(objective(mu)) > 0
    assert (
        relative_error(autograd_gradient(objective, mu), finite_difference_gradient(objective, mu))
        <= 1e-6
    )
    assert gradcheck(objective, (mu.clone().requires_grad_(True),))


def test_barrier_gradient_is_finite_on_inverted_tets_and_pushes_them_back():
    points = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=F64)
    mesh = TetMesh(points, torch.tensor([[0, 1, 2, 3]]))
    displacement = torch.zeros(4, 3, dtype=F64)
    displacement[3, 2] = -1.5  # vertex 3 through the opposite face: volume ratio -0.5
    displacement.requires_grad_(True)
    penalty = validity_barrier(mesh, displacement)
    (gradient,) = torch.autograd.grad(penalty, displacement)
    assert bool(torch.isfinite(gradient).all()) and float(gradient.abs().max()) > 0
    assert float(gradient[3, 2]) < 0  # descent raises vertex 3: the volume grows
    stepped = displacement.detach() - 0.01 * gradient
    before = signed_volumes(points + displacement.detach(), mesh.tets)
    after = signed_volumes(points + stepped, mesh.tets)
    assert float(after) > float(before)
    assert float(validity_barrier(mesh, stepped)) < float(penalty.detach())


# --------------------------------------------------------------------------------------
# GPU
# --------------------------------------------------------------------------------------


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("kind", KINDS)
def test_gradients_on_cuda_match_cpu(kind):
    morph, inputs, outputs = build(kind)
    family = vector_family(inputs)
    mu = PARAMETERS["vector"][1]
    weights = output_weights(outputs.shape)
    expected = autograd_gradient(lambda value: (weights * morph(family(value))).sum(), mu)
    on_gpu = morph.to("cuda")
    gpu_family, gpu_weights = vector_family(inputs.to("cuda")), weights.to("cuda")
    got = autograd_gradient(
        lambda value: (gpu_weights * on_gpu(gpu_family(value))).sum(), mu.to("cuda")
    )
    torch.testing.assert_close(got.cpu(), expected, rtol=1e-10, atol=1e-12)
