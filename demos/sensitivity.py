"""The paper's sensitivity studies as PNG figures.

For each case asked for (``--cases``, default all three):

- ``<case>_radius.png``: number of control points, assembly / deformation time,
  relative error against IDW (P1 mass-matrix norm) and max / mean Q of the deformed mesh as
  functions of the selection radius R (Figs. 5–6 for case A with SIDW and ESIDW,
  Fig. 10 for case B — box R, left/right walls 0.5 R, wing 0.1 R — and Fig. 13 for
  case C, ESIDW with one R on every wall and on the hull, the "uniform" variant);
- case A: ``wing_factor.png``, control points and error of SIDW as functions of a
  with b = 1/a for R = 0.02, 0.05, 0.2, 0.3 (Fig. 7);
- ``spectra.png``: the normalised singular values σ_i/σ_1 of POD-IDW and POD-ESIDW
  (Figs. 14–16, left), one panel per case;
- case C: ``hull_angle.png``, the POD error against the rotation angle with one and
  two modes, and the mesh quality (Fig. 16, centre and right).

The numbers go to ``sensitivity.json`` beside the figures::

    python demos/sensitivity.py --size small --out out/sensitivity
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from torchmorph._atomic import atomic_output
from torchmorph.paper import (
    CaseContext,
    SelectionPoint,
    factor_sweep,
    get_case,
    pod_parameter_sweep,
    pod_spectra,
    prepare_case,
    radius_sweep,
    selective_morph,
)

#: Radii of Fig. 7 (case A) and the annulus factors a (b = 1/a) swept for each.
FACTOR_RADII = (0.02, 0.05, 0.2, 0.3)
FACTORS = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 0.95)


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _series(points: list[SelectionPoint], enrich: bool) -> dict[str, list[float]]:
    chosen = [p for p in points if p.enrich == enrich]
    return {
        key: [getattr(p, key) for p in chosen]
        for key in (
            "radius",
            "a",
            "controls",
            "assembly_s",
            "deformation_s",
            "selection_s",
            "error",
            "max_q",
            "mean_q",
            "inverted",
        )
    }


def plot_radius(context: CaseContext, points: list[SelectionPoint], path: Path) -> None:
    """Figs. 5–6 / 10 / 13: controls, times, error and quality against R."""
    plt = _pyplot()
    spec = context.spec
    figure, axes = plt.subplots(1, 4, figsize=(18, 4.2), constrained_layout=True)
    styles = {False: ("SIDW", "o", "C1"), True: ("ESIDW", "s", "C0")}
    for enrich in sorted({p.enrich for p in points}):
        label, marker, colour = styles[enrich]
        s = _series(points, enrich)
        r = s["radius"]
        axes[0].plot(r, s["controls"], marker=marker, color=colour, label=label)
        axes[1].plot(r, s["assembly_s"], marker=marker, color=colour, label=f"{label}: assembly")
        axes[1].plot(
            r,
            s["deformation_s"],
            marker=marker,
            color=colour,
            alpha=0.6,
            ls="--",
            label=f"{label}: deformation",
        )
        total = [a + d for a, d in zip(s["assembly_s"], s["deformation_s"], strict=True)]
        axes[1].plot(
            r, total, marker=marker, color=colour, alpha=0.35, ls=":", label=f"{label}: total"
        )
        axes[2].plot(r, s["error"], marker=marker, color=colour, label=label)
        axes[3].plot(r, s["max_q"], marker=marker, color=colour, label=f"{label}: max Q")
        axes[3].plot(
            r,
            s["mean_q"],
            marker=marker,
            color=colour,
            alpha=0.6,
            ls="--",
            label=f"{label}: mean Q",
        )
        for radius, max_q, count in zip(r, s["max_q"], s["inverted"], strict=True):
            if count:  # a mesh with inverted tets: say how many
                axes[3].annotate(
                    f"{count} inv.",
                    (radius, max_q),
                    textcoords="offset points",
                    xytext=(-4, 4),
                    ha="right",
                    fontsize=7,
                    color=colour,
                )
    boundary = context.idw.num_controls
    axes[0].axhline(boundary, color="0.5", ls=":", label=f"IDW ({boundary})")
    reference = context.reference_quality
    axes[3].axhline(reference["max_edge_ratio"], color="0.5", ls=":", label="reference max Q")
    axes[3].axhline(reference["mean_edge_ratio"], color="0.5", ls="-.", label="reference mean Q")
    titles = (
        "control points",
        "CPU time [s]",
        "relative error vs IDW (P1 mass norm)",
        "mesh quality Q (edge ratio); inverted tets",
    )
    for ax, title in zip(axes, titles, strict=True):
        ax.set_xscale("log")
        ax.set_xlabel("R [m]")
        ax.set_title(title)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    for ax in axes[:3]:
        ax.set_yscale("log")
    figure.suptitle(
        f"Case {spec.letter}: {spec.title} — sensitivity to R "
        f"({spec.sweep_note}; a = {spec.a}, b = {spec.b}; "
        f"{context.mesh.num_nodes:,} nodes)",
        fontsize=10,
    )
    with atomic_output(path) as temporary:
        figure.savefig(temporary, dpi=100, format="png")
    plt.close(figure)


def plot_factor(results: dict[float, list[SelectionPoint]], path: Path) -> None:
    """Fig. 7: SIDW control points (top) and error (bottom) against a, b = 1/a."""
    plt = _pyplot()
    figure, axes = plt.subplots(2, 2, figsize=(11, 7), constrained_layout=True, sharex=True)
    for column, radii in enumerate((FACTOR_RADII[:2], FACTOR_RADII[2:])):
        for index, radius in enumerate(radii):
            points = results[radius]
            a = [p.a for p in points]
            style = ("o-", "s--")[index]
            axes[0, column].plot(a, [p.controls for p in points], style, label=f"R = {radius:g}")
            axes[1, column].plot(a, [p.error for p in points], style, label=f"R = {radius:g}")
        axes[0, column].set_ylabel("control points")
        axes[1, column].set_ylabel("relative error vs IDW (P1 mass norm)")
        axes[1, column].set_xlabel("a (b = 1/a)")
        for ax in axes[:, column]:
            ax.set_yscale("log")
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize=8)
    figure.suptitle(
        "Case A: SIDW sensitivity to the annulus factor a with b = 1/a "
        "(R on the end faces, 10 R on top and bottom)",
        fontsize=10,
    )
    with atomic_output(path) as temporary:
        figure.savefig(temporary, dpi=100, format="png")
    plt.close(figure)


def plot_spectra(spectra: dict[str, dict[str, Tensor]], path: Path) -> None:
    """Figs. 14–16 (left): σ_i/σ_1 of POD-IDW and POD-ESIDW per case."""
    plt = _pyplot()
    figure, axes = plt.subplots(
        1, len(spectra), figsize=(5 * len(spectra), 3.8), constrained_layout=True, squeeze=False
    )
    for ax, (case, values) in zip(axes[0], spectra.items(), strict=True):
        spec = get_case(case)
        for (name, sigma), style in zip(values.items(), ("o-", "s--"), strict=True):
            index = range(1, len(sigma) + 1)
            ax.semilogy(index, [max(float(v), 1e-17) for v in sigma], style, label=name)
        ax.axhline(1e-16, color="0.7", lw=0.5)
        ax.set_xlabel("i")
        ax.set_ylabel("σ_i / σ_1")
        ax.set_title(f"Case {spec.letter}: n_train = {spec.n_train}")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    figure.suptitle("Singular-value decay of the POD snapshots", fontsize=10)
    with atomic_output(path) as temporary:
        figure.savefig(temporary, dpi=100, format="png")
    plt.close(figure)


def plot_angle(sweep: dict[str, Any], path: Path) -> None:
    """Fig. 16 (centre, right): POD error, mesh quality and inversions against the angle."""
    plt = _pyplot()
    figure, axes = plt.subplots(1, 3, figsize=(17, 4.2), constrained_layout=True)
    mu = sweep["mu"].tolist()
    styles = {
        "IDW": ("k", "-", ""),
        "ESIDW": ("k", ":", ""),
        "POD-IDW, 1 mode": ("C0", "-", "o"),
        "POD-IDW, 2 modes": ("C1", "--", "s"),
        "POD-ESIDW, 1 mode": ("C2", "-", "o"),
        "POD-ESIDW, 2 modes": ("C3", "--", "s"),
    }

    def draw(ax, label, values, *, log=False):
        colour, line, marker = styles[label]
        values = [max(float(v), 1e-17) for v in values] if log else [float(v) for v in values]
        ax.plot(
            mu,
            values,
            color=colour,
            ls=line,
            marker=marker,
            ms=3,
            label=label,
            lw=2.0 if label == "ESIDW" else 1.2,
            zorder=3 if label == "ESIDW" else 2,
        )

    for label, error in sweep["error"].items():
        draw(axes[0], label, error, log=True)
    axes[0].set_yscale("log")
    axes[0].set_ylabel("relative error vs IDW (P1 mass norm)")
    axes[0].set_title("POD error against the angle (n_train = 50 random angles)", fontsize=10)
    for label, values in sweep["max_q"].items():
        draw(axes[1], label, values)
    axes[1].set_ylabel("max Q (edge ratio)")
    axes[1].set_title("max Q of the deformed mesh", fontsize=10)
    for label, values in sweep["inverted"].items():
        draw(axes[2], label, values)
    axes[2].set_ylabel("inverted tetrahedra")
    axes[2].set_title("inverted tetrahedra of the deformed mesh", fontsize=10)
    for ax in axes:
        ax.set_xlabel("rotation angle μ [°]")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    figure.suptitle(
        "Case C: rotating hull — POD-IDW and POD-ESIDW with one and two modes", fontsize=10
    )
    with atomic_output(path) as temporary:
        figure.savefig(temporary, dpi=100, format="png")
    plt.close(figure)


def _jsonable(value: Any) -> Any:
    if isinstance(value, torch.Tensor):
        return value.tolist()
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, SelectionPoint):
        return asdict(value)
    return value


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Run the sensitivity studies; returns the measured numbers (also in sensitivity.json)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", choices=("small", "paper"), default="paper")
    parser.add_argument("--out", default="out/sensitivity", help="output directory")
    parser.add_argument(
        "--cases",
        nargs="+",
        default=["wing", "fluid-wing", "hull"],
        help="cases to study: wing, fluid-wing, hull (or A, B, C)",
    )
    parser.add_argument("--mesher", choices=("gmsh", "pytetwild"), default="gmsh")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--repeats", type=int, default=3, help="timed repeats of each deformation (median)"
    )
    parser.add_argument(
        "--threads", type=int, default=None, help="torch intra-op threads (default: torch's choice)"
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    args = parser.parse_args(argv)
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    progress = not args.quiet
    results: dict[str, Any] = {
        "size": args.size,
        "mesher": args.mesher,
        "seed": args.seed,
        "threads": torch.get_num_threads(),
        "cases": {},
    }
    spectra: dict[str, dict[str, Tensor]] = {}
    files = []
    for case in args.cases:
        spec = get_case(case)
        start = time.perf_counter()
        context = prepare_case(spec, size=args.size, mesher=args.mesher)
        record: dict[str, Any] = {
            "nodes": context.mesh.num_nodes,
            "reference_quality": context.reference_quality,
        }
        sweep_context = context
        if spec.key == "hull":  # Fig. 13 varies one R on every wall and on the hull
            sweep_context = dataclasses.replace(context, spec=get_case("hull", "uniform"))
        points = radius_sweep(
            sweep_context, seed=args.seed, repeats=args.repeats, progress=progress
        )
        record["radius"] = points
        path = out / f"{spec.key.replace('-', '_')}_radius.png"
        plot_radius(context, points, path)
        files.append(path)
        if spec.key == "wing":
            factors = {
                radius: factor_sweep(
                    context,
                    radius,
                    FACTORS,
                    seed=args.seed,
                    repeats=args.repeats,
                    progress=progress,
                )
                for radius in FACTOR_RADII
            }
            record["factor"] = {str(radius): value for radius, value in factors.items()}
            path = out / "wing_factor.png"
            plot_factor(factors, path)
            files.append(path)
        esidw = selective_morph(context, enrich=True, seed=args.seed)
        spectra[spec.key] = pod_spectra(context, seed=args.seed, esidw=esidw)
        record["spectra"] = spectra[spec.key]
        if spec.key == "hull":
            low, high = spec.domain
            angles = torch.arange(low, high, 1.0, dtype=context.mesh.dtype)
            sweep = pod_parameter_sweep(context, angles, seed=args.seed, esidw=esidw)
            record["angle"] = sweep
            path = out / "hull_angle.png"
            plot_angle(sweep, path)
            files.append(path)
        record["seconds"] = time.perf_counter() - start
        results["cases"][spec.key] = _jsonable(record)
        del context, esidw
        if progress:
            print(f"case {spec.letter}: {record['seconds']:.1f} s", file=sys.stderr)
    path = out / "spectra.png"
    plot_spectra(spectra, path)
    files.append(path)
    path = out / "sensitivity.json"
    with atomic_output(path) as temporary:
        temporary.write_text(json.dumps(results, indent=1))
    files.append(path)
    results["files"] = [str(f) for f in files]
    if progress:
        print("Wrote: " + ", ".join(results["files"]))
    return results


if __name__ == "__main__":
    main()
