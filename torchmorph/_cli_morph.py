"""``torchmorph morph``: a mesh, a boundary displacement and a selection in, the morphed
mesh out (the paper's Algorithm 2); the command-line layer over :class:`MeshMorph`."""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from torchmorph._cli_common import (
    EXIT_INVERTED,
    EXIT_OK,
    CommandError,
    _boundary_rows,
    _check_names,
    _line,
    _load_displacement,
    _read,
    _seconds,
    _Stages,
    _warn,
)

if TYPE_CHECKING:
    from torchmorph.mesh import TetMesh
    from torchmorph.selection import UncoveredNodesError

__all__: list[str] = []

# Name of the temporary node set that holds every boundary node for --select.
_ALL_BOUNDARY = "(boundary)"


def _split_names(values: Sequence[str] | None) -> list[str] | None:
    """Names given as ``a b`` or ``a,b`` (or both), in order, without repeats."""
    if values is None:
        return None
    names: list[str] = []
    for value in values:
        for name in value.split(","):
            name = name.strip()
            if name and name not in names:
                names.append(name)
    return names


def _selection_plan(args: argparse.Namespace, mesh: TetMesh) -> tuple[Any, TetMesh, str]:
    """The SelectionPlan of the options (or None), the mesh to select on, and a description."""
    from torchmorph.mesh import TetMesh
    from torchmorph.selection import Region, SelectionPlan

    enrich = _split_names(args.enrich) or []
    if args.select is None and not args.region:
        return None, mesh, "IDW: every boundary node is a control point"
    method = "ESIDW" if enrich else "SIDW"
    if args.select is not None:
        radius, a, b = args.select
        sets = {**mesh.node_sets, _ALL_BOUNDARY: mesh.boundary_nodes}
        selection_mesh = TetMesh(mesh.points, mesh.tets, sets, name=mesh.name)
        regions = [Region(_ALL_BOUNDARY, radius, a, b)]
        text = f"all boundary nodes R={radius:g}, a={a:g}, b={b:g}"
    else:
        for names, _ in args.region:
            _check_names(mesh, names, "--region")
        selection_mesh = mesh
        regions = [Region(names, *parameters) for names, parameters in args.region]
        text = "; ".join(
            f"{region.label} R={region.radius:g}, a={region.a:g}, b={region.b:g}"
            for region in regions
        )
    if enrich:
        text += f"; enriched with {', '.join(enrich)}"
    plan = SelectionPlan(
        regions,
        enrich=enrich,
        strategy=args.strategy,
        overlap=args.overlap,
        uncovered=args.uncovered,
    )
    return plan, selection_mesh, f"{method} ({args.strategy}): {text}"


def _uncovered_message(mesh: TetMesh, error: UncoveredNodesError) -> str:
    """The library's uncovered-nodes error in command-line terms, with where the nodes lie."""
    missing = np.asarray(error.nodes)
    is_missing = np.zeros(mesh.num_nodes, dtype=bool)
    is_missing[missing] = True
    where = []
    in_some_set = np.zeros(mesh.num_nodes, dtype=bool)
    for name in sorted(mesh.node_sets):
        nodes = mesh.node_sets[name].cpu().numpy()
        in_some_set[nodes] = True
        count = int(is_missing[nodes].sum())
        if count:
            where.append(f"{count} in {name}")
    outside = int((is_missing & ~in_some_set).sum())
    if outside:
        where.append(f"{outside} in no node set")
    examples = ", ".join(str(int(node)) for node in missing[:5])
    return (
        f"{missing.size} of the {error.total} boundary nodes are in no --region and no "
        f"--enrich set ({'; '.join(where)}; e.g. node(s) {examples}); add their sets with "
        "--region SET=R or --enrich SET, or pass --uncovered ignore to never select them"
    )


# --------------------------------------------------------------------------- commands


def _run_morph(args: argparse.Namespace) -> int:
    import torch

    from torchmorph.io import MESH_FORMATS, write_mesh
    from torchmorph.morph import MeshMorph
    from torchmorph.quality import edge_ratio, quality_summary
    from torchmorph.selection import RegionOverlapError, UncoveredNodesError

    output = Path(args.output)
    if output.suffix.lower() not in MESH_FORMATS:
        args.parser.error(
            f"argument --output/-o: unsupported mesh file extension "
            f"{output.suffix or '(none)'!r}; supported: "
            f"{', '.join(sorted(MESH_FORMATS))}"
        )
    if args.enrich and args.select is None and not args.region:
        args.parser.error(
            "argument --enrich: needs --select or --region (without a selection "
            "every boundary node is a control point already)"
        )
    try:
        device = torch.device(args.device)
    except RuntimeError as error:
        args.parser.error(f"argument --device: {error}")
    if device.type == "cuda" and not torch.cuda.is_available():
        raise CommandError(
            f"--device {args.device}: CUDA is not available in this torch build or on this machine"
        )
    dtype = getattr(torch, args.dtype)
    moving = _split_names(args.moving)

    stages = _Stages(5, args.progress)
    try:
        with stages.step("reading mesh"):
            mesh, _, _ = _read(args.mesh)
            array = _load_displacement(args.displacement)
        mesh_cpu = mesh
        boundary = mesh.boundary_nodes.cpu().numpy()
        moving_nodes = None
        if moving is not None:
            _check_names(mesh, moving, "--moving")
            moving_nodes = mesh.nodes_of(moving).cpu().numpy()
            is_boundary = np.zeros(mesh.num_nodes, dtype=bool)
            is_boundary[boundary] = True
            for name in moving:
                nodes = mesh.node_set(name).cpu().numpy()
                inside = nodes[~is_boundary[nodes]]
                if inside.size:
                    raise CommandError(
                        f"--moving node set {name!r} holds {inside.size} interior node(s) (e.g. "
                        f"node {int(inside[0])}); only boundary nodes can be prescribed, the "
                        "interior is interpolated"
                    )
        if args.enrich:
            _check_names(mesh, _split_names(args.enrich), "--enrich")
        moving_label = ", ".join(moving) if moving else ""
        rows, layout, dropped = _boundary_rows(
            array,
            source=args.displacement,
            num_nodes=mesh.num_nodes,
            boundary_nodes=boundary,
            moving_nodes=moving_nodes,
            moving_label=moving_label,
            batch_index=args.batch_index,
        )
        if dropped > 0:
            _warn(
                "morph",
                f"the displacement file gives non-zero rows (max |value| {dropped:.3g}) "
                f"for boundary nodes outside the moving sets ({moving_label}); they "
                "are fixed (zero displacement)",
            )
        mesh = mesh.to(device=device, dtype=dtype)
        plan, selection_mesh, method = _selection_plan(args, mesh)
        generator = torch.Generator().manual_seed(args.seed)
        with stages.step("selecting controls, assembling W"):
            try:
                morph = MeshMorph(
                    selection_mesh, plan, power=args.power, mode=args.mode, generator=generator
                )
            except UncoveredNodesError as error:
                raise CommandError(_uncovered_message(mesh, error)) from error
            except RegionOverlapError as error:
                first, second = error.first, error.second
                raise CommandError(
                    f"--region {first.label}={first.radius:g},{first.a:g},{first.b:g} and "
                    f"--region {second.label}={second.radius:g},{second.a:g},{second.b:g} share "
                    f"{error.count} node(s) but have different parameters; pass --overlap first "
                    "(a shared node goes to the first region listing it) or --overlap share "
                    "(each region keeps all its nodes)"
                ) from error
        boundary_displacement = torch.as_tensor(rows, dtype=dtype, device=device)
        with stages.step("morphing"):
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            start = time.perf_counter()
            with torch.no_grad():
                field = morph(boundary_displacement)
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            morph_time = time.perf_counter() - start
        with stages.step("mesh quality"):
            before = quality_summary(mesh)
            after = quality_summary(mesh, field)
            deformed_points = mesh.points + field
            quality_after = edge_ratio(deformed_points, mesh.tets)
            quality_before = edge_ratio(mesh.points, mesh.tets)
            inverted = (mesh.deformed(field).volumes <= 0).to(torch.uint8)
        with stages.step("writing output"):
            control_flag = torch.zeros(mesh.num_nodes, dtype=torch.uint8)
            control_flag[morph.control_nodes.cpu()] = 1
            written = (
                mesh_cpu.deformed(field.cpu().to(mesh_cpu.dtype))
                if args.write_deformed
                else mesh_cpu
            )
            output.parent.mkdir(parents=True, exist_ok=True)
            write_mesh(
                output,
                written,
                point_data={"displacement": field.cpu(), "control_point": control_flag},
                cell_data={
                    "quality": quality_after.cpu(),
                    "quality_reference": quality_before.cpu(),
                    "inverted": inverted.cpu(),
                },
            )
    finally:
        stages.close()

    num_inverted = int(after["num_inverted"])
    _line(
        "mesh",
        f"{args.mesh}: {mesh.num_nodes} nodes, {mesh.num_tets} tets "
        f"({morph.num_boundary} boundary, {morph.num_interior} interior nodes)",
    )
    if moving is not None:
        _line(
            "moving",
            f"{moving_label}: {moving_nodes.size} nodes; the other "
            f"{boundary.size - moving_nodes.size} boundary nodes are fixed",
        )
    else:
        _line("moving", "every boundary node, as given in the file")
    _line(
        "displacement",
        f"{args.displacement}: {layout}; max |d| on the boundary "
        f"{float(np.abs(rows).max()) if rows.size else 0.0:.4g}",
    )
    _line("method", method)
    _line("controls", f"{morph.num_controls} of {morph.num_boundary} boundary nodes")
    _line("selection", _seconds(morph.selection_time))
    storage = (
        "matrix-free: weights recomputed at every morph"
        if morph.idw.mode == "matrix_free"
        else "dense, stored"
    )
    _line(
        "assembly",
        f"{_seconds(morph.assembly_time)} (W {morph.num_interior} x "
        f"{morph.num_controls}, {storage}; p={args.power:g}, "
        f"{args.dtype} on {device})",
    )
    _line("morph", _seconds(morph_time))
    _line(
        "quality Q",
        f"max {before['max_edge_ratio']:.4g} -> {after['max_edge_ratio']:.4g}, "
        f"mean {before['mean_edge_ratio']:.4g} -> {after['mean_edge_ratio']:.4g}",
    )
    _line("min vol. ratio", f"{after['min_volume_ratio']:.4g} (deformed / reference volume)")
    _line("inverted tets", f"{num_inverted} of {mesh.num_tets}")
    _line(
        "wrote",
        f"{output} ({'deformed' if args.write_deformed else 'reference'} mesh; point "
        "data displacement, control_point; cell data quality, quality_reference, "
        "inverted)",
    )
    if num_inverted:
        _warn(
            "morph",
            f"the morph inverts {num_inverted} of {mesh.num_tets} tetrahedra (cell "
            "data 'inverted' marks them); try a smaller displacement, more control "
            "points (smaller R, --enrich) or a larger --power",
        )
        if args.strict:
            return EXIT_INVERTED
    return EXIT_OK
