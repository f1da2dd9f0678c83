"""Collectives and partitioned rows shared by the sharded modules of
:mod:`torchmorph.distributed`: rank/world queries, even row shards, replication with
summed gradients, gathering, and atomic partitioned files."""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import torch
import torch.distributed as dist
from torch import Tensor

from torchmorph._atomic import atomic_output

if TYPE_CHECKING:
    pass


# --------------------------------------------------------------------------- #
# process group helpers
# --------------------------------------------------------------------------- #
def _group_info(group) -> tuple[int, int]:
    """(rank, world size) in ``group``, with a clear error when there is no process group."""
    if not (dist.is_available() and dist.is_initialized()):
        raise RuntimeError(
            "torch.distributed is not initialized: call "
            "torch.distributed.init_process_group first (or launch with torchrun)"
        )
    return dist.get_rank(group), dist.get_world_size(group)


def _comm_device(group, like: Tensor) -> torch.device:
    """The device collectives run on: the current CUDA device for NCCL, else the CPU
    (gloo, whatever device ``like`` lives on)."""
    del like
    if dist.get_backend(group) == "nccl":
        return torch.device("cuda", torch.cuda.current_device())
    return torch.device("cpu")


def shard_rows(
    count: int, *, rank: int | None = None, world_size: int | None = None, group=None
) -> slice:
    """The contiguous slice of ``count`` rows that ``rank`` owns.

    Rows are split as evenly as possible: the first ``count % world_size`` ranks own
    one row more (``numpy.array_split``'s rule). Ranks past ``count`` own none.

    Parameters
    ----------
    count : int
        Number of rows to split (targets, or mesh nodes).
    rank, world_size : int, optional
        Default: this process's rank and the world size of ``group``.
    """
    if isinstance(count, bool) or not isinstance(count, int) or count < 0:
        raise ValueError(f"count must be a non-negative integer, got {count!r}")
    if rank is None or world_size is None:
        own_rank, own_world = _group_info(group)
        rank = own_rank if rank is None else rank
        world_size = own_world if world_size is None else world_size
    if not (0 <= rank < world_size):
        raise ValueError(f"rank must be in [0, {world_size}), got {rank}")
    base, extra = divmod(count, world_size)
    start = rank * base + min(rank, extra)
    return slice(start, start + base + (1 if rank < extra else 0))


class _Replicate(torch.autograd.Function):
    """Identity forward; backward all-reduces (sums) each gradient over the group."""

    @staticmethod
    def forward(ctx, group, *tensors):
        ctx.group = group
        return tuple(t.view_as(t) for t in tensors)

    @staticmethod
    def backward(ctx, *grads):
        reduced = []
        for grad in grads:  # one collective per input, in argument order on every rank
            grad = grad.contiguous().clone()
            device = _comm_device(ctx.group, grad)
            buffer = grad.to(device)
            dist.all_reduce(buffer, op=dist.ReduceOp.SUM, group=ctx.group)
            reduced.append(buffer.to(grad.device))
        return (None, *reduced)


def replicate(*tensors: Tensor | None, group=None) -> tuple[Tensor | None, ...]:
    """Mark tensors as replicated on every rank: identity forward, summed gradients.

    After ``backward``, the gradient of a replicated leaf is the sum over ranks of
    each rank's gradient: the gradient of the sum of the ranks' losses. All tensors
    go through one autograd node, so the gradients are reduced in one fixed order.

    Parameters
    ----------
    *tensors : Tensor or None
        The same values on every rank (``None`` entries are passed through).

    Returns
    -------
    tuple of Tensor or None
        The inputs (as views) in the same order.
    """
    _group_info(group)
    present = [t for t in tensors if t is not None]
    if not (torch.is_grad_enabled() and any(t.requires_grad for t in present)):
        return tensors
    outputs = iter(_Replicate.apply(group, *present))
    return tuple(None if t is None else next(outputs) for t in tensors)


def _attach(output: Tensor, *inputs: Tensor | None) -> Tensor:
    """``output``, connected to the inputs that require grad when it is not already
    (an empty slice): a rank with no rows must still take part in the backward
    all-reduce."""
    if not torch.is_grad_enabled() or output.requires_grad:
        return output
    linked = [t for t in inputs if t is not None and t.requires_grad]
    if not linked:
        return output
    zero = sum(t.sum() for t in linked) * 0
    return output + zero.to(output.dtype)


def _global_tolerance(controls: Tensor, targets: Tensor, tolerance: float, group) -> float:
    """The coincidence tolerance that gives this rank's IDW the radius of the single-
    process IDW over all ranks' targets.

    :class:`~torchmorph.idw.IDW` measures the coincidence radius as a fraction of the
    bounding-box diagonal of its controls and targets; a rank sees only its targets,
    so its fraction is rescaled by (global diagonal / local diagonal).
    """
    device = _comm_device(group, controls)
    with torch.no_grad():
        c = controls.detach().double()
        t = targets.detach().double()
        inf = torch.full((3,), torch.inf, dtype=torch.float64)
        low = t.amin(0).cpu() if t.shape[0] else inf.clone()
        high = t.amax(0).cpu() if t.shape[0] else -inf
        global_low, global_high = low.to(device), high.to(device)
        dist.all_reduce(global_low, op=dist.ReduceOp.MIN, group=group)
        dist.all_reduce(global_high, op=dist.ReduceOp.MAX, group=group)
        c_low, c_high = c.amin(0).cpu(), c.amax(0).cpu()
        local = torch.maximum(c_high, high) - torch.minimum(c_low, low)
        whole = torch.maximum(c_high, global_high.cpu()) - torch.minimum(c_low, global_low.cpu())
        local_diagonal = float(torch.linalg.vector_norm(local))
        global_diagonal = float(torch.linalg.vector_norm(whole))
    if local_diagonal == 0.0:
        return tolerance
    return tolerance * global_diagonal / local_diagonal


# --------------------------------------------------------------------------- #
# gathering and writing distributed fields
# --------------------------------------------------------------------------- #
def _as_rows(rows: Tensor | Sequence[int], name: str, count: int, num_rows: int) -> Tensor:
    rows = torch.as_tensor(rows).detach().cpu()
    if rows.ndim != 1 or rows.shape[0] != count or (rows.numel() and rows.is_floating_point()):
        raise ValueError(
            f"{name} must be a 1-D integer tensor of {count} global row ids, got "
            f"shape {tuple(rows.shape)} and dtype {rows.dtype}"
        )
    rows = rows.long()
    if rows.numel() and (int(rows.min()) < 0 or int(rows.max()) >= num_rows):
        raise ValueError(
            f"{name} must lie in [0, {num_rows}), got ids from {int(rows.min())} "
            f"to {int(rows.max())}"
        )
    return rows


def gather_rows(
    local: Tensor,
    rows: Tensor | Sequence[int],
    num_rows: int,
    *,
    dst: int | None = 0,
    group=None,
) -> Tensor | None:
    """Assemble a row-distributed field on one rank (or on all).

    Parameters
    ----------
    local : Tensor, shape (n_local, K) or (B, n_local, K)
        This rank's rows (e.g. the output of a sharded forward pass).
    rows : Tensor, shape (n_local,)
        Their global row ids (``morph.owned_nodes``, or ``morph.target_rows``).
    num_rows : int
        Rows of the full field; rows no rank provides are zero.
    dst : int or None
        The rank that receives the field; ``None``: every rank does.

    Returns
    -------
    Tensor, shape (num_rows, K) or (B, num_rows, K), on ``dst`` (every rank when
    ``dst`` is None); None on the other ranks. Not differentiable.
    """
    rank, world = _group_info(group)
    if not isinstance(local, Tensor) or local.ndim not in (2, 3):
        shape = tuple(local.shape) if isinstance(local, Tensor) else type(local).__name__
        raise ValueError(
            f"local must be a tensor of shape (n_local, K) or (B, n_local, K), got {shape}"
        )
    rows = _as_rows(rows, "rows", local.shape[-2], num_rows)
    device = _comm_device(group, local)
    with torch.no_grad():
        moved = local.detach().movedim(-2, 0)  # (n_local, [B,] K)
        counts = torch.tensor([moved.shape[0]], dtype=torch.int64, device=device)
        sizes = [torch.zeros_like(counts) for _ in range(world)]
        dist.all_gather(sizes, counts, group=group)
        sizes = [int(s) for s in sizes]
        longest = max(sizes)
        padded = moved.new_zeros(longest, *moved.shape[1:]).to(device)
        padded[: moved.shape[0]] = moved.to(device)
        padded_rows = torch.zeros(longest, dtype=torch.int64, device=device)
        padded_rows[: rows.shape[0]] = rows.to(device)
        if dst is None:
            values = [torch.empty_like(padded) for _ in range(world)]
            ids = [torch.empty_like(padded_rows) for _ in range(world)]
            dist.all_gather(values, padded, group=group)
            dist.all_gather(ids, padded_rows, group=group)
        else:
            receiving = rank == dst
            values = [torch.empty_like(padded) for _ in range(world)] if receiving else None
            ids = [torch.empty_like(padded_rows) for _ in range(world)] if receiving else None
            dist.gather(padded, values, dst=dst, group=group)
            dist.gather(padded_rows, ids, dst=dst, group=group)
            if not receiving:
                return None
        full = moved.new_zeros(num_rows, *moved.shape[1:])
        for size, value, index in zip(sizes, values, ids, strict=True):
            full[index[:size].to(full.device)] = value[:size].to(full.device)
    return full.movedim(0, -2)


_PART = re.compile(r"part-(\d{5})-of-(\d{5})\.pt$")


def save_partitioned(
    directory: str | os.PathLike,
    local: Tensor,
    rows: Tensor | Sequence[int],
    num_rows: int,
    *,
    group=None,
) -> Path:
    """Write each rank's rows of a field to its own file, atomically.

    Rank r writes ``directory/part-{r:05d}-of-{world:05d}.pt`` (a ``torch.save`` dict
    with ``rows``, ``values`` and ``num_rows``) through a temporary file renamed over
    the target, so a crash never leaves a half-written part; all ranks then wait for
    each other (a barrier). :func:`load_partitioned` reads the parts back.

    Returns
    -------
    Path
        This rank's file.
    """
    rank, world = _group_info(group)
    if not isinstance(local, Tensor) or local.ndim not in (2, 3):
        shape = tuple(local.shape) if isinstance(local, Tensor) else type(local).__name__
        raise ValueError(
            f"local must be a tensor of shape (n_local, K) or (B, n_local, K), got {shape}"
        )
    rows = _as_rows(rows, "rows", local.shape[-2], num_rows)
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"part-{rank:05d}-of-{world:05d}.pt"
    with atomic_output(path) as temporary:
        torch.save(
            {"rows": rows, "values": local.detach().cpu(), "num_rows": int(num_rows)}, temporary
        )
    dist.barrier(group=group)
    return path


def load_partitioned(directory: str | os.PathLike) -> Tensor:
    """The full field from the parts :func:`save_partitioned` wrote (any process).

    Raises
    ------
    FileNotFoundError
        If ``directory`` holds no parts.
    ValueError
        If parts are missing or come from runs with different world sizes or sizes.
    """
    directory = Path(directory)
    parts = (
        sorted(p for p in directory.iterdir() if _PART.search(p.name)) if directory.is_dir() else []
    )
    if not parts:
        raise FileNotFoundError(f"directory {str(directory)!r} holds no part-*-of-*.pt files")
    worlds = {int(_PART.search(p.name).group(2)) for p in parts}
    if len(worlds) != 1:
        raise ValueError(
            f"directory {str(directory)!r} mixes parts of runs with world sizes {sorted(worlds)}"
        )
    (world,) = worlds
    ranks = sorted(int(_PART.search(p.name).group(1)) for p in parts)
    if ranks != list(range(world)):
        missing = sorted(set(range(world)) - set(ranks))
        raise ValueError(
            f"directory {str(directory)!r}: parts of ranks {missing} are missing "
            f"(world size {world})"
        )
    pieces = [torch.load(p, weights_only=True) for p in parts]
    num_rows = {piece["num_rows"] for piece in pieces}
    if len(num_rows) != 1:
        raise ValueError(
            f"directory {str(directory)!r}: parts disagree on the number of rows "
            f"({sorted(num_rows)})"
        )
    first = pieces[0]["values"]
    full = first.new_zeros(*first.shape[:-2], num_rows.pop(), first.shape[-1])
    for piece in pieces:
        full.index_copy_(-2, piece["rows"], piece["values"])
    return full
