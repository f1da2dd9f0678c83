"""TetMesh: validation, orientation, derived topology and geometry."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from _grids import kuhn_grid

from torchmorph.mesh import FLAT_TET_TOLERANCE, TetMesh, box_mesh

F64 = torch.float64

REFERENCE_POINTS = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]


@pytest.fixture
def reference_tet() -> TetMesh:
    return TetMesh(torch.tensor(REFERENCE_POINTS, dtype=F64), torch.tensor([[0, 1, 2, 3]]))


@pytest.fixture
def cube_grid() -> TetMesh:
    points, tets = kuhn_grid(4)
    return TetMesh(points, tets)


# ----------------------------------------------------------------------------- construction


def test_reference_tetrahedron(reference_tet):
    mesh = reference_tet
    assert mesh.num_nodes == 4 and mesh.num_tets == 1
    torch.testing.assert_close(
        mesh.volumes, torch.tensor([1.0 / 6.0], dtype=F64), rtol=0, atol=1e-15
    )
    assert mesh.boundary_faces.shape == (4, 3)
    assert mesh.boundary_nodes.tolist() == [0, 1, 2, 3]
    assert mesh.interior_nodes.numel() == 0
    assert mesh.edges.tolist() == [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]


def test_numpy_input_becomes_float64_and_int64():
    mesh = TetMesh(np.array(REFERENCE_POINTS, dtype=np.float32), np.array([[0, 1, 2, 3]], np.int32))
    assert mesh.points.dtype == F64
    assert mesh.tets.dtype == torch.int64


def test_negative_tet_is_reoriented_without_touching_the_input():
    tets = torch.tensor([[0, 2, 1, 3]])
    mesh = TetMesh(torch.tensor(REFERENCE_POINTS, dtype=F64), tets)
    assert mesh.tets.tolist() == [[0, 2, 3, 1]]
    assert float(mesh.volumes[0]) == pytest.approx(1.0 / 6.0, abs=1e-15)
    assert tets.tolist() == [[0, 2, 1, 3]]


def test_cube_grid_counts_and_orientation(cube_grid):
    n = 4
    mesh = cube_grid
    assert mesh.num_tets == 6 * n**3
    assert bool((mesh.volumes > 0).all())
    torch.testing.assert_close(mesh.volumes.sum(), torch.tensor(1.0, dtype=F64))
    assert mesh.boundary_faces.shape == (12 * n**2, 3)
    # axis edges + face diagonals + body diagonals of the Kuhn triangulation
    assert mesh.edges.shape == (3 * n * (n + 1) ** 2 + 3 * n**2 * (n + 1) + n**3, 2)
    # Euler characteristic of a ball: V - E + F - T = 1
    num_faces = (4 * mesh.num_tets + mesh.boundary_faces.shape[0]) // 2
    assert mesh.num_nodes - mesh.edges.shape[0] + num_faces - mesh.num_tets == 1


def test_interior_nodes_are_the_inner_grid_points(cube_grid):
    n = 4
    points = cube_grid.points
    inside = ((points > 1e-12) & (points < 1 - 1e-12)).all(dim=1)
    expected = torch.nonzero(inside).flatten()
    assert cube_grid.interior_nodes.numel() == (n - 1) ** 3
    assert torch.equal(cube_grid.interior_nodes, expected)
    assert torch.equal(cube_grid.boundary_nodes, torch.nonzero(~inside).flatten())


def test_boundary_faces_point_outward(cube_grid):
    points = cube_grid.points
    a, b, c = (points[cube_grid.boundary_faces[:, i]] for i in range(3))
    normals = torch.linalg.cross(b - a, c - a, dim=1)
    centroid = (a + b + c) / 3
    # every outward normal points away from the cube's centre
    assert bool(((normals * (centroid - 0.5)).sum(1) > 0).all())
    # divergence theorem: the enclosed volume from the oriented surface
    enclosed = (torch.linalg.cross(b, c, dim=1) * a).sum() / 6
    torch.testing.assert_close(enclosed, torch.tensor(1.0, dtype=F64))


def test_boundary_faces_without_int64_keys_agree(cube_grid, monkeypatch):
    # meshes with more than ~2e6 nodes use unique rows instead of packed keys
    import torchmorph.mesh.tetmesh

    monkeypatch.setattr(torchmorph.mesh.tetmesh, "_MAX_NODES_FOR_FACE_KEYS", 0)
    fresh = TetMesh(cube_grid.points, cube_grid.tets)
    assert sorted(map(tuple, fresh.boundary_faces.tolist())) == sorted(
        map(tuple, cube_grid.boundary_faces.tolist())
    )


def test_edges_are_unique_and_ordered(cube_grid):
    edges = cube_grid.edges
    assert bool((edges[:, 0] < edges[:, 1]).all())
    assert torch.unique(edges, dim=0).shape == edges.shape
    # tet_edges maps each tet's six local edges to rows of `edges`
    local = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    tets = cube_grid.tets
    for column, (i, j) in enumerate(local):
        pair = edges[cube_grid.tet_edges[:, column]]
        expected = torch.sort(tets[:, [i, j]], dim=1).values
        assert torch.equal(pair, expected)


def test_unused_nodes_are_allowed_and_count_as_interior():
    points = torch.tensor(REFERENCE_POINTS + [[5.0, 5.0, 5.0]], dtype=F64)
    mesh = TetMesh(points, torch.tensor([[0, 1, 2, 3]]))
    assert mesh.interior_nodes.tolist() == [4]


def test_relative_flatness_tolerance_accepts_tiny_and_graded_meshes():
    points, tets = kuhn_grid(2)
    tiny = TetMesh(points * 1e-9, tets)
    assert bool((tiny.volumes > 0).all())
    # a sliver much thinner than the mesh but far from flat relative to its own edges
    sliver = torch.tensor(REFERENCE_POINTS, dtype=F64)
    sliver[3, 2] = 1e-7
    TetMesh(sliver, torch.tensor([[0, 1, 2, 3]]))


# ----------------------------------------------------------------------------- node sets


def test_node_sets_are_sorted_unique_and_accept_masks(reference_tet):
    mask = torch.tensor([True, False, True, False])
    mesh = TetMesh(
        reference_tet.points, reference_tet.tets, {"root": [3, 1, 1], "tip": mask, "none": []}
    )
    assert mesh.node_set("root").tolist() == [1, 3]
    assert mesh.node_set("root").dtype == torch.int64
    assert mesh.node_set("tip").tolist() == [0, 2]
    assert mesh.node_set("none").numel() == 0
    assert mesh.nodes_of(["root", "tip"]).tolist() == [0, 1, 2, 3]
    assert mesh.nodes_of("root").tolist() == [1, 3]
    assert mesh.nodes_of([]).numel() == 0


def test_unknown_node_set_lists_the_known_ones(reference_tet):
    mesh = TetMesh(reference_tet.points, reference_tet.tets, {"root": [0], "tip": [1]})
    with pytest.raises(ValueError, match=r"unknown marker 'wing'; known: root, tip"):
        mesh.node_set("wing")
    with pytest.raises(ValueError, match=r"unknown marker 'x'; known: \(none\)"):
        reference_tet.node_set("x")


# ----------------------------------------------------------------------------- errors


@pytest.mark.parametrize(
    ("points", "tets", "node_sets", "message"),
    [
        (REFERENCE_POINTS, [[0, 1, 2, 4]], None, r"tets holds vertex indices outside \[0, 4\)"),
        (REFERENCE_POINTS, [[0, 1, 2, -1]], None, r"tets holds vertex indices outside.*min -1"),
        (REFERENCE_POINTS, [[0, 1, 2]], None, r"tets must have shape \(M, 4\)"),
        (REFERENCE_POINTS, [[0.0, 1.0, 2.0, 3.0]], None, r"tets must hold integer"),
        (REFERENCE_POINTS, np.zeros((0, 4), int), None, r"tets is empty"),
        ([[0.0, 0.0]] * 4, [[0, 1, 2, 3]], None, r"points must have shape \(N, 3\)"),
        (REFERENCE_POINTS[:3] + [[0, 0, np.nan]], [[0, 1, 2, 3]], None, r"points holds 1 NaN"),
        (
            REFERENCE_POINTS[:3] + [[0, 0, np.inf]],
            [[0, 1, 2, 3]],
            None,
            r"points holds 1 NaN or inf",
        ),
        (REFERENCE_POINTS, [[0, 1, 2, 2]], None, r"tets: 1 tetrahedra have zero volume"),
        (REFERENCE_POINTS[:3] + [[0.3, 0.3, 0.0]], [[0, 1, 2, 3]], None, r"zero volume.*indices 0"),
        (REFERENCE_POINTS, [[0, 1, 2, 3]], {"root": [0, 7]}, r"node_sets\['root'\] holds indices"),
        (REFERENCE_POINTS, [[0, 1, 2, 3]], {"root": [-1]}, r"node_sets\['root'\] holds indices"),
        (REFERENCE_POINTS, [[0, 1, 2, 3]], {"": [0]}, r"node_sets: names must be non-empty"),
        (REFERENCE_POINTS, [[0, 1, 2, 3]], {"a": [0.5]}, r"node_sets\['a'\] must hold integer"),
    ],
)
def test_invalid_input_raises(points, tets, node_sets, message):
    with pytest.raises(ValueError, match=message):
        TetMesh(np.asarray(points, dtype=float), tets, node_sets)


def test_nearly_flat_tet_is_rejected_relative_to_its_size():
    points = torch.tensor(REFERENCE_POINTS, dtype=F64) * 1e3
    points[3, 2] = 1e3 * FLAT_TET_TOLERANCE  # |V| / L**3 is about 6e-14
    with pytest.raises(ValueError, match="zero volume"):
        TetMesh(points, torch.tensor([[0, 1, 2, 3]]))


# ----------------------------------------------------------------------------- new meshes


def test_deformed_is_not_revalidated(reference_tet):
    displacement = torch.zeros(4, 3, dtype=F64)
    displacement[3, 2] = -2.0  # reflect vertex 3 through the opposite face
    moved = reference_tet.deformed(displacement)
    assert torch.equal(moved.tets, reference_tet.tets)
    torch.testing.assert_close(moved.volumes, torch.tensor([-1.0 / 6.0], dtype=F64))
    torch.testing.assert_close(moved.points[3], torch.tensor([0.0, 0.0, -1.0], dtype=F64))
    flat = torch.zeros(4, 3, dtype=F64)
    flat[3, 2] = -1.0
    assert float(reference_tet.deformed(flat).volumes[0]) == 0.0


def test_deformed_keeps_node_sets_topology_and_gradients(cube_grid):
    mesh = TetMesh(cube_grid.points, cube_grid.tets, {"bottom": cube_grid.points[:, 2] == 0})
    displacement = torch.zeros(mesh.num_nodes, 3, dtype=F64, requires_grad=True)
    moved = mesh.deformed(displacement)
    assert torch.equal(moved.node_set("bottom"), mesh.node_set("bottom"))
    assert torch.equal(moved.boundary_faces, mesh.boundary_faces)
    moved.volumes.sum().backward()
    assert displacement.grad is not None and bool(displacement.grad.abs().sum() > 0)


@pytest.mark.parametrize("shape", [(4, 2), (3, 3), (1, 4, 3)])
def test_deformed_rejects_wrong_shapes(reference_tet, shape):
    with pytest.raises(ValueError, match=r"displacement must have shape \(4, 3\)"):
        reference_tet.deformed(torch.zeros(shape, dtype=F64))


def test_deformed_rejects_non_finite(reference_tet):
    displacement = torch.zeros(4, 3, dtype=F64)
    displacement[0, 0] = float("nan")
    with pytest.raises(ValueError, match="displacement holds 1 NaN"):
        reference_tet.deformed(displacement)


def test_to_changes_dtype_and_keeps_everything_else(cube_grid):
    single = cube_grid.to(dtype=torch.float32)
    assert single.points.dtype == torch.float32
    assert torch.equal(single.tets, cube_grid.tets)
    assert torch.equal(single.interior_nodes, cube_grid.interior_nodes)
    with pytest.raises(ValueError, match="dtype must be a floating-point dtype"):
        cube_grid.to(dtype=torch.int64)


def test_repr_names_the_mesh(reference_tet):
    mesh = TetMesh(reference_tet.points, reference_tet.tets, {"root": [0]}, name="wing")
    assert "TetMesh('wing', nodes=4, tets=1, node_sets=[root]" in repr(mesh)


def test_folded_reference_tetrahedra_are_rejected():
    # An interior node pushed through its neighbours: orientation fixing alone would
    # hide the inversion, but the tets on both sides of some face then overlap.
    points, tets = kuhn_grid(3)
    points = torch.as_tensor(points, dtype=F64).clone()
    inner = int(np.flatnonzero((points > 0).all(1) & (points < 1).all(1))[0])
    points[inner] += torch.tensor([0.5, 0.45, 0.4], dtype=F64)
    with pytest.raises(
        ValueError,
        match=r"tets: \d+ interior face\(s\) have both of their "
        r"tetrahedra on the same side",
    ):
        TetMesh(points, tets)


def test_faces_shared_by_three_tetrahedra_are_rejected():
    points, tets = kuhn_grid(2)
    duplicated = np.concatenate([tets, tets[:1]])
    with pytest.raises(ValueError, match="belong to more than two tetrahedra"):
        TetMesh(points, duplicated)


def test_fold_check_agrees_without_int64_face_keys(monkeypatch):
    import torchmorph.mesh.tetmesh as mesh_module

    points, tets = kuhn_grid(3)
    reference = TetMesh(points, tets).boundary_faces
    monkeypatch.setattr(mesh_module, "_MAX_NODES_FOR_FACE_KEYS", 0)
    assert torch.equal(
        torch.sort(TetMesh(points, tets).boundary_faces.sort(1).values, 0).values,
        torch.sort(reference.sort(1).values, 0).values,
    )
    with pytest.raises(ValueError, match="belong to more than two tetrahedra"):
        TetMesh(points, np.concatenate([tets, tets[:1]]))


def test_overlapping_tets_that_share_no_face_are_rejected():
    from itertools import combinations

    cube = box_mesh(2)  # one interior node, the centre
    (centre,) = cube.interior_nodes.tolist()
    corners = [
        k for k in range(cube.num_nodes) if all(float(x) in (0.0, 1.0) for x in cube.points[k])
    ]
    faces = {tuple(sorted(face)) for tet in cube.tets.tolist() for face in combinations(tet, 3)}
    for a, b, c in combinations(corners, 3):
        extra = [centre, a, b, c]
        if any(tuple(sorted(face)) in faces for face in combinations(extra, 3)):
            continue
        volume = torch.linalg.det(cube.points[[a, b, c]] - cube.points[centre])
        if abs(float(volume)) > 1e-3:
            break
    tets = torch.cat([cube.tets, torch.tensor([extra])])
    with pytest.raises(
        ValueError,
        match=r"tets: the tetrahedra around \d+ node\(s\) cover more "
        r"than one sphere .* e\.g\. node \d+: solid angle",
    ):
        TetMesh(cube.points, tets)


def test_the_mesh_copies_its_inputs():
    cube = box_mesh(2)
    points, tets = cube.points.clone(), cube.tets.clone()
    mesh = TetMesh(points, tets)
    volumes = mesh.volumes.clone()
    points.mul_(2.0)
    tets[:, [2, 3]] = tets[:, [3, 2]]
    assert torch.equal(mesh.points, cube.points) and torch.equal(mesh.tets, cube.tets)
    assert torch.equal(TetMesh(mesh.points, mesh.tets).volumes, volumes)
    moved = cube.points.clone().requires_grad_(True)
    TetMesh(moved, cube.tets).volumes.sum().backward()
    assert moved.grad is not None
