"""Your own shape end to end: a closed surface -> a tetrahedral mesh in a tunnel -> an ESIDW morph.

Without options the shape is a simple car-like body (the convex hull of a lower box and a
narrower cabin: sharp edges and smooth patches, no boolean operations needed), written to
``OUT/car.stl`` first, so the run shows exactly what a user with an STL file does:

1. :func:`torchmorph.meshing.mesh_surfaces` puts it in a tunnel (box padded 1x the body's
   length upstream, 2.5x downstream, 1x sideways and above, 0.1x below), tetrahedralises
   the fluid with fTetWild, snaps the boundary back onto the surface and names the node
   sets: the body, the walls ``wall_x0`` ... ``wall_z1``, and with the feature angle the
   body's sharp edges ``<body>_edges`` and its smooth patches;
2. the body is stretched by ``mu``: lengthened about its centre and raised from its
   bottom, ``d = mu * ((x - x_c), 0, (z - z_min))``; the walls are fixed;
3. the fluid follows by IDW from every boundary node (the reference) and by ESIDW
   (Ballarin et al. 2017, Algorithm 2): a selection per region (body: radius R, walls: 5 R)
   enriched with the body's sharp edges; the relative L2 error, the controls and the
   quality of both are printed. Thinning the fixed walls far more than the body weakens
   the body's pull (IDW weights count control points), so the walls' radius should not
   outgrow the body's by much more than their mesh sizes do;
4. ``OUT/reference.vtu`` (point data ``displacement``, ``control_point``),
   ``OUT/deformed_esidw.vtu`` and ``OUT/own_shape.png`` are written.

Usage::

    python demos/own_shape.py [--surface body.stl | --mesh body.vtu --body body] [--out DIR]

``--surface`` meshes your file the same way; ``--mesh`` takes a mesh made by
``torchmorph mesh body.stl --box 1,2.5,1,1,0.1,1 --feature-angle 30 -o body.vtu``.
Needs ``pip install 'torchmorph[tetwild,plot]'`` (not for ``--mesh``).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

from torchmorph import MeshMorph, quality_summary, read_mesh, relative_l2_error, write_mesh
from torchmorph._atomic import atomic_output
from torchmorph.selection import SelectionPlan

#: Padding of the tunnel (x0, x1, y0, y1, z0, z1) in multiples of the body's largest extent.
TUNNEL = (1.0, 2.5, 1.0, 1.0, 0.1, 1.0)
#: Edge lengths, relative to the body's largest extent: on the body and far from it.
SIZES = {"small": (0.09, 0.6), "fine": (0.035, 0.35)}


def car_surface(path: Path) -> Path:
    """A car-like convex body (length 1 m) written as STL: the hull of a body and a cabin."""
    import trimesh

    lower = np.array([[x, y, z] for x in (0.0, 1.0) for y in (-0.22, 0.22) for z in (0.0, 0.2)])
    cabin = np.array([[x, y, 0.36] for x in (0.32, 0.68) for y in (-0.17, 0.17)])
    nose = np.array([[-0.04, y, 0.09] for y in (-0.18, 0.18)])  # a chamfered front
    hull = trimesh.convex.convex_hull(np.concatenate([lower, cabin, nose]))
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_output(path) as temporary:
        hull.export(temporary)
    return path


def stretch(points: torch.Tensor, mu: float) -> torch.Tensor:
    """``mu * ((x - x_c), 0, (z - z_min))`` for the body's points."""
    centre = 0.5 * (points[:, 0].min() + points[:, 0].max())
    bottom = points[:, 2].min()
    zero = torch.zeros_like(points[:, 0])
    return mu * torch.stack([points[:, 0] - centre, zero, points[:, 2] - bottom], 1)


def plot(path: Path, mesh, body: str, displacement: torch.Tensor, controls: torch.Tensor) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    points = mesh.points.numpy()
    body_nodes = mesh.node_set(body).numpy()
    is_control = np.zeros(mesh.num_nodes, dtype=bool)
    is_control[controls.numpy()] = True
    magnitude = displacement.norm(dim=1).numpy()
    figure = plt.figure(figsize=(12, 4.8), constrained_layout=True)
    left = figure.add_subplot(1, 2, 1, projection="3d")
    on_body = body_nodes[~is_control[body_nodes]]
    chosen = body_nodes[is_control[body_nodes]]
    left.scatter(*points[on_body].T, s=2, c="0.6", label=f"{body} nodes ({len(body_nodes)})")
    left.scatter(*points[chosen].T, s=8, c="crimson", label=f"ESIDW controls ({len(chosen)})")
    low, high = points[body_nodes].min(0), points[body_nodes].max(0)
    centre, half = (low + high) / 2, (high - low).max() / 2
    for axis, setter in enumerate((left.set_xlim, left.set_ylim, left.set_zlim)):
        setter(centre[axis] - half, centre[axis] + half)
    left.set_box_aspect((1, 1, 1))
    left.set_title(f"{body}: control points on the body")
    left.legend(loc="upper left", fontsize=8)
    right = figure.add_subplot(1, 2, 2)
    slab = np.abs(points[:, 1] - centre[1]) < 0.03 * (high - low).max() + 1e-12
    moved = points + displacement.numpy()
    shown = slab & (np.abs(moved[:, 0] - centre[0]) < 2 * half) & (moved[:, 2] < high[2] + 2 * half)
    scatter = right.scatter(
        moved[shown, 0], moved[shown, 2], c=magnitude[shown], s=6, cmap="viridis"
    )
    right.set_aspect("equal")
    right.set_xlabel("x")
    right.set_ylabel("z")
    right.set_title("deformed nodes near the mid-plane y = y_c, coloured by |d|")
    figure.colorbar(scatter, ax=right, label="|d| (ESIDW)", shrink=0.85)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_output(path) as temporary:
        figure.savefig(temporary, dpi=110)
    plt.close(figure)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    source = parser.add_mutually_exclusive_group()
    source.add_argument(
        "--surface", type=Path, help="closed surface file (default: a car-like body)"
    )
    source.add_argument("--mesh", type=Path, help="a mesh from 'torchmorph mesh' (skips meshing)")
    parser.add_argument(
        "--body", default=None, help="node set of the body (default: the surface file's name)"
    )
    parser.add_argument(
        "--size",
        choices=tuple(SIZES),
        default="fine",
        help="mesh size (default fine; small is quicker)",
    )
    parser.add_argument(
        "--feature-angle", type=float, default=30.0, help="sharp-edge angle in degrees (default 30)"
    )
    parser.add_argument("--mu", type=float, default=0.1, help="stretch parameter (default 0.1)")
    parser.add_argument(
        "--radius",
        type=float,
        default=0.05,
        help="selection radius R on the body, relative to its extent (default "
        "0.05); the walls use 5 R",
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=Path("out/own_shape"),
        help="output directory (default %(default)s)",
    )
    parser.add_argument("--quiet", action="store_true", help="print nothing")
    args = parser.parse_args(argv)
    say = (lambda *a: None) if args.quiet else print

    start = time.perf_counter()
    if args.mesh is not None:
        mesh = read_mesh(args.mesh)
        body = args.body or args.mesh.stem
    else:
        from torchmorph.meshing import load_surface, mesh_surfaces

        surface_file = args.surface or car_surface(args.out / "car.stl")
        body = args.body or surface_file.stem
        surface = load_surface(surface_file, name=body)
        extent = float(np.ptp(surface.bounds, axis=0).max())
        near, far = SIZES[args.size]
        mesh = mesh_surfaces(
            {body: surface},
            box=TUNNEL,
            body_edge_length=near * extent,
            edge_length=far * extent,
            grading=extent,
            feature_angle=args.feature_angle,
            progress=not args.quiet,
        )
    if body not in mesh.node_sets:
        sys.exit(
            f"own_shape: no node set {body!r} in the mesh; pass --body (known: "
            f"{', '.join(sorted(mesh.node_sets))})"
        )
    meshed = time.perf_counter() - start
    reference_quality = quality_summary(mesh)
    say(
        f"mesh: {mesh.num_nodes} nodes ({mesh.boundary_nodes.numel()} boundary), "
        f"{mesh.num_tets} tets in {meshed:.1f} s; Q max {reference_quality['max_edge_ratio']:.3g}"
        f", mean {reference_quality['mean_edge_ratio']:.3g}; node sets "
        f"{', '.join(f'{k} {v.numel()}' for k, v in mesh.node_sets.items())}"
    )

    body_points = mesh.points[mesh.node_set(body)]
    extent = float((body_points.max(0).values - body_points.min(0).values).max())
    walls = [name for name in mesh.node_sets if name.startswith("wall_")]
    edges = [f"{body}_edges"] if f"{body}_edges" in mesh.node_sets else []
    regions = {body: args.radius * extent}
    if walls:
        regions[tuple(walls)] = 5 * args.radius * extent
    plan = SelectionPlan(regions, enrich=edges, overlap="first")
    generator = torch.Generator().manual_seed(0)

    results = {}
    fields = {}
    for label, selection in (("IDW", None), ("ESIDW", plan)):
        begin = time.perf_counter()
        morph = MeshMorph(mesh, selection, generator=generator)
        built = time.perf_counter() - begin
        boundary = morph.boundary_displacement(body, lambda p: stretch(p, args.mu))
        begin = time.perf_counter()
        with torch.no_grad():
            field = morph(boundary)
        seconds = time.perf_counter() - begin
        fields[label] = (field, morph.control_nodes)
        summary = quality_summary(mesh, field)
        results[label] = {
            "controls": morph.num_controls,
            "setup_s": built,
            "morph_s": seconds,
            **summary,
        }
    for label, row in results.items():
        error = float(relative_l2_error(mesh, fields[label][0], fields["IDW"][0]))
        row["error"] = error
        say(
            f"{label:6s} {row['controls']:6d} controls, setup {row['setup_s']:.3f} s, morph "
            f"{row['morph_s'] * 1e3:.2f} ms, L2 error vs IDW {error:.2e}, Q max "
            f"{row['max_edge_ratio']:.3g}, inverted {row['num_inverted']}"
        )

    field, controls = fields["ESIDW"]
    flag = torch.zeros(mesh.num_nodes, dtype=torch.uint8)
    flag[controls] = 1
    args.out.mkdir(parents=True, exist_ok=True)
    files = [
        args.out / "reference.vtu",
        args.out / "deformed_esidw.vtu",
        args.out / "own_shape.png",
    ]
    write_mesh(files[0], mesh, point_data={"displacement": field, "control_point": flag})
    write_mesh(files[1], mesh.deformed(field), point_data={"displacement": field})
    plot(files[2], mesh, body, field, controls)
    say("wrote " + ", ".join(str(path) for path in files))
    return {"mesh": mesh, "body": body, "results": results, "files": files}


if __name__ == "__main__":
    main()
