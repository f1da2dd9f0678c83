"""Exodus II files that are malformed, and data that cannot be written: every error is a
``ValueError`` naming the file (or the data's entry) and what is wrong, with nothing read
silently wrong or dropped. Malformed files are written with netCDF4 directly."""

from __future__ import annotations

import re

import numpy as np
import pytest
from _kinds import box, columns, rectangle
from test_exodus import KINDS, raw_exodus

from torchmorph.mesh import Mesh, read_mesh, write_mesh
from torchmorph.mesh.formats._data import MeshData
from torchmorph.mesh.formats.exodus import read_exodus, write_exodus
from torchmorph.mesh.io import mesh_data

netCDF4 = pytest.importorskip("netCDF4")


def _hex_file(path, elem_type="HEX8", side_sets=(), extra=()):
    points, cells = box(("hexahedron",), 1)
    raw_exodus(path, points, [(elem_type, cells[0][1] + 1), *extra], side_sets=side_sets)


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        ({"side_sets": [("wall", [1, 99], [1, 2])]}, (r"side set 10 \('wall'\): entry 1 names "
         r"element 99, outside the file's elements 1\.\.1")),
        ({"side_sets": [("wall", [1], [7])]}, (r"side set 10 \('wall'\): entry 0: side 7 of element 1 \(element block 10 "
         r"\(HEX8\)\) is not one of its sides 1\.\.6")),
        ({"elem_type": "HEX9"}, (r"element block 10: element type 'HEX9' names 9 nodes "
         r"per element, the block has 8")),
        ({"elem_type": "BRICK"}, (r"element block 10: element type 'BRICK' is not "
         r"supported; supported: TETRA/TET")),
        ({"extra": [("BEAM2", [[1, 2]])]}, (r"element block 20 \(BEAM2\): 1-D elements in a "
         r"3-D mesh cannot be represented")),
        ({"extra": [("QUAD4", [[1, 2, 3, 7]])]}, (r"element block 20 \(QUAD4\): row 0 \(quad "
         r"\[0, 1, 2, 6\]\) is no side of a cell of the mesh; a block of 2-D elements")),
    ],
)  # fmt: skip
def test_read_errors_name_the_file_and_the_entry(tmp_path, arguments, message):
    _hex_file(tmp_path / "bad.exo", **arguments)
    with pytest.raises(ValueError, match=r"path: '.*bad\.exo': " + message):
        read_mesh(tmp_path / "bad.exo")


def test_missing_and_foreign_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        read_exodus(tmp_path / "none.exo")
    with pytest.raises(FileNotFoundError, match="does not exist"):
        read_mesh(tmp_path / "none.e")
    (tmp_path / "text.exo").write_text("not netCDF\n")
    with pytest.raises(ValueError, match="is not a netCDF file"):
        read_mesh(tmp_path / "text.exo")


def test_write_errors_leave_nothing(tmp_path):
    mesh = Mesh(*KINDS["hexahedron20"]())
    data = mesh_data(mesh)
    facet = mesh.boundary_facets[0]  # quad8 facets
    data.face_sets = {"linear": [("quad", facet.nodes[:1, :4].numpy())]}
    with pytest.raises(
        ValueError, match=r"data.face_sets\['linear'\]\[0\]: row 0 .* a quad8: give it"
    ):
        write_exodus(tmp_path / "m.exo", data)
    nodes = facet.nodes[:2].numpy().copy()
    elsewhere = np.setdiff1d(np.arange(mesh.num_nodes), nodes[0])[0]
    nodes[1, 0] = elsewhere  # a corner off the face
    data.face_sets = {"nowhere": [("quad8", nodes)]}
    with pytest.raises(ValueError, match=r"\]\[0\]: row 1 .* is no side of a cell of the mesh"):
        write_exodus(tmp_path / "m.exo", data)
    nodes = facet.nodes[:1].numpy().copy()
    nodes[0, 7] = elsewhere  # a mid-side node off the face
    data.face_sets = {"midway": [("quad8", nodes)]}
    with pytest.raises(ValueError, match="row 0 .* has the corners of side .* not its other nodes"):
        write_exodus(tmp_path / "m.exo", data)
    data.face_sets = {"edge": [("line", np.array([[0, 1]]))]}
    with pytest.raises(ValueError, match="'line' is not a facet of a 3-D mesh"):
        write_exodus(tmp_path / "m.exo", data)
    assert not list(tmp_path.iterdir())


def test_without_netcdf4_the_message_names_the_extra(tmp_path, monkeypatch):
    import sys

    write_mesh(tmp_path / "m.exo", Mesh(*KINDS["quad"]()))
    monkeypatch.setitem(sys.modules, "netCDF4", None)
    with pytest.raises(ImportError, match=r"netCDF4 package: pip install 'torchmorph\[exodus\]'"):
        read_mesh(tmp_path / "m.exo")


# --------------------------------------------------------------------------- side numbers


def _hex_and_wedges(path, elements, sides):
    """Hexahedra (block 10, elements 1-4) beside wedges (block 20, elements 5-12) with one
    side set ``wall`` of the given elements and sides."""
    points, cells = columns(2)
    blocks = [("HEX8", cells[0][1] + 1), ("WEDGE6", cells[1][1] + 1)]
    raw_exodus(path, points, blocks, side_sets=[("wall", elements, sides)])
    return cells


@pytest.mark.parametrize(
    ("element", "side", "block", "valid"),
    [(1, 1025, r"10 \(HEX8\)", "1..6"), (1, 1029, r"10 \(HEX8\)", "1..6"),
     (5, -1019, r"20 \(WEDGE6\)", "1..5"), (5, 0, r"20 \(WEDGE6\)", "1..5"),
     (5, 6, r"20 \(WEDGE6\)", "1..5")],
)  # fmt: skip
def test_a_side_number_out_of_its_elements_range(tmp_path, element, side, block, valid):
    # 1025 was read as side 1 of the next block's element, -1019 raised an IndexError
    _hex_and_wedges(tmp_path / "bad.exo", [5, element], [1, side])
    message = (
        rf"path: '.*bad\.exo': side set 10 \('wall'\): entry 1: side {side} of element "
        rf"{element} \(element block {block}\) is not one of its sides {valid}"
    )
    with pytest.raises(ValueError, match=message):
        read_exodus(tmp_path / "bad.exo")


def test_side_sets_over_two_blocks_keep_their_order(tmp_path):
    cells = _hex_and_wedges(tmp_path / "ok.exo", [5, 1, 6, 2], [4, 1, 1, 6])
    hexes, wedges = cells[0][1], cells[1][1]
    triangles, quads = read_exodus(tmp_path / "ok.exo").face_sets["wall"]
    assert triangles[0] == "triangle" and quads[0] == "quad"
    np.testing.assert_array_equal(triangles[1], wedges[[0]][:, [0, 2, 1]])
    expected = [hexes[0, [0, 1, 5, 4]], wedges[1, [0, 1, 4, 3]], hexes[1, [4, 5, 6, 7]]]
    np.testing.assert_array_equal(quads[1], expected)


# --------------------------------------------------------------------------- writing


def test_a_facet_on_a_node_no_cell_uses_is_no_side(tmp_path):
    # the side index keyed corners by the largest node the cells use: [0, 13] met the
    # key of [1, 4] and was reported as that side with other nodes
    points, cells = rectangle("quad", 2)
    points = np.vstack([points, np.full((5, 2), 9.0)])  # nodes 9..13 in no cell
    for facet in ([0, 13], [3, 13]):
        data = MeshData(points=points, cells=cells, face_sets={"x": [("line", [facet])]})
        with pytest.raises(
            ValueError, match=rf"row 0 \(line {re.escape(str(facet))}\) is no side of a cell"
        ):
            write_exodus(tmp_path / "s.exo", data)
    assert not list(tmp_path.iterdir())


def test_sets_of_non_integer_nodes_are_refused(tmp_path):
    points, cells = box(("hexahedron",), 1)
    data = MeshData(points=points, cells=cells, node_sets={"n": np.array([1.7])})
    with pytest.raises(
        ValueError, match=r"data.node_sets\['n'\]: node rows must be integers, got float64"
    ):
        write_exodus(tmp_path / "m.exo", data)
    data = MeshData(points=points, cells=cells, face_sets={"f": [("quad", [[0.0, 1, 3, 2]])]})
    with pytest.raises(ValueError, match=r"data.face_sets\['f'\]\[0\]: node numbers must be int"):
        write_exodus(tmp_path / "m.exo", data)
    assert not list(tmp_path.iterdir())


# --------------------------------------------------------------------------- malformed files


def _good(path):
    """A file with a node set, a side set, a nodal and an element variable."""
    points, cells = columns(2)
    data = MeshData(
        points=points,
        cells=cells,
        node_sets={"n": np.array([0, 1])},
        face_sets={"f": [("quad", cells[0][1][:1, [0, 3, 7, 4]])]},
        point_data={"u": np.ones((len(points), 3))},
        cell_data={"c": [np.ones(len(nodes)) for _, nodes in cells]},
    )
    write_exodus(path, data)


def _copy(source, target, drop=(), replace=None):
    """``source`` written again without the variables ``drop``, with ``replace``'s
    variables (name: (type, dimensions, values)) instead of the file's."""
    replace = replace or {}
    with (
        netCDF4.Dataset(source) as old,
        netCDF4.Dataset(target, "w", format=old.file_format) as new,
    ):
        for name, dimension in old.dimensions.items():
            new.createDimension(name, None if dimension.isunlimited() else len(dimension))
        new.setncatts({key: old.getncattr(key) for key in old.ncattrs()})
        for name, variable in old.variables.items():
            if name in drop:
                continue
            variable.set_auto_mask(False)
            kind, dimensions, values = replace.get(
                name, (variable.datatype, variable.dimensions, variable[:])
            )
            copy = new.createVariable(name, kind, dimensions)
            copy.setncatts({key: variable.getncattr(key) for key in variable.ncattrs()})
            copy[:] = values


@pytest.mark.parametrize(
    ("drop", "replace", "message"),
    [
        ((), {"vals_nod_var1": ("f8", ("time_step", "num_el_in_blk1"), np.ones((1, 4)))},
         r"nodal variable 'u_x': 4 values for the 27 nodes"),
        (("vals_nod_var2",), {}, r"nodal variable 'u_y': no vals_nod_var2"),
        ((), {"vals_elem_var1eb2": ("f8", ("time_step", "num_el_in_blk1"), np.ones((1, 4)))},
         (r"element variable 'c': vals_elem_var1eb2 holds 4 values for the 8 elements of "
          r"element block 2 \(WEDGE\)")),
        (("elem_ss1",), {}, r"side set 1 \('f'\): 1 sides but no elem_ss1"),
        (("elem_ss1", "side_ss1"), {}, r"side set 1 \('f'\): 1 sides but no elem_ss1 or side_ss1"),
        (("node_ns1",), {}, r"node set 1 \('n'\): 2 nodes but no node_ns1"),
        ((), {"side_ss1": ("f8", ("num_side_ss1",), [1.5])}, r"side_ss1 holds 1\.5, not an integer"),
        ((), {"node_ns1": ("f8", ("num_nod_ns1",), [1.0, 2.7])}, r"node_ns1 holds 2\.7, not an int"),
        ((), {"connect1": ("f4", ("num_el_in_blk1", "num_nod_per_el1"), np.full((4, 8), 1.5))},
         r"connect1 holds 1\.5, not an integer"),
        (("connect1",), {}, r"element block 1: 4 elements but no connect1 with an elem_type"),
        (("coordy",), {}, r"no coordinates \(coordx, coordy\[, coordz\] or coord\)"),
        ((), {"ns_names": ("S1", ("num_el_blk", "len_name"), np.zeros((2, 256), "S1"))},
         r"ns_names has shape \(2, 256\), not \(1, len_name\)"),
        ((), {"eb_prop1": ("i4", ("num_node_sets",), [7])}, r"eb_prop1 holds 1 ids for 2 entries"),
    ],
)  # fmt: skip
def test_malformed_files_name_the_file_and_the_variable(tmp_path, drop, replace, message):
    _good(tmp_path / "good.exo")
    read_exodus(tmp_path / "good.exo")
    _copy(tmp_path / "good.exo", tmp_path / "bad.exo", drop, replace)
    with pytest.raises(ValueError, match=r"path: '.*bad\.exo': " + message):
        read_exodus(tmp_path / "bad.exo")


@pytest.mark.parametrize("fraction", [0.5, 0.8, 0.99])
def test_a_truncated_file(tmp_path, fraction):
    # the netCDF library reads the missing end of a classic file as zeros, without error
    _good(tmp_path / "good.exo")
    data = (tmp_path / "good.exo").read_bytes()
    (tmp_path / "bad.exo").write_bytes(data[: int(len(data) * fraction)])
    with pytest.raises(
        ValueError, match=r"path: '.*bad\.exo' is truncated: the file has \d+ bytes, its header"
    ):
        read_exodus(tmp_path / "bad.exo")
