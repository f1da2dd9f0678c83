"""CalculiX/Abaqus decks: the reader on hand-written decks (values checked by hand), on
every deck of CalculiX's own test suite, the byte-exact writer, and ``ccx`` solving
morphed decks."""

from __future__ import annotations

import gzip
import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from torchmorph.mesh.formats.abaqus import (
    CALCULIX_FIELD_WIDTH,
    element_kind,
    format_coordinate,
    read_deck,
    write_deck,
)

TEST_DECKS = Path("/usr/share/doc/calculix-ccx-test/examples/test")
needs_decks = pytest.mark.skipif(not TEST_DECKS.is_dir(), reason="CalculiX test decks absent")
needs_ccx = pytest.mark.skipif(shutil.which("ccx") is None, reason="ccx is not installed")


def write(directory: Path, name: str, text: str) -> Path:
    path = directory / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(text.encode("latin-1"))
    return path


def deck_text(path: Path) -> bytes:
    data = path.read_bytes()
    return gzip.decompress(data) if path.name.endswith(".gz") else data


#: Corner triples (corner, then three neighbours, right-handed for a valid cell) of the
#: meshio kinds, written out from the kinds' reference cells, independent of the library.
CORNERS = {
    "tetra": [(0, 1, 2, 3)],
    "hexahedron": [(i, (i + 1) % 4, (i + 3) % 4, i + 4) for i in range(4)]
    + [(4 + i, 4 + (i + 3) % 4, 4 + (i + 1) % 4, i) for i in range(4)],
    "wedge": [(0, 1, 2, 3), (1, 2, 0, 4), (2, 0, 1, 5), (3, 5, 4, 0), (4, 3, 5, 1), (5, 4, 3, 2)],
}
CORNERS.update(tetra10=CORNERS["tetra"], hexahedron20=CORNERS["hexahedron"])
CORNERS.update(wedge15=CORNERS["wedge"])
PLANE_CORNERS = {"triangle": 3, "triangle6": 3, "quad": 4, "quad8": 4}


def corner_jacobians(points: np.ndarray, kind: str, cells: np.ndarray) -> np.ndarray:
    """Signed corner volumes (3-D) or areas (2-D) of every cell, shape (M, corners)."""
    if kind in PLANE_CORNERS:
        n = PLANE_CORNERS[kind]
        out = []
        for i in range(n):
            a = points[cells[:, (i + 1) % n]] - points[cells[:, i]]
            b = points[cells[:, (i - 1) % n]] - points[cells[:, i]]
            out.append(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])
        return np.stack(out, 1)
    out = []
    for corner, i, j, k in CORNERS[kind]:
        e = [points[cells[:, x]] - points[cells[:, corner]] for x in (i, j, k)]
        out.append(np.einsum("ij,ij->i", np.cross(e[0], e[1]), e[2]))
    return np.stack(out, 1)


TET_DECK = """\
** a comment line
*HEADING
Two tets, one heading line with commas, = signs and *stars*
*Node, Nset = Nall
  1, 0.0, 0.0, 0.0
  2, 1.0, 0.0, 0.0

  3, 0.0, 1.0, 0.0
  4, 0.0, 0.0, 1.0
  5, 1.0, 1.0, 1.0
**  comment between data lines
*element , type = c3d4 , elset = Eall
 10, 1, 2, 3, 4
 11, 2, 3, 4, 5
*nset, nset=base
1, 2, 3
*Material, name=steel
*Elastic
210000., 0.3
*Solid Section, elset=EALL, material=steel
*Step
*Static
*Boundary
BASE, 1, 3
*Cload
5, 3, -1.
*End Step
"""


# -- the parser on hand-written decks --------------------------------------------------


def test_keywords_any_case_comments_blank_lines(tmp_path):
    deck = read_deck(write(tmp_path, "tets.inp", TET_DECK))
    np.testing.assert_array_equal(deck.node_ids, [1, 2, 3, 4, 5])
    np.testing.assert_array_equal(deck.points[4], [1.0, 1.0, 1.0])
    mesh = deck.to_mesh_data()
    assert [kind for kind, _ in mesh.cells] == ["tetra"]
    np.testing.assert_array_equal(mesh.cells[0][1], [[0, 1, 2, 3], [1, 2, 3, 4]])
    np.testing.assert_array_equal(mesh.cell_data["element_id"][0], [10, 11])
    assert set(mesh.node_sets) == {"Nall", "base"}
    np.testing.assert_array_equal(mesh.node_sets["base"], [0, 1, 2])
    np.testing.assert_array_equal(deck.element_sets["Eall"], [10, 11])
    assert deck.element_blocks[0].type == "C3D4" and deck.element_blocks[0].elset == "Eall"
    assert deck.unsupported_elements == {} and deck.warnings == []
    assert (
        repr(deck)
        == f"AbaqusDeck({str(tmp_path / 'tets.inp')!r}, 5 nodes, elements: C3D4 (2), 1 file(s))"
    )


def test_omitted_and_empty_coordinates_are_zero(tmp_path):
    text = "*NODE\n7, 1.0\n8, 1.5, 2.0\n9\n10, , 3.0\n11,1.,2.,3.,\n12, 1.5D1, -2.5E-1, .5\n"
    deck = read_deck(write(tmp_path, "nodes.inp", text))
    np.testing.assert_array_equal(deck.node_ids, [7, 8, 9, 10, 11, 12])
    expected = [[1, 0, 0], [1.5, 2, 0], [0, 0, 0], [0, 3, 0], [1, 2, 3], [15, -0.25, 0.5]]
    np.testing.assert_array_equal(deck.points, expected)


def test_sparse_unordered_node_numbers(tmp_path):
    text = (
        "*NODE\n100, 0., 0., 1.\n5, 0., 0., 0.\n42, 1., 0., 0.\n7, 0., 1., 0.\n"
        "*ELEMENT, TYPE=C3D4\n3, 5, 42, 7, 100\n"
    )
    deck = read_deck(write(tmp_path, "sparse.inp", text))
    np.testing.assert_array_equal(deck.node_ids, [5, 7, 42, 100])
    np.testing.assert_array_equal(deck.points, [[0, 0, 0], [0, 1, 0], [1, 0, 0], [0, 0, 1]])
    np.testing.assert_array_equal(deck.to_mesh_data().cells[0][1], [[0, 2, 1, 3]])
    np.testing.assert_array_equal(deck.node_rows([100, 5]), [3, 0])
    with pytest.raises(ValueError, match="node_ids: 6 is no node"):
        deck.node_rows([6])


def unit_hex20_nodes() -> tuple[str, list[int]]:
    """Node lines of the unit hexahedron20 in VTK's order (numbers 1..20)."""
    corners = [
        (0, 0, 0),
        (1, 0, 0),
        (1, 1, 0),
        (0, 1, 0),
        (0, 0, 1),
        (1, 0, 1),
        (1, 1, 1),
        (0, 1, 1),
    ]
    edges = [(0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6), (6, 7), (7, 4)]
    edges += [(0, 4), (1, 5), (2, 6), (3, 7)]
    coordinates = corners + [tuple((np.add(corners[a], corners[b]) / 2).tolist()) for a, b in edges]
    lines = "".join(f"{i + 1}, {x}, {y}, {z}\n" for i, (x, y, z) in enumerate(coordinates))
    return lines, list(range(1, 21))


def test_element_lines_continue(tmp_path):
    nodes, numbers = unit_hex20_nodes()
    first, second = ", ".join(map(str, numbers[:15])), ", ".join(map(str, numbers[15:]))
    text = (
        f"*NODE\n{nodes}"
        "*ELEMENT, TYPE=C3D20R, ELSET=E\n"
        f"1, {first},\n {second}\n"  # the usual trailing comma
        f"2, {first}\n{second}\n"  # none: CalculiX counts the nodes
        f"3, {', '.join(map(str, numbers[:3]))},\n{', '.join(map(str, numbers[3:]))}\n"
    )
    mesh = read_deck(write(tmp_path, "hex20.inp", text)).to_mesh_data()
    assert mesh.cells[0][0] == "hexahedron20"
    np.testing.assert_array_equal(mesh.cells[0][1], np.tile(np.arange(20), (3, 1)))
    assert (corner_jacobians(mesh.points, "hexahedron20", mesh.cells[0][1]) > 0).all()


def test_extra_nodes_are_ignored_as_calculix_does(tmp_path):
    text = "*NODE\n1,0,0,0\n2,1,0,0\n3,0,1,0\n4,0,0,1\n*ELEMENT, TYPE=C3D4\n1, 1, 2, 3, 4, 9, 9,\n"
    deck = read_deck(write(tmp_path, "extra.inp", text))
    np.testing.assert_array_equal(deck.element_blocks[0].nodes, [[1, 2, 3, 4]])
    assert len(deck.warnings) == 1 and "extra.inp, line 6" in deck.warnings[0]


def test_sets_generate_names_and_parameters(tmp_path):
    nodes = "".join(f"{i}, {i}., 0., 0.\n" for i in range(1, 13))
    text = (
        f"*NODE, NSET=Nall\n{nodes}"
        "*NSET, NSET=odd, GENERATE\n1, 9, 2\n"
        "*NSET, NSET=pair\n11, 12\n"
        "*NSET, NSET=Mixed\nODD, 4\nPair\n"
        "*NSET, NSET=odd\n12\n"  # a second *NSET of a set adds to it
        "*NSET, NSET=range, generate\n3, 6\n"
        "*NSET, NSET=gaps, GENERATE\n10, 20, 5\n"  # 15 and 20 are no nodes: left out
        "*ELEMENT, TYPE=T3D2, ELSET=Bars\n1, 1, 2\n2, 2, 3\n5, 3, 4\n"
        "*ELSET, ELSET=some, GENERATE\n1, 5, 4\n"
        "*ELSET, ELSET=all\nbars, 2\n"
    )
    deck = read_deck(write(tmp_path, "sets.inp", text))
    sets = deck.node_sets
    np.testing.assert_array_equal(sets["odd"], [1, 3, 5, 7, 9, 12])
    np.testing.assert_array_equal(sets["Mixed"], [1, 3, 4, 5, 7, 9, 11, 12])  # before "12"
    np.testing.assert_array_equal(sets["range"], [3, 4, 5, 6])
    np.testing.assert_array_equal(sets["gaps"], [10])
    np.testing.assert_array_equal(sets["Nall"], np.arange(1, 13))
    np.testing.assert_array_equal(deck.element_sets["some"], [1, 5])
    np.testing.assert_array_equal(deck.element_sets["all"], [1, 2, 5])
    np.testing.assert_array_equal(deck.element_sets["Bars"], [1, 2, 5])
    mesh = deck.to_mesh_data(ignore_unsupported=True)
    np.testing.assert_array_equal(mesh.node_sets["odd"], [0, 2, 4, 6, 8, 11])


def test_nset_of_an_element_set(tmp_path):
    text = TET_DECK.replace("*nset, nset=base\n1, 2, 3\n", "*NSET, NSET=top, ELSET=Top\n")
    text = text.replace(" 11, 2, 3, 4, 5\n", "*ELEMENT, TYPE=C3D4, ELSET=Top\n 11, 2, 3, 4, 5\n")
    text = text.replace("BASE, 1, 3", "TOP, 1, 3")
    deck = read_deck(write(tmp_path, "nodesof.inp", text))
    np.testing.assert_array_equal(deck.node_sets["top"], [2, 3, 4, 5])


def test_member_set_must_be_defined_before(tmp_path):
    text = "*NODE\n1, 0.\n*NSET, NSET=A\nB\n*NSET, NSET=B\n1\n"
    with pytest.raises(ValueError, match=r"later\.inp, line 4: node set 'B' is not defined"):
        read_deck(write(tmp_path, "later.inp", text))


def test_includes_relative_and_nested(tmp_path):
    source = tmp_path / "case"
    main = write(
        source,
        "main.inp",
        "*HEADING\nincluded mesh\n*NODE, NSET=NALL\n*INCLUDE, INPUT=mesh/nodes.inp\n"
        "*INCLUDE,input=mesh/elements.inp\n*STEP\n*STATIC\n*END STEP\n",
    )
    # bare node lines: the *NODE of the including file goes on inside the include
    write(source, "mesh/nodes.inp", "1, 0., 0., 0.\n2, 1., 0., 0.\n*INCLUDE, INPUT=more.inp\n")
    write(source, "mesh/more.inp", "3, 0., 1., 0.\r\n4, 0., 0., 1.\r\n")  # beside its includer
    write(source, "mesh/elements.inp", "*ELEMENT, TYPE=C3D4, ELSET=EALL\n1, 1, 2, 3, 4")
    deck = read_deck(main)
    assert [str(f.name) for f in deck.files] == [
        "main.inp",
        "mesh/nodes.inp",
        "mesh/more.inp",
        "mesh/elements.inp",
    ]
    np.testing.assert_array_equal(deck.node_sets["NALL"], [1, 2, 3, 4])
    np.testing.assert_array_equal(deck.points[3], [0, 0, 1])
    np.testing.assert_array_equal(deck.node_files, [1, 1, 2, 2])

    unchanged = tmp_path / "copy"
    unchanged.mkdir()
    write_deck(deck, deck.points, unchanged / "main.inp")
    for file in deck.files:
        assert (unchanged / file.name).read_bytes() == file.path.read_bytes(), file.name

    moved = deck.points.copy()
    moved[3] = [0.125, 0.0, 1.5]
    out = tmp_path / "moved"
    out.mkdir()
    write_deck(deck, moved, out / "morphed.inp")
    assert (out / "morphed.inp").read_bytes() == main.read_bytes()
    assert (out / "mesh/nodes.inp").read_bytes() == (source / "mesh/nodes.inp").read_bytes()
    assert (out / "mesh/more.inp").read_bytes() == b"3, 0., 1., 0.\r\n4, 0.125, 0., 1.5\r\n"
    np.testing.assert_array_equal(read_deck(out / "morphed.inp").points, moved)


def test_include_falls_back_to_the_main_directory(tmp_path):
    # CalculiX opens included files from its working directory, the main deck's
    write(tmp_path, "main.inp", "*INCLUDE, INPUT=sub/a.inp\n")
    write(tmp_path, "sub/a.inp", "*INCLUDE, INPUT=sub/b.inp\n")
    write(tmp_path, "sub/b.inp", "*NODE\n1, 2.\n")
    deck = read_deck(tmp_path / "main.inp")
    assert str(deck.files[2].name) == "sub/b.inp"
    np.testing.assert_array_equal(deck.points, [[2, 0, 0]])


def test_writing_beside_the_original_keeps_its_included_files(tmp_path):
    write(tmp_path, "main.inp", "*INCLUDE, INPUT=nodes.inp\n")
    write(tmp_path, "nodes.inp", "*NODE\n1, 2.\n")
    deck = read_deck(tmp_path / "main.inp")
    write_deck(deck, deck.points, tmp_path / "same.inp")  # nothing moved: fine
    with pytest.raises(ValueError, match="would overwrite the included file"):
        write_deck(deck, deck.points + 1.0, tmp_path / "other.inp")
    assert (tmp_path / "nodes.inp").read_text() == "*NODE\n1, 2.\n"
    write_deck(deck, deck.points + 1.0, tmp_path / "main.inp")  # the deck itself: in place
    assert (tmp_path / "nodes.inp").read_text() == "*NODE\n1, 3.0, 1.0, 1.0\n"


def test_gzip_decks(tmp_path):
    path = tmp_path / "tets.inp.gz"
    path.write_bytes(gzip.compress(TET_DECK.encode()))
    deck = read_deck(path)
    assert deck.files[0].compressed and len(deck.node_ids) == 5
    write_deck(deck, deck.points, tmp_path / "plain.inp")
    assert (tmp_path / "plain.inp").read_text() == TET_DECK
    write_deck(deck, deck.points, tmp_path / "again.inp.gz")
    assert gzip.decompress((tmp_path / "again.inp.gz").read_bytes()).decode() == TET_DECK


def test_unsupported_elements_are_reported(tmp_path):
    text = TET_DECK.replace(
        "*nset,",
        "*ELEMENT, TYPE=SPRINGA, ELSET=springs\n20, 5, 6\n21, 4, 6\n"
        "*ELEMENT, TYPE=B31\n30, 1, 6\n*nset,",
    ).replace("  5, 1.0, 1.0, 1.0\n", "  5, 1.0, 1.0, 1.0\n  6, 2.0, 2.0, 2.0\n")
    deck = read_deck(write(tmp_path, "springs.inp", text))
    assert deck.unsupported_elements == {"SPRINGA": 2, "B31": 1}
    with pytest.raises(ValueError, match=r"types SPRINGA \(2\), B31 \(1\) are not solid"):
        deck.to_mesh_data()
    mesh = deck.to_mesh_data(ignore_unsupported=True)
    assert [kind for kind, _ in mesh.cells] == ["tetra"]
    assert mesh.points.shape == (6, 3)  # the springs' node 6 is still a node
    np.testing.assert_array_equal(deck.element_sets["springs"], [20, 21])


def test_solid_and_plane_elements_do_not_mix(tmp_path):
    text = TET_DECK.replace("*nset,", "*ELEMENT, TYPE=CPS3\n30, 1, 2, 3\n*nset,")
    with pytest.raises(ValueError, match=r"mixes 3-D solid elements \(C3D4\) with 2-D plane"):
        read_deck(write(tmp_path, "mixed.inp", text)).to_mesh_data()


def test_plane_deck(tmp_path):
    text = (
        "*NODE\n1, 0., 0.\n2, 2., 0.\n3, 2., 1.\n4, 0., 1.\n5, 3., 0.5\n"
        "*ELEMENT, TYPE=CPS4R\n1, 1, 2, 3, 4\n*ELEMENT, TYPE=CAX3\n2, 2, 5, 3\n"
    )
    deck = read_deck(write(tmp_path, "plane.inp", text))
    assert deck.dimension == 2
    mesh = deck.to_mesh_data()
    assert mesh.points.shape == (5, 2) and [k for k, _ in mesh.cells] == ["quad", "triangle"]
    for kind, cells in mesh.cells:
        assert (corner_jacobians(mesh.points, kind, cells) > 0).all()
    moved = mesh.points * 2.0
    write_deck(deck, moved, tmp_path / "bigger.inp")
    assert (tmp_path / "bigger.inp").read_text().splitlines()[2] == "2, 4.0, 0."
    np.testing.assert_array_equal(read_deck(tmp_path / "bigger.inp").points[:, :2], moved)


@pytest.mark.parametrize(
    ("element_type", "kind"),
    [
        ("C3D4", "tetra"), ("c3d10", "tetra10"), ("C3D10T", "tetra10"),
        ("C3D8", "hexahedron"), ("C3D8R", "hexahedron"), ("C3D8I", "hexahedron"),
        ("C3D8T", "hexahedron"), ("DC3D8", "hexahedron"), ("F3D8", "hexahedron"),
        ("C3D20", "hexahedron20"), ("C3D20R", "hexahedron20"), ("C3D6", "wedge"),
        ("C3D15", "wedge15"), ("C3D5", "pyramid"), ("CPS3", "triangle"), ("CPE3", "triangle"),
        ("CAX3", "triangle"), ("CPS4", "quad"), ("CPE4R", "quad"), ("CAX4R", "quad"),
        ("CPS6", "triangle6"), ("CAX6", "triangle6"), ("CPS8", "quad8"), ("CAX8R", "quad8"),
        ("S8R", None), ("S4", None), ("B31", None), ("B32", None), ("SPRINGA", None),
        ("MASS", None), ("GAPUNI", None), ("DCOUP3D", None), ("D", None), ("U1", None),
        ("T3D2", None), ("DASHPOTA", None), ("M3D8", None),
    ],
)  # fmt: skip
def test_element_kinds(element_type, kind):
    assert element_kind(element_type) == kind


def test_user_and_unknown_element_lines(tmp_path):
    text = (
        "*NODE\n"
        + "".join(f"{i}, {i}.\n" for i in range(1, 6))
        + "*USER ELEMENT, TYPE=U1, NODES=5\n"
        "*ELEMENT, TYPE=U1\n1, 1, 2, 3,\n4, 5\n"  # a count from *USER ELEMENT
        "*ELEMENT, TYPE=XYZ9\n2, 1, 2,\n3,\n4\n3, 5, 1, 2, 3\n"  # unknown: commas continue
        "*ELEMENT, TYPE=D\n4, 0, 1, 2\n5, 2, 3, 0\n"  # network ends may be node 0
    )
    deck = read_deck(write(tmp_path, "user.inp", text))
    np.testing.assert_array_equal(deck.element_blocks[0].nodes, [[1, 2, 3, 4, 5]])
    np.testing.assert_array_equal(deck.element_blocks[1].nodes, [[1, 2, 3, 4], [5, 1, 2, 3]])
    np.testing.assert_array_equal(deck.element_blocks[2].nodes, [[0, 1, 2], [2, 3, 0]])
    assert deck.unsupported_elements == {"U1": 1, "XYZ9": 2, "D": 2}


# -- bad input ---------------------------------------------------------------------------

NODES = "*NODE\n1, 0., 0., 0.\n2, 1., 0., 0.\n3, 0., 1., 0.\n4, 0., 0., 1.\n"


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (
            NODES + "*ELEMENT, TYPE=C3D4\n1, 1, 2, 3, 9\n",
            r"bad\.inp, line 7: element 1 \(TYPE=C3D4\) refers to node 9, which no \*NODE",
        ),
        (
            NODES + "*ELEMENT, TYPE=C3D10\n1, 1, 2, 3, 4, 1, 2,\n*STEP\n",
            r"bad\.inp, line 7: element 1 \(TYPE=C3D10\) is incomplete: 6 nodes of 10",
        ),
        (
            NODES + "*ELEMENT, TYPE=C3D20\n1, 1, 2, 3, 4, 1, 2, 3, 4, 1, 2, 3, 4, 1, 2, 3,\n",
            r"bad\.inp, line 7: element 1 \(TYPE=C3D20\) is incomplete: 15 nodes of 20",
        ),
        (NODES + "*NSET, NSET=A, GENERATE\n1, 4, 0\n", r"bad\.inp, line 7: GENERATE range 1, 4, 0"),
        (NODES + "*NSET, NSET=A, GENERATE\n4, 1\n", r"bad\.inp, line 7: GENERATE range 4, 1, 1"),
        (
            NODES + "*ELSET, ELSET=A, GENERATE\n1, 4, 1, 2\n",
            r"bad\.inp, line 7: GENERATE takes 'first, last\[, step\]', got 4 fields",
        ),
        (
            NODES + "*NSET, NSET=A, GENERATE\n1, x\n",
            r"bad\.inp, line 7: GENERATE bound 'x' is not an integer",
        ),
        (
            NODES + "*INCLUDE, INPUT=missing.inp\n",
            r"bad\.inp, line 6: included file 'missing\.inp' not found",
        ),
        (NODES + "*INCLUDE, INPUT=bad.inp\n", r"bad\.inp, line 6: .*bad\.inp' includes itself"),
        (NODES + "2, 5., 0., 0.\n", r"bad\.inp, line 6: node 2 is defined a second time"),
        (NODES + "*ELEMENT, ELSET=E\n1, 1, 2, 3, 4\n", r"bad\.inp, line 6: \*ELEMENT without"),
        ("*NODE\n1, 0.5.\n", r"bad\.inp, line 2: coordinate '0\.5\.' is not a number"),
        ("*NODE\nA, 0.5\n", r"bad\.inp, line 2: node number 'A' is not an integer"),
        ("*NODE\n1, 1e999\n", r"bad\.inp, line 2: coordinate '1e999' is out of range"),
        ("*NODE\n" + "9" * 20 + ", 1.\n", r"bad\.inp, line 2: node number '9+' is out of"),
        ("*NSET, NSET=A\n1, 1" + "0" * 20 + "\n", r"bad\.inp, line 2: set member '10+'"),
        ("*NODE\n1, 0.\n*ELEMENT, TYPE=\n", r"bad\.inp, line 3: parameter TYPE has no value"),
        (
            NODES + "*ELEMENT, TYPE=C3D4\n1, 1, 2, 3, 4\n1, 1, 2, 4, 3\n",
            r"bad\.inp, line 8: element 1 is defined a second time",
        ),
    ],
)
def test_malformed_decks_name_file_and_line(tmp_path, text, message):
    with pytest.raises(ValueError, match=message):
        read_deck(write(tmp_path, "bad.inp", text))


def test_damaged_decks_raise_only_value_errors(tmp_path):
    """Random edits of a deck: it reads, or raises ValueError (never another exception);
    what reads writes back and reads again."""
    base = (
        TET_DECK + "*NSET, NSET=G, GENERATE\n1, 5, 2\n*ELEMENT, TYPE=C3D10\n20, 1, 2, 3,\n4, 1, 2\n"
    )
    alphabet = "*,=\n 0123456789.-+eEdDNODELEMSTYPC3D4GENRAT\r\t"
    rng = np.random.default_rng(11)
    path = tmp_path / "damaged.inp"
    for _ in range(300):
        text = list(base)
        for _ in range(rng.integers(1, 6)):
            where = int(rng.integers(len(text)))
            action = rng.integers(3)
            if action == 0:
                del text[where]
            else:
                text.insert(where, alphabet[rng.integers(len(alphabet))])
                if action == 2:
                    del text[where + 1]
        path.write_text("".join(text), encoding="latin-1")
        try:
            deck = read_deck(path)
            mesh = deck.to_mesh_data(ignore_unsupported=True)
        except ValueError:
            continue
        write_deck(deck, mesh.points * 2.0, tmp_path / "out.inp")
        np.testing.assert_array_equal(read_deck(tmp_path / "out.inp").points, deck.points * 2.0)


def test_missing_file_nested_include_names_the_including_file(tmp_path):
    write(tmp_path, "main.inp", "*INCLUDE, INPUT=a.inp\n")
    write(tmp_path, "a.inp", "** a\n*INCLUDE, INPUT=b.inp\n")
    with pytest.raises(ValueError, match=r"a\.inp, line 2: included file 'b\.inp' not found"):
        read_deck(tmp_path / "main.inp")


def test_read_deck_missing_path(tmp_path):
    with pytest.raises(FileNotFoundError, match="path: .*nothere.inp' is not a file"):
        read_deck(tmp_path / "nothere.inp")


# -- writing -----------------------------------------------------------------------------


def test_write_unchanged_is_byte_for_byte(tmp_path):
    path = write(tmp_path, "tets.inp", TET_DECK)
    deck = read_deck(path)
    write_deck(deck, deck.points, tmp_path / "out.inp")
    assert (tmp_path / "out.inp").read_bytes() == path.read_bytes()


def test_any_bytes_come_back(tmp_path):
    # Latin-1 and UTF-8 letters, a form feed and NEL (line breaks to str.splitlines), CRLF,
    # tabs, no newline at the end
    data = TET_DECK.encode().replace(b"Two tets,", b"H\xfceber H\xc3\xbceber \x0c\x85 \t,")
    data = data.replace(b"  3, 0.0, 1.0, 0.0\n", b"\t3,\t0.0,\t1.0,\t0.0\r\n").rstrip(b"\n")
    path = tmp_path / "bytes.inp"
    path.write_bytes(data)
    deck = read_deck(path)
    np.testing.assert_array_equal(deck.points[2], [0, 1, 0])
    write_deck(deck, deck.points, tmp_path / "out.inp")
    assert (tmp_path / "out.inp").read_bytes() == data
    moved = deck.points.copy()
    moved[2, 2] = 0.5
    write_deck(deck, moved, tmp_path / "out.inp")
    expected = data.replace(b"\t3,\t0.0,\t1.0,\t0.0\r\n", b"\t3,\t0.0,\t1.0,\t0.5\r\n")
    assert (tmp_path / "out.inp").read_bytes() == expected


def test_write_changes_only_moved_node_lines(tmp_path):
    deck = read_deck(write(tmp_path, "tets.inp", TET_DECK))
    moved = deck.points.copy()
    moved[1, 0] = 0.25  # node 2: x only
    moved[4] = [1.0, -1.2345678901234567e-05, 1.0 / 3.0]  # node 5: y and z
    write_deck(deck, moved, tmp_path / "out.inp")
    before = TET_DECK.splitlines(keepends=True)
    after = (tmp_path / "out.inp").read_text().splitlines(keepends=True)
    changed = [i for i, (a, b) in enumerate(zip(before, after, strict=True)) if a != b]
    assert changed == [5, 9]
    assert after[5] == "  2, 0.25, 0.0, 0.0\n"
    assert after[9] == "  5, 1.0, -1.2345678901235e-05, 0.3333333333333333\n"
    again = read_deck(tmp_path / "out.inp").points
    np.testing.assert_array_equal(np.delete(again, 4, 0), np.delete(moved, 4, 0))
    np.testing.assert_allclose(again[4], moved[4], rtol=5e-14, atol=0)


def test_write_appends_omitted_coordinates(tmp_path):
    deck = read_deck(write(tmp_path, "short.inp", "*NODE\n7, 1.0\n8, 2.0,,\n"))
    write_deck(deck, [[1.0, 0.0, 0.5], [2.0, 0.0, 3.0]], tmp_path / "out.inp")
    assert (tmp_path / "out.inp").read_text() == "*NODE\n7, 1.0, 0.0, 0.5\n8, 2.0,,3.0\n"


def test_format_coordinate_fits_calculix_fields():
    rng = np.random.default_rng(7)
    values = rng.standard_normal(2000) * 10.0 ** rng.integers(-120, 120, 2000)
    values = np.concatenate([values, [0.0, -0.0, 1.0, 0.1 + 0.2, -1e-300, 5e-324, 1.7e308]])
    for value in values:
        text = format_coordinate(value)
        assert len(text) <= CALCULIX_FIELD_WIDTH, text
        # 14 or 15 significant digits where the exponent has two digits, 13 with three
        bound = 5e-14 if 1e-99 <= abs(value) < 1e100 else 5e-13
        assert float(text) == pytest.approx(value, rel=bound, abs=0)
        if len(repr(float(value))) <= CALCULIX_FIELD_WIDTH:
            assert float(text) == value


def test_write_checks_points(tmp_path):
    deck = read_deck(write(tmp_path, "tets.inp", TET_DECK))
    with pytest.raises(ValueError, match=r"points: expected shape \(5, 3\)"):
        write_deck(deck, np.zeros((5, 2)), tmp_path / "out.inp")
    with pytest.raises(ValueError, match=r"points: expected shape \(5, 3\)"):
        write_deck(deck, np.zeros((4, 3)), tmp_path / "out.inp")
    bad = deck.points.copy()
    bad[2, 1] = np.nan
    with pytest.raises(ValueError, match=r"points: row 2 \(node 3\) is not finite"):
        write_deck(deck, bad, tmp_path / "out.inp")
    assert not (tmp_path / "out.inp").exists()


def test_write_accepts_a_tensor(tmp_path):
    torch = pytest.importorskip("torch")
    deck = read_deck(write(tmp_path, "tets.inp", TET_DECK))
    points = torch.tensor(deck.points * 2.0, requires_grad=True)
    write_deck(deck, points, tmp_path / "out.inp")
    np.testing.assert_array_equal(read_deck(tmp_path / "out.inp").points, deck.points * 2.0)


# -- CalculiX's test decks ---------------------------------------------------------------


def all_test_decks() -> list[Path]:
    return sorted([*TEST_DECKS.glob("*.inp"), *TEST_DECKS.glob("*.inp.gz")])


@needs_decks
@pytest.mark.slow
def test_every_calculix_test_deck(tmp_path):
    """Every deck reads, or is refused with a clear ValueError; unchanged points write
    back byte for byte; every cell has positive corner volumes."""
    outcome: dict[str, list[str]] = {"mesh": [], "without others": [], "no nodes": []}
    for path in all_test_decks():
        deck = read_deck(path)  # any exception fails the test
        text = deck_text(path).decode("latin-1")
        if not len(deck.node_ids):
            with pytest.raises(ValueError, match="defines no nodes"):
                deck.to_mesh_data()
            assert re.search(r"^\*RESTART, *READ", text, re.I | re.M), path.name
            outcome["no nodes"].append(path.name)
            continue
        if deck.unsupported_elements:
            with pytest.raises(ValueError, match="are not solid or plane cells"):
                deck.to_mesh_data()
            for element_type in deck.unsupported_elements:
                assert re.search(rf"TYPE *= *{element_type}\b", text, re.I), path.name
            mesh = deck.to_mesh_data(ignore_unsupported=True)
            outcome["without others"].append(path.name)
        else:
            mesh = deck.to_mesh_data()
            outcome["mesh"].append(path.name)
        for kind, cells in mesh.cells:
            jacobians = corner_jacobians(mesh.points, kind, cells)
            assert (jacobians > 0).all(), (path.name, kind)
        write_deck(deck, deck.points, tmp_path / "copy.inp")
        assert (tmp_path / "copy.inp").read_bytes() == deck_text(path), path.name
    counts = {key: len(names) for key, names in outcome.items()}
    print(f"CalculiX test decks: {counts}")
    assert outcome["no nodes"] == ["beamread.inp"]
    assert counts["mesh"] > 200 and counts["without others"] > 100


def element_counts_from_text(text: str) -> dict[str, int]:
    """Elements per type counted from the deck's text alone: the integers of each
    *ELEMENT block's data lines, divided by (1 + nodes per element)."""
    nodes = {"C3D4": 4, "C3D6": 6, "C3D8": 8, "C3D10": 10, "C3D15": 15, "C3D20": 20}
    counts: dict[str, int] = {}
    element_type = None
    numbers = 0
    for line in [*text.splitlines(), "*END"]:
        if line.startswith("*") and not line.startswith("**"):
            if element_type is not None:
                per = 1 + nodes[element_type]
                assert numbers % per == 0
                counts[element_type] = counts.get(element_type, 0) + numbers // per
            match = re.match(r"\*ELEMENT\s*,.*TYPE\s*=\s*(\w+)", line, re.I)
            element_type = match.group(1).upper().rstrip("R") if match else None
            numbers = 0
        elif element_type is not None and line.strip():
            numbers += len([f for f in line.split(",") if f.strip()])
    return counts


NAMED_DECKS = {
    "beam10p.inp.gz": {"tetra10"},  # quadratic tets
    "beam20p.inp.gz": {"hexahedron20"},  # quadratic hexes
    "c3d6.inp": {"wedge"},  # linear wedges
    "c3d15.inp.gz": {"wedge15"},  # quadratic wedges
    "metalforming.inp.gz": {"wedge", "hexahedron"},  # wedges and hexes
    "cubef2f1.inp.gz": {"tetra10", "hexahedron20"},  # quadratic tets and hexes
}
KINDS_OF = {"C3D6": "wedge", "C3D8": "hexahedron", "C3D10": "tetra10", "C3D15": "wedge15"}
KINDS_OF["C3D20"] = "hexahedron20"


@needs_decks
@pytest.mark.parametrize(("name", "kinds"), NAMED_DECKS.items())
def test_named_decks_read_right(name, kinds):
    path = TEST_DECKS / name
    text = deck_text(path).decode("latin-1")
    mesh = read_deck(path).to_mesh_data()
    assert {kind for kind, _ in mesh.cells} == kinds
    counted: dict[str, int] = {}
    for kind, cells in mesh.cells:
        counted[kind] = counted.get(kind, 0) + len(cells)
        assert (corner_jacobians(mesh.points, kind, cells) > 0).all()
    expected = {KINDS_OF[t]: n for t, n in element_counts_from_text(text).items()}
    assert counted == expected
    node_lines = re.search(r"^\*NODE\b[^\n]*\n(.*?)^\*", text, re.I | re.M | re.S).group(1)
    first = [float(f) for f in node_lines.splitlines()[0].split(",") if f.strip()]
    row = int(np.searchsorted(read_deck(path).node_ids, int(first[0])))
    np.testing.assert_array_equal(mesh.points[row], first[1:] + [0.0] * (4 - len(first)))


@needs_decks
def test_moved_test_deck_changes_only_node_lines(tmp_path):
    deck = read_deck(TEST_DECKS / "cubef2f1.inp.gz")
    rng = np.random.default_rng(3)
    moved = deck.points.copy()
    chosen = rng.choice(len(moved), 50, replace=False)
    moved[chosen] += rng.uniform(-1e-3, 1e-3, (50, 3))
    write_deck(deck, moved, tmp_path / "moved.inp")
    before = deck.files[0].lines
    after = (tmp_path / "moved.inp").read_text(encoding="latin-1").splitlines(keepends=True)
    assert len(after) == len(before)
    changed = {i for i, (a, b) in enumerate(zip(before, after, strict=True)) if a != b}
    assert changed == set(deck.node_lines[chosen].tolist())
    for i in changed:
        assert before[i].split(",")[0] == after[i].split(",")[0]  # the node number as written
    again = read_deck(tmp_path / "moved.inp")
    np.testing.assert_allclose(again.points, moved, rtol=5e-14, atol=0)
    assert again.to_mesh_data().cells[0][1].tolist() == deck.to_mesh_data().cells[0][1].tolist()


# -- ccx solves morphed decks --------------------------------------------------------------


def run_ccx(directory: Path, job: str) -> str:
    environment = dict(os.environ, OMP_NUM_THREADS="1", CCX_NPROC_EQUATION_SOLVER="1")
    result = subprocess.run(
        ["ccx", job], cwd=directory, capture_output=True, text=True, timeout=300, env=environment
    )
    return result.stdout + result.stderr + f"\nexit status {result.returncode}"


def assert_solved(directory: Path, job: str, output: str) -> None:
    assert output.endswith("exit status 0"), output[-2000:]
    assert "nonpositive jacobian" not in output and "*ERROR" not in output, output[-2000:]
    assert (directory / f"{job}.dat").stat().st_size > 0
    assert (directory / f"{job}.frd").stat().st_size > 0


def von_mises(dat: Path) -> np.ndarray:
    """Von Mises stress at every integration point of the .dat's stress tables."""
    values, reading = [], False
    for line in dat.read_text().splitlines():
        if line.strip().startswith("stresses"):
            reading = True
        elif reading and line.strip():
            fields = line.split()
            if len(fields) != 8:
                reading = False
                continue
            sxx, syy, szz, sxy, sxz, syz = map(float, fields[2:])
            values.append(
                np.sqrt(
                    0.5 * ((sxx - syy) ** 2 + (syy - szz) ** 2 + (szz - sxx) ** 2)
                    + 3.0 * (sxy**2 + sxz**2 + syz**2)
                )
            )
    return np.asarray(values)


def bent(points: np.ndarray) -> np.ndarray:
    """A smooth, small motion: a gentle bend along the longest axis plus a 4-degree
    rotation about a skew axis through the centre."""
    low, high = points.min(0), points.max(0)
    extent = high - low
    axis = int(np.argmax(extent))
    across = (axis + 1) % 3
    s = (points[:, axis] - low[axis]) / extent[axis]
    moved = points.copy()
    moved[:, across] += 0.05 * extent[axis] * s**2
    unit = np.array([1.0, 2.0, 2.0]) / 3.0
    angle = np.radians(4.0)
    cross = np.array([[0, -unit[2], unit[1]], [unit[2], 0, -unit[0]], [-unit[1], unit[0], 0]])
    rotation = np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross
    centre = (low + high) / 2
    return (moved - centre) @ rotation.T + centre


@needs_decks
@needs_ccx
@pytest.mark.slow
@pytest.mark.parametrize("name", ["beam10p.inp.gz", "beam20p.inp.gz", "c3d15.inp.gz"])
def test_ccx_solves_morphed_decks(tmp_path, name):
    deck = read_deck(TEST_DECKS / name)
    job = name.split(".")[0]
    runs = {}
    # a half turn about z and a shift: a rigid motion that maps the decks' axis-aligned
    # supports onto themselves and their loads (y forces, pressures) onto their negatives
    # or themselves, so that the von Mises stress of this linear static step is unchanged
    half_turn = deck.points * np.array([-1.0, -1.0, 1.0]) + np.array([10.25, -3.5, 7.0])
    for label, points in [("original", deck.points), ("rigid", half_turn)]:
        directory = tmp_path / label
        directory.mkdir()
        write_deck(deck, points, directory / f"{job}.inp")
        assert_solved(directory, job, run_ccx(directory, job))
        runs[label] = von_mises(directory / f"{job}.dat")
    assert runs["original"].size > 0
    scale = np.abs(runs["original"]).max()
    np.testing.assert_allclose(runs["rigid"], runs["original"], rtol=0, atol=1e-5 * scale)

    morphed = bent(deck.points)
    mesh = deck.to_mesh_data()
    for kind, cells in mesh.cells:
        assert (corner_jacobians(morphed, kind, cells) > 0).all()
    directory = tmp_path / "bent"
    directory.mkdir()
    write_deck(deck, morphed, directory / f"{job}.inp")
    assert_solved(directory, job, run_ccx(directory, job))
    assert np.isfinite(von_mises(directory / f"{job}.dat")).all()


@needs_decks
@needs_ccx
@pytest.mark.slow
def test_ccx_rejects_an_inverted_deck(tmp_path):
    """The check above can fail: a mirrored mesh is refused by ccx."""
    deck = read_deck(TEST_DECKS / "beam10p.inp.gz")
    write_deck(deck, deck.points * np.array([-1.0, 1.0, 1.0]), tmp_path / "mirror.inp")
    output = run_ccx(tmp_path, "mirror")
    assert "nonpositive jacobian" in output and not output.endswith("exit status 0")
