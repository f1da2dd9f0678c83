"""The one timing helper: median wall time of repeated calls after a warm-up.

Used by the benchmarks (``benchmarks/_timing.py`` re-exports it), the demos and the
reproduction of the paper's tables, so that every reported time is measured the same
way: ``warmup`` untimed calls, then ``repeats`` timed ones; on a CUDA device the
device is synchronised after the warm-up and after each timed call.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable

import torch

__all__ = ["median_time", "synchronise", "wall_times"]


def synchronise(device: torch.device | None) -> None:
    """Wait for the work queued on ``device`` when it is a CUDA device; nothing otherwise."""
    if device is not None and device.type == "cuda":
        torch.cuda.synchronize(device)


def wall_times(
    function: Callable[[], object],
    repeats: int,
    *,
    warmup: int = 1,
    device: torch.device | None = None,
) -> list[float]:
    """Wall times of ``repeats`` calls of ``function`` after ``warmup`` untimed calls."""
    if repeats < 1 or warmup < 0:
        raise ValueError(f"repeats must be >= 1 and warmup >= 0, got {repeats}, {warmup}")
    for _ in range(warmup):
        function()
    synchronise(device)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        synchronise(device)
        times.append(time.perf_counter() - start)
    return times


def median_time(
    function: Callable[[], object],
    repeats: int,
    *,
    warmup: int = 1,
    device: torch.device | None = None,
) -> float:
    """Median wall time of ``repeats`` calls after ``warmup`` calls (see :func:`wall_times`)."""
    return statistics.median(wall_times(function, repeats, warmup=warmup, device=device))
