"""Every format of the table: every cell block written and read back in order, markers
(node and face sets) surviving where the format holds them, and files written again
moved with everything else kept."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from _kinds import box, columns, quadratic, rectangle

from torchmorph.mesh import Mesh, read_mesh, write_mesh
from torchmorph.mesh.io import FORMATS, format_of, write_morphed

F64 = torch.float64


def with_markers(points, cells) -> Mesh:
    """The mesh with a face set on its bottom (z = 0, or y = 0 in 2-D) and a node set."""
    mesh = Mesh(points, cells)
    axis = mesh.dim - 1
    face_sets = {}
    for block in mesh.boundary_facets:
        low = (mesh.points[block.nodes][..., axis] == 0).all(1)
        if bool(low.any()):
            face_sets.setdefault("bottom-wall", []).append((block.kind, block.nodes[low]))
    node_sets = {"corner": [0]}
    return Mesh(points, cells, node_sets, face_sets, name="m")


MESHES = {
    "hybrid": lambda: box(("wedge", "tetra"), 2),
    "hex+wedge": lambda: columns(2),
    "pyramids": lambda: box(("hexahedron", "pyramid"), 1),
    "tetra10": lambda: quadratic(*box(("tetra",), 1)),
    "hexahedron20": lambda: quadratic(*box(("hexahedron",), 1)),
    "wedge15": lambda: quadratic(*box(("wedge",), 1)),
    "hexahedron27": lambda: quadratic(*box(("hexahedron",), 1), full=True),
    "quad+": lambda: rectangle("quad", 2),
    "triangle6": lambda: quadratic(*rectangle("triangle", 2)),
    "quad9": lambda: quadratic(*rectangle("quad", 2), full=True),
}
LINEAR_ONLY = {"su2"}
#: formats that keep marker names (medit keeps references, not names)
NAMED = {"vtu", "vtk", "xdmf", "gmsh", "su2"}


def cases():
    for fmt, extension in [
        ("vtu", ".vtu"),
        ("vtk", ".vtk"),
        ("xdmf", ".xdmf"),
        ("gmsh", ".msh"),
        ("medit", ".mesh"),
        ("su2", ".su2"),
    ]:
        for name in MESHES:
            linear = name in ("hybrid", "hex+wedge", "pyramids", "quad+")
            if fmt in LINEAR_ONLY and not linear:
                continue
            if fmt in ("medit", "xdmf") and not linear:
                continue  # medit holds no quadratic kinds; meshio's XDMF no mix with them
            yield fmt, extension, name


@pytest.mark.parametrize(("fmt", "extension", "name"), list(cases()))
def test_every_cell_and_marker_survives_a_round_trip(tmp_path, fmt, extension, name):
    mesh = with_markers(*MESHES[name]())
    path = tmp_path / f"m{extension}"
    write_mesh(path, mesh)
    again = read_mesh(path)
    assert [b.kind for b in again.cells] == [b.kind for b in mesh.cells]
    for block, original in zip(again.cells, mesh.cells, strict=True):
        assert torch.equal(block.nodes, original.nodes), block.kind
    torch.testing.assert_close(again.points, mesh.points, rtol=0, atol=1e-12)
    torch.testing.assert_close(again.boundary_nodes, mesh.boundary_nodes)
    bottom = mesh.node_set("bottom-wall")
    if fmt in NAMED:
        assert "bottom-wall" in again.face_sets
        assert torch.equal(again.node_set("bottom-wall"), bottom)
    else:
        assert torch.equal(again.node_set(next(iter(again.face_sets))), bottom)
    if fmt not in ("su2", "medit"):
        assert torch.equal(again.node_set("corner"), torch.tensor([0]))


@pytest.mark.parametrize(
    ("extension", "name"), [(".vtu", "hybrid"), (".msh", "hexahedron20"), (".su2", "quad+")]
)
def test_a_file_written_again_moved_keeps_everything_else(tmp_path, extension, name):
    mesh = with_markers(*MESHES[name]())
    source = tmp_path / f"m{extension}"
    write_mesh(source, mesh, point_data={"temperature": torch.arange(mesh.num_nodes, dtype=F64)})
    moved = mesh.points * 1.5 + 0.25
    output = write_morphed(source, moved, tmp_path / f"moved{extension}")
    again, point_data, _ = read_mesh(output, return_data=True)
    torch.testing.assert_close(again.points, moved, rtol=0, atol=1e-12)
    assert again.markers == read_mesh(source).markers
    if extension != ".su2":
        torch.testing.assert_close(
            point_data["temperature"], torch.arange(mesh.num_nodes, dtype=F64)
        )


@pytest.mark.parametrize(
    ("extension", "message"),
    [
        (".mesh", "a medit file cannot hold cells of kind line3, triangle6"),
        (".xdmf", "meshio reads no XDMF file back whose topology mixes kinds"),
    ],
)
def test_formats_refuse_what_they_cannot_hold(tmp_path, extension, message):
    mesh = with_markers(*MESHES["triangle6"]())
    with pytest.raises(ValueError, match=message):
        write_mesh(tmp_path / f"m{extension}", mesh)
    assert not list(tmp_path.iterdir())  # nothing written


def test_msh_files_of_several_blocks_refuse_cell_data_meshio_cannot_read_back(tmp_path):
    mesh = Mesh(*columns(1))
    with pytest.raises(ValueError, match="meshio reads no MSH file back whose cell data spans"):
        write_mesh(tmp_path / "m.msh", mesh, cell_data={"q": torch.ones(mesh.num_cells)})
    write_mesh(tmp_path / "m.vtu", mesh, cell_data={"q": torch.ones(mesh.num_cells)})


def test_unsupported_cells_are_named_never_dropped(tmp_path):
    import meshio

    from torchmorph.mesh.io import from_meshio

    points = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]])
    higher = meshio.Mesh(points, [("tetra", [[0, 1, 2, 3]]), ("tetra20", [list(range(5)) * 4])])
    with pytest.raises(ValueError, match=r"cells of kind tetra20 cannot be handled"):
        from_meshio(higher)


def test_nastran_keeps_boundary_elements_as_property_ids(tmp_path):
    mesh = with_markers(*MESHES["hybrid"]())
    faces = mesh.face_sets["bottom-wall"]
    mesh = Mesh(
        mesh.points,
        [(b.kind, b.nodes) for b in mesh.cells],
        face_sets={"bottom-wall": faces, "pid7": faces[:1]},
    )
    write_mesh(tmp_path / "m.bdf", mesh)
    again = read_mesh(tmp_path / "m.bdf")
    assert [(b.kind, b.nodes.tolist()) for b in again.cells] == [
        (b.kind, b.nodes.tolist()) for b in mesh.cells
    ]
    # Nastran holds numbers: pid7 keeps its id, the other name gets the next free one
    assert set(again.face_sets) == {"pid7", "pid8"}
    assert torch.equal(again.face_sets["pid8"][0].nodes, faces[0].nodes)
    assert torch.equal(again.node_set("pid7"), mesh.node_set("pid7"))


@pytest.mark.parametrize("name", ["hex+wedge", "hexahedron20", "quad+"])
def test_abaqus_decks_written_new_get_every_marker_as_an_nset(tmp_path, name):
    mesh = with_markers(*MESHES[name]())
    write_mesh(tmp_path / "m.inp", mesh)
    text = (tmp_path / "m.inp").read_text()
    again = read_mesh(tmp_path / "m.inp")
    assert [(b.kind, b.nodes.tolist()) for b in again.cells] == [
        (b.kind, b.nodes.tolist()) for b in mesh.cells
    ]
    assert "*NSET" in text.upper() and not again.face_sets  # no boundary elements written
    for marker in mesh.markers:
        assert torch.equal(again.node_set(marker), mesh.node_set(marker)), marker


def test_lower_dimensional_cells_of_no_marker_are_kept(tmp_path):
    import meshio

    points, cells = MESHES["hybrid"]()
    mesh = Mesh(points, cells)
    triangles = mesh.boundary_facets[0].nodes.numpy()
    edges = triangles[:, :2]
    written = meshio.Mesh(
        np.asarray(points),
        [*[(k, np.asarray(c)) for k, c in cells], ("triangle", triangles), ("line", edges)],
    )
    meshio.write(tmp_path / "m.vtu", written)
    again = read_mesh(tmp_path / "m.vtu")
    assert mesh.boundary_facets[0].kind == "triangle"
    assert set(again.face_sets) == {"unmarked"} and set(again.node_sets) == {"unmarked_lines"}
    assert torch.equal(again.face_sets["unmarked"][0].nodes, torch.from_numpy(triangles))
    assert torch.equal(again.node_set("unmarked_lines"), torch.unique(torch.from_numpy(edges)))


def test_the_format_table(tmp_path):
    assert format_of("a.su2") is FORMATS["su2"] and format_of("a.inp") is FORMATS["abaqus"]
    assert format_of("a.MSH") is FORMATS["gmsh"] and format_of("d.inp.gz") is FORMATS["abaqus"]
    assert format_of(tmp_path) is FORMATS["openfoam"]  # a directory: a case
    with pytest.raises(ValueError, match=r"path: unsupported mesh file extension '.stl'"):
        format_of("body.stl")
    mesh = Mesh(*rectangle("quad", 1))
    with pytest.raises(ValueError, match="torchmorph writes no new openfoam files"):
        write_mesh(tmp_path, mesh)
    write_mesh(tmp_path / "a.su2", mesh)
    with pytest.raises(ValueError, match="output: .* is not a su2 file like the source"):
        write_morphed(tmp_path / "a.su2", mesh.points, tmp_path / "b.vtu")


def test_a_node_set_named_like_a_face_set_with_other_nodes_is_kept_renamed():
    from torchmorph.mesh.formats._data import MeshData
    from torchmorph.mesh.io import mesh_from_data

    points, cells = MESHES["hex+wedge"]()
    mesh = Mesh(points, cells)
    facets = [(b.kind, b.nodes.numpy()[:1]) for b in mesh.boundary_facets[:1]]
    own = np.unique(facets[0][1])
    data = MeshData(
        np.asarray(mesh.points),
        [(b.kind, b.nodes.numpy()) for b in mesh.cells],
        node_sets={"same": own, "other": np.union1d(own, [0, 1])},
        face_sets={"same": facets, "other": facets},
    )
    with pytest.warns(UserWarning, match="node set 'other' is named like a face set"):
        again = mesh_from_data(data)
    assert set(again.node_sets) == {"other_nodes"}  # 'same' is the face set's own nodes
    assert torch.equal(again.node_set("other_nodes"), torch.from_numpy(np.union1d(own, [0, 1])))
    assert torch.equal(again.node_set("other"), torch.from_numpy(own))
