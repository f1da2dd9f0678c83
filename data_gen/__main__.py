"""Command line: build one of the paper's meshes, write it, print its figures.

python -m data_gen wing --size paper --mesher gmsh -o wing.vtu
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import os
import sys
import time
from pathlib import Path

from data_gen.cases import (
    CASES,
    MESHERS,
    PAPER_MESHES,
    SIZES,
    build_arrays,
    cache_path,
    canonical_case,
)

_ROWS = (
    ("tets", "tetrahedra"),
    ("nodes", "nodes"),
    ("interior", "interior nodes"),
    ("boundary", "boundary nodes"),
    ("max_q", "max Q (edge ratio)"),
    ("mean_q", "mean Q"),
)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m data_gen",
        description="Build a test mesh of the POD-Selective IDW paper (case A wing, B wing in a "
        "tunnel, C Wigley hull in a box), print its Table 1-3 figures beside the paper's and "
        "optionally write it (node sets as point data 'set:<name>').",
    )
    parser.add_argument("case", help=f"one of {', '.join(CASES)} (or A, B, C)")
    parser.add_argument(
        "--size", choices=SIZES, default="paper", help="mesh preset (default: paper)"
    )
    parser.add_argument("--mesher", choices=MESHERS, default="gmsh", help="mesher (default: gmsh)")
    parser.add_argument(
        "-o", "--output", type=Path, help="write the mesh here (.vtu, .vtk, .msh, .xdmf)"
    )
    parser.add_argument(
        "--mesh-scale", type=float, default=1.0, help="multiply every mesh size (default 1)"
    )
    parser.add_argument("--seed", type=int, default=1, help="gmsh's Mesh.RandomSeed (default 1)")
    parser.add_argument(
        "--cache-dir",
        type=Path,
        help="cache directory (default $TORCHMORPH_CACHE or ~/.cache/torchmorph/meshes)",
    )
    parser.add_argument(
        "--no-cache", action="store_true", help="mesh anew, write nothing to the cache"
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="print the mesher's log")
    return parser


def _format(value) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.2f}"
    return f"{value:,}"


def _write(path: Path, mesh) -> None:
    from torchmorph.mesh import TetMesh
    from torchmorph.mesh.io import write_mesh

    write_mesh(path, TetMesh(mesh.points, mesh.tets, mesh.node_sets))


class _ArgumentError(ValueError):
    """A bad command-line argument, reported as one line before any meshing."""


def _check_arguments(args: argparse.Namespace) -> str:
    """The canonical case name, after checking every argument that meshing would use.

    Raises ``_ArgumentError`` with a message that names the argument (and path).
    """
    try:
        case = canonical_case(args.case)
    except (TypeError, ValueError) as error:
        raise _ArgumentError(f"case: {error}") from None
    if not math.isfinite(args.mesh_scale) or args.mesh_scale <= 0:
        raise _ArgumentError(f"--mesh-scale must be a finite number > 0, got {args.mesh_scale!r}")
    if args.seed < 0:
        raise _ArgumentError(f"--seed must be >= 0, got {args.seed}")
    if args.output is not None:
        from torchmorph.mesh.io import MESH_FORMATS

        output = args.output
        if output.is_dir():
            raise _ArgumentError(f"--output: {str(output)!r} is a directory")
        if output.suffix.lower() not in MESH_FORMATS:
            raise _ArgumentError(
                f"--output: unsupported mesh file extension "
                f"{output.suffix or '(none)'!r} in {str(output)!r}; supported: "
                f"{', '.join(sorted(MESH_FORMATS))}"
            )
        parent = output.parent if str(output.parent) else Path(".")
        if not parent.is_dir():
            raise _ArgumentError(f"--output: directory {str(parent)!r} does not exist")
        if not os.access(parent, os.W_OK):
            raise _ArgumentError(f"--output: directory {str(parent)!r} is not writable")
        if MESH_FORMATS[output.suffix.lower()] == "xdmf":
            try:
                import h5py  # noqa: F401
            except ImportError:
                raise _ArgumentError(
                    f"--output: XDMF files ({str(output)!r}) need the h5py "
                    "package: pip install h5py"
                ) from None
    if args.cache_dir is not None and args.cache_dir.exists() and not args.cache_dir.is_dir():
        raise _ArgumentError(f"--cache-dir: {str(args.cache_dir)!r} is not a directory")
    module = {"gmsh": "gmsh", "pytetwild": "pytetwild"}[args.mesher]
    if importlib.util.find_spec(module) is None:
        raise _ArgumentError(
            f"--mesher {args.mesher}: the {module} package is not installed (pip install {module})"
        )
    return case


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        case = _check_arguments(args)
    except _ArgumentError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    try:
        return _run(case, args)
    except (OSError, RuntimeError, ValueError, ImportError) as error:
        print(f"error: {type(error).__name__}: {error}", file=sys.stderr)
        return 1


def _run(case: str, args: argparse.Namespace) -> int:
    cached = (
        not args.no_cache
        and cache_path(
            case,
            args.size,
            args.mesher,
            mesh_scale=args.mesh_scale,
            seed=args.seed,
            cache_dir=args.cache_dir,
        ).exists()
    )
    start = time.perf_counter()
    mesh = build_arrays(
        case,
        args.size,
        args.mesher,
        mesh_scale=args.mesh_scale,
        seed=args.seed,
        cache_dir=args.cache_dir,
        cache=not args.no_cache,
        verbose=args.verbose,
    )
    seconds = time.perf_counter() - start
    figures = mesh.info["figures"]
    paper = PAPER_MESHES[case]
    how = f"loaded from the cache in {seconds:.2f} s" if cached else f"built in {seconds:.2f} s"
    print(
        f"{case} ({args.size}, {args.mesher}): {how} "
        f"(meshing took {mesh.info['build_seconds']:.2f} s)"
    )
    print(f"  {'':22s}{'ours':>12s}{'paper':>12s}")
    for key, label in _ROWS:
        print(f"  {label:22s}{_format(figures[key]):>12s}{_format(paper[key]):>12s}")
    print(
        "  node sets: "
        + ", ".join(f"{name} ({len(nodes)})" for name, nodes in sorted(mesh.node_sets.items()))
    )
    if args.output is not None:
        _write(args.output, mesh)
        print(f"  wrote {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
