"""The paper's three test cases as data, and their reproduction.

Ballarin, D'Amario, Perotto and Rozza (2017), Section 2.3 (Tables 1–3, Figs. 4–13)
and Section 3.1 (Tables 4–6, Figs. 14–16). A package above the core: the core
modules (idw, selection, morph, pod, mesh, quality, io) never import it.

- :mod:`.cases` — the cases as data (:class:`CaseSpec`, :data:`CASES`, :data:`VARIANTS`);
- :mod:`.experiments` — :func:`reproduce` and the sweeps it and the figures share;
- :mod:`.reports` — result rows, tables and output files;
- :mod:`.plots` — the case figures and the one-mode POD figure.

:data:`CASES` holds one :class:`CaseSpec` per test case of Ballarin, D'Amario,
Perotto and Rozza (2017):

- ``"wing"`` (A): structural deformation of a NACA0012 wing, δy = μ z² on every
  boundary node (the clamped root z = 0 gets 0 by the formula itself);
- ``"fluid-wing"`` (B): the fluid mesh of a wind tunnel around that wing, δy = μ z²
  on the wing's nodes, the tunnel walls fixed;
- ``"hull"`` (C): the fluid mesh of a box around a Wigley hull, the hull rotated by
  μ degrees about the z axis through its centre (the origin), the box fixed.

Each spec carries the moving node sets, the displacement family (batched over μ),
the parameter domain D, the target μ*, the training-set size, the selection regions
with their radii, the ESIDW enrichment sets and the paper's own figures (Tables 1–6).

:func:`reproduce` builds (or loads) the mesh with :mod:`data_gen`, runs IDW, SIDW
(case A), ESIDW, POD-IDW and POD-ESIDW with the paper's parameters and prints the
tables beside the paper's values. The pieces it is made of — :func:`prepare_case`,
:func:`selective_morph`, :func:`selection_point`, :func:`radius_sweep`,
:func:`factor_sweep`, :func:`pod_spectra`, :func:`pod_parameter_sweep` — are the ones
the sensitivity study (``demos/sensitivity.py``) plots, so tables and figures share
their code.

Notes
-----
* "online time" is the wall-clock time of one morph for μ*, from the parameter value
  to the full nodal displacement field (evaluating the boundary displacement
  included), median of a few repeats after one warm-up call.
* "offline time" is the offline phase of the paper's Algorithm 3, steps (a)–(e):
  control-point selection, assembly of W, snapshots, SVD and online matrices. The
  POD fit alone (steps (b)–(e)) is reported as ``fit_s``.
* The POD online coefficients use the ``"projection"`` variant of
  :class:`~torchmorph.pod.PODReducer` (the orthogonal projection onto the POD space)
  unless ``online="paper"`` (the paper's eq. 16) is asked for; the latter needs W's
  pseudo-inverse offline (minutes for case B).
* Errors are relative errors against full IDW with every boundary node a control
  point, over the whole mesh, in two norms: the nodal ℓ2 norm (the paper's reading:
  it defines Ω_h as the set of nodes) and the P1 mass-matrix norm (L2(Ω) of the
  piecewise-linear field), see :func:`torchmorph.mesh.quality.relative_l2_error`.
"""

from __future__ import annotations

from torchmorph.paper.cases import (
    CASES,
    ENERGY_TOLERANCE,
    HULL_CENTRE,
    VARIANTS,
    CaseSpec,
    PaperMesh,
    PaperRow,
    case_key,
    get_case,
    hull_rotation,
    load_mesh,
    wing_bending,
)
from torchmorph.paper.experiments import (
    CaseContext,
    SelectionPoint,
    adaptive_morph,
    factor_sweep,
    pod_parameter_sweep,
    pod_spectra,
    prepare_case,
    radius_sweep,
    selection_point,
    selective_morph,
)
from torchmorph.paper.plots import plane_section, plot_case, plot_one_mode_bound
from torchmorph.paper.reports import CaseResult, MethodResult
from torchmorph.paper.reproduce import reproduce

__all__ = [
    "CASES",
    "ENERGY_TOLERANCE",
    "HULL_CENTRE",
    "VARIANTS",
    "CaseContext",
    "CaseResult",
    "CaseSpec",
    "MethodResult",
    "PaperMesh",
    "PaperRow",
    "SelectionPoint",
    "adaptive_morph",
    "case_key",
    "factor_sweep",
    "get_case",
    "hull_rotation",
    "load_mesh",
    "plane_section",
    "plot_case",
    "plot_one_mode_bound",
    "pod_parameter_sweep",
    "pod_spectra",
    "prepare_case",
    "radius_sweep",
    "reproduce",
    "selection_point",
    "selective_morph",
    "wing_bending",
]
