"""``torchmorph info MESH``: cells by kind, markers, bounding box and quality of a mesh file,
deck or OpenFOAM case."""

from __future__ import annotations

import argparse
import time

import numpy as np

from torchmorph.cli._common import (
    EXIT_OK,
    MESH_HELP,
    _line,
    _progress_option,
    _read,
    _seconds,
    _Stages,
)


def add_parser(commands, common: argparse.ArgumentParser) -> None:
    """Add the ``info`` subcommand to ``commands`` (the subparsers of ``torchmorph``)."""
    info = commands.add_parser(
        "info",
        parents=[common],
        help="describe a mesh file, deck or OpenFOAM case",
        description="Print the dimension, the node and cell counts by kind, boundary/interior "
        "node counts, the markers (node sets, face sets with their facet counts, groups) "
        "with their node counts, the bounding box, the quality (edge ratio Q, smallest "
        "scaled Jacobian, smallest volume) and the inverted cells of a mesh.",
    )
    info.add_argument("mesh", metavar="MESH", help=MESH_HELP)
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
            boundary = mesh.boundary_nodes.cpu().numpy()
            in_a_marker = np.zeros(mesh.num_nodes, dtype=bool)
            for name in mesh.markers:
                in_a_marker[mesh.node_set(name).cpu().numpy()] = True
            uncovered = int((~in_a_marker[boundary]).sum())
            box = mesh.points.min(0).values.tolist(), mesh.points.max(0).values.tolist()
    finally:
        stages.close()

    _line("mesh", f"{args.mesh} (read in {_seconds(read_time)})")
    _line("dimension", f"{mesh.dim}-D")
    _line(
        "nodes",
        f"{mesh.num_nodes} ({boundary.size} boundary, {mesh.interior_nodes.numel()} interior)",
    )
    _line("cells", f"{mesh.num_cells}")
    for kind, count in mesh.cell_counts.items():
        print(f"  {kind:<14}  {count}")
    facets = sum(int(block.nodes.shape[0]) for block in mesh.boundary_facets)
    _line("boundary facets", f"{facets}")
    _line("markers", f"{len(mesh.markers)}" if mesh.markers else "none")
    width = max((len(name) for name in mesh.markers), default=0)
    is_boundary = np.zeros(mesh.num_nodes, dtype=bool)
    is_boundary[boundary] = True
    for name in mesh.markers:
        nodes = mesh.node_set(name).cpu().numpy()
        on_boundary = int(is_boundary[nodes].sum())
        note = "" if on_boundary == nodes.size else f" ({on_boundary} on the boundary)"
        if name in mesh.face_sets:
            count = sum(int(b.nodes.shape[0]) for b in mesh.face_sets[name])
            kind = "face set"
            detail = f", {count} facets"
        elif name in mesh.groups:
            kind, detail = "group", f" of {', '.join(mesh.groups[name])}"
        else:
            kind, detail = "node set", ""
        print(f"  {name:<{width}}  {nodes.size} nodes{note} ({kind}{detail})")
    _line("", f"{uncovered} boundary node(s) in no marker")
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
    _line("min Jacobian", f"{summary['min_scaled_jacobian']:.4g} (scaled, 1 is best)")
    _line("min volume", f"{summary['min_volume']:.6g}")
    _line("inverted cells", f"{summary['num_inverted']}")
    for label, data in (("point data", point_data), ("cell data", cell_data)):
        if data:
            _line(
                label,
                ", ".join(f"{name} {tuple(value.shape)}" for name, value in sorted(data.items())),
            )
    return EXIT_OK
