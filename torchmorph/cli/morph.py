"""``torchmorph morph``: a mesh, a boundary displacement and a selection in, the morphed
mesh out (the paper's Algorithm 2); the command-line layer over :class:`MeshMorph`."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from torchmorph.cli._common import (
    EXIT_INVERTED,
    EXIT_OK,
    MESH_HELP,
    CommandError,
    _boundary_rows,
    _check_names,
    _line,
    _load_displacement,
    _positive_int,
    _progress_option,
    _read,
    _seconds,
    _Stages,
    _warn,
)
from torchmorph.cli._ffd import ffd_rows
from torchmorph.cli._methods import add_method_arguments, method_options, method_summary
from torchmorph.cli._selection import (
    _adaptive_plan,
    _selection_plan,
    _split_names,
    _uncovered_message,
    add_selection_arguments,
)

__all__: list[str] = []


def add_parser(commands, common: argparse.ArgumentParser) -> None:
    """Add the ``morph`` subcommand to ``commands`` (the subparsers of ``torchmorph``)."""
    morph = commands.add_parser(
        "morph",
        parents=[common],
        help="morph a mesh from a boundary displacement",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Morph a mesh: boundary nodes take the prescribed displacement\n"
        "exactly, interior nodes are interpolated by IDW (or, --method rbf, radial basis\n"
        "functions) from the control points (all boundary nodes, or a selection:\n"
        "--select / --region, with --enrich).",
        epilog=_MORPH_EPILOG,
    )
    morph.add_argument("mesh", metavar="MESH", help=MESH_HELP)
    morph.add_argument(
        "--moving",
        nargs="+",
        action="extend",
        metavar="SET",
        help="node sets that move (names separated by spaces or commas); every other boundary "
        "node is fixed. Without it the file must give every boundary node",
    )
    morph.add_argument(
        "--displacement",
        "-d",
        metavar="FILE",
        help="displacement file (.npy, .npz, .csv, .txt, .dat); accepted shapes below "
        "(this or --ffd)",
    )
    morph.add_argument(
        "--ffd",
        metavar="LATTICE",
        help="move the boundary by a free-form deformation lattice instead of -d: a .npz "
        "with origin (D,), lengths (D,), displacements (n_1, ..., n_D, D) and optionally "
        "basis, degree, rotation; nodes outside the box stay",
    )
    morph.add_argument(
        "--output",
        "-o",
        required=True,
        metavar="OUT",
        help="output: the source's format for a solver's own input (OpenFOAM case, "
        ".inp deck, .su2, Exodus .exo/.e), which comes back with only its coordinates "
        "moved; else a mesh file with the morph's fields (.vtu, .vtk, .xdmf, .msh, ...)",
    )
    add_selection_arguments(morph)
    add_method_arguments(morph)
    idw = morph.add_argument_group("morphing")
    idw.add_argument(
        "--rotations",
        action="store_true",
        help="rotation-aware IDW for bodies that turn far: each control carries the rotation "
        "of its neighbourhood on the boundary as well as its displacement",
    )
    idw.add_argument(
        "--steps",
        type=_positive_int,
        default=1,
        metavar="K",
        help="apply the displacement in K equal increments, each from the previous mesh "
        "(default 1); the first step that inverts a cell is reported",
    )
    idw.add_argument(
        "--batch-index",
        type=int,
        default=None,
        metavar="I",
        help="field to use from a batched file (B, ..., D); negative counts from the end",
    )
    idw.add_argument("--device", default="cpu", help="torch device (default cpu), e.g. cuda")
    idw.add_argument(
        "--dtype",
        choices=("float64", "float32"),
        default="float64",
        help="floating-point precision (default float64)",
    )
    out = morph.add_argument_group("result")
    out.add_argument(
        "--write-deformed",
        action="store_true",
        help="write the deformed coordinates instead of the reference mesh",
    )
    out.add_argument(
        "--strict",
        action="store_true",
        help=f"exit with code {EXIT_INVERTED} when the morph inverts cells "
        "(the output is written all the same)",
    )
    _progress_option(out)
    morph.set_defaults(run=run, parser=morph)


_MORPH_EPILOG = """\
displacement file layouts (D = the mesh's dimension, 2 or 3; n_moving = nodes
in the union of the --moving sets, N_b = boundary nodes, N = all nodes):
  (n_moving, D)  rows of the moving nodes, in ascending global node id
  (N_b, D)       rows of the boundary nodes, in ascending global node id
  (N, D)         a nodal field; its boundary rows are used
  (D,)           one translation of every moving node
  (B, ..., D)    a batch of any of these; pick one with --batch-index
Boundary nodes outside the --moving sets are fixed (zero displacement).

output: an OpenFOAM case, .inp deck, .su2 or Exodus (.exo, .e) file given as
input and as output comes back whole with only its coordinates moved (an
Exodus file's results, attributes and records too); any other output is the
reference mesh with point data 'displacement' (use ParaView's Warp By Vector)
and 'control_point', cell data 'quality' (Q after the morph),
'quality_reference' and 'inverted'.

examples:
  torchmorph morph wing.vtu --moving tip -d tip.npy -o out.vtu
  torchmorph morph wing.vtu --moving upper lower -d d.npy --region root+tip=0.05 \\
      --region upper+lower=0.5 --overlap first --enrich leading_edge trailing_edge \\
      -o out.vtu
(regions that share nodes, here the profiles where root and tip meet the sides,
need --overlap first or --overlap share)
  torchmorph morph wing.vtu --moving upper lower --ffd lattice.npz -o out.vtu
(the lattice moves the wing's surfaces inside its box, IDW the volume)
  torchmorph morph wing.vtu --moving tip -d tip.npy --select 0.05 --method rbf \\
      --kernel wendland_c2 --support-radius 2.0 -o out.vtu
(radial basis functions from the selected controls; a Wendland kernel's support
radius, in the mesh's units, should span the moving part and its surroundings)
"""


# --------------------------------------------------------------------------- commands


def run(args: argparse.Namespace) -> int:
    import torch

    from torchmorph.large_motions import morph_in_steps
    from torchmorph.mesh.io import FORMATS, format_of, write_mesh, write_morphed
    from torchmorph.mesh.quality import cell_edge_ratio, inverted, quality_summary
    from torchmorph.morph import MeshMorph
    from torchmorph.selection.plan import RegionOverlapError, UncoveredNodesError

    output = Path(args.output)
    source = Path(args.mesh)
    source_format = format_of(source) if source.exists() else None
    if source_format is FORMATS["openfoam"] and not output.suffix:
        output_format = source_format  # a new case directory
    else:
        try:
            output_format = format_of(output, "argument --output/-o")
        except ValueError as error:
            args.parser.error(str(error))
    # a solver's deck, case, SU2 or Exodus file comes back whole, moved; other formats get
    # the reference (or deformed) mesh with the displacement and quality fields
    solver_output = output_format is source_format and output_format.name in (
        "openfoam",
        "abaqus",
        "su2",
        "exodus",
        "cgns",
        "med",
    )
    if output_format.write is None and not solver_output:
        args.parser.error(
            f"argument --output/-o: a {output_format.name} output needs a {output_format.name} "
            "input (torchmorph writes those back moved, it does not write new ones)"
        )
    if (args.displacement is None) == (args.ffd is None):
        args.parser.error(
            "argument --displacement/-d: give a displacement file (-d) or an FFD lattice "
            "(--ffd), one of the two"
        )
    if args.ffd is not None and args.batch_index is not None:
        args.parser.error("argument --batch-index: picks a field of a -d file, not of --ffd")
    if args.max_controls is not None and args.adaptive is None:
        args.parser.error("argument --max-controls: needs --adaptive")
    if args.enrich and args.select is None and not args.region and args.adaptive is None:
        args.parser.error(
            "argument --enrich: needs --select, --region or --adaptive (without a selection "
            "every boundary node is a control point already)"
        )
    options = method_options(args)
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
            array = None if args.ffd else _load_displacement(args.displacement)
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
            _check_names(mesh, _split_names(args.enrich) or [], "--enrich")
        moving_label = ", ".join(moving) if moving else ""
        if array is None:  # --ffd
            rows, layout = ffd_rows(args.ffd, mesh.points.cpu().numpy(), boundary, moving_nodes)
            dropped = 0.0
        else:
            rows, layout, dropped = _boundary_rows(
                array,
                source=args.displacement,
                num_nodes=mesh.num_nodes,
                boundary_nodes=boundary,
                moving_nodes=moving_nodes,
                moving_label=moving_label,
                batch_index=args.batch_index,
                dim=mesh.dim,
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
        if args.adaptive is not None:
            plan, method = _adaptive_plan(args, plan, rows, mesh, method)
        if args.method == "rbf":  # the selection is the same, the interpolation RBF
            method = (
                "RBF: every boundary node is a control point"
                if plan is None
                else f"RBF on the controls of {method}"
            )
        generator = torch.Generator().manual_seed(args.seed)
        with stages.step("selecting controls, assembling W"):
            try:
                morph = MeshMorph(
                    selection_mesh, plan, mode=args.mode, generator=generator, **options
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
            except ValueError as error:
                if args.adaptive is None or "displacements" not in str(error):
                    raise
                raise CommandError(f"--adaptive: {error}") from error
        boundary_displacement = torch.as_tensor(rows, dtype=dtype, device=device)
        with stages.step("morphing"):
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            start = time.perf_counter()
            rotations = "fit" if args.rotations else None
            first_inverted = None
            with torch.no_grad():
                if args.steps > 1:
                    stepped = morph_in_steps(
                        morph, boundary_displacement, args.steps, rotations=rotations
                    )
                    field, first_inverted = stepped.displacement, stepped.first_inverted
                else:
                    field = morph(boundary_displacement, rotations=rotations)
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            morph_time = time.perf_counter() - start
        with stages.step("mesh quality"):
            before = quality_summary(mesh)
            after = quality_summary(mesh, field)
            quality_after = cell_edge_ratio(mesh, field)
            quality_before = cell_edge_ratio(mesh)
            flipped = inverted(mesh, field).to(torch.uint8)
        with stages.step("writing output"):
            if output.parent != Path(""):
                output.parent.mkdir(parents=True, exist_ok=True)
            if solver_output:
                moved = mesh_cpu.points + field.cpu().to(mesh_cpu.dtype)
                write_morphed(source, moved, output)
            else:
                control_flag = torch.zeros(mesh.num_nodes, dtype=torch.uint8)
                control_flag[morph.control_nodes.cpu()] = 1
                written = (
                    mesh_cpu.deformed(field.cpu().to(mesh_cpu.dtype))
                    if args.write_deformed
                    else mesh_cpu
                )
                cell_data = {
                    "quality": quality_after.cpu(),
                    "quality_reference": quality_before.cpu(),
                    "inverted": flipped.cpu(),
                }
                blocks = len(mesh.cells) + sum(len(b) for b in mesh.face_sets.values())
                if output_format.name == "gmsh" and blocks > 1:
                    cell_data = {}  # meshio reads no such MSH file back (see write_mesh)
                write_mesh(
                    output,
                    written,
                    point_data={"displacement": field.cpu(), "control_point": control_flag},
                    cell_data=cell_data,
                )
    finally:
        stages.close()

    num_inverted = int(after["num_inverted"])
    kinds = ", ".join(f"{count} {kind}" for kind, count in mesh.cell_counts.items())
    _line(
        "mesh",
        f"{args.mesh}: {mesh.dim}-D, {mesh.num_nodes} nodes, {kinds} "
        f"({morph.num_boundary} boundary, {morph.num_interior} interior nodes)",
    )
    if moving_nodes is not None:  # the --moving sets were given
        _line(
            "moving",
            f"{moving_label}: {moving_nodes.size} nodes; the other "
            f"{boundary.size - moving_nodes.size} boundary nodes are fixed",
        )
    else:
        _line(
            "moving",
            "every boundary node, as "
            + ("the lattice moves it" if args.ffd else "given in the file"),
        )
    _line(
        "displacement",
        f"{args.displacement or args.ffd}: {layout}; max |d| on the boundary "
        f"{float(np.abs(rows).max()) if rows.size else 0.0:.4g}",
    )
    _line("method", method)
    _line("interpolation", method_summary(morph))
    _line("controls", f"{morph.num_controls} of {morph.num_boundary} boundary nodes")
    result = getattr(plan, "result_", None)
    if result is not None and plan.method_ == "rbf":
        _line(
            "boundary error",
            f"{result.error:.4g}: max |s - d| / max |d| of the RBF at the boundary nodes "
            f"({result.reason}, {result.rounds} scorings)",
        )
    elif result is not None:
        _line(
            "nodal error",
            f"{result.error:.4g} against full IDW ({result.reason}, {result.rounds} scorings; "
            f"estimated on {plan.sampled_targets_} of {morph.num_interior} interior nodes)",
        )
    if result is not None and not result.converged:
        _warn(
            "morph",
            f"--adaptive {args.adaptive:g} not reached: the error is {result.error:.4g} "
            f"with {morph.num_controls} controls ({result.reason}); raise --max-controls",
        )
    _line("selection", _seconds(morph.selection_time))
    if morph.method == "idw":
        storage = {
            "matrix_free": "matrix-free: weights recomputed at every morph",
            "tree": "tree: far controls by clusters, tolerance "
            f"{getattr(morph.idw, 'tolerance', None)}",
        }.get(morph.idw.mode, "dense, stored")
        built = f"W {morph.num_interior} x {morph.num_controls}, {storage}"
    else:
        from torchmorph.rbf import SparseRBF

        mode = getattr(
            morph.rbf, "mode", "sparse" if isinstance(morph.rbf, SparseRBF) else "partition"
        )
        storage = {
            "matrix_free": "kernel evaluated at every morph",
            "partition": "partition of unity: a coarse global fit and local patches",
            "sparse": "sparse: kernel and evaluation matrices within the support radius",
        }.get(mode, f"evaluation matrix {morph.num_interior} rows, stored")
        if getattr(morph.rbf, "tolerance", None) is not None:
            storage += f", the global fit to {morph.rbf.tolerance:g} by iterations"
        built = f"system of {morph.num_controls} controls factorised, {storage}"
    _line("assembly", f"{_seconds(morph.assembly_time)} ({built}; {args.dtype} on {device})")
    how = ["rotation-aware"] if args.rotations else []
    if args.steps > 1:
        how.append(f"in {args.steps} steps")
    _line("morph", _seconds(morph_time) + (f" ({', '.join(how)})" if how else ""))
    if first_inverted is not None:
        step = round(first_inverted * args.steps)
        _warn(
            "morph",
            f"--steps {args.steps}: a cell first inverted at step {step} of {args.steps} "
            f"({100 * first_inverted:.0f} % of the displacement)",
        )
    _line(
        "quality Q",
        f"max {before['max_edge_ratio']:.4g} -> {after['max_edge_ratio']:.4g}, "
        f"mean {before['mean_edge_ratio']:.4g} -> {after['mean_edge_ratio']:.4g}",
    )
    _line("min vol. ratio", f"{after['min_volume_ratio']:.4g} (deformed / reference volume)")
    _line(
        "min Jacobian",
        f"{before['min_scaled_jacobian']:.4g} -> {after['min_scaled_jacobian']:.4g} (scaled)",
    )
    _line("inverted cells", f"{num_inverted} of {mesh.num_cells}")
    if solver_output:
        _line(
            "wrote", f"{output} (the morphed {output_format.name} input: coordinates changed only)"
        )
    else:
        cells_written = (
            "cell data quality, quality_reference, inverted"
            if cell_data
            else "no cell data: an MSH file of several cell blocks cannot hold it, write .vtu"
        )
        _line(
            "wrote",
            f"{output} ({'deformed' if args.write_deformed else 'reference'} mesh; point "
            f"data displacement, control_point; {cells_written})",
        )
    if num_inverted:
        _warn(
            "morph",
            f"the morph inverts {num_inverted} of {mesh.num_cells} cells (cell "
            "data 'inverted' marks them); try a smaller displacement, more control "
            "points (smaller R, --enrich) or "
            + ("a larger --power" if morph.method == "idw" else "--method idw"),
        )
        if args.strict:
            return EXIT_INVERTED
    return EXIT_OK
