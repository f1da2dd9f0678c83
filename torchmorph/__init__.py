"""torchmorph: fast, differentiable, parametrized shape morphing of meshes.

Inverse Distance Weighting (IDW), Selective IDW control-point selection and the
POD-reduced offline/online morph of Ballarin, D'Amario, Perotto and Rozza (2017),
as PyTorch modules.
"""

from torchmorph import _moved  # noqa: F401  (0.1.0's module names, deprecated)
from torchmorph.ffd import FFD
from torchmorph.idw import IDW, idw_apply, idw_weights
from torchmorph.mesh import (
    Mesh,
    TetMesh,
    box_mesh,
    count_inverted,
    edge_ratio,
    inverted,
    mass_matrix,
    quality_by_kind,
    quality_summary,
    read_mesh,
    relative_l2_error,
    relative_nodal_error,
    signed_volumes,
    validity_barrier,
    write_mesh,
    write_morphed,
)
from torchmorph.morph import MeshMorph
from torchmorph.pod import PODReducer
from torchmorph.rbf import RBF, RBFErrorOracle, rbf_interpolate
from torchmorph.selection import Region, SelectionPlan, select_control_points

__all__ = [
    "FFD",
    "IDW",
    "RBF",
    "Mesh",
    "MeshMorph",
    "PODReducer",
    "RBFErrorOracle",
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
    "quality_by_kind",
    "quality_summary",
    "rbf_interpolate",
    "read_mesh",
    "relative_l2_error",
    "relative_nodal_error",
    "select_control_points",
    "signed_volumes",
    "validity_barrier",
    "write_mesh",
    "write_morphed",
]

__version__ = "0.3.0.dev0"
