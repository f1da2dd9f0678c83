"""Mesh builders for the three test cases of the POD-Selective IDW paper.

Quick use::

    import data_gen
    mesh = data_gen.build("wing", size="paper")          # a torchmorph TetMesh
    mesh.node_set("root")

or from a shell: ``python -m data_gen wing --size paper -o wing.vtu``.
See :mod:`data_gen.cases` for the cases, sizes and meshers and
:mod:`data_gen.geometry` for the exact geometry and axes.
"""

from data_gen._arrays import MeshArrays, edge_ratio, mesh_figures
from data_gen.cache import default_cache_dir
from data_gen.cases import (
    CASES,
    MESHERS,
    PAPER_MESHES,
    PARAMETERS,
    SIZES,
    build,
    build_arrays,
    cache_path,
    canonical_case,
    fluid_wing,
    hull,
    wing,
)

__all__ = [
    "CASES",
    "MESHERS",
    "PAPER_MESHES",
    "PARAMETERS",
    "SIZES",
    "MeshArrays",
    "build",
    "build_arrays",
    "cache_path",
    "canonical_case",
    "default_cache_dir",
    "edge_ratio",
    "fluid_wing",
    "hull",
    "mesh_figures",
    "wing",
]
