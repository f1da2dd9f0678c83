"""The Algorithm 2 morph of a tetrahedral mesh (the paper's section 2)."""

from __future__ import annotations

import io

import numpy as np
import pytest
import torch
from torch.autograd import gradcheck

from torchmorph import MeshMorph, TetMesh
from torchmorph.mesh.quality import count_inverted
from torchmorph.selection import SelectionPlan

F64 = torch.float64
FACES = ("x0", "x1", "y0", "y1", "z0", "z1")


def bend_top(points: torch.Tensor) -> torch.Tensor:
    """Top face (z = 1) pushed up by a smooth bump, zero on its edges."""
    x, y = points[:, 0], points[:, 1]
    bump = 0.1 * torch.sin(torch.pi * x) * torch.sin(torch.pi * y)
    return torch.stack([torch.zeros_like(x), torch.zeros_like(x), bump], 1)


def brute_force_interior(mesh, displacement_of_boundary):
    """Eq. (2) in float64 NumPy from every boundary node to every interior node."""
    points = mesh.points.numpy()
    boundary, interior = mesh.boundary_nodes.numpy(), mesh.interior_nodes.numpy()
    result = np.zeros((len(interior), 3))
    for row, node in enumerate(interior):
        inverse = ((points[node] - points[boundary]) ** 2).sum(1) ** -2.0
        result[row] = inverse @ displacement_of_boundary.numpy() / inverse.sum()
    return torch.from_numpy(result)


def test_boundary_is_exact_and_interior_is_plain_idw(cube):
    morph = MeshMorph(cube)
    assert morph.num_controls == cube.boundary_nodes.numel() == 98
    boundary = morph.boundary_displacement("z1", bend_top)
    field = morph(boundary)
    assert field.shape == (cube.num_nodes, 3)
    assert torch.equal(field[cube.boundary_nodes], boundary)
    torch.testing.assert_close(
        field[cube.interior_nodes], brute_force_interior(cube, boundary), rtol=1e-12, atol=1e-15
    )


def test_selecting_everything_equals_plain_idw(cube):
    spacing = 0.25
    plan = SelectionPlan(dict.fromkeys(FACES, spacing / 10))
    selective = MeshMorph(cube, plan)
    plain = MeshMorph(cube)
    assert torch.equal(selective.control_nodes, plain.control_nodes)
    boundary = plain.boundary_displacement("z1", bend_top)
    torch.testing.assert_close(selective(boundary), plain(boundary), rtol=0, atol=0)


def test_selection_uses_fewer_controls_and_keeps_the_boundary_exact(cube):
    plan = SelectionPlan(dict.fromkeys(FACES, 0.6), enrich=["z1"])
    morph = MeshMorph(cube, plan, generator=torch.Generator().manual_seed(3))
    top = set(cube.node_set("z1").tolist())
    assert top <= set(morph.control_nodes.tolist())
    assert morph.num_controls < cube.boundary_nodes.numel()
    boundary = morph.boundary_displacement("z1", bend_top)
    field = morph(boundary)
    assert torch.equal(field[cube.boundary_nodes], boundary)
    weights = morph.idw.weights_matrix()
    torch.testing.assert_close(field[cube.interior_nodes], weights @ boundary[morph.selected])


def test_batched_equals_loop(cube):
    morph = MeshMorph(cube)
    amplitudes = torch.linspace(0.1, 1.0, 4, dtype=F64)
    batch = morph.boundary_displacement(
        "z1", lambda p: amplitudes[:, None, None] * bend_top(p)[None]
    )
    assert batch.shape == (4, morph.num_boundary, 3)
    torch.testing.assert_close(
        morph(batch), torch.stack([morph(single) for single in batch]), rtol=1e-14, atol=1e-15
    )


def test_matrix_free_equals_dense(cube):
    dense, free = MeshMorph(cube, mode="dense"), MeshMorph(cube, mode="matrix_free")
    boundary = dense.boundary_displacement("z1", bend_top)
    torch.testing.assert_close(free(boundary), dense(boundary), rtol=0, atol=1e-14)


def test_state_dict_round_trip(cube):
    plan = SelectionPlan(dict.fromkeys(FACES, 0.6))
    morph = MeshMorph(cube, plan, generator=torch.Generator().manual_seed(1))
    other = MeshMorph(cube, plan, generator=torch.Generator().manual_seed(2))
    if torch.equal(other.control_nodes, morph.control_nodes):
        pytest.skip("both seeds happened to pick the same controls")
    other.load_state_dict(morph.state_dict())
    boundary = morph.boundary_displacement("z1", bend_top)
    assert torch.equal(other(boundary), morph(boundary))


def test_gradcheck_through_the_morph(cube):
    morph = MeshMorph(cube, SelectionPlan(dict.fromkeys(FACES, 0.6)))
    boundary = morph.boundary_displacement("z1", bend_top).requires_grad_(True)
    assert gradcheck(morph, (boundary,))


def test_gradient_with_respect_to_reference_points(cube):
    morph = MeshMorph(cube)
    boundary = morph.boundary_displacement("z1", bend_top)
    points = cube.points.clone().requires_grad_(True)
    morph(boundary, points=points)[cube.interior_nodes].sum().backward()
    assert points.grad is not None and torch.isfinite(points.grad).all()
    assert points.grad[cube.interior_nodes].abs().sum() > 0
    assert points.grad[cube.boundary_nodes].abs().sum() > 0


def test_count_inverted(cube):
    morph = MeshMorph(cube)
    gentle = morph(morph.boundary_displacement("z1", bend_top))
    assert morph.count_inverted(gentle) == 0
    crushed = morph(
        morph.boundary_displacement(
            "z1", lambda p: torch.tensor([0.0, 0.0, -1.5], dtype=F64).expand_as(p)
        )
    )
    assert morph.count_inverted(crushed) > 0
    count = morph.count_inverted(crushed)
    assert isinstance(count, int)
    assert count == count_inverted(cube, crushed)
    counts = morph.inverted(torch.stack([gentle, crushed])).sum(-1)
    assert counts.tolist() == [0, count]
    with pytest.raises(ValueError, match=r"count_inverted takes one field \(N, D\)"):
        morph.count_inverted(torch.stack([gentle, crushed]))


def test_errors(cube):
    morph = MeshMorph(cube)
    with pytest.raises(ValueError, match=r"boundary_displacement must have shape \(98, 3\)"):
        morph(torch.zeros(97, 3, dtype=F64))
    with pytest.raises(ValueError, match="unknown marker 'wing'; known: x0, x1"):
        morph.boundary_displacement("wing", bend_top)
    with pytest.raises(ValueError, match=r"displacement must return shape \(25, 3\)"):
        morph.boundary_displacement("z1", lambda p: p[:, :2])
    with pytest.raises(ValueError, match="boundary_displacement has dtype torch.float32"):
        morph(torch.zeros(98, 3))
    with pytest.raises(TypeError, match="mesh must be a torchmorph Mesh"):
        MeshMorph(cube.points)


# ------------------------------------------------------------------ state


def saved(module: torch.nn.Module) -> dict:
    buffer = io.BytesIO()
    torch.save(module.state_dict(), buffer)
    buffer.seek(0)
    return torch.load(buffer, weights_only=False)


def test_state_dict_keeps_node_sets_and_loads_into_another_mesh(cube):
    from conftest import structured_cube

    small = structured_cube(2)
    source = MeshMorph(
        cube, SelectionPlan(dict.fromkeys(FACES, 0.6)), generator=torch.Generator().manual_seed(1)
    )
    target = MeshMorph(TetMesh(small.points, small.tets, {"other": [0, 1]}))
    target.load_state_dict(saved(source))
    assert sorted(target.node_sets) == sorted(source.node_sets)
    for name, nodes in source.node_sets.items():
        assert torch.equal(target.node_sets[name], nodes)
    for name in MeshMorph._STATE_BUFFERS:
        assert torch.equal(getattr(target, name), getattr(source, name)), name
    boundary = source.boundary_displacement("z1", bend_top)
    assert torch.equal(target.boundary_displacement("z1", bend_top), boundary)
    assert torch.equal(target(boundary), source(boundary))


def test_node_sets_are_copies_of_the_mesh_sets(cube):
    mesh = TetMesh(cube.points, cube.tets, {k: v.clone() for k, v in cube.node_sets.items()})
    morph = MeshMorph(mesh)
    before = morph.boundary_mask("z1").clone()
    mesh.node_sets["z1"][:] = 0  # the caller edits its own arrays afterwards
    morph.node_sets["z1"][:] = 0  # or the ones the morph hands out
    assert torch.equal(morph.boundary_mask("z1"), before)


@pytest.mark.parametrize(
    ("key", "change", "message"),
    [
        ("selected", lambda v: v + 1000, r"'selected'\]: holds indices outside"),
        ("control_nodes", lambda v: v.flip(0), r"'control_nodes'\]: must equal boundary_nodes"),
        ("interior_nodes", lambda v: v[1:], r"'interior_nodes'\]: boundary_nodes and interior"),
        ("cell_nodes", lambda v: v + 10_000, r"'cell_nodes'\]: holds indices outside"),
        ("cell_nodes", lambda v: v[1:], r"'cell_nodes'\]: holds 1535 entries but the cell"),
        ("cell_orientation", lambda v: v[1:], r"'cell_orientation'\]: holds 383 entries"),
        (
            "_extra_state",
            lambda v: {**v, "cell_blocks": [["tetra10", 384]]},
            r"'cell_nodes'\]: holds 1536 entries but the cell blocks need 3840",
        ),
        (
            "_extra_state",
            lambda v: {**v, "cell_blocks": [["polygon", 384]]},
            r"'_extra_state'\]: .*cell kind 'polygon' is not supported",
        ),
        ("node_set_members", lambda v: v + 10_000, r"'node_set_members'\]: holds indices"),
        ("node_set_offsets", lambda v: v[:-1], r"'node_set_offsets'\]: must rise from 0"),
        (
            "idw.targets",
            lambda v: v[1:],
            r"'idw.targets'\]: has 26 rows but the morph's state needs 27",
        ),
        (
            "_extra_state",
            lambda v: {**v, "node_set_names": ["a"]},
            r"'node_set_offsets'\]: holds 6 node sets but the names are 1",
        ),
        ("_extra_state", lambda v: {**v, "version": 99}, r"'_extra_state'\]: version 99"),
    ],
)
def test_a_tampered_state_fails_to_load_and_leaves_the_module_intact(cube, key, change, message):
    morph = MeshMorph(cube, SelectionPlan(dict.fromkeys(FACES, 0.6)))
    state = saved(morph)
    state[key] = change(state[key])
    before = {name: getattr(morph, name).clone() for name in MeshMorph._STATE_BUFFERS}
    with pytest.raises(ValueError, match=message):
        morph.load_state_dict(state)
    for name, value in before.items():
        assert torch.equal(getattr(morph, name), value), name


def test_implementation_reaches_the_idw(cube):
    plain = MeshMorph(cube, implementation="torch")
    assert plain.idw.implementation == "torch"
    with pytest.raises(ValueError, match="implementation must be one of 'auto', 'fused', 'torch'"):
        MeshMorph(cube, implementation="gpu")
