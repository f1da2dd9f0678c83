"""Meshes: the model of any element kinds in 2-D and 3-D (:mod:`torchmorph.mesh.model`,
the kinds in :mod:`torchmorph.mesh.cells`) with its tetrahedral special case
(:mod:`torchmorph.mesh.tetmesh`), quality and error measures
(:mod:`torchmorph.mesh.quality`) and files (:mod:`torchmorph.mesh.io`)."""

from torchmorph._atomic import atomic_output
from torchmorph.mesh.cells import CELL_KINDS, CellKind
from torchmorph.mesh.io import (
    MESH_FORMATS,
    decode_set_name,
    encode_set_name,
    from_meshio,
    read_mesh,
    to_meshio,
    write_mesh,
    write_morphed,
)
from torchmorph.mesh.model import CellBlock, Mesh
from torchmorph.mesh.norms import (
    ERROR_NORMS,
    mass_matrix,
    relative_l2_error,
    relative_nodal_error,
)
from torchmorph.mesh.quality import (
    cell_edge_ratio,
    cell_volumes,
    count_inverted,
    edge_ratio,
    inverted,
    quality_by_kind,
    quality_report,
    quality_summary,
    scaled_jacobian,
    signed_volumes,
    validity_barrier,
)
from torchmorph.mesh.tetmesh import FLAT_TET_TOLERANCE, TetMesh, box_mesh

__all__ = [
    "CELL_KINDS",
    "ERROR_NORMS",
    "FLAT_TET_TOLERANCE",
    "MESH_FORMATS",
    "CellBlock",
    "CellKind",
    "Mesh",
    "TetMesh",
    "atomic_output",
    "box_mesh",
    "cell_edge_ratio",
    "cell_volumes",
    "count_inverted",
    "decode_set_name",
    "edge_ratio",
    "encode_set_name",
    "from_meshio",
    "inverted",
    "mass_matrix",
    "quality_by_kind",
    "quality_report",
    "quality_summary",
    "read_mesh",
    "relative_l2_error",
    "relative_nodal_error",
    "scaled_jacobian",
    "signed_volumes",
    "to_meshio",
    "validity_barrier",
    "write_mesh",
    "write_morphed",
]
