"""The ``torchmorph`` console command.

Subcommands
-----------
``torchmorph info MESH``
    Node, tetrahedron, boundary and interior counts, the node sets with their
    sizes, the bounding box, the quality ``Q`` (max/mean edge ratio) and the
    smallest tetrahedron volume of a mesh file.
``torchmorph morph MESH --displacement FILE [--moving SET ...] -o OUT``
    Morph a mesh (the paper's Algorithm 2, Section 2.2.1): prescribe the displacement of the
    boundary nodes, interpolate the interior by IDW from all boundary nodes
    (IDW), from a selection (``--select``/``--region``: SIDW) and from
    enrichment sets (``--enrich``: ESIDW), and write the result.
``torchmorph reproduce wing|fluid-wing|hull``
    Run one of the paper's test cases (:func:`torchmorph.paper.reproduce`).
``torchmorph mesh SURFACE [SURFACE ...] -o OUT``
    Tetrahedralise your own closed surfaces (STL, OBJ, PLY, OFF) with fTetWild,
    optionally in a box, with named boundary node sets
    (:func:`torchmorph.meshing.mesh_surfaces`).

Displacement files (``morph --displacement``)
---------------------------------------------
``.npy`` (``numpy.save``), ``.npz`` (the array named ``displacement``, or the
only array), ``.csv`` (comma-separated) or ``.txt``/``.dat`` (whitespace
separated, read by ``numpy.loadtxt``). Accepted shapes, with ``n_moving`` the
number of nodes in the union of the ``--moving`` sets, ``N_b`` the number of
boundary nodes and ``N`` the number of nodes:

- ``(n_moving, 3)``: one row per node of the moving sets, in the order of the
  sorted union of their node ids (ascending global node number);
- ``(N_b, 3)``: one row per boundary node, in the order of the mesh's sorted
  boundary node ids (``TetMesh.boundary_nodes``);
- ``(N, 3)``: a nodal field; its boundary rows are used, its interior rows are
  ignored (the interior is what IDW computes);
- ``(3,)``: one translation applied to every node of the moving sets;
- any of these with a leading batch axis ``(B, ..., 3)``: the field
  ``--batch-index i`` is used (default: the only one when ``B == 1``).

With ``--moving`` every boundary node outside the moving sets is fixed (zero
displacement), whatever the file holds for it (a warning says so when those
rows were not zero). Without ``--moving`` the file must give every boundary
node, as ``(N_b, 3)`` or ``(N, 3)``, and all its boundary rows are used.
When two layouts have the same number of rows they coincide (the moving nodes
are then all the boundary nodes, or every node is a boundary node), so a shape
is never ambiguous.

Output (``morph -o``)
---------------------
The *reference* mesh (``--write-deformed``: the deformed one) with its node sets
(point data ``set:<name>``), point data ``displacement`` (N, 3) — ParaView's
"Warp By Vector" on it shows the morph — and ``control_point`` (1 for the
control points of the IDW), and cell data ``quality`` (``Q`` after the morph),
``quality_reference`` (``Q`` before) and ``inverted`` (1 for a tetrahedron whose
signed volume is <= 0 after the morph). Formats: ``.vtu``, ``.vtk``,
``.xdmf``/``.xmf``, ``.msh``.

Exit codes
----------
0 success; 1 runtime error (missing or unreadable file, unknown node set, bad
displacement shape, invalid selection, missing optional dependency); 2 usage
error (argparse: unknown option, bad number, out-of-range ``R``/``a``/``b``);
3 the morph inverted tetrahedra and ``--strict`` was given (without
``--strict`` inverted tetrahedra only print a WARNING and the output is still
written); 130 interrupted. Error messages go to stderr, one line, without a
Python traceback (``--debug`` shows it).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from torchmorph import _cli_mesh
from torchmorph._cli_common import (
    DISPLACEMENT_FORMATS,
    EXIT_ERROR,
    EXIT_INTERRUPTED,
    EXIT_INVERTED,
    EXIT_OK,
    EXIT_USAGE,
    CommandError,
    _line,
    _positive_float,
    _progress_option,
    _read,
    _seconds,
    _Stages,
)
from torchmorph._cli_morph import _run_morph

if TYPE_CHECKING:
    pass

__all__ = [
    "DISPLACEMENT_FORMATS",
    "EXIT_ERROR",
    "EXIT_INTERRUPTED",
    "EXIT_INVERTED",
    "EXIT_OK",
    "EXIT_USAGE",
    "CommandError",
    "build_parser",
    "main",
]

#: Case names of ``reproduce`` (aliases: data_gen.cases.CASE_ALIASES, the one table).
_CASES = ("wing", "fluid-wing", "hull")

_MESH_EXTRA_HINT = "install the optional mesh dependencies: pip install 'torchmorph[mesh]'"


# --------------------------------------------------------------------------- parser


def _version() -> str:
    try:
        from importlib.metadata import PackageNotFoundError, version

        return version("torchmorph")
    except (ImportError, PackageNotFoundError):  # running from a source tree
        from torchmorph import __version__

        return __version__


def _selection_parameters(text: str) -> tuple[float, float, float]:
    """Parse ``R[,a[,b]]`` and validate it with :class:`~torchmorph.selection.Region`."""
    parts = [part.strip() for part in text.split(",")]
    if not 1 <= len(parts) <= 3 or not all(parts):
        raise argparse.ArgumentTypeError(
            f"expected R, R,a or R,a,b (radius and factors, e.g. 0.3,0.8,1.3), got {text!r}"
        )
    try:
        numbers = [float(part) for part in parts]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected numbers R[,a[,b]] (e.g. 0.3,0.8,1.3), got {text!r}"
        ) from None
    from torchmorph.selection import Region

    try:
        region = Region("region", *numbers)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None
    return region.parameters


def _region_option(text: str) -> tuple[tuple[str, ...], tuple[float, float, float]]:
    """Parse ``SET[+SET...]=R[,a[,b]]``."""
    names, equals, parameters = text.rpartition("=")
    names_list = tuple(name.strip() for name in names.split("+"))
    if not equals or not all(names_list):
        raise argparse.ArgumentTypeError(
            f"expected SET=R[,a,b] or SET1+SET2=R[,a,b] (e.g. top=0.5,0.8,1.3), got {text!r}"
        )
    return names_list, _selection_parameters(parameters)


def _case_name(text: str) -> str:
    from data_gen.cases import canonical_case

    try:
        return canonical_case(text).replace("_", "-")
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"unknown case {text!r}; choose from {', '.join(_CASES)} (or A, B, C)"
        ) from None


def _common_options() -> argparse.ArgumentParser:
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument(
        "--debug",
        action="store_true",
        help="show the Python traceback of an error instead of a one-line message",
    )
    return common


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``torchmorph`` command (info, morph, reproduce, mesh)."""
    common = _common_options()
    parser = argparse.ArgumentParser(
        prog="torchmorph",
        description="IDW / Selective IDW morphing of tetrahedral meshes (Ballarin, D'Amario, "
        "Perotto, Rozza 2017: A POD-Selective Inverse Distance Weighting method for "
        "fast parametrized shape morphing, Sections 2-3), tetrahedral meshes from "
        "your own surfaces, and the reproduction of the paper's test cases.",
        epilog="Run 'torchmorph COMMAND --help' for the options of a command. Exit codes: "
        "0 ok, 1 runtime error, 2 usage error, 3 inverted tetrahedra with --strict.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND")
    commands.required = True

    # ---------------------------------------------------------------- info
    info = commands.add_parser(
        "info",
        parents=[common],
        help="describe a tetrahedral mesh file",
        description="Print node and tetrahedron counts, boundary/interior node counts, the node "
        "sets and their sizes, the bounding box, the quality Q (edge ratio, max and "
        "mean) and the smallest tetrahedron volume of a mesh.",
    )
    info.add_argument("mesh", metavar="MESH", help="mesh file (.vtu, .vtk, .xdmf, .xmf, .msh)")
    _progress_option(info)
    info.set_defaults(run=_run_info, parser=info)

    # --------------------------------------------------------------- morph
    morph = commands.add_parser(
        "morph",
        parents=[common],
        help="morph a mesh from a boundary displacement",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Morph a tetrahedral mesh: boundary nodes take the prescribed displacement\n"
        "exactly, interior nodes are interpolated by IDW from the control points (all\n"
        "boundary nodes, or a selection: --select / --region, with --enrich).",
        epilog=_MORPH_EPILOG,
    )
    morph.add_argument("mesh", metavar="MESH", help="mesh file (.vtu, .vtk, .xdmf, .xmf, .msh)")
    morph.add_argument(
        "--moving",
        nargs="+",
        action="extend",
        metavar="SET",
        help="node sets that move (names separated by spaces or commas); every other boundary "
        "node is fixed. Without it the file must give every boundary node",
    )
    morph.add_argument(
        "--displacement",
        "-d",
        required=True,
        metavar="FILE",
        help="displacement file (.npy, .npz, .csv, .txt, .dat); accepted shapes below",
    )
    morph.add_argument(
        "--output",
        "-o",
        required=True,
        metavar="OUT",
        help="output mesh file (.vtu, .vtk, .xdmf, .xmf, .msh)",
    )
    selection = morph.add_argument_group(
        "control-point selection (default: every boundary node, plain IDW)"
    )
    exclusive = selection.add_mutually_exclusive_group()
    exclusive.add_argument(
        "--select",
        type=_selection_parameters,
        metavar="R[,a,b]",
        help="Selective IDW on all boundary nodes as one region: radius R > 0, "
        "0 < a < 1 (default 0.8), b > 1 (default 1.3)",
    )
    exclusive.add_argument(
        "--region",
        type=_region_option,
        action="append",
        metavar="SET=R[,a,b]",
        help="Selective IDW per node set (repeatable; SET1+SET2=R for a union); every boundary "
        "node must be in a region or an --enrich set unless --uncovered ignore",
    )
    selection.add_argument(
        "--enrich",
        nargs="+",
        action="extend",
        metavar="SET",
        help="node sets whose nodes are always control points (ESIDW); needs --select or --region",
    )
    selection.add_argument(
        "--strategy",
        choices=("random", "centroid", "farthest"),
        default="random",
        help="SelectControlPoint strategy (default: random, the paper's)",
    )
    selection.add_argument(
        "--overlap",
        choices=("error", "first", "share"),
        default="error",
        help="nodes in several --region sets with different parameters: error (default), give "
        "them to the first region, or let every region keep them",
    )
    selection.add_argument(
        "--uncovered",
        choices=("error", "ignore"),
        default="error",
        help="boundary nodes in no --region and no --enrich set: error (default), or never "
        "select them",
    )
    selection.add_argument(
        "--seed", type=int, default=0, help="seed of the random selection (default 0)"
    )
    idw = morph.add_argument_group("interpolation")
    idw.add_argument(
        "--power", type=_positive_float, default=4.0, help="IDW exponent p (default 4, the paper's)"
    )
    idw.add_argument(
        "--mode",
        choices=("auto", "dense", "matrix_free"),
        default="auto",
        help="store W (dense), recompute it in tiles (matrix_free), or choose by size (auto)",
    )
    idw.add_argument(
        "--batch-index",
        type=int,
        default=None,
        metavar="I",
        help="field to use from a batched file (B, ..., 3); negative counts from the end",
    )
    idw.add_argument("--device", default="cpu", help="torch device (default cpu), e.g. cuda")
    idw.add_argument(
        "--dtype",
        choices=("float64", "float32"),
        default="float64",
        help="floating-point precision (default float64)",
    )
    out = morph.add_argument_group("result")
    out.add_argument(
        "--write-deformed",
        action="store_true",
        help="write the deformed coordinates instead of the reference mesh",
    )
    out.add_argument(
        "--strict",
        action="store_true",
        help=f"exit with code {EXIT_INVERTED} when the morph inverts tetrahedra "
        "(the output is written all the same)",
    )
    _progress_option(out)
    morph.set_defaults(run=_run_morph, parser=morph)

    # ----------------------------------------------------------- reproduce
    reproduce = commands.add_parser(
        "reproduce",
        parents=[common],
        help="run one of the paper's test cases",
        description="Reproduce a test case of the POD-Selective IDW paper: build its mesh, run "
        "IDW, SIDW (wing), ESIDW, POD-IDW and POD-ESIDW with the paper's parameters "
        "and print the results beside the paper's (with progress bars). Needs the "
        "optional mesh dependencies: pip install 'torchmorph[mesh]' (gmsh; with "
        "--mesher pytetwild: 'torchmorph[tetwild]').",
    )
    reproduce.add_argument(
        "case", type=_case_name, metavar="CASE", help="wing (A), fluid-wing (B) or hull (C)"
    )
    reproduce.add_argument(
        "--size",
        choices=("small", "paper"),
        default="paper",
        help="mesh size: paper (node counts near the paper's, default) or small (a quick run)",
    )
    reproduce.add_argument(
        "--out",
        metavar="DIR",
        default=None,
        help="directory for the VTU and PNG files (default: none written)",
    )
    reproduce.add_argument(
        "--mesher",
        choices=("gmsh", "pytetwild"),
        default="gmsh",
        help="mesh generator (default gmsh)",
    )
    reproduce.add_argument(
        "--seed",
        type=int,
        default=0,
        help="seed of the random selection and training set (default 0)",
    )
    reproduce.set_defaults(run=_run_reproduce, parser=reproduce)

    _cli_mesh.add_parser(commands, common)
    return parser


_MORPH_EPILOG = """\
displacement file layouts (n_moving = nodes in the union of the --moving sets,
N_b = boundary nodes, N = all nodes):
  (n_moving, 3)  rows of the moving nodes, in ascending global node id
  (N_b, 3)       rows of the boundary nodes, in ascending global node id
  (N, 3)         a nodal field; its boundary rows are used
  (3,)           one translation of every moving node
  (B, ..., 3)    a batch of any of these; pick one with --batch-index
Boundary nodes outside the --moving sets are fixed (zero displacement).

output: the reference mesh with point data 'displacement' (use ParaView's
Warp By Vector) and 'control_point', cell data 'quality' (Q after the morph),
'quality_reference' and 'inverted'.

examples:
  torchmorph morph wing.vtu --moving tip -d tip.npy -o out.vtu
  torchmorph morph wing.vtu --moving upper lower -d d.npy --region root+tip=0.05 \\
      --region upper+lower=0.5 --overlap first --enrich leading_edge trailing_edge \\
      -o out.vtu
(regions that share nodes, here the profiles where root and tip meet the sides,
need --overlap first or --overlap share)
"""


# --------------------------------------------------------------------------- output


# --------------------------------------------------------------------------- commands


def _run_info(args: argparse.Namespace) -> int:
    from torchmorph.quality import quality_summary

    stages = _Stages(2, args.progress)
    try:
        with stages.step("reading mesh"):
            start = time.perf_counter()
            mesh, point_data, cell_data = _read(args.mesh)
            read_time = time.perf_counter() - start
        with stages.step("quality"):
            summary = quality_summary(mesh)
            boundary = mesh.boundary_nodes
            in_a_set = np.zeros(mesh.num_nodes, dtype=bool)
            for nodes in mesh.node_sets.values():
                in_a_set[nodes.cpu().numpy()] = True
            uncovered = int((~in_a_set[boundary.cpu().numpy()]).sum())
            box = mesh.points.min(0).values.tolist(), mesh.points.max(0).values.tolist()
    finally:
        stages.close()

    _line("mesh", f"{args.mesh} (read in {_seconds(read_time)})")
    _line(
        "nodes",
        f"{mesh.num_nodes} ({boundary.numel()} boundary, {mesh.interior_nodes.numel()} interior)",
    )
    _line("tetrahedra", f"{mesh.num_tets}")
    _line("boundary faces", f"{mesh.boundary_faces.shape[0]}")
    _line("node sets", f"{len(mesh.node_sets)}" if mesh.node_sets else "none")
    width = max((len(name) for name in mesh.node_sets), default=0)
    boundary_mask = np.zeros(mesh.num_nodes, dtype=bool)
    boundary_mask[boundary.cpu().numpy()] = True
    for name in sorted(mesh.node_sets):
        nodes = mesh.node_sets[name].cpu().numpy()
        on_boundary = int(boundary_mask[nodes].sum())
        note = "" if on_boundary == nodes.size else f" ({on_boundary} on the boundary)"
        print(f"  {name:<{width}}  {nodes.size} nodes{note}")
    _line("", f"{uncovered} boundary node(s) in no node set")
    low, high = box
    extent = [h - lo for lo, h in zip(low, high, strict=True)]
    _line(
        "bounding box",
        f"[{', '.join(f'{v:.6g}' for v in low)}] .. [{', '.join(f'{v:.6g}' for v in high)}]",
    )
    _line("extent", " x ".join(f"{v:.6g}" for v in extent))
    _line(
        "quality Q",
        f"max {summary['max_edge_ratio']:.4g}, mean {summary['mean_edge_ratio']:.4g}"
        " (edge ratio, 1 is best)",
    )
    _line("min volume", f"{summary['min_volume']:.6g}")
    for label, data in (("point data", point_data), ("cell data", cell_data)):
        if data:
            _line(
                label,
                ", ".join(f"{name} {tuple(value.shape)}" for name, value in sorted(data.items())),
            )
    return EXIT_OK


def _run_reproduce(args: argparse.Namespace) -> int:
    try:
        from torchmorph import paper
    except ModuleNotFoundError as error:
        if error.name == "torchmorph.paper":
            raise CommandError("torchmorph.paper is not part of this installation") from error
        raise
    if args.out is not None:
        Path(args.out).mkdir(parents=True, exist_ok=True)
    # verbose: progress bars, the tables beside the paper's values and the files written
    paper.reproduce(
        args.case, size=args.size, out=args.out, mesher=args.mesher, seed=args.seed, verbose=True
    )
    return EXIT_OK


# --------------------------------------------------------------------------- main


def _import_error_message(error: ImportError) -> str:
    message = str(error) or type(error).__name__
    if "torchmorph[" in message:  # names its extra already
        return message
    return f"{message}; {_MESH_EXTRA_HINT}"


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``torchmorph`` command.

    Parameters
    ----------
    argv : sequence of str, optional
        The arguments without the program name; default ``sys.argv[1:]``.

    Returns
    -------
    int
        The exit code: 0 ok, 1 runtime error, 2 usage error, 3 inverted
        tetrahedra with ``morph --strict``, 130 interrupted.
    """
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as done:  # --help, --version and usage errors
        return done.code if isinstance(done.code, int) else EXIT_USAGE
    prefix = f"torchmorph {args.command}: error:"
    try:
        return args.run(args)
    except SystemExit as done:  # parser.error() from a command's own checks
        return done.code if isinstance(done.code, int) else EXIT_USAGE
    except KeyboardInterrupt:
        print(f"torchmorph {args.command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception as error:  # reported as one line; --debug shows the traceback
        if args.debug:
            raise
        if isinstance(error, CommandError):
            print(f"{prefix} {error}", file=sys.stderr)
            return error.code
        if isinstance(error, ImportError):
            print(f"{prefix} {_import_error_message(error)}", file=sys.stderr)
        elif isinstance(error, (FileNotFoundError, ValueError, TypeError, OSError)):
            print(f"{prefix} {error}", file=sys.stderr)
        else:
            print(
                f"{prefix} {type(error).__name__}: {error} (run with --debug for the traceback)",
                file=sys.stderr,
            )
        return EXIT_ERROR


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
