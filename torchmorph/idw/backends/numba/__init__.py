"""The numba backend of IDW: fused CPU kernels (:mod:`~torchmorph.idw.backends.numba.kernels`,
compiled from :mod:`~torchmorph.idw.backends.numba._jit`) behind the
:class:`~torchmorph.idw.backends.Backend` protocol."""

from __future__ import annotations

import torch
from torch import Tensor

from torchmorph._dense import MAX_COLUMNS
from torchmorph.idw.backends.numba import kernels
from torchmorph.idw.backends.torch import nearest_by_kd_tree, rows_per_block

__all__ = ["GEMM_BLOCK_BYTES", "GEMM_COLUMNS", "KD_TREE_BYTES", "NumbaBackend"]

#: the nearest control: up to this many bytes of control coordinates per dimension
#: (4,096 float32 or 2,048 float64 controls) a fused brute-force pass, beyond it scipy's
#: KD-tree. Measured on one thread with controls on a boundary and targets filling the
#: volume (every IDW morph: the KD-tree visits most of its leaves for a target far from
#: the boundary): the pass was 1.3-2.8x faster in float32 up to 3,845 controls and
#: 1.9-2.7x in float64 up to 1,216, about even at ~2,700-3,800 float64 controls; with 1e4
#: or more controls the KD-tree was up to 2.4x faster (3e3-1e6 targets, meshes, clouds).
KD_TREE_BYTES = 16 * 1024

#: value columns beyond which the matrix-free apply and its transpose assemble W in
#: blocks of GEMM_BLOCK_BYTES and multiply each by torch's GEMM: the fused kernel's cost
#: grows with every column (one dot product per column and chunk), a GEMM's hardly.
#: Measured at case-B counts (14,126 x 21,910), 1 and 2 threads, p = 4: the fused kernel
#: was faster up to 12 columns (1.1-3.7x), about even at 24, and the blocks 1.5-3.5x
#: faster at 48 columns (a batch of 16) and 2.2-5x at 300.
GEMM_COLUMNS = 24
GEMM_BLOCK_BYTES = 16 << 20


class NumbaBackend:
    """numba kernels on the CPU; geometry as given, (N, D) rows."""

    name = "numba"
    differentiable = False

    def __init__(self) -> None:
        if not kernels.available():
            raise ImportError("numba is not installed")

    @staticmethod
    def layout(points: Tensor) -> Tensor:
        return points.contiguous()

    def nearest(self, targets: Tensor, controls: Tensor) -> Tensor:
        if controls.shape[0] * controls.element_size() <= KD_TREE_BYTES:
            nearest2 = kernels.nearest_squared(targets, controls)
        else:  # many controls: scipy's KD-tree, the distance recomputed exactly
            nearest2 = nearest_by_kd_tree(targets, controls)
        return nearest2.clamp_min(torch.finfo(targets.dtype).tiny)

    @staticmethod
    def apply_streaming(targets, controls, values, power, radius2):
        """(W @ values, the row sums, nearest2) in one pass over the controls, for a call
        without ``nearest2`` (a one-shot apply, a module's first call): the nearest
        distance is found on the way (:func:`kernels.apply_streaming`). Measured on one
        thread at 20,000 × 50,000: 1.05-1.09x the time of :meth:`apply` given nearest2,
        where the nearest pass first and the apply after took 1.4-1.5x."""
        return kernels.apply_streaming(targets, controls, values, power, radius2)

    @staticmethod
    def needs_nearest(columns: int) -> bool:
        return columns <= GEMM_COLUMNS  # the blocks of W find it themselves

    def apply(self, targets, controls, values, power, radius2, nearest2):
        """(W @ values, the row sums s_i, or None where W came in blocks)."""
        if values.shape[1] > GEMM_COLUMNS:
            return self._by_blocks(targets, controls, values, power, radius2), None
        if nearest2 is None:
            nearest2 = self.nearest(targets, controls)
        return kernels.apply(targets, controls, values, power, radius2, nearest2)

    def apply_transposed(self, targets, controls, grad, power, radius2, nearest2, sums):
        if sums is None or nearest2 is None or grad.shape[1] > GEMM_COLUMNS:
            return self._by_blocks(targets, controls, grad, power, radius2, transposed=True)
        return kernels.apply_transposed(targets, controls, grad, power, radius2, nearest2, sums)

    @staticmethod
    def _by_blocks(targets, controls, values, power, radius2, transposed=False):
        """W @ values (or Wᵀ @ values): blocks of rows of W from the fused assembly kernel,
        each multiplied by torch's GEMM while it is in cache; W is never stored whole."""
        n_targets, n_controls = targets.shape[0], controls.shape[0]
        rows = rows_per_block(n_controls, controls.element_size(), GEMM_BLOCK_BYTES, copies=1)
        buffer = targets.new_empty(min(rows, n_targets), n_controls)
        if transposed:
            out = targets.new_zeros(n_controls, values.shape[1])
        else:
            out = targets.new_empty(n_targets, values.shape[1])
        for start in range(0, n_targets, rows):
            block = targets[start : start + rows]
            weights = kernels.weights(block, controls, power, radius2, out=buffer[: block.shape[0]])
            if transposed:
                out.addmm_(weights.mT, values[start : start + rows])
            else:
                torch.mm(weights, values, out=out[start : start + rows])
        return out

    @staticmethod
    def weights(targets, controls, power, radius2, out=None):
        return kernels.weights(targets, controls, power, radius2, out=out)

    @staticmethod
    def dense_columns() -> int:
        # the pass of torchmorph._dense: 2.9x the BLAS product for 3 columns at case C's W
        return MAX_COLUMNS

    @staticmethod
    def dense_apply(weights, values):
        return kernels.dense_apply(weights, values)

    @staticmethod
    def position_gradients_for(dim: int, columns: int) -> bool:
        return False

    def position_gradients(self, *args, **kwargs):
        raise NotImplementedError("the numba backend has no fused gradients to positions")
