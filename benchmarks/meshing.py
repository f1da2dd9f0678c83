"""Benchmark of graded CAD meshing: a swept, tapered wing like the ONERA M6 in a box.

The wing (1.196 m span, root chord 0.806 m, 30 degrees of sweep, NACA 0010 sections;
``tests/meshing/_wing.py``) is written to a STEP file in metres, as the M6's file is,
and meshed like ``torchmorph mesh m6.stp --box 1 --body-edge-length H`` (edge length
away from the wing: the default, the box's diagonal / 20) for each ``H``. Each size runs
in a fresh process, so that its peak memory (the process's maximum resident set,
Python, torch and gmsh included) is its own.

Printed (markdown): the sizes, the estimated and the real number of tetrahedra, the
seconds of ``mesh_cad`` and the peak memory.

Run ``python benchmarks/meshing.py`` (about 10 s on 2 cores); ``--sizes 0.05 0.02 0.01``,
``--algorithm 1`` for gmsh's Delaunay instead of HXT.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _one(path: str, body_size: float, algorithm: int) -> dict:
    """Mesh the wing once (in this process) and return the figures."""
    import io
    from contextlib import redirect_stderr

    from torchmorph.meshing import mesh_cad

    log = io.StringIO()
    start = time.perf_counter()
    with redirect_stderr(log):
        mesh = mesh_cad(path, box=1, body_mesh_size=body_size, algorithm=algorithm, progress=True)
    seconds = time.perf_counter() - start
    text = log.getvalue()
    estimate = re.search(r"estimate: about ([\d,]+) tetrahedra", text).group(1)
    size = re.search(r"gmsh: meshing \(size ([\d.e+-]+)", text).group(1)
    return {
        "body_size": body_size,
        "size": float(size),
        "estimate": int(estimate.replace(",", "")),
        "tets": mesh.num_tets,
        "nodes": mesh.num_nodes,
        "seconds": seconds,
        "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }


def _quietly(function) -> None:
    """Run ``function`` with the process's standard output (file descriptor 1) discarded."""
    sys.stdout.flush()
    saved, devnull = os.dup(1), os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)
    try:
        function()
    finally:
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=float, nargs="+", default=[0.05, 0.02])
    parser.add_argument("--algorithm", type=int, default=10, help="gmsh's Mesh.Algorithm3D")
    parser.add_argument("--one", nargs=2, metavar=("FILE", "SIZE"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        print(json.dumps(_one(args.one[0], float(args.one[1]), args.algorithm)))
        return
    sys.path.insert(0, str(ROOT / "tests" / "meshing"))
    from _wing import write_wing

    rows = []
    with tempfile.TemporaryDirectory() as directory:
        wing = Path(directory) / "m6.step"
        _quietly(lambda: write_wing(wing, metres=True))  # OpenCASCADE's writer talks on fd 1
        for body_size in args.sizes:
            command = [sys.executable, __file__, "--one", str(wing), str(body_size)]
            command += ["--algorithm", str(args.algorithm)]
            result = subprocess.run(command, capture_output=True, text=True, check=True)
            rows.append(json.loads(result.stdout.strip().splitlines()[-1]))
    print(
        f"Wing in a box (--box 1), gmsh Algorithm3D {args.algorithm}, one thread; "
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs\n"
    )
    columns = ("body edge length", "edge length", "estimated tets", "tetrahedra", "nodes")
    print("| " + " | ".join((*columns, "seconds", "peak memory")) + " |")
    print("|---|---|---|---|---|---|---|")
    for row in rows:
        print(
            f"| {row['body_size']:g} | {row['size']:.3g} | {row['estimate']:,} | {row['tets']:,} "
            f"| {row['nodes']:,} | {row['seconds']:.2f} | {row['peak_mb']:,.0f} MB |"
        )


if __name__ == "__main__":
    main()
