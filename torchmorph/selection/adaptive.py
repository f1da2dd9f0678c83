"""Error-driven selection of IDW control points: the adaptive alternative to SIDW/ESIDW.

Algorithm 1 (SIDW) spreads control points by distance, whatever the displacement does;
the paper names "an adaptive selection of the control points driven by some quantity of
interest" as future work (Ballarin et al. 2017, Section 4). Here the error of the
selective morph against full IDW (every candidate a control) chooses the controls:
:func:`select_adaptive` runs the greedy loop of :mod:`torchmorph.selection.greedy` with
:class:`IDWErrorOracle`, and :class:`~torchmorph.selection.plan.AdaptivePlan` does it
on a mesh for :class:`~torchmorph.morph.MeshMorph` (a drop-in for a
:class:`~torchmorph.selection.SelectionPlan`).

The start
---------
Far from the candidates, a selection reproduces full IDW when it holds the same share
of the candidates in every region (:mod:`torchmorph.selection.stratified`); SIDW's
spacing does not on graded boundaries. So by default (``start="stratified"``) the
selection first finds, by its errors, the shortest prefix of the candidates'
count-stratified order that meets the tolerance, starts from :data:`START_SHARE` of it
and adds the controls the error asks for (the result is the prefix itself where that
is shorter). The loop then adds candidates one at a time from a pool of the best
scores, each the one that lowers the error most given those added before it
(:meth:`IDWErrorOracle.pick`): candidates that each correct the same far-field error
are not added together, which had overshot (case C: 16 candidates of the best scores,
each lowering the error alone, raised it from 1.7 % to 3.4 % together).

Cost
----
The oracle's (:mod:`torchmorph.selection.oracle`): ``W`` once on the sampled targets,
the prefixes' errors from sums of their rows, a scoring per round and the picks.
Measured at size paper on one thread, at ESIDW's error (benchmarks/adaptive.py): 7, 2
and 8 full IDW evaluations in all on cases A, B and C.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchmorph._checks import check_choice
from torchmorph.idw.functional import idw_apply
from torchmorph.selection.greedy import (
    ErrorOracle,
    GreedySelection,
    _initial,
    check_budget,
    greedy_selection,
)
from torchmorph.selection.oracle import (
    DEFAULT_SAMPLE_BYTES,
    DEFAULT_SCORE_SAMPLES,
    IDWErrorOracle,
    _weights,
)
from torchmorph.selection.sidw import DEFAULT_SEED
from torchmorph.selection.stratified import nested_order, stratified_count

__all__ = [
    "DEFAULT_SAMPLE_BYTES",
    "DEFAULT_SCORE_SAMPLES",
    "START_SHARE",
    "STRATIFIED_SCORE_SAMPLES",
    "ErrorOracle",
    "GreedySelection",
    "IDWErrorOracle",
    "greedy_selection",
    "select_adaptive",
]

#: ``score_samples`` when it is None and ``start="stratified"``: the scores only choose
#: the pool that the exact picks read on every sampled target
#: (:meth:`IDWErrorOracle.pick`), so they may be noisy (case C at 1.26 %: 410 controls
#: in 6.9 full IDW evaluations with 1,024, 410 in 10.7 with all 3,173).
STRATIFIED_SCORE_SAMPLES = 1024

#: ``start="stratified"``: the selection starts from this share of the shortest
#: count-stratified prefix that meets the tolerance (see
#: :mod:`torchmorph.selection.stratified`) and adds the controls the error asks for.
START_SHARE = 0.75

# Checks of a sampled selection on every target, each followed by a new sample.
_CHECKS = 8


def select_adaptive(
    candidates: Tensor,
    targets: Tensor,
    displacements: Tensor,
    *,
    tolerance: float,
    max_controls: int | None = None,
    initial: Tensor | None = None,
    weights: Tensor | None = None,
    candidate_weights: Tensor | None = None,
    power: float = 4.0,
    num_samples: int | None = None,
    sample_bytes: int = DEFAULT_SAMPLE_BYTES,
    score_samples: int | None = DEFAULT_SCORE_SAMPLES,
    generator: torch.Generator | None = None,
    min_batch: int = 8,
    spacing: float = 0.5,
    start: str = "stratified",
) -> GreedySelection:
    """Error-driven selection of IDW control points among ``candidates``.

    Adds candidates to the controls, in batches, by the decrease of the
    error of selective IDW against full IDW at (a sample of) ``targets``, until the
    worst relative error over the family ``displacements`` is at most ``tolerance`` or
    ``max_controls`` are selected. See the module's notes for the error, the scores and
    the cost, and :func:`~torchmorph.selection.greedy.greedy_selection` for the loop.

    Parameters
    ----------
    candidates, targets, displacements, weights, candidate_weights, power
        As :class:`IDWErrorOracle`.
    num_samples, sample_bytes, score_samples, generator
        As :class:`IDWErrorOracle`.
    tolerance : float, keyword
        Relative error to reach, > 0 (e.g. 0.01 for 1 %).
    max_controls : int, optional
        At most this many controls (>= 1), ``initial`` included.
    initial : Tensor of int, optional
        Candidates that are controls from the start (a coarse SIDW/ESIDW set).
    min_batch, spacing
        As :func:`~torchmorph.selection.greedy.greedy_selection`.
    start : {"stratified", "empty"}, default "stratified"
        ``"stratified"``: the loop starts from ``initial`` and :data:`START_SHARE` of
        the shortest count-stratified prefix of the candidates that meets the
        tolerance with them (:mod:`torchmorph.selection.stratified`; of the budget
        when none does), adds candidates by exact sequential picks from a pool of the
        best scores (the scores on :data:`STRATIFIED_SCORE_SAMPLES` targets unless
        ``score_samples`` is given), and the prefix is the result when it is shorter
        than the loop's: a few full IDW evaluations in all. ``"empty"``: from
        ``initial`` alone, by batches of the best scores and their prefixes; tens to
        hundreds of full IDW evaluations, but fewer controls at tight tolerances (case
        A at size paper and 0.1 %: 722 controls in 29 evaluations, against 1,307 in 10;
        docs/results.md).

    Returns
    -------
    GreedySelection
        ``indices`` into ``candidates`` (initial ones first, then the stratified
        start), the final worst error (estimated on the sample), whether it converged
        and the history.

    Raises
    ------
    ValueError
        For ``tolerance`` not finite and > 0, ``max_controls`` < 1, points or
        displacements of the wrong shape or holding NaN/inf, negative or all-zero
        weights, a family member with a zero reference field, or bad loop parameters.
    """
    return _checked_selection(
        candidates,
        targets,
        displacements,
        tolerance=tolerance,
        max_controls=max_controls,
        initial=initial,
        weights=weights,
        candidate_weights=candidate_weights,
        power=power,
        num_samples=num_samples,
        sample_bytes=sample_bytes,
        score_samples=score_samples,
        generator=generator,
        min_batch=min_batch,
        spacing=spacing,
        start=start,
    )[0]


def _stratified_start(
    oracle: IDWErrorOracle, tolerance: float, max_controls: int | None, initial
) -> tuple[Tensor, Tensor | None, list[tuple[int, float]]]:
    """``(start, shortest, history)``: ``initial`` and the first :data:`START_SHARE` of
    the shortest prefix of the candidates' :func:`~torchmorph.selection.stratified.nested_order`
    that meets ``tolerance`` with them (of the budget when none does), ``initial`` with
    that prefix (None when none does), and the ``(controls, error)`` of every prefix tried."""
    count = oracle.points.shape[0]
    base = torch.from_numpy(_initial(initial, count))
    order = nested_order(oracle.points)
    order = order[~torch.isin(order, base)]
    budget = count if max_controls is None else min(check_budget(max_controls), count)
    limit = budget - len(base)
    history: list[tuple[int, float]] = []
    if limit <= 0:
        return base, None, history

    def errors(counts: list[int]) -> list[float]:
        values = oracle.prefix_errors(base, order, counts).tolist()
        history.extend((len(base) + n, value) for n, value in zip(counts, values, strict=True))
        return values

    length = stratified_count(errors, tolerance, limit)
    share = int(START_SHARE * (limit if length is None else length))
    shortest = None if length is None else torch.cat([base, order[:length]])
    return torch.cat([base, order[:share]]), shortest, history


def _checked_selection(
    candidates, targets, displacements, *, tolerance, max_controls, initial, **options
) -> tuple[GreedySelection, int]:
    """:func:`select_adaptive`, and the number of targets its error was measured at.

    When the targets are sampled, the selection's error is checked on every target
    (one full IDW evaluation for the reference, one of the selection per check); while
    it is above the tolerance (at most ``_CHECKS`` times) the targets of largest error,
    half a sample's worth, join those of the earlier checks in the sample, half a sample
    more is drawn at random among the others (each standing for its share of them), and
    the selection goes on from where it is.
    """
    loop = {key: options.pop(key) for key in ("min_batch", "spacing")}
    start = check_choice(options.pop("start"), "start", ("stratified", "empty"))
    loop["sequential"] = start == "stratified"
    if start == "stratified" and options.get("score_samples") is None:
        options["score_samples"] = STRATIFIED_SCORE_SAMPLES
    oracle = IDWErrorOracle(candidates, targets, displacements, **options)
    shortest: Tensor | None = None
    searched: list[tuple[int, float]] = []
    if start == "stratified":
        initial, shortest, searched = _stratified_start(oracle, tolerance, max_controls, initial)
    result = greedy_selection(
        oracle, tolerance=tolerance, max_controls=max_controls, initial=initial, **loop
    )
    result.history[:0] = searched
    if shortest is not None and len(shortest) < len(result.indices):
        result.indices = shortest  # the stratified prefix alone was shorter
        result.error = float(oracle.errors(shortest).max())
        result.converged, result.reason = result.error <= tolerance, "tolerance"
    num_targets = targets.shape[0]
    if len(oracle.sample) == num_targets:
        return result, num_targets
    points, family = oracle.points, oracle.family  # the family's distinct members
    weights = _weights(options.get("weights"), "weights", num_targets, points)
    targets = targets.to(points)
    with torch.no_grad():
        reference = idw_apply(
            controls=points, targets=targets, displacements=family, power=oracle.power
        )
        norm = (weights[None, :, None] * reference.square()).sum((1, 2))
        norm += (oracle.candidate_weights[None, :, None] * family.square()).sum((1, 2))
    generator = torch.Generator().manual_seed(DEFAULT_SEED + 1)
    certain = torch.zeros(num_targets, dtype=torch.bool)  # sampled for sure
    size = len(oracle.sample)
    for check in range(_CHECKS + 1):
        selected = result.indices.to(points.device)
        with torch.no_grad():
            field = idw_apply(
                controls=points[selected],
                targets=targets,
                displacements=family[:, selected],
                power=oracle.power,
            )
            shares = weights[None, :, None] * (field - reference).square() / norm[:, None, None]
            errors = torch.sqrt(shares.sum((1, 2)))
        result.error = float(errors.max())
        result.converged = result.error <= tolerance
        result.history.append((len(selected), result.error))
        if result.converged or result.reason != "tolerance" or check == _CHECKS:
            break
        # the targets of largest error join those of the earlier checks; as many again
        # are drawn at random among the others, each standing for its share of them
        order = torch.argsort(shares.sum((0, 2)).cpu(), descending=True)
        fresh = order[~certain[order]][: max(1, size // 2)]
        certain[fresh] = True
        worst = torch.nonzero(certain).flatten()
        rest = torch.nonzero(~certain).flatten()
        rest = rest[torch.randperm(len(rest), generator=generator)[: max(size // 2, 1)]]
        stands_for = (num_targets - len(worst)) / max(1, len(rest))
        scale = torch.cat([torch.ones(len(worst)), torch.full((len(rest),), stands_for)])
        options.update(sample=torch.cat([worst, rest]), sample_scale=scale)
        oracle = IDWErrorOracle(candidates, targets, displacements, **options)
        earlier = result
        result = greedy_selection(
            oracle,
            tolerance=tolerance,
            max_controls=max_controls,
            initial=earlier.indices,
            **loop,
        )
        result.rounds += earlier.rounds
        result.history[:0] = earlier.history
    return result, num_targets
