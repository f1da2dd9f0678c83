"""Which backend does the work: the one table of fused backends per device type, the
choice per call (:func:`backend_for`), and the autograd functions that wrap the fused
backends (whose kernels carry no autograd graph of their own).

``implementation="torch"`` always takes :class:`~torchmorph.idw.backends.torch.TorchBackend`;
``"fused"`` the device's fused backend, or raises saying why it cannot run; ``"auto"``
the fused backend where it can run and torch elsewhere (traced calls, other dtypes,
devices without one, gradients to positions it does not fuse).
"""

from __future__ import annotations

import importlib
import math
from typing import Literal

import torch
from torch import Tensor

from torchmorph._checks import check_choice, is_traced, plain_tensor
from torchmorph.idw.backends import Backend
from torchmorph.idw.backends.torch import TorchBackend

__all__ = ["FUSED_BACKENDS", "IMPLEMENTATIONS", "Implementation", "backend_for", "fused_available"]

#: The values of ``implementation`` (see the module notes).
Implementation = Literal["auto", "fused", "torch"]
IMPLEMENTATIONS: tuple[Implementation, ...] = ("auto", "fused", "torch")

#: The fused backend of each device type: (module, class), loaded on first use. Devices
#: of other types, and calls a fused backend cannot serve, take the torch backend.
FUSED_BACKENDS: dict[str, tuple[str, str]] = {
    "cuda": ("torchmorph.idw.backends.triton", "TritonBackend"),
    "cpu": ("torchmorph.idw.backends.numba", "NumbaBackend"),
}
_LOADED: dict[str, Backend | None] = {}


def _fused_backend(device: torch.device) -> Backend | None:
    """The fused backend for ``device``, or None where there is none (or it cannot load)."""
    kind = device.type
    if kind not in _LOADED:
        entry = FUSED_BACKENDS.get(kind)
        try:
            if entry is None:
                _LOADED[kind] = None
            else:
                module, name = entry
                _LOADED[kind] = getattr(importlib.import_module(module), name)()
        except ImportError:
            _LOADED[kind] = None
    return _LOADED[kind]


def fused_available(device: torch.device | str = "cpu") -> bool:
    """Whether fused kernels run on ``device`` (Triton on CUDA, numba on the CPU)."""
    return _fused_backend(torch.device(device)) is not None


def check_implementation(implementation: str) -> Implementation:
    return check_choice(implementation, "implementation", IMPLEMENTATIONS)


def backend_for(
    implementation: str,
    *tensors: Tensor,
    positions_grad: bool = False,
    shape: tuple[int, int] = (3, 3),
    block_bytes: int | None = None,
) -> Backend:
    """The backend to run ``tensors`` (the first one sets device and dtype) on.

    ``positions_grad``: gradients to the points are wanted, for points of dimension
    ``shape[0]`` and ``shape[1]`` value columns. ``implementation="fused"`` raises
    ``ValueError`` where the fused kernels cannot run, saying why.
    """
    implementation = check_implementation(implementation)
    if implementation == "torch":
        return TorchBackend(block_bytes)
    reason = None
    reference = tensors[0]
    fused = _fused_backend(reference.device)
    if any(is_traced(t) for t in tensors):
        reason = "the call is traced (torch.compile or torch.func): use the torch implementation"
    elif reference.dtype not in (torch.float32, torch.float64):
        reason = f"dtype {reference.dtype} (the kernels take float32 and float64)"
    elif fused is None:
        reason = (
            f"no fused kernels on device {reference.device} (Triton on CUDA; numba on "
            f"the CPU, installed with torchmorph)"
        )
    elif positions_grad and not fused.position_gradients_for(*shape):
        reason = (
            f"gradients to point positions are not fused by the {fused.name} backend for "
            f"D = {shape[0]} and {shape[1]} value columns: the torch implementation computes them"
        )
    if reason is None and fused is not None:
        return fused
    if implementation == "fused":
        raise ValueError(f"implementation='fused' cannot run here: {reason}")
    return TorchBackend(block_bytes)


class FusedApply(torch.autograd.Function):
    """``W @ values`` by a fused backend (points in the backend's layout). The backward
    pass is fused too: Wᵀ applied to the incoming gradient for the values, and two
    passes (one over targets, one over controls) for the point positions."""

    @staticmethod
    def forward(ctx, targets, controls, values, backend, power, radius2, nearest2):
        values = values.contiguous()
        streaming = getattr(backend, "apply_streaming", None)
        if nearest2 is None and backend.needs_nearest(values.shape[1]) and streaming:
            out, sums, nearest2 = streaming(
                targets.detach(), controls.detach(), values.detach(), power, radius2
            )
        else:
            if nearest2 is None and backend.needs_nearest(values.shape[1]):
                nearest2 = backend.nearest(targets.detach(), controls.detach())
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


def apply_with(
    backend: Backend,
    targets: Tensor,
    controls: Tensor,
    values: Tensor,
    power: float,
    radius2: float,
    nearest2: Tensor | None = None,
    magnitude: float = 0.0,
) -> Tensor:
    """``W @ values`` (N_t, K) by ``backend``, differentiable: directly for the torch
    backend, through :class:`FusedApply` for the fused ones (normalised points in the
    backend's layout; ``nearest2`` when the caller keeps it).

    ``magnitude`` is the largest |value|: the kernels sum up to N_c unnormalised terms of
    the values before dividing by the weights' sum, so values within a factor N_c of the
    dtype's largest number are scaled down by a power of two (exact) and back up after.
    """
    finfo = torch.finfo(values.dtype)
    if magnitude * max(1, values.shape[0]) > finfo.max / 4:
        exponent = math.frexp(magnitude)[1]  # the values scaled into [-1, 1], exactly
        down = math.ldexp(1.0, -exponent)
        scaled = _apply(backend, targets, controls, values * down, power, radius2, nearest2)
        return scaled * math.ldexp(1.0, exponent - 1) * 2.0  # 2**exponent may overflow
    return _apply(backend, targets, controls, values, power, radius2, nearest2)


def _apply(backend, targets, controls, values, power, radius2, nearest2) -> Tensor:
    if backend.differentiable:
        return backend.apply(targets, controls, values, power, radius2, nearest2)[0]
    needs_graph = torch.is_grad_enabled() and any(
        x.requires_grad for x in (targets, controls, values)
    )
    if needs_graph:
        return FusedApply.apply(targets, controls, values, backend, power, radius2, nearest2)
    if nearest2 is None and backend.needs_nearest(values.shape[1]):
        streaming = getattr(backend, "apply_streaming", None)
        if streaming:  # one pass: the nearest distance found on the way
            return streaming(targets, controls, values.contiguous(), power, radius2)[0]
        nearest2 = backend.nearest(targets, controls)
    return backend.apply(targets, controls, values.contiguous(), power, radius2, nearest2)[0]


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


def assemble_weights(
    targets: Tensor,
    controls: Tensor,
    power: float,
    radius2: float,
    block_bytes: int | None,
    implementation: str = "auto",
) -> Tensor:
    """Dense W (N_t, N_c) of normalised points, row-major, without autograd: written once
    by a fused kernel, or block by block in place by the torch backend."""
    backend = backend_for(implementation, targets, controls, block_bytes=block_bytes)
    weights = torch.empty(
        targets.shape[0], controls.shape[0], dtype=controls.dtype, device=controls.device
    )
    with torch.no_grad():
        return backend.weights(
            backend.layout(targets), backend.layout(controls), power, radius2, out=weights
        )


def dense_apply(weights: Tensor, displacements: Tensor, implementation: str = "auto") -> Tensor:
    """``W @ d`` for d of shape (N_c, D) or (B, N_c, D), as one contraction.

    One displacement on a device with fused kernels goes through a kernel that
    reads W once (a GEMM with three columns reaches a fraction of the memory
    bandwidth). Under ``vmap`` a single (N_c, D) displacement is a batch in
    disguise: written as ``(dᵀ Wᵀ)ᵀ`` with a contiguous ``dᵀ`` the batch folds into
    the rows of one GEMM, where ``W @ d`` becomes a batched product that reads W
    once per batch entry (7x slower for 2,000 values at case-C size).
    """
    if displacements.ndim == 2:
        traced = torch.compiler.is_compiling() or plain_tensor(displacements)[1]
        backend = None if traced else backend_for(implementation, weights, displacements)
        if backend is not None and displacements.shape[1] <= backend.dense_columns():
            if torch.is_grad_enabled() and displacements.requires_grad:
                return _FusedDenseApply.apply(weights, displacements, backend)
            return backend.dense_apply(weights, displacements.contiguous())
        if not torch.compiler.is_compiling() and plain_tensor(displacements)[1]:
            return (displacements.mT.contiguous() @ weights.mT).mT
        return weights @ displacements
    # a batch as the rows of one GEMM, dᵀ Wᵀ: 0.48 s against 1.03 s for W d at case B's W
    # with 30 columns (two threads)
    batch, n_controls, dim = displacements.shape
    rows = displacements.mT.reshape(batch * dim, n_controls)
    return (rows @ weights.mT).reshape(batch, dim, -1).mT.contiguous()
