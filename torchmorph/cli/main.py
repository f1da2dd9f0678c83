"""The ``torchmorph`` console command.

Subcommands
-----------
``torchmorph info MESH``
    The dimension, node counts and cells by kind, the markers (node sets, face
    sets, groups) with their node counts, the bounding box, the quality (edge
    ratio ``Q``, smallest scaled Jacobian and volume) and the inverted cells of a
    mesh file, solver deck or OpenFOAM case.
``torchmorph morph MESH --displacement FILE [--moving SET ...] -o OUT``
    Morph a mesh (the paper's Algorithm 2, Section 2.2.1): prescribe the displacement of the
    boundary nodes, interpolate the interior by IDW from all boundary nodes
    (IDW), from a selection (``--select``/``--region``: SIDW) and from
    enrichment sets (``--enrich``: ESIDW), and write the result.
``torchmorph reproduce wing|fluid-wing|hull``
    Run one of the paper's test cases (:func:`torchmorph.paper.reproduce`).
``torchmorph mesh SURFACE [SURFACE ...] -o OUT``
    Tetrahedralise your own closed surfaces (STL, OBJ, PLY, OFF) with fTetWild or
    CAD files (STEP, IGES) with gmsh, optionally in a box, with named boundary node
    sets (:mod:`torchmorph.meshing`).

Displacement files (``morph --displacement``)
---------------------------------------------
``.npy`` (``numpy.save``), ``.npz`` (the array named ``displacement``, or the
only array), ``.csv`` (comma-separated) or ``.txt``/``.dat`` (whitespace
separated, read by ``numpy.loadtxt``). Accepted shapes, with ``D`` the mesh's
dimension (2 or 3), ``n_moving`` the number of nodes in the union of the
``--moving`` sets, ``N_b`` the number of boundary nodes and ``N`` the number of
nodes:

- ``(n_moving, D)``: one row per node of the moving sets, in the order of the
  sorted union of their node ids (ascending global node number);
- ``(N_b, D)``: one row per boundary node, in the order of the mesh's sorted
  boundary node ids (``Mesh.boundary_nodes``);
- ``(N, D)``: a nodal field; its boundary rows are used, its interior rows are
  ignored (the interior is what IDW computes);
- ``(D,)``: one translation applied to every node of the moving sets;
- any of these with a leading batch axis ``(B, ..., D)``: the field
  ``--batch-index i`` is used (default: the only one when ``B == 1``).

With ``--moving`` every boundary node outside the moving sets is fixed (zero
displacement), whatever the file holds for it (a warning says so when those
rows were not zero). Without ``--moving`` the file must give every boundary
node, as ``(N_b, D)`` or ``(N, D)``, and all its boundary rows are used.
When two layouts have the same number of rows they coincide (the moving nodes
are then all the boundary nodes, or every node is a boundary node), so a shape
is never ambiguous.

Output (``morph -o``)
---------------------
A solver's own input given in the same format (an OpenFOAM case directory, a
CalculiX/Abaqus deck, an SU2 file, an Exodus II file) comes back whole with only
its coordinates moved (:func:`torchmorph.mesh.io.write_morphed`). Any other output is the
*reference* mesh (``--write-deformed``: the deformed one) with its markers,
point data ``displacement`` (N, D) — ParaView's "Warp By Vector" on it shows the
morph — and ``control_point`` (1 for the control points of the IDW), and cell
data ``quality`` (``Q`` after the morph), ``quality_reference`` (``Q`` before)
and ``inverted`` (1 for a cell that the morph inverts), in any format
:func:`torchmorph.mesh.io.write_mesh` writes (``.vtu``, ``.vtk``, ``.xdmf``,
``.msh``, ...; a ``.msh`` file of several cell blocks gets no cell data).

Exit codes
----------
0 success; 1 runtime error (missing or unreadable file, unknown node set, bad
displacement shape, invalid selection, missing optional dependency); 2 usage
error (argparse: unknown option, bad number, out-of-range ``R``/``a``/``b``);
3 the morph inverted cells and ``--strict`` was given (without ``--strict``
inverted cells only print a WARNING and the output is still written); 130 interrupted. Error messages go to stderr, one line, without a
Python traceback (``--debug`` shows it).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from torchmorph.cli import info, mesh, morph, reproduce
from torchmorph.cli._common import EXIT_ERROR, EXIT_INTERRUPTED, EXIT_USAGE, CommandError

__all__ = ["build_parser", "main"]

_MESH_EXTRA_HINT = "install the optional mesh dependencies: pip install 'torchmorph[mesh]'"


# --------------------------------------------------------------------------- parser


def _version() -> str:
    try:
        from importlib.metadata import PackageNotFoundError, version

        return version("torchmorph")
    except (ImportError, PackageNotFoundError):  # running from a source tree
        from torchmorph import __version__

        return __version__


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
        description="IDW / Selective IDW morphing of volume meshes (Ballarin, D'Amario, "
        "Perotto, Rozza 2017: A POD-Selective Inverse Distance Weighting method for "
        "fast parametrized shape morphing, Sections 2-3), tetrahedral meshes from "
        "your own surfaces, and the reproduction of the paper's test cases.",
        epilog="Run 'torchmorph COMMAND --help' for the options of a command. Exit codes: "
        "0 ok, 1 runtime error, 2 usage error, 3 inverted cells with --strict.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND")
    commands.required = True

    for command in (info, morph, reproduce, mesh):
        command.add_parser(commands, common)
    return parser


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
        cells with ``morph --strict``, 130 interrupted.
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
