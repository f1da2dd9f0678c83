"""Small OpenFOAM cases for the polyMesh tests: dictionaries written from Python,
meshes made by blockMesh (or gmshToFoam), and OpenFOAM's own tools run on them.

Every command runs with ``HOME`` set inside the case's parent directory, so that
nothing is written into the user's home.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

BASHRC = Path("/usr/share/openfoam/etc/bashrc")

HEADER = """FoamFile
{{
    version     2.0;
    format      ascii;
    class       {kind};
    object      {name};
}}
"""


def needs_openfoam(*tools: str) -> None:
    """Skip the calling test unless OpenFOAM's environment, blockMesh, checkMesh and
    ``tools`` are installed."""
    if not BASHRC.is_file():
        pytest.skip(f"OpenFOAM is not installed (no {BASHRC})")
    for tool in ("blockMesh", "checkMesh", *tools):
        if shutil.which(tool) is None:
            pytest.skip(f"OpenFOAM's {tool} is not installed")


def foam(command: str, case: Path, *, check: bool = True) -> str:
    """Run an OpenFOAM command (``"checkMesh"``, ``"blockMesh"`` ...) on ``case``; its log."""
    home = case.parent / ".home"
    home.mkdir(exist_ok=True)
    script = f"source {BASHRC} >/dev/null 2>&1; {command} -case {case}"
    result = subprocess.run(
        ["bash", "-c", script],
        capture_output=True,
        text=True,
        env={**os.environ, "HOME": str(home)},
        timeout=300,
        check=False,
    )
    log = result.stdout + result.stderr
    if check and (result.returncode != 0 or "FOAM FATAL" in log):
        raise AssertionError(f"{command} failed on {case}:\n{log[-3000:]}")
    return log


def write_dict(path: Path, body: str, *, kind: str = "dictionary") -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(HEADER.format(kind=kind, name=path.name) + body)


def control_dict(case: Path, *, write_format: str = "ascii", compression: str = "off") -> None:
    write_dict(
        case / "system" / "controlDict",
        f"""application potentialFoam;
startFrom startTime; startTime 0; stopAt endTime; endTime 1; deltaT 1;
writeControl timeStep; writeInterval 1; writeFormat {write_format}; writePrecision 17;
writeCompression {compression}; timeFormat general; timePrecision 6;
runTimeModifiable false;
""",
    )


def block_mesh(
    case: Path,
    vertices: list[tuple[float, float, float]],
    blocks: list[str],
    boundary: str,
    *,
    edges: str = "",
) -> str:
    """Write a blockMeshDict (and a controlDict) into ``case`` and run blockMesh; its log."""
    control_dict(case)
    points = "\n".join(f"    ({x!r} {y!r} {z!r})" for x, y, z in vertices)
    write_dict(
        case / "system" / "blockMeshDict",
        f"scale 1;\nvertices\n(\n{points}\n);\nblocks\n(\n"
        + "\n".join(f"    {b}" for b in blocks)
        + f"\n);\nedges\n(\n{edges}\n);\nboundary\n(\n{boundary}\n);\n",
    )
    return foam("blockMesh", case)


def fv_dicts(case: Path) -> None:
    """fvSchemes and fvSolution enough for checkMesh and potentialFoam."""
    write_dict(
        case / "system" / "fvSchemes",
        """ddtSchemes { default steadyState; }
gradSchemes { default Gauss linear; }
divSchemes { default none; div(phi,U) bounded Gauss linear; div(div(phi,U)) Gauss linear; }
laplacianSchemes { default Gauss linear corrected; }
interpolationSchemes { default linear; }
snGradSchemes { default corrected; }
""",
    )
    write_dict(
        case / "system" / "fvSolution",
        """solvers
{
    Phi { solver PCG; preconditioner DIC; tolerance 1e-10; relTol 0; }
    p { $Phi; }
}
potentialFlow { nNonOrthogonalCorrectors 3; }
""",
    )


def potential_fields(case: Path, roles: dict[str, str]) -> None:
    """``0/U`` and ``0/p`` for potentialFoam; ``roles`` gives each patch's role:
    ``inlet`` (U = (1 0 0)), ``outlet`` (p = 0), ``wall`` (slip), or a constraint type
    (``empty``, ``symmetryPlane``, ``symmetry``, ``wedge``) used as is."""
    velocity, pressure = [], []
    for patch, role in roles.items():
        if role == "inlet":
            u, p = "type fixedValue; value uniform (1 0 0);", "type zeroGradient;"
        elif role == "outlet":
            u, p = "type zeroGradient;", "type fixedValue; value uniform 0;"
        elif role == "wall":
            u, p = "type slip;", "type zeroGradient;"
        else:
            u = p = f"type {role};"
        velocity.append(f"    {patch} {{ {u} }}")
        pressure.append(f"    {patch} {{ {p} }}")
    for name, kind, dimensions, value, entries in (
        ("U", "volVectorField", "[0 1 -1 0 0 0 0]", "(0 0 0)", velocity),
        ("p", "volScalarField", "[0 2 -2 0 0 0 0]", "0", pressure),
    ):
        write_dict(
            case / "0" / name,
            f"dimensions {dimensions};\ninternalField uniform {value};\n"
            "boundaryField\n{\n" + "\n".join(entries) + "\n}\n",
            kind=kind,
        )


def mesh_statistics(log: str) -> dict[str, int]:
    """The counts blockMesh or checkMesh report (``points``, ``faces``, ``internal
    faces``, ``cells``, and checkMesh's cell kinds: ``hexahedra``, ``prisms`` ...)."""
    found: dict[str, int] = {}
    for line in log.splitlines():
        words = line.replace(":", " ").split()
        if len(words) == 2 and words[1].isdigit():
            found[words[0]] = int(words[1])
    aliases = {"nPoints": "points", "nCells": "cells", "nFaces": "faces"}
    for alias, name in aliases.items():
        if alias in found:
            found[name] = found[alias]
    if "nInternalFaces" in found:
        found["internal faces"] = found["nInternalFaces"]
    for line in log.splitlines():
        head, _, tail = line.strip().partition(":")
        if tail.strip().isdigit():
            found[head.strip()] = int(tail)
    return found


def channel(case: Path, cells: tuple[int, int, int] = (8, 5, 3)) -> str:
    """A box [0, 2] x [0, 1] x [0, 0.5] of hexahedra: patches inlet (x = 0), outlet
    (x = 2), walls (y = 0 and 1, ``inGroups (wall solid)``), bottom (z = 0,
    symmetryPlane), top (z = 0.5, symmetry). blockMesh's log."""
    vertices = [(0, 0, 0), (2, 0, 0), (2, 1, 0), (0, 1, 0)]
    vertices += [(x, y, 0.5) for x, y, _ in vertices]
    nx, ny, nz = cells
    return block_mesh(
        case,
        vertices,
        [f"hex (0 1 2 3 4 5 6 7) ({nx} {ny} {nz}) simpleGrading (1 1 1)"],
        """    inlet { type patch; faces ((0 4 7 3)); }
    outlet { type patch; faces ((1 2 6 5)); }
    walls { type wall; inGroups (wall solid); faces ((0 1 5 4) (3 7 6 2)); }
    bottom { type symmetryPlane; faces ((0 3 2 1)); }
    top { type symmetry; faces ((4 5 6 7)); }""",
    )


def axisymmetric_wedge(case: Path, *, length=2.0, radius=0.5, angle=5.0, cells=(6, 4)) -> str:
    """OpenFOAM's axisymmetric set-up: a wedge of ``angle`` degrees about the x axis,
    one cell thick, its cells along the axis collapsed into prisms. Patches inlet,
    outlet, wall (r = radius), front and back (``wedge``); blockMesh's log."""
    half = np.radians(angle / 2)
    c, s = radius * np.cos(half), radius * np.sin(half)
    vertices = [(0, 0, 0), (length, 0, 0), (length, c, -s), (0, c, -s)]
    vertices += [(length, c, s), (0, c, s)]
    nx, nr = cells
    return block_mesh(
        case,
        [tuple(float(v) for v in vertex) for vertex in vertices],
        [f"hex (0 1 2 3 0 1 4 5) ({nx} {nr} 1) simpleGrading (1 1 1)"],
        """    inlet { type patch; faces ((0 0 5 3)); }
    outlet { type patch; faces ((1 2 4 1)); }
    wall { type wall; faces ((3 5 4 2)); }
    front { type wedge; faces ((0 1 4 5)); }
    back { type wedge; faces ((0 3 2 1)); }
    axis { type empty; faces ((0 1 1 0)); }""",
    )


def flat_channel(case: Path, cells: tuple[int, int] = (20, 8), thickness: float = 0.1) -> str:
    """A pseudo-2-D channel [0, 4] x [0, 1], one cell thick in z (0 .. thickness):
    inlet, outlet, lower and upper (walls, ``inGroups (walls)``), frontAndBack (empty);
    blockMesh's log."""
    vertices = [(0, 0, 0), (4, 0, 0), (4, 1, 0), (0, 1, 0)]
    vertices += [(x, y, thickness) for x, y, _ in vertices]
    nx, ny = cells
    return block_mesh(
        case,
        vertices,
        [f"hex (0 1 2 3 4 5 6 7) ({nx} {ny} 1) simpleGrading (1 1 1)"],
        """    inlet { type patch; faces ((0 4 7 3)); }
    outlet { type patch; faces ((1 2 6 5)); }
    lower { type wall; inGroups (walls); faces ((0 1 5 4)); }
    upper { type wall; inGroups (walls); faces ((3 7 6 2)); }
    frontAndBack { type empty; faces ((0 3 2 1) (4 5 6 7)); }""",
    )


#: The faces of each cell kind (meshio's node order), for finding a mesh's boundary.
CELL_FACES = {
    "tetra": [(0, 1, 2), (0, 1, 3), (1, 2, 3), (0, 2, 3)],
    "pyramid": [(0, 1, 2, 3), (0, 1, 4), (1, 2, 4), (2, 3, 4), (3, 0, 4)],
    "wedge": [(0, 1, 2), (3, 4, 5), (0, 1, 4, 3), (1, 2, 5, 4), (2, 0, 3, 5)],
    "hexahedron": [
        (0, 1, 2, 3),
        (4, 5, 6, 7),
        (0, 1, 5, 4),
        (1, 2, 6, 5),
        (2, 3, 7, 6),
        (3, 0, 4, 7),
    ],
}


def mixed_cells() -> tuple[np.ndarray, list[tuple[str, np.ndarray]]]:
    """Three unit cubes along x, conforming: [-1, 0] split into 2 wedges, [0, 1] one
    hexahedron, [1, 2] six pyramids about its centre of which the one on x = 2 is split
    into 2 tetrahedra. Points (17, 3) and cell blocks in meshio's order (positive)."""
    square = [(0, 0), (1, 0), (1, 1), (0, 1)]
    points = [(x, y, z) for z in (0, 1) for x, y in square]  # cube A: 0..7
    points += [(2, 0, 0), (2, 1, 0), (2, 1, 1), (2, 0, 1), (1.5, 0.5, 0.5)]  # B: 8..12
    points += [(-1, 0, 0), (-1, 1, 0), (-1, 1, 1), (-1, 0, 1)]  # C: 13..16
    points = np.array(points, dtype=float)
    apex = 12
    pyramids, tets = [], []
    for base in (
        (1, 2, 6, 5),
        (8, 9, 10, 11),
        (1, 8, 11, 5),
        (2, 9, 10, 6),
        (1, 8, 9, 2),
        (5, 11, 10, 6),
    ):
        a, b, c, _ = points[list(base)]
        if np.cross(b - a, c - a) @ (points[apex] - a) < 0:
            base = base[::-1]
        if 8 in base and 9 in base and 10 in base:
            tets += [(base[0], base[1], base[2], apex), (base[0], base[2], base[3], apex)]
        else:
            pyramids.append((*base, apex))
    cells = [
        ("tetra", np.array(tets)),
        ("pyramid", np.array(pyramids)),
        ("wedge", np.array([(13, 0, 3, 16, 4, 7), (13, 3, 14, 16, 7, 15)])),
        ("hexahedron", np.array([(0, 1, 2, 3, 4, 5, 6, 7)])),
    ]
    return points, cells


def gmsh_case(case: Path, points: np.ndarray, cells: list[tuple[str, np.ndarray]]) -> str:
    """A case meshed by ``gmshToFoam`` from ``cells``: patches inlet (x = min), outlet
    (x = max) and walls (the rest of the boundary). gmshToFoam's log."""
    import meshio

    seen: dict[tuple, tuple] = {}
    for kind, block in cells:
        for cell in block:
            for face in CELL_FACES[kind]:
                vertices = tuple(int(cell[k]) for k in face)
                key = tuple(sorted(vertices))
                seen[key] = None if key in seen else vertices
    boundary = [face for face in seen.values() if face is not None]
    low, high = points[:, 0].min(), points[:, 0].max()
    groups = {"inlet": 1, "outlet": 2, "walls": 3}
    facets: dict[tuple[str, int], list] = {}
    for face in boundary:
        x = points[list(face), 0]
        group = "inlet" if np.all(x == low) else "outlet" if np.all(x == high) else "walls"
        facets.setdefault(("triangle" if len(face) == 3 else "quad", groups[group]), []).append(
            face
        )
    blocks = [(kind, np.array(faces)) for (kind, _), faces in facets.items()]
    tags = [np.full(len(faces), tag) for (_, tag), faces in facets.items()]
    blocks += cells
    tags += [np.full(len(block), 4) for _, block in cells]
    mesh = meshio.Mesh(
        points,
        blocks,
        cell_data={"gmsh:physical": tags, "gmsh:geometrical": tags},
        field_data={
            **{name: np.array([tag, 2]) for name, tag in groups.items()},
            "fluid": np.array([4, 3]),
        },
    )
    control_dict(case)
    mesh.write(case / "mesh.msh", file_format="gmsh22", binary=False)
    return foam(f"gmshToFoam {case / 'mesh.msh'}", case)


def triangle_slab(case: Path, cells: int = 4) -> str:
    """A pseudo-2-D triangle (0, 0), (1, 0), (0.5, 1), one cell thick in z (0 .. 0.1),
    from a blockMesh block with a collapsed edge: wedges at the apex, hexahedra
    elsewhere. Patches bottom (wall), right, left, frontAndBack (empty) and blockMesh's
    defaultFaces (no faces); blockMesh's log."""
    return block_mesh(
        case,
        [(0, 0, 0), (1, 0, 0), (0.5, 1, 0), (0, 0, 0.1), (1, 0, 0.1), (0.5, 1, 0.1)],
        [f"hex (0 1 2 2 3 4 5 5) ({cells} {cells} 1) simpleGrading (1 1 1)"],
        """    bottom { type wall; faces ((0 1 4 3)); }
    right { type patch; faces ((1 2 5 4)); }
    left { type patch; faces ((2 0 3 5)); }
    frontAndBack { type empty; faces ((0 2 2 1) (3 4 5 5)); }""",
    )


# -- polyMesh files written by hand (no OpenFOAM needed) ----------------------------

#: A hexahedron's faces out of it (meshio's node order).
HEX_OUTWARD = ((0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7))


def box_hexes(counts=(3, 2, 2), lengths=(3.0, 2.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """A structured box of hexahedra: points (N, 3) (x fastest) and hexes (M, 8)."""
    nx, ny, nz = counts
    axes = [np.linspace(0.0, length, n + 1) for length, n in zip(lengths, counts, strict=True)]
    z, y, x = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    points = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    number = np.arange(points.shape[0]).reshape(nz + 1, ny + 1, nx + 1)
    corners = [
        (0, 0, 0),
        (0, 0, 1),
        (0, 1, 1),
        (0, 1, 0),
        (1, 0, 0),
        (1, 0, 1),
        (1, 1, 1),
        (1, 1, 0),
    ]
    hexes = np.stack(
        [number[k : k + nz, j : j + ny, i : i + nx].ravel() for k, j, i in corners], axis=1
    )
    return points, hexes


def polymesh_arrays(points: np.ndarray, hexes: np.ndarray, patch_of) -> dict:
    """OpenFOAM's arrays for a hexahedral mesh: ``faces`` (list of tuples), ``owner``,
    ``neighbour``, ``patches`` [(name, type, n_faces, start_face)]. Internal faces first in
    upper-triangular order, then the boundary faces patch by patch; ``patch_of(centre)``
    names a boundary face's patch as (name, type)."""
    found: dict[frozenset, list] = {}
    for cell, hexahedron in enumerate(hexes):
        for face in HEX_OUTWARD:
            vertices = tuple(int(hexahedron[k]) for k in face)
            key = frozenset(vertices)
            if key in found:
                found[key][2] = cell
            else:
                found[key] = [vertices, cell, -1]
    internal = sorted((f for f in found.values() if f[2] >= 0), key=lambda f: (f[1], f[2]))
    by_patch: dict[tuple[str, str], list] = {}
    for face in (f for f in found.values() if f[2] < 0):
        by_patch.setdefault(patch_of(points[list(face[0])].mean(axis=0)), []).append(face)
    faces = [f[0] for f in internal]
    owner = [f[1] for f in internal]
    patches = []
    for (name, kind), members in by_patch.items():
        patches.append((name, kind, len(members), len(faces)))
        faces += [f[0] for f in members]
        owner += [f[1] for f in members]
    return {
        "points": points,
        "faces": faces,
        "owner": np.array(owner),
        "neighbour": np.array([f[2] for f in internal]),
        "patches": patches,
    }


def box_case(counts=(3, 2, 2), lengths=(3.0, 2.0, 1.0), *, empty_z: bool = False) -> dict:
    """A box's polyMesh arrays: patches xmin, xmax (patch), ymin, ymax (wall), and zmin,
    zmax (symmetryPlane), or one ``frontAndBack`` (empty) for both with ``empty_z``."""
    points, hexes = box_hexes(counts, lengths)

    def patch_of(centre):
        for axis, (low, high) in enumerate(
            ((0.0, lengths[0]), (0.0, lengths[1]), (0.0, lengths[2]))
        ):
            side = (
                "min"
                if np.isclose(centre[axis], low)
                else "max"
                if np.isclose(centre[axis], high)
                else None
            )
            if side is None:
                continue
            if axis == 2:
                return ("frontAndBack", "empty") if empty_z else (f"z{side}", "symmetryPlane")
            return (f"{'xy'[axis]}{side}", "patch" if axis == 0 else "wall")
        raise AssertionError(centre)

    return polymesh_arrays(points, hexes, patch_of)


def foam_header(kind: str, name: str, *, binary: bool = False, arch: str | None = None) -> bytes:
    arch_line = f'    arch        "{arch}";\n' if arch else ""
    return (
        "/*--------------------------------*- C++ -*----------------------------------*\\\n"
        "  a hand-written polyMesh file\n"
        "\\*---------------------------------------------------------------------------*/\n"
        "FoamFile\n{\n    version     2.0;\n"
        f"    format      {'binary' if binary else 'ascii'};\n    class       {kind};\n"
        f'{arch_line}    location    "constant/polyMesh";\n    object      {name};\n}}\n'
        "// * * * * * * * * * * * * * * * * * * * * * * * * * * * * * * * * * * * //\n\n\n"
    ).encode()


FOOTER = b"\n\n// ************************************************************************* //\n"


def write_polymesh(
    mesh_dir: Path,
    arrays: dict,
    *,
    binary: bool = False,
    label_bits: int = 32,
    scalar_bits: int = 64,
    byte_order: str = "<",
    compact_ascii: bool = False,
    compress: bool = False,
) -> None:
    """Write ``arrays`` (of :func:`polymesh_arrays`) as the five polyMesh files."""
    import gzip

    mesh_dir.mkdir(parents=True, exist_ok=True)
    arch = f"{'LSB' if byte_order == '<' else 'MSB'};label={label_bits};scalar={scalar_bits}"
    label = np.dtype(f"{byte_order}i{label_bits // 8}")
    scalar = np.dtype(f"{byte_order}f{scalar_bits // 8}")

    def labels(values) -> bytes:
        values = np.asarray(values, dtype=np.int64)
        if binary:
            return b"%d\n(" % values.size + values.astype(label).tobytes() + b")"
        return b"%d\n(\n" % values.size + b"".join(b"%d\n" % v for v in values) + b")"

    points = arrays["points"]
    if binary:
        point_list = b"%d\n(" % len(points) + points.astype(scalar).tobytes() + b")"
    else:
        point_list = (
            b"%d\n(\n" % len(points)
            + b"".join(b"(%.17g %.17g %.17g)\n" % tuple(p) for p in points)
            + b")"
        )
    faces = arrays["faces"]
    if binary or compact_ascii:
        offsets = np.concatenate([[0], np.cumsum([len(f) for f in faces])])
        flat = [v for f in faces for v in f]
        face_list, face_class = labels(offsets) + b"\n\n" + labels(flat), "faceCompactList"
    else:
        face_list = (
            b"%d\n(\n" % len(faces)
            + b"".join(b"%d(%s)\n" % (len(f), " ".join(map(str, f)).encode()) for f in faces)
            + b")"
        )
        face_class = "faceList"
    patches = (
        b"%d\n(\n" % len(arrays["patches"])
        + b"".join(
            f"    {name}\n    {{\n        type            {kind};\n"
            f"        inGroups        List<word> 1(group_{kind});\n"
            f"        nFaces          {n};\n        startFace       {start};\n    }}\n".encode()
            for name, kind, n, start in arrays["patches"]
        )
        + b")"
    )
    contents = {
        "points": ("vectorField", point_list, binary),
        "faces": (face_class, face_list, binary),
        "owner": ("labelList", labels(arrays["owner"]), binary),
        "neighbour": ("labelList", labels(arrays["neighbour"]), binary),
        "boundary": ("polyBoundaryMesh", patches, False),
    }
    for name, (kind, body, is_binary) in contents.items():
        data = foam_header(kind, name, binary=is_binary, arch=arch if binary else None)
        data += body + FOOTER
        if compress:
            (mesh_dir / f"{name}.gz").write_bytes(gzip.compress(data))
        else:
            (mesh_dir / name).write_bytes(data)
