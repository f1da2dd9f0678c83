"""Exodus II files (``.e``, ``.exo``): every kind's round trip with node and side sets,
side numbers and quadratic node orders against the Exodus II manual (files written here
with netCDF4 directly, not by torchmorph), files of meshio's independent Exodus writer,
files written again moved with everything else kept, and a morph through the
command (errors: test_exodus_errors.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from _kinds import CENTRES, EDGES, box, columns, idw_reference, quadratic, rectangle
from test_formats import with_markers

from torchmorph.mesh import Mesh, read_mesh, write_mesh
from torchmorph.mesh.formats.exodus import move_exodus, read_exodus
from torchmorph.mesh.io import mesh_from_data, write_morphed

netCDF4 = pytest.importorskip("netCDF4")

F64 = torch.float64

KINDS = {
    "hexahedron": lambda: box(("hexahedron",), 2),
    "wedge+tetra": lambda: box(("wedge", "tetra"), 2),
    "hexahedron+pyramid": lambda: box(("hexahedron", "pyramid"), 1),
    "hex beside wedge": lambda: columns(2),
    "tetra10": lambda: quadratic(*box(("tetra",), 1)),
    "hexahedron20": lambda: quadratic(*box(("hexahedron",), 1)),
    "wedge15": lambda: quadratic(*box(("wedge",), 1)),
    "pyramid13": lambda: quadratic(*box(("hexahedron", "pyramid"), 1)),
    "hexahedron27": lambda: quadratic(*box(("hexahedron",), 1), full=True),
    "wedge18": lambda: quadratic(*box(("wedge",), 1), full=True),
    "pyramid14": lambda: quadratic(*box(("hexahedron", "pyramid"), 1), full=True),
    "triangle": lambda: rectangle("triangle", 2),
    "quad": lambda: rectangle("quad", 2),
    "triangle6": lambda: quadratic(*rectangle("triangle", 2)),
    "quad8": lambda: quadratic(*rectangle("quad", 2)),
    "quad9": lambda: quadratic(*rectangle("quad", 2), full=True),
}


def raw_exodus(path, points, blocks, *, side_sets=(), node_sets=(), fmt="NETCDF3_CLASSIC"):
    """An Exodus II file written with netCDF4 directly, as the manual's netCDF appendix
    names things: ``blocks`` are (elem_type, 1-based connectivity), ``side_sets`` (name,
    elements, sides) and ``node_sets`` (name, nodes), 1-based, ids 10, 20, …."""
    points = np.asarray(points, dtype=np.float64)
    with netCDF4.Dataset(path, "w", format=fmt) as nc:
        nc.api_version, nc.version = np.float32(8.03), np.float32(8.03)
        nc.floating_point_word_size, nc.file_size = np.int32(8), np.int32(1)
        nc.title = "written by hand"
        for name, size in (("len_name", 33), ("four", 4), ("time_step", None)):
            nc.createDimension(name, size)
        nc.createDimension("num_dim", points.shape[1])
        nc.createDimension("num_nodes", len(points))
        nc.createDimension("num_elem", sum(len(c) for _, c in blocks))
        nc.createDimension("num_el_blk", len(blocks))
        for axis, letter in enumerate("xyz"[: points.shape[1]]):
            nc.createVariable(f"coord{letter}", "f8", ("num_nodes",))[:] = points[:, axis]
        nc.createVariable("eb_prop1", "i4", ("num_el_blk",))[:] = 10 * np.arange(1, len(blocks) + 1)
        for k, (elem_type, connect) in enumerate(blocks, 1):
            connect = np.asarray(connect, dtype=np.int32)
            nc.createDimension(f"num_el_in_blk{k}", connect.shape[0])
            nc.createDimension(f"num_nod_per_el{k}", connect.shape[1])
            dims = (f"num_el_in_blk{k}", f"num_nod_per_el{k}")
            variable = nc.createVariable(f"connect{k}", "i4", dims)
            variable.elem_type = elem_type
            variable[:] = connect
        for prefix, count, sets, members in (
            ("ss", "num_side_sets", side_sets, ("elem_ss", "side_ss")),
            ("ns", "num_node_sets", node_sets, ("node_ns",)),
        ):
            if not sets:
                continue
            nc.createDimension(count, len(sets))
            nc.createVariable(f"{prefix}_prop1", "i4", (count,))[:] = 10 * np.arange(
                1, len(sets) + 1
            )
            names = nc.createVariable(f"{prefix}_names", "S1", (count, "len_name"))
            names[:] = netCDF4.stringtochar(np.array([s[0] for s in sets], dtype="S33"))
            for k, (_, *arrays) in enumerate(sets, 1):
                size = f"num_side_ss{k}" if prefix == "ss" else f"num_nod_ns{k}"
                nc.createDimension(size, len(arrays[0]))
                for member, array in zip(members, arrays, strict=True):
                    nc.createVariable(f"{member}{k}", "i4", (size,))[:] = array


def same_mesh(again: Mesh, mesh: Mesh) -> None:
    assert [b.kind for b in again.cells] == [b.kind for b in mesh.cells]
    for block, original in zip(again.cells, mesh.cells, strict=True):
        assert torch.equal(block.nodes, original.nodes), block.kind
    assert torch.equal(again.points, mesh.points)
    assert again.node_sets.keys() == mesh.node_sets.keys()
    for name, nodes in mesh.node_sets.items():
        assert torch.equal(again.node_sets[name], nodes)
    assert again.face_sets.keys() == mesh.face_sets.keys()
    for name, blocks in mesh.face_sets.items():
        assert [b.kind for b in again.face_sets[name]] == [b.kind for b in blocks]
        for block, original in zip(again.face_sets[name], blocks, strict=True):
            assert torch.equal(block.nodes, original.nodes), (name, block.kind)


# --------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("name", list(KINDS))
def test_every_kind_round_trips_with_its_markers_and_fields(tmp_path, name):
    mesh = with_markers(*KINDS[name]())
    assert mesh.face_sets["bottom-wall"]  # facets of every kind the mesh has at z = 0
    generator = torch.Generator().manual_seed(0)
    temperature = torch.rand(mesh.num_nodes, generator=generator, dtype=F64)
    velocity = torch.rand(mesh.num_nodes, mesh.dim, generator=generator, dtype=F64)
    quality = torch.rand(mesh.num_cells, generator=generator, dtype=F64)
    path = tmp_path / "m.exo"
    write_mesh(
        path,
        mesh,
        point_data={"temperature": temperature, "velocity": velocity},
        cell_data={"quality": quality},
    )
    again, point_data, cell_data = read_mesh(path, return_data=True)
    same_mesh(again, mesh)
    assert torch.equal(point_data["temperature"], temperature)
    assert torch.equal(point_data["velocity"], velocity)
    assert torch.equal(cell_data["quality"], quality)


def _rolled(nodes: torch.Tensor) -> list[list[int]]:
    """Each linear facet's corners from its smallest one on, the cyclic order kept."""
    return [row[row.index(min(row)) :] + row[: row.index(min(row))] for row in nodes.tolist()]


@pytest.mark.parametrize("name", ["hex beside wedge", "hexahedron+pyramid", "wedge+tetra"])
def test_face_sets_on_every_wall_come_back_as_the_same_facets(tmp_path, name):
    """Side sets give each facet's nodes as the Exodus manual lists the side, which for a
    hexahedron's side 4 and a wedge's side 3 starts at another corner than torchmorph's
    facet tables: the same facets, turning the same way."""
    mesh = Mesh(*KINDS[name]())
    low, high = mesh.points.amin(0), mesh.points.amax(0)
    walls = {}
    for axis in range(3):
        for end, value in (("0", low[axis]), ("1", high[axis])):
            on = [
                (b.kind, b.nodes[(mesh.points[b.nodes][..., axis] == value).all(1)])
                for b in mesh.boundary_facets
            ]
            walls["xyz"[axis] + end] = [(kind, nodes) for kind, nodes in on if len(nodes)]
    mesh = Mesh(mesh.points, [(b.kind, b.nodes) for b in mesh.cells], face_sets=walls)
    write_mesh(tmp_path / "walls.exo", mesh)
    again = read_mesh(tmp_path / "walls.exo")
    assert again.face_sets.keys() == mesh.face_sets.keys()
    for wall, blocks in mesh.face_sets.items():
        assert [b.kind for b in again.face_sets[wall]] == [b.kind for b in blocks]
        for block, original in zip(again.face_sets[wall], blocks, strict=True):
            assert _rolled(block.nodes) == _rolled(original.nodes)


@pytest.mark.parametrize("name", ["wedge+tetra", "hex beside wedge", "tetra10", "quad", "quad9"])
def test_meshio_reads_our_files(tmp_path, name):
    """meshio's own Exodus reader (an independent one, which keeps Exodus's node order)
    reads what we write: the same blocks and node sets."""
    import meshio

    mesh = with_markers(*KINDS[name]())
    write_mesh(tmp_path / "m.e", mesh)
    m = meshio.read(tmp_path / "m.e")
    assert [(b.type, b.data.tolist()) for b in m.cells] == [
        (b.kind, b.nodes.tolist()) for b in mesh.cells
    ]
    np.testing.assert_array_equal(m.points[:, : mesh.dim], mesh.points.numpy())
    assert list(m.point_sets) == ["corner"]


@pytest.mark.parametrize(
    "name",
    ["wedge+tetra", "hex beside wedge", "hexahedron+pyramid", "tetra10", "quad", "triangle6"],
)
def test_files_of_meshio_exodus_writer(tmp_path, name):
    """A file of meshio's Exodus writer (the older ``coord`` layout, a netCDF-4 file, no
    names of blocks): every cell and node set read. (meshio writes quadratic kinds in
    VTK's order, so only the kinds whose orders agree are compared.)"""
    import meshio

    points, cells = KINDS[name]()
    sets = {"left": np.flatnonzero(points[:, 0] == 0), "one": np.array([1])}
    meshio.write(tmp_path / "m.exo", meshio.Mesh(points, cells, point_sets=sets))
    data = read_exodus(tmp_path / "m.exo")
    assert [kind for kind, _ in data.cells] == [kind for kind, _ in cells]
    for (_, nodes), (_, original) in zip(data.cells, cells, strict=True):
        np.testing.assert_array_equal(nodes, original)
    np.testing.assert_array_equal(data.points, points)
    assert data.node_sets.keys() == sets.keys()
    for key, nodes in sets.items():
        np.testing.assert_array_equal(data.node_sets[key], nodes)
    mesh_from_data(data)  # a valid mesh


# --------------------------------------------------------------------------- the manual

# Reference elements in Exodus's node numbering and the side node lists of the manual's
# table "Sideset Node Ordering" (1-based), written out by hand.
REFERENCE = {
    "HEX8": (
        [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]],
        [[1, 2, 6, 5], [2, 3, 7, 6], [3, 4, 8, 7], [1, 5, 8, 4], [1, 4, 3, 2], [5, 6, 7, 8]],
    ),
    "TETRA": (
        [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]],
        [[1, 2, 4], [2, 3, 4], [1, 4, 3], [1, 3, 2]],
    ),
    "WEDGE": (
        [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [0, 1, 1]],
        [[1, 2, 5, 4], [2, 3, 6, 5], [1, 4, 6, 3], [1, 3, 2], [4, 5, 6]],
    ),
    "PYRAMID": (
        [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 1]],
        [[1, 2, 5], [2, 3, 5], [3, 4, 5], [4, 1, 5], [1, 4, 3, 2]],
    ),
    "QUAD4": ([[0, 0], [1, 0], [1, 1], [0, 1]], [[1, 2], [2, 3], [3, 4], [4, 1]]),
    "TRI3": ([[0, 0], [1, 0], [0, 1]], [[1, 2], [2, 3], [3, 1]]),
}


@pytest.mark.parametrize("elem_type", list(REFERENCE))
def test_sides_are_numbered_as_in_the_exodus_manual(tmp_path, elem_type):
    corners, manual = REFERENCE[elem_type]
    corners = np.array(corners, dtype=np.float64)
    count = len(corners)
    # the element's nodes stored in a scrambled order, with a node of no element
    stored = np.random.default_rng(1).permutation(count + 1)  # element node i -> file row
    points = np.full((count + 1, corners.shape[1]), 7.0)
    points[stored[:count]] = corners
    sides = np.arange(len(manual), 0, -1)  # listed last side first
    raw_exodus(
        tmp_path / "one.exo",
        points,
        [(elem_type, [stored[:count] + 1])],
        side_sets=[("every side", np.ones(len(sides), dtype=int), sides)],
    )
    data = read_exodus(tmp_path / "one.exo")
    np.testing.assert_array_equal(data.cells[0][1], [stored[:count]])
    expected: dict[str, list] = {}
    for side in sides:
        rows = stored[np.array(manual[side - 1]) - 1]
        kind = {2: "line", 3: "triangle", 4: "quad"}[len(rows)]
        expected.setdefault(kind, []).append(rows.tolist())
    got = data.face_sets["every side"]
    assert [(kind, nodes.tolist()) for kind, nodes in got] == list(expected.items())
    # and each side so listed points out of its element (right-hand rule; in 2-D the
    # edge runs counter-clockwise, its outward normal on its right)
    centre = corners.mean(0)
    for side in sides:
        face = corners[np.array(manual[side - 1]) - 1]
        if face.shape[1] == 2:
            (x0, y0), (x1, y1) = face
            normal = np.array([y1 - y0, x0 - x1])
        else:
            normal = np.cross(face[1] - face[0], face[2] - face[0])
        assert normal @ (face.mean(0) - centre) > 0, side


# Exodus's node numbering of the quadratic kinds (the manual's element figures): corners,
# then mid-edge nodes on these corner pairs (1-based), then face centres on these faces.
EXODUS_QUADRATIC = {
    "HEX20": ("HEX8", [(1, 2), (2, 3), (3, 4), (4, 1), (1, 5), (2, 6), (3, 7), (4, 8),
                       (5, 6), (6, 7), (7, 8), (8, 5)], []),
    "HEX27": ("HEX8", [(1, 2), (2, 3), (3, 4), (4, 1), (1, 5), (2, 6), (3, 7), (4, 8),
                       (5, 6), (6, 7), (7, 8), (8, 5)],
              [(1, 2, 3, 4, 5, 6, 7, 8), (1, 2, 3, 4), (5, 6, 7, 8), (1, 4, 8, 5),
               (2, 3, 7, 6), (1, 2, 6, 5), (3, 4, 8, 7)]),
    "WEDGE15": ("WEDGE", [(1, 2), (2, 3), (3, 1), (1, 4), (2, 5), (3, 6), (4, 5), (5, 6),
                          (6, 4)], []),
    "WEDGE18": ("WEDGE", [(1, 2), (2, 3), (3, 1), (1, 4), (2, 5), (3, 6), (4, 5), (5, 6),
                          (6, 4)], [(1, 2, 5, 4), (2, 3, 6, 5), (1, 4, 6, 3)]),
    "PYRAMID13": ("PYRAMID", [(1, 2), (2, 3), (3, 4), (4, 1), (1, 5), (2, 5), (3, 5), (4, 5)], []),
    "PYRAMID14": ("PYRAMID", [(1, 2), (2, 3), (3, 4), (4, 1), (1, 5), (2, 5), (3, 5), (4, 5)],
                  [(1, 2, 3, 4)]),
    "TETRA10": ("TETRA", [(1, 2), (2, 3), (1, 3), (1, 4), (2, 4), (3, 4)], []),
    "TRI6": ("TRI3", [(1, 2), (2, 3), (3, 1)], []),
    "QUAD8": ("QUAD4", [(1, 2), (2, 3), (3, 4), (4, 1)], []),
    "QUAD9": ("QUAD4", [(1, 2), (2, 3), (3, 4), (4, 1)], [(1, 2, 3, 4)]),
}  # fmt: skip
LINEAR = {"HEX8": "hexahedron", "WEDGE": "wedge", "PYRAMID": "pyramid", "TETRA": "tetra"}
LINEAR |= {"TRI3": "triangle", "QUAD4": "quad"}


@pytest.mark.parametrize("elem_type", list(EXODUS_QUADRATIC))
def test_quadratic_node_orders_become_vtk_orders(tmp_path, elem_type):
    """An element in Exodus's numbering, read: its nodes sit where meshio's (VTK's)
    order puts them (mid-edge nodes on the edges of ``_kinds.EDGES`` in order, face
    centres on the faces of ``_kinds.CENTRES``, the body centre last)."""
    linear, mids, centres = EXODUS_QUADRATIC[elem_type]
    corners = np.array(REFERENCE[linear][0], dtype=np.float64)
    points = [*corners]
    points += [corners[[a - 1, b - 1]].mean(0) for a, b in mids]
    points += [corners[[c - 1 for c in face]].mean(0) for face in centres]
    points = np.array(points)
    raw_exodus(tmp_path / "q.exo", points, [(elem_type, [np.arange(len(points)) + 1])])
    ((kind, nodes),) = read_exodus(tmp_path / "q.exo").cells
    at = points[nodes[0]]
    base = LINEAR[linear]
    n = len(corners)
    np.testing.assert_array_equal(at[:n], corners)
    for k, (a, b) in enumerate(EDGES[base]):
        np.testing.assert_array_equal(at[n + k], corners[[a, b]].mean(0))
    faces, body = CENTRES.get(kind, ([], False))
    start = n + len(EDGES[base])
    for k, face in enumerate(faces):
        np.testing.assert_array_equal(at[start + k], corners[list(face)].mean(0))
    if body:
        np.testing.assert_array_equal(at[-1], corners.mean(0))
    assert len(at) == start + len(faces) + int(body)


def test_the_side_tables_agree_with_the_cell_kinds_facets():
    """Every kind's Exodus sides, mapped to VTK's node order, are its facets in
    :data:`torchmorph.mesh.cells.CELL_KINDS`, turning the same way."""
    from torchmorph.mesh.cells import CELL_KINDS
    from torchmorph.mesh.formats._exodus_tables import (
        EXODUS_TYPES,
        SIDES,
        TO_VTK,
        facet_kind,
        side_table,
    )

    for kind in EXODUS_TYPES:
        order = TO_VTK.get(kind, tuple(range(CELL_KINDS[kind].num_nodes)))
        to_vtk = np.argsort(order)  # Exodus node -> VTK node
        sides = [facet_kind(kind, side) for side in SIDES[side_table(kind)]]
        sides = [(name, tuple(to_vtk[list(local)].tolist())) for name, local in sides]
        facets = CELL_KINDS[kind].facets
        assert sorted((n, sorted(f)) for n, f in sides) == sorted((n, sorted(f)) for n, f in facets)
        for name, local in sides:
            (match,) = [f for n, f in facets if sorted(f) == sorted(local)]
            corners = {"l": 2, "t": 3, "q": 4}[name[0]]
            start = match.index(local[0])
            assert match[start:corners] + match[:start] == local[:corners], (kind, local, match)


# The Exodus library (SEACAS's C library, Debian's libexodusii-dev) reads a file and
# lists every side's nodes from its own side tables (ex_get_side_set_node_list).
EXODUS_LIBRARY_READER = r"""
#include <stdio.h>
#include <stdlib.h>
#include <exodusII.h>
int main(int argc, char **argv) {
  int cpu_ws = 8, io_ws = 0, ndim, nnodes, nelem, nblk, nns, nss;
  float version;
  char title[MAX_LINE_LENGTH + 1];
  int exoid = ex_open(argv[1], EX_READ, &cpu_ws, &io_ws, &version);
  if (exoid < 0 || ex_get_init(exoid, title, &ndim, &nnodes, &nelem, &nblk, &nns, &nss)) return 1;
  int *ids = malloc(sizeof(int) * (nss + 1));
  char **names = malloc(sizeof(char *) * (nss + 1));
  for (int k = 0; k < nss; k++) names[k] = calloc(MAX_STR_LENGTH + 1, 1);
  if (ex_get_side_set_ids(exoid, ids) || ex_get_names(exoid, EX_SIDE_SET, names)) return 1;
  for (int k = 0; k < nss; k++) {
    int sides, factors, length;
    ex_get_side_set_param(exoid, ids[k], &sides, &factors);
    ex_get_side_set_node_list_len(exoid, ids[k], &length);
    int *counts = malloc(sizeof(int) * sides), *nodes = calloc(length + 16, sizeof(int));
    if (ex_get_side_set_node_list(exoid, ids[k], counts, nodes)) return 1;
    printf("%s", names[k]);
    for (int j = 0; j < counts[0]; j++) printf(" %d", nodes[j]);
    printf("\n");
  }
  return ex_close(exoid);
}
"""


# ... and writes one: a HEX20 in Exodus's numbering beside a WEDGE, a side set on sides
# of both, an unnamed node set.
EXODUS_LIBRARY_WRITER = r"""
#include <exodusII.h>
int main(int argc, char **argv) {
  int cpu_ws = 8, io_ws = 8;
  int exoid = ex_create(argv[1], EX_CLOBBER, &cpu_ws, &io_ws);
  double c[8][3] = {{0,0,0},{1,0,0},{1,1,0},{0,1,0},{0,0,1},{1,0,1},{1,1,1},{0,1,1}};
  int mids[12][2] = {{1,2},{2,3},{3,4},{4,1},{1,5},{2,6},{3,7},{4,8},{5,6},{6,7},{7,8},{8,5}};
  double x[22], y[22], z[22];
  for (int i = 0; i < 8; i++) { x[i] = c[i][0]; y[i] = c[i][1]; z[i] = c[i][2]; }
  for (int i = 0; i < 12; i++) {
    int a = mids[i][0] - 1, b = mids[i][1] - 1;
    x[8 + i] = (c[a][0] + c[b][0]) / 2; y[8 + i] = (c[a][1] + c[b][1]) / 2;
    z[8 + i] = (c[a][2] + c[b][2]) / 2;
  }
  x[20] = 2; y[20] = 0; z[20] = 0; x[21] = 2; y[21] = 0; z[21] = 1;
  int hex[20], wedge[6] = {2, 21, 3, 6, 22, 7}, elements[3] = {1, 2, 1}, sides[3] = {4, 4, 2};
  int nodes[2] = {21, 1};
  for (int i = 0; i < 20; i++) hex[i] = i + 1;
  char *names[1] = {"walls"};
  if (exoid < 0 || ex_put_init(exoid, "by the library", 3, 22, 2, 2, 1, 1)
      || ex_put_coord(exoid, x, y, z) || ex_put_elem_block(exoid, 7, "HEX20", 1, 20, 0)
      || ex_put_elem_block(exoid, 9, "WEDGE", 1, 6, 0) || ex_put_elem_conn(exoid, 7, hex)
      || ex_put_elem_conn(exoid, 9, wedge) || ex_put_side_set_param(exoid, 40, 3, 0)
      || ex_put_side_set(exoid, 40, elements, sides) || ex_put_names(exoid, EX_SIDE_SET, names)
      || ex_put_node_set_param(exoid, 50, 2, 0) || ex_put_node_set(exoid, 50, nodes))
    return 1;
  return ex_close(exoid);
}
"""


@pytest.fixture(scope="module")
def exodus_library(tmp_path_factory):
    """The compiled programs ``reader`` and ``writer`` of the two sources above (skips
    without a C compiler and the Exodus library)."""
    import shutil
    import subprocess

    compiler = shutil.which("cc") or shutil.which("gcc")
    if compiler is None:
        pytest.skip("no C compiler")
    folder = tmp_path_factory.mktemp("exodus_library")
    programs = {}
    for name, source in (("reader", EXODUS_LIBRARY_READER), ("writer", EXODUS_LIBRARY_WRITER)):
        (folder / f"{name}.c").write_text(source)
        for library in ("-lexodus", "-lexoIIv2c"):  # SEACAS's name, Debian's
            command = [compiler, "-o", str(folder / name), str(folder / f"{name}.c"), library]
            if subprocess.run([*command, "-lnetcdf"], capture_output=True).returncode == 0:
                programs[name] = folder / name
                break
        else:
            pytest.skip("the Exodus II C library is not installed (Debian: libexodusii-dev)")
    return programs


def test_a_file_the_exodus_library_wrote(tmp_path, exodus_library):
    import subprocess

    assert subprocess.run([exodus_library["writer"], tmp_path / "lib.exo"]).returncode == 0
    data = read_exodus(tmp_path / "lib.exo")
    hex20 = [*range(12), 16, 17, 18, 19, 12, 13, 14, 15]  # VTK's order of Exodus's nodes
    assert [(kind, nodes.tolist()) for kind, nodes in data.cells] == [
        ("hexahedron20", [hex20]),
        ("wedge", [[1, 20, 2, 5, 21, 6]]),
    ]
    # the manual: HEX side 4 is 1, 5, 8, 4, 13, 20, 16, 12; side 2 is 2, 3, 7, 6, 10, 15,
    # 18, 14; WEDGE side 4 is 1, 3, 2 (of the wedge's nodes 2, 21, 3, ...)
    quads = [[1, 5, 8, 4, 13, 20, 16, 12], [2, 3, 7, 6, 10, 15, 18, 14]]
    assert [(kind, nodes.tolist()) for kind, nodes in data.face_sets["walls"]] == [
        ("quad8", (np.array(quads) - 1).tolist()),
        ("triangle", [[1, 2, 20]]),
    ]
    assert list(data.node_sets) == ["nodeset_50"]
    np.testing.assert_array_equal(data.node_sets["nodeset_50"], [0, 20])


@pytest.mark.parametrize("name", list(KINDS))
def test_the_exodus_library_lists_the_sides_we_read(tmp_path, exodus_library, name):
    """Every boundary facet as a side set of its own, written by us; the Exodus library's
    side node list of each equals our facet. (Exodus 6's library predates WEDGE18's and
    PYRAMID14's face-centre nodes, and counts a WEDGE15's triangle as 7 nodes: the nodes
    it lists are compared.)"""
    import subprocess

    mesh = Mesh(*KINDS[name]())
    facets = [(b.kind, row[None]) for b in mesh.boundary_facets for row in b.nodes]
    face_sets = {f"facet{k}": [facet] for k, facet in enumerate(facets)}
    write_mesh(tmp_path / "m.exo", Mesh(mesh.points, list(mesh.cells), face_sets=face_sets))
    ours = {
        k: blocks[0][1][0].tolist()
        for k, blocks in read_exodus(tmp_path / "m.exo").face_sets.items()
    }
    reader = exodus_library["reader"]
    listed = subprocess.run([reader, tmp_path / "m.exo"], capture_output=True, text=True)
    assert listed.returncode == 0, listed.stderr
    lines = [line.split() for line in listed.stdout.splitlines()]
    assert [line[0] for line in lines] == list(ours)
    for key, *nodes in lines:
        nodes = [int(node) - 1 for node in nodes]
        count = min(len(nodes), len(ours[key]))
        assert count >= len(ours[key]) - 1  # at most a face centre missing
        assert nodes[:count] == ours[key][:count], key


# --------------------------------------------------------------------------- markers


def test_side_sets_of_interior_facets_and_facet_blocks(tmp_path):
    """A side set on interior faces (an interface) and a SHELL4 block of boundary faces;
    blocks, side sets and node sets named and unnamed."""
    points, cells = box(("hexahedron", "hexahedron"), 1)  # two hexahedra, z in [0, 2]
    hexes = cells[0][1] + 1
    top = hexes[1][[4, 5, 6, 7]]  # the top face of the upper hexahedron, a skin
    raw_exodus(
        tmp_path / "m.exo",
        points,
        [("HEX", hexes), ("SHELL4", [top])],
        side_sets=[("interface", [1], [6]), ("", [2, 1], [5, 1])],
        node_sets=[("", [1, 2])],
    )
    data = read_exodus(tmp_path / "m.exo")
    assert list(data.face_sets) == ["interface", "sideset_20", "block_20"]
    assert data.face_sets["interface"][0][1].tolist() == [(hexes[0][[4, 5, 6, 7]] - 1).tolist()]
    assert data.face_sets["block_20"][0][1].tolist() == [(top - 1).tolist()]
    assert list(data.node_sets) == ["nodeset_10"]
    np.testing.assert_array_equal(data.node_sets["nodeset_10"], [0, 1])
    mesh = mesh_from_data(data)
    write_mesh(tmp_path / "again.exo", mesh)
    same_mesh(read_mesh(tmp_path / "again.exo"), mesh)


def test_a_node_set_named_like_a_side_set(tmp_path):
    points, cells = box(("hexahedron",), 1)
    hexes = cells[0][1] + 1
    bottom = hexes[0][[0, 1, 2, 3]]
    side_sets = [("bottom", [1], [5])]
    raw_exodus(tmp_path / "same.exo", points, [("HEX8", hexes)], side_sets=side_sets,
               node_sets=[("bottom", bottom)])  # fmt: skip
    mesh = read_mesh(tmp_path / "same.exo")
    assert mesh.markers == ("bottom",)  # the same nodes: one marker, the side set's
    raw_exodus(tmp_path / "other.exo", points, [("HEX8", hexes)], side_sets=side_sets,
               node_sets=[("bottom", [1])])  # fmt: skip
    with pytest.warns(UserWarning, match="named like a side set but holds other nodes"):
        mesh = read_mesh(tmp_path / "other.exo")
    assert mesh.markers == ("nodeset_10", "bottom")


def test_a_planar_mesh_of_shells_in_3d(tmp_path):
    """Cubit's default 2-D export: SHELL4 elements at z = const in a 3-D file, side sets
    on their edges (sides 3..6)."""
    points, cells = rectangle("quad", 2)
    lifted = np.column_stack([points, np.full(len(points), 0.5)])
    raw_exodus(tmp_path / "p.exo", lifted, [("SHELL4", cells[0][1] + 1)],
               side_sets=[("edge", [1], [3])])  # fmt: skip
    data = read_exodus(tmp_path / "p.exo")
    assert data.planar_coordinate == 0.5 and data.points.shape == (len(points), 2)
    assert data.face_sets["edge"][0][0] == "line"
    assert data.face_sets["edge"][0][1].tolist() == [cells[0][1][0][[0, 1]].tolist()]
    raw_exodus(tmp_path / "face.exo", lifted, [("SHELL4", cells[0][1] + 1)],
               side_sets=[("face", [1], [1])])  # fmt: skip
    with pytest.raises(ValueError, match=r"side 1 of element 1 .* 3\.\.6 \(1 and 2 are the"):
        read_exodus(tmp_path / "face.exo")


# --------------------------------------------------------------------------- moved files


def test_a_file_written_again_moved_keeps_everything_else(tmp_path):
    mesh = with_markers(*KINDS["wedge+tetra"]())
    source = tmp_path / "m.exo"
    temperature = torch.arange(mesh.num_nodes, dtype=F64)
    write_mesh(source, mesh, point_data={"temperature": temperature})
    with netCDF4.Dataset(source, "a") as nc:  # what a solver adds: a global attribute, a
        nc.solver = "heat v1.0"  # QA record, a second time step with a global variable
        nc.createDimension("num_qa_rec", 1)
        qa = nc.createVariable("qa_records", "S1", ("num_qa_rec", "four", "len_string"))
        qa[0] = netCDF4.stringtochar(np.array(["heat", "1.0", "today", "now"], dtype="S33"))
        nc.createDimension("num_glo_var", 1)
        nc.createVariable("vals_glo_var", "f8", ("time_step", "num_glo_var"))[:] = [[1.5], [2.5]]
        nc.variables["time_whole"][1] = 1.0
        nc.variables["vals_nod_var1"][1] = 2 * temperature.numpy()
    moved = mesh.points * 1.5 + 0.25
    output = write_morphed(source, moved, tmp_path / "moved.exo")
    with netCDF4.Dataset(source) as a, netCDF4.Dataset(output) as b:
        assert a.__dict__ == b.__dict__
        assert {k: len(v) for k, v in a.dimensions.items()} == {
            k: len(v) for k, v in b.dimensions.items()
        }
        assert a.variables.keys() == b.variables.keys()
        for name, variable in a.variables.items():
            assert variable.__dict__ == b.variables[name].__dict__
            if name not in ("coordx", "coordy", "coordz"):
                np.testing.assert_array_equal(variable[:], b.variables[name][:], err_msg=name)
    again, point_data, _ = read_mesh(output, return_data=True)
    assert torch.equal(again.points, moved)
    assert torch.equal(point_data["temperature"], 2 * temperature)  # the last time step
    before, after = source.read_bytes(), output.read_bytes()
    assert len(before) == len(after)
    changed = np.frombuffer(before, np.uint8) != np.frombuffer(after, np.uint8)
    assert changed.sum() <= moved.numel() * 8  # the coordinates' bytes at most
    unmoved = write_morphed(source, mesh.points, tmp_path / "unmoved.exo")
    assert unmoved.read_bytes() == before  # byte for byte


def test_a_planar_file_and_the_coord_layout_move(tmp_path):
    import meshio

    points, cells = rectangle("triangle", 2)
    lifted = np.column_stack([points, np.full(len(points), -2.0)])
    meshio.write(tmp_path / "m.exo", meshio.Mesh(lifted, cells))  # `coord` (3, N)
    moved = points + 0.125
    move_exodus(tmp_path / "m.exo", moved, tmp_path / "out.exo")
    data = read_exodus(tmp_path / "out.exo")
    np.testing.assert_array_equal(data.points, moved)
    assert data.planar_coordinate == -2.0
    with pytest.raises(ValueError, match=r"points must have shape \(9, 2\), got \(9, 3\)"):
        move_exodus(tmp_path / "m.exo", lifted, tmp_path / "bad.exo")
    assert not (tmp_path / "bad.exo").exists()


# --------------------------------------------------------------------------- the command


def test_a_morph_through_the_command_writes_the_file_back_moved(tmp_path, capsys):
    from torchmorph.cli import EXIT_OK, main

    points, cells = box(("wedge", "tetra"), 2)
    mesh = Mesh(points, cells)
    top = [
        (b.kind, b.nodes[(mesh.points[b.nodes][..., 2] == 2).all(1)]) for b in mesh.boundary_facets
    ]
    mesh = Mesh(points, cells, face_sets={"top": [t for t in top if len(t[1])]})
    source = tmp_path / "mesh.exo"
    write_mesh(source, mesh, point_data={"pressure": torch.arange(mesh.num_nodes, dtype=F64)})
    moving = mesh.node_set("top").numpy()
    rows = 0.05 * np.stack([np.cos(points[moving].sum(1) + k) for k in range(3)], 1)
    np.save(tmp_path / "d.npy", rows)
    out = tmp_path / "out.exo"
    arguments = ["morph", str(source), "--moving", "top", "-d", str(tmp_path / "d.npy")]
    assert main([*arguments, "-o", str(out), "--no-progress", "--strict"]) == EXIT_OK
    assert "the morphed exodus input: coordinates changed only" in capsys.readouterr().out
    again, point_data, _ = read_mesh(out, return_data=True)
    for block, original in zip(again.face_sets["top"], mesh.face_sets["top"], strict=True):
        assert torch.equal(block.nodes, original.nodes)
    assert torch.equal(point_data["pressure"], torch.arange(mesh.num_nodes, dtype=F64))
    moved = again.points.numpy()
    boundary = mesh.boundary_nodes.numpy()
    values = np.zeros((len(boundary), 3))
    values[np.searchsorted(boundary, moving)] = rows  # the other boundary nodes are fixed
    np.testing.assert_allclose(moved[boundary], points[boundary] + values, rtol=0, atol=1e-15)
    interior = np.setdiff1d(np.arange(len(points)), boundary)
    expected = points[interior] + idw_reference(points[interior], points[boundary], values)
    scale = np.abs(rows).max()
    np.testing.assert_allclose(moved[interior], expected, rtol=0, atol=1e-9 * scale)
