"""numba's thread count for one call of a parallel kernel.

Every numba kernel of the library with ``prange`` loops runs inside :func:`numba_threads`:
torch's thread count by default (what a user sets with ``torch.set_num_threads``), or
an explicit count, capped by numba's pool.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch

try:  # numba is optional
    import numba
except ImportError:  # pragma: no cover - exercised where numba is missing
    numba = None  # type: ignore[assignment]

__all__ = ["numba_threads"]


@contextlib.contextmanager
def numba_threads(count: int | None = None) -> Iterator[None]:
    """numba's thread count set to ``count`` (default ``torch.get_num_threads()``, capped
    by numba's pool) for one call, and its blocks asked to be handed out one at a time
    (``set_parallel_chunksize(1)``), so that a thread slowed by a competing process would
    take fewer blocks instead of holding up the others. Measured with numba 0.68 on its
    OpenMP and workqueue layers, the setting does not change how a ``prange`` loop is
    split: each thread gets a contiguous range (a loop of 1,000 light then 1,000 heavy
    iterations took 0.24 s on two threads with or without it, 0.27 s on one). A kernel
    whose iterations differ in cost orders them so that ranges balance (the RBF
    treecode's groups run in a shuffled order).

    torch's count is restored last: with numba's OpenMP layer both libraries share one
    OpenMP runtime, so restoring numba's count alone would also set torch's (a user's
    ``torch.set_num_threads(1)`` became 2 after the first kernel call)."""
    torch_threads = torch.get_num_threads()
    if numba is None:
        yield
        return
    wanted = torch_threads if count is None else count
    previous, previous_chunk = numba.get_num_threads(), numba.get_parallel_chunksize()
    numba.set_num_threads(max(1, min(wanted, numba.config.NUMBA_NUM_THREADS)))  # type: ignore[attr-defined]
    numba.set_parallel_chunksize(1)
    try:
        yield
    finally:
        numba.set_parallel_chunksize(previous_chunk)
        numba.set_num_threads(previous)
        if torch.get_num_threads() != torch_threads:
            torch.set_num_threads(torch_threads)
