"""The lattice sum ``Σ_(i,j,k) B_i B_j B_k d_ijk`` at many points: the one operation an
FFD forward performs, blocked over the points so that memory stays bounded.

Two contraction orders, chosen by the number of value columns C (batch × D):

* ``dense`` (C > :data:`FACTORED_COLUMNS`): the tensor-product weights of a block of
  points, (rows, n_1 ⋯ n_D), times the displacements as (n_1 ⋯ n_D, C): one GEMM per
  block, efficient when C is large.
* ``factored`` (C ≤ :data:`FACTORED_COLUMNS`): sum factorisation, one axis at a time —
  a GEMM with the last axis's basis, then a per-point product with each other axis —
  which never forms the weights; for few columns it moves less memory than the GEMM
  with the weights, whose cost is then spent forming them.

Both have a transpose (``Wᵀ g``, the backward pass), and a custom autograd function
recomputes the blocks in the backward pass instead of keeping them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

__all__ = [
    "DEFAULT_BLOCK_BYTES",
    "DEFAULT_CUDA_BLOCK_BYTES",
    "FACTORED_COLUMNS",
    "lattice_sum",
    "tensor_product",
]

DEFAULT_BLOCK_BYTES = 4 * 2**20
"""Byte budget of one block of temporaries (weights or partial sums) on the CPU: a few
MiB, so that a block stays in cache between being formed and being used."""
DEFAULT_CUDA_BLOCK_BYTES = 256 * 2**20
"""The same budget on a CUDA device."""
FACTORED_COLUMNS = 12
"""Up to this many value columns (batch × D) the sum is factorised axis by axis; above,
blocks of tensor-product weights are multiplied by the displacements (measured on one
CPU thread, 10^3 lattice: the factorised sum 2–3× faster for one field in 3-D, the GEMM
about 2× faster for a batch of 16 fields, and even at 12 columns)."""


def tensor_product(bases: Sequence[Tensor]) -> Tensor:
    """Rows of the tensor-product basis: (M, n_1 ⋯ n_D), column (i, j, k) in C order
    holding ``bases[0][:, i] · bases[1][:, j] · bases[2][:, k]``."""
    weights = bases[0]
    for factor in bases[1:]:
        weights = (weights[:, :, None] * factor[:, None, :]).reshape(weights.shape[0], -1)
    return weights


def block_rows(bases: Sequence[Tensor], columns: int, block_bytes: int | None) -> int:
    """Points per block so that one block of temporaries fits ``block_bytes``."""
    if block_bytes is None:
        cuda = bases[0].device.type == "cuda"
        block_bytes = DEFAULT_CUDA_BLOCK_BYTES if cuda else DEFAULT_BLOCK_BYTES
    lattice = math.prod(factor.shape[1] for factor in bases)
    per_row = max(lattice, lattice // bases[-1].shape[1] * columns)
    return max(1, int(block_bytes) // (per_row * bases[0].element_size()))


def _reversed_layout(values: Tensor, sizes: Sequence[int]) -> Tensor:
    """(n_1 ⋯ n_D, C) in C order → (n_D, n_(D−1) ⋯ n_1 · C): the last axis first, the
    others reversed, so that each factored step contracts the leading axis."""
    dim, columns = len(sizes), values.shape[1]
    order = (*range(dim - 1, -1, -1), dim)
    return values.reshape(*sizes, columns).permute(order).reshape(sizes[-1], -1)


def _natural_layout(values: Tensor, sizes: Sequence[int], columns: int) -> Tensor:
    """The inverse of :func:`_reversed_layout`."""
    dim = len(sizes)
    order = (*range(dim - 1, -1, -1), dim)
    return values.reshape(*reversed(sizes), columns).permute(order).reshape(-1, columns)


def _factored_block(block: Sequence[Tensor], reversed_values: Tensor) -> Tensor:
    """W @ values for one block, one axis at a time: (rows, C)."""
    rows = block[0].shape[0]
    partial = block[-1] @ reversed_values  # (rows, n_(D−1) ⋯ n_1 · C)
    for factor in reversed(block[:-1]):
        partial = torch.bmm(factor[:, None, :], partial.view(rows, factor.shape[1], -1))
        partial = partial.view(rows, -1)
    return partial


def _factored_transpose_block(block: Sequence[Tensor], values: Tensor) -> Tensor:
    """Wᵀ @ values for one block in the reversed layout: (n_D, n_(D−1) ⋯ n_1 · C)."""
    rows = block[0].shape[0]
    spread = values
    for factor in block[:-1]:
        spread = (factor[:, :, None] * spread[:, None, :]).reshape(rows, -1)
    return block[-1].T @ spread


def _forward(bases: Sequence[Tensor], values: Tensor, rows: int, factored: bool) -> Tensor:
    """W @ values, W (M, L) the tensor product of ``bases``, block by block: (M, C)."""
    count = bases[0].shape[0]
    sizes = [factor.shape[1] for factor in bases]
    if factored:
        reversed_values = _reversed_layout(values, sizes)
    blocks = []
    for start in range(0, count, rows):
        block = [factor[start : start + rows] for factor in bases]
        if factored:
            blocks.append(_factored_block(block, reversed_values))
        else:
            blocks.append(tensor_product(block) @ values)
    return torch.cat(blocks) if blocks else values.new_zeros(0, values.shape[1])


def _transpose(bases: Sequence[Tensor], values: Tensor, rows: int, factored: bool) -> Tensor:
    """Wᵀ @ values, W formed (or factorised) block by block and never whole: (L, C)."""
    count, columns = bases[0].shape[0], values.shape[1]
    sizes = [factor.shape[1] for factor in bases]
    lattice = math.prod(sizes)
    if factored:
        total = values.new_zeros(sizes[-1], lattice // sizes[-1] * columns)
    else:
        total = values.new_zeros(lattice, columns)
    for start in range(0, count, rows):
        block = [factor[start : start + rows] for factor in bases]
        # out of place, so that vmap can batch the accumulation
        if factored:
            total = total + _factored_transpose_block(block, values[start : start + rows])
        else:
            total = torch.addmm(total, tensor_product(block).T, values[start : start + rows])
    return _natural_layout(total, sizes, columns) if factored else total


class _LatticeSum(torch.autograd.Function):
    """W @ values (or Wᵀ @ values) with W recomputed block by block in the backward pass,
    so that autograd keeps the per-axis bases, not the (M, L) matrix. Differentiable in
    ``values`` only (the bases are constants here), to any order: the backward of one
    is the other, and forward mode (``jvp``) is the sum itself. ``torch.func.vmap``
    batches it by running the forward batched."""

    generate_vmap_rule = True

    @staticmethod
    def forward(
        values: Tensor, rows: int, factored: bool, transpose: bool, *bases: Tensor
    ) -> Tensor:
        if transpose:
            return _transpose(bases, values, rows, factored)
        return _forward(bases, values, rows, factored)

    @staticmethod
    def setup_context(ctx, inputs, output) -> None:
        _, rows, factored, transpose, *bases = inputs
        ctx.rows, ctx.factored, ctx.transpose = rows, factored, transpose
        ctx.save_for_backward(*bases)
        ctx.save_for_forward(*bases)

    @staticmethod
    def backward(ctx, grad: Tensor):
        bases = ctx.saved_tensors
        values_grad = _LatticeSum.apply(grad, ctx.rows, ctx.factored, not ctx.transpose, *bases)
        return (values_grad, None, None, None, *([None] * len(bases)))

    @staticmethod
    def jvp(ctx, tangent: Tensor, *_) -> Tensor:
        # linear in the values: the tangent goes through the same sum
        return _LatticeSum.apply(tangent, ctx.rows, ctx.factored, ctx.transpose, *ctx.saved_tensors)


def lattice_sum(
    bases: Sequence[Tensor],
    displacements: Tensor,
    *,
    block_bytes: int | None = None,
    factored: bool | None = None,
) -> Tensor:
    """``Σ_ijk B_i B_j B_k d_ijk`` at every row of the bases.

    Parameters
    ----------
    bases : sequence of D Tensors, shapes (M, n_k)
        One basis matrix per axis (from :func:`~torchmorph.ffd.ffd_bases`).
    displacements : Tensor, shape (..., n_1, …, n_D, D)
        Control-point displacements, any number of leading batch dimensions.
    block_bytes : int, optional
        Byte budget of one block of temporaries (default :data:`DEFAULT_BLOCK_BYTES`,
        :data:`DEFAULT_CUDA_BLOCK_BYTES` on CUDA).
    factored : bool, optional
        Force the factorised (True) or the dense (False) contraction; default: factorised
        for at most :data:`FACTORED_COLUMNS` value columns (batch × D).

    Returns
    -------
    Tensor, shape (..., M, D)

    Notes
    -----
    O(M · n_1 ⋯ n_D · C) operations for C = batch × D value columns, in blocks of points;
    the (M, n_1 ⋯ n_D) weights are never formed whole. When no basis requires grad, the
    backward pass recomputes the blocks instead of keeping them, so memory stays at one
    block whatever M; bases that require grad (moved points) are differentiated through
    plain torch operations, which keep every block for the backward pass. The local
    support of B-splines is not exploited: a B-spline lattice costs what a Bernstein
    lattice of the same size does (gathering the (p + 1)^D control points of each point
    instead was measured 1.5–2× slower than these blocks on the CPU, 10^3 lattice).
    """
    dim = len(bases)
    lead = displacements.shape[: displacements.ndim - dim - 1]
    lattice = math.prod(factor.shape[1] for factor in bases)
    batch = math.prod(lead)
    columns = batch * dim
    values = displacements.reshape(batch, lattice, dim).permute(1, 0, 2).reshape(lattice, -1)
    if factored is None:
        factored = columns <= FACTORED_COLUMNS
    rows = block_rows(bases, columns if factored else 0, block_bytes)
    if torch.is_grad_enabled() and any(factor.requires_grad for factor in bases):
        result = _forward(bases, values, rows, factored)
    else:
        result = _LatticeSum.apply(values, rows, factored, False, *bases)
    count = bases[0].shape[0]
    return result.reshape(count, batch, dim).permute(1, 0, 2).reshape(*lead, count, dim)
