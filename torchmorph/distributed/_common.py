"""Collectives and partitioned rows shared by the sharded modules of
:mod:`torchmorph.distributed`: even row shards, replication with summed gradients, the
global coincidence radius, gathering, and atomic partitioned files. Every collective
here first checks that the ranks agree (:mod:`torchmorph.distributed._agreement`)."""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any, overload

import torch
import torch.distributed as dist
from torch import Tensor

from torchmorph._atomic import atomic_output
from torchmorph.distributed._agreement import (
    Agreement,
    _comm_device,
    _group_info,
    agree_on_rows,
    digest,
    local_rows,
)

__all__ = ["gather_rows", "load_partitioned", "replicate", "save_partitioned", "shard_rows"]


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


@overload
def replicate(
    first: Tensor, second: Tensor | None, /, *, group: Any = None
) -> tuple[Tensor, Tensor | None]: ...
@overload
def replicate(*tensors: Tensor | None, group: Any = None) -> tuple[Tensor | None, ...]: ...
def replicate(*tensors: Tensor | None, group: Any = None) -> tuple[Tensor | None, ...]:
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
    total = linked[0].sum()
    for t in linked[1:]:
        total = total + t.sum()
    return output + (total * 0).to(output.dtype)


def _global_tolerance(controls: Tensor, targets: Tensor, tolerance: float, group: Any) -> float:
    """The coincidence tolerance that gives this rank's IDW the radius of the single-
    process IDW over all ranks' targets (collective: one all-reduce of 2·D numbers).

    :class:`~torchmorph.idw.IDW` measures the coincidence radius as a fraction of the
    bounding-box diagonal of its controls and targets; a rank sees only its targets,
    so its fraction is rescaled by (global diagonal / local diagonal).
    """
    device = _comm_device(group, controls)
    with torch.no_grad():
        c = controls.detach().double().cpu()
        t = targets.detach().double().cpu()
        dim = c.shape[1]
        inf = torch.full((dim,), torch.inf, dtype=torch.float64)
        low = t.amin(0) if t.shape[0] else inf.clone()
        high = t.amax(0) if t.shape[0] else -inf
        both = torch.cat([high, -low]).to(device)  # the largest of both: max and -min
        dist.all_reduce(both, op=dist.ReduceOp.MAX, group=group)
        both = both.cpu()
        global_high, global_low = both[:dim], -both[dim:]
        c_low, c_high = c.amin(0), c.amax(0)
        local = torch.maximum(c_high, high) - torch.minimum(c_low, low)
        whole = torch.maximum(c_high, global_high) - torch.minimum(c_low, global_low)
        local_diagonal = float(torch.linalg.vector_norm(local))
        global_diagonal = float(torch.linalg.vector_norm(whole))
    if local_diagonal == 0.0:
        return tolerance
    return tolerance * global_diagonal / local_diagonal


# --------------------------------------------------------------------------- #
# gathering and writing distributed fields
# --------------------------------------------------------------------------- #
def _check_count(value: Any, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ValueError(f"{name} must be a non-negative integer, got {value!r}")
    return value


def _check_field(local: Any) -> Tensor:
    if not isinstance(local, Tensor) or local.ndim not in (2, 3):
        shape = tuple(local.shape) if isinstance(local, Tensor) else type(local).__name__
        raise ValueError(
            f"local must be a tensor of shape (n_local, K) or (B, n_local, K), got {shape}"
        )
    return local


def _check_destination(dst: Any, world: int) -> None:
    if dst is not None and (
        isinstance(dst, bool) or not isinstance(dst, int) or not 0 <= dst < world
    ):
        raise ValueError(f"dst must be a rank in [0, {world}) or None, got {dst!r}")


def _distributed_field(
    agreement: Agreement, local: Any, rows: Any, num_rows: Any
) -> tuple[Tensor | None, Tensor | None]:
    """This rank's checks of a row-distributed field and its part of the fingerprint:
    ``num_rows`` and the shape of ``local`` but its rows, and its dtype, must agree."""
    count = agreement.attempt("num_rows", _check_count, num_rows, "num_rows")
    local = agreement.attempt("local", _check_field, local)
    rows = agreement.attempt(
        "rows", local_rows, rows, "rows", None if local is None else local.shape[-2], count
    )
    agreement.same("num_rows", count)
    agreement.same_tensor("local", local, rows_dim=-2)
    agreement.per_rank("rows", 0 if rows is None else rows.numel())
    return local, rows


def gather_rows(
    local: Tensor,
    rows: Tensor | Sequence[int],
    num_rows: int,
    *,
    dst: int | None = 0,
    group: Any = None,
) -> Tensor | None:
    """Assemble a row-distributed field on one rank (or on all).

    Parameters
    ----------
    local : Tensor, shape (n_local, K) or (B, n_local, K)
        This rank's rows (e.g. the output of a sharded forward pass).
    rows : Tensor, shape (n_local,)
        Their global row ids (``morph.owned_nodes``, or ``morph.target_rows``).
    num_rows : int
        Rows of the full field; together the ranks' ``rows`` must hold each exactly once.
    dst : int or None
        The rank that receives the field; ``None``: every rank does.

    Returns
    -------
    Tensor, shape (num_rows, K) or (B, num_rows, K), on ``dst`` (every rank when
    ``dst`` is None); None on the other ranks. Not differentiable.

    Raises
    ------
    ValueError
        On every rank, before any data moves: ``local`` or ``rows`` malformed on a
        rank (that rank's own message; the others name it), ``local`` of another
        width, batch size or dtype than on other ranks, ``num_rows`` or ``dst`` that
        differ across ranks, or rows that no rank or several ranks provide.

    Notes
    -----
    Communication: one all-reduce of a fingerprint (a few numbers per rank), one of
    ``num_rows`` 32-bit counts (the partition), then the gather of the data.
    """
    rank, world = _group_info(group)
    context = "gathering rows"
    agreement = Agreement(group, context)
    field, row_ids = _distributed_field(agreement, local, rows, num_rows)
    agreement.attempt("dst", _check_destination, dst, world)
    agreement.same("dst", dst)
    sizes = [int(size) for size in agreement.exchange()["rows"]]
    # exchange() raised on every rank if this rank's field failed its checks
    assert field is not None and row_ids is not None
    agree_on_rows(row_ids, num_rows, name="rows", what="rows", group=group, context=context)
    device = _comm_device(group, field)
    with torch.no_grad():
        moved = field.detach().movedim(-2, 0)  # (n_local, [B,] K)
        longest = max(sizes)
        padded = moved.new_zeros(longest, *moved.shape[1:]).to(device)
        padded[: moved.shape[0]] = moved.to(device)
        padded_rows = torch.zeros(longest, dtype=torch.int64, device=device)
        padded_rows[: row_ids.shape[0]] = row_ids.to(device)
        if dst is not None and rank != dst:  # a sender only
            dist.gather(padded, None, dst=dst, group=group)
            dist.gather(padded_rows, None, dst=dst, group=group)
            return None
        values = [torch.empty_like(padded) for _ in range(world)]
        ids = [torch.empty_like(padded_rows) for _ in range(world)]
        if dst is None:
            dist.all_gather(values, padded, group=group)
            dist.all_gather(ids, padded_rows, group=group)
        else:
            dist.gather(padded, values, dst=dst, group=group)
            dist.gather(padded_rows, ids, dst=dst, group=group)
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
    group: Any = None,
) -> Path:
    """Write each rank's rows of a field to its own file, atomically.

    Rank r writes ``directory/part-{r:05d}-of-{world:05d}.pt`` (a ``torch.save`` dict
    with ``rows``, ``values``, ``num_rows``, ``rank``, ``world_size`` and ``run``: the
    checksums of every rank's rows and values, the same in each part) through a
    temporary file renamed over the target, so a crash never leaves a half-written
    part. :func:`load_partitioned` reads the parts back and checks with ``run`` that
    they were written together.

    Returns
    -------
    Path
        This rank's file.

    Raises
    ------
    ValueError
        On every rank, before anything is written, as :func:`gather_rows`; on every
        rank after the writes when a rank could not write its part.
    """
    rank, world = _group_info(group)
    context = "saving partitioned rows"
    agreement = Agreement(group, context)
    field, row_ids = _distributed_field(agreement, local, rows, num_rows)
    sums = (0, 0) if field is None or row_ids is None else digest(row_ids, field)
    agreement.per_rank("first checksum", sums[0])
    agreement.per_rank("second checksum", sums[1])
    shared = agreement.exchange()
    # exchange() raised on every rank if this rank's field failed its checks
    assert field is not None and row_ids is not None
    agree_on_rows(row_ids, num_rows, name="rows", what="rows", group=group, context=context)
    run = [
        [int(first), int(second)]
        for first, second in zip(shared["first checksum"], shared["second checksum"], strict=True)
    ]
    path = Path(directory) / f"part-{rank:05d}-of-{world:05d}.pt"
    failure = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        part = {
            "rows": row_ids,
            "values": field.detach().cpu(),
            "num_rows": int(num_rows),
            "rank": rank,
            "world_size": world,
            "run": run,
        }
        with atomic_output(path) as temporary:
            torch.save(part, temporary)
    except Exception as error:  # noqa: BLE001  every rank hears of it (this replaces a barrier)
        failure = ("directory (writing the part)", error)
    agree_on_rows(None, 0, name="", what="", group=group, context=context, failure=failure)
    return path


def load_partitioned(directory: str | os.PathLike) -> Tensor:
    """The full field from the parts :func:`save_partitioned` wrote (any process).

    Returns
    -------
    Tensor, shape (num_rows, K) or (B, num_rows, K)

    Raises
    ------
    FileNotFoundError
        If ``directory`` holds no parts.
    ValueError
        If parts are missing, come from different runs (another world size or number
        of rows, or checksums that do not match the ``run`` every part records), hold
        values of different shapes or dtypes, or do not cover every row exactly once.
    """
    directory = Path(directory)
    where = f"directory {str(directory)!r}"
    parts: list[tuple[Path, re.Match[str]]] = []  # (file, its name's rank and world size)
    if directory.is_dir():
        for path in sorted(directory.iterdir()):
            match = _PART.search(path.name)
            if match:
                parts.append((path, match))
    if not parts:
        raise FileNotFoundError(f"{where} holds no part-*-of-*.pt files")
    worlds = {int(match.group(2)) for _, match in parts}
    if len(worlds) != 1:
        raise ValueError(f"{where} mixes parts of runs with world sizes {sorted(worlds)}")
    (world,) = worlds
    ranks = sorted(int(match.group(1)) for _, match in parts)
    if ranks != list(range(world)):
        missing = sorted(set(range(world)) - set(ranks))
        raise ValueError(f"{where}: parts of ranks {missing} are missing (world size {world})")
    pieces = [torch.load(path, weights_only=True) for path, _ in parts]
    num_rows = {piece["num_rows"] for piece in pieces}
    if len(num_rows) != 1:
        raise ValueError(f"{where}: parts disagree on the number of rows ({sorted(num_rows)})")
    (num_rows,) = num_rows
    _check_run(pieces, where)
    first = pieces[0]["values"]
    counts = torch.zeros(num_rows, dtype=torch.int64)
    for rank, piece in enumerate(pieces):
        values, rows = piece["values"], piece["rows"]
        if (
            not isinstance(values, Tensor)
            or values.ndim != first.ndim
            or values.shape[:-2] != first.shape[:-2]
            or values.shape[-1] != first.shape[-1]
            or values.dtype != first.dtype
        ):
            shape = tuple(values.shape) if isinstance(values, Tensor) else type(values).__name__
            raise ValueError(
                f"{where}: part {rank} holds values of shape {shape} and dtype "
                f"{getattr(values, 'dtype', None)}, part 0 of shape {tuple(first.shape)} and "
                f"dtype {first.dtype}: only the number of rows may differ"
            )
        rows = local_rows(rows, f"{where}: part {rank}'s rows", values.shape[-2], num_rows)
        counts.index_add_(0, rows, torch.ones_like(rows))
        piece["rows"] = rows
    orphans, shared = int((counts == 0).sum()), int((counts > 1).sum())
    if orphans or shared:
        raise ValueError(
            f"{where}: the parts must hold each of the {num_rows} rows exactly once: "
            f"{orphans} are in no part and {shared} in several"
        )
    full = first.new_zeros(*first.shape[:-2], num_rows, first.shape[-1])
    for piece in pieces:
        full.index_copy_(-2, piece["rows"], piece["values"])
    return full


def _check_run(pieces: list[dict], where: str) -> None:
    """Every part records the same ``run`` (parts of 0.1.0 record none: then all must
    lack it), and each part's rows and values match its own checksums there."""
    runs = [piece.get("run") for piece in pieces]
    for rank, run in enumerate(runs):
        if run != runs[0]:
            raise ValueError(
                f"{where}: parts 0 and {rank} were written by different runs of "
                "save_partitioned (each part records the checksums of every part of its run)"
            )
    if runs[0] is None:
        return
    for rank, piece in enumerate(pieces):
        if list(digest(piece["rows"], piece["values"])) != list(runs[0][rank]):
            raise ValueError(
                f"{where}: part {rank}'s rows or values do not match the checksums its run "
                "recorded (a part of another run with the same checksums list, or changed since)"
            )
