"""CGNS/HDF5 files (torchmorph.mesh.formats.cgns), what is refused and what is kept: node
sets and fields of the wrong size or type refused by name on writing, integers kept
exact, cell-centred fields of a MIXED section read by element id, vector fields read
back as one, malformed sections, offsets and coordinates refused naming the node, a BC
of facets and edges whose nodes differ kept as two markers."""

from __future__ import annotations

import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
from _kinds import box, columns

from torchmorph.mesh.formats._cgns_nodes import new_node
from torchmorph.mesh.formats._data import MeshData
from torchmorph.mesh.formats._hdf5 import set_text_attribute
from torchmorph.mesh.formats.cgns import move_cgns, read_cgns, write_cgns

ZONE = "Base/Zone1"


def hex_and_wedges(**kwargs) -> MeshData:
    points, cells = columns(2)[:2]  # 4 hexahedra, 8 prisms, 27 nodes
    return MeshData(points=points, cells=cells, **kwargs)


@pytest.mark.parametrize(
    ("entry", "match"),
    [
        ({"node_sets": {"a": np.array([1.7])}}, r"data.node_sets\['a'\]: node rows must be int"),
        ({"node_sets": {"a": np.array([27])}}, r"data.node_sets\['a'\]: rows outside \[0, 27\)"),
        (
            {"point_data": {"u": np.ones(26)}},
            r"data.point_data\['u'\]: must be numbers of shape \(27,\)",
        ),
        (
            {"cell_data": {"c": [np.arange(3.0), np.arange(9.0)]}},
            r"data.cell_data\['c'\]: must be numbers of shape \(4,\)",
        ),
        ({"cell_data": {"c": [np.arange(4.0)]}}, r"data.cell_data\['c'\]: 1 arrays for 2"),
        (
            {"point_data": {"u": np.full(27, 2**63, np.uint64)}},
            r"data.point_data\['u'\]: unsigned integers above 2\*\*63 - 1",
        ),
        (
            {"node_sets": {"n": np.array([0])}, "groups": {"Zone1": ["n"]}},
            r"data.groups: a group named 'Zone1' cannot be written",
        ),
    ],
)
def test_bad_sets_fields_and_groups_are_refused_on_writing(tmp_path, entry, match):
    with pytest.raises(ValueError, match=match):
        write_cgns(tmp_path / "m.cgns", hex_and_wedges(**entry))
    assert not list(tmp_path.iterdir())


def test_integer_fields_and_vectors_come_back_as_written(tmp_path):
    fields = {
        "big": np.full(27, 3_000_000_000, np.uint32),
        "small": np.arange(27, dtype=np.int16),
        "flag": np.arange(27) % 2 == 0,
        "u": np.arange(81.0).reshape(27, 3),
        "w": np.ones((27, 1)),
    }
    write_cgns(tmp_path / "m.cgns", hex_and_wedges(point_data=fields))
    again = read_cgns(tmp_path / "m.cgns")
    assert again.point_data.keys() == fields.keys()
    fields["w"] = fields["w"][:, 0]  # one column: one array, no suffix
    for name, values in fields.items():
        assert again.point_data[name].shape == values.shape, name
        np.testing.assert_array_equal(again.point_data[name], values)
    with h5py.File(tmp_path / "m.cgns") as f:
        assert "ZoneBC" not in f[ZONE]  # no markers: no ZoneBC_t


def test_a_planar_vector_comes_back_as_one_field(tmp_path):
    from _kinds import rectangle

    points, cells = rectangle("quad", 2)
    uv = np.arange(2.0 * len(points)).reshape(-1, 2)
    write_cgns(tmp_path / "m.cgns", MeshData(points=points, cells=cells, point_data={"uv": uv}))
    np.testing.assert_array_equal(read_cgns(tmp_path / "m.cgns").point_data["uv"], uv)


def mixed(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """The hexahedra and prisms of :func:`hex_and_wedges` in one MIXED section, the kinds
    interleaved, with a cell-centred field of each element's id; returns the ids of the
    hexahedra and of the prisms."""
    data = hex_and_wedges(cell_data={"c": [np.zeros(4), np.zeros(8)]})
    write_cgns(path, data)
    (_, hexes), (_, wedges) = data.cells
    order = [("h", 0), ("w", 0), ("w", 1), ("h", 1), ("w", 2), ("w", 3), ("h", 2)]
    order += [("w", 4), ("w", 5), ("h", 3), ("w", 6), ("w", 7)]
    connectivity: list[int] = []
    for kind, i in order:
        connectivity += [17, *(hexes[i] + 1)] if kind == "h" else [14, *(wedges[i] + 1)]
    with h5py.File(path, "r+") as f:
        zone = f[ZONE]
        for name in [n for n in zone if n.startswith("GridElements")]:
            del zone[name]
        section = new_node(zone, "Mixed", "Elements_t", "I4", [20, 0])
        new_node(section, "ElementRange", "IndexRange_t", "I4", [1, 12])
        new_node(section, "ElementConnectivity", "DataArray_t", "I4", np.array(connectivity))
        del zone["FlowSolutionCells/c/ data"]
        zone["FlowSolutionCells/c"].create_dataset(" data", data=np.arange(1.0, 13.0))
    return np.array([1, 4, 7, 10]), np.array([2, 3, 5, 6, 8, 9, 11, 12])


def test_cell_centred_fields_of_a_mixed_section_are_read_by_element_id(tmp_path):
    hex_ids, wedge_ids = mixed(tmp_path / "m.cgns")
    again = read_cgns(tmp_path / "m.cgns")
    assert [(kind, len(nodes)) for kind, nodes in again.cells] == [
        ("hexahedron", 4),
        ("wedge", 8),
    ]
    np.testing.assert_array_equal(again.cell_data["c"][0], hex_ids)
    np.testing.assert_array_equal(again.cell_data["c"][1], wedge_ids)


def test_a_negative_element_start_offset_is_refused(tmp_path):
    points, cells = box(("hexahedron",), 1)
    write_cgns(tmp_path / "o.cgns", MeshData(points=points, cells=cells))
    with h5py.File(tmp_path / "o.cgns", "r+") as f:
        zone = f[ZONE]
        del zone["GridElements"]
        section = new_node(zone, "Mixed", "Elements_t", "I4", [20, 0])
        new_node(section, "ElementRange", "IndexRange_t", "I4", [1, 2])
        new_node(section, "ElementStartOffset", "DataArray_t", "I4", np.array([-9, 0, 9]))
        new_node(section, "ElementConnectivity", "DataArray_t", "I4", [17, *(cells[0][1][0] + 1)])
    with pytest.raises(ValueError, match=r"'Mixed': ElementStartOffset must start at 0"):
        read_cgns(tmp_path / "o.cgns")


def put(f, name: str, values) -> None:
    del f[name + "/ data"]
    f[name].create_dataset(" data", data=values)


CORRUPTIONS = {
    "no ElementRange data": (
        lambda f: f[ZONE + "/GridElements/ElementRange"].__delitem__(" data"),
        r"section 'GridElements': ElementRange holds 0",
    ),
    "one-value ElementRange": (
        lambda f: put(f, ZONE + "/GridElements/ElementRange", np.array([1], np.int32)),
        r"section 'GridElements': ElementRange holds 1 int32 values, not two integers",
    ),
    "empty section header": (
        lambda f: put(f, ZONE + "/GridElements", np.zeros(0, np.int32)),
        r"section 'GridElements': its data \(element type, boundary count\) is 0",
    ),
    "short point field": (
        lambda f: put(f, ZONE + "/FlowSolution/uX", np.ones(26)),
        r"FlowSolution 'FlowSolution': uX holds 26 values for the zone's 27 vertices",
    ),
    "long cell field": (
        lambda f: put(f, ZONE + "/FlowSolutionCells/c", np.ones(13)),
        r"FlowSolution 'FlowSolutionCells': c holds 13 values for the zone's 12 cells",
    ),
    "float PointList": (
        lambda f: put(f, ZONE + "/ZoneBC/n/PointList", np.array([[0.5], [1.7]])),
        r"BC 'n': PointList holds float64 values, not integer ids",
    ),
}


def written(tmp_path: Path) -> Path:
    points, cells = columns(2)[:2]
    data = MeshData(
        points=points,
        cells=cells,
        node_sets={"n": np.array([0, 1])},
        face_sets={"f": [("quad", cells[0][1][:1, :4])]},
        point_data={"u": np.ones((len(points), 3))},
        cell_data={"c": [np.ones(4), np.ones(8)]},
    )
    write_cgns(tmp_path / "g.cgns", data)
    return tmp_path / "g.cgns"


@pytest.mark.parametrize("name", list(CORRUPTIONS))
def test_malformed_files_are_refused_naming_the_node(tmp_path, name):
    change, match = CORRUPTIONS[name]
    path = written(tmp_path)
    with h5py.File(path, "r+") as f:
        change(f)
    with pytest.raises(ValueError, match=rf"path: '{path}': {match}"):
        read_cgns(path)


@pytest.mark.parametrize(
    ("change", "match"),
    [
        (lambda grid: grid.__delitem__("CoordinateY"), "GridCoordinates has no CoordinateY"),
        (lambda grid: grid.__delitem__("CoordinateY/ data"), "GridCoordinates has no CoordinateY"),
        (
            lambda grid: put(grid, "CoordinateY", np.ones(26)),
            "CoordinateY holds 26 values for the zone's 27 vertices",
        ),
    ],
)
def test_a_file_with_malformed_coordinates_is_not_moved(tmp_path, change, match):
    good = written(tmp_path)
    path = tmp_path / "b.cgns"
    shutil.copy(good, path)
    with h5py.File(path, "r+") as f:
        change(f[ZONE + "/GridCoordinates"])
    with pytest.raises(ValueError, match=rf"path: '{path}': {match}"):
        move_cgns(path, read_cgns(good).points, tmp_path / "moved.cgns")
    assert not (tmp_path / "moved.cgns").exists()


def test_a_bc_of_facets_and_edges_of_other_nodes_keeps_both(tmp_path):
    """A BC referring to a boundary quadrangle and to an edge off it: the face set keeps
    the name, the edge's nodes become the node set '<BC>_nodes'."""
    path = written(tmp_path)
    data = read_cgns(path)
    quad = data.face_sets["f"][0][1][0]
    edge = [quad[0], next(n for n in range(27) if n not in quad)]
    with h5py.File(path, "r+") as f:
        zone = f[ZONE]
        last = int(zone["f/ElementRange/ data"][1])
        bars = new_node(zone, "Edges", "Elements_t", "I4", [3, 0])
        new_node(bars, "ElementRange", "IndexRange_t", "I4", [last + 1, last + 1])
        new_node(bars, "ElementConnectivity", "DataArray_t", "I4", np.array(edge) + 1)
        bc = zone["ZoneBC/f"]
        del bc["PointRange"]
        new_node(bc, "PointList", "IndexArray_t", "I4", np.array([[last], [last + 1]]))
    with pytest.warns(UserWarning, match=r"BC 'f' is named like a face set .* 'f_nodes'"):
        again = read_cgns(path)
    assert [kind for kind, _ in again.face_sets["f"]] == ["quad"]
    assert again.node_sets["f_nodes"].tolist() == sorted(edge)


def test_text_attributes_too_long_are_refused(tmp_path):
    with h5py.File(tmp_path / "t.h5", "w") as f:
        with pytest.raises(ValueError, match="name: 'x{33}' holds 33 bytes; .* at most 32"):
            set_text_attribute(f, "name", "x" * 33, 33)
