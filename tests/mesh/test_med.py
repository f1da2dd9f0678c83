"""MED files (torchmorph.mesh.formats.med): every kind MED holds written and read back with
its groups, a file written by meshio with families of nodes, cells and boundary faces,
files written back moved with every other dataset kept, bad files refused by name, and a
morph through the command against an independent float64 IDW."""

from __future__ import annotations

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
KINDS["quad8"] = lambda: quadratic(*rectangle("quad", 2))
KINDS["tetra"] = lambda: box(("tetra",), 2)


def facets(mesh: Mesh) -> dict[str, list]:
    return {
        name: sorted((b.kind, tuple(sorted(row))) for b in blocks for row in b.nodes.tolist())
        for name, blocks in mesh.face_sets.items()
    }


@pytest.mark.parametrize("name", list(KINDS))
def test_every_kind_and_group_survives_a_round_trip(tmp_path, name):
    mesh = with_markers(*KINDS[name]())
    path = tmp_path / "m.med"
    first = torch.cat([mesh.points[b.nodes[:, 0], 0] for b in mesh.cells])
    regions = {"cell_set:left": (first < 1).to(torch.uint8)}  # cells by their first corner
    write_mesh(path, mesh, cell_data=regions)
    again, _, cell_data = read_mesh(path, return_data=True)
    assert [b.kind for b in again.cells] == [b.kind for b in mesh.cells]
    for block, original in zip(again.cells, mesh.cells, strict=True):
        assert torch.equal(block.nodes, original.nodes), block.kind
    assert torch.equal(again.points, mesh.points)
    assert facets(again) == facets(mesh)
    assert torch.equal(again.node_set("corner"), torch.tensor([0]))
    assert torch.equal(cell_data["cell_set:left"], regions["cell_set:left"])
    assert (torch.cat(again.orientation) == 1).all()


def test_meshios_med_reader_reads_the_groups_written(tmp_path):
    import meshio

    mesh = with_markers(*box(("hexahedron", "pyramid"), 1))
    write_mesh(tmp_path / "m.med", mesh, point_data={"T": torch.arange(mesh.num_nodes) * 1.0})
    m = meshio.read(tmp_path / "m.med")
    names = {n for groups in m.cell_tags.values() for n in groups}
    assert names == {"bottom-wall"} and list(m.point_tags.values()) == [["corner"]]
    np.testing.assert_array_equal(m.point_data["T"], np.arange(mesh.num_nodes))
    # MED lists a hexahedron's bottom face the other way round: its normal points out
    hexes = {b.type: b.data for b in m.cells}["hexahedron"]
    np.testing.assert_array_equal(hexes, mesh.cells[0].nodes.numpy()[:, [0, 3, 2, 1, 4, 7, 6, 5]])


def meshio_file(path: Path):
    """A MED file written by meshio: tetrahedra in MED's order (the face N1 N2 N3 turns
    so that its normal points away from N4, MED's and Code_Aster's convention: the
    reverse of VTK's), the bottom's triangles in families of one and of two groups, the
    other boundary triangles in none, families of nodes, and a field."""
    import meshio

    points, ((_, tets),) = box(("tetra",), 1)
    tets = tets[:, [0, 2, 1, 3]]  # VTK's order mirrored: MED's
    bottom = np.array([[0, 2, 6], [0, 6, 4]])  # z = 0: nodes 0 (0,0,0) 2 (0,1,0) 4 6
    top = np.array([[1, 5, 7], [1, 7, 3]])
    mesh = meshio.Mesh(
        points,
        [("tetra", tets), ("triangle", np.concatenate([bottom, top]))],
        point_data={"point_tags": np.array([1, 2, 0, 0, 0, 0, 0, 0]), "T": np.arange(8.0)},
        cell_data={"cell_tags": [np.full(6, -1), np.array([-2, -3, 0, 0])]},
    )
    mesh.point_tags = {1: ["corner"], 2: ["corner", "apex"]}
    mesh.cell_tags = {-1: ["solid"], -2: ["bottom"], -3: ["bottom", "wall"]}
    meshio.write(path, mesh)
    return points, tets, bottom, top


def test_a_file_written_by_meshio_with_families(tmp_path):
    points, tets, bottom, top = meshio_file(tmp_path / "f.med")
    mesh, point_data, cell_data = read_mesh(tmp_path / "f.med", return_data=True)
    np.testing.assert_array_equal(mesh.points.numpy(), points)
    np.testing.assert_array_equal(mesh.cells[0].nodes.numpy(), tets[:, [0, 2, 1, 3]])
    assert (mesh.orientation[0] == 1).all()  # MED's positive cells are torchmorph's
    assert facets(mesh) == {
        "bottom": sorted(("triangle", tuple(sorted(r))) for r in bottom.tolist()),
        "wall": [("triangle", tuple(sorted(bottom[1].tolist())))],
        "unmarked": sorted(("triangle", tuple(sorted(r))) for r in top.tolist()),
    }
    assert torch.equal(mesh.node_sets["corner"], torch.tensor([0, 1]))
    assert torch.equal(mesh.node_sets["apex"], torch.tensor([1]))
    assert torch.equal(cell_data["cell_set:solid"], torch.ones(6, dtype=torch.uint8))
    assert torch.equal(point_data["T"], torch.arange(8.0, dtype=torch.float64))


FIXTURE = Path(__file__).resolve().parents[1] / "data" / "medloader_block.med"


def test_a_file_written_by_salomes_med_library():
    """A file MEDCoupling's MEDLoader wrote (tests/data/make_medloader_block.py): cells it
    oriented itself come out positive, every mid-edge node at the middle of its edge as
    torchmorph's kinds number the edges, the groups where they were put."""
    from torchmorph.mesh.cells import CELL_KINDS

    mesh, _, cell_data = read_mesh(FIXTURE, return_data=True)
    assert mesh.cell_counts == {"hexahedron20": 1, "wedge15": 2}
    assert all((o == 1).all() for o in mesh.orientation)
    points = mesh.points.numpy()
    for block in mesh.cells:
        linear = CELL_KINDS[CELL_KINDS[block.kind].linear]
        nodes = block.nodes.numpy()
        for k, (a, b) in enumerate(linear.edges):
            middle = (points[nodes[:, a]] + points[nodes[:, b]]) / 2
            np.testing.assert_array_equal(points[nodes[:, linear.num_nodes + k]], middle)
    x, z = points[:, 0], points[:, 2]
    for name, on in (("inlet", x == 0), ("outlet", x == 2), ("floor", z == 0)):
        assert torch.equal(mesh.node_set(name), torch.from_numpy(np.flatnonzero(on))), name
    assert [b.kind for b in mesh.face_sets["floor"]] == ["quad8", "triangle6"]
    unmarked = mesh.node_set("unmarked")  # the skin's other faces
    assert torch.equal(
        torch.unique(torch.cat([unmarked, mesh.node_set("floor")])), mesh.boundary_nodes
    )
    assert torch.equal(mesh.node_sets["origin"], torch.tensor([0]))
    assert torch.equal(cell_data["cell_set:prisms"], torch.tensor([0, 1, 1], dtype=torch.uint8))


def test_a_file_written_again_moved_keeps_every_other_dataset(tmp_path):
    source = tmp_path / "f.med"
    meshio_file(source)
    mesh = read_mesh(source)
    moved = mesh.points * 2.0 - 0.5
    output = write_morphed(source, moved, tmp_path / "moved.med")
    again = read_mesh(output)
    assert torch.equal(again.points, moved)
    assert facets(again) == facets(mesh)
    before, after = datasets(source), datasets(output)
    assert before.keys() == after.keys()
    changed = {k for k in before if not np.array_equal(before[k], after[k])}
    assert changed == {"ENS_MAA/mesh/-0000000000000000001-0000000000000000001/NOE/COO"}


def datasets(path: Path) -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda n, obj: out.update({n: obj[()]}) if hasattr(obj, "shape") else None)
    return out


def test_bad_files_and_meshes_are_refused_by_name(tmp_path):
    meshio_file(tmp_path / "poly.med")
    with h5py.File(tmp_path / "poly.med", "r+") as f:
        step = f["ENS_MAA/mesh/-0000000000000000001-0000000000000000001/MAI"]
        step.create_group("POG")
    with pytest.raises(ValueError, match=r"polygons of MED type POG cannot be handled"):
        read_mesh(tmp_path / "poly.med")
    meshio_file(tmp_path / "two.med")
    with h5py.File(tmp_path / "two.med", "r+") as f:
        f.copy(f["ENS_MAA/mesh"], "ENS_MAA/other")
    with pytest.raises(ValueError, match=r"holds 2 meshes \(mesh, other\)"):
        read_mesh(tmp_path / "two.med")
    with pytest.raises(FileNotFoundError, match="does not exist"):
        read_mesh(tmp_path / "missing.med")
    pyramids = Mesh(*quadratic(*box(("hexahedron", "pyramid"), 1), full=True))
    with pytest.raises(ValueError, match=r"cannot hold 'pyramid14' cells: MED has no such type"):
        write_mesh(tmp_path / "p.med", pyramids)
    long_name = Mesh(*box(("tetra",), 1), node_sets={"n" * 81: [0]})
    with pytest.raises(
        ValueError, match="MED group names are non-empty strings of at most 80 bytes"
    ):
        write_mesh(tmp_path / "n.med", long_name)
    with pytest.raises(ValueError, match="MED field names hold 1 to 64 bytes"):
        write_mesh(
            tmp_path / "f.med", Mesh(*box(("tetra",), 1)), point_data={"f" * 65: torch.ones(8)}
        )
    assert not {"p.med", "n.med", "f.med"} & {p.name for p in tmp_path.iterdir()}


@pytest.mark.parametrize("name", ["tetra", "wedge15", "quad+"])
def test_a_morph_through_the_command_comes_back_as_med(tmp_path, name, capsys):
    from torchmorph.cli import EXIT_OK, main

    points, cells = KINDS[name]()
    source = tmp_path / "mesh.med"
    write_mesh(source, with_markers(points, cells))
    boundary = on_box_surface(points)
    p = points[boundary]
    rows = 0.03 * np.stack([np.cos(2 * p.sum(1) + k) for k in range(points.shape[1])], 1)
    np.save(tmp_path / "d.npy", rows)
    out = tmp_path / "out.med"
    arguments = ["morph", str(source), "-d", str(tmp_path / "d.npy"), "-o", str(out)]
    assert main([*arguments, "--strict", "--no-progress"]) == EXIT_OK
    assert "coordinates changed only" in capsys.readouterr().out
    moved = read_mesh(out)
    field = moved.points.numpy() - points
    np.testing.assert_allclose(field[boundary], rows, rtol=0, atol=4e-16 * np.abs(points).max())
    interior = np.setdiff1d(np.arange(len(points)), boundary)
    expected = idw_reference(points[interior], p, rows)
    np.testing.assert_allclose(field[interior], expected, rtol=0, atol=1e-9 * np.abs(rows).max())
    assert facets(moved) == facets(read_mesh(source))
