"""The ``torchmorph`` console command: :func:`main` and the parser in
:mod:`torchmorph.cli.main`, one module per subcommand (:mod:`~torchmorph.cli.info`,
:mod:`~torchmorph.cli.morph`, :mod:`~torchmorph.cli.mesh`,
:mod:`~torchmorph.cli.reproduce`), their shared pieces in ``_common``."""

from torchmorph.cli._common import (
    DISPLACEMENT_FORMATS,
    EXIT_ERROR,
    EXIT_INTERRUPTED,
    EXIT_INVERTED,
    EXIT_OK,
    EXIT_USAGE,
    CommandError,
)
from torchmorph.cli.main import build_parser, main

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
