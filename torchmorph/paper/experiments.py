"""Experiments on the paper's cases: the reference IDW, selective morphs and the
sensitivity sweeps (Figs. 5–7, 10, 13–16); :mod:`torchmorph.paper.reproduce` runs
Tables 1–6 on them."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from torchmorph._timing import median_time
from torchmorph.idw import Mode
from torchmorph.idw.module import auto_mode
from torchmorph.mesh.norms import relative_l2_error
from torchmorph.mesh.quality import edge_ratio, inverted, quality_summary
from torchmorph.mesh.tetmesh import TetMesh, box_mesh
from torchmorph.morph import MeshMorph
from torchmorph.paper.cases import (
    ENERGY_TOLERANCE,
    CaseSpec,
    get_case,
    load_mesh,
)

if TYPE_CHECKING:
    from torchmorph.pod.reducer import OnlineVariant, PODReducer

__all__ = [
    "CaseContext",
    "SelectionPoint",
    "adaptive_morph",
    "factor_sweep",
    "pod_parameter_sweep",
    "pod_spectra",
    "prepare_case",
    "radius_sweep",
    "selection_point",
    "selective_morph",
]

# --------------------------------------------------------------------------------------
# meshes
# --------------------------------------------------------------------------------------


def mesh_figures(mesh: TetMesh, summary: dict[str, Any]) -> dict[str, Any]:
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


def median_seconds(function: Callable[[], Any], repeats: int) -> float:
    """Median wall-clock seconds of ``repeats`` calls after one warm-up call."""
    return median_time(function, max(1, int(repeats)))


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
        :func:`~torchmorph.mesh.quality.quality_summary` of the reference mesh.
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
    mode: Mode = "auto"

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
    mode: Mode = "auto",
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
        IDW storage mode of every morph made from this context; "auto" stores W where
        it fits in float64, as Algorithm 2 does (:func:`torchmorph.idw.module.auto_mode`
        with the torch implementation).
    verbose : bool
        Print data_gen's progress.
    """
    spec = get_case(case)
    if mesh is None:
        mesh = load_mesh(spec, size=size, mesher=mesher, verbose=verbose)
    if mode == "auto":  # Algorithm 2 stores W in its selection phase: so do we, where it fits
        mode = auto_mode(
            len(mesh.interior_nodes),
            len(mesh.boundary_nodes),
            dtype=mesh.dtype,
            device=mesh.device,
            implementation="torch",
        )
    with torch.no_grad():
        # a small morph first loads the kernels (numba's compiled cache) once, so that the
        # assembly times reported below are the assembly's alone
        warm = MeshMorph(box_mesh(2).to(mesh.device, mesh.dtype), mode=mode)
        warm(torch.zeros(warm.num_boundary, 3, dtype=mesh.dtype, device=mesh.device))
        idw = MeshMorph(mesh, mode=mode)
        family = spec.family(idw)
        mu_star = torch.tensor(spec.mu_star, dtype=mesh.dtype)
        boundary_star = family(mu_star)
        reference_star = idw(boundary_star)
    return CaseContext(
        spec=spec,
        mesh=mesh,
        size=size,
        mesher=mesher,
        idw=idw,
        family=family,
        mu_star=mu_star,
        boundary_star=boundary_star,
        reference_star=reference_star,
        reference_quality=quality_summary(mesh),
        mode=mode,
    )


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


def adaptive_morph(
    context: CaseContext, parameters: Tensor, *, tolerance: float | None = None
) -> MeshMorph:
    """The morph of error-driven controls (:class:`~torchmorph.selection.AdaptivePlan`).

    The family that drives the selection is the boundary displacement at μ* and at
    every training value ``parameters`` (the POD snapshots); the tolerance defaults to
    the paper's ESIDW error of the case.
    """
    from torchmorph.selection.plan import AdaptivePlan

    if tolerance is None:
        row = context.spec.paper_row("ESIDW")
        assert row is not None and row.error_value is not None
        tolerance = row.error_value
    with torch.no_grad():
        family = torch.cat([context.boundary_star[None], context.family(parameters)])
        plan = AdaptivePlan(tolerance, family)
        return MeshMorph(context.mesh, plan, mode=context.mode)


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
        seconds = median_seconds(lambda: morph(context.family(context.mu_star)), repeats)
        summary = quality_summary(context.mesh, displacement)
        error = float(context.error(displacement))
        error_nodal = float(context.error_nodal(displacement))
    return SelectionPoint(
        radius=radius,
        a=a,
        b=b,
        enrich=enrich,
        controls=morph.num_controls,
        selection_s=morph.selection_time,
        assembly_s=morph.assembly_time,
        deformation_s=seconds,
        error=error,
        max_q=summary["max_edge_ratio"],
        mean_q=summary["mean_edge_ratio"],
        inverted=int(summary["num_inverted"]),
        error_nodal=error_nodal,
    )


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
        selection_point(context, radius, enrich=enrich, a=a, b=1.0 / a, seed=seed, repeats=repeats)
        for a in _progress(
            factors, desc=f"{context.spec.letter}: a sweep, R={radius:g}", show=progress
        )
    ]


def fit_pod(
    morph: MeshMorph,
    family: Callable[[Tensor], Tensor],
    parameters: Tensor,
    *,
    num_modes: int | None = None,
    online: OnlineVariant = "projection",
) -> PODReducer:
    from torchmorph.pod.reducer import PODReducer

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
        values = fit_pod(morph, context.family, parameters).singular_values_
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
    result: dict[str, Any] = {
        "mu": mus,
        "error": {},
        "error_nodal": {},
        "max_q": {},
        "mean_q": {},
        "inverted": {},
    }
    with torch.no_grad():
        boundary = context.family(mus)
        reference = context.idw(boundary)
        fields = {"IDW": reference, "ESIDW": esidw(boundary)}
        for name, morph in (("POD-IDW", context.idw), ("POD-ESIDW", esidw)):
            for count in modes:
                reducer = fit_pod(morph, context.family, parameters, num_modes=count)
                label = f"{name}, {count} mode{'s' if count > 1 else ''}"
                fields[label] = reducer(boundary)
        for label, displacement in fields.items():
            if label != "IDW":
                result["error"][label] = relative_l2_error(
                    context.mesh, displacement, reference, norm="mass"
                )
                result["error_nodal"][label] = relative_l2_error(
                    context.mesh, displacement, reference, norm="nodal"
                )
            deformed = context.mesh.points + displacement
            q = edge_ratio(deformed, context.mesh.tets)
            result["max_q"][label] = q.amax(-1)
            result["mean_q"][label] = q.mean(-1)
            result["inverted"][label] = inverted(context.mesh, displacement).sum(-1)
    return result
