"""``torchmorph morph`` on a mesh file of every element kind, 2-D and 3-D, linear and
quadratic: every cell kept, the boundary exact, the interior equal to an independent
float64 IDW from the true boundary to 1e-9 of max|d|."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "mesh"))

from _kinds import box, columns, idw_reference, on_box_surface, quadratic, rectangle

from torchmorph.cli import EXIT_OK, main
from torchmorph.mesh import Mesh, read_mesh, write_mesh

MESHES = {
    "hexahedron": lambda: box(("hexahedron",), 2),
    "wedge+tetra": lambda: box(("wedge", "tetra"), 2),
    "hexahedron+pyramid": lambda: box(("hexahedron", "pyramid"), 2),
    "hex beside wedge": lambda: columns(2),
    "tetra10": lambda: quadratic(*box(("tetra",), 2)),
    "hexahedron20": lambda: quadratic(*box(("hexahedron",), 2)),
    "wedge15": lambda: quadratic(*box(("wedge",), 2)),
    "pyramid13": lambda: quadratic(*box(("hexahedron", "pyramid"), 1)),
    "hexahedron27": lambda: quadratic(*box(("hexahedron",), 2), full=True),
    "wedge18": lambda: quadratic(*box(("wedge",), 1), full=True),
    "pyramid14": lambda: quadratic(*box(("hexahedron", "pyramid"), 1), full=True),
    "triangle": lambda: rectangle("triangle", 3),
    "quad": lambda: rectangle("quad", 3),
    "triangle6": lambda: quadratic(*rectangle("triangle", 3)),
    "quad8": lambda: quadratic(*rectangle("quad", 3)),
    "quad9": lambda: quadratic(*rectangle("quad", 3), full=True),
}


@pytest.mark.parametrize("name", list(MESHES))
def test_a_morph_through_the_command_equals_float64_idw(tmp_path, name, capsys):
    points, cells = MESHES[name]()
    source = tmp_path / ("mesh.msh" if name == "pyramid14" else "mesh.vtu")  # VTK has none
    write_mesh(source, Mesh(points, cells))
    boundary = on_box_surface(points)
    p = points[boundary]
    rows = 0.03 * np.stack([np.cos(2 * p.sum(1) + k) for k in range(points.shape[1])], 1)
    np.save(tmp_path / "d.npy", rows)  # one row per boundary node, ascending id
    out = tmp_path / f"out{source.suffix}"
    arguments = ["morph", str(source), "-d", str(tmp_path / "d.npy"), "-o", str(out)]
    assert main([*arguments, "--strict", "--no-progress"]) == EXIT_OK
    assert "inverted cells  0 of" in capsys.readouterr().out
    mesh, point_data, cell_data = read_mesh(out, return_data=True)
    assert [b.kind for b in mesh.cells] == [kind for kind, _ in cells]  # every cell kept
    assert mesh.num_cells == sum(len(nodes) for _, nodes in cells)
    field = point_data["displacement"].numpy()[:, : points.shape[1]]
    scale = np.abs(rows).max()
    np.testing.assert_allclose(field[boundary], rows, rtol=0, atol=1e-15 * scale)
    interior = np.setdiff1d(np.arange(len(points)), boundary)
    expected = idw_reference(points[interior], p, rows)
    np.testing.assert_allclose(field[interior], expected, rtol=0, atol=1e-9 * scale)
    if source.suffix == ".vtu":  # an MSH file of several blocks holds no cell data
        assert cell_data["inverted"].numel() == mesh.num_cells
