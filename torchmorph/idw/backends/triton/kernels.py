"""Fused IDW kernels in Triton (CUDA; and the CPU through ``TRITON_INTERPRET=1``).

Each kernel computes the paper's eq. (2) weights in registers and never writes a
pairwise tile to memory. The caller (:mod:`torchmorph.idw`) hands over geometry
already scaled by a power of two so that every coordinate lies in [-1, 1] (not
translated), coordinates stored axis by axis (shape ``(D, N)``, contiguous), so every
squared distance lies in [0, 4D] and a block of one coordinate is one contiguous load.

For target ``i`` and control ``k``, with ``d²_ik`` from direct coordinate
differences floored at the dtype's smallest normal ``tiny`` and ``m_i = min_k d²_ik``:

- an ordinary row (``m_i > radius2``) has ``r_ik = (m_i / d²_ik)^(p/2)`` (every term
  in [0, 1]) and ``w_ik = r_ik / s_i`` with ``s_i = Σ_k r_ik``;
- a coincident row (``m_i <= radius2``) has ``r_ik = [d²_ik <= radius2]`` and
  ``s_i`` their count: the target takes the mean of the controls it sits on.

Kernels (in :mod:`torchmorph.idw.backends.triton._jit`)
------------------------------------------
``_nearest_kernel``
    pass 1: ``m_i`` for each target (once per geometry: modules keep it).
``_apply_kernel``
    pass 2, ``W @ V`` for V of shape (N_c, K), K <= 3: the weights against ``[v, 1]``
    accumulated per tile position, divided by the row sums at the end; also returns
    ``s_i`` for the backward pass.
``_apply_dot_kernel``
    pass 2 for more columns (a batch of displacements): the weight tile times
    ``[V, 1]`` on the matrix units (float32 in three tf32 products, float32 accuracy).
``_transposed_kernel``, ``_transposed_dot_kernel``
    ``Wᵀ @ G`` (the gradient to the displacements): parallel over controls, looping
    over targets with the saved ``m_i`` and ``s_i``.
``_weights_kernel``
    dense W, written tile by tile after the row statistics.
``_dense_apply_kernel``
    ``W @ v`` for a stored W and at most three columns, reading W once.
``_position_grad_kernel``
    the gradients to target and control positions.

Each has a plain torch twin in :mod:`torchmorph.idw.backends.torch` that the tests compare
it with.
"""

from __future__ import annotations

import os

import torch
import triton
from torch import Tensor

from torchmorph.idw.backends._protocol import power_code
from torchmorph.idw.backends.triton._jit import (
    _apply_dot_kernel,
    _apply_kernel,
    _dense_apply_kernel,
    _nearest_kernel,
    _position_grad_kernel,
    _transposed_dot_kernel,
    _transposed_kernel,
    _weights_kernel,
)

__all__ = [
    "apply",
    "apply_transposed",
    "dense_apply",
    "nearest_squared",
    "position_gradients",
    "tile_shapes",
    "weights",
]


# --------------------------------------------------------------------------- #
# launchers
# --------------------------------------------------------------------------- #
#: (BLOCK_rows, BLOCK_cols, num_warps) per kernel and dtype, from sweeps of
#: ``benchmarks/gpu_tiles.py`` on an H100; ``None`` is any dtype.
_TILES: dict[tuple[str, torch.dtype | None], tuple[int, int, int]] = {
    ("nearest", torch.float32): (16, 128, 4),
    ("nearest", torch.float64): (32, 64, 4),
    ("apply", torch.float32): (32, 64, 4),
    ("apply", torch.float64): (16, 128, 4),
    ("apply_dot", None): (32, 32, 4),
    ("transposed", None): (16, 128, 4),
    ("transposed_dot", torch.float32): (128, 32, 8),
    ("transposed_dot", torch.float64): (64, 32, 4),
    ("weights", None): (32, 256, 4),
    ("dense_apply", torch.float32): (8, 512, 8),
    ("dense_apply", torch.float64): (4, 512, 4),
    ("position_grad", None): (32, 64, 4),
}

#: Fused gradients to point positions: up to this many columns and three dimensions.
POSITION_GRAD_COLUMNS = 24

#: Tile shapes forced by the sweep script, by kernel name.
_OVERRIDE: dict[str, tuple[int, int, int]] = {}

#: Up to this many columns are accumulated one by one; more go through ``tl.dot``.
SMALL_COLUMNS = 3

#: The widest ``tl.dot`` launch, in padded columns (KP): a wider batch runs in groups of
#: columns, one launch each (the weights recomputed per group), so that the accumulator
#: and the operand tiles keep fitting in registers and shared memory. On an H100 at
#: case-B counts a batch of 1000 took 63 ms in groups of 64, 46 ms of 128, 77 ms of 256.
DOT_COLUMNS = 128


def tile_shapes(kernel: str, dtype: torch.dtype) -> tuple[int, int, int]:
    """(BLOCK_rows, BLOCK_cols, num_warps) for ``kernel`` at ``dtype``."""
    if kernel in _OVERRIDE:
        return _OVERRIDE[kernel]
    return _TILES.get((kernel, dtype), _TILES.get((kernel, None), (64, 64, 4)))


def _interpreted() -> bool:
    return os.environ.get("TRITON_INTERPRET", "0") not in ("", "0")


def _constants(dtype: torch.dtype, power: float, radius2: float):
    """(radius2, tiny, p/2, KIND, FAST) for a launch."""
    tiny = torch.finfo(dtype).tiny
    fast = 0 if _interpreted() else (1 if dtype == torch.float32 else 2)
    return max(float(radius2), tiny), tiny, float(power) / 2, power_code(power), fast


def _dot_operands(values: Tensor, ones_column: bool) -> tuple[Tensor, Tensor, int, bool]:
    """(hi, lo, KP, SPLIT): ``values`` (N, K) padded with zero columns to KP (a power of
    two >= 16, with room for a column of ones after the K columns when ``ones_column``:
    the row sums), contiguous, for a ``tl.dot`` kernel. float32 comes split as
    ``hi + lo`` with ``hi`` truncated to tf32, so that three tf32 products give float32
    accuracy on the matrix units (``_dot_accumulate`` of :mod:`._jit`); any other
    dtype as is (``lo`` is ``hi``)."""
    rows, columns = values.shape
    padded = max(16, triton.next_power_of_2(columns + int(ones_column)))
    full = values.new_zeros(rows, padded)
    full[:, :columns] = values
    if ones_column:
        full[:, columns] = 1.0
    if values.dtype != torch.float32:
        return full, full, padded, False
    hi = (full.view(torch.int32) & -8192).view(torch.float32)
    return hi, full - hi, padded, True


def _dot_groups(values: Tensor, ones_column: bool):
    """``(start, width, hi, lo, KP, SPLIT)`` for each launch of a ``tl.dot`` kernel: the
    columns of ``values`` in groups of at most :data:`DOT_COLUMNS` padded columns (one
    fewer values with the column of ones), each group as :func:`_dot_operands` gives it."""
    group = DOT_COLUMNS - int(ones_column)
    for start in range(0, values.shape[1], group):
        part = values[:, start : start + group]
        yield (start, part.shape[1], *_dot_operands(part, ones_column))


def nearest_squared(targets_t: Tensor, controls_t: Tensor) -> Tensor:
    """``max(min_k d²_ik, tiny)`` for each target, shape (N_t,)."""
    dim, n_t = targets_t.shape
    out = targets_t.new_empty(n_t)
    if n_t == 0:
        return out
    block_t, block_c, warps = tile_shapes("nearest", targets_t.dtype)
    _nearest_kernel[(triton.cdiv(n_t, block_t),)](
        targets_t,
        controls_t,
        out,
        n_t,
        controls_t.shape[1],
        torch.finfo(targets_t.dtype).tiny,
        D=dim,
        BLOCK_T=block_t,
        BLOCK_C=block_c,
        num_warps=warps,
    )
    return out


def apply(
    targets_t: Tensor,
    controls_t: Tensor,
    values: Tensor,
    power: float,
    radius2: float,
    nearest2: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """``W @ values`` with W never stored.

    Parameters
    ----------
    targets_t : Tensor, shape (D, N_t), contiguous, normalised coordinates
    controls_t : Tensor, shape (D, N_c), contiguous, normalised coordinates
    values : Tensor, shape (N_c, K), rows contiguous (K may be 0: row sums only)
    power, radius2 : the exponent p and the squared coincidence radius
    nearest2 : Tensor, shape (N_t,), optional
        :func:`nearest_squared` of the same geometry, when the caller has it.

    Returns
    -------
    (out (N_t, K), sums (N_t,)): the result and the row sums ``s_i`` for
    :func:`apply_transposed`.
    """
    dim, n_t = targets_t.shape
    n_c, columns = values.shape
    if nearest2 is None:
        nearest2 = nearest_squared(targets_t, controls_t)
    out = values.new_empty(n_t, columns)
    sums = values.new_empty(n_t)
    if n_t == 0:
        return out, sums
    radius2, tiny, half_power, kind, fast = _constants(values.dtype, power, radius2)
    if columns <= SMALL_COLUMNS:
        block_t, block_c, warps = tile_shapes("apply", values.dtype)
        _apply_kernel[(triton.cdiv(n_t, block_t),)](
            targets_t,
            controls_t,
            values,
            nearest2,
            out,
            sums,
            n_t,
            n_c,
            values.stride(0) if n_c else 0,
            out.stride(0) if columns else 0,
            radius2,
            tiny,
            half_power,
            D=dim,
            K=columns,
            KIND=kind,
            FAST=fast,
            BLOCK_T=block_t,
            BLOCK_C=block_c,
            num_warps=warps,
        )
    else:
        block_t, block_c, warps = tile_shapes("apply_dot", values.dtype)
        for start, width, v_hi, v_lo, padded, split in _dot_groups(values, ones_column=True):
            _apply_dot_kernel[(triton.cdiv(n_t, block_t),)](
                targets_t,
                controls_t,
                v_hi,
                v_lo,
                nearest2,
                out[:, start:],
                sums,
                n_t,
                n_c,
                out.stride(0),
                radius2,
                tiny,
                half_power,
                D=dim,
                K=width,
                KP=padded,
                KIND=kind,
                FAST=fast,
                SPLIT=split,
                BLOCK_T=block_t,
                BLOCK_C=block_c,
                num_warps=warps,
            )
    return out, sums


def apply_transposed(
    targets_t: Tensor,
    controls_t: Tensor,
    grad: Tensor,
    power: float,
    radius2: float,
    nearest2: Tensor,
    sums: Tensor,
) -> Tensor:
    """``Wᵀ @ grad`` for grad of shape (N_t, K), from the row statistics of :func:`apply`."""
    dim, n_c = controls_t.shape
    n_t, columns = grad.shape
    scaled = (grad / sums[:, None]).contiguous()
    out = grad.new_zeros(n_c, columns)
    if n_t == 0 or columns == 0:
        return out
    radius2, tiny, half_power, kind, fast = _constants(grad.dtype, power, radius2)
    if columns <= SMALL_COLUMNS:
        block_c, block_t, warps = tile_shapes("transposed", grad.dtype)
        _transposed_kernel[(triton.cdiv(n_c, block_c),)](
            controls_t,
            targets_t,
            nearest2,
            scaled,
            out,
            n_c,
            n_t,
            scaled.stride(0),
            out.stride(0),
            radius2,
            tiny,
            half_power,
            D=dim,
            K=columns,
            KIND=kind,
            FAST=fast,
            BLOCK_C=block_c,
            BLOCK_T=block_t,
            num_warps=warps,
        )
    else:
        block_c, block_t, warps = tile_shapes("transposed_dot", grad.dtype)
        for start, width, g_hi, g_lo, padded, split in _dot_groups(scaled, ones_column=False):
            _transposed_dot_kernel[(triton.cdiv(n_c, block_c),)](
                controls_t,
                targets_t,
                nearest2,
                g_hi,
                g_lo,
                out[:, start:],
                n_c,
                n_t,
                out.stride(0),
                radius2,
                tiny,
                half_power,
                D=dim,
                K=width,
                KP=padded,
                KIND=kind,
                FAST=fast,
                SPLIT=split,
                BLOCK_C=block_c,
                BLOCK_T=block_t,
                num_warps=warps,
            )
    return out


def weights(
    targets_t: Tensor, controls_t: Tensor, power: float, radius2: float, out: Tensor | None = None
) -> Tensor:
    """Dense W (N_t, N_c), rows summing to 1, written once (into ``out`` if given)."""
    dim, n_t = targets_t.shape
    n_c = controls_t.shape[1]
    dtype = controls_t.dtype
    if out is None:
        out = controls_t.new_empty(n_t, n_c)
    if n_t == 0:
        return out
    nearest2 = nearest_squared(targets_t, controls_t)
    _, sums = apply(targets_t, controls_t, controls_t.new_empty(n_c, 0), power, radius2, nearest2)
    radius2, tiny, half_power, kind, fast = _constants(dtype, power, radius2)
    block_t, block_c, warps = tile_shapes("weights", dtype)
    grid = (triton.cdiv(n_t, block_t), triton.cdiv(n_c, block_c))
    _weights_kernel[grid](
        targets_t,
        controls_t,
        nearest2,
        sums,
        out,
        n_t,
        n_c,
        out.stride(0),
        radius2,
        tiny,
        half_power,
        D=dim,
        KIND=kind,
        FAST=fast,
        BLOCK_T=block_t,
        BLOCK_C=block_c,
        num_warps=warps,
    )
    return out


def dense_apply(weights_matrix: Tensor, values: Tensor) -> Tensor:
    """``W @ values`` for a stored row-major W and at most three columns, reading W once."""
    n_t, n_c = weights_matrix.shape
    columns = values.shape[1]
    if not 1 <= columns <= SMALL_COLUMNS:
        raise ValueError(f"values: dense_apply takes 1 to {SMALL_COLUMNS} columns, got {columns}")
    out = values.new_empty(n_t, columns)
    if n_t == 0:
        return out
    block_t, block_c, warps = tile_shapes("dense_apply", values.dtype)
    _dense_apply_kernel[(triton.cdiv(n_t, block_t),)](
        weights_matrix,
        values,
        out,
        n_t,
        n_c,
        weights_matrix.stride(0),
        values.stride(0),
        out.stride(0),
        K=columns,
        BLOCK_T=block_t,
        BLOCK_C=block_c,
        num_warps=warps,
    )
    return out


def position_gradients(
    targets_t: Tensor,
    controls_t: Tensor,
    values: Tensor,
    grad: Tensor,
    out: Tensor,
    nearest2: Tensor,
    sums: Tensor,
    power: float,
    radius2: float,
    need_targets: bool = True,
    need_controls: bool = True,
) -> tuple[Tensor | None, Tensor | None]:
    """Gradients of ``L`` to the target and control coordinates, in the (D, N) layout,
    given ``grad = dL/d out`` for ``out = W @ values`` (from :func:`apply`).

    Coincident rows contribute nothing (their weights are locally constant). At most
    :data:`POSITION_GRAD_COLUMNS` columns and D <= 3.
    """
    dim, n_t = targets_t.shape
    n_c, columns = values.shape
    if dim > 3 or columns > POSITION_GRAD_COLUMNS:
        raise ValueError(
            f"position_gradients takes D <= 3 and at most {POSITION_GRAD_COLUMNS} "
            f"columns, got D = {dim}, {columns} columns"
        )
    scaled = (grad / sums[:, None]).contiguous()
    extra = (scaled * out).sum(1).contiguous()
    values = values.contiguous()
    radius2, tiny, half_power, kind, fast = _constants(values.dtype, power, radius2)
    block_r, block_c, warps = tile_shapes("position_grad", values.dtype)
    grad_targets = grad_controls = None
    if need_targets:
        grad_targets = torch.zeros_like(targets_t)
        if n_t:
            _position_grad_kernel[(triton.cdiv(n_t, block_r),)](
                targets_t,
                controls_t,
                scaled,
                values,
                extra,
                extra,
                nearest2,
                grad_targets,
                n_t,
                n_c,
                scaled.stride(0),
                values.stride(0),
                radius2,
                tiny,
                half_power,
                D=dim,
                K=columns,
                KIND=kind,
                FAST=fast,
                TARGET_ROWS=True,
                BLOCK_R=block_r,
                BLOCK_C=block_c,
                num_warps=warps,
            )
    if need_controls:
        grad_controls = torch.zeros_like(controls_t)
        if n_t:
            _position_grad_kernel[(triton.cdiv(n_c, block_r),)](
                controls_t,
                targets_t,
                values,
                scaled,
                extra,
                extra,
                nearest2,
                grad_controls,
                n_c,
                n_t,
                values.stride(0),
                scaled.stride(0),
                radius2,
                tiny,
                half_power,
                D=dim,
                K=columns,
                KIND=kind,
                FAST=fast,
                TARGET_ROWS=False,
                BLOCK_R=block_r,
                BLOCK_C=block_c,
                num_warps=warps,
            )
    return grad_targets, grad_controls
