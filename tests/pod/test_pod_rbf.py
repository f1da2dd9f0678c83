"""POD reduction (Algorithm 3) of RBF snapshots: a MeshMorph(method="rbf") in the offline
phase, its reduced morph equal to the full one on the training data with every mode kept."""

from __future__ import annotations

import pytest
import torch

from torchmorph.mesh import box_mesh
from torchmorph.morph import MeshMorph
from torchmorph.pod import PODReducer
from torchmorph.selection import SelectionPlan

pytestmark = pytest.mark.usefixtures("one_thread")

F64 = torch.float64
FACES = ("x0", "x1", "y0", "y1", "z0", "z1")


def relative(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).norm() / b.norm())


def top_family(morph: MeshMorph):
    """The top face z = 1 bent by μ₀ x², lifted by μ₁ sin(3y) and sheared by μ₂ x y."""

    def family(mu: torch.Tensor) -> torch.Tensor:
        def field(points):
            x, y = points[:, 0], points[:, 1]
            out = torch.zeros(mu.shape[0], *points.shape, dtype=points.dtype)
            out[..., 2] = mu[:, :1] * x**2 + mu[:, 1:2] * torch.sin(3 * y)
            out[..., 0] = mu[:, 2:] * x * y
            return out

        return morph.boundary_displacement("z1", field)

    return family


@pytest.fixture(scope="module")
def mesh():
    return box_mesh(4)


@pytest.mark.parametrize("online", ["projection", "paper"])
@pytest.mark.parametrize("mode", ["dense", "matrix_free"])
def test_every_mode_kept_reproduces_the_rbf_morph(mesh, mode, online):
    plan = SelectionPlan(dict.fromkeys(FACES, 0.45), enrich=["z1"])
    morph = MeshMorph(
        mesh, plan, method="rbf", mode=mode, generator=torch.Generator().manual_seed(0)
    )
    assert morph.num_controls < morph.num_boundary
    family = top_family(morph)
    parameters = torch.rand(6, 3, generator=torch.Generator().manual_seed(1), dtype=F64)
    reducer = PODReducer(num_modes=3, online=online).fit(
        morph, family=family, parameters=parameters
    )
    training = family(parameters)
    full = morph(training)
    reduced = reducer(training)
    assert relative(reduced, full) < 1e-12
    assert torch.equal(reduced[:, morph.boundary_nodes], training)
    # the family is linear in μ: three modes span it, fresh values included
    fresh = torch.randn(4, 3, generator=torch.Generator().manual_seed(2), dtype=F64)
    assert relative(reducer.morph_parameters(fresh), morph(family(fresh))) < 1e-12
    assert float(reducer.relative_error(family(fresh)).max()) < 1e-12


def test_fewer_modes_are_the_optimal_projection(mesh):
    # with two of three modes, the reduced interior is the projection of the full one on
    # the POD space: its error is the discarded singular value's share
    morph = MeshMorph(mesh, method="rbf")
    family = top_family(morph)
    parameters = torch.rand(8, 3, generator=torch.Generator().manual_seed(3), dtype=F64)
    reducer = PODReducer(num_modes=2).fit(morph, family=family, parameters=parameters)
    training = family(parameters)
    interior = morph.interior_nodes
    error = reducer(training)[:, interior] - morph(training)[:, interior]
    discarded = reducer.singular_values_[2:]
    torch.testing.assert_close(error.norm(), discarded.norm(), rtol=1e-10, atol=0)
