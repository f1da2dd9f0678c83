"""How the ranks of a group agree before they work together.

Every sharded constructor, :meth:`~torchmorph.distributed.ShardedPOD.fit`,
:func:`~torchmorph.distributed.gather_rows` and
:func:`~torchmorph.distributed.save_partitioned` first run :meth:`Agreement.exchange`:
one all-reduce (the maximum of float64 entries, each sent with its negation, so that
every rank learns the largest and the smallest value of each) of

* a fingerprint of what must be the same on every rank: hyper-parameters (``power``,
  tolerances, ``num_modes``) and a record of each replicated tensor (its shape, dtype
  and two checksums of its bits), never the data itself;
* what each rank has of its own (its number of rows);
* the outcome of each rank's local checks (a NaN target on one rank only, a
  malformed ``target_rows``).

The exchange is the collective every rank reaches; after it either no rank raises or
every rank does: a rank whose own check failed raises its own error, the others a
``ValueError`` naming the argument and the rank; replicated data or hyper-parameters
that differ give the same ``ValueError`` on every rank, naming each argument that
differs. A rank never raises alone, so none is left waiting for another.
:func:`agree_on_rows` does the same for a partition of rows (an all-reduce of one
32-bit count per row) and for failures of local work done after the exchange.

Checksums are exact integer sums over the tensor's bits (16-bit words times
position-dependent weights, modulo 2**48): the same on every device and thread count.
Replicated tensors must therefore be equal bit for bit (-0.0 and 0.0 count as equal).
The checksums are not cryptographic: they catch any realistic difference (values
moved, reordered, missing or computed otherwise), not a deliberately crafted one.

What is not detected: the exchanged vector's length depends on the calls made, not on
the data, so ranks that run different code (a ShardedIDW on one rank and a
ShardedMeshMorph on another, in one ``ShardedPOD.fit``) send vectors of different
lengths, which gloo answers by aborting the processes.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

import torch
import torch.distributed as dist
from torch import Tensor

__all__ = ["Agreement", "agree_on_rows", "digest", "local_rows", "tensor_checksums"]

T = TypeVar("T")

_DTYPES = (
    torch.float32,
    torch.float64,
    torch.float16,
    torch.bfloat16,
    torch.complex64,
    torch.complex128,
    torch.int64,
    torch.int32,
    torch.int16,
    torch.int8,
    torch.uint8,
    torch.bool,
)
"""Dtypes a record names (code = position + 1; 0 for any other)."""

SHAPE_SLOTS = 4
"""Dimensions a tensor record holds (further ones are folded into the last)."""

CHECKSUM_BLOCK = 1 << 20
"""16-bit words per block: each block's weighted sums stay below 2**51, so float64
products and sums are exact integers in any order (BLAS, threads, devices)."""

_PRIMES = (65521, 65519)
_MULTIPLIERS = (40503, 52711)
_BLOCK_FACTORS = (1_000_003, 999_983)
_MODULUS = 1 << 48


def _group_info(group: Any) -> tuple[int, int]:
    """(rank, world size) in ``group``, with a clear error when there is no process group."""
    if not (dist.is_available() and dist.is_initialized()):
        raise RuntimeError(
            "torch.distributed is not initialized: call "
            "torch.distributed.init_process_group first (or launch with torchrun)"
        )
    return dist.get_rank(group), dist.get_world_size(group)


def _comm_device(group: Any, like: Tensor) -> torch.device:
    """The device collectives run on: the current CUDA device for NCCL, else the CPU
    (gloo, whatever device ``like`` lives on)."""
    del like
    if dist.get_backend(group) == "nccl":
        return torch.device("cuda", torch.cuda.current_device())
    return torch.device("cpu")


def tensor_checksums(value: Tensor) -> tuple[int, int]:
    """Two checksums of ``value``'s bits, each in [0, 2**48): sums of its 16-bit words
    (bytes for one-byte dtypes) times weights that depend on the word's position.

    The sums are exact integers (one float64 matrix-vector product per block of
    :data:`CHECKSUM_BLOCK` words, every partial sum an integer below 2**53), so the
    result is the same on any device and thread count; a value moved, swapped or
    changed in any bit changes both (barring a crafted collision). -0.0 counts as 0.0.
    """
    flat = value.detach().reshape(-1)
    if flat.is_floating_point() or flat.is_complex():
        flat = flat + 0  # -0.0 + 0 = +0.0
    flat = flat.contiguous()
    words = flat.view(torch.int16) if flat.element_size() >= 2 else flat.view(torch.uint8)
    length = min(words.numel(), CHECKSUM_BLOCK)
    position = torch.arange(length, dtype=torch.int64, device=words.device)
    weights = torch.stack(
        [
            (position * multiplier) % prime + 1
            for prime, multiplier in zip(_PRIMES, _MULTIPLIERS, strict=True)
        ],
        1,
    ).double()  # (length, 2), entries below 2**16
    sums = [
        words[start : start + length].double() @ weights[: min(length, words.numel() - start)]
        for start in range(0, words.numel(), length or 1)
    ]
    totals = [0, 0]
    for block, pair in enumerate(torch.stack(sums).tolist() if sums else []):
        for index, (factor, part) in enumerate(zip(_BLOCK_FACTORS, pair, strict=True)):
            totals[index] = (totals[index] + (block * factor + 1) * int(part)) % _MODULUS
    return totals[0], totals[1]


def digest(*tensors: Tensor | str) -> tuple[int, int]:
    """Checksums of several tensors (and strings) folded in order, each in [0, 2**48)."""
    folded = [len(tensors), len(tensors)]
    for item in tensors:
        if isinstance(item, str):
            parts: tuple[int, ...] = (zlib.crc32(item.encode()),) * 2
        else:
            shape = zlib.crc32(repr((tuple(item.shape), str(item.dtype))).encode())
            parts = tuple((value + shape) % _MODULUS for value in tensor_checksums(item))
        folded = [
            (1_000_003 * old + new) % _MODULUS for old, new in zip(folded, parts, strict=True)
        ]
    return folded[0], folded[1]


def _code(name: str) -> int:
    """A non-zero 31-bit code naming a check (it fits an int32 and a float64 exactly)."""
    return (zlib.crc32(name.encode()) & 0x7FFFFFFF) or 1


def _number(value: float) -> str:
    if value == -math.inf:
        return "None"
    if float(value).is_integer() and abs(value) < 2**53:
        return str(int(value))
    return repr(float(value))


class Agreement:
    """One rank's side of a check that the ranks of a group agree (see the module notes).

    Record what must agree with :meth:`same`, :meth:`same_tensor`, :meth:`same_digest`
    and :meth:`same_presence`, what each rank has with :meth:`per_rank`, run the
    rank's own checks through :meth:`attempt`, then call :meth:`exchange` on every
    rank, in the same order of calls (the entries must have the same layout on every
    rank; their values may differ).

    Parameters
    ----------
    group : ProcessGroup or None
        The ranks that must agree (None: the world).
    context : str
        What the ranks were about to do, for the messages (``"building a ShardedIDW"``).
    """

    def __init__(self, group: Any, context: str) -> None:
        self.group = group
        self.rank, self.world_size = _group_info(group)
        self.context = context
        self.error: Exception | None = None
        self._failed = 0
        self._names: dict[int, str] = {}
        self._entries: list[tuple[str, str, list[float]]] = []

    # ------------------------------------------------------------ local checks
    def attempt(self, name: str, check: Callable[..., T], *args: Any, **kwargs: Any) -> T | None:
        """``check(*args, **kwargs)``, or None when it raises (the error is kept and
        raised by :meth:`exchange`) or when an earlier check of this rank failed."""
        self._names[_code(name)] = name
        if self.error is not None:
            return None
        try:
            return check(*args, **kwargs)
        except Exception as error:  # noqa: BLE001  raised by exchange, on every rank
            self.fail(name, error)
            return None

    def fail(self, name: str, error: Exception) -> None:
        """Record that this rank's check of ``name`` failed with ``error``."""
        self._names[_code(name)] = name
        if self.error is None:
            self.error, self._failed = error, _code(name)

    # ------------------------------------------------------------ fingerprint
    def same(self, name: str, value: float | int | bool | None) -> None:
        """A number every rank must share (None is a value of its own)."""
        self._entries.append(("number", name, [-math.inf if value is None else float(value)]))

    def same_presence(self, name: str, present: bool) -> None:
        """An optional argument that every rank must give, or none."""
        self._entries.append(("presence", name, [float(bool(present))]))

    def same_tensor(self, name: str, value: Tensor | None, *, rows_dim: int | None = None) -> None:
        """A tensor every rank must hold bit for bit: its shape, dtype and checksums.
        With ``rows_dim``, only the shape (that dimension excepted) and the dtype must
        agree: a rank's own rows of a field."""
        if not isinstance(value, Tensor):
            self._entries.append(("tensor", name, [-math.inf] * (SHAPE_SLOTS + 4)))
            return
        shape = list(value.shape)
        if rows_dim is not None and shape:
            shape[rows_dim] = -1
        if len(shape) > SHAPE_SLOTS:
            shape = [*shape[: SHAPE_SLOTS - 1], math.prod(shape[SHAPE_SLOTS - 1 :])]
        shape = shape + [-2] * (SHAPE_SLOTS - len(shape))
        code = _DTYPES.index(value.dtype) + 1 if value.dtype in _DTYPES else 0
        sums = (0, 0) if rows_dim is not None else tensor_checksums(value)
        self._entries.append(("tensor", name, [value.ndim, *shape, code, *sums]))

    def same_digest(self, name: str, *parts: Tensor | str) -> None:
        """Several tensors (and strings) that every rank must hold alike, as one digest."""
        self._entries.append(("digest", name, [float(value) for value in digest(*parts)]))

    def per_rank(self, name: str, value: float | int) -> None:
        """A number of this rank's own; :meth:`exchange` returns every rank's."""
        slots = [-math.inf] * self.world_size
        slots[self.rank] = float(value)
        self._entries.append(("rank", name, slots))

    # ------------------------------------------------------------ the collective
    def exchange(self) -> dict[str, list[float]]:
        """The all-reduce (collective: every rank of the group calls it).

        Returns
        -------
        dict
            For each :meth:`per_rank` entry, its value on every rank, in rank order.

        Raises
        ------
        Exception
            On every rank when a rank's own check failed: that rank raises its own
            error, the others a ``ValueError`` naming the argument and the rank.
        ValueError
            On every rank when a fingerprint entry differs across ranks, naming each.
        """
        failures = [0.0] * self.world_size
        failures[self.rank] = float(self._failed)
        values = [value for _, _, entry in self._entries for value in entry] + failures
        vector = torch.tensor(values, dtype=torch.float64)
        both = torch.cat([vector, -vector]).to(_comm_device(self.group, vector))
        dist.all_reduce(both, op=dist.ReduceOp.MAX, group=self.group)
        both = both.cpu()
        size = vector.numel()
        high, low = both[:size].tolist(), (-both[size:]).tolist()

        codes = high[size - self.world_size :]
        failed = [rank for rank, code in enumerate(codes) if code > 0]
        if failed:
            if self.error is not None:
                raise self.error
            name = self._names.get(int(codes[failed[0]]), "a check")
            listed = ", ".join(map(str, failed[:4])) + (", ..." if len(failed) > 4 else "")
            where = f"rank {listed} (that rank" if len(failed) == 1 else f"ranks {listed} (each"
            raise ValueError(
                f"{name} failed its check on {where} raised the error that says why); "
                f"every rank stops {self.context}"
            )

        differences, shared, offset = [], {}, 0
        for kind, name, entry in self._entries:
            top, bottom = high[offset : offset + len(entry)], low[offset : offset + len(entry)]
            offset += len(entry)
            if kind == "rank":
                shared[name] = top
            elif top != bottom:
                differences.append(_difference(kind, name, bottom, top))
        if differences:
            raise ValueError("; ".join(differences) + f"; every rank stops {self.context}")
        return shared


def _difference(kind: str, name: str, low: list[float], high: list[float]) -> str:
    """What differs in one fingerprint entry, from its smallest and largest values."""
    if kind == "number":
        return f"{name} is {_number(low[0])} on some ranks and {_number(high[0])} on others"
    if kind == "presence":
        return f"{name} is given on some ranks and None on others"
    if kind == "digest":
        return f"{name} differs across ranks (it must be the same on every rank)"
    if low[0] == -math.inf or high[0] == -math.inf:
        return f"{name} is a tensor on some ranks only"
    if low[: SHAPE_SLOTS + 1] != high[: SHAPE_SLOTS + 1]:
        return f"{name} has shape {_shape(low)} on some ranks and {_shape(high)} on others"
    if low[SHAPE_SLOTS + 1] != high[SHAPE_SLOTS + 1]:
        return (
            f"{name} has dtype {_dtype(low[SHAPE_SLOTS + 1])} on some ranks and "
            f"{_dtype(high[SHAPE_SLOTS + 1])} on others"
        )
    return f"{name} holds other values on some ranks (replicated data must be equal bit for bit)"


def _shape(entry: list[float]) -> str:
    dims = ["n" if dim == -1 else str(int(dim)) for dim in entry[1 : 1 + SHAPE_SLOTS]]
    dims = dims[: min(int(entry[0]), SHAPE_SLOTS)]
    return "(" + ", ".join(dims) + ("," if len(dims) == 1 else "") + ")"


def _dtype(code: float) -> str:
    return str(_DTYPES[int(code) - 1]) if 1 <= code <= len(_DTYPES) else "another dtype"


def agree_on_rows(
    rows: Tensor | None,
    num_rows: int,
    *,
    name: str,
    what: str,
    group: Any,
    context: str,
    failure: tuple[str, Exception] | None = None,
    steps: Sequence[str] = (),
    verb: str = "provided",
) -> None:
    """Check, on every rank at once, that the ranks' ``rows`` partition ``num_rows`` rows
    and that no rank's local work failed (collective: one all-reduce of ``num_rows``
    + world-size 32-bit integers).

    Parameters
    ----------
    rows : Tensor, shape (n_local,), or None
        This rank's row ids, distinct, in [0, num_rows) (None: none, as on a rank
        whose work failed).
    num_rows : int
        The same on every rank; 0 exchanges only the failures.
    name, what, verb : str
        For the message: the argument, the rows and how a rank holds them
        (``"owned_nodes"``, ``"mesh nodes"``, ``"owned"``).
    failure : (step, exception), optional
        This rank's failed work: it raises ``exception``, the others a ``ValueError``
        naming the step (one of ``name`` and ``steps``) and the rank.

    Raises
    ------
    ValueError
        On every rank: ``"{name} must partition the {num_rows} {what} across the
        ranks: k are {verb} by no rank and j by several"``.
    """
    rank, world = _group_info(group)
    counts = torch.zeros(num_rows + world, dtype=torch.int32)
    if failure is not None:
        counts[num_rows + rank] = _code(failure[0])
    elif rows is not None and num_rows:
        counts.index_add_(0, rows.cpu(), torch.ones(rows.numel(), dtype=torch.int32))
    reduced = counts.to(_comm_device(group, counts))
    dist.all_reduce(reduced, group=group)
    reduced = reduced.cpu()
    failed = torch.nonzero(reduced[num_rows:]).flatten().tolist()
    if failed:
        if failure is not None:
            raise failure[1]
        code = int(reduced[num_rows + failed[0]])
        culprit = {_code(step): step for step in (name, *steps)}.get(code, "a step")
        raise ValueError(
            f"{culprit} failed on rank {failed[0]} (that rank raised the error that says "
            f"why); every rank stops {context}"
        )
    owners = reduced[:num_rows]
    orphans, shared = int((owners == 0).sum()), int((owners > 1).sum())
    if orphans or shared:
        raise ValueError(
            f"{name} must partition the {num_rows} {what} across the ranks: {orphans} "
            f"{'is' if orphans == 1 else 'are'} {verb} by no rank and {shared} by several"
        )


def local_rows(
    value: Tensor | Sequence[int], name: str, count: int | None, size: int | None
) -> Tensor:
    """``value`` as a 1-D int64 CPU tensor of ``count`` distinct row ids in [0, size)
    (``None``: any count, no upper bound)."""
    rows = torch.as_tensor(value).detach().cpu()
    if rows.ndim != 1 or (rows.numel() and (rows.is_floating_point() or rows.is_complex())):
        raise ValueError(
            f"{name} must be a 1-D integer tensor of row ids, got shape "
            f"{tuple(rows.shape)} and dtype {rows.dtype}"
        )
    if count is not None and rows.numel() != count:
        raise ValueError(
            f"{name} must hold {count} row ids (one per local row), got {rows.numel()}"
        )
    rows = rows.long()
    if rows.numel():
        low, high = int(rows.min()), int(rows.max())
        if low < 0 or (size is not None and high >= size):
            where = "be non-negative" if size is None else f"lie in [0, {size})"
            raise ValueError(f"{name} must {where}, got ids from {low} to {high}")
        repeated = rows.numel() - int(rows.unique().numel())
        if repeated:
            raise ValueError(f"{name} holds {repeated} repeated row id(s)")
    return rows
