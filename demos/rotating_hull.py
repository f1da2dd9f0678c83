"""Case C of the paper: fluid mesh motion around a rotating hull (Tables 3 and 6).

A Wigley hull (length 2.5 m) in a 50 × 25 × 10 m box is rotated by μ degrees about
the z axis through the hull's centre (μ* = -5°, D = [-36°, 0°]); the box is fixed.
Runs IDW, ESIDW, POD-IDW and POD-ESIDW (also with exactly 1 and 2 POD modes, as
the paper reports) and prints the tables beside the paper's::

    python demos/rotating_hull.py                  # paper-size mesh
    python demos/rotating_hull.py --size small     # seconds
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

    return case_main("hull", argv)


if __name__ == "__main__":
    main()
