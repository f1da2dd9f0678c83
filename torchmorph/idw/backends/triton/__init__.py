"""The Triton backend of IDW: fused CUDA kernels (:mod:`~torchmorph.idw.backends.triton.kernels`,
launching those of :mod:`~torchmorph.idw.backends.triton._jit`) behind the
:class:`~torchmorph.idw.backends.Backend` protocol. Importing this package does not
import Triton; building a :class:`TritonBackend` does."""

from __future__ import annotations

from torch import Tensor

__all__ = ["TritonBackend"]


class TritonBackend:
    """Triton kernels on CUDA; geometry laid out axis by axis, (D, N)."""

    name = "triton"
    differentiable = False

    def __init__(self) -> None:
        from torchmorph.idw.backends.triton import kernels

        self.kernels = kernels

    @staticmethod
    def layout(points: Tensor) -> Tensor:
        return points.T.contiguous()

    def nearest(self, targets, controls):
        return self.kernels.nearest_squared(targets, controls)

    @staticmethod
    def needs_nearest(columns: int) -> bool:
        return True

    def apply(self, targets, controls, values, power, radius2, nearest2):
        return self.kernels.apply(targets, controls, values, power, radius2, nearest2)

    def apply_transposed(self, targets, controls, grad, power, radius2, nearest2, sums):
        if nearest2 is None:
            nearest2 = self.nearest(targets, controls)
        if sums is None:  # the row sums alone: an apply to no value columns
            empty = grad.new_empty(controls.shape[1], 0)
            _, sums = self.apply(targets, controls, empty, power, radius2, nearest2)
        return self.kernels.apply_transposed(
            targets, controls, grad, power, radius2, nearest2, sums
        )

    def weights(self, targets, controls, power, radius2, out=None):
        return self.kernels.weights(targets, controls, power, radius2, out=out)

    def dense_columns(self) -> int:
        return self.kernels.SMALL_COLUMNS

    def dense_apply(self, weights, values):
        return self.kernels.dense_apply(weights, values)

    def position_gradients_for(self, dim: int, columns: int) -> bool:
        return dim <= 3 and columns <= self.kernels.POSITION_GRAD_COLUMNS

    def position_gradients(
        self,
        targets,
        controls,
        values,
        grad,
        out,
        nearest2,
        sums,
        power,
        radius2,
        need_targets,
        need_controls,
    ):
        return self.kernels.position_gradients(
            targets,
            controls,
            values,
            grad,
            out,
            nearest2,
            sums,
            power,
            radius2,
            need_targets,
            need_controls,
        )
