"""torchmorph: fast, differentiable, parametrized shape morphing of tetrahedral meshes.

Inverse Distance Weighting (IDW), Selective IDW control-point selection and the
POD-reduced offline/online morph of Ballarin, D'Amario, Perotto and Rozza (2017),
as PyTorch modules.
"""

from .idw import IDW, idw_apply, idw_weights

__all__ = [
    "IDW",
    "idw_apply",
    "idw_weights",
]

__version__ = "0.1.0"
