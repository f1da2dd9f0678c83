"""Error-driven selection of IDW control points: the adaptive alternative to SIDW/ESIDW.

Algorithm 1 (SIDW) spreads control points by distance, whatever the displacement does;
the paper names "an adaptive selection of the control points driven by some quantity of
interest" as future work (Ballarin et al. 2017, Section 4). Here the error of the
selective morph against full IDW (every candidate a control) chooses the controls:
:func:`select_adaptive` runs the greedy loop of :mod:`torchmorph.selection.greedy` with
:class:`IDWErrorOracle`, and :class:`~torchmorph.selection.plan.AdaptivePlan` does it
on a mesh for :class:`~torchmorph.morph.MeshMorph` (a drop-in for a
:class:`~torchmorph.selection.SelectionPlan`).

The error
---------
For a family of control displacements ``d_f`` (f = 1..F: several parameter values, or
POD training snapshots), the relative error of member f is

    err_f = sqrt(Σ_i w_i |u_S,f(x_i) - u_f(x_i)|²) / sqrt(Σ_i w_i |u_f(x_i)|² + Σ_c v_c |d_f,c|²)

over the targets ``x_i`` (interior nodes) with weights ``w_i`` and the candidates ``c``
(boundary nodes, exact in both fields) with weights ``v_c``; ``u_f`` is full IDW and
``u_S,f`` IDW from the selected candidates ``S`` only. With unit weights this is the
relative nodal ℓ2 error over the whole mesh (``torchmorph.mesh.norms.relative_nodal_error``),
the measure of the paper's tables; other weights give a quantity-of-interest variant
(e.g. weight 1 near a wall and 0 elsewhere). The loop stops when the worst member is
within the tolerance.

The scores
----------
With ``W`` the full IDW weights (rows: targets, columns: candidates), ``σ_i`` the sum
of row i of ``W`` over the selected candidates ``S`` and ``a_f,i = u_S,f(x_i)``, adding
one candidate j to ``S`` moves target i by exactly

    Δ_f,ij = t_ij (d_f,j - a_f,i),    t_ij = W_ij / (σ_i + W_ij),

so the decrease of ``Σ_f err_f²`` it brings, ``Σ_f Σ_i w_i (2 e_f,i · Δ_f,ij -
|Δ_f,ij|²) / n_f²`` (``e = u - u_S``, ``n_f`` the denominator above), is a handful of
products of ``T = (t_ij)`` and ``T²`` with fields on the targets: every candidate is
scored exactly, at the cost of one pass over the sampled ``W``. When no candidate
lowers the error on its own (from one control, a rotation needs controls on both sides
of its axis), the candidates are ranked by their first-order share of the error
instead, ``Σ_i w_i e_f,i · W_ij (d_f,j - a_f,i)``, which add up to it: the selective
field differs from full IDW by exactly ``Σ_{j ∉ S} W_ij (d_f,j - a_f,i)``.

This sees what a distance criterion cannot: thinning a densely sampled moving body
lowers its total weight in the far field of IDW, and the far field's error is then
charged to the body's nodes.

Cost
----
``W`` is assembled once on a sample of the targets (all of them when the sample fits
``sample_bytes``) by the fused kernels. A scoring is one pass over the sampled ``W``
(a numba kernel forms each candidate's ratios ``t_ij`` once and reduces them against the
fields' columns, ``T`` is never stored): about two full IDW evaluations when every
target is sampled. The greedy loop's trial prefixes extend the last scoring's selection,
so their errors add the new candidates' rows of ``W`` to the sums kept from it. Rounds
grow with the number of controls the tolerance needs and with how strongly candidates
pull the same targets (see benchmarks/adaptive.py).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchmorph._checks import as_points, check_float_dtype, check_positive, dim_of
from torchmorph.idw.functional import idw_apply, idw_weights
from torchmorph.selection import _score_jit
from torchmorph.selection.greedy import (
    ErrorOracle,
    GreedySelection,
    greedy_selection,
)
from torchmorph.selection.sidw import DEFAULT_SEED, _check_generator

__all__ = [
    "DEFAULT_SAMPLE_BYTES",
    "DEFAULT_SCORE_SAMPLES",
    "ErrorOracle",
    "GreedySelection",
    "IDWErrorOracle",
    "greedy_selection",
    "select_adaptive",
]

#: Largest size of the sampled full-IDW weights (targets × candidates) an oracle keeps:
#: the targets are sampled down to fit it (256 MiB: 2,300 targets of case B's 14,126
#: candidates in float64).
DEFAULT_SAMPLE_BYTES = 256 * 2**20

#: Targets whose errors score the candidates (the first of the sample; None: all of it).
#: Fewer make a scoring cheaper but the scores noisier: more rounds and more controls
#: (case C at 1.26 %: 450 controls with 1,024, 358 with all 3,173).
DEFAULT_SCORE_SAMPLES = None

# Checks of a sampled selection on every target, each followed by a new sample.
_CHECKS = 8

# Rows of the sampled weights are scored in blocks of about this many bytes.
_SCORE_BLOCK_BYTES = 4 * 2**20


class IDWErrorOracle:
    """Error of selective IDW against full IDW on sampled targets, and candidate scores.

    Parameters
    ----------
    candidates : Tensor, shape (N_c, D)
        Points that may become controls (a mesh's boundary nodes). Full IDW uses all.
    targets : Tensor, shape (N_t, D)
        Points the error is measured at (a mesh's interior nodes), ``N_t >= 1``.
    displacements : Tensor, shape (N_c, D) or (F, N_c, D)
        The family of candidate displacements; the error is the worst over it. Members
        that are multiples of one another (same relative errors) count once.
    weights : Tensor, shape (N_t,), optional
        Weight ``w_i >= 0`` of each target in the error (default 1); not all zero.
    candidate_weights : Tensor, shape (N_c,), optional
        Weight ``v_c >= 0`` of each candidate in the norm of the reference (default 1).
    power : float, default 4
        IDW exponent p.
    num_samples : int, optional
        Number of targets sampled (uniformly, without replacement); default: as many
        as fit ``sample_bytes``, all of them when they do.
    sample_bytes : int, default :data:`DEFAULT_SAMPLE_BYTES`
        Memory budget of the sampled weights when ``num_samples`` is not given.
    score_samples : int, optional
        Score the candidates on the first this many targets of the sample only
        (default :data:`DEFAULT_SCORE_SAMPLES`: all of them).
    generator : torch.Generator, optional
        CPU generator of the sample; default seeded with ``DEFAULT_SEED``.

    Attributes
    ----------
    points : Tensor (N_c, D)
        The candidates.
    sample : Tensor (N_s,), int64
        Indices of the sampled targets, in random order.

    Notes
    -----
    With a sample, sums over the targets are estimated by the sample's sum times
    ``N_t / N_s``; the reported errors are then estimates (the final morph's error is
    measured on every node by the caller). Computations run in the candidates'
    dtype, without autograd.
    """

    def __init__(
        self,
        candidates: Tensor,
        targets: Tensor,
        displacements: Tensor,
        *,
        weights: Tensor | None = None,
        candidate_weights: Tensor | None = None,
        power: float = 4.0,
        num_samples: int | None = None,
        sample_bytes: int = DEFAULT_SAMPLE_BYTES,
        score_samples: int | None = DEFAULT_SCORE_SAMPLES,
        generator: torch.Generator | None = None,
        sample: Tensor | None = None,
        sample_scale: Tensor | None = None,
    ) -> None:
        candidates = as_points(candidates, "candidates", dim=dim_of(candidates))
        dim = candidates.shape[1]
        targets = as_points(targets, "targets", dim=dim)
        targets = targets.to(candidates.dtype)
        family = _family(displacements, candidates.shape[0], dim).to(candidates.dtype)
        self.power = check_positive(power, "power")
        n_targets, n_candidates = targets.shape[0], candidates.shape[0]
        target_weights = _weights(weights, "weights", n_targets, candidates)
        self.candidate_weights = _weights(
            candidate_weights, "candidate_weights", n_candidates, candidates
        )
        if not bool((target_weights > 0).any()):
            raise ValueError("weights are all zero: no target counts in the error")
        if num_samples is None:
            itemsize = candidates.element_size()
            if not isinstance(sample_bytes, int) or sample_bytes < 1:
                raise ValueError(f"sample_bytes must be an integer >= 1, got {sample_bytes!r}")
            num_samples = max(1, min(n_targets, sample_bytes // (n_candidates * itemsize)))
        elif isinstance(num_samples, bool) or not isinstance(num_samples, int) or num_samples < 1:
            raise ValueError(f"num_samples must be an integer >= 1, got {num_samples!r}")
        num_samples = min(num_samples, n_targets) if sample is None else len(sample)
        if score_samples is not None and (
            isinstance(score_samples, bool)
            or not isinstance(score_samples, int)
            or score_samples < 1
        ):
            raise ValueError(f"score_samples must be an integer >= 1, got {score_samples!r}")
        if sample is None:  # in random order: the first ``score_samples`` are a sample too
            sample = torch.randperm(n_targets, generator=_check_generator(generator))
            sample = sample[:num_samples]
            sample_scale = torch.full((num_samples,), n_targets / num_samples)
        self.sample = sample
        self.score_samples = (
            num_samples if score_samples is None else min(score_samples, num_samples)
        )
        sample = self.sample.to(candidates.device)
        self.points = candidates.detach()
        scale = torch.as_tensor(sample_scale, dtype=candidates.dtype, device=candidates.device)
        with torch.no_grad():
            self.targets = targets.detach()[sample]
            # w_i times how many targets the sampled one stands for
            self.target_weights = target_weights[sample] * scale
            self.family = family.detach()  # (F, N_c, D)
            self.weights_t = self._transposed_weights()  # (N_c, N_s): Wᵀ, rows contiguous
            self.reference = self._field(self.weights_t.mT @ self._columns(self.family))
            reference_sq = self._weighted_squares(self.reference) + (
                self.candidate_weights[None, :, None] * self.family.square()
            ).sum((1, 2))
        zero = torch.nonzero(reference_sq <= 0).flatten()
        if zero.numel():
            raise ValueError(
                f"displacements: member {int(zero[0])} of the family has a zero reference "
                "field (in the weighted norm): its relative error is undefined"
            )
        # members equal up to a factor have the same relative error: keep one of each
        kept = _distinct_up_to_scale(self.family)
        self.family, self.reference = self.family[kept], self.reference[kept]
        self.reference_sq = reference_sq[kept]
        columns = self._columns(self.family)
        self._with_ones = torch.cat([columns, columns.new_ones(columns.shape[0], 1)], dim=1)
        # the selection of the last scoring and its accumulated sums (see _accumulated)
        self._base = (torch.zeros(0, dtype=torch.int64, device=self.points.device), columns)

    def _transposed_weights(self) -> Tensor:
        """Full IDW's weights from every candidate to the sampled targets, stored as
        ``Wᵀ`` (N_c, N_s) so that the rows of any subset of candidates are contiguous;
        assembled in blocks of targets by the fused kernels."""
        num_targets = self.targets.shape[0]
        out = self.points.new_empty(self.points.shape[0], num_targets)
        rows = max(1, _SCORE_BLOCK_BYTES // (self.points.shape[0] * self.points.element_size()))
        for begin in range(0, num_targets, rows):
            block = idw_weights(
                controls=self.points, targets=self.targets[begin : begin + rows], power=self.power
            )
            out[:, begin : begin + rows] = block.mT
        return out

    @property
    def num_members(self) -> int:
        return int(self.family.shape[0])

    def _columns(self, family: Tensor) -> Tensor:
        """(F, N_c, D) -> (N_c, F·D)."""
        return family.permute(1, 0, 2).reshape(family.shape[1], -1)

    def _weighted_squares(self, field: Tensor) -> Tensor:
        """``Σ_s w_s c_s |field_s|²`` per member, shape (F,): ``c_s`` the number of
        targets sampled target s stands for."""
        return (self.target_weights[None, :, None] * field.square()).sum((1, 2))

    def _selective(self, selected: Tensor) -> tuple[Tensor, Tensor]:
        """IDW from the candidates ``selected`` at the sampled targets, (F, N_s, D), and
        ``σ_i = Σ_{k∈S} W_ik`` (N_s,): ``W_S = W[:, S] / σ``."""
        if selected.numel() == 0:
            return torch.zeros_like(self.reference), self.reference.new_zeros(len(self.sample))
        selected = selected.to(self.points.device)
        both = self._accumulated(selected)
        sums = both[:, -1]
        tiny = torch.finfo(sums.dtype).tiny / torch.finfo(sums.dtype).eps
        field = self._field(both[:, :-1] / sums[:, None].clamp_min(tiny))
        lost = torch.nonzero(sums <= tiny).flatten()
        if lost.numel():  # a target on an unselected candidate, or weights that underflowed
            field[:, lost] = idw_apply(
                controls=self.points[selected],
                targets=self.targets[lost],
                displacements=self.family[:, selected],
                power=self.power,
            )
        return field, sums

    def _accumulated(self, selected: Tensor) -> Tensor:
        """``Σ_{k∈S} W_ik [d_k | 1]`` at the sampled targets, (N_s, F·D + 1). When
        ``selected`` extends the selection of the last scoring (the greedy loop's
        prefixes do), only the added candidates' rows are read."""
        base, sums = self._base
        start = 0
        if 0 < base.numel() <= selected.numel() and torch.equal(selected[: base.numel()], base):
            start = base.numel()
        added = selected[start:]
        if not added.numel():
            return sums
        weights = self.weights_t.index_select(0, added)  # (|added|, N_s): W's columns
        product = weights.mT @ self._with_ones.index_select(0, added)
        return product if start == 0 else sums + product

    def _field(self, flat: Tensor) -> Tensor:
        num_members, dim = self.family.shape[0], self.family.shape[2]
        return flat.reshape(flat.shape[0], num_members, dim).permute(1, 0, 2)

    def _flat(self, field: Tensor) -> Tensor:
        """(F, N_s, K) -> (N_s, F·K)."""
        return field.permute(1, 0, 2).reshape(field.shape[1], -1)

    def errors(self, selected: Tensor) -> Tensor:
        """Relative error of each member with ``selected`` as controls, shape (F,)."""
        with torch.no_grad():
            error = self.reference - self._selective(selected)[0]
            return torch.sqrt(self._weighted_squares(error) / self.reference_sq)

    def scores(self, selected: Tensor) -> tuple[Tensor, Tensor]:
        """``(errors (F,), scores (N_c,))``. A candidate's score is the decrease of
        ``Σ_f err_f²`` that adding it alone to ``selected`` brings (see the module's
        notes) or, when no candidate alone lowers it, its first-order share of
        ``Σ_f err_f²``; ``-inf`` for the selected ones."""
        with torch.no_grad():
            selected = selected.to(self.points.device)
            if selected.numel():  # later prefixes of the greedy loop start from these sums
                self._base = (selected.clone(), self._accumulated(selected))
            approx, sums = self._selective(selected)
            error = self.reference - approx
            errors = torch.sqrt(self._weighted_squares(error) / self.reference_sq)
            count = self.score_samples  # the scores read the first targets of the sample
            gains = self._gains(error[:, :count], approx[:, :count], sums[:count], selected)
        return errors, gains

    def _gains(self, error: Tensor, approx: Tensor, sums: Tensor, selected: Tensor) -> Tensor:
        """``Σ_f (|e_f|² - |e_f - Δ_f,j|²)_w / n_f²`` per candidate j, where adding j moves
        target i by ``Δ_f,ij = t_ij (d_f,j - a_f,i)``, ``t_ij = W_ij / (σ_i + W_ij)``."""
        num_members, dim = self.family.shape[0], self.family.shape[2]
        count = sums.shape[0]
        weight = self.target_weights[None, :count, None] / self.reference_sq[:, None, None]
        we = weight * error
        wa = weight * approx
        # Σ_i t_ij [...] and Σ_i t_ij² [...] as products of T and T² with these columns
        linear = torch.cat([self._flat(we), self._flat((we * approx).sum(-1, keepdim=True))], 1)
        square = torch.cat(
            [
                self._flat(weight),
                self._flat(wa),
                self._flat((wa * approx).sum(-1, keepdim=True)),
            ],
            1,
        )
        weights_t = self.weights_t[:, :count]
        if _score_jit.available(self.weights_t):  # one pass over Wᵀ, T never formed
            first, second = _score_jit.score_rows(self.weights_t, count, sums, linear, square)
            first, second = first.to(linear.dtype), second.to(square.dtype)
        else:
            first = linear.new_empty(self.points.shape[0], linear.shape[1])
            second = square.new_empty(self.points.shape[0], square.shape[1])
            tiny = torch.finfo(sums.dtype).tiny
            rows = max(1, _SCORE_BLOCK_BYTES // (count * weights_t.element_size()))
            for begin in range(0, weights_t.shape[0], rows):
                block = weights_t[begin : begin + rows]  # candidates' rows of Wᵀ
                end = begin + block.shape[0]
                ratio = block / (sums[None, :] + block).clamp_min(tiny)
                torch.mm(ratio, linear, out=first[begin:end])
                torch.mm(ratio.square_(), square, out=second[begin:end])
        family = self.family  # (F, N_c, D)
        gain = 2.0 * self._linear_term(first)
        q = second[:, :num_members].mT
        g2 = second[:, num_members : num_members * (dim + 1)]
        g2 = g2.reshape(-1, num_members, dim).permute(1, 0, 2)
        h2 = second[:, num_members * (dim + 1) :].mT
        gain -= family.square().sum(-1) * q - 2.0 * (family * g2).sum(-1) + h2
        gain = gain.sum(0)
        selected = selected.to(gain.device)
        gain[selected] = -math.inf
        if selected.numel() and bool((gain > 0).any()):
            return gain
        # no candidate alone lowers the error (from one control, a rotation needs
        # controls on both sides of its axis): rank by the first-order shares instead
        share = self._linear_term(weights_t @ linear).sum(0)
        share[selected] = -math.inf
        return share

    def _linear_term(self, product: Tensor) -> Tensor:
        """``d_f,j · g_f,j - h_f,j`` (F, N_c) from ``[g | h]`` (N_c, F·D + F)."""
        num_members, dim = self.family.shape[0], self.family.shape[2]
        g = product[:, : num_members * dim].reshape(-1, num_members, dim).permute(1, 0, 2)
        h = product[:, num_members * dim :].mT
        return (self.family * g).sum(-1) - h


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

    Returns
    -------
    GreedySelection
        ``indices`` into ``candidates`` (initial ones first), the final worst error
        (estimated on the sample), whether it converged and the history.

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
    )[0]


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
    oracle = IDWErrorOracle(candidates, targets, displacements, **options)
    result = greedy_selection(
        oracle, tolerance=tolerance, max_controls=max_controls, initial=initial, **loop
    )
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


def _distinct_up_to_scale(family: Tensor) -> Tensor:
    """Indices of the members of ``family`` (F, N, D) that are no multiple of an earlier
    one (a family linear in one parameter, δ = μ f, collapses to one member)."""
    flat = family.reshape(family.shape[0], -1)
    unit = flat / torch.linalg.vector_norm(flat, dim=1, keepdim=True)
    parallel = (unit @ unit.mT).abs() >= 1 - 64 * torch.finfo(unit.dtype).eps
    kept = [0]
    for member in range(1, family.shape[0]):
        if not bool(parallel[member, kept].any()):
            kept.append(member)
    return torch.tensor(kept, dtype=torch.int64, device=family.device)


def _family(displacements: Tensor, count: int, dim: int) -> Tensor:
    if not isinstance(displacements, Tensor):
        raise TypeError(f"displacements must be a torch.Tensor, got {type(displacements).__name__}")
    if displacements.ndim not in (2, 3) or displacements.shape[-2:] != (count, dim):
        raise ValueError(
            f"displacements must have shape ({count}, {dim}) or (F, {count}, {dim}) for "
            f"{count} candidates, got {tuple(displacements.shape)}"
        )
    check_float_dtype(displacements, "displacements")
    if not bool(torch.isfinite(displacements).all()):
        bad = int((~torch.isfinite(displacements)).sum())
        raise ValueError(f"displacements holds {bad} NaN or infinite value(s)")
    if displacements.shape[0] == 0:
        raise ValueError("displacements is an empty family (F = 0)")
    return displacements if displacements.ndim == 3 else displacements[None]


def _weights(value: Tensor | None, name: str, count: int, like: Tensor) -> Tensor:
    if value is None:
        return torch.ones(count, dtype=like.dtype, device=like.device)
    value = torch.as_tensor(value)
    if value.shape != (count,):
        raise ValueError(f"{name} must have shape ({count},), got {tuple(value.shape)}")
    value = value.to(device=like.device, dtype=like.dtype)
    if not bool(torch.isfinite(value).all()):
        raise ValueError(f"{name} holds NaN or infinite value(s)")
    if bool((value < 0).any()):
        raise ValueError(f"{name} holds negative value(s); weights must be >= 0")
    return value
