"""torchmorph: fast, differentiable, parametrized shape morphing of tetrahedral meshes.

Inverse Distance Weighting (IDW), Selective IDW control-point selection and the
POD-reduced offline/online morph of Ballarin, D'Amario, Perotto and Rozza (2017),
as PyTorch modules.
"""

from .idw import IDW, idw_apply, idw_weights
from .io import read_mesh, write_mesh
from .mesh import TetMesh, box_mesh
from .morph import MeshMorph
from .pod import PODReducer
from .quality import (
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
from .selection import Region, SelectionPlan, select_control_points

__all__ = [
    "IDW",
    "MeshMorph",
    "PODReducer",
    "Region",
    "SelectionPlan",
    "TetMesh",
    "box_mesh",
    "count_inverted",
    "edge_ratio",
    "idw_apply",
    "idw_weights",
    "inverted",
    "mass_matrix",
    "quality_summary",
    "read_mesh",
    "relative_l2_error",
    "relative_nodal_error",
    "select_control_points",
    "signed_volumes",
    "validity_barrier",
    "write_mesh",
]

__version__ = "0.1.0"
