"""``torchmorph info MESH``: counts, node sets, bounding box and quality of a mesh file."""

from __future__ import annotations

import argparse
import time

import numpy as np

from torchmorph.cli._common import EXIT_OK, _line, _progress_option, _read, _seconds, _Stages


def add_parser(commands, common: argparse.ArgumentParser) -> None:
    """Add the ``info`` subcommand to ``commands`` (the subparsers of ``torchmorph``)."""
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
    info.set_defaults(run=run, parser=info)


def run(args: argparse.Namespace) -> int:
    from torchmorph.mesh.quality import quality_summary

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
