"""``torchmorph mesh``: tetrahedralise your own closed surfaces (see :mod:`torchmorph.meshing`)."""

from __future__ import annotations

import argparse
import re
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from torchmorph.cli._common import (
    EXIT_OK,
    CommandError,
    _float_list,
    _line,
    _positive_float,
    _positive_int,
    _seconds,
)
from torchmorph.meshing.estimate import MAX_ELEMENTS

if TYPE_CHECKING:
    from torchmorph.meshing.surfaces import Surface


def add_parser(commands, common: argparse.ArgumentParser) -> None:
    """Add the ``mesh`` subcommand to ``commands`` (the subparsers of ``torchmorph``)."""
    mesh = commands.add_parser(
        "mesh",
        parents=[common],
        help="tetrahedralise your own closed surface (STL, OBJ, PLY) or CAD solid (STEP, IGES, BREP)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Tetrahedralise the volume inside closed triangle surfaces (or around them, in\n"
        "a box) with fTetWild, snap the boundary nodes back onto the surfaces and\n"
        "name the boundary node sets: one per surface file (NAME=FILE names it), one\n"
        "per face group of a file (OBJ g/o groups, PLY face labels), the box walls\n"
        "wall_x0 ... wall_z1, and with --feature-angle the sharp edges\n"
        "(<surface>_edges) and the smooth patches between them (<surface>_patch<k>).\n"
        "The solids of CAD files (.step/.stp, .iges/.igs, .brep) are meshed with gmsh on\n"
        "the exact CAD geometry instead (no snapping; --edge-length, --body-edge-length\n"
        "and --grading are its sizes, the fTetWild options do not apply), with one node\n"
        "set per CAD face (<surface>_face<k>) and the nodes on the curves between faces\n"
        "(<surface>_edges). CAD and triangle files cannot be mixed in one call.\n"
        "Before meshing, the number of tetrahedra is estimated from the sizes and the\n"
        "geometry, and a mesh larger than --max-elements is refused with the size to\n"
        "raise; bodies that overlap or touch are refused. Prints the estimate, the steps\n"
        "and the elapsed time on stderr (--no-progress: silent) and the mesh's quality.\n"
        "Needs: pip install 'torchmorph[tetwild]' (triangle surfaces) or\n"
        "'torchmorph[mesh]' (CAD files).",
        epilog=_MESH_EPILOG,
    )
    mesh.add_argument(
        "surfaces",
        nargs="+",
        metavar="SURFACE",
        help="closed surface file (.stl, .obj, .ply, .off) or CAD file (.step, .stp, "
        ".iges, .igs, .brep), or NAME=FILE",
    )
    mesh.add_argument(
        "--output",
        "-o",
        required=True,
        metavar="OUT",
        help="output mesh file (.vtu, .vtk, .xdmf, .xmf, .msh)",
    )
    mesh.add_argument(
        "--repair",
        action="store_true",
        help="let trimesh remove zero-area faces, fix the winding and fill holes "
        "(default: a surface that is not closed is an error)",
    )
    far = mesh.add_argument_group("far field (default: mesh the inside of the surfaces)")
    place = far.add_mutually_exclusive_group()
    place.add_argument(
        "--box",
        type=_float_list(1, 6),
        metavar="PAD[,...]",
        help="place the surfaces in a box padded by PAD times their largest "
        "extent on every side, or per side X0,X1,Y0,Y1,Z0,Z1 (a tunnel)",
    )
    place.add_argument(
        "--bounds", type=_float_list(6), metavar="X0,Y0,Z0,X1,Y1,Z1", help="the box's corners"
    )
    sizing = mesh.add_argument_group("size and quality (fTetWild)")
    sizing.add_argument(
        "--edge-length",
        type=_positive_float,
        metavar="H",
        help="target edge length (default: the bounding-box diagonal / 20)",
    )
    sizing.add_argument(
        "--body-edge-length",
        type=_positive_float,
        metavar="H",
        help="edge length on the surfaces, growing to --edge-length away from "
        "them (needs --box or --bounds)",
    )
    sizing.add_argument(
        "--grading",
        type=_positive_float,
        metavar="D",
        help="distance over which the size grows from --body-edge-length to "
        "--edge-length (default: the surfaces' largest extent)",
    )
    sizing.add_argument(
        "--epsilon",
        type=_positive_float,
        default=1e-3,
        help="envelope: the mesh's surface stays within epsilon x the bounding-box "
        "diagonal of the input (default 1e-3; smaller is closer, slower)",
    )
    sizing.add_argument(
        "--stop-energy",
        type=_positive_float,
        default=10.0,
        help="stop optimising once the worst element's AMIPS energy is below "
        "this (default 10; 3 is a perfect tetrahedron; smaller is better, "
        "slower)",
    )
    sizing.add_argument(
        "--iterations",
        type=int,
        default=80,
        help="at most this many optimisation passes (default 80)",
    )
    sizing.add_argument(
        "--threads",
        type=_positive_int,
        default=1,
        help="fTetWild's threads, gmsh's for CAD files (default 1: reproducible)",
    )
    sizing.add_argument(
        "--max-elements",
        type=_max_elements,
        default=MAX_ELEMENTS,
        metavar="N",
        help="refuse to mesh when the estimated number of tetrahedra is above N "
        f"(default {MAX_ELEMENTS:,}; 'none': no limit)",
    )
    sets = mesh.add_argument_group("node sets")
    sets.add_argument(
        "--feature-angle",
        type=float,
        metavar="DEG",
        help="add sharp-edge and smooth-patch node sets: an edge is sharp where "
        "the surface turns by more than DEG degrees",
    )
    sets.add_argument(
        "--no-snap",
        dest="snap",
        action="store_false",
        help="leave the boundary nodes where fTetWild put them (within epsilon of the surface)",
    )
    mesh.add_argument(
        "--progress",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="print the estimate, the steps and the elapsed time on stderr (default: on)",
    )
    mesh.set_defaults(run=run, parser=mesh)


_MESH_EPILOG = """\
examples:
  torchmorph mesh body.stl --box 2 --feature-angle 30 -o body.vtu
  torchmorph mesh car=car.obj --box 1,2.5,1,1,0.1,1 --body-edge-length 0.08 \\
      --edge-length 0.6 --feature-angle 30 -o car.vtu
  torchmorph mesh part.step --box 1 --edge-length 0.8 --body-edge-length 0.3 -o part.vtu
  torchmorph morph body.vtu --moving body -d d.npy -o out.vtu
(the first: a body in a box padded by twice its size, node sets body, far_field,
wall_x0 ... wall_z1 and, if the body has sharp edges, body_edges, body_patch0 ...;
the second: a tunnel 1 length upstream, 2.5 downstream, 0.1 below the body, graded
from 0.08 on the car to 0.6; the third: a CAD part in a box, meshed with gmsh, node
sets part, far_field, the walls, part_face0 ... and part_edges; the fourth morphs
the first result by a displacement of the body, see 'torchmorph morph --help')
"""


def _max_elements(text: str) -> int | None:
    if text.strip().lower() == "none":
        return None
    try:
        number = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number or 'none', got {text!r}") from None
    if not (number >= 1 and number == int(number)):
        raise argparse.ArgumentTypeError(f"must be an integer >= 1 or 'none', got {text!r}")
    return int(number)


#: The library's argument names in messages, as this command's options.
_OPTIONS = {
    "body_edge_length": "--body-edge-length",
    "edge_length": "--edge-length",
    "grading": "--grading",
    "max_elements": "--max-elements",
    "threads": "--threads",
    "bounds": "--bounds",
}


def _message(error: Exception) -> str:
    """A library error in the command's terms: options for argument names, no prefix."""
    text = str(error).removeprefix("files: ").removeprefix("surfaces: ")
    text = re.sub(r"\b(" + "|".join(_OPTIONS) + r")\b", lambda m: _OPTIONS[m.group(1)], text)
    return text.replace("(None: no limit)", "('none': no limit)")


def _surface_argument(text: str) -> tuple[str | None, str]:
    """``NAME=FILE`` or ``FILE``."""
    name, equals, path = text.partition("=")
    if equals and name and not Path(text).exists():
        return name, path
    return None, text


def run(args: argparse.Namespace) -> int:
    from torchmorph import meshing  # the face: mesh_surfaces, mesh_cad
    from torchmorph.mesh.io import MESH_FORMATS

    output = Path(args.output)
    if output.suffix.lower() not in MESH_FORMATS:
        args.parser.error(
            f"argument --output/-o: unsupported mesh file extension "
            f"{output.suffix or '(none)'!r}; supported: "
            f"{', '.join(sorted(MESH_FORMATS))}"
        )
    if args.feature_angle is not None and not 0 < args.feature_angle < 180:
        args.parser.error(
            f"argument --feature-angle: must be in (0, 180) degrees, got {args.feature_angle:g}"
        )
    if (args.body_edge_length or args.grading) and args.box is None and args.bounds is None:
        args.parser.error("argument --body-edge-length/--grading: needs --box or --bounds")
    progress = args.progress  # plain lines, not bars: on in logs too
    try:  # CAD files and triangle surfaces cannot be mixed
        meshing.is_cad_input([_surface_argument(text)[1] for text in args.surfaces])
    except ValueError as error:
        raise CommandError(str(error).removeprefix("surfaces: ")) from error
    surfaces: dict[str, str | Surface] = {}  # CAD files by path, triangle surfaces read
    for text in args.surfaces:
        name, path = _surface_argument(text)
        if meshing.is_cad_file(path):  # gmsh reads it (mesh_surfaces -> mesh_cad)
            name = name or Path(path).stem
            if name in surfaces:
                raise CommandError(f"two surfaces are named {name!r}; name them with NAME=FILE")
            surfaces[name] = path
            _line("CAD file", f"{name}: {path}")
            continue
        try:
            surface = meshing.load_surface(path, name=name, repair=args.repair)
        except (ValueError, FileNotFoundError) as error:
            raise CommandError(str(error).removeprefix("path: ")) from error
        if surface.name in surfaces:
            raise CommandError(f"two surfaces are named {surface.name!r}; name them with NAME=FILE")
        surfaces[surface.name] = surface
        groups = f", groups {', '.join(surface.groups)}" if surface.groups else ""
        _line(
            "surface",
            f"{surface.name}: {path} ({len(surface.vertices)} vertices, "
            f"{len(surface.faces)} triangles{groups})",
        )
    bounds = None
    if args.bounds is not None:
        bounds = np.reshape(args.bounds, (2, 3))
    start = time.perf_counter()
    try:
        mesh = meshing.mesh_surfaces(
            surfaces,
            box=args.box,
            bounds=bounds,
            edge_length=args.edge_length,
            body_edge_length=args.body_edge_length,
            grading=args.grading,
            epsilon=args.epsilon,
            stop_energy=args.stop_energy,
            iterations=args.iterations,
            feature_angle=args.feature_angle,
            snap=args.snap,
            repair=args.repair,
            threads=args.threads,
            max_elements=args.max_elements,
            progress=progress,
        )
    except (ValueError, FileNotFoundError) as error:
        raise CommandError(_message(error)) from error
    _report(mesh, output, time.perf_counter() - start)
    return EXIT_OK


def _report(mesh, output: Path, elapsed: float) -> None:
    """Write the mesh and print its size, quality and node sets."""
    from torchmorph.mesh.io import write_mesh
    from torchmorph.mesh.quality import quality_summary

    summary = quality_summary(mesh)
    output.parent.mkdir(parents=True, exist_ok=True)
    write_mesh(output, mesh)
    _line(
        "mesh",
        f"{mesh.num_nodes} nodes ({mesh.boundary_nodes.numel()} boundary), "
        f"{mesh.num_tets} tetrahedra in {_seconds(elapsed)}",
    )
    _line(
        "quality Q",
        f"max {summary['max_edge_ratio']:.4g}, mean "
        f"{summary['mean_edge_ratio']:.4g} (edge ratio, 1 is best)",
    )
    _line("min volume", f"{summary['min_volume']:.6g}")
    _line("inverted tets", f"{summary['num_inverted']}")
    _line("node sets", f"{len(mesh.node_sets)}")
    width = max((len(name) for name in mesh.node_sets), default=0)
    for name in mesh.node_sets:
        print(f"  {name:<{width}}  {mesh.node_sets[name].numel()} nodes")
    _line("wrote", f"{output}")
