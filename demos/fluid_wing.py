"""Case B of the paper: fluid mesh motion around a wing (Tables 2 and 5).

The wing of case A in a 10 × 5 × 4π m tunnel, its root on the wall z = 0; the
wing moves by δy = μ z² (μ* = 0.01, D = [0, 0.05]), the tunnel walls are fixed.
Runs IDW, ESIDW, POD-IDW and POD-ESIDW and prints the tables beside the paper's::

    python demos/fluid_wing.py                  # paper-size mesh (~34k nodes)
    python demos/fluid_wing.py --size small     # seconds
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

    return case_main("fluid-wing", argv)


if __name__ == "__main__":
    main()
