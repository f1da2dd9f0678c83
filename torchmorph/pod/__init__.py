"""POD-reduced morphing, Algorithm 3 of the paper: the :class:`PODReducer` estimator
(:mod:`torchmorph.pod.reducer`) over the plain functions of
:mod:`torchmorph.pod.functional` (the POD basis, the online matrices of the
projection and of the paper's eq. 16)."""

from torchmorph.pod.functional import (
    check_energy_tolerance,
    check_num_modes,
    paper_matrices,
    pod_basis,
    projection_matrix,
)
from torchmorph.pod.reducer import PODReducer

__all__ = [
    "PODReducer",
    "check_energy_tolerance",
    "check_num_modes",
    "paper_matrices",
    "pod_basis",
    "projection_matrix",
]
