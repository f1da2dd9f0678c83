"""``torchmorph reproduce CASE``: one of the paper's test cases
(:func:`torchmorph.paper.reproduce`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from torchmorph.cli._common import EXIT_OK, CommandError


def _case_name(text: str) -> str:
    """The reproduction's key of a case name or letter (:func:`torchmorph.paper.case_key`)."""
    try:
        from torchmorph.paper import case_key
    except ModuleNotFoundError as error:
        if error.name == "torchmorph.paper":
            return text  # run() says that the reproduction is not installed
        raise
    try:
        return case_key(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def add_parser(commands, common: argparse.ArgumentParser) -> None:
    """Add the ``reproduce`` subcommand to ``commands`` (the subparsers of ``torchmorph``)."""
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
    reproduce.set_defaults(run=run, parser=reproduce)


def run(args: argparse.Namespace) -> int:
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
