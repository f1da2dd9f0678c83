"""Free-form deformation (Sederberg and Parry 1986): displacements of a control lattice
in a box to displacements of the points inside it, with Bernstein polynomials (PyGeM,
SU2's ``BEZIER``) or clamped uniform B-splines (the knots of SU2's
``BSPLINE_UNIFORM``), in 2-D and 3-D.

The one-dimensional bases (:mod:`torchmorph.ffd.basis`), the functional core
(:mod:`torchmorph.ffd.functional`: :func:`ffd_bases`, :func:`ffd_apply`), the lattice
sum they share (:mod:`torchmorph.ffd.lattice`) and the :class:`FFD` module
(:mod:`torchmorph.ffd.module`) over them.
"""

from torchmorph.ffd.basis import (
    bernstein_basis,
    bspline_basis,
    clamped_uniform_knots,
    greville_abscissae,
)
from torchmorph.ffd.functional import (
    BASES,
    BOUNDARY_ULPS,
    DEFAULT_DEGREE,
    Basis,
    control_coordinates,
    ffd_apply,
    ffd_bases,
    local_coordinates,
)
from torchmorph.ffd.lattice import (
    DEFAULT_BLOCK_BYTES,
    DEFAULT_CUDA_BLOCK_BYTES,
    FACTORED_COLUMNS,
    lattice_sum,
)
from torchmorph.ffd.module import FFD

__all__ = [
    "BASES",
    "BOUNDARY_ULPS",
    "DEFAULT_BLOCK_BYTES",
    "DEFAULT_CUDA_BLOCK_BYTES",
    "DEFAULT_DEGREE",
    "FACTORED_COLUMNS",
    "FFD",
    "Basis",
    "bernstein_basis",
    "bspline_basis",
    "clamped_uniform_knots",
    "control_coordinates",
    "ffd_apply",
    "ffd_bases",
    "greville_abscissae",
    "lattice_sum",
    "local_coordinates",
]
