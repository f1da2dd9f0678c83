"""Non-conforming interfaces: a quadrilateral face against two triangular faces split along
one of its diagonals matches no facet, so it would read as boundary and its nodes be held
fixed by a morph. Building such a mesh is an error naming the cells; the layers that
conform (``_kinds.box``'s docstring) and boundary quads beside boundary triangles are
accepted, with the box's surface as their boundary."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from _kinds import box, columns, on_box_surface, quadratic

from torchmorph.mesh import Mesh
from torchmorph.mesh.cells import CELL_KINDS

#: Layer pairs with a quad face (hexahedron, pyramid base) against two triangles (wedge,
#: tetrahedron: the cube face cut along its diagonal 0-2).
NON_CONFORMING = [
    ("hexahedron", "wedge"),
    ("wedge", "hexahedron"),
    ("hexahedron", "tetra"),
    ("tetra", "hexahedron"),
    ("pyramid", "wedge"),
    ("wedge", "pyramid"),
    ("pyramid", "tetra"),
    ("tetra", "pyramid"),
]
CONFORMING = [
    ("wedge", "tetra"),
    ("tetra", "wedge"),
    ("hexahedron", "pyramid"),
    ("pyramid", "hexahedron"),
    ("hexahedron", "hexahedron"),
    ("wedge", "wedge", "tetra", "tetra"),
]

#: Hexahedron and pyramid node orders turned by a quarter about the cube's z axis: the
#: same cells, their faces read from another corner, so the split diagonal (the cube's
#: corners 0-2) becomes the diagonal 1-3 of the face's corner list.
TURNED = {
    "hexahedron": [1, 2, 3, 0, 5, 6, 7, 4],
    "pyramid": [1, 2, 3, 0, 4],
}


@pytest.mark.parametrize("layers", NON_CONFORMING, ids="+".join)
def test_a_quad_against_two_triangles_is_an_error_naming_the_cells(layers):
    points, cells = box(layers, 2)
    quads = 0 if layers[0] in ("hexahedron", "pyramid") else 1  # the block with the quads
    kind, other = cells[quads][0], cells[1 - quads][0]
    with pytest.raises(ValueError, match=r"^cells: 4 quadrilateral face\(s\) lie against") as info:
        Mesh(points, cells)
    message = str(info.value)  # one quad face per column of the 2 x 2 interface
    assert f"of cells[{quads}] ({kind}) against the triangles of cell " in message
    assert message.count(f"of cells[{1 - quads}] ({other})") == 2
    assert "a non-conforming interface" in message and "insert pyramids" in message
    assert "split the cells with quad faces along that diagonal" in message


def _quad_and_halves(message: str) -> tuple[list[int], tuple[int, int]]:
    """The quad's corners and the diagonal the message names."""
    corners = message.split("with corners [")[1].split("]")[0]
    diagonal = message.split("along its diagonal ")[1].split(";")[0]
    first, second = diagonal.split("-")
    return [int(c) for c in corners.split(", ")], (int(first), int(second))


@pytest.mark.parametrize("turned", [False, True], ids=["diagonal 0-2", "diagonal 1-3"])
@pytest.mark.parametrize("layers", [("hexahedron", "wedge"), ("tetra", "pyramid")], ids="+".join)
def test_either_diagonal_of_the_quad_is_found(layers, turned):
    points, cells = box(layers, 2)
    if turned:
        cells = [(k, c[:, TURNED[k]]) if k in TURNED else (k, c) for k, c in cells]
    with pytest.raises(ValueError, match="4 quadrilateral face") as info:
        Mesh(points, cells)
    corners, diagonal = _quad_and_halves(str(info.value))
    position = corners.index(diagonal[0])
    assert corners[(position + 2) % 4] == diagonal[1]  # a diagonal, not an edge
    assert position == (1 if turned else 0)
    # the diagonal is the cube's 0-2: both ends at the same height, x and y both differ
    ends = points[list(diagonal)]
    assert ends[0, 2] == ends[1, 2] and (ends[0, :2] != ends[1, :2]).all()


def test_a_mixed_interface_counts_every_split_quad_once():
    """Quads split along either diagonal in one interface, and quadratic cells (whose
    facets are matched by their corners): every quad of the interface is counted."""
    points, cells = box(("hexahedron", "wedge"), 3)
    hexes = cells[0][1].copy()
    hexes[::2] = hexes[::2][:, TURNED["hexahedron"]]
    with pytest.raises(ValueError, match="^cells: 9 quadrilateral face"):
        Mesh(points, [("hexahedron", hexes), cells[1]])
    with pytest.raises(ValueError, match=r"^cells: 9 quadrilateral face.*\(hexahedron20\)"):
        Mesh(*quadratic(points, cells))
    mirrored = [(kind, nodes[:, list(CELL_KINDS[kind].mirror)]) for kind, nodes in cells]
    with pytest.raises(ValueError, match="^cells: 9 quadrilateral face"):
        Mesh(points, mirrored)  # mirrored cells: their facets flipped, still found


@pytest.mark.parametrize("layers", CONFORMING, ids="+".join)
def test_conforming_layers_are_accepted_with_the_box_surface_as_boundary(layers):
    """Boundary quads beside boundary triangles on the box's walls (a wedge layer's side
    quads under a tetra layer's side triangles, sharing an edge) are a legal boundary."""
    points, cells = box(layers, 2)
    mesh = Mesh(points, cells)
    assert np.array_equal(mesh.boundary_nodes.numpy(), on_box_surface(points))
    assert float(mesh.volumes.sum()) == pytest.approx(4.0 * len(layers), rel=1e-14)


def test_quads_sharing_edges_with_boundary_triangles_are_a_legal_boundary():
    """A lone pyramid (its base beside its four triangles), a lone wedge (quads beside
    both end triangles) and hexahedra beside wedges (whole quads shared): boundary quads
    that share nodes with boundary triangles, but no triangle lies on three of a quad's
    corners."""
    pyramid = Mesh(
        np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 1]]),
        [("pyramid", [[0, 1, 2, 3, 4]])],
    )
    assert {b.kind: b.nodes.shape[0] for b in pyramid.boundary_facets} == {
        "quad": 1,
        "triangle": 4,
    }
    wedge = Mesh(*box(("wedge",), 1))
    assert {b.kind: b.nodes.shape[0] for b in wedge.boundary_facets} == {
        "quad": 4,
        "triangle": 4,
    }
    points, cells = columns(2)
    beside = Mesh(points, cells)
    assert np.array_equal(beside.boundary_nodes.numpy(), on_box_surface(points))


def test_split_quads_are_found_when_facets_are_sorted_column_by_column():
    """With more nodes than an int64 key of three corners holds, facets are sorted
    column by column: the check finds the same quads."""
    from torchmorph.mesh._topology import as_cell_blocks, cell_orientations, match_facets

    points, cells = box(("hexahedron", "wedge"), 2)
    mesh_points = torch.from_numpy(points)
    blocks = as_cell_blocks(cells, mesh_points.shape[0], mesh_points.device)
    orientations = cell_orientations(mesh_points, blocks)
    for num_nodes in (mesh_points.shape[0], 2**21):  # 2**63 > 2**62: no key fits
        with pytest.raises(ValueError, match="^cells: 4 quadrilateral face"):
            match_facets(blocks, orientations, num_nodes)
