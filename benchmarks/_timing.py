"""Timing helpers shared by the benchmark scripts (run as ``python benchmarks/X.py``, which
puts this folder on ``sys.path``: ``from _timing import median_time``)."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable

import torch

__all__ = ["median_and_min", "median_time", "seconds", "synchronise", "wall_times"]


def synchronise(device: torch.device | None) -> None:
    """Wait for the work queued on ``device`` when it is a CUDA device; nothing otherwise."""
    if device is not None and device.type == "cuda":
        torch.cuda.synchronize(device)


def wall_times(function: Callable[[], object], repeats: int, *, warmup: int = 1,
               device: torch.device | None = None) -> list[float]:
    """Wall times of ``repeats`` calls of ``function`` after ``warmup`` untimed calls.

    With a CUDA ``device``, the device is synchronised after the warm-up and after each
    timed call, so that a time covers the call's kernels.
    """
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


def median_time(function: Callable[[], object], repeats: int, *, warmup: int = 1,
                device: torch.device | None = None) -> float:
    """Median wall time of ``repeats`` calls after ``warmup`` calls (see :func:`wall_times`)."""
    return statistics.median(wall_times(function, repeats, warmup=warmup, device=device))


def median_and_min(function: Callable[[], object], repeats: int, *,
                   warmup: int = 1) -> tuple[float, float]:
    """(median, minimum) wall time of ``repeats`` calls after ``warmup`` calls."""
    times = wall_times(function, repeats, warmup=warmup)
    return statistics.median(times), min(times)


def seconds(value: float) -> str:
    """A duration for a table: µs below a millisecond, ms below a second, else s."""
    if value < 1e-3:
        return f"{value * 1e6:,.1f} µs"
    return f"{value * 1e3:,.2f} ms" if value < 1 else f"{value:,.2f} s"
