"""Command-line plumbing and timing shared by the demo scripts (not part of the library)."""

from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
from typing import Any

import torch

from torchmorph._timing import median_time, synchronise
from torchmorph.paper import VARIANTS, CaseResult, get_case, reproduce

__all__ = ["case_main", "median_seconds", "set_threads", "synchronise"]


def set_threads(threads: int | None) -> None:
    """Use ``threads`` intra-op threads in torch (None: torch's default)."""
    if threads is not None:
        torch.set_num_threads(int(threads))


def median_seconds(
    function: Callable[[], Any], repeats: int, device: torch.device | None = None
) -> float:
    """Median wall time of ``repeats`` calls of ``function`` after one untimed call
    (:func:`torchmorph._timing.median_time`, the helper the benchmarks use too)."""
    return median_time(function, repeats, warmup=1, device=device)


def case_main(case: str, argv: Sequence[str] | None = None) -> CaseResult:
    """Parse the demo options and run :func:`torchmorph.paper.reproduce` for ``case``."""
    spec = get_case(case)
    parser = argparse.ArgumentParser(
        description=f"Reproduce case {spec.letter} of the paper: {spec.title} "
        f"(Tables {spec.mesh_table} and {spec.results_table}).",
    )
    parser.add_argument(
        "--size",
        choices=("small", "paper"),
        default="paper",
        help="mesh size: 'paper' (near the paper's node counts, default) or 'small' (seconds)",
    )
    parser.add_argument(
        "--out",
        default=f"out/{spec.key}",
        help="output directory for VTU meshes, the PNG and results.json "
        "(default: %(default)s); '' writes nothing",
    )
    parser.add_argument(
        "--mesher",
        choices=("gmsh", "pytetwild"),
        default="gmsh",
        help="mesh generator (default: %(default)s)",
    )
    parser.add_argument(
        "--seed",
        type=int,
        default=0,
        help="seed of the control-point selection and the POD training set",
    )
    parser.add_argument(
        "--repeats",
        type=int,
        default=5,
        help="timed repeats of each online morph (median; default %(default)s)",
    )
    parser.add_argument(
        "--online",
        choices=("projection", "paper"),
        default="projection",
        help="POD online coefficients: orthogonal projection (default) or the "
        "paper's eq. 16 (needs W's pseudo-inverse: slow offline)",
    )
    parser.add_argument(
        "--variant",
        choices=tuple(VARIANTS[spec.key]),
        default="paper",
        help="selection set-up: 'paper' (default, the one that reproduces the "
        "paper's figures) or a documented alternative "
        "(docs/results.md)",
    )
    parser.add_argument(
        "--threads", type=int, default=None, help="torch intra-op threads (default: torch's choice)"
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bars or tables")
    args = parser.parse_args(argv)
    set_threads(args.threads)
    return reproduce(
        spec.key,
        size=args.size,
        out=args.out or None,
        mesher=args.mesher,
        seed=args.seed,
        verbose=not args.quiet,
        repeats=args.repeats,
        online=args.online,
        variant=args.variant,
    )
