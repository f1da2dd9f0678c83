"""Selection of control points: Algorithm 1 (SIDW), per-region selection plans and the
error-driven plan.

:func:`select_control_points` implements Algorithm 1 of the paper (Ballarin et al. 2017,
Section 2.2) on a cloud of candidate points of any dimension; :class:`SelectionPlan` runs it on named node sets
of a :class:`~torchmorph.mesh.TetMesh`, each with its own radius ``R`` and factors
``a``, ``b``, takes the union and adds enrichment node sets (ESIDW: Algorithm 2,
step (ii), Section 2.2.1). :class:`AdaptivePlan` chooses the controls by the morph's
error instead (:mod:`torchmorph.selection.adaptive`).

Definitions used throughout (the paper's Section 2.2): ``B(c; r)`` is the open ball
``|x - c| < r`` and ``B(c; r_i, r_e)`` the shell ``r_i <= |x - c| < r_e``, so that a
point at distance exactly ``R`` of a selected point survives the removal and may be
selected itself. Consequences kept by the implementation: every candidate lies within
distance ``R`` of a selected point, and selected points are pairwise at least ``R``
apart.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from torchmorph._checks import as_index, check_choice, check_positive
from torchmorph.selection.adaptive import (
    DEFAULT_SAMPLE_BYTES,
    DEFAULT_SCORE_SAMPLES,
    GreedySelection,
    _checked_selection,
)
from torchmorph.selection.greedy import check_budget, greedy_selection
from torchmorph.selection.sidw import (
    DEFAULT_SEED,
    STRATEGIES,
    _check_factor,
    _check_generator,
    _check_strategy,
    select_control_points,
)

#: The RBF options an :class:`AdaptivePlan` with ``method="rbf"`` takes (None: the morph's).
_RBF_OPTIONS = ("kernel", "epsilon", "degree", "support_radius")

__all__ = [
    "DEFAULT_SEED",
    "STRATEGIES",
    "AdaptivePlan",
    "Region",
    "RegionOverlapError",
    "SelectionPlan",
    "UncoveredNodesError",
    "select_control_points",
]


class RegionOverlapError(ValueError):
    """Two regions with different parameters share nodes (``overlap="error"``).

    ``first`` and ``second`` are the two :class:`Region` objects, ``count`` the
    number of nodes they share.
    """

    def __init__(self, message: str, *, first: Region, second: Region, count: int) -> None:
        super().__init__(message)
        self.first, self.second, self.count = first, second, count


class UncoveredNodesError(ValueError):
    """Candidate nodes in no region and no enrichment set (``uncovered="error"``).

    ``nodes`` holds their global ids (int64 array), ``total`` the number of candidates.
    """

    def __init__(self, message: str, *, nodes: np.ndarray, total: int) -> None:
        super().__init__(message)
        self.nodes, self.total = nodes, total


# --------------------------------------------------------------------------------------
# regions and plans
# --------------------------------------------------------------------------------------

_OVERLAP = ("error", "first", "share")
_UNCOVERED = ("error", "ignore")


@dataclass(frozen=True)
class Region:
    """Node sets selected together with one set of Algorithm-1 parameters.

    Parameters
    ----------
    nodes : str or tuple of str
        Name(s) of mesh node sets (``TetMesh.node_set``); their union is the region.
    radius : float
        Selection radius ``R > 0``.
    a : float, default 0.8
        Annulus thickness factor, ``0 < a < 1``.
    b : float, default 1.3
        Selection-shell factor, ``b > 1``.
    """

    nodes: str | tuple[str, ...]
    radius: float
    a: float = 0.8
    b: float = 1.3

    def __post_init__(self) -> None:
        nodes = self.nodes
        if isinstance(nodes, str):
            names: tuple[str, ...] = (nodes,)
        elif isinstance(nodes, Sequence):
            names = tuple(nodes)
        else:
            raise TypeError(f"nodes must be a node-set name or a sequence of names, got {nodes!r}")
        if not names or not all(isinstance(name, str) and name for name in names):
            raise ValueError(f"nodes must name at least one node set, got {nodes!r}")
        object.__setattr__(self, "nodes", nodes if isinstance(nodes, str) else names)
        object.__setattr__(self, "radius", check_positive(self.radius, "radius"))
        object.__setattr__(self, "a", _check_factor(self.a, "a", low=0.0, high=1.0))
        object.__setattr__(self, "b", _check_factor(self.b, "b", low=1.0, high=np.inf))

    @property
    def names(self) -> tuple[str, ...]:
        """The node-set names, always as a tuple."""
        return (self.nodes,) if isinstance(self.nodes, str) else self.nodes

    @property
    def label(self) -> str:
        """A readable name for messages: the node-set names joined by '+'."""
        return "+".join(self.names)

    @property
    def parameters(self) -> tuple[float, float, float]:
        """``(radius, a, b)``."""
        return (self.radius, self.a, self.b)


def _as_region(key: Any, value: Any) -> Region:
    nodes = key if isinstance(key, str) else tuple(key)
    if isinstance(value, Region):
        raise TypeError(f"regions[{key!r}]: give a radius or (radius, a, b), not a Region")
    if isinstance(value, Mapping):
        return Region(nodes, **value)
    if isinstance(value, (tuple, list)):
        if not 1 <= len(value) <= 3:
            raise ValueError(
                f"regions[{key!r}] must be radius or (radius[, a[, b]]), got {value!r}"
            )
        return Region(nodes, *value)
    return Region(nodes, value)


@dataclass
class SelectionPlan:
    """Per-region control-point selection with enrichment (Algorithm 2 (i)-(ii), Section 2.2.1).

    Parameters
    ----------
    regions : sequence of Region, or mapping
        The regions, in priority order. A mapping is shorthand: its keys are node-set
        names (or tuples of names) and its values a radius, ``(radius, a, b)`` (a
        shorter tuple keeps the remaining defaults) or a dict of ``Region`` keywords,
        e.g. ``{"root": 0.05, "tip": 0.05, "upper": 0.5, "lower": 0.5}``.
    enrich : sequence of str, default ()
        Node sets whose nodes are always control points (ESIDW), e.g. the end profiles
        and leading/trailing edges of a wing, or nodes held fixed.
    strategy : {"random", "centroid", "farthest"}, default "random"
        ``SelectControlPoint`` used in every region (see :func:`select_control_points`).
    overlap : {"error", "first", "share"}, default "error"
        Nodes listed by several regions. With ``"error"``, regions with different
        ``(radius, a, b)`` must not share nodes (``ValueError`` naming both); a node
        shared by regions with equal parameters goes to the first of them. With
        ``"first"`` every shared node goes to the first region listing it. With
        ``"share"`` every region keeps all its nodes: each runs Algorithm 1 on its full
        node set and a shared node may be chosen by several regions.
    uncovered : {"error", "ignore"}, default "error"
        Candidate nodes in no region and no enrichment set. ``"error"`` raises
        ``ValueError``; ``"ignore"`` leaves them out: they are never selected, and no
        selected point is guaranteed within any distance of them (e.g. a far wall
        deliberately left out of the controls).

    Notes
    -----
    The candidates are the mesh's boundary nodes unless ``candidates`` is given to
    :meth:`select`; region and enrichment nodes must be candidates (Algorithm 2 draws
    its controls from the boundary and interpolates only the interior). Regions run
    in order, each drawing its start point (and, with ``"random"``, its choices) from
    the same generator. An empty region (e.g. all of its nodes taken by an earlier
    region under ``"first"``) selects nothing. After construction ``regions`` is a
    tuple of :class:`Region` and ``enrich`` a tuple of names.
    """

    regions: Sequence[Region] | Mapping[Any, Any]
    enrich: Sequence[str] = ()
    strategy: str = "random"
    overlap: str = "error"
    uncovered: str = "error"

    def __post_init__(self) -> None:
        regions = self.regions
        if isinstance(regions, Mapping):
            regions = tuple(_as_region(key, value) for key, value in regions.items())
        elif isinstance(regions, Region):
            regions = (regions,)
        elif isinstance(regions, Sequence) and not isinstance(regions, str):
            regions = tuple(regions)
            for position, region in enumerate(regions):
                if not isinstance(region, Region):
                    raise TypeError(
                        f"regions[{position}] must be a Region, got {type(region).__name__}"
                    )
        else:
            raise TypeError(
                f"regions must be a sequence of Region or a mapping, got {type(regions).__name__}"
            )
        self.regions = regions
        enrich = (self.enrich,) if isinstance(self.enrich, str) else tuple(self.enrich)
        if not all(isinstance(name, str) and name for name in enrich):
            raise ValueError(f"enrich must be a sequence of node-set names, got {self.enrich!r}")
        self.enrich = enrich
        _check_strategy(self.strategy)
        check_choice(self.overlap, "overlap", _OVERLAP)
        check_choice(self.uncovered, "uncovered", _UNCOVERED)

    def region_nodes(self, mesh: Any, *, candidates: Any = None) -> list[Tensor]:
        """Global node ids each region selects from, after resolving overlaps.

        Parameters
        ----------
        mesh : TetMesh
            Needs ``points``, ``boundary_nodes`` and ``node_set(name)``.
        candidates : Tensor or array of int, optional
            Global ids of the nodes that may be control points; default
            ``mesh.boundary_nodes``.

        Returns
        -------
        list of Tensor (int64, sorted unique)
            One per region, in the order of ``self.regions``, on the CPU.

        Raises
        ------
        ValueError
            Unknown node-set names (listing the known ones), region or enrichment nodes
            that are not candidates, conflicting overlaps under ``overlap="error"``, or
            uncovered candidates under ``uncovered="error"``.
        """
        return self._resolve(mesh, candidates)[0]

    def select(
        self,
        mesh: Any,
        *,
        generator: torch.Generator | None = None,
        candidates: Any = None,
    ) -> Tensor:
        """Run Algorithm 1 on every region, take the union and add the enrichment sets.

        Parameters
        ----------
        mesh : TetMesh
            Needs ``points``, ``boundary_nodes`` and ``node_set(name)``.
        generator : torch.Generator, optional
            CPU generator for start points and random choices; ``None`` uses a fresh
            generator seeded with :data:`DEFAULT_SEED` (reproducible).
        candidates : Tensor or array of int, optional
            Global ids of the nodes that may be control points; default
            ``mesh.boundary_nodes``.

        Returns
        -------
        Tensor, shape (N_sel,), int64
            Sorted unique global node ids of the control points, on the device of
            ``mesh.points``.

        Raises
        ------
        ValueError
            As :meth:`region_nodes`, or for a generator that is not on the CPU.
        """
        generator = _check_generator(generator)
        per_region, enriched, points = self._resolve(mesh, candidates)
        chosen = [enriched]
        for region, nodes in zip(self.regions, per_region, strict=True):
            if nodes.numel() == 0:
                continue
            node_ids = nodes.numpy()
            local = select_control_points(
                points[node_ids],
                region.radius,
                a=region.a,
                b=region.b,
                strategy=self.strategy,
                generator=generator,
            )
            chosen.append(node_ids[local.numpy()])
        control_nodes = np.unique(np.concatenate(chosen))
        return torch.as_tensor(control_nodes, dtype=torch.int64, device=mesh.points.device)

    def _resolve(self, mesh: Any, candidates: Any) -> tuple[list[Tensor], np.ndarray, np.ndarray]:
        """Region node ids (after overlap rules), enrichment ids and the points array."""
        points = mesh.points
        points = (
            points.detach().to("cpu", torch.float64).numpy()
            if isinstance(points, Tensor)
            else np.asarray(points, dtype=np.float64)
        )
        num_nodes = points.shape[0]
        if candidates is None:
            candidate_ids = _id_array(mesh.boundary_nodes)
            what = "boundary nodes"
        else:
            candidate_ids = as_index(candidates, "candidates", size=num_nodes).cpu().numpy()
            what = "candidates"
        is_candidate = np.zeros(num_nodes, dtype=bool)
        is_candidate[candidate_ids] = True

        def nodes_of(name: str, role: str) -> np.ndarray:
            ids = _id_array(mesh.node_set(name))
            outside = ids[~is_candidate[ids]]
            if outside.size:
                raise ValueError(
                    f"{role} node set {name!r} holds {outside.size} node(s) that are not "
                    f"{what} (e.g. node {int(outside[0])}); control points are drawn from "
                    f"the {what} only"
                )
            return ids

        region_ids = [
            np.unique(np.concatenate([nodes_of(name, "region") for name in region.names]))
            for region in self.regions
        ]
        enrich_ids = [nodes_of(name, "enrichment") for name in self.enrich]
        enriched = (
            np.unique(np.concatenate(enrich_ids)) if enrich_ids else np.zeros(0, dtype=np.int64)
        )

        if self.overlap != "share":
            owner = np.full(num_nodes, -1, dtype=np.int64)
            for position, ids in enumerate(region_ids):
                taken = owner[ids]
                shared = taken >= 0
                if self.overlap == "error":
                    for other in np.unique(taken[shared]):
                        first, second = self.regions[other], self.regions[position]
                        if first.parameters != second.parameters:
                            count = int((taken == other).sum())
                            raise RegionOverlapError(
                                f"regions {first.label!r} (R={first.radius:g}, a={first.a:g}, "
                                f"b={first.b:g}) and {second.label!r} (R={second.radius:g}, "
                                f"a={second.a:g}, b={second.b:g}) share {count} node(s) but "
                                "have different parameters; pass overlap='first' (a shared "
                                "node goes to the first region listing it) or overlap='share' "
                                "(each region keeps all its nodes)",
                                first=first,
                                second=second,
                                count=count,
                            )
                owner[ids[~shared]] = position
                region_ids[position] = ids[~shared]

        if self.uncovered == "error":
            covered = np.zeros(num_nodes, dtype=bool)
            for ids in region_ids:
                covered[ids] = True
            covered[enriched] = True
            missing = candidate_ids[~covered[candidate_ids]]
            if missing.size:
                raise UncoveredNodesError(
                    f"{missing.size} of the {candidate_ids.size} {what} are in no region and "
                    f"no enrichment set (e.g. node {int(missing[0])}); add them to a region, "
                    "enrich them, or pass uncovered='ignore' to leave them out of the selection",
                    nodes=missing,
                    total=int(candidate_ids.size),
                )
        return [torch.from_numpy(ids) for ids in region_ids], enriched, points


def _id_array(ids: Any) -> np.ndarray:
    if isinstance(ids, Tensor):
        ids = ids.detach().cpu().numpy()
    return np.asarray(ids, dtype=np.int64).reshape(-1)


@dataclass
class AdaptivePlan:
    """Error-driven control points of a mesh, for :class:`~torchmorph.morph.MeshMorph`.

    The candidates are the mesh's boundary nodes and the error is measured at its
    interior nodes against full IDW (every boundary node a control), for a family of
    boundary displacements: the relative nodal error of the morph, the measure of the
    paper's tables (weighted by ``weights`` when given). Pass it where a
    :class:`~torchmorph.selection.SelectionPlan` goes: ``MeshMorph(mesh, plan)``.

    Parameters
    ----------
    tolerance : float
        Relative error to reach, > 0 (the worst over the family).
    displacements : Tensor or callable
        The family: a boundary displacement (N_b, D) or several (F, N_b, D), rows
        ordered as ``mesh.boundary_nodes``; or a callable mapping the boundary points
        (N_b, D) to one of those (e.g. the POD training set of a parametrised family).
    max_controls : int, optional
        At most this many controls (>= 1), the ``start`` set included.
    start : "stratified", SelectionPlan or None, default "stratified"
        Where the selection starts. ``"stratified"``: from a share of the shortest
        count-stratified prefix of the boundary nodes that meets the tolerance
        (:func:`select_adaptive`'s ``start``; IDW's error only). A coarse SIDW/ESIDW
        plan: its selection is kept and grown (e.g. the enrichment sets alone, or a
        large radius). None: from no control.
    weights : Tensor, shape (N,), optional
        Node weights of the error (quantity of interest), >= 0, not all zero on the
        interior nodes; default 1 everywhere (the nodal error).
    power : float, default 4
        The IDW exponent; use the morph's.
    num_samples, sample_bytes, score_samples, min_batch, spacing
        As :func:`select_adaptive` (the first three: IDW's error only).
    method : {"idw", "rbf"}, optional
        The interpolation whose error drives the selection. Default: the morph's when the
        plan is given to :class:`~torchmorph.morph.MeshMorph` (its ``method`` and RBF
        options), IDW when :meth:`select` is called alone.
    kernel, epsilon, degree, support_radius : optional
        ``method="rbf"``: the RBF, as :class:`~torchmorph.rbf.RBF`; default the morph's
        (else RBF's defaults: the thin-plate spline with the linear polynomial).

    Attributes
    ----------
    result_ : GreedySelection or None
        The last selection's record (indices into the boundary nodes, error, history).
    sampled_targets_ : int
        The number of interior nodes its error was measured at.

    Notes
    -----
    The selection is a set of boundary nodes like SIDW's, so the morph, its POD
    reduction and its state are the same as for any plan. The error is estimated on a
    sample of the interior nodes when they are many (see :class:`IDWErrorOracle`);
    check the final morph with ``torchmorph.mesh.norms.relative_nodal_error``.

    With ``method="rbf"`` the error is the RBF's interpolation error at the boundary
    nodes, ``max |s(x) − d(x)| / max |d|`` (the worst over the family), and the
    controls with the largest one are added (greedy RBF reduction, with the
    factorisation grown by bordered updates: :class:`~torchmorph.rbf.RBFErrorOracle`);
    the selection starts with the nodes that carry the polynomial. Node ``weights`` and
    the target sample do not apply there.
    """

    tolerance: float
    displacements: Tensor | Callable[[Tensor], Tensor]
    max_controls: int | None = None
    start: Any = "stratified"
    weights: Tensor | None = None
    power: float = 4.0
    num_samples: int | None = None
    sample_bytes: int = DEFAULT_SAMPLE_BYTES
    score_samples: int | None = DEFAULT_SCORE_SAMPLES
    min_batch: int = 8
    spacing: float = 0.5
    method: str | None = None
    kernel: str | None = None
    epsilon: float | None = None
    degree: int | None = None
    support_radius: float | None = None
    result_: GreedySelection | None = field(default=None, init=False, repr=False)
    sampled_targets_: int = field(default=0, init=False, repr=False)
    method_: str = field(default="idw", init=False, repr=False)

    def __post_init__(self) -> None:
        self.tolerance = check_positive(self.tolerance, "tolerance")
        if self.max_controls is not None:
            self.max_controls = check_budget(self.max_controls)
        if not (isinstance(self.displacements, Tensor) or callable(self.displacements)):
            raise TypeError(
                "displacements must be a Tensor (N_b, D) / (F, N_b, D) or a callable of "
                f"the boundary points, got {type(self.displacements).__name__}"
            )
        if isinstance(self.start, str):
            check_choice(self.start, "start", ("stratified",))
        elif self.start is not None and not callable(getattr(self.start, "select", None)):
            raise TypeError(
                "start must be 'stratified', a SelectionPlan or None, got "
                f"{type(self.start).__name__}"
            )
        if self.method is not None:
            check_choice(self.method, "method", ("idw", "rbf"))
        rbf_given = [name for name in _RBF_OPTIONS if getattr(self, name) is not None]
        if self.method == "idw" and rbf_given:
            raise ValueError(f"{rbf_given[0]}: an option of method='rbf', not of method='idw'")

    def select(
        self,
        mesh: Any,
        *,
        generator: torch.Generator | None = None,
        morph: tuple[str, Mapping[str, Any]] | None = None,
    ) -> Tensor:
        """The control points: sorted unique global node ids, on the mesh's device.

        Parameters
        ----------
        mesh : Mesh
            Needs ``points``, ``boundary_nodes`` and ``interior_nodes``.
        generator : torch.Generator, optional
            Randomness of the ``start`` plan (the target sample is seeded with
            ``DEFAULT_SEED``: the same mesh and family give the same selection).
        morph : (str, mapping), optional
            The morph's method and options (``MeshMorph`` passes them): what ``method``
            and the RBF options left at None follow.
        """
        method = self.method or (morph[0] if morph is not None else "idw")
        check_choice(method, "method", ("idw", "rbf"))
        self.method_ = method
        boundary, interior = mesh.boundary_nodes, mesh.interior_nodes
        if interior.numel() == 0:
            raise ValueError("mesh has no interior node: there is no error to drive a selection")
        points = mesh.points.detach()
        boundary_points = points[boundary]
        family = self.displacements
        if not isinstance(family, Tensor):
            family = family(boundary_points)
            if not isinstance(family, Tensor):
                raise TypeError(
                    f"displacements(boundary points) must return a Tensor, got "
                    f"{type(family).__name__}"
                )
        weights = candidate_weights = None
        if self.weights is not None:
            node_weights = torch.as_tensor(self.weights)
            if node_weights.shape != (mesh.num_nodes,):
                raise ValueError(
                    f"weights must have shape ({mesh.num_nodes},) (one per node), got "
                    f"{tuple(node_weights.shape)}"
                )
            node_weights = node_weights.to(points.device)
            weights, candidate_weights = node_weights[interior], node_weights[boundary]
        initial = None
        generator = _check_generator(generator)
        stratified = isinstance(self.start, str)
        if self.start is not None and not stratified:
            chosen = torch.as_tensor(self.start.select(mesh, generator=generator)).to(boundary)
            initial = torch.searchsorted(boundary, chosen.unique()).cpu()
        if method == "rbf":
            options = dict(morph[1]) if morph is not None and morph[0] == "rbf" else {}
            result = self._rbf_selection(boundary_points, family, initial, options)
            self.result_, self.sampled_targets_ = result, 0
            return torch.sort(boundary[result.indices.to(boundary.device)]).values
        result, measured = _checked_selection(
            boundary_points,
            points[interior],
            family,
            tolerance=self.tolerance,
            max_controls=self.max_controls,
            initial=initial,
            weights=weights,
            candidate_weights=candidate_weights,
            power=self.power,
            num_samples=self.num_samples,
            sample_bytes=self.sample_bytes,
            score_samples=self.score_samples,
            generator=torch.Generator().manual_seed(DEFAULT_SEED),
            min_batch=self.min_batch,
            spacing=self.spacing,
            start="stratified" if stratified else "empty",
        )
        self.result_, self.sampled_targets_ = result, measured
        return torch.sort(boundary[result.indices.to(boundary.device)]).values

    def _rbf_selection(
        self, points: Tensor, family: Tensor, initial: Tensor | None, options: dict[str, Any]
    ) -> GreedySelection:
        """Greedy RBF reduction of the boundary nodes ``points`` for ``family``, from
        the polynomial's anchors and ``initial``; the RBF from this plan's options, else
        the morph's ``options``."""
        from torchmorph.rbf.greedy import RBFErrorOracle

        for name, value in (
            ("weights", self.weights),
            ("num_samples", self.num_samples),
            ("score_samples", self.score_samples),
        ):
            if value is not None:
                raise ValueError(
                    f"{name}: the RBF error is measured at every boundary node, with no node "
                    "weights and no sample of targets; leave it None with method='rbf'"
                )
        for name in _RBF_OPTIONS:
            if getattr(self, name) is not None:
                options[name] = getattr(self, name)
        kernel_options = {name: options[name] for name in _RBF_OPTIONS if name in options}
        oracle = RBFErrorOracle(points, family, **kernel_options)
        anchors = oracle.anchors.cpu()
        if initial is not None:
            initial = torch.cat([anchors, initial[~torch.isin(initial, anchors)]])
        else:
            initial = anchors
        if self.max_controls is not None and self.max_controls < len(initial):
            raise ValueError(
                f"max_controls ({self.max_controls}) is smaller than the {len(initial)} "
                "nodes the selection starts with (the polynomial's anchors and the start plan)"
            )
        return greedy_selection(
            oracle,
            tolerance=self.tolerance,
            max_controls=self.max_controls,
            initial=initial,
            min_batch=self.min_batch,
            spacing=self.spacing,
        )
