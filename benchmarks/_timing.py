"""Timing helpers shared by the benchmark scripts (run as ``python benchmarks/X.py``, which
puts this folder on ``sys.path``: ``from _timing import median_time``). The measuring
itself is :mod:`torchmorph._timing`'s, shared with the demos and the reproduction."""

from __future__ import annotations

import statistics
from collections.abc import Callable

from torchmorph._timing import median_time, synchronise, wall_times

__all__ = ["median_and_min", "median_time", "seconds", "synchronise", "wall_times"]


def median_and_min(
    function: Callable[[], object], repeats: int, *, warmup: int = 1
) -> tuple[float, float]:
    """(median, minimum) wall time of ``repeats`` calls after ``warmup`` calls."""
    times = wall_times(function, repeats, warmup=warmup)
    return statistics.median(times), min(times)


def seconds(value: float) -> str:
    """A duration for a table: µs below a millisecond, ms below a second, else s."""
    if value < 1e-3:
        return f"{value * 1e6:,.1f} µs"
    return f"{value * 1e3:,.2f} ms" if value < 1 else f"{value:,.2f} s"
