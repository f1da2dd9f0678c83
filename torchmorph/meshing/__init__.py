"""Tetrahedral meshes of your own geometry: closed triangle surfaces (STL, OBJ, PLY,
OFF) through fTetWild (:mod:`torchmorph.meshing.tetwild`) and CAD files (STEP, IGES,
BREP) through gmsh (:mod:`torchmorph.meshing.cad`), optionally in a far-field box, with
named boundary node sets; surface reading and geometry in
:mod:`torchmorph.meshing.surfaces`. Before meshing, the number of tetrahedra is
estimated and refused above ``max_elements`` (:mod:`torchmorph.meshing.estimate`), and
bodies that overlap or touch are refused (:mod:`torchmorph.meshing.checks`). Not
imported by the morphing core."""

from torchmorph.mesh.quality import quality_report
from torchmorph.meshing.cad import is_cad_file, is_cad_input, mesh_cad
from torchmorph.meshing.estimate import MAX_ELEMENTS, TetEstimate, estimate_tets
from torchmorph.meshing.surfaces import (
    BOX_WALLS,
    CAD_FORMATS,
    PLY_LABELS,
    SURFACE_FORMATS,
    WALL_NAMES,
    Surface,
    box_bounds,
    box_surface,
    closest_points,
    feature_edges,
    load_surface,
    surface_problems,
)
from torchmorph.meshing.tetwild import mesh_surfaces, tetrahedralize

__all__ = [
    "BOX_WALLS",
    "CAD_FORMATS",
    "MAX_ELEMENTS",
    "PLY_LABELS",
    "SURFACE_FORMATS",
    "WALL_NAMES",
    "Surface",
    "TetEstimate",
    "box_bounds",
    "box_surface",
    "closest_points",
    "estimate_tets",
    "feature_edges",
    "is_cad_file",
    "is_cad_input",
    "load_surface",
    "mesh_cad",
    "mesh_surfaces",
    "quality_report",
    "surface_problems",
    "tetrahedralize",
]
