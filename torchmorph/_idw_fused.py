"""Dispatch to the fused IDW kernels: one table of backends, and the autograd functions.

Triton kernels on CUDA devices (:mod:`torchmorph._triton_kernels`) and numba kernels on
the CPU (:mod:`torchmorph._cpu_kernels`, when numba is installed) share one interface,
so :mod:`torchmorph.idw` picks a backend per call in one place (:func:`_fused_for`).
"""

from __future__ import annotations

import torch
from torch import Tensor

from ._checks import is_traced, plain_tensor
from ._idw_torch import _block_bytes, _rows_per_block, _weights_block

__all__ = ["IMPLEMENTATIONS", "fused_available"]

IMPLEMENTATIONS = ("auto", "fused", "torch")


class _TritonBackend:
    """Triton kernels on CUDA; geometry laid out axis by axis, (D, N)."""

    def __init__(self):
        from . import _triton_kernels

        self.kernels = _triton_kernels

    @staticmethod
    def layout(points: Tensor) -> Tensor:
        return points.T.contiguous()

    def nearest(self, targets, controls):
        return self.kernels.nearest_squared(targets, controls)

    @staticmethod
    def needs_nearest(columns: int) -> bool:
        return True

    def apply(self, targets, controls, values, power, radius2, nearest2):
        out, nearest2, sums = self.kernels.apply(
            targets, controls, values, power, radius2, nearest2
        )
        return out, sums

    def apply_transposed(self, targets, controls, grad, power, radius2, nearest2, sums):
        return self.kernels.apply_transposed(
            targets, controls, grad, nearest2, sums, power, radius2
        )

    def weights(self, targets, controls, power, radius2, out=None):
        return self.kernels.weights(targets, controls, power, radius2, out=out)

    def dense_columns(self) -> int:
        """Up to how many columns :meth:`dense_apply` beats the BLAS product."""
        return self.kernels.SMALL_COLUMNS

    def position_gradients_for(self, dim: int, columns: int) -> bool:
        """Whether :meth:`position_gradients` handles this many dimensions and columns."""
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

    def dense_apply(self, weights, values):
        return self.kernels.dense_apply(weights, values)


#: the nearest control: up to this many bytes of control coordinates per dimension
#: (4,096 float32 or 2,048 float64 controls) a fused brute-force pass, beyond it scipy's
#: KD-tree. Measured on one thread with controls on a boundary and targets filling the
#: volume (every IDW morph: the KD-tree visits most of its leaves for a target far from
#: the boundary): the pass was 1.3-2.8x faster in float32 up to 3,845 controls and
#: 1.9-2.7x in float64 up to 1,216, about even at ~2,700-3,800 float64 controls; with 1e4
#: or more controls the KD-tree was up to 2.4x faster (3e3-1e6 targets, meshes, clouds).
KD_TREE_BYTES = 16 * 1024

#: value columns beyond which the CPU's matrix-free apply and its transpose assemble W
#: in blocks of GEMM_BLOCK_BYTES and multiply each by torch's GEMM: the fused kernel's
#: cost grows with every column (one dot product per column and chunk), a GEMM's
#: hardly. Measured at case-B counts (14,126 x 21,910), 1 and 2 threads, p = 4: the
#: fused kernel was faster up to 12 columns (1.1-3.7x), about even at 24, and the blocks
#: 1.5-3.5x faster at 48 columns (a batch of 16) and 2.2-5x at 300. The assembly runs on
#: all of torch's threads (numba, blocks of rows handed out one at a time) and the GEMM
#: on half of them: a GEMM splits its work statically, so on a machine whose every core
#: is busy the thread that shares its core with another process sets the pace (beside a
#: busy process on 2 cores and 2 threads: 2.4-3.3x the quiet time with the GEMM on both
#: threads, 1.6-2.3x with it on one, and still 1.3-1.7x faster than the fused kernel).
GEMM_COLUMNS = 24
GEMM_BLOCK_BYTES = 16 << 20


class _NumbaBackend:
    """numba kernels on the CPU; geometry as given, (N, D) rows."""

    def __init__(self):
        from . import _cpu_kernels

        if not _cpu_kernels.available():
            raise ImportError("numba is not installed")
        self.kernels = _cpu_kernels

    @staticmethod
    def layout(points: Tensor) -> Tensor:
        return points.contiguous()

    def nearest(self, targets, controls):
        if controls.shape[0] * controls.element_size() <= KD_TREE_BYTES:
            nearest2 = self.kernels.nearest_squared(targets, controls)
        else:  # many controls: scipy's KD-tree, the distance recomputed exactly
            from ._idw_torch import _nearest_squared_distance

            nearest2 = _nearest_squared_distance(targets, controls, (1, 1)).flatten()
        return nearest2.clamp_min(torch.finfo(targets.dtype).tiny)

    @staticmethod
    def needs_nearest(columns: int) -> bool:
        return columns <= GEMM_COLUMNS  # the blocks of W find it themselves

    def apply(self, targets, controls, values, power, radius2, nearest2):
        """(W @ values, the row sums s_i, or None where W came in blocks)."""
        if values.shape[1] > GEMM_COLUMNS:
            return self._by_blocks(targets, controls, values, power, radius2), None
        return self.kernels.apply(targets, controls, values, power, radius2, nearest2)

    def apply_transposed(self, targets, controls, grad, power, radius2, nearest2, sums):
        if sums is None or grad.shape[1] > GEMM_COLUMNS:
            return self._by_blocks(targets, controls, grad, power, radius2, transposed=True)
        return self.kernels.apply_transposed(
            targets, controls, grad, power, radius2, nearest2, sums
        )

    def _by_blocks(self, targets, controls, values, power, radius2, transposed=False):
        """W @ values (or Wᵀ @ values): blocks of rows of W from the fused assembly kernel,
        each multiplied by torch's GEMM while it is in cache; W is never stored whole.
        torch's thread count is halved for each GEMM and restored after it (the count is
        process-wide: torch work in other Python threads meanwhile sees it too)."""
        n_targets, n_controls = targets.shape[0], controls.shape[0]
        rows = _rows_per_block(n_controls, controls.element_size(), GEMM_BLOCK_BYTES, copies=1)
        buffer = targets.new_empty(min(rows, n_targets), n_controls)
        if transposed:
            out = targets.new_zeros(n_controls, values.shape[1])
        else:
            out = targets.new_empty(n_targets, values.shape[1])
        threads = torch.get_num_threads()
        gemm_threads = max(1, threads // 2)  # the other half free for a competing process
        for start in range(0, n_targets, rows):
            block = targets[start : start + rows]
            weights = self.kernels.weights(
                block, controls, power, radius2, out=buffer[: block.shape[0]]
            )
            if gemm_threads != threads:
                torch.set_num_threads(gemm_threads)
            try:
                if transposed:
                    out.addmm_(weights.mT, values[start : start + rows])
                else:
                    torch.mm(weights, values, out=out[start : start + rows])
            finally:
                if gemm_threads != threads:
                    torch.set_num_threads(threads)
        return out

    def weights(self, targets, controls, power, radius2, out=None):
        return self.kernels.weights(targets, controls, power, radius2, out=out)

    def dense_columns(self) -> int:
        # the BLAS product reads a stored W as fast (0.65-1.2x measured) and keeps threads
        return 0

    def position_gradients_for(self, dim: int, columns: int) -> bool:
        return False

    def dense_apply(self, weights, values):
        return self.kernels.dense_apply(weights, values)


_BACKENDS = {"cuda": _TritonBackend, "cpu": _NumbaBackend}
_LOADED: dict[str, object] = {}


def _backend(device: torch.device):
    """The fused backend for ``device``, or None where there is none (or it cannot load)."""
    kind = device.type
    if kind not in _LOADED:
        factory = _BACKENDS.get(kind)
        try:
            _LOADED[kind] = factory() if factory is not None else None
        except ImportError:
            _LOADED[kind] = None
    return _LOADED[kind]


def fused_available(device: torch.device | str = "cpu") -> bool:
    """Whether fused kernels run on ``device`` (Triton on CUDA, numba on the CPU)."""
    return _backend(torch.device(device)) is not None


def _check_implementation(implementation: str) -> str:
    if implementation not in IMPLEMENTATIONS:
        raise ValueError(
            f"implementation must be 'auto', 'fused' or 'torch', got {implementation!r}"
        )
    return implementation


def _fused_for(
    implementation: str,
    *tensors: Tensor,
    positions_grad: bool = False,
    shape: tuple[int, int] = (3, 3),
):
    """The fused backend to use for ``tensors``, or None for the torch implementation.

    ``positions_grad``: gradients to the points are wanted, for points of dimension
    ``shape[0]`` and ``shape[1]`` value columns. ``implementation="fused"`` raises where
    the kernels cannot run, saying why.
    """
    implementation = _check_implementation(implementation)
    if implementation == "torch":
        return None
    reason = None
    reference = tensors[0]
    if any(is_traced(t) for t in tensors):
        reason = "the call is traced (torch.compile or torch.func): use the torch implementation"
    elif reference.dtype not in (torch.float32, torch.float64):
        reason = f"dtype {reference.dtype} (the kernels take float32 and float64)"
    elif _backend(reference.device) is None:
        reason = (
            f"no fused kernels on device {reference.device} (Triton on CUDA; numba on "
            f"the CPU, installed with torchmorph)"
        )
    elif positions_grad and not _backend(reference.device).position_gradients_for(*shape):
        reason = (
            f"gradients to point positions are fused on CUDA for D <= 3 and at most "
            f"{_POSITION_GRAD_COLUMNS} value columns, here {reference.device}, D = "
            f"{shape[0]}, {shape[1]} columns: the torch implementation computes them"
        )
    if reason is None:
        return _backend(reference.device)
    if implementation == "fused":
        raise ValueError(f"implementation='fused' cannot run here: {reason}")
    return None


_POSITION_GRAD_COLUMNS = 24


class _FusedApply(torch.autograd.Function):
    """``W @ values`` by a fused backend (points in the backend's layout). The backward
    pass is fused too: Wᵀ applied to the incoming gradient for the values, and two
    passes (one over targets, one over controls) for the point positions."""

    @staticmethod
    def forward(ctx, targets, controls, values, backend, power, radius2, nearest2):
        if nearest2 is None and backend.needs_nearest(values.shape[1]):
            nearest2 = backend.nearest(targets.detach(), controls.detach())
        values = values.contiguous()
        out, sums = backend.apply(
            targets.detach(), controls.detach(), values.detach(), power, radius2, nearest2
        )
        ctx.save_for_backward(
            targets.detach(), controls.detach(), values.detach(), out, nearest2, sums
        )
        ctx.settings = (backend, power, radius2)
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):
        targets, controls, values, out, nearest2, sums = ctx.saved_tensors
        backend, power, radius2 = ctx.settings
        grad = grad.contiguous()
        grad_targets = grad_controls = grad_values = None
        if ctx.needs_input_grad[2]:
            grad_values = backend.apply_transposed(
                targets, controls, grad, power, radius2, nearest2, sums
            )
        if ctx.needs_input_grad[0] or ctx.needs_input_grad[1]:
            grad_targets, grad_controls = backend.position_gradients(
                targets,
                controls,
                values,
                grad,
                out,
                nearest2,
                sums,
                power,
                radius2,
                ctx.needs_input_grad[0],
                ctx.needs_input_grad[1],
            )
        return grad_targets, grad_controls, grad_values, None, None, None, None


class _FusedDenseApply(torch.autograd.Function):
    """``W @ values`` for a stored W by a fused kernel that reads W once; backward Wᵀ g."""

    @staticmethod
    def forward(ctx, weights, values, backend):
        ctx.save_for_backward(weights)
        return backend.dense_apply(weights, values.contiguous())

    @staticmethod
    def backward(ctx, grad):
        (weights,) = ctx.saved_tensors
        return None, weights.mT @ grad, None


def _assemble_weights(
    targets: Tensor,
    controls: Tensor,
    power: float,
    radius2: float,
    block_bytes: int | None,
    implementation: str = "auto",
) -> Tensor:
    """Dense W (N_t, N_c) of normalised points, row-major, without autograd: by a fused
    kernel that writes W once, or block by block in place."""
    weights = torch.empty(
        targets.shape[0], controls.shape[0], dtype=controls.dtype, device=controls.device
    )
    backend = _fused_for(implementation, targets, controls)
    with torch.no_grad():
        if backend is not None:
            return backend.weights(
                backend.layout(targets), backend.layout(controls), power, radius2, out=weights
            )
        rows = _rows_per_block(
            controls.shape[0], controls.element_size(), _block_bytes(block_bytes, controls.device)
        )
        controls_t = controls.T.contiguous()
        for start in range(0, targets.shape[0], rows):
            _weights_block(
                targets[start : start + rows],
                controls,
                power,
                radius2,
                out=weights[start : start + rows],
                controls_t=controls_t,
            )
    return weights


def _dense_apply(weights: Tensor, displacements: Tensor, implementation: str = "auto") -> Tensor:
    """``W @ d`` for d of shape (N_c, 3) or (B, N_c, 3), as one contraction.

    One displacement on a device with fused kernels goes through a kernel that
    reads W once (a GEMM with three columns reaches a fraction of the memory
    bandwidth). Under ``vmap`` a single (N_c, 3) displacement is a batch in
    disguise: written as ``(dᵀ Wᵀ)ᵀ`` with a contiguous ``dᵀ`` the batch folds into
    the rows of one GEMM, where ``W @ d`` becomes a batched product that reads W
    once per batch entry (7x slower for 2,000 values at case-C size).
    """
    if displacements.ndim == 2:
        traced = torch.compiler.is_compiling() or plain_tensor(displacements)[1]
        backend = None if traced else _fused_for(implementation, weights, displacements)
        if backend is not None and displacements.shape[1] <= backend.dense_columns():
            if torch.is_grad_enabled() and displacements.requires_grad:
                return _FusedDenseApply.apply(weights, displacements, backend)
            return backend.dense_apply(weights, displacements.contiguous())
        if not torch.compiler.is_compiling() and plain_tensor(displacements)[1]:
            return (displacements.mT.contiguous() @ weights.mT).mT
        return weights @ displacements
    batch, n_controls, _ = displacements.shape
    stacked = displacements.permute(1, 0, 2).reshape(n_controls, batch * 3)
    return (weights @ stacked).reshape(-1, batch, 3).permute(1, 0, 2)
