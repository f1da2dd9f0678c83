"""Inverse Distance Weighting (the paper's Section 2, eqs. 1–4).

The functional core (:mod:`torchmorph.idw.functional`: :func:`idw_weights`,
:func:`idw_apply`) and the :class:`IDW` module (:mod:`torchmorph.idw.module`) over it;
:class:`StiffenedIDW` (:mod:`torchmorph.idw.stiffened`) adds near-wall stiffening.
Both hand the kernel work to one of the backends of :mod:`torchmorph.idw.backends`
(torch operations, Triton on CUDA, numba on the CPU), chosen per call in
:mod:`torchmorph.idw._dispatch`.
"""

from torchmorph.idw._dispatch import IMPLEMENTATIONS, fused_available
from torchmorph.idw.backends.torch import DEFAULT_BLOCK_BYTES, DEFAULT_CUDA_BLOCK_BYTES
from torchmorph.idw.functional import (
    DEFAULT_COINCIDENCE_TOLERANCE,
    Implementation,
    idw_apply,
    idw_weights,
)
from torchmorph.idw.module import DEFAULT_DENSE_BYTES, IDW, Mode
from torchmorph.idw.stiffened import StiffenedIDW, stiffening_blend

__all__ = [
    "DEFAULT_BLOCK_BYTES",
    "DEFAULT_COINCIDENCE_TOLERANCE",
    "DEFAULT_CUDA_BLOCK_BYTES",
    "DEFAULT_DENSE_BYTES",
    "IDW",
    "IMPLEMENTATIONS",
    "Implementation",
    "Mode",
    "StiffenedIDW",
    "fused_available",
    "idw_apply",
    "idw_weights",
    "stiffening_blend",
]
