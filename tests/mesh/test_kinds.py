"""Meshes of every element kind, 2-D and 3-D, linear and quadratic: every cell kept, the
boundary where the geometry says it is, volumes and quality against hand-computed values,
and the morph against an independent float64 IDW from the true boundary."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from _kinds import box, columns, idw_reference, on_box_surface, quadratic, rectangle

from torchmorph import MeshMorph
from torchmorph.mesh import (
    Mesh,
    cell_edge_ratio,
    cell_volumes,
    count_inverted,
    inverted,
    mass_matrix,
    quality_by_kind,
    relative_l2_error,
    scaled_jacobian,
)
from torchmorph.mesh.cells import CELL_KINDS

F64 = torch.float64


def linear(name: str):
    if name == "columns":
        return columns(2)
    if name in ("quad", "triangle"):
        return rectangle(name, 3)
    return box(tuple(name.split("+")), 2)


LINEAR = [
    "hexahedron",
    "wedge",
    "pyramid",
    "tetra",
    "wedge+tetra",  # a prism layer under a tetrahedral core
    "hexahedron+pyramid",
    "columns",  # hexahedra beside wedges
    "quad",
    "triangle",
]


def case(name: str, order: str):
    points, cells = linear(name)
    if order == "quadratic":
        points, cells = quadratic(points, cells)
    elif order == "full":
        points, cells = quadratic(points, cells, full=True)
    return points, cells


CASES = [(name, order) for name in LINEAR for order in ("linear", "quadratic", "full")]


@pytest.mark.parametrize(("name", "order"), CASES)
def test_every_cell_kept_and_the_boundary_is_the_box_surface(name, order):
    points, cells = case(name, order)
    mesh = Mesh(points, cells)
    assert [b.kind for b in mesh.cells] == [kind for kind, _ in cells]
    for block, (_, nodes) in zip(mesh.cells, cells, strict=True):
        assert torch.equal(block.nodes, torch.from_numpy(nodes))  # node order as given
    assert mesh.num_cells == sum(len(nodes) for _, nodes in cells)
    # mid-side and face nodes of boundary facets are boundary nodes, the others interior
    assert torch.equal(mesh.boundary_nodes, torch.from_numpy(on_box_surface(points)))
    extent = points.max(0) - points.min(0)
    torch.testing.assert_close(mesh.volumes.sum(), torch.tensor(float(np.prod(extent)), dtype=F64))
    assert count_inverted(mesh) == 0
    # the mass matrix integrates 1 to the volume
    ones = torch.ones(mesh.num_nodes, dtype=F64)
    total = ones @ torch.sparse.mm(mass_matrix(mesh), ones[:, None])[:, 0]
    torch.testing.assert_close(total, torch.tensor(float(np.prod(extent)), dtype=F64))


@pytest.mark.parametrize(("name", "order"), CASES)
def test_morph_equals_an_independent_float64_idw_from_the_true_boundary(name, order):
    points, cells = case(name, order)
    mesh = Mesh(points, cells)
    boundary = on_box_surface(points)
    interior = np.setdiff1d(np.arange(len(points)), boundary)
    # a smooth displacement of the whole boundary
    p = points[boundary]
    values = 0.05 * np.stack([np.sin(p.sum(1) + k) for k in range(points.shape[1])], 1)
    morph = MeshMorph(mesh, mode="dense")
    field = morph(torch.from_numpy(values))
    assert torch.equal(field[torch.from_numpy(boundary)], torch.from_numpy(values))
    expected = idw_reference(points[interior], p, values)
    scale = np.abs(values).max()
    np.testing.assert_allclose(
        field[torch.from_numpy(interior)].numpy(), expected, atol=1e-12 * scale
    )


@pytest.mark.parametrize(("name", "order"), [(n, "quadratic") for n in LINEAR])
def test_a_rigid_translation_of_the_boundary_moves_the_whole_mesh(name, order):
    points, cells = case(name, order)
    mesh = Mesh(points, cells)
    morph = MeshMorph(mesh)
    shift = torch.tensor([0.3, -0.2, 0.1][: mesh.dim], dtype=F64)
    field = morph(shift.expand(morph.num_boundary, -1).contiguous())
    torch.testing.assert_close(field, shift.expand(mesh.num_nodes, -1), rtol=0, atol=1e-14)
    assert count_inverted(mesh, field) == 0


def test_unit_cells_have_the_hand_computed_quality():
    cube = Mesh(*box(("hexahedron",), 1))
    torch.testing.assert_close(cell_volumes(cube), torch.ones(1, dtype=F64))
    torch.testing.assert_close(scaled_jacobian(cube), torch.ones(1, dtype=F64))
    torch.testing.assert_close(cell_edge_ratio(cube), torch.ones(1, dtype=F64))
    # a right-angled wedge: corner angles 90, 45, 45 degrees; scaled by 2/sqrt(3)
    wedge = Mesh(*box(("wedge",), 1))
    torch.testing.assert_close(cell_volumes(wedge), torch.full((2,), 0.5, dtype=F64))
    expected = math.sin(math.pi / 4) * 2 / math.sqrt(3)
    torch.testing.assert_close(scaled_jacobian(wedge), torch.full((2,), expected, dtype=F64))
    torch.testing.assert_close(cell_edge_ratio(wedge), torch.full((2,), math.sqrt(2), dtype=F64))
    # a unit square stretched by 2 along x: area 2, Jacobian still 1, edge ratio 2
    square = Mesh(np.array([[0.0, 0], [2, 0], [2, 1], [0, 1]]), [("quad", [[0, 1, 2, 3]])])
    assert float(cell_volumes(square)) == 2.0 and float(scaled_jacobian(square)) == 1.0
    assert float(cell_edge_ratio(square)) == 2.0
    # a sheared hexahedron (top face moved by s along x): volume 1, corner Jacobians 1/sqrt(1+s^2)
    s = 0.5
    shift = torch.zeros(8, 3, dtype=F64)
    shift[cube.points[:, 2] == 1, 0] = s
    torch.testing.assert_close(cell_volumes(cube, shift), torch.ones(1, dtype=F64))
    torch.testing.assert_close(
        scaled_jacobian(cube, shift), torch.tensor([1 / math.sqrt(1 + s * s)], dtype=F64)
    )


def test_inverted_cells_are_found_for_every_kind():
    for name in ("hexahedron", "wedge", "pyramid", "quad", "triangle"):
        points, cells = linear(name)
        mesh = Mesh(points, cells)
        # push the node at the middle of the box's bottom (or a corner) through its cells
        node = int(
            np.argmin(np.linalg.norm(points - points.mean(0) * [1, 1, 0][: mesh.dim], axis=1))
        )
        move = torch.zeros(mesh.num_nodes, mesh.dim, dtype=F64)
        move[node, -1] = 5.0
        flipped = inverted(mesh, move)
        assert bool(flipped.any()), name
        owners = torch.zeros(mesh.num_cells, dtype=torch.bool)
        offset = 0
        for block in mesh.cells:  # the inverted cells all hold the node
            owners[offset : offset + block.nodes.shape[0]] = (block.nodes == node).any(1)
            offset += block.nodes.shape[0]
        assert not bool((flipped & ~owners).any()), name


def test_mirrored_cells_are_valid_and_their_facets_point_out():
    points, cells = box(("hexahedron", "pyramid"), 2)
    mirrored = [(kind, nodes[:, list(CELL_KINDS[kind].mirror)]) for kind, nodes in cells]
    mesh = Mesh(points, mirrored)
    assert all(bool((o == -1).all()) for o in mesh.orientation)
    torch.testing.assert_close(mesh.volumes.sum(), torch.tensor(8.0, dtype=F64))
    assert count_inverted(mesh) == 0
    centre = torch.from_numpy(points.mean(0))
    for block in mesh.boundary_facets:  # outward: the normal points away from the centre
        p = mesh.points[block.nodes]
        normal = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=1)
        assert bool(((normal * (p.mean(1) - centre)).sum(1) > 0).all())


def test_quality_by_kind_and_the_error_norm_on_a_hybrid_mesh():
    points, cells = box(("wedge", "tetra"), 2)
    mesh = Mesh(points, cells)
    by_kind = quality_by_kind(mesh)
    assert sorted(by_kind) == ["tetra", "wedge"]
    assert by_kind["wedge"]["num_cells"] == 8 and by_kind["tetra"]["num_cells"] == 24
    field = torch.ones(mesh.num_nodes, 3, dtype=F64)
    assert float(relative_l2_error(mesh, 2 * field, field)) == pytest.approx(1.0)


@pytest.mark.parametrize(
    ("cells", "message"),
    [
        ([("polygon", [[0, 1, 2]])], r"cells\[0\]: cell kind 'polygon' is not supported"),
        ([("tetra", [[0, 1, 2, 3]]), ("triangle", [[0, 1, 2]])], "cells of dimension 2 and 3"),
        ([("tetra", [[0, 1, 2]])], r"\(tetra\) must have shape \(M, 4\)"),
        ([("tetra", [[0, 1, 2, 9]])], r"node indices outside \[0, 5\)"),
        ([("tetra", [[0, 1, 2, 3]] * 3)], "more than two cells"),
        ([("tetra", [[0, 1, 2, 3]] * 2)], "both of their cells on the same side"),
        ([("tetra", [[0, 1, 2, 4]])], r"1 cell\(s\) are flat"),
        ([("tetra", [])], "cells is empty"),
    ],
)
def test_bad_cells_are_clear_errors(cells, message):
    points = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0.5, 0.5, 0]])
    with pytest.raises(ValueError, match=message):
        Mesh(points, cells)


def test_a_folded_or_tangled_reference_cell_is_refused():
    points, cells = box(("hexahedron",), 1)
    tangled = points.copy()
    tangled[6] = [0.2, 0.2, 0.2]  # a corner pulled inside the cell through its diagonal
    with pytest.raises(ValueError, match=r"inverted at some corners"):
        Mesh(tangled, cells)


def test_markers_node_sets_face_sets_and_groups():
    points, cells = rectangle("quad", 2)
    mesh = Mesh(
        points,
        cells,
        {"corner": [0]},
        {"bottom": [("line", [[0, 3], [3, 6]])], "left": [("line", [[0, 1], [1, 2]])]},
        groups={"walls": ["bottom", "left"]},
    )
    assert mesh.markers == ("corner", "bottom", "left", "walls")
    assert mesh.node_set("bottom").tolist() == [0, 3, 6]
    assert mesh.node_set("walls").tolist() == [0, 1, 2, 3, 6]
    with pytest.raises(
        ValueError, match=r"unknown marker 'top'; known: corner, bottom, left, walls"
    ):
        mesh.node_set("top")
    with pytest.raises(ValueError, match=r"facet kind 'triangle' is not a facet of a 2-D mesh"):
        Mesh(points, cells, face_sets={"x": [("triangle", [[0, 1, 2]])]})
    with pytest.raises(ValueError, match=r"groups\['g'\]: unknown member marker\(s\) 'nope'"):
        Mesh(points, cells, groups={"g": ["nope"]})
    with pytest.raises(ValueError, match="used by both"):
        Mesh(points, cells, {"bottom": [0]}, {"bottom": [("line", [[0, 3]])]})


def test_a_2d_displacement_for_a_3d_mesh_is_refused():
    mesh = Mesh(*box(("hexahedron",), 1))
    morph = MeshMorph(mesh)
    with pytest.raises(ValueError, match=r"boundary_displacement must have shape \(8, 3\)"):
        morph(torch.zeros(8, 2, dtype=F64))
    with pytest.raises(
        ValueError, match=r"points must have shape \(N, 2\) for cells of dimension 2"
    ):
        Mesh(np.zeros((4, 3)) + np.eye(4, 3), [("quad", [[0, 1, 2, 3]])])


def test_a_cell_pushed_through_its_neighbour_is_refused_whatever_its_kind():
    # two cubes side by side; the second's far corners pulled back through the shared face:
    # it is then a valid-looking mirrored cell on the first one's side
    points, cells = columns(1)
    hexes = cells[0][1]
    assert Mesh(points, cells).num_cells == 3
    squeezed = points.copy()
    far = np.isclose(points[:, 0], 2.0)
    squeezed[far, 0] = 0.5  # x = 2 -> x = 0.5: the wedges fold back over the hexahedron
    with pytest.raises(ValueError, match="both of their cells on the same side"):
        Mesh(squeezed, cells)
    assert hexes.shape == (1, 8)


@pytest.mark.parametrize("width", [2, 3, 4])
def test_facet_sorting_by_keys_and_by_columns_agree(width):
    """Facets are matched by one int64 key of their three smallest corners where the node
    count allows it, else column by column: both find the same equal rows."""
    from torchmorph.mesh._topology import _sort_rows, _sorted_columns

    generator = torch.Generator().manual_seed(width)
    distinct = torch.arange(300)[:, None] + 300 * torch.arange(width)  # rows of distinct sets
    shuffled = torch.argsort(torch.rand(300, width, generator=generator), 1)
    rows = distinct.gather(1, shuffled)
    rows = torch.cat([rows, rows[::3].flip(1)]).to(torch.int32)  # every third one twice
    columns = _sorted_columns(rows)
    assert torch.equal(torch.stack(columns, 1), rows.sort(1).values)
    found = []
    for num_nodes in (1200, 2**31 - 1):  # keys fit in int64 / they do not (for width >= 3)
        order, same = _sort_rows(columns, num_nodes)
        first, second = order[:-1][same].tolist(), order[1:][same].tolist()
        found.append({(min(a, b), max(a, b)) for a, b in zip(first, second, strict=True)})
    assert found[0] == found[1] == {(k, 300 + k // 3) for k in range(0, 300, 3)}
