"""Case A of the paper: structural deformation of a NACA0012 wing (Tables 1 and 4).

The wing (chord 1.01 m, span 2π m) is bent by δy = μ z² on every boundary node
(the clamped root z = 0 stays put), μ* = 0.01, D = [0, 1.3]. Runs IDW, SIDW, ESIDW,
POD-IDW and POD-ESIDW and prints the tables beside the paper's::

    python demos/structural_wing.py                  # paper-size mesh
    python demos/structural_wing.py --size small     # seconds
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path

from torchmorph.paper import CaseResult


def main(argv: Sequence[str] | None = None) -> CaseResult:
    """Run the demo with command-line arguments ``argv`` (default ``sys.argv[1:]``)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from _common import case_main

    return case_main("wing", argv)


if __name__ == "__main__":
    main()
