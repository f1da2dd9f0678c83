"""Radial basis function morphing: scipy's :class:`~scipy.interpolate.RBFInterpolator`
kernels and Wendland's compactly supported ones, with a polynomial tail.

The kernels and the matrices built from them (:mod:`torchmorph.rbf.kernels`), the
factorised interpolation system (:mod:`torchmorph.rbf.system`), the functional core
(:mod:`torchmorph.rbf.functional`: :func:`rbf_interpolate`), the :class:`RBF` module
(:mod:`torchmorph.rbf.module`) over them, the partition-of-unity :class:`PartitionRBF`
for many controls (:mod:`torchmorph.rbf.partition`; :func:`build_rbf` of :mod:`torchmorph.rbf.solvers` choosing it, the
sparse fit or the dense one), the :class:`SparseRBF` of a compactly supported kernel
(:mod:`torchmorph.rbf.sparse`), and greedy reduction
(:mod:`torchmorph.rbf.greedy`: :class:`RBFErrorOracle`, the oracle of
:func:`torchmorph.selection.greedy.greedy_selection` for RBF interpolation).
"""

from torchmorph.rbf.functional import (
    DEFAULT_BLOCK_BYTES,
    DEFAULT_CUDA_BLOCK_BYTES,
    rbf_interpolate,
)
from torchmorph.rbf.greedy import RBFErrorOracle
from torchmorph.rbf.kernels import KERNELS, MIN_DEGREE, SCALE_INVARIANT, WENDLAND
from torchmorph.rbf.module import RBF
from torchmorph.rbf.partition import PartitionRBF
from torchmorph.rbf.solvers import PARTITION_CONTROLS, build_rbf
from torchmorph.rbf.sparse import SparseRBF

__all__ = [
    "DEFAULT_BLOCK_BYTES",
    "DEFAULT_CUDA_BLOCK_BYTES",
    "KERNELS",
    "MIN_DEGREE",
    "PARTITION_CONTROLS",
    "RBF",
    "SCALE_INVARIANT",
    "WENDLAND",
    "PartitionRBF",
    "RBFErrorOracle",
    "SparseRBF",
    "build_rbf",
    "rbf_interpolate",
]
