"""POD-reduced morphs on error-driven controls: the training snapshots drive the selection."""

from __future__ import annotations

import torch

from torchmorph.mesh.norms import relative_nodal_error
from torchmorph.mesh.tetmesh import box_mesh
from torchmorph.morph import MeshMorph
from torchmorph.pod import PODReducer
from torchmorph.selection import AdaptivePlan


def _family(morph: MeshMorph):
    """Top face y = 1 bent by μ₀ x² and twisted by μ₁ sin(3x): two parameters."""

    def boundary_displacement(mu: torch.Tensor) -> torch.Tensor:
        def field(points):
            out = torch.zeros(mu.shape[0], *points.shape, dtype=points.dtype)
            out[..., 1] = mu[:, :1] * points[:, 0] ** 2
            out[..., 2] = mu[:, 1:] * torch.sin(3 * points[:, 0])
            return out

        return morph.boundary_displacement("y1", field)

    return boundary_displacement


def test_pod_of_an_adaptive_morph_trained_on_the_family():
    mesh = box_mesh(5)
    full = MeshMorph(mesh)
    family = _family(full)
    training = torch.rand(12, 2, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    snapshots = family(0.2 * training)
    tolerance = 0.02
    morph = MeshMorph(mesh, AdaptivePlan(tolerance, snapshots))
    assert morph.num_controls < morph.num_boundary
    reducer = PODReducer().fit(morph, snapshots)
    fresh = family(
        0.2 * torch.rand(5, 2, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    )
    # every training member is within the tolerance of full IDW; fresh parameter values
    # are here too (the selection bounds the training members only, not in general)
    for displacement in (*snapshots, *fresh):
        error = relative_nodal_error(mesh, reducer(displacement), full(displacement))
        assert float(error) <= tolerance * (1 + 1e-6)


def test_an_adaptive_morph_saves_and_loads_like_any_other():
    mesh = box_mesh(4)
    full = MeshMorph(mesh)
    displacement = _family(full)(torch.tensor([[0.1, 0.05]], dtype=torch.float64))[0]
    morph = MeshMorph(mesh, AdaptivePlan(0.05, displacement))
    copy = MeshMorph(mesh)  # every boundary node: other buffer sizes
    copy.load_state_dict(morph.state_dict())
    assert torch.equal(copy.control_nodes, morph.control_nodes)
    torch.testing.assert_close(copy(displacement), morph(displacement), rtol=0, atol=1e-15)
