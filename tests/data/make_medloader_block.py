"""Writes ``medloader_block.med``: a MED file written by Salome's own MED library
(MEDCoupling's MEDLoader, ``pip install medcoupling``; the file was made with 9.14), so that
``test_med`` reads a file that torchmorph did not write.

The mesh is the box [0, 2] x [0, 1] x [0, 1]: one hexahedron (x < 1) and two prisms (x > 1),
oriented by MEDCoupling itself (``findAndCorrectBadOriented3DCells``), made quadratic by
MEDCoupling (HEXA20, PENTA15), with its skin (QUAD8, TRI6) as boundary elements; groups:
faces ``inlet`` (x = 0), ``outlet`` (x = 2), ``floor`` (z = 0), cells ``prisms``, node
``origin``. The test needs neither MEDCoupling nor this script; it is kept to show how the
file was made.
"""

from pathlib import Path

import medcoupling as mc
import numpy as np


def main() -> None:
    corners = [(x, y, z) for z in (0, 1) for y in (0, 1) for x in (0, 1, 2)]

    def node(x: int, y: int, z: int) -> int:
        return z * 6 + y * 3 + x

    mesh = mc.MEDCouplingUMesh("block", 3)
    mesh.setCoords(mc.DataArrayDouble(np.array(corners, float).ravel().tolist(), 12, 3))
    mesh.allocateCells(3)
    hexahedron = [node(0, 0, 0), node(1, 0, 0), node(1, 1, 0), node(0, 1, 0)]
    mesh.insertNextCell(mc.NORM_HEXA8, hexahedron + [n + 6 for n in hexahedron])
    for base in (
        [node(1, 0, 0), node(2, 0, 0), node(2, 1, 0)],
        [node(1, 0, 0), node(2, 1, 0), node(1, 1, 0)],
    ):
        mesh.insertNextCell(mc.NORM_PENTA6, base + [n + 6 for n in base])
    mesh.finishInsertingCells()
    mesh.findAndCorrectBadOriented3DCells()
    mesh.convertLinearCellsToQuadratic(0)
    mesh.sortCellsInMEDFileFrmt()
    skin = mesh.computeSkin()
    skin.sortCellsInMEDFileFrmt()
    coordinates = np.array(mesh.getCoords().getValues()).reshape(-1, 3)

    def centres(m) -> np.ndarray:
        return np.array(
            [coordinates[m.getNodeIdsOfCell(i)].mean(0) for i in range(m.getNumberOfCells())]
        )

    def group(name: str, rows: np.ndarray):
        array = mc.DataArrayInt(np.flatnonzero(rows).tolist())
        array.setName(name)
        return array

    faces, cells = centres(skin), centres(mesh)
    file_mesh = mc.MEDFileUMesh()
    file_mesh.setMeshAtLevel(0, mesh)
    file_mesh.setMeshAtLevel(-1, skin)
    file_mesh.setGroupsAtLevel(
        -1,
        [
            group("inlet", np.isclose(faces[:, 0], 0)),
            group("outlet", np.isclose(faces[:, 0], 2)),
            group("floor", np.isclose(faces[:, 2], 0)),
        ],
    )
    file_mesh.setGroupsAtLevel(0, [group("prisms", cells[:, 0] > 1)])
    file_mesh.setGroupsAtLevel(1, [group("origin", np.arange(len(coordinates)) == 0)])
    file_mesh.write(str(Path(__file__).with_name("medloader_block.med")), 2)


if __name__ == "__main__":
    main()
