"""The fused thin-plate pass of :mod:`torchmorph.rbf._numba` over several threads (numba
``prange`` over chunks of targets, ``numba.get_num_threads()`` of them), for the
partition-of-unity RBF (:mod:`torchmorph.rbf.partition`), whose evaluations at 10⁶
targets dominate a morph. The per-target sums are :mod:`torchmorph.rbf._numba`'s
(squared distances, ``s log(s) / 2`` and the dot products with the value columns, by
chunks of controls); the one-thread :func:`torchmorph.rbf._numba.tps_apply` runs the same
sums (the tests compare them).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import numpy as np
import torch
from torch import Tensor

from torchmorph._threads import numba_threads
from torchmorph.rbf import _numba
from torchmorph.rbf.functional import evaluate
from torchmorph.rbf.kernels import fused

try:
    from numba import njit, prange
except ImportError:  # pragma: no cover - exercised where numba is missing
    njit = prange = None  # type: ignore[assignment,misc]

__all__ = ["CHUNK_TARGETS", "kernel_sum", "one_torch_thread", "tps_apply_parallel"]

#: Targets per ``prange`` iteration (one scratch row per chunk).
CHUNK_TARGETS = 256


def _apply_chunks(tx, ty, tz, cx, cy, cz, scale2, weights_t, out, chunk):
    total = tx.shape[0]
    chunks = (total + chunk - 1) // chunk
    for index in prange(chunks):  # one chunk of targets per iteration, its own scratch
        row, exponent, mantissa_bits, totals = _numba.scratch(weights_t.shape[0])
        for i in range(index * chunk, min(total, (index + 1) * chunk)):
            _numba._target_sums(
                tx[i],
                ty[i],
                tz[i],
                cx,
                cy,
                cz,
                scale2,
                weights_t,
                row,
                exponent,
                mantissa_bits,
                totals,
            )
            out[i, :] = totals


if njit is not None:
    _apply_chunks = njit(
        parallel=True, fastmath=_numba._FLAGS, error_model="numpy", cache=True, nogil=True
    )(_apply_chunks)


@contextlib.contextmanager
def one_torch_thread() -> Iterator[None]:
    """torch on one thread for a loop of small operations (a patch's solve: on a machine
    shared with other work, each parallel region of a small operation waits for a
    descheduled sibling thread, measured 50 ms instead of 0.5 ms for a 314-control solve
    on two threads); its count restored after."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def tps_apply_parallel(
    points: Tensor, centres: Tensor, scale: float, weights: Tensor, threads: int
) -> Tensor:
    """``Σ_j φ(scale · |points_i − centres_j|) weights_j``, shape (N, S), float64 CPU, the
    thin-plate spline ``φ(r) = r² log r``, on ``threads`` of numba's threads."""
    out = torch.empty(points.shape[0], weights.shape[1], dtype=torch.float64)
    if not points.shape[0]:
        return out
    weights_t = np.ascontiguousarray(weights.detach().numpy().T)
    tx, ty, tz = _numba._axes(points)
    cx, cy, cz = _numba._axes(centres)
    with numba_threads(threads):
        _apply_chunks(tx, ty, tz, cx, cy, cz, scale * scale, weights_t, out.numpy(), CHUNK_TARGETS)
    return out


class _ParallelFused(torch.autograd.Function):
    """``Φ(points, centres) @ weights`` by the thin-plate spline's fused pass on numba's
    threads, differentiable in the weights (the backward pass swaps the point sets)."""

    @staticmethod
    def forward(ctx, points, centres, scale, weights, threads):  # type: ignore[override]
        ctx.save_for_backward(points, centres)
        ctx.scale, ctx.threads = scale, threads
        return tps_apply_parallel(points, centres, scale, weights, threads)

    @staticmethod
    def backward(ctx, grad):  # type: ignore[override]
        points, centres = ctx.saved_tensors
        weights_grad = None
        if ctx.needs_input_grad[3]:
            weights_grad = tps_apply_parallel(centres, points, ctx.scale, grad, ctx.threads)
        return None, None, None, weights_grad, None


def kernel_sum(
    points: Tensor,
    centres: Tensor,
    weights: Tensor,
    kernel: str,
    scale: float,
    block_bytes: int | None,
    threads: int,
) -> Tensor:
    """``Σ_k weights_k φ(scale |x − centres_k|)`` at ``points`` (float64), shape (N, S):
    the fused pass on ``threads`` of numba's threads for the thin-plate spline on the
    CPU, torch blocks otherwise."""
    if fused(kernel, centres) and points.shape[0]:
        return _ParallelFused.apply(points, centres, scale, weights, threads)
    empty = weights.new_zeros(0, weights.shape[1])
    return evaluate(
        points,
        centres,
        weights,
        empty,
        kernel=kernel,
        scale=scale,
        powers=[],
        shift=centres.new_zeros(centres.shape[1]),
        poly_scale=centres.new_ones(centres.shape[1]),
        block_bytes=block_bytes,
    )
