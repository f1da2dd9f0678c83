"""The reproduction of one of the paper's test cases (its Tables 1–6): :func:`reproduce`
runs the experiments of :mod:`torchmorph.paper.experiments` and writes the report of
:mod:`torchmorph.paper.reports`."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from torchmorph.idw import Mode
from torchmorph.mesh.norms import relative_l2_error
from torchmorph.mesh.quality import quality_summary
from torchmorph.mesh.tetmesh import TetMesh
from torchmorph.morph import MeshMorph
from torchmorph.paper.cases import get_case, load_mesh_ticking
from torchmorph.paper.experiments import (
    adaptive_morph,
    fit_pod,
    median_seconds,
    mesh_figures,
    prepare_case,
    selective_morph,
)
from torchmorph.paper.reports import CaseResult, MethodResult, write_outputs

if TYPE_CHECKING:
    from torchmorph.pod.reducer import OnlineVariant, PODReducer

__all__ = ["reproduce"]


def reproduce(
    case: str,
    *,
    size: str = "paper",
    out: str | Path | None = None,
    mesher: str = "gmsh",
    seed: int = 0,
    verbose: bool = True,
    repeats: int = 5,
    online: OnlineVariant = "projection",
    mode: Mode = "auto",
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
        ``"uniform"``, R = 1.5 m on every wall and on the hull as printed; every case:
        ``"adaptive"``, rows "adaptive" and "POD-adaptive" of error-driven controls at
        the paper's ESIDW error, :func:`~torchmorph.paper.experiments.adaptive_morph`).
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
    adaptive = spec.variant == "adaptive"
    steps += (4 if spec.key == "hull" else 2) if adaptive else 0
    bar = tqdm(
        total=steps,
        desc=f"case {spec.letter}",
        disable=not verbose,
        bar_format="{l_bar}{bar}| {n_fmt}/{total_fmt} [{elapsed}] {postfix}",
    )

    def step(text: str) -> None:
        bar.set_postfix_str(text)

    step("mesh (meshing a new mesh takes seconds to minutes)")
    if mesh is None:
        mesh = load_mesh_ticking(spec, size=size, mesher=mesher, bar=bar)
    bar.update()
    step("IDW")
    context = prepare_case(spec, size=size, mesher=mesher, mesh=mesh, mode=mode)
    family, mu_star = context.family, context.mu_star
    parameters = spec.training_parameters(seed, dtype=mesh.dtype)

    rows: list[MethodResult] = []
    fields: dict[str, Tensor] = {}
    morphs: dict[str, MeshMorph] = {"IDW": context.idw}
    spectra: dict[str, list[float]] = {}

    def add_row(
        method: str,
        morph: MeshMorph,
        apply: Callable[[Tensor], Tensor],
        *,
        reducer: PODReducer | None = None,
        error_range=None,
        error_nodal_range=None,
    ) -> None:
        with torch.no_grad():
            displacement = apply(context.boundary_star)
            online_s = median_seconds(lambda: apply(family(mu_star)), repeats)
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
        rows.append(
            MethodResult(
                method=method,
                controls=morph.num_controls,
                online_s=online_s,
                error=error,
                inverted=int(summary["num_inverted"]),
                max_q=summary["max_edge_ratio"],
                mean_q=summary["mean_edge_ratio"],
                selection_s=selection_s,
                assembly_s=morph.assembly_time,
                offline_s=offline_s,
                fit_s=fit_s,
                modes=None if reducer is None else reducer.num_modes_,
                error_range=error_range,
                error_nodal=error_nodal,
                error_nodal_range=error_nodal_range,
            )
        )

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
    if adaptive:
        step("adaptive (error-driven controls)")
        morphs["adaptive"] = adaptive_morph(context, parameters)
        add_row("adaptive", morphs["adaptive"], morphs["adaptive"])
        bar.update()

    sweep = None
    if spec.key == "hull":  # the paper gives the one-mode errors over a range of angles
        low, high = spec.domain
        sweep = torch.arange(math.ceil(low), math.floor(high), 1.0, dtype=mesh.dtype)
        sweep = sweep[sweep != 0]
        with torch.no_grad():
            sweep_boundary = family(sweep)
            sweep_reference = context.idw(sweep_boundary)
    pods = [("POD-IDW", context.idw), ("POD-ESIDW", esidw)]
    if adaptive:
        pods.append(("POD-adaptive", morphs["adaptive"]))
    for name, morph in pods:
        step(name)
        reducer = fit_pod(morph, family, parameters, online=online)
        spectra[name] = (reducer.singular_values_ / reducer.singular_values_[0])[:10].tolist()
        add_row(name, morph, reducer, reducer=reducer)
        bar.update()
        if sweep is None:
            continue
        for count in (1, 2):
            label = f"{name} ({count} mode{'s' if count > 1 else ''})"
            step(label)
            fixed = fit_pod(morph, family, parameters, num_modes=count, online=online)
            with torch.no_grad():
                reduced = fixed(sweep_boundary)
                errors = relative_l2_error(mesh, reduced, sweep_reference, norm="mass")
                nodal = relative_l2_error(mesh, reduced, sweep_reference, norm="nodal")
            add_row(
                label,
                morph,
                fixed,
                reducer=fixed,
                error_range=(float(errors.min()), float(errors.max())),
                error_nodal_range=(float(nodal.min()), float(nodal.max())),
            )
            bar.update()

    quality_deformed = {
        row.method: {
            "max_edge_ratio": row.max_q,
            "mean_edge_ratio": row.mean_q,
            "num_inverted": row.inverted,
        }
        for row in rows
        if row.method in ("IDW", "ESIDW")
    }
    result = CaseResult(
        case=spec.key,
        letter=spec.letter,
        title=spec.title,
        size=size,
        mesher=mesher,
        seed=int(seed),
        mu_star=spec.mu_star,
        mesh=mesh_figures(mesh, context.reference_quality),
        paper_mesh=spec.paper_mesh,
        rows=rows,
        paper_rows=spec.paper_rows,
        quality_reference=context.reference_quality,
        quality_deformed=quality_deformed,
        singular_values=spectra,
        mesh_table=spec.mesh_table,
        results_table=spec.results_table,
        variant=spec.variant,
        selection_note=spec.selection_note,
    )
    if out is not None:
        step("writing")
        result.files = [
            str(path) for path in write_outputs(Path(out), context, morphs, fields, result)
        ]
        bar.update()
    bar.close()
    if verbose:
        print(result.report())
        if result.files:
            print("\nWrote: " + ", ".join(result.files))
    return result
