"""CGNS/HDF5 files (torchmorph.mesh.formats.cgns): every kind written and read back with
its markers, files laid out by hand as other tools write them (element sections, MIXED
sections of CGNS 3 and 4, BCs by PointRange, PointList, ElementRange and at vertices,
families), independent readers (meshio's, VTK's) of the files written, files written
back moved with every other node kept, bad files refused by name, and a morph through
the command against an independent float64 IDW."""

from __future__ import annotations

import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
from _kinds import box, idw_reference, on_box_surface, quadratic, rectangle
from test_formats import MESHES, with_markers

from torchmorph.mesh import Mesh, read_mesh, write_mesh
from torchmorph.mesh.io import write_morphed

KINDS = dict(MESHES)
KINDS["wedge18"] = lambda: quadratic(*box(("wedge",), 1), full=True)
KINDS["pyramid13"] = lambda: quadratic(*box(("hexahedron", "pyramid"), 1))
KINDS["pyramid14"] = lambda: quadratic(*box(("hexahedron", "pyramid"), 1), full=True)
KINDS["quad8"] = lambda: quadratic(*rectangle("quad", 2))
KINDS["tetra"] = lambda: box(("tetra",), 2)


def facets(mesh: Mesh) -> dict[str, list]:
    """Face sets as sorted (kind, sorted nodes) lists: equal whatever the block order."""
    return {
        name: sorted((b.kind, tuple(sorted(row))) for b in blocks for row in b.nodes.tolist())
        for name, blocks in mesh.face_sets.items()
    }


@pytest.mark.parametrize("name", list(KINDS))
def test_every_kind_and_marker_survives_a_round_trip(tmp_path, name):
    mesh = with_markers(*KINDS[name]())
    path = tmp_path / "m.cgns"
    write_mesh(path, mesh)
    again = read_mesh(path)
    assert [b.kind for b in again.cells] == [b.kind for b in mesh.cells]
    for block, original in zip(again.cells, mesh.cells, strict=True):
        assert torch.equal(block.nodes, original.nodes), block.kind
    assert torch.equal(again.points, mesh.points)  # R8: exact
    assert facets(again) == facets(mesh)
    assert again.node_sets.keys() == {"corner"}
    assert torch.equal(again.node_set("corner"), torch.tensor([0]))


@pytest.mark.parametrize("name", list(KINDS))
def test_vtks_own_cgns_reader_sees_the_cells_written(tmp_path, name):
    """VTK's reader (built on the CGNS library, with its own CGNS -> VTK permutations)
    reads every file written with the same connectivity in VTK's order, and the face
    sets as boundary patches."""
    pytest.importorskip("vtkmodules.vtkIOCGNSReader")
    from vtkmodules.vtkCommonCore import vtkLogger
    from vtkmodules.vtkIOCGNSReader import vtkCGNSReader

    vtkLogger.SetStderrVerbosity(vtkLogger.VERBOSITY_OFF)
    mesh = with_markers(*KINDS[name]())
    path = tmp_path / "m.cgns"
    write_mesh(path, mesh)
    reader = vtkCGNSReader()
    reader.SetFileName(str(path))
    reader.SetLoadBndPatch(1)
    reader.Update()
    blocks = {}
    iterator = reader.GetOutput().NewIterator()
    iterator.InitTraversal()
    while not iterator.IsDoneWithTraversal():
        name_of = iterator.GetCurrentMetaData().Get(reader.GetOutput().NAME())
        blocks[name_of] = iterator.GetCurrentDataObject()
        iterator.GoToNextItem()
    grid = blocks["Internal"]
    cells = [
        [grid.GetCell(i).GetPointId(j) for j in range(grid.GetCell(i).GetNumberOfPoints())]
        for i in range(grid.GetNumberOfCells())
    ]
    assert cells == [row for b in mesh.cells for row in b.nodes.tolist()]
    points = np.array([grid.GetPoint(i)[: mesh.dim] for i in range(grid.GetNumberOfPoints())])
    np.testing.assert_array_equal(points, mesh.points.numpy())
    assert blocks["bottom-wall"].GetNumberOfCells() == sum(
        len(b.nodes) for b in mesh.face_sets["bottom-wall"]
    )


def test_meshios_cgns_reader_reads_a_tetrahedral_file_written(tmp_path):
    """meshio's reader knows one tetrahedral section Base/Zone1/GridElements only."""
    import meshio

    mesh = with_markers(*box(("tetra",), 2))
    write_mesh(tmp_path / "m.cgns", mesh)
    m = meshio.read(tmp_path / "m.cgns")
    assert [b.type for b in m.cells] == ["tetra"]
    np.testing.assert_array_equal(m.cells[0].data, mesh.cells[0].nodes.numpy())
    np.testing.assert_array_equal(m.points, mesh.points.numpy())


# --------------------------------------------------------------------------- by hand


def node(parent, name, label, kind="MT", value=None):
    """A CGNS/HDF5 node as the CGNS library's ADFH layer lays it out (NUL-terminated
    33-byte name and label), written here without torchmorph."""
    group = parent.create_group(name, track_order=True)
    for key, text, size in (("name", name, 33), ("label", label, 33), ("type", kind, 3)):
        string = h5py.h5t.C_S1.copy()
        string.set_size(size)
        string.set_strpad(h5py.h5t.STR_NULLTERM)
        attribute = h5py.h5a.create(
            group.id, key.encode(), string, h5py.h5s.create(h5py.h5s.SCALAR)
        )
        attribute.write(np.array(text.encode().ljust(size, b"\0"), dtype=f"S{size}"), mtype=string)
    group.attrs.create("flags", np.array([1], dtype=np.int32))
    if kind == "C1":
        group.create_dataset(" data", data=np.frombuffer(value.encode(), dtype=np.int8))
    elif kind != "MT":
        dtype = {"I4": np.int32, "I8": np.int64, "R8": np.float64}[kind]
        group.create_dataset(" data", data=np.asarray(value, dtype=dtype))
    return group


# Two unit hexahedra side by side along x (nodes 1-based as in the file):
#   bottom z=0: 1 (0,0) 2 (1,0) 3 (2,0) 4 (0,1) 5 (1,1) 6 (2,1); top z=1: 7..12 likewise
HEXES = [[1, 2, 5, 4, 7, 8, 11, 10], [2, 3, 6, 5, 8, 9, 12, 11]]
# boundary quads, element ids 3..12: x=0, x=2, y=0 (two), y=1 (two), z=0 (two), z=1 (two)
QUADS = [
    [1, 4, 10, 7], [3, 9, 12, 6], [1, 7, 8, 2], [2, 8, 9, 3], [4, 5, 11, 10],
    [5, 6, 12, 11], [1, 2, 5, 4], [2, 3, 6, 5], [7, 10, 11, 8], [8, 11, 12, 9],
]  # fmt: skip


def hand_written(path: Path, domain: str = "HEXA_8", *, bad_bc: bool = False, zones: int = 1):
    """A file as a mesher writes it: the hexahedra (a HEXA_8 section, or MIXED as CGNS 3
    writes it, or MIXED with CGNS 4's ElementStartOffset), a QUAD_4 boundary section,
    and BCs: 'inlet' by PointRange at FaceCenter, 'walls' by PointList at FaceCenter
    with a family, 'outlet' by a CGNS 2 ElementRange, 'corner' at Vertex."""
    x, y, z = np.meshgrid([0.0, 1.0, 2.0], [0.0, 1.0], [0.0, 1.0], indexing="ij")
    order = np.lexsort((x.ravel(), y.ravel(), z.ravel()))  # x fastest, then y, then z
    coordinates = np.stack([x.ravel(), y.ravel(), z.ravel()], 1)[order]
    with h5py.File(path, "w", track_order=True) as f:
        node(f, "CGNSLibraryVersion", "CGNSLibraryVersion_t", "R8", [4.2])
        base = node(f, "Base", "CGNSBase_t", "I4", [3, 3])
        node(base, "wallfam", "Family_t")
        for k in range(zones):
            zone = node(base, f"blk{k}", "Zone_t", "I4", [[12], [2], [0]])
            node(zone, "ZoneType", "ZoneType_t", "C1", "Unstructured")
            grid = node(zone, "GridCoordinates", "GridCoordinates_t")
            for axis, column in zip("XYZ", coordinates.T, strict=True):
                node(grid, f"Coordinate{axis}", "DataArray_t", "R8", column)
            if domain == "HEXA_8":
                hexes = node(zone, "Hexes", "Elements_t", "I4", [17, 0])
                values = np.ravel(HEXES)
            else:
                hexes = node(zone, "Hexes", "Elements_t", "I4", [20, 0])
                values = np.ravel([[17, *h] for h in HEXES])
                if domain == "MIXED4":
                    node(hexes, "ElementStartOffset", "DataArray_t", "I8", [0, 9, 18])
            node(hexes, "ElementRange", "IndexRange_t", "I4", [1, 2])
            node(hexes, "ElementConnectivity", "DataArray_t", "I4", values)
            quads = node(zone, "Boundaries", "Elements_t", "I4", [7, 0])
            node(quads, "ElementRange", "IndexRange_t", "I4", [3, 12])
            node(quads, "ElementConnectivity", "DataArray_t", "I4", np.ravel(QUADS))
            zbc = node(zone, "ZoneBC", "ZoneBC_t")
            inlet = node(zbc, "inlet", "BC_t", "C1", "BCInflow")
            node(inlet, "GridLocation", "GridLocation_t", "C1", "FaceCenter")
            node(inlet, "PointRange", "IndexRange_t", "I4", [[3], [99 if bad_bc else 3]])
            walls = node(zbc, "walls", "BC_t", "C1", "FamilySpecified")
            node(walls, "GridLocation", "GridLocation_t", "C1", "FaceCenter")
            node(walls, "PointList", "IndexArray_t", "I4", [[5], [6], [7], [8]])
            node(walls, "FamilyName", "FamilyName_t", "C1", "wallfam")
            outlet = node(zbc, "outlet", "BC_t", "C1", "BCOutflow")
            node(outlet, "ElementRange", "IndexRange_t", "I4", [[4], [4]])
            corner = node(zbc, "corner", "BC_t", "C1", "BCWall")
            node(corner, "PointList", "IndexArray_t", "I4", [[1], [2]])
    return coordinates


@pytest.mark.parametrize("domain", ["HEXA_8", "MIXED3", "MIXED4"])
def test_a_file_laid_out_as_meshers_write_it(tmp_path, domain):
    coordinates = hand_written(tmp_path / "h.cgns", domain)
    mesh = read_mesh(tmp_path / "h.cgns")
    np.testing.assert_array_equal(mesh.points.numpy(), coordinates)
    assert [b.kind for b in mesh.cells] == ["hexahedron"]
    np.testing.assert_array_equal(mesh.cells[0].nodes.numpy(), np.array(HEXES) - 1)
    quads = np.array(QUADS) - 1
    expected = {  # hand-computed from the BCs; the quads no BC names keep their section's
        "inlet": quads[[0]],
        "walls": quads[[2, 3, 4, 5]],
        "outlet": quads[[1]],
        "Boundaries": quads[[6, 7, 8, 9]],
    }
    assert set(mesh.face_sets) == set(expected)
    for name, rows in expected.items():
        (block,) = mesh.face_sets[name]
        assert block.kind == "quad"
        np.testing.assert_array_equal(block.nodes.numpy(), rows)
    assert torch.equal(mesh.node_sets["corner"], torch.tensor([0, 1]))
    assert mesh.groups == {"wallfam": ("walls",)}
    assert torch.equal(mesh.node_set("wallfam"), torch.unique(torch.from_numpy(quads[2:6])))
    assert mesh.boundary_nodes.numel() == 12


def test_a_file_written_again_moved_keeps_every_other_node(tmp_path):
    source = tmp_path / "h.cgns"
    hand_written(source, "MIXED4")
    mesh = read_mesh(source)
    moved = mesh.points * 1.5 + 0.25
    output = write_morphed(source, moved, tmp_path / "moved.cgns")
    assert torch.equal(read_mesh(output).points, moved)
    assert read_mesh(output).markers == mesh.markers
    before, after = datasets(source), datasets(output)
    assert before.keys() == after.keys()
    changed = {k for k in before if not np.array_equal(before[k], after[k])}
    assert changed == {f"Base/blk0/GridCoordinates/Coordinate{a}/ data" for a in "XYZ"}
    assert attributes(source) == attributes(output)


def test_a_written_file_moved_keeps_its_fields_and_markers(tmp_path):
    mesh = with_markers(*box(("wedge", "tetra"), 2))
    source = tmp_path / "m.cgns"
    temperature = torch.arange(mesh.num_nodes, dtype=torch.float64)
    write_mesh(source, mesh, point_data={"T": temperature, "u": torch.ones(mesh.num_nodes, 3)})
    output = write_morphed(source, mesh.points + 1.0, tmp_path / "moved.cgns")
    again, point_data, _ = read_mesh(output, return_data=True)
    assert torch.equal(point_data["T"], temperature)
    assert set(point_data) == {"T", "u"}  # uX, uY, uZ in the file, one field again
    assert torch.equal(point_data["u"], torch.ones(mesh.num_nodes, 3, dtype=torch.float64))
    assert facets(again) == facets(mesh)
    before, after = datasets(source), datasets(output)
    assert {k for k in before if not np.array_equal(before[k], after[k])} == {
        f"Base/Zone1/GridCoordinates/Coordinate{a}/ data" for a in "XYZ"
    }


def datasets(path: Path) -> dict[str, np.ndarray]:
    out = {}
    with h5py.File(path, "r") as f:
        f.visititems(
            lambda name, obj: out.update({name: obj[()]}) if hasattr(obj, "shape") else None
        )
        out.update({name: f[name][()] for name in f if hasattr(f[name], "shape")})
    return out


def attributes(path: Path) -> dict[str, dict]:
    out = {}
    with h5py.File(path, "r") as f:
        f.visititems(
            lambda name, obj: out.update(
                {name: {k: bytes(np.asarray(v).tobytes()) for k, v in obj.attrs.items()}}
            )
        )
    return out


# --------------------------------------------------------------------------- bad files


def test_bad_files_are_refused_by_name(tmp_path):
    hand_written(tmp_path / "bc.cgns", bad_bc=True)
    with pytest.raises(
        ValueError, match=r"BC 'inlet' points at element ids outside the element sections' ranges"
    ):
        read_mesh(tmp_path / "bc.cgns")
    hand_written(tmp_path / "zones.cgns", zones=2)
    with pytest.raises(ValueError, match=r"holds 2 zones \(Base/blk0, Base/blk1\).*merge"):
        read_mesh(tmp_path / "zones.cgns")
    with pytest.raises(FileNotFoundError, match="does not exist"):
        read_mesh(tmp_path / "missing.cgns")
    (tmp_path / "adf.cgns").write_bytes(b"\xc0\xa8\xa3\xa9ADF Database Version B02012>" + bytes(64))
    with pytest.raises(ValueError, match="in the ADF format; torchmorph reads CGNS/HDF5"):
        read_mesh(tmp_path / "adf.cgns")


def test_polyhedral_sections_are_refused(tmp_path):
    path = tmp_path / "poly.cgns"
    hand_written(path)
    with h5py.File(path, "r+") as f:
        zone = f["Base/blk0"]
        faces = node(zone, "Faces", "Elements_t", "I4", [22, 0])
        node(faces, "ElementRange", "IndexRange_t", "I4", [13, 13])
        node(faces, "ElementStartOffset", "DataArray_t", "I4", [0, 4])
        node(faces, "ElementConnectivity", "DataArray_t", "I4", [1, 2, 5, 4])
    with pytest.raises(
        ValueError, match=r"section 'Faces': element type NGON_n: polyhedral sections not supported"
    ):
        read_mesh(path)


def test_names_cgns_cannot_hold_are_refused(tmp_path):
    mesh = Mesh(*box(("tetra",), 1), node_sets={"a/b": [0]})
    with pytest.raises(
        ValueError, match=r"data.node_sets: CGNS names must be non-empty strings without '/'"
    ):
        write_mesh(tmp_path / "m.cgns", mesh)
    mesh = Mesh(*box(("tetra",), 1), node_sets={"x" * 33: [0]})
    with pytest.raises(ValueError, match="CGNS names hold at most 32 characters"):
        write_mesh(tmp_path / "m.cgns", mesh)
    assert not list(tmp_path.iterdir())


# --------------------------------------------------------------------------- command


@pytest.mark.parametrize("name", ["tetra", "hexahedron20", "quad+"])
def test_a_morph_through_the_command_comes_back_as_cgns(tmp_path, name, capsys):
    from torchmorph.cli import EXIT_OK, main

    points, cells = KINDS[name]()
    source = tmp_path / "mesh.cgns"
    write_mesh(source, with_markers(points, cells))
    boundary = on_box_surface(points)
    p = points[boundary]
    rows = 0.03 * np.stack([np.cos(2 * p.sum(1) + k) for k in range(points.shape[1])], 1)
    np.save(tmp_path / "d.npy", rows)
    out = tmp_path / "out.cgns"
    arguments = ["morph", str(source), "-d", str(tmp_path / "d.npy"), "-o", str(out)]
    assert main([*arguments, "--strict", "--no-progress"]) == EXIT_OK
    assert "coordinates changed only" in capsys.readouterr().out
    moved = read_mesh(out)
    field = moved.points.numpy() - points
    scale = np.abs(rows).max()
    # the file holds the moved coordinates: d is exact to their rounding
    np.testing.assert_allclose(field[boundary], rows, rtol=0, atol=4e-16 * np.abs(points).max())
    interior = np.setdiff1d(np.arange(len(points)), boundary)
    expected = idw_reference(points[interior], p, rows)
    np.testing.assert_allclose(field[interior], expected, rtol=0, atol=1e-9 * scale)
    assert facets(moved) == facets(read_mesh(source))


if __name__ == "__main__":  # pragma: no cover
    sys.exit(pytest.main([__file__]))
