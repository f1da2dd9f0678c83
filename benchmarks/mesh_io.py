"""Reading a large hybrid mesh: ``read_mesh`` (meshio's read, every cell block kept, the
checks of the mesh model, the boundary) against meshio's read alone, on one thread.

The mesh: a box of ``n^3`` unit cubes, hexahedra in one half and each cube of the other
half cut into two wedges (a prism region sharing whole quads with the hexahedra), about
1.5 n^3 cells, written once as a binary Gmsh MSH 2.2 file into a temporary directory.
Target (the mesh issue): reading and boundary extraction of a 10^6-cell hybrid mesh
within 5x the time meshio alone takes.

    python benchmarks/mesh_io.py            # n = 88: 1.02e6 cells
    python benchmarks/mesh_io.py --n 40     # a quick run
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import meshio
import numpy as np
import torch

from torchmorph.mesh import read_mesh


def hybrid_box(n: int) -> meshio.Mesh:
    """Hexahedra for x < n/2, wedges for x > n/2, on an (n+1)^3 grid of points."""
    ticks = np.arange(n + 1, dtype=np.float64)
    grid = np.stack(np.meshgrid(ticks, ticks, ticks, indexing="ij"), -1).reshape(-1, 3)
    index = np.arange(grid.shape[0]).reshape(n + 1, n + 1, n + 1)
    i, j, k = (a.ravel() for a in np.meshgrid(*(np.arange(n),) * 3, indexing="ij"))
    corners = np.stack(
        [
            index[i, j, k],
            index[i + 1, j, k],
            index[i + 1, j + 1, k],
            index[i, j + 1, k],
            index[i, j, k + 1],
            index[i + 1, j, k + 1],
            index[i + 1, j + 1, k + 1],
            index[i, j + 1, k + 1],
        ],
        1,
    )
    left = i < n // 2
    right = corners[~left]
    wedges = np.concatenate([right[:, [0, 1, 2, 4, 5, 6]], right[:, [0, 2, 3, 4, 6, 7]]])
    return meshio.Mesh(grid, [("hexahedron", corners[left]), ("wedge", wedges)])


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=88, help="cubes per axis (default 88)")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    mesh = hybrid_box(args.n)
    cells = sum(len(block.data) for block in mesh.cells)
    with tempfile.TemporaryDirectory() as directory:
        path = Path(directory) / "hybrid.msh"
        meshio.write(path, mesh, file_format="gmsh22", binary=True)
        meshio_times, ours, boundary = [], [], []
        for _ in range(args.repeats):
            start = time.perf_counter()
            meshio.read(path)
            meshio_times.append(time.perf_counter() - start)
            start = time.perf_counter()
            ours_mesh = read_mesh(path)
            middle = time.perf_counter()
            nodes = ours_mesh.boundary_nodes
            end = time.perf_counter()
            ours.append(middle - start)
            boundary.append(end - middle)
    base, read, edge = (statistics.median(t) for t in (meshio_times, ours, boundary))
    print(f"hybrid mesh: {cells:,} cells ({ours_mesh.cell_counts}), {len(mesh.points):,} nodes")
    print(f"{'step':<36}{'median s':>10}{'x meshio':>10}")
    print(f"{'meshio.read':<36}{base:>10.3f}{1:>10.2f}")
    print(f"{'read_mesh (read, cells, checks)':<36}{read:>10.3f}{read / base:>10.2f}")
    print(f"{'boundary_nodes after read':<36}{edge:>10.3f}{edge / base:>10.2f}")
    print(f"{'read_mesh + boundary':<36}{read + edge:>10.3f}{(read + edge) / base:>10.2f}")
    print(f"({nodes.numel():,} boundary nodes; one thread; medians of {args.repeats} runs)")


if __name__ == "__main__":
    main()
