"""Results of a reproduction: rows beside the paper's, printed tables, output files."""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import Tensor

from torchmorph._atomic import atomic_output
from torchmorph.mesh.quality import edge_ratio
from torchmorph.morph import MeshMorph
from torchmorph.paper.cases import PaperMesh, PaperRow

if TYPE_CHECKING:
    from torchmorph.paper.experiments import CaseContext

__all__ = ["CaseResult", "MethodResult", "write_outputs"]

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
            rows.append(
                (f"max Q ({method}, μ*)", f"{summary['max_edge_ratio']:.2f}", _opt(paper_max))
            )
            rows.append(
                (f"mean Q ({method}, μ*)", f"{summary['mean_edge_ratio']:.2f}", _opt(paper_mean))
            )
            rows.append((f"inverted tets ({method}, μ*)", f"{summary['num_inverted']}", "–"))
        header = (f"Table {self.mesh_table}", "ours", "paper")
        return _format_table(header, rows, markdown=markdown)

    def result_lines(self, *, markdown: bool = False) -> list[str]:
        """The results table (Tables 4–6) beside the paper's, as text lines."""
        header = (
            "method",
            "controls",
            "paper",
            "offline [s]",
            "paper",
            "modes",
            "paper",
            "online [s]",
            "paper",
            "paper/ours",
            "nodal error",
            "mass error",
            "paper",
            "inverted",
            "max Q",
            "mean Q",
        )
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
            rows.append(
                (
                    row.method,
                    f"{row.controls:,}",
                    "–" if paper is None else f"{paper.controls:,}",
                    _opt(row.offline_s, "{:.2f}"),
                    "–" if paper is None else _opt(paper.offline_s, "{:.2f}"),
                    _opt(row.modes, "{}"),
                    "–" if paper is None else _opt(paper.modes, "{}"),
                    _seconds(row.online_s),
                    "–" if paper is None else f"{paper.online_s:g}",
                    speedup,
                    nodal,
                    error,
                    "–" if paper is None else paper.error,
                    f"{row.inverted}",
                    f"{row.max_q:.2f}",
                    f"{row.mean_q:.3f}",
                )
            )
        return _format_table(header, rows, markdown=markdown)

    def timing_lines(self, *, markdown: bool = False) -> list[str]:
        """Selection, assembly and POD-fit seconds per method."""
        header = (
            "method",
            "selection [s]",
            "assembly [s]",
            "POD fit [s]",
            "offline [s]",
            "online [s]",
        )
        rows = [
            (
                row.method,
                _opt(row.selection_s, "{:.3f}"),
                _opt(row.assembly_s, "{:.3f}"),
                _opt(row.fit_s, "{:.3f}"),
                _opt(row.offline_s, "{:.3f}"),
                _seconds(row.online_s),
            )
            for row in self.rows
        ]
        return _format_table(header, rows, markdown=markdown)

    def report(self) -> str:
        """All tables as one printable text."""
        title = (
            f"Case {self.letter} — {self.title} (size={self.size}, mesher={self.mesher}, "
            f"seed={self.seed}, μ* = {self.mu_star:g}, variant={self.variant})"
        )
        parts = [title]
        if self.selection_note:
            parts.append(f"Selection: {self.selection_note}")
        parts += [
            "",
            *self.mesh_lines(),
            "",
            f"Table {self.results_table}:",
            *self.result_lines(),
            (
                "Errors against full IDW at μ*: 'nodal' in the nodal ℓ2 norm (the paper's "
                "Ω_h = {x_i}: its reading), 'mass' in the P1 mass-matrix norm; "
                "(a–b): min–max over D."
            ),
        ]
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


def _format_table(
    header: Sequence[str], rows: Sequence[Sequence[str]], *, markdown: bool = False
) -> list[str]:
    if markdown:
        lines = [
            "| " + " | ".join(header) + " |",
            "|" + "|".join("---" if i == 0 else "---:" for i in range(len(header))) + "|",
        ]
        return lines + ["| " + " | ".join(row) + " |" for row in rows]
    widths = [max(len(str(cell)) for cell in column) for column in zip(header, *rows, strict=True)]

    def line(cells: Sequence[str]) -> str:
        first = f"{cells[0]:<{widths[0]}}"
        return "  ".join(
            [first, *(f"{c:>{w}}" for c, w in zip(cells[1:], widths[1:], strict=True))]
        )

    return [line(header), "  ".join("-" * w for w in widths), *(line(row) for row in rows)]


# --------------------------------------------------------------------------------------
# output files
# --------------------------------------------------------------------------------------


def _file_label(method: str) -> str:
    return method.lower().replace(" ", "_").replace("(", "").replace(")", "").replace("-", "_")


def write_outputs(
    out: Path,
    context: CaseContext,
    morphs: dict[str, MeshMorph],
    fields: dict[str, Tensor],
    result: CaseResult,
) -> list[Path]:
    from torchmorph.mesh.io import write_mesh
    from torchmorph.paper.plots import plot_case

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
    write_mesh(
        path, mesh, point_data=point_data, cell_data={"Q": edge_ratio(mesh.points, mesh.tets)}
    )
    files.append(path)
    for method in ("IDW", "ESIDW"):
        displacement = fields[method]
        moved = mesh.deformed(displacement)
        path = out / f"deformed_{_file_label(method)}.vtu"
        point_data = {"displacement": displacement}
        if method != "IDW":
            point_data["difference_from_IDW"] = displacement - fields["IDW"]
        write_mesh(
            path,
            moved,
            point_data=point_data,
            cell_data={
                "Q": edge_ratio(moved.points, mesh.tets),
                "inverted": (moved.volumes <= 0).to(torch.uint8),
            },
        )
        files.append(path)
    path = out / f"{context.spec.key}.png"
    plot_case(context, fields, morphs, path)
    files.append(path)
    path = out / "results.json"
    with atomic_output(path) as temporary:
        temporary.write_text(json.dumps(result.to_dict(), indent=2, default=_json_default))
    files.append(path)
    return files


def _json_default(value: Any) -> Any:
    if isinstance(value, Tensor):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"not serialisable: {type(value).__name__}")
