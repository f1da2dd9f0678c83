"""Writes ``medloader_full.med``: a MED file of a HEXA27 and two PENTA18 cells written by
Salome's own MED library (MEDCoupling's MEDLoader, ``pip install medcoupling``; the file
was made with 9.15), so that ``test_med`` checks torchmorph's permutations of their face
centres against MED's own numbering, not against torchmorph's writer.

The mesh is the box [0, 2] x [0, 1] x [0, 1] of ``make_medloader_block.py``: one
hexahedron (x < 1) made HEXA27 by MEDCoupling (``convertLinearCellsToQuadratic(1)``: it
places the mid-edge, face and body centre nodes itself) and two prisms (x > 1) made
PENTA15 by MEDCoupling, then PENTA18 with three more nodes each, put at the centre of the
quadrangle whose centre node MEDCoupling's cell model says it is (the QUAD9 faces of
``buildDescendingConnectivity``). The test needs neither MEDCoupling nor this script.
"""

from pathlib import Path

import medcoupling as mc
import numpy as np


def node(x: int, y: int, z: int) -> int:
    return z * 6 + y * 3 + x


def linear(cells: list[tuple[int, list[int]]]) -> mc.MEDCouplingUMesh:
    corners = [(x, y, z) for z in (0, 1) for y in (0, 1) for x in (0, 1, 2)]
    mesh = mc.MEDCouplingUMesh("block", 3)
    mesh.setCoords(mc.DataArrayDouble(np.array(corners, float).ravel().tolist(), 12, 3))
    mesh.allocateCells(len(cells))
    for kind, nodes in cells:
        mesh.insertNextCell(kind, nodes)
    mesh.finishInsertingCells()
    mesh.findAndCorrectBadOriented3DCells()
    return mesh


def main() -> None:
    bottom = [node(0, 0, 0), node(1, 0, 0), node(1, 1, 0), node(0, 1, 0)]
    hexahedron = linear([(mc.NORM_HEXA8, bottom + [n + 6 for n in bottom])])
    hexahedron.convertLinearCellsToQuadratic(1)  # HEXA27
    bases = (
        [node(1, 0, 0), node(2, 0, 0), node(2, 1, 0)],
        [node(1, 0, 0), node(2, 1, 0), node(1, 1, 0)],
    )
    prisms = linear([(mc.NORM_PENTA6, b + [n + 6 for n in b]) for b in bases])
    prisms.convertLinearCellsToQuadratic(0)  # PENTA15
    points = np.array(prisms.getCoords().getValues()).reshape(-1, 3)
    cells = []
    for k in range(prisms.getNumberOfCells()):
        extra = list(range(len(points) + 3 * k, len(points) + 3 * k + 3))
        cells.append(list(prisms.getNodeIdsOfCell(k)) + extra)
    points = np.concatenate([points, np.zeros((3 * len(cells), 3))])
    full = mc.MEDCouplingUMesh("block", 3)
    full.setCoords(mc.DataArrayDouble(points.ravel().tolist(), len(points), 3))
    full.allocateCells(len(cells))
    for nodes in cells:
        full.insertNextCell(mc.NORM_PENTA18, nodes)
    full.finishInsertingCells()
    faces = full.buildDescendingConnectivity()[0]
    for f in range(faces.getNumberOfCells()):
        nodes = faces.getNodeIdsOfCell(f)
        if faces.getTypeOfCell(f) == mc.NORM_QUAD9:
            points[nodes[8]] = points[nodes[:4]].mean(0)
    full.setCoords(mc.DataArrayDouble(points.ravel().tolist(), len(points), 3))
    mesh = mc.MEDCouplingUMesh.MergeUMeshes([hexahedron, full])
    mesh.mergeNodes(1e-12)
    mesh.sortCellsInMEDFileFrmt()
    mesh.setName("block")
    file_mesh = mc.MEDFileUMesh()
    file_mesh.setMeshAtLevel(0, mesh)
    file_mesh.write(str(Path(__file__).with_name("medloader_full.med")), 2)


if __name__ == "__main__":
    main()
