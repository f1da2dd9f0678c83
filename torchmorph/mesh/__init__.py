"""Meshes: the model (:mod:`torchmorph.mesh.model`), quality and error measures
(:mod:`torchmorph.mesh.quality`) and files (:mod:`torchmorph.mesh.io`)."""

from torchmorph._atomic import atomic_output
from torchmorph.mesh.io import (
    MESH_FORMATS,
    decode_set_name,
    encode_set_name,
    from_meshio,
    read_mesh,
    to_meshio,
    write_mesh,
)
from torchmorph.mesh.model import FLAT_TET_TOLERANCE, TetMesh, box_mesh
from torchmorph.mesh.quality import (
    ERROR_NORMS,
    count_inverted,
    edge_ratio,
    inverted,
    mass_matrix,
    quality_summary,
    relative_l2_error,
    relative_nodal_error,
    signed_volumes,
    validity_barrier,
)

__all__ = [
    "ERROR_NORMS",
    "FLAT_TET_TOLERANCE",
    "MESH_FORMATS",
    "TetMesh",
    "atomic_output",
    "box_mesh",
    "count_inverted",
    "decode_set_name",
    "edge_ratio",
    "encode_set_name",
    "from_meshio",
    "inverted",
    "mass_matrix",
    "quality_summary",
    "read_mesh",
    "relative_l2_error",
    "relative_nodal_error",
    "signed_volumes",
    "to_meshio",
    "validity_barrier",
    "write_mesh",
]
