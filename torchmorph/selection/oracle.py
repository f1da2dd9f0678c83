"""The error of selective IDW against full IDW, and the scores of candidate controls:
:class:`IDWErrorOracle`, the oracle of the error-driven selection
(:mod:`torchmorph.selection.adaptive`) in the loop of :mod:`torchmorph.selection.greedy`.

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
``sample_bytes``) by a numba kernel that writes ``Wᵀ`` (one row per candidate) and sums
the reference field as it goes: about two full IDW evaluations when every target is
sampled. A scoring is one pass over the first ``score_samples`` targets of it (a numba
kernel forms each candidate's ratios ``t_ij`` once and reduces them against the fields'
columns, four candidates at a time; ``T`` is never stored). The errors of the start's
prefixes, and of the greedy loop's trial selections, add the new candidates' rows of
``W`` to sums kept from the shorter ones. A pick reads the pool's rows of ``W`` once per
added candidate."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from torchmorph._checks import as_points, check_float_dtype, check_positive, dim_of
from torchmorph.idw._dispatch import backend_for
from torchmorph.idw._geometry import prepare
from torchmorph.idw.functional import DEFAULT_COINCIDENCE_TOLERANCE, idw_apply, idw_weights
from torchmorph.selection import _score_jit
from torchmorph.selection.sidw import _check_generator

__all__ = ["DEFAULT_SAMPLE_BYTES", "DEFAULT_SCORE_SAMPLES", "IDWErrorOracle"]

#: Largest size of the sampled full-IDW weights (targets × candidates) an oracle keeps:
#: the targets are sampled down to fit it (256 MiB: 2,300 targets of case B's 14,126
#: candidates in float64).
DEFAULT_SAMPLE_BYTES = 256 * 2**20

#: Targets whose errors score the candidates (the first of the sample; None: all of it).
#: Fewer make a scoring cheaper but the scores noisier: more rounds and more controls
#: (case C at 1.26 %, ``start="empty"``: 450 controls with 1,024, 358 with all 3,173).
DEFAULT_SCORE_SAMPLES = None

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
            columns = self._columns(self.family)
            with_ones = torch.cat([columns, columns.new_ones(len(columns), 1)], 1)
            # (N_c, N_s): Wᵀ, rows contiguous; W @ [d | 1] (N_s, F·D + 1)
            self.weights_t, both = self._transposed_weights(with_ones)
            self._column_sums = both[:, -1]  # Wᵀ's columns are W's rows up to these
            self.reference = self._field(both[:, :-1] / self._column_sums[:, None])
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
        # the last prefix_errors' base, order and sums by prefix length
        self._prefixes: tuple[Tensor | None, Tensor | None, dict[int, Tensor]] = (None, None, {})

    def _transposed_weights(self, values: Tensor) -> tuple[Tensor, Tensor]:
        """Full IDW's weights from every candidate to the sampled targets, stored as
        ``Wᵀ`` (N_c, N_s) so that the rows of any subset of candidates are contiguous,
        each target's column up to a factor (every use is a ratio within a column), and
        ``Wᵀᵀ @ values``: on the CPU in one pass of
        :func:`_score_jit.weights_transposed`, elsewhere assembled in blocks of targets
        by the fused kernels."""
        num_targets = self.targets.shape[0]
        shape = (self.points.shape[0], num_targets)
        if _score_jit.available(self.points) and self.points.dtype == torch.float64:
            # numpy's allocation: the C heap keeps a freed block for the next oracle
            # (a fresh 100 MB block of torch's costs 3× its writing in page faults)
            out = torch.from_numpy(np.empty(shape))
            targets, points, power, radius2 = prepare(
                self.targets, self.points, self.power, DEFAULT_COINCIDENCE_TOLERANCE
            )
            nearest = backend_for("auto", targets, points).nearest(targets, points)
            product = _score_jit.weights_transposed(
                points, targets, nearest, power, radius2, values, out
            )
            return out, product
        out = self.points.new_empty(shape)
        rows = max(1, _SCORE_BLOCK_BYTES // (self.points.shape[0] * self.points.element_size()))
        for begin in range(0, num_targets, rows):
            block = idw_weights(
                controls=self.points, targets=self.targets[begin : begin + rows], power=self.power
            )
            out[:, begin : begin + rows] = block.mT
        return out, (values.mT @ out).mT

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

    def _selective(self, selected: Tensor, both: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """IDW from the candidates ``selected`` at the sampled targets, (F, N_s, D), and
        ``σ_i = Σ_{k∈S} W_ik`` (N_s,): ``W_S = W[:, S] / σ``; from their accumulated
        sums ``both`` when given."""
        if selected.numel() == 0:
            return torch.zeros_like(self.reference), self.reference.new_zeros(len(self.sample))
        selected = selected.to(self.points.device)
        both = self._accumulated(selected) if both is None else both
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

    def prefix_errors(self, base: Tensor, order: Tensor, counts: list[int]) -> Tensor:
        """Worst error over the family, shape (len(counts),), with the candidates
        ``base`` and the first n of ``order`` as controls, for each n of the increasing
        ``counts``: each prefix adds its new candidates' rows of ``W`` to the sums of the
        longest shorter one evaluated (by this call or, for the same ``base`` and
        ``order``, the last one); ``order`` disjoint from ``base``."""
        with torch.no_grad():
            if self._prefixes[0] is not base or self._prefixes[1] is not order:
                start = self._accumulated(base.to(self.points.device))
                self._prefixes = (base, order, {0: start})
            known = self._prefixes[2]
            base, order = base.to(self.points.device), order.to(self.points.device)
            worst = []
            for count in counts:
                done = max(n for n in known if n <= count)
                both = known[done]
                if count > done:
                    both = known[count] = both + self._row_sums(order[done:count])
                selected = torch.cat([base, order[:count]])
                error = self.reference - self._selective(selected, both)[0]
                worst.append(torch.sqrt(self._weighted_squares(error) / self.reference_sq).max())
        return torch.stack(worst)

    def _accumulated(self, selected: Tensor) -> Tensor:
        """``Σ_{k∈S} W_ik [d_k | 1]`` at the sampled targets, (N_s, F·D + 1). When
        ``selected`` extends the selection of the last scoring (the greedy loop's
        prefixes do), only the added candidates' rows are read."""
        if not selected.numel():
            return self._with_ones.new_zeros(len(self.sample), self._with_ones.shape[1])
        base, sums = self._base
        start = 0
        if 0 < base.numel() <= selected.numel() and torch.equal(selected[: base.numel()], base):
            start = base.numel()
        added = selected[start:]
        if not added.numel():
            return sums
        product = self._row_sums(added)
        return product if start == 0 else sums + product

    def _row_sums(self, added: Tensor) -> Tensor:
        """``Σ_{k∈added} W_ik [d_k | 1]`` at the sampled targets, (N_s, F·D + 1)."""
        values = self._with_ones.index_select(0, added)
        if _score_jit.available(self.weights_t) and self.weights_t.dtype == torch.float64:
            out = values.new_zeros(values.shape[1], self.weights_t.shape[1])
            _score_jit.accumulate(self.weights_t, added.cpu(), values, out)
            return out.mT  # the rows of W in place
        return (values.mT @ self.weights_t.index_select(0, added)).mT

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

    def pick(self, selected: Tensor, pool: Tensor, tolerance: float, limit: int) -> Tensor | None:
        """Candidates of ``pool`` (best first; its first ``max(16, len(pool) // F)``
        for F members, each costing F times the work) added to ``selected`` one at a
        time, each the one that lowers ``Σ_f err_f²`` most at the sampled targets
        (exactly: the sums are updated after each), until the worst error is at most
        ``tolerance``, ``limit`` are added or none lowers it (the greedy loop's step;
        see its notes). None where the numba kernels do not serve these weights."""
        if not (_score_jit.available(self.weights_t) and self.weights_t.dtype == torch.float64):
            return None
        with torch.no_grad():
            selected = selected.to(self.points.device)
            both = self._accumulated(selected)
            approx = self._selective(selected, both)[0]
            totals = self._weighted_squares(self.reference - approx) / self.reference_sq
            omega = self.target_weights[None, :] / self.reference_sq[:, None]
            return _score_jit.pick(
                self.weights_t,
                pool.cpu()[: max(16, len(pool) // self.num_members)],
                both[:, -1],
                self._field(both[:, :-1]),
                approx,
                self.reference,
                omega,
                self.family,
                totals,
                tolerance**2,
                limit,
            )

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
        share = self._linear_term(weights_t @ (linear / self._column_sums[:count, None])).sum(0)
        share[selected] = -math.inf
        return share

    def _linear_term(self, product: Tensor) -> Tensor:
        """``d_f,j · g_f,j - h_f,j`` (F, N_c) from ``[g | h]`` (N_c, F·D + F)."""
        num_members, dim = self.family.shape[0], self.family.shape[2]
        g = product[:, : num_members * dim].reshape(-1, num_members, dim).permute(1, 0, 2)
        h = product[:, num_members * dim :].mT
        return (self.family * g).sum(-1) - h


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
