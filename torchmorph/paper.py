"""The paper's three test cases as data, and their reproduction (SPEC.md §6).

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
  :class:`~torchmorph.pod.PODReducer` (SPEC.md §4) unless ``online="paper"`` is
  asked for; the latter needs W's pseudo-inverse offline (minutes for case B).
* Errors are relative errors in L2(Ω_h) (P1 mass matrix, SPEC.md §5) against full
  IDW with every boundary node a control point, over the whole mesh.
"""

from __future__ import annotations

import dataclasses
import json
import math
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import Tensor

from .mesh import TetMesh
from .morph import MeshMorph
from .quality import edge_ratio, inverted, quality_summary, relative_l2_error
from .selection import Region, SelectionPlan

if TYPE_CHECKING:
    from .pod import PODReducer

__all__ = [
    "CASES",
    "ENERGY_TOLERANCE",
    "HULL_CENTRE",
    "CaseContext",
    "CaseResult",
    "CaseSpec",
    "MethodResult",
    "PaperMesh",
    "PaperRow",
    "SelectionPoint",
    "VARIANTS",
    "case_key",
    "factor_sweep",
    "get_case",
    "hull_rotation",
    "load_mesh",
    "plane_section",
    "plot_case",
    "pod_parameter_sweep",
    "pod_spectra",
    "prepare_case",
    "radius_sweep",
    "reproduce",
    "selection_point",
    "selective_morph",
    "wing_bending",
]

#: Centre of the hull's rotation (case C): the centre of the Wigley hull, which
#: ``data_gen`` places at the origin (mid-length, on the waterline, mid-beam).
HULL_CENTRE = (0.0, 0.0, 0.0)

#: Energy tolerance ε of the POD (the paper's, all three cases).
ENERGY_TOLERANCE = 1e-5


# --------------------------------------------------------------------------------------
# displacement families
# --------------------------------------------------------------------------------------


def _as_mu(mu: Tensor | float | Sequence[float], points: Tensor) -> Tensor:
    if not isinstance(mu, Tensor):
        mu = torch.as_tensor(mu, dtype=points.dtype)
    mu = mu.to(device=points.device, dtype=points.dtype)
    if mu.ndim > 1:
        raise ValueError(f"mu must be a scalar or of shape (B,), got {tuple(mu.shape)}")
    return mu


def wing_bending(points: Tensor, mu: Tensor | float) -> Tensor:
    """Vertical bending of the wing, δy = μ z² (paper eqs. 7 and 17).

    Parameters
    ----------
    points : Tensor, shape (n, 3)
        Reference coordinates of the moving nodes; z is the distance from the
        clamped root z = 0.
    mu : float or Tensor, shape () or (B,)
        Bending parameter(s).

    Returns
    -------
    Tensor, shape (n, 3) or (B, n, 3)
        ``(0, μ z², 0)`` per node; differentiable with respect to ``mu``.
    """
    mu = _as_mu(mu, points)
    z2 = points[:, 2].square()
    dy = mu[..., None] * z2
    zero = torch.zeros_like(dy)
    return torch.stack([zero, dy, zero], dim=-1)


def hull_rotation(
    points: Tensor,
    mu: Tensor | float,
    *,
    centre: Sequence[float] = HULL_CENTRE,
) -> Tensor:
    """Rigid rotation by μ degrees about the z axis through ``centre`` (case C).

    ``d = (R(μ) - I)(x - centre)`` with ``R(μ)`` the counter-clockwise rotation
    of the x–y plane by μ; the paper's μ* = -5° turns the bow (x > 0) down.

    Parameters
    ----------
    points : Tensor, shape (n, 3)
        Reference coordinates of the moving nodes.
    mu : float or Tensor, shape () or (B,)
        Rotation angle(s) in degrees.
    centre : sequence of 3 floats
        A point of the rotation axis; default :data:`HULL_CENTRE`.

    Returns
    -------
    Tensor, shape (n, 3) or (B, n, 3)
        Displacements; z components are 0. Differentiable with respect to ``mu``.
    """
    mu = _as_mu(mu, points)
    theta = torch.deg2rad(mu)[..., None]
    cos, sin = torch.cos(theta), torch.sin(theta)
    relative = points - torch.as_tensor(centre, dtype=points.dtype, device=points.device)
    x, y = relative[:, 0], relative[:, 1]
    dx = (cos - 1.0) * x - sin * y
    dy = sin * x + (cos - 1.0) * y
    return torch.stack([dx, dy, torch.zeros_like(dx)], dim=-1)


# --------------------------------------------------------------------------------------
# the paper's figures
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PaperMesh:
    """A row of the paper's Tables 1–3 (None where the paper gives no value)."""

    tets: int
    nodes: int
    interior: int
    boundary: int
    max_q: float | None = None
    mean_q: float | None = None
    max_q_deformed: float | None = None
    mean_q_deformed: float | None = None


@dataclass(frozen=True)
class PaperRow:
    """A row of the paper's Tables 4–6 (or the text of Section 2.3 for SIDW).

    ``error`` is the paper's wording (e.g. ``"< 1e-7"``, ``"0.23–2.85 %"``);
    ``error_value`` a number where the paper gives one (a fraction, 0.0106 for
    1.06 %), the upper end of a range, or the bound of ``"< x"``.
    """

    method: str
    controls: int
    offline_s: float | None
    modes: int | None
    online_s: float
    error: str
    error_value: float | None


@dataclass(frozen=True)
class CaseSpec:
    """One of the paper's test cases: geometry, displacement family, selection, results.

    Attributes
    ----------
    key : str
        ``"wing"``, ``"fluid-wing"`` or ``"hull"``.
    letter : str
        ``"A"``, ``"B"`` or ``"C"``.
    title : str
        The paper's name of the case.
    mesh_case : str
        The :func:`data_gen.build` case name.
    moving : tuple of str
        Node sets that move; every other boundary node is fixed.
    displacement : callable
        ``displacement(points (n, 3), mu () | (B,)) -> (n, 3) | (B, n, 3)``: the
        prescribed displacement of the moving nodes.
    parameter, unit : str
        Name and unit of μ for labels (``"μ"``, ``""`` or ``"°"``).
    domain : (float, float)
        The parameter domain D.
    mu_star : float
        The target parameter value μ*.
    n_train : int
        Size of the POD training set (drawn uniformly in D).
    radius : float
        The reference selection radius R of the tables.
    region_factors : tuple of (tuple of str, float)
        The selection regions: node sets and their radius as a multiple of R.
    enrich : tuple of str
        The ESIDW enrichment node sets.
    a, b : float
        Annulus and selection-shell factors of Algorithm 1.
    run_sidw : bool
        Whether the paper reports plain SIDW (case A only).
    mesh_table, results_table : int
        Numbers of the paper's mesh and results tables.
    paper_mesh : PaperMesh
        The paper's mesh (Tables 1–3, quality from Section 2.3).
    paper_rows : tuple of PaperRow
        The paper's results (Tables 4–6, SIDW from Section 2.3.1).
    sweep_radii : tuple of float
        Radii R of the sensitivity study (Figs. 5–6, 10, 13).
    sweep_note : str
        How the regions' radii follow R in the sensitivity study.
    variant : str
        ``"paper"`` for the configuration that reproduces the paper's figures
        (the default of every case); other names for documented alternatives
        (:data:`VARIANTS`).
    selection_note : str
        One line saying how the regions' radii were chosen.
    """

    key: str
    letter: str
    title: str
    mesh_case: str
    moving: tuple[str, ...]
    displacement: Callable[[Tensor, Tensor], Tensor]
    parameter: str
    unit: str
    domain: tuple[float, float]
    mu_star: float
    n_train: int
    radius: float
    region_factors: tuple[tuple[tuple[str, ...], float], ...]
    enrich: tuple[str, ...]
    a: float
    b: float
    run_sidw: bool
    mesh_table: int
    results_table: int
    paper_mesh: PaperMesh
    paper_rows: tuple[PaperRow, ...]
    sweep_radii: tuple[float, ...]
    sweep_note: str
    variant: str = "paper"
    selection_note: str = ""

    def regions(
        self, radius: float | None = None, *, a: float | None = None, b: float | None = None
    ) -> tuple[Region, ...]:
        """The selection regions for reference radius ``radius`` (default :attr:`radius`).

        Every region's radius is ``factor * radius``; ``a`` and ``b`` default to the
        paper's 0.8 and 1.3.
        """
        radius = self.radius if radius is None else float(radius)
        a = self.a if a is None else a
        b = self.b if b is None else b
        return tuple(Region(names, factor * radius, a, b) for names, factor in self.region_factors)

    def plan(
        self,
        radius: float | None = None,
        *,
        enrich: bool = True,
        a: float | None = None,
        b: float | None = None,
        strategy: str = "random",
    ) -> SelectionPlan:
        """The SIDW (``enrich=False``) or ESIDW selection plan of the case.

        Regions are listed finest radius first and a node shared by regions of
        different radii goes to the first (``overlap="first"``): the curves
        between faces are sampled at the finer face's radius.
        """
        regions = sorted(self.regions(radius, a=a, b=b), key=lambda region: region.radius)
        return SelectionPlan(regions, enrich=self.enrich if enrich else (),
                             strategy=strategy, overlap="first")

    def family(self, morph: MeshMorph) -> Callable[[Tensor | float], Tensor]:
        """The boundary displacement of ``morph`` as a function of μ.

        Returns
        -------
        callable
            ``mu () | (B,) -> (N_b, 3) | (B, N_b, 3)``, rows ordered as
            ``morph.boundary_nodes``; the moving sets get :attr:`displacement`,
            every other boundary node 0.
        """
        moving, displacement = self.moving, self.displacement

        def boundary_displacement(mu: Tensor | float) -> Tensor:
            return morph.boundary_displacement(moving, lambda points: displacement(points, mu))

        return boundary_displacement

    def training_parameters(
        self, seed: int = 0, *, dtype: torch.dtype = torch.float64
    ) -> Tensor:
        """``n_train`` values drawn uniformly in D with a seeded generator, shape (n_train,)."""
        generator = torch.Generator().manual_seed(int(seed))
        low, high = self.domain
        return low + (high - low) * torch.rand(self.n_train, generator=generator, dtype=dtype)

    def paper_row(self, method: str) -> PaperRow | None:
        """The paper's row for ``method`` (None if the paper has none)."""
        for row in self.paper_rows:
            if row.method == method:
                return row
        return None


def _row(method, controls, offline, modes, online, error, value):
    return PaperRow(method, controls, offline, modes, online, error, value)


_WING_ROWS = (
    _row("IDW", 1666, None, None, 0.25, "–", None),
    _row("SIDW", 92, None, None, 0.015, "≈ 4 %", 0.04),
    _row("ESIDW", 390, None, None, 0.034, "1.06 %", 0.0106),
    _row("POD-IDW", 1666, 90.93, 1, 0.013, "< 1e-7", 1e-7),
    _row("POD-ESIDW", 390, 76.84, 1, 0.013, "1.09 %", 0.0109),
)
_FLUID_WING_ROWS = (
    _row("IDW", 14126, None, None, 83.09, "–", None),
    _row("ESIDW", 9339, None, None, 23.90, "5.86 %", 0.0586),
    _row("POD-IDW", 14126, 2479.51, 1, 0.55, "< 1e-8", 1e-8),
    _row("POD-ESIDW", 9339, 1613.65, 1, 0.55, "5.94 %", 0.0594),
)
_HULL_ROWS = (
    _row("IDW", 3864, None, None, 4.51, "–", None),
    _row("ESIDW", 1057, None, None, 2.56, "2.42 %", 0.0242),
    _row("POD-IDW", 3864, 203.07, 2, 0.38, "< 1e-8", 1e-8),
    _row("POD-IDW (1 mode)", 3864, 203.07, 1, 0.38, "0.23–2.85 %", 0.0285),
    _row("POD-IDW (2 modes)", 3864, 203.07, 2, 0.38, "< 1e-8", 1e-8),
    _row("POD-ESIDW", 1057, 150.26, 2, 0.38, "2.43 %", 0.0243),
    _row("POD-ESIDW (1 mode)", 1057, 150.26, 1, 0.38, "2.62–3.84 %", 0.0384),
    _row("POD-ESIDW (2 modes)", 1057, 150.26, 2, 0.38, "2.43 %", 0.0243),
)

_WING = CaseSpec(
    key="wing",
    letter="A",
    title="Structural deformation of a wing",
    mesh_case="wing",
    moving=("wing",),
    displacement=wing_bending,
    parameter="μ",
    unit="",
    domain=(0.0, 1.3),
    mu_star=0.01,
    n_train=100,
    radius=0.05,
    # R_lr = R on the two end faces, R_tb = 10 R on the top and bottom surfaces
    region_factors=((("root",), 1.0), (("tip",), 1.0), (("upper",), 10.0), (("lower",), 10.0)),
    enrich=("root_profile", "tip_profile", "leading_edge", "trailing_edge"),
    a=0.8,
    b=1.3,
    run_sidw=True,
    mesh_table=1,
    results_table=4,
    paper_mesh=PaperMesh(tets=8850, nodes=2463, interior=797, boundary=1666),
    paper_rows=_WING_ROWS,
    sweep_radii=(0.005, 0.01, 0.02, 0.03, 0.05, 0.1, 0.2, 0.3, 0.5),
    sweep_note="R on the end faces (root, tip), 10 R on the upper and lower surfaces",
)
_FLUID_WING = CaseSpec(
    key="fluid-wing",
    letter="B",
    title="Fluid mesh motion around a wing",
    mesh_case="fluid_wing",
    moving=("wing",),
    displacement=wing_bending,
    parameter="μ",
    unit="",
    domain=(0.0, 0.05),
    mu_star=0.01,
    n_train=20,
    radius=0.5,
    # box: R on top, bottom, front, rear; 0.5 R on left/right; wing: 0.1 R
    region_factors=(
        (("wall_x0",), 1.0), (("wall_x1",), 1.0), (("wall_y0",), 1.0), (("wall_y1",), 1.0),
        (("wall_z0",), 0.5), (("wall_z1",), 0.5),
        (("upper",), 0.1), (("lower",), 0.1), (("tip",), 0.1),
    ),
    enrich=("root_profile", "tip_profile", "leading_edge", "trailing_edge"),
    a=0.8,
    b=1.3,
    run_sidw=False,
    mesh_table=2,
    results_table=5,
    paper_mesh=PaperMesh(tets=169598, nodes=36036, interior=21910, boundary=14126,
                         max_q=4.31, mean_q=1.48, max_q_deformed=4.31, mean_q_deformed=1.48),
    paper_rows=_FLUID_WING_ROWS,
    sweep_radii=(0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 3.0, 5.0),
    sweep_note="R on the top, bottom, front and rear walls, 0.5 R on the left and right "
               "walls, 0.1 R on the wing",
)
_HULL_WALLS = ("wall_x0", "wall_x1", "wall_y0", "wall_y1", "wall_z0", "wall_z1")
_HULL = CaseSpec(
    key="hull",
    letter="C",
    title="Fluid mesh motion around a rotating hull",
    mesh_case="hull",
    moving=("hull",),
    displacement=hull_rotation,
    parameter="μ",
    unit="°",
    domain=(-36.0, 0.0),
    mu_star=-5.0,
    n_train=50,
    radius=1.5,
    # balanced thinning: walls at 4/3 R = 2 m, hull at R/30 = 0.05 m, so that both keep
    # the same share (~28 %) of their nodes; see docs/results.md, case C
    region_factors=(
        *(((wall,), 4.0 / 3.0) for wall in _HULL_WALLS),
        (("hull",), 1.0 / 30.0),
    ),
    enrich=("hull_edges",),
    a=0.8,
    b=1.3,
    run_sidw=False,
    mesh_table=3,
    results_table=6,
    paper_mesh=PaperMesh(tets=30265, nodes=7186, interior=3322, boundary=3864,
                         max_q=2.47, mean_q=1.62, max_q_deformed=2.56, mean_q_deformed=1.63),
    paper_rows=_HULL_ROWS,
    sweep_radii=(0.05, 0.1, 0.2, 0.5, 1.0, 1.5, 2.0, 3.0, 5.0, 8.0),
    sweep_note="4/3 R on every box wall, R/30 on the hull",
    selection_note=(
        "walls R = 2 m, hull R = 0.05 m, hull edges enriched: body and walls thinned "
        "alike (our wall mesh, 1.7 m, is coarser than the paper's R = 1.5 m, which "
        "therefore cannot thin it)"
    ),
)
_HULL_UNIFORM = dataclasses.replace(
    _HULL,
    region_factors=tuple(((name,), 1.0) for name in (*_HULL_WALLS, "hull")),
    sweep_note="R on every box wall and on the hull",
    variant="uniform",
    selection_note=(
        "R = 1.5 m on every wall and on the hull, as printed in the paper: the walls "
        "keep ~92 % of their nodes, the hull ~9 %, and the far field is wrong"
    ),
)

#: The paper's three test cases, keyed ``"wing"`` (A), ``"fluid-wing"`` (B), ``"hull"`` (C).
CASES: dict[str, CaseSpec] = {spec.key: spec for spec in (_WING, _FLUID_WING, _HULL)}

#: Documented alternatives to a case's paper configuration, by case and variant name.
VARIANTS: dict[str, dict[str, CaseSpec]] = {
    "wing": {"paper": _WING},
    "fluid-wing": {"paper": _FLUID_WING},
    "hull": {"paper": _HULL, "uniform": _HULL_UNIFORM},
}


def case_key(case: str) -> str:
    """The key of :data:`CASES` for any spelling of a case name.

    Spellings come from the one table of case names,
    :func:`data_gen.cases.canonical_case` (``"fluid_wing"``, ``"fluid-wing"``,
    ``"B"``, …); the reproduction's keys write ``fluid-wing`` with a hyphen.
    """
    from data_gen.cases import canonical_case

    if not isinstance(case, str):
        raise TypeError(f"case must be a string, got {type(case).__name__}")
    try:
        name = canonical_case(case)
    except ValueError:
        raise ValueError(f"unknown case {case!r}; known: {', '.join(CASES)} (or A, B, C)") from None
    return name.replace("_", "-")


def get_case(case: str | CaseSpec, variant: str | None = None) -> CaseSpec:
    """The :class:`CaseSpec` for a case name or letter, and a variant of it.

    Parameters
    ----------
    case : str or CaseSpec
        ``"wing"``, ``"fluid-wing"`` (or ``"fluid_wing"``), ``"hull"``, or ``"A"``,
        ``"B"``, ``"C"``; a spec is returned as it is (``variant`` must be None).
    variant : str, optional
        ``"paper"`` (default) or a name in ``VARIANTS[case]``, e.g. ``"uniform"``
        for case C with R = 1.5 m everywhere.
    """
    if isinstance(case, CaseSpec):
        if variant not in (None, case.variant):
            raise ValueError(f"variant must be None for a CaseSpec, got {variant!r}")
        return case
    key = case_key(case)
    if variant is None:
        return CASES[key]
    if variant not in VARIANTS[key]:
        raise ValueError(f"variant must be one of {', '.join(VARIANTS[key])} for case {key!r}, "
                         f"got {variant!r}")
    return VARIANTS[key][variant]


# --------------------------------------------------------------------------------------
# meshes
# --------------------------------------------------------------------------------------


def load_mesh(
    case: str | CaseSpec,
    *,
    size: str = "paper",
    mesher: str = "gmsh",
    verbose: bool = False,
) -> TetMesh:
    """Build (or load from the cache) the case's mesh with :mod:`data_gen`.

    Raises
    ------
    ImportError
        If ``data_gen`` or the mesher (gmsh / pytetwild) is not installed; the
        message names the ``mesh`` extra.
    """
    spec = get_case(case)
    hint = ("the paper's meshes are generated with gmsh or pytetwild: install the "
            "'mesh' extra, e.g. pip install 'torchmorph[mesh]'")
    try:
        import data_gen
    except ImportError as error:
        raise ImportError(f"data_gen is not importable ({error}); {hint}") from error
    if not hasattr(data_gen, "build"):  # e.g. an unrelated namespace package of that name
        raise ImportError(f"the data_gen found at {list(getattr(data_gen, '__path__', []))} is "
                          f"not torchmorph's mesh builder package; {hint}")
    try:
        return data_gen.build(spec.mesh_case, size, mesher, verbose=verbose)
    except ImportError as error:
        raise ImportError(f"{error}; {hint}") from error


def _load_mesh_ticking(spec: CaseSpec, *, size: str, mesher: str, bar) -> TetMesh:
    """:func:`load_mesh` while a thread refreshes ``bar`` every second, so that a
    long meshing step shows its elapsed time instead of sitting still."""
    import threading

    done = threading.Event()

    def tick() -> None:
        while not done.wait(1.0):
            bar.refresh()

    thread = threading.Thread(target=tick, daemon=True)
    thread.start()
    try:
        return load_mesh(spec, size=size, mesher=mesher)
    finally:
        done.set()
        thread.join()


def _mesh_figures(mesh: TetMesh, summary: dict[str, Any]) -> dict[str, Any]:
    return {
        "tets": mesh.num_tets,
        "nodes": mesh.num_nodes,
        "interior": int(mesh.interior_nodes.numel()),
        "boundary": int(mesh.boundary_nodes.numel()),
        "max_q": summary["max_edge_ratio"],
        "mean_q": summary["mean_edge_ratio"],
    }


# --------------------------------------------------------------------------------------
# the building blocks
# --------------------------------------------------------------------------------------


def _median_time(function: Callable[[], Any], repeats: int) -> float:
    """Median wall-clock seconds of ``repeats`` calls after one warm-up call."""
    function()
    times = []
    for _ in range(max(1, int(repeats))):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


@dataclass
class CaseContext:
    """A case ready for experiments: mesh, full IDW morph and its answer at μ*.

    Attributes
    ----------
    spec : CaseSpec
    mesh : TetMesh
        The reference mesh.
    size, mesher : str
    idw : MeshMorph
        Full IDW: every boundary node is a control point.
    family : callable
        μ -> boundary displacement of ``idw`` (every morph of the mesh shares the
        boundary ordering, so it serves them all).
    mu_star : Tensor, shape ()
    boundary_star : Tensor, shape (N_b, 3)
        The boundary displacement at μ*.
    reference_star : Tensor, shape (N, 3)
        Full IDW's displacement at μ*: the reference of every error.
    reference_quality : dict
        :func:`~torchmorph.quality.quality_summary` of the reference mesh.
    """

    spec: CaseSpec
    mesh: TetMesh
    size: str
    mesher: str
    idw: MeshMorph
    family: Callable[[Tensor | float], Tensor]
    mu_star: Tensor
    boundary_star: Tensor
    reference_star: Tensor
    reference_quality: dict[str, Any]
    mode: str = "auto"

    def error(self, displacement: Tensor, reference: Tensor | None = None) -> Tensor:
        """Relative error in the P1 mass-matrix norm against full IDW at μ* (or ``reference``)."""
        reference = self.reference_star if reference is None else reference
        return relative_l2_error(self.mesh, displacement, reference, norm="mass")

    def error_nodal(self, displacement: Tensor, reference: Tensor | None = None) -> Tensor:
        """Relative error in the nodal ℓ2 norm (the paper's reading of L2(Ω_h))."""
        reference = self.reference_star if reference is None else reference
        return relative_l2_error(self.mesh, displacement, reference, norm="nodal")


def prepare_case(
    case: str | CaseSpec,
    *,
    size: str = "paper",
    mesher: str = "gmsh",
    mesh: TetMesh | None = None,
    mode: str = "auto",
    verbose: bool = False,
) -> CaseContext:
    """Load the mesh and assemble full IDW (the reference of every error).

    Parameters
    ----------
    case : str or CaseSpec
    size, mesher : str
        Passed to :func:`load_mesh`.
    mesh : TetMesh, optional
        Use this mesh instead of building one (its node sets must be the case's).
    mode : {"auto", "dense", "matrix_free"}
        IDW storage mode of every morph made from this context.
    verbose : bool
        Print data_gen's progress.
    """
    spec = get_case(case)
    if mesh is None:
        mesh = load_mesh(spec, size=size, mesher=mesher, verbose=verbose)
    with torch.no_grad():
        idw = MeshMorph(mesh, mode=mode)
        family = spec.family(idw)
        mu_star = torch.tensor(spec.mu_star, dtype=mesh.dtype)
        boundary_star = family(mu_star)
        reference_star = idw(boundary_star)
    return CaseContext(spec=spec, mesh=mesh, size=size, mesher=mesher, idw=idw, family=family,
                       mu_star=mu_star, boundary_star=boundary_star,
                       reference_star=reference_star, reference_quality=quality_summary(mesh),
                       mode=mode)


def selective_morph(
    context: CaseContext,
    radius: float | None = None,
    *,
    enrich: bool = True,
    a: float | None = None,
    b: float | None = None,
    seed: int = 0,
) -> MeshMorph:
    """SIDW (``enrich=False``) or ESIDW morph of the case for reference radius ``radius``.

    The selection's randomness comes from ``torch.Generator().manual_seed(seed)``.
    """
    plan = context.spec.plan(radius, enrich=enrich, a=a, b=b)
    generator = torch.Generator().manual_seed(int(seed))
    with torch.no_grad():
        return MeshMorph(context.mesh, plan, generator=generator, mode=context.mode)


@dataclass
class SelectionPoint:
    """One (R, a, b) point of a sensitivity study (SIDW or ESIDW against IDW at μ*).

    ``error`` is the relative error in the P1 mass-matrix norm, ``error_nodal`` in
    the nodal ℓ2 norm (the paper's reading).
    """

    radius: float
    a: float
    b: float
    enrich: bool
    controls: int
    selection_s: float
    assembly_s: float
    deformation_s: float
    error: float
    max_q: float
    mean_q: float
    inverted: int
    error_nodal: float | None = None

    @property
    def method(self) -> str:
        return "ESIDW" if self.enrich else "SIDW"


def selection_point(
    context: CaseContext,
    radius: float | None = None,
    *,
    enrich: bool = True,
    a: float | None = None,
    b: float | None = None,
    seed: int = 0,
    repeats: int = 3,
) -> SelectionPoint:
    """Select, assemble, morph μ* and measure: one point of Figs. 5–7, 10, 13.

    Returns
    -------
    SelectionPoint
        Number of control points, selection / assembly / deformation seconds
        (deformation: median of ``repeats`` morphs of μ*), relative L2 error
        against full IDW, max / mean Q and inverted tets of the morphed mesh.
    """
    spec = context.spec
    radius = spec.radius if radius is None else float(radius)
    a = spec.a if a is None else float(a)
    b = spec.b if b is None else float(b)
    morph = selective_morph(context, radius, enrich=enrich, a=a, b=b, seed=seed)
    with torch.no_grad():
        displacement = morph(context.boundary_star)
        seconds = _median_time(lambda: morph(context.family(context.mu_star)), repeats)
        summary = quality_summary(context.mesh, displacement)
        error = float(context.error(displacement))
        error_nodal = float(context.error_nodal(displacement))
    return SelectionPoint(radius=radius, a=a, b=b, enrich=enrich, controls=morph.num_controls,
                          selection_s=morph.selection_time, assembly_s=morph.assembly_time,
                          deformation_s=seconds, error=error,
                          max_q=summary["max_edge_ratio"], mean_q=summary["mean_edge_ratio"],
                          inverted=summary["num_inverted"], error_nodal=error_nodal)


def _progress(iterable, *, desc: str = "", show: bool = False):
    from tqdm.auto import tqdm

    return tqdm(iterable, desc=desc, disable=not show, leave=False)


def radius_sweep(
    context: CaseContext,
    radii: Sequence[float] | None = None,
    *,
    enrich: Sequence[bool] | None = None,
    seed: int = 0,
    repeats: int = 3,
    progress: bool = False,
) -> list[SelectionPoint]:
    """Sensitivity to the selection radius R (Figs. 5–6, 10, 13).

    Parameters
    ----------
    radii : sequence of float, optional
        Reference radii; default the case's :attr:`CaseSpec.sweep_radii`. The
        regions' radii follow R as :attr:`CaseSpec.sweep_note` says.
    enrich : sequence of bool, optional
        Variants to run: default SIDW and ESIDW for case A, ESIDW for B and C.
    """
    spec = context.spec
    radii = spec.sweep_radii if radii is None else tuple(radii)
    enrich = ((False, True) if spec.run_sidw else (True,)) if enrich is None else tuple(enrich)
    jobs = [(radius, flag) for flag in enrich for radius in radii]
    return [
        selection_point(context, radius, enrich=flag, seed=seed, repeats=repeats)
        for radius, flag in _progress(jobs, desc=f"{spec.letter}: R sweep", show=progress)
    ]


def factor_sweep(
    context: CaseContext,
    radius: float,
    factors: Sequence[float],
    *,
    enrich: bool = False,
    seed: int = 0,
    repeats: int = 3,
    progress: bool = False,
) -> list[SelectionPoint]:
    """Sensitivity to the annulus factor a with b = 1/a (Fig. 7; SIDW by default)."""
    return [
        selection_point(context, radius, enrich=enrich, a=a, b=1.0 / a, seed=seed,
                        repeats=repeats)
        for a in _progress(factors, desc=f"{context.spec.letter}: a sweep, R={radius:g}",
                           show=progress)
    ]


def _fit_pod(
    morph: MeshMorph,
    family: Callable[[Tensor], Tensor],
    parameters: Tensor,
    *,
    num_modes: int | None = None,
    online: str = "projection",
) -> PODReducer:
    from .pod import PODReducer

    reducer = PODReducer(energy_tolerance=ENERGY_TOLERANCE, num_modes=num_modes, online=online)
    return reducer.fit(morph, family=family, parameters=parameters, batched=True)


def pod_spectra(
    context: CaseContext,
    *,
    seed: int = 0,
    esidw: MeshMorph | None = None,
    count: int = 10,
) -> dict[str, Tensor]:
    """Normalised singular values σ_i/σ_1 of POD-IDW and POD-ESIDW (Figs. 14–16, left).

    Returns
    -------
    dict
        ``{"POD-IDW": (k,), "POD-ESIDW": (k,)}``, the first ``count`` values
        (fewer if the training set is smaller).
    """
    parameters = context.spec.training_parameters(seed, dtype=context.mesh.dtype)
    esidw = selective_morph(context, enrich=True, seed=seed) if esidw is None else esidw
    spectra = {}
    for name, morph in (("POD-IDW", context.idw), ("POD-ESIDW", esidw)):
        values = _fit_pod(morph, context.family, parameters).singular_values_
        spectra[name] = (values / values[0])[:count].cpu()
    return spectra


def pod_parameter_sweep(
    context: CaseContext,
    mus: Sequence[float] | Tensor,
    *,
    modes: Sequence[int] = (1, 2),
    seed: int = 0,
    esidw: MeshMorph | None = None,
) -> dict[str, Any]:
    """POD error and mesh quality as functions of μ (Fig. 16, centre and right).

    For each of POD-IDW and POD-ESIDW with each number of modes in ``modes``
    (trained on the case's training set), and for ESIDW itself: the relative
    L2 error against full IDW at every μ, and max/mean Q of the morphed mesh.

    Returns
    -------
    dict
        ``"mu"`` (B,), ``"error"`` (mass norm) and ``"error_nodal"`` {label: (B,)},
        ``"max_q"`` / ``"mean_q"``
        {label: (B,)}, ``"inverted"`` {label: (B,)}, labels like
        ``"POD-ESIDW, 2 modes"``, ``"ESIDW"``, ``"IDW"``.
    """
    spec = context.spec
    dtype = context.mesh.dtype
    mus = torch.as_tensor(mus, dtype=dtype)
    parameters = spec.training_parameters(seed, dtype=dtype)
    esidw = selective_morph(context, enrich=True, seed=seed) if esidw is None else esidw
    result: dict[str, Any] = {"mu": mus, "error": {}, "error_nodal": {}, "max_q": {},
                              "mean_q": {}, "inverted": {}}
    with torch.no_grad():
        boundary = context.family(mus)
        reference = context.idw(boundary)
        fields = {"IDW": reference, "ESIDW": esidw(boundary)}
        for name, morph in (("POD-IDW", context.idw), ("POD-ESIDW", esidw)):
            for count in modes:
                reducer = _fit_pod(morph, context.family, parameters, num_modes=count)
                label = f"{name}, {count} mode{'s' if count > 1 else ''}"
                fields[label] = reducer(boundary)
        for label, displacement in fields.items():
            if label != "IDW":
                result["error"][label] = relative_l2_error(context.mesh, displacement, reference,
                                                           norm="mass")
                result["error_nodal"][label] = relative_l2_error(context.mesh, displacement,
                                                                 reference, norm="nodal")
            deformed = context.mesh.points + displacement
            q = edge_ratio(deformed, context.mesh.tets)
            result["max_q"][label] = q.amax(-1)
            result["mean_q"][label] = q.mean(-1)
            result["inverted"][label] = inverted(context.mesh, displacement).sum(-1)
    return result


# --------------------------------------------------------------------------------------
# results
# --------------------------------------------------------------------------------------


@dataclass
class MethodResult:
    """Our row of Tables 4–6 for one method, at μ*.

    ``error`` is the relative error against full IDW in the P1 mass-matrix norm
    (L2(Ω) of the piecewise-linear field), ``error_nodal`` the same in the nodal
    ℓ2 norm, every node weighing the same — the paper's reading, since it defines
    Ω_h as the set of nodes (Section 2.3). ``offline_s`` is Algorithm 3's offline
    phase (selection + assembly + POD fit), ``fit_s`` the POD fit alone;
    ``error_range`` / ``error_nodal_range`` are the (min, max) errors over a sweep
    of D (case C's POD rows, as the paper reports for one mode).
    """

    method: str
    controls: int
    online_s: float
    error: float | None
    inverted: int
    max_q: float
    mean_q: float
    selection_s: float | None = None
    assembly_s: float | None = None
    offline_s: float | None = None
    fit_s: float | None = None
    modes: int | None = None
    error_range: tuple[float, float] | None = None
    error_nodal: float | None = None
    error_nodal_range: tuple[float, float] | None = None


@dataclass
class CaseResult:
    """Everything :func:`reproduce` measured for one case."""

    case: str
    letter: str
    title: str
    size: str
    mesher: str
    seed: int
    mu_star: float
    mesh: dict[str, Any]
    paper_mesh: PaperMesh
    rows: list[MethodResult]
    paper_rows: tuple[PaperRow, ...]
    quality_reference: dict[str, Any]
    quality_deformed: dict[str, dict[str, Any]]
    singular_values: dict[str, list[float]]
    mesh_table: int
    results_table: int
    files: list[str] = field(default_factory=list)
    variant: str = "paper"
    selection_note: str = ""

    def row(self, method: str) -> MethodResult:
        """Our row for ``method`` (KeyError naming the known methods otherwise)."""
        for row in self.rows:
            if row.method == method:
                return row
        raise KeyError(f"no method {method!r}; known: {', '.join(r.method for r in self.rows)}")

    def paper_row(self, method: str) -> PaperRow | None:
        for row in self.paper_rows:
            if row.method == method:
                return row
        return None

    def to_dict(self) -> dict[str, Any]:
        """Plain data (JSON-serialisable); :meth:`from_dict` reads it back."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> CaseResult:
        """A result from :meth:`to_dict`'s output (e.g. a ``results.json`` written by
        :func:`reproduce`)."""
        data = dict(data)
        rows = []
        for row in data["rows"]:
            row = dict(row)
            for key in ("error_range", "error_nodal_range"):
                if row.get(key) is not None:
                    row[key] = tuple(row[key])
            rows.append(MethodResult(**row))
        data["rows"] = rows
        data["paper_rows"] = tuple(PaperRow(**row) for row in data["paper_rows"])
        data["paper_mesh"] = PaperMesh(**data["paper_mesh"])
        return cls(**data)

    # ---------------------------------------------------------------- printing

    def mesh_lines(self, *, markdown: bool = False) -> list[str]:
        """The mesh table (Tables 1–3) beside the paper's, as text lines."""
        paper = self.paper_mesh
        q_ref = self.quality_reference
        rows = [
            ("tetrahedra", f"{self.mesh['tets']:,}", f"{paper.tets:,}"),
            ("nodes", f"{self.mesh['nodes']:,}", f"{paper.nodes:,}"),
            ("interior nodes", f"{self.mesh['interior']:,}", f"{paper.interior:,}"),
            ("boundary nodes", f"{self.mesh['boundary']:,}", f"{paper.boundary:,}"),
            ("max Q (reference)", f"{q_ref['max_edge_ratio']:.2f}", _opt(paper.max_q)),
            ("mean Q (reference)", f"{q_ref['mean_edge_ratio']:.2f}", _opt(paper.mean_q)),
        ]
        for method, summary in self.quality_deformed.items():
            paper_max = paper.max_q_deformed if method in ("IDW", "ESIDW") else None
            paper_mean = paper.mean_q_deformed if method in ("IDW", "ESIDW") else None
            rows.append((f"max Q ({method}, μ*)", f"{summary['max_edge_ratio']:.2f}",
                         _opt(paper_max)))
            rows.append((f"mean Q ({method}, μ*)", f"{summary['mean_edge_ratio']:.2f}",
                         _opt(paper_mean)))
            rows.append((f"inverted tets ({method}, μ*)", f"{summary['num_inverted']}", "–"))
        header = (f"Table {self.mesh_table}", "ours", "paper")
        return _format_table(header, rows, markdown=markdown)

    def result_lines(self, *, markdown: bool = False) -> list[str]:
        """The results table (Tables 4–6) beside the paper's, as text lines."""
        header = ("method", "controls", "paper", "offline [s]", "paper", "modes", "paper",
                  "online [s]", "paper", "paper/ours", "nodal error", "mass error", "paper",
                  "inverted", "max Q", "mean Q")
        rows = []
        for row in self.rows:
            paper = self.paper_row(row.method)
            error = "–" if row.error is None else _percent(row.error)
            if row.error_range is not None:
                error += f" ({_percent(row.error_range[0])}–{_percent(row.error_range[1])})"
            nodal = "–" if row.error_nodal is None else _percent(row.error_nodal)
            if row.error_nodal_range is not None:
                low, high = row.error_nodal_range
                nodal += f" ({_percent(low)}–{_percent(high)})"
            speedup = "–" if paper is None else f"{paper.online_s / row.online_s:,.0f}×"
            rows.append((
                row.method,
                f"{row.controls:,}", "–" if paper is None else f"{paper.controls:,}",
                _opt(row.offline_s, "{:.2f}"),
                "–" if paper is None else _opt(paper.offline_s, "{:.2f}"),
                _opt(row.modes, "{}"), "–" if paper is None else _opt(paper.modes, "{}"),
                _seconds(row.online_s), "–" if paper is None else f"{paper.online_s:g}",
                speedup, nodal, error, "–" if paper is None else paper.error,
                f"{row.inverted}", f"{row.max_q:.2f}", f"{row.mean_q:.3f}",
            ))
        return _format_table(header, rows, markdown=markdown)

    def timing_lines(self, *, markdown: bool = False) -> list[str]:
        """Selection, assembly and POD-fit seconds per method."""
        header = ("method", "selection [s]", "assembly [s]", "POD fit [s]", "offline [s]",
                  "online [s]")
        rows = [(row.method, _opt(row.selection_s, "{:.3f}"), _opt(row.assembly_s, "{:.3f}"),
                 _opt(row.fit_s, "{:.3f}"), _opt(row.offline_s, "{:.3f}"),
                 _seconds(row.online_s)) for row in self.rows]
        return _format_table(header, rows, markdown=markdown)

    def report(self) -> str:
        """All tables as one printable text."""
        title = (f"Case {self.letter} — {self.title} (size={self.size}, mesher={self.mesher}, "
                 f"seed={self.seed}, μ* = {self.mu_star:g}, variant={self.variant})")
        parts = [title]
        if self.selection_note:
            parts.append(f"Selection: {self.selection_note}")
        parts += ["", *self.mesh_lines(), "", f"Table {self.results_table}:",
                  *self.result_lines(),
                  "Errors against full IDW at μ*: 'nodal' in the nodal ℓ2 norm (the paper's "
                  "Ω_h = {x_i}: its reading), 'mass' in the P1 mass-matrix norm; "
                  "(a–b): min–max over D."]
        parts += ["", "Times:", *self.timing_lines()]
        if self.singular_values:
            parts += ["", "Normalised singular values σ_i/σ_1 (first 5):"]
            for name, values in self.singular_values.items():
                parts.append(f"  {name}: " + ", ".join(f"{v:.2e}" for v in values[:5]))
        return "\n".join(parts)


def _opt(value: Any, fmt: str = "{:.2f}") -> str:
    return "–" if value is None else fmt.format(value)


def _percent(value: float) -> str:
    if value == 0.0:
        return "0"
    if value < 1e-4:
        return f"{value:.1e}"
    return f"{100 * value:.2f} %"


def _seconds(value: float) -> str:
    return f"{value:.2e}" if value < 1e-3 else f"{value:.4f}"


def _format_table(header: Sequence[str], rows: Sequence[Sequence[str]], *,
                  markdown: bool = False) -> list[str]:
    if markdown:
        lines = ["| " + " | ".join(header) + " |",
                 "|" + "|".join("---" if i == 0 else "---:" for i in range(len(header))) + "|"]
        return lines + ["| " + " | ".join(row) + " |" for row in rows]
    widths = [max(len(str(cell)) for cell in column) for column in zip(header, *rows)]

    def line(cells: Sequence[str]) -> str:
        first = f"{cells[0]:<{widths[0]}}"
        return "  ".join([first, *(f"{c:>{w}}" for c, w in zip(cells[1:], widths[1:]))])

    return [line(header), "  ".join("-" * w for w in widths), *(line(row) for row in rows)]


# --------------------------------------------------------------------------------------
# reproduction
# --------------------------------------------------------------------------------------


def reproduce(
    case: str,
    *,
    size: str = "paper",
    out: str | Path | None = None,
    mesher: str = "gmsh",
    seed: int = 0,
    verbose: bool = True,
    repeats: int = 5,
    online: str = "projection",
    mode: str = "auto",
    variant: str | None = None,
    mesh: TetMesh | None = None,
) -> CaseResult:
    """Reproduce one of the paper's test cases: Tables 1–3 and 4–6 beside the paper's.

    Runs full IDW (every boundary node a control point: the reference), SIDW (case
    A), ESIDW, POD-IDW and POD-ESIDW (and, for case C, POD with 1 and 2 modes, whose
    one-mode errors are also given as a range over D as the paper does) with the
    paper's parameters; times one morph of μ* per method; measures the relative
    L2(Ω_h) error against IDW, the mesh quality and the inverted tetrahedra.

    Parameters
    ----------
    case : str
        ``"wing"``, ``"fluid-wing"``, ``"hull"`` (or ``"A"``, ``"B"``, ``"C"``).
    size : {"small", "paper"}
        Mesh size passed to :func:`data_gen.build`.
    out : str or Path, optional
        Output directory: ``reference.vtu`` (every method's displacement at μ*, the
        selected control points as flags, the quality Q per tet),
        ``deformed_<method>.vtu`` (IDW and ESIDW), ``<case>.png`` (sections of the
        reference and deformed mesh) and ``results.json``.
    mesher : {"gmsh", "pytetwild"}
    seed : int
        Seeds the random start points / choices of the selection and the training
        set.
    verbose : bool
        Progress bars and printed tables.
    repeats : int
        Timed repeats of every online morph (median, after one warm-up).
    online : {"projection", "paper"}
        POD online variant (:class:`~torchmorph.pod.PODReducer`).
    mode : {"auto", "dense", "matrix_free"}
        IDW storage mode.
    variant : str, optional
        The selection set-up: ``"paper"`` (default), the one that reproduces the
        paper's figures, or a documented alternative of :data:`VARIANTS` (case C:
        ``"uniform"``, R = 1.5 m on every wall and on the hull as printed).
    mesh : TetMesh, optional
        Use this mesh (with the case's node sets) instead of building or loading
        one; ``size`` and ``mesher`` are then only labels.

    Returns
    -------
    CaseResult

    Raises
    ------
    ImportError
        If the mesh has to be generated and gmsh / data_gen are missing.
    """
    from tqdm.auto import tqdm

    spec = get_case(case, variant)
    # mesh, IDW, [SIDW], ESIDW, POD-IDW, POD-ESIDW, [4 fixed-mode PODs], [writing]
    steps = 5 + int(spec.run_sidw) + (4 if spec.key == "hull" else 0) + int(out is not None)
    bar = tqdm(total=steps, desc=f"case {spec.letter}", disable=not verbose,
               bar_format="{l_bar}{bar}| {n_fmt}/{total_fmt} [{elapsed}] {postfix}")

    def step(text: str) -> None:
        bar.set_postfix_str(text)

    step("mesh (meshing a new mesh takes seconds to minutes)")
    if mesh is None:
        mesh = _load_mesh_ticking(spec, size=size, mesher=mesher, bar=bar)
    bar.update()
    step("IDW")
    context = prepare_case(spec, size=size, mesher=mesher, mesh=mesh, mode=mode)
    family, mu_star = context.family, context.mu_star
    parameters = spec.training_parameters(seed, dtype=mesh.dtype)

    rows: list[MethodResult] = []
    fields: dict[str, Tensor] = {}
    morphs: dict[str, MeshMorph] = {"IDW": context.idw}
    spectra: dict[str, list[float]] = {}

    def add_row(method: str, morph: MeshMorph, apply: Callable[[Tensor], Tensor], *,
                reducer: PODReducer | None = None, error_range=None,
                error_nodal_range=None) -> None:
        with torch.no_grad():
            displacement = apply(context.boundary_star)
            online_s = _median_time(lambda: apply(family(mu_star)), repeats)
            summary = quality_summary(mesh, displacement)
            error = error_nodal = None
            if method != "IDW":
                error = float(context.error(displacement))
                error_nodal = float(context.error_nodal(displacement))
        fields[method] = displacement
        selection_s = None if method == "IDW" else morph.selection_time
        fit_s = offline_s = None
        if reducer is not None:
            fit_s = reducer.offline_time_["total"]
            offline_s = morph.selection_time + morph.assembly_time + fit_s
        rows.append(MethodResult(
            method=method, controls=morph.num_controls, online_s=online_s, error=error,
            inverted=summary["num_inverted"], max_q=summary["max_edge_ratio"],
            mean_q=summary["mean_edge_ratio"], selection_s=selection_s,
            assembly_s=morph.assembly_time, offline_s=offline_s, fit_s=fit_s,
            modes=None if reducer is None else reducer.num_modes_, error_range=error_range,
            error_nodal=error_nodal, error_nodal_range=error_nodal_range))

    add_row("IDW", context.idw, context.idw)
    bar.update()
    if spec.run_sidw:
        step("SIDW")
        morphs["SIDW"] = selective_morph(context, enrich=False, seed=seed)
        add_row("SIDW", morphs["SIDW"], morphs["SIDW"])
        bar.update()
    step("ESIDW")
    morphs["ESIDW"] = esidw = selective_morph(context, enrich=True, seed=seed)
    add_row("ESIDW", esidw, esidw)
    bar.update()

    sweep = None
    if spec.key == "hull":  # the paper gives the one-mode errors over a range of angles
        low, high = spec.domain
        sweep = torch.arange(math.ceil(low), math.floor(high), 1.0, dtype=mesh.dtype)
        sweep = sweep[sweep != 0]
        with torch.no_grad():
            sweep_boundary = family(sweep)
            sweep_reference = context.idw(sweep_boundary)
    for name, morph in (("POD-IDW", context.idw), ("POD-ESIDW", esidw)):
        step(name)
        reducer = _fit_pod(morph, family, parameters, online=online)
        spectra[name] = (reducer.singular_values_ / reducer.singular_values_[0])[:10].tolist()
        add_row(name, morph, reducer, reducer=reducer)
        bar.update()
        if sweep is None:
            continue
        for count in (1, 2):
            label = f"{name} ({count} mode{'s' if count > 1 else ''})"
            step(label)
            fixed = _fit_pod(morph, family, parameters, num_modes=count, online=online)
            with torch.no_grad():
                reduced = fixed(sweep_boundary)
                errors = relative_l2_error(mesh, reduced, sweep_reference, norm="mass")
                nodal = relative_l2_error(mesh, reduced, sweep_reference, norm="nodal")
            add_row(label, morph, fixed, reducer=fixed,
                    error_range=(float(errors.min()), float(errors.max())),
                    error_nodal_range=(float(nodal.min()), float(nodal.max())))
            bar.update()

    quality_deformed = {
        row.method: {"max_edge_ratio": row.max_q, "mean_edge_ratio": row.mean_q,
                     "num_inverted": row.inverted}
        for row in rows if row.method in ("IDW", "ESIDW")
    }
    result = CaseResult(
        case=spec.key, letter=spec.letter, title=spec.title, size=size, mesher=mesher,
        seed=int(seed), mu_star=spec.mu_star,
        mesh=_mesh_figures(mesh, context.reference_quality), paper_mesh=spec.paper_mesh,
        rows=rows, paper_rows=spec.paper_rows, quality_reference=context.reference_quality,
        quality_deformed=quality_deformed, singular_values=spectra,
        mesh_table=spec.mesh_table, results_table=spec.results_table,
        variant=spec.variant, selection_note=spec.selection_note,
    )
    if out is not None:
        step("writing")
        result.files = [str(path) for path in _write_outputs(Path(out), context, morphs, fields,
                                                             result)]
        bar.update()
    bar.close()
    if verbose:
        print(result.report())
        if result.files:
            print("\nWrote: " + ", ".join(result.files))
    return result


# --------------------------------------------------------------------------------------
# output files
# --------------------------------------------------------------------------------------


def _file_label(method: str) -> str:
    return method.lower().replace(" ", "_").replace("(", "").replace(")", "").replace("-", "_")


def _write_outputs(out: Path, context: CaseContext, morphs: dict[str, MeshMorph],
                   fields: dict[str, Tensor], result: CaseResult) -> list[Path]:
    from .io import write_mesh

    out.mkdir(parents=True, exist_ok=True)
    mesh = context.mesh
    files = []
    point_data: dict[str, Any] = {}
    for method, displacement in fields.items():
        if "mode" in method:
            continue
        point_data[f"displacement_{method}"] = displacement
    for method, morph in morphs.items():
        if method == "IDW":
            continue
        flags = torch.zeros(mesh.num_nodes, dtype=torch.uint8)
        flags[morph.control_nodes.cpu()] = 1
        point_data[f"control_{method}"] = flags
    boundary = torch.zeros(mesh.num_nodes, dtype=torch.uint8)
    boundary[mesh.boundary_nodes.cpu()] = 1
    point_data["boundary"] = boundary
    path = out / "reference.vtu"
    write_mesh(path, mesh, point_data=point_data,
               cell_data={"Q": edge_ratio(mesh.points, mesh.tets)})
    files.append(path)
    for method in ("IDW", "ESIDW"):
        displacement = fields[method]
        moved = mesh.deformed(displacement)
        path = out / f"deformed_{_file_label(method)}.vtu"
        point_data = {"displacement": displacement}
        if method != "IDW":
            point_data["difference_from_IDW"] = displacement - fields["IDW"]
        write_mesh(path, moved, point_data=point_data,
                   cell_data={"Q": edge_ratio(moved.points, mesh.tets),
                              "inverted": (moved.volumes <= 0).to(torch.uint8)})
        files.append(path)
    path = out / f"{context.spec.key}.png"
    plot_case(context, fields, morphs, path)
    files.append(path)
    path = out / "results.json"
    path.write_text(json.dumps(result.to_dict(), indent=2, default=_json_default))
    files.append(path)
    return files


def _json_default(value: Any) -> Any:
    if isinstance(value, Tensor):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"not serialisable: {type(value).__name__}")


_TET_EDGES = np.array(((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)))


def plane_section(
    points: np.ndarray | Tensor,
    tets: np.ndarray | Tensor,
    axis: int,
    value: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Cut a tetrahedral mesh by the plane ``x[axis] = value``.

    Parameters
    ----------
    points : array, shape (N, 3)
    tets : array, shape (M, 4)
    axis : int
        0, 1 or 2.
    value : float
        Position of the plane. Nodes exactly on the plane count as lying on its
        positive side.

    Returns
    -------
    cut : array of int, shape (K,)
        Indices of the tetrahedra the plane crosses.
    first, second : arrays of int, shape (K, 4)
        End nodes of the (up to four) crossed edges of each cut tetrahedron, in
        polygon order; a triangle repeats its last vertex.
    weight : array of float, shape (K, 4)
        Position along each edge: the polygon's vertices are
        ``(1 - weight) * x[first] + weight * x[second]`` for the reference points
        ``x`` — and, applied to moved points, follow the mesh as it deforms.
    """
    points = points.detach().cpu().numpy() if isinstance(points, Tensor) else np.asarray(points)
    tets = tets.detach().cpu().numpy() if isinstance(tets, Tensor) else np.asarray(tets)
    side = points[:, axis] - value
    side = np.where(side == 0.0, np.finfo(np.float64).tiny, side)
    per_tet = side[tets]
    cut = np.flatnonzero((per_tet.min(1) < 0) & (per_tet.max(1) > 0))
    corners = tets[cut]
    sides = per_tet[cut]
    first = corners[:, _TET_EDGES[:, 0]]
    second = corners[:, _TET_EDGES[:, 1]]
    s_first = sides[:, _TET_EDGES[:, 0]]
    s_second = sides[:, _TET_EDGES[:, 1]]
    crossed = s_first * s_second < 0
    weight = np.where(crossed, s_first / np.where(crossed, s_first - s_second, 1.0), 0.0)
    vertices = (1 - weight)[..., None] * points[first] + weight[..., None] * points[second]
    plane_axes = [i for i in range(3) if i != axis]
    flat = vertices[..., plane_axes]
    centre = (flat * crossed[..., None]).sum(1) / crossed.sum(1, keepdims=True)
    angle = np.arctan2(flat[..., 1] - centre[:, 1:2], flat[..., 0] - centre[:, 0:1])
    angle = np.where(crossed, angle, np.inf)
    order = np.argsort(angle, axis=1)[:, :4]
    take = np.take_along_axis
    first, second, weight = (take(a, order, 1) for a in (first, second, weight))
    count = crossed.sum(1)
    triangle = count == 3
    for array in (first, second, weight):
        array[triangle, 3] = array[triangle, 2]
    return cut, first, second, weight


def _section_polygons(points: np.ndarray, first, second, weight, plane_axes) -> np.ndarray:
    vertices = (1 - weight)[..., None] * points[first] + weight[..., None] * points[second]
    return vertices[..., plane_axes]


def plot_case(
    context: CaseContext,
    fields: dict[str, Tensor],
    morphs: dict[str, MeshMorph],
    path: str | Path,
) -> Path:
    """PNG of the reference and ESIDW-deformed geometry at μ*.

    Wing cases: the section of the mesh at mid-span (z = π), reference and
    deformed, coloured by the displacement magnitude, and a side view (z–y) of
    the wing's boundary nodes before and after. Hull: the section z = 0 (the
    hull's centre plane, x–y) around the hull, reference and deformed, and the
    hull's profile (its edge nodes) before and after the rotation.
    """
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        from matplotlib.collections import PolyCollection
    except ImportError as error:  # pragma: no cover - matplotlib is a test dependency
        raise ImportError("plots need matplotlib: pip install 'torchmorph[plot]'") from error

    spec, mesh = context.spec, context.mesh
    points = mesh.points.detach().cpu().numpy()
    tets = mesh.tets.cpu().numpy()
    displacement = fields["ESIDW"].detach().cpu().numpy()
    moved = points + displacement
    magnitude = np.linalg.norm(displacement, axis=1)
    hull = spec.key == "hull"
    if hull:
        axis, value, plane_axes = 2, 1e-6, (0, 1)
        window = ((-2.5, 2.5), (-1.2, 1.2))
        labels = ("x [m]", "y [m]")
    else:  # mid-span of the wing (span 2π from the root z = 0)
        axis, value, plane_axes = 2, math.pi, (0, 1)
        if spec.key == "fluid-wing":
            window = ((-0.5, 1.5), (-0.45, 0.6))
        else:
            window = ((-0.1, 1.1), (-0.2, 0.35))
        labels = ("x [m]", "y [m]")
    _, first, second, weight = plane_section(points, tets, axis, value)
    shade = ((1 - weight) * magnitude[first] + weight * magnitude[second]).mean(1)
    reference = _section_polygons(points, first, second, weight, list(plane_axes))
    deformed = _section_polygons(moved, first, second, weight, list(plane_axes))

    fluid = spec.key == "fluid-wing"
    if fluid:  # the whole tunnel section, then a zoom on the wing
        box = mesh.points[mesh.nodes_of([f"wall_{a}{s}" for a in "xy" for s in "01"])]
        low, high = box.amin(0).tolist(), box.amax(0).tolist()
        window, zoom = ((low[0], high[0]), (low[1], high[1])), ((-0.3, 1.3), (-0.3, 0.45))
    figure, axes = plt.subplots(1, 4 if fluid else 3, figsize=(21 if fluid else 16, 4.6),
                                constrained_layout=True)
    where = f"z = {value:.3g} m" if not hull else "z = 0 (hull centre plane)"
    mu_text = f"{spec.parameter}* = {spec.mu_star:g}{spec.unit}"

    def section_panel(ax, polygons, colour, title, limits):
        if colour is not None:  # the reference section underneath, faint, to show the motion
            ax.add_collection(PolyCollection(list(reference), linewidths=0.3, facecolors="none",
                                             edgecolors="0.75", zorder=0))
        collection = PolyCollection(list(polygons), linewidths=0.3, edgecolors="0.35")
        if colour is None:
            collection.set_facecolor("white")
        else:
            collection.set_array(colour)
            collection.set_cmap("viridis")
            collection.set_clim(0.0, float(colour.max()) if colour.size else 1.0)
            collection.set_alpha(0.85)
        ax.add_collection(collection)
        ax.set_xlim(*limits[0])
        ax.set_ylim(*limits[1])
        ax.set_aspect("equal")
        ax.set_xlabel(labels[0])
        ax.set_ylabel(labels[1])
        ax.set_title(title, fontsize=10)
        return collection

    section_panel(axes[0], reference, None, f"reference mesh, section {where}", window)
    coloured = section_panel(axes[1], deformed, shade,
                             f"ESIDW deformed, {mu_text} (grey: reference)", window)
    figure.colorbar(coloured, ax=axes[1], shrink=0.8, label="|displacement| [m]")
    if fluid:
        section_panel(axes[2], deformed, shade, f"ESIDW deformed, {mu_text}, near the wing",
                      zoom)

    ax = axes[-1]
    if hull:
        # the hull's centre-plane profile is the rectangle |x| <= L/2, |y| <= T
        hull_points = points[mesh.node_set("hull").cpu().numpy()]
        (x0, y0), (x1, y1) = hull_points[:, :2].min(0), hull_points[:, :2].max(0)
        outline = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1], [x0, y0]])
        angle = math.radians(spec.mu_star)
        rotation = np.array([[math.cos(angle), -math.sin(angle)],
                             [math.sin(angle), math.cos(angle)]])
        centre = np.asarray(HULL_CENTRE[:2])
        rotated = (outline - centre) @ rotation.T + centre
        bow = ((x1 - 0.6, x1 + 0.5), (-0.45, 0.4))
        section_panel(ax, deformed, shade, f"bow, ESIDW deformed, {mu_text}", bow)
        for target in (axes[1], ax):
            target.plot(*outline.T, "--", color="0.3", lw=1.0, label="hull profile, reference")
            target.plot(*rotated.T, "-", color="C3", lw=1.2,
                        label=f"hull profile rotated by {spec.mu_star:g}°")
        axes[1].plot([centre[0]], [centre[1]], "k+", ms=8, label="rotation centre")
        ax.legend(loc="lower left", fontsize=7)
    else:
        wing = mesh.node_set("wing").cpu().numpy()
        wing = wing[:: max(1, len(wing) // 3000)]  # enough dots to see the shape
        ax.plot(points[wing, 2], points[wing, 1], ".", ms=1.5, color="0.6", label="reference")
        ax.plot(moved[wing, 2], moved[wing, 1], ".", ms=1.5, color="C0",
                label=f"deformed, {mu_text}")
        ax.axvline(value, color="C3", lw=0.8, ls="--", label="section")
        ax.set_xlabel("z (span) [m]")
        ax.set_ylabel("y [m]")
        ax.set_title("side view of the wing (boundary nodes)", fontsize=10)
        ax.legend(loc="upper left", fontsize=8, markerscale=4)
    figure.suptitle(f"Case {spec.letter}: {spec.title} ({context.size} mesh, "
                    f"{mesh.num_nodes:,} nodes)")
    path = Path(path)
    figure.savefig(path, dpi=90)
    plt.close(figure)
    return path
