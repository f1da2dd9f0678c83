"""MED files (torchmorph.mesh.formats.med), what is refused and what is kept: node sets,
groups of cells and fields of the wrong size or type refused by name on writing, files
whose datasets are missing or of the wrong size refused naming the dataset, a group of
nodes named like a group of faces, empty groups, and MED's own numbering of the HEXA27
and PENTA18 face centres (a file Salome's MED library wrote)."""

from __future__ import annotations

import warnings
from pathlib import Path

import h5py
import numpy as np
import pytest
from _kinds import box, columns

from torchmorph.mesh import read_mesh
from torchmorph.mesh.formats._data import MeshData
from torchmorph.mesh.formats.med import move_med, read_med, write_med

STEP = "ENS_MAA/mesh/-0000000000000000001-0000000000000000001"
FIXTURE = Path(__file__).resolve().parents[1] / "data" / "medloader_full.med"


def hex_and_wedges(**kwargs) -> MeshData:
    points, cells = columns(2)[:2]  # 4 hexahedra, 8 prisms, 27 nodes
    return MeshData(points=points, cells=cells, **kwargs)


@pytest.mark.parametrize(
    ("entry", "match"),
    [
        ({"node_sets": {"a": np.array([-1])}}, r"data.node_sets\['a'\]: rows outside \[0, 27\)"),
        ({"node_sets": {"a": np.array([27])}}, r"data.node_sets\['a'\]: rows outside \[0, 27\)"),
        ({"node_sets": {"a": np.array([1.7])}}, r"data.node_sets\['a'\]: node rows must be int"),
        (
            {"cell_data": {"cell_set:g": [np.array([1, 0]), np.array([1, 0])]}},
            r"data.cell_data\['cell_set:g'\]: must be numbers of shape \(4,\)",
        ),
        (
            {"cell_data": {"cell_set:g": [np.array([1, 0, 0, 0])]}},
            r"data.cell_data\['cell_set:g'\]: 1 arrays for 2 cell blocks",
        ),
        (
            {"point_data": {"u": np.ones(26)}},
            r"data.point_data\['u'\]: must be numbers of shape \(27,\)",
        ),
        (
            {"cell_data": {"c": [np.arange(3.0), np.arange(9.0)]}},
            r"data.cell_data\['c'\]: must be numbers of shape \(4,\)",
        ),
    ],
)
def test_bad_sets_and_fields_are_refused_on_writing(tmp_path, entry, match):
    with pytest.raises(ValueError, match=match):
        write_med(tmp_path / "m.med", hex_and_wedges(**entry))
    assert not list(tmp_path.iterdir())


def test_empty_node_sets_and_face_sets_are_kept(tmp_path):
    data = hex_and_wedges(node_sets={"none": np.zeros(0, np.int64)}, face_sets={"nothing": []})
    write_med(tmp_path / "m.med", data)
    again = read_med(tmp_path / "m.med")
    assert again.node_sets.keys() == {"none"} and again.node_sets["none"].size == 0
    assert again.face_sets == {"nothing": []}


def edited(tmp_path: Path, change) -> Path:
    """A file written with node and face groups, groups of cells and fields, then
    ``change``d."""
    points, cells = columns(2)[:2]
    data = MeshData(
        points=points,
        cells=cells,
        node_sets={"n": np.array([0, 1])},
        face_sets={"f": [("quad", cells[0][1][:1, :4])]},
        point_data={"u": np.ones((len(points), 3))},
        cell_data={"c": [np.ones(4), np.ones(8)], "cell_set:left": [np.ones(4), np.zeros(8)]},
    )
    path = tmp_path / "m.med"
    write_med(path, data)
    with h5py.File(path, "r+") as f:
        change(f)
    return path


def replace(f, name: str, values, count: int | None = None) -> None:
    parent, _, leaf = name.rpartition("/")
    del f[name]
    dataset = f[parent].create_dataset(leaf, data=values)
    if count is not None:
        dataset.attrs["NBR"] = np.int64(count)


_NP = "MED_NO_PROFILE_INTERNAL"
CORRUPTIONS = {
    "no NOE": (lambda f: f[STEP].__delitem__("NOE"), r"has no nodes \(NOE/COO\)"),
    "no NBR": (
        lambda f: f[STEP + "/NOE/COO"].attrs.__delitem__("NBR"),
        r"NOE/COO has no NBR",
    ),
    "wrong NBR": (
        lambda f: f[STEP + "/NOE/COO"].attrs.__setitem__("NBR", np.int64(5)),
        r"NOE/COO holds 81 values, not NBR = 5 rows of 3",
    ),
    "wrong ESP": (
        lambda f: f["ENS_MAA/mesh"].attrs.__setitem__("ESP", np.int64(2)),
        r"NOE/COO holds 81 values, not NBR = 27 rows of 2",
    ),
    "no NOD": (lambda f: f[STEP + "/MAI/HE8"].__delitem__("NOD"), r"MAI/HE8 has no NOD"),
    "short NOD": (
        lambda f: replace(f, STEP + "/MAI/HE8/NOD", f[STEP + "/MAI/HE8/NOD"][:-1], 4),
        r"MAI/HE8/NOD holds 31 values, not NBR = 4 rows of 8",
    ),
    "short node FAM": (
        lambda f: replace(f, STEP + "/NOE/FAM", f[STEP + "/NOE/FAM"][:3]),
        r"NOE/FAM holds 3 int64 values, not a family number for each of the 27",
    ),
    "long HE8 FAM": (
        lambda f: replace(f, STEP + "/MAI/HE8/FAM", np.tile(f[STEP + "/MAI/HE8/FAM"][()], 2)),
        r"MAI/HE8/FAM holds 8 int64 values, not a family number for each of the 4",
    ),
    "short QU4 FAM": (
        lambda f: replace(f, STEP + "/MAI/QU4/FAM", np.zeros(0, np.int64)),
        r"MAI/QU4/FAM holds 0 int64 values",
    ),
    "50-byte group name": (
        lambda f: replace(f, "FAS/mesh/ELEME/FAM_-1/GRO/NOM", np.zeros(50, np.int8)),
        r"FAS/mesh/ELEME/FAM_-1/GRO/NOM holds 50 bytes, not names of 80",
    ),
    "point field of N - 1 rows": (
        lambda f: replace(f, f"CHA/u/{next(iter(f['CHA/u']))}/NOE/{_NP}/CO", np.ones(78)),
        r"field 'u' holds 78 values on the nodes \(.*/CO\), not 27 rows of NCO = 3",
    ),
    "cell field of the wrong length": (
        lambda f: replace(f, f"CHA/c/{next(iter(f['CHA/c']))}/MAI.HE8/{_NP}/CO", np.ones(3)),
        r"field 'c' holds 3 values on the HE8 elements \(.*/CO\), not 4 rows",
    ),
}


@pytest.mark.parametrize("name", list(CORRUPTIONS))
def test_malformed_files_are_refused_naming_the_dataset(tmp_path, name):
    change, match = CORRUPTIONS[name]
    path = edited(tmp_path, change)
    with pytest.raises(ValueError, match=rf"path: '{path}': .*{match}"):
        read_med(path)


def test_a_file_without_coordinates_is_not_moved(tmp_path):
    path = edited(tmp_path, lambda f: f[STEP + "/NOE"].__delitem__("COO"))
    with pytest.raises(ValueError, match=r"has no nodes \(NOE/COO\)"):
        move_med(path, np.zeros((27, 3)), tmp_path / "moved.med")
    assert not (tmp_path / "moved.med").exists()


def named_like_faces(path: Path, node_tags: list[int]) -> None:
    """meshio's MED file of a box of tetrahedra whose group 'bottom' holds the bottom's
    two triangles and the nodes flagged in ``node_tags``."""
    import meshio

    points, ((_, tets),) = box(("tetra",), 1)
    mesh = meshio.Mesh(
        points,
        [("tetra", tets[:, [0, 2, 1, 3]]), ("triangle", np.array([[0, 2, 6], [0, 6, 4]]))],
        point_data={"point_tags": np.array(node_tags)},
        cell_data={"cell_tags": [np.zeros(6, int), np.array([-2, -2])]},
    )
    mesh.point_tags = {1: ["bottom"]}
    mesh.cell_tags = {-2: ["bottom"]}
    meshio.write(path, mesh)


def test_a_group_of_nodes_named_like_a_group_of_faces_keeps_its_nodes(tmp_path):
    named_like_faces(tmp_path / "other.med", [1, 1, 1, 0, 1, 0, 1, 0])  # node 1 is no face's
    with pytest.warns(UserWarning, match="read as the node set 'bottom_nodes'"):
        mesh = read_mesh(tmp_path / "other.med")
    assert mesh.node_sets["bottom_nodes"].tolist() == [0, 1, 2, 4, 6]
    assert mesh.node_set("bottom").tolist() == [0, 2, 4, 6]
    named_like_faces(tmp_path / "same.med", [1, 0, 1, 0, 1, 0, 1, 0])  # the faces' nodes
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mesh = read_mesh(tmp_path / "same.med")
    assert mesh.markers == ("bottom",)
    assert mesh.node_set("bottom").tolist() == [0, 2, 4, 6]


def test_meds_own_hexa27_and_penta18_numbering():
    """A file MEDCoupling wrote (tests/data/make_medloader_full.py), the face and body
    centres placed by its own cell models: read in VTK's order, every mid-edge node is at
    the middle of its edge and every face centre at the centre of its face as torchmorph's
    kinds number them (a wrong permutation puts a centre on another face)."""
    from torchmorph.mesh.cells import CELL_KINDS

    data = read_med(FIXTURE)
    assert [(kind, len(nodes)) for kind, nodes in data.cells] == [
        ("hexahedron27", 1),
        ("wedge18", 2),
    ]
    faces = {
        "hexahedron27": ((0, 3, 7, 4), (1, 2, 6, 5), (0, 1, 5, 4), (3, 2, 6, 7), (0, 1, 2, 3))
        + ((4, 5, 6, 7),),
        "wedge18": ((0, 1, 4, 3), (1, 2, 5, 4), (2, 0, 3, 5)),
    }
    points = data.points
    for kind, nodes in data.cells:
        linear = CELL_KINDS[CELL_KINDS[kind].linear]
        first = linear.num_nodes + len(linear.edges)
        for row in nodes:
            for k, (a, b) in enumerate(linear.edges):
                middle = (points[row[a]] + points[row[b]]) / 2
                np.testing.assert_allclose(points[row[linear.num_nodes + k]], middle, atol=1e-15)
            for k, face in enumerate(faces[kind]):
                centre = points[row[list(face)]].mean(0)
                np.testing.assert_allclose(points[row[first + k]], centre, atol=1e-15)
            if kind == "hexahedron27":
                np.testing.assert_allclose(points[row[26]], points[row[:8]].mean(0), atol=1e-15)
    mesh = read_mesh(FIXTURE)
    assert all((o == 1).all() for o in mesh.orientation)
