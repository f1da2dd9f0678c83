"""``torchmorph morph``'s control-point selection: the options (``--select``, ``--region``,
``--enrich``, ``--adaptive`` ...), their parsers, and the
:class:`~torchmorph.selection.SelectionPlan` or :class:`~torchmorph.selection.AdaptivePlan`
they stand for."""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from torchmorph.cli._common import _check_names, _positive_float, _positive_int
from torchmorph.cli._methods import DEFAULT_POWER

if TYPE_CHECKING:
    from torchmorph.mesh.model import Mesh
    from torchmorph.selection.plan import UncoveredNodesError

__all__: list[str] = []


def _selection_parameters(text: str) -> tuple[float, float, float]:
    """Parse ``R[,a[,b]]`` and validate it with :class:`~torchmorph.selection.Region`."""
    parts = [part.strip() for part in text.split(",")]
    if not 1 <= len(parts) <= 3 or not all(parts):
        raise argparse.ArgumentTypeError(
            f"expected R, R,a or R,a,b (radius and factors, e.g. 0.3,0.8,1.3), got {text!r}"
        )
    try:
        numbers = [float(part) for part in parts]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected numbers R[,a[,b]] (e.g. 0.3,0.8,1.3), got {text!r}"
        ) from None
    from torchmorph.selection.plan import Region

    try:
        region = Region("region", *numbers)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None
    return region.parameters


def _region_option(text: str) -> tuple[tuple[str, ...], tuple[float, float, float]]:
    """Parse ``SET[+SET...]=R[,a[,b]]``."""
    names, equals, parameters = text.rpartition("=")
    names_list = tuple(name.strip() for name in names.split("+"))
    if not equals or not all(names_list):
        raise argparse.ArgumentTypeError(
            f"expected SET=R[,a,b] or SET1+SET2=R[,a,b] (e.g. top=0.5,0.8,1.3), got {text!r}"
        )
    return names_list, _selection_parameters(parameters)


def add_selection_arguments(parser: argparse.ArgumentParser) -> None:
    """The control-point selection options of ``torchmorph morph``."""
    selection = parser.add_argument_group(
        "control-point selection (default: every boundary node, plain IDW)"
    )
    exclusive = selection.add_mutually_exclusive_group()
    exclusive.add_argument(
        "--select",
        type=_selection_parameters,
        metavar="R[,a,b]",
        help="Selective IDW on all boundary nodes as one region: radius R > 0, "
        "0 < a < 1 (default 0.8), b > 1 (default 1.3)",
    )
    exclusive.add_argument(
        "--region",
        type=_region_option,
        action="append",
        metavar="SET=R[,a,b]",
        help="Selective IDW per node set (repeatable; SET1+SET2=R for a union); every boundary "
        "node must be in a region or an --enrich set unless --uncovered ignore",
    )
    selection.add_argument(
        "--enrich",
        nargs="+",
        action="extend",
        metavar="SET",
        help="node sets whose nodes are always control points (ESIDW); needs --select, "
        "--region or --adaptive",
    )
    selection.add_argument(
        "--strategy",
        choices=("random", "centroid", "farthest"),
        default="random",
        help="SelectControlPoint strategy (default: random, the paper's)",
    )
    selection.add_argument(
        "--overlap",
        choices=("error", "first", "share"),
        default="error",
        help="nodes in several --region sets with different parameters: error (default), give "
        "them to the first region, or let every region keep them",
    )
    selection.add_argument(
        "--uncovered",
        choices=("error", "ignore"),
        default="error",
        help="boundary nodes in no --region and no --enrich set: error (default), or never "
        "select them",
    )
    selection.add_argument(
        "--seed", type=int, default=0, help="seed of the random selection (default 0)"
    )
    selection.add_argument(
        "--adaptive",
        type=_positive_float,
        metavar="TOL",
        help="error-driven selection: add boundary nodes to the controls, those that lower "
        "the error most first, until the morph's relative nodal error against full IDW "
        "(every boundary node a control) is at most TOL (e.g. 0.01); with --method rbf, "
        "until the RBF's error at the boundary nodes, max |s - d| / max |d|, is (greedy RBF "
        "reduction with the --kernel given); a --select, --region or --enrich selection is "
        "where it starts",
    )
    selection.add_argument(
        "--max-controls",
        type=_positive_int,
        metavar="N",
        help="with --adaptive: at most N control points (the starting selection included)",
    )


# Name of the temporary node set that holds every boundary node for --select.
_ALL_BOUNDARY = "(boundary)"


def _split_names(values: Sequence[str] | None) -> list[str] | None:
    """Names given as ``a b`` or ``a,b`` (or both), in order, without repeats."""
    if values is None:
        return None
    names: list[str] = []
    for value in values:
        for name in value.split(","):
            name = name.strip()
            if name and name not in names:
                names.append(name)
    return names


def _selection_plan(args: argparse.Namespace, mesh: Mesh) -> tuple[Any, Mesh, str]:
    """The SelectionPlan of the options (or None), the mesh to select on, and a description."""
    from torchmorph.selection.plan import Region, SelectionPlan

    enrich = _split_names(args.enrich) or []
    if args.select is None and not args.region:
        return None, mesh, "IDW: every boundary node is a control point"
    method = "ESIDW" if enrich else "SIDW"
    if args.select is not None:
        radius, a, b = args.select
        selection_mesh = mesh.with_node_sets({_ALL_BOUNDARY: mesh.boundary_nodes})
        regions = [Region(_ALL_BOUNDARY, radius, a, b)]
        text = f"all boundary nodes R={radius:g}, a={a:g}, b={b:g}"
    else:
        for names, _ in args.region:
            _check_names(mesh, names, "--region")
        selection_mesh = mesh
        regions = [Region(names, *parameters) for names, parameters in args.region]
        text = "; ".join(
            f"{region.label} R={region.radius:g}, a={region.a:g}, b={region.b:g}"
            for region in regions
        )
    if enrich:
        text += f"; enriched with {', '.join(enrich)}"
    plan = SelectionPlan(
        regions,
        enrich=enrich,
        strategy=args.strategy,
        overlap=args.overlap,
        uncovered=args.uncovered,
    )
    return plan, selection_mesh, f"{method} ({args.strategy}): {text}"


def _adaptive_plan(
    args: argparse.Namespace, start: Any, rows: np.ndarray, mesh: Mesh, method: str
) -> tuple[Any, str]:
    """The error-driven plan of ``--adaptive``, started from the SIDW/ESIDW ``start``
    (or from ``--enrich`` alone), driven by the boundary displacement ``rows``."""
    import torch

    from torchmorph.selection.plan import AdaptivePlan, SelectionPlan

    enrich = _split_names(args.enrich) or []
    if start is None and enrich:
        start = SelectionPlan((), enrich=enrich, uncovered="ignore")
    family = torch.as_tensor(rows, dtype=mesh.dtype, device=mesh.device)
    plan = AdaptivePlan(
        args.adaptive,
        family,
        max_controls=args.max_controls,
        start="stratified" if start is None else start,
        power=DEFAULT_POWER if args.power is None else args.power,
    )
    budget = "" if args.max_controls is None else f", at most {args.max_controls} controls"
    if start is None:  # the stratified start is IDW's; RBF starts from its anchors
        origin = "from no control" if args.method == "rbf" else "from a count-stratified start"
    elif args.select is None and not args.region:
        origin = f"from the enrichment sets {', '.join(enrich)}"
    else:
        origin = "from " + method
    measure = "RBF error at the boundary nodes" if args.method == "rbf" else "nodal error"
    return plan, f"adaptive: {measure} <= {args.adaptive:g}{budget}, {origin}"


def _uncovered_message(mesh: Mesh, error: UncoveredNodesError) -> str:
    """The library's uncovered-nodes error in command-line terms, with where the nodes lie."""
    missing = np.asarray(error.nodes)
    is_missing = np.zeros(mesh.num_nodes, dtype=bool)
    is_missing[missing] = True
    where = []
    in_some_set = np.zeros(mesh.num_nodes, dtype=bool)
    for name in sorted(mesh.markers):
        nodes = mesh.node_set(name).cpu().numpy()
        in_some_set[nodes] = True
        count = int(is_missing[nodes].sum())
        if count:
            where.append(f"{count} in {name}")
    outside = int((is_missing & ~in_some_set).sum())
    if outside:
        where.append(f"{outside} in no marker")
    examples = ", ".join(str(int(node)) for node in missing[:5])
    return (
        f"{missing.size} of the {error.total} boundary nodes are in no --region and no "
        f"--enrich set ({'; '.join(where)}; e.g. node(s) {examples}); add their sets with "
        "--region SET=R or --enrich SET, or pass --uncovered ignore to never select them"
    )
