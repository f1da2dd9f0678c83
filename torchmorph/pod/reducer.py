"""POD-reduced morphing: POD-(E)SIDW, Algorithm 3 of Ballarin et al. (2017), section 3.

The IDW (or selective IDW) map ``d_int = W d_sel`` is linear, but ``W`` is large:
N_int × N_sel entries, read once per parameter value. For a parametrized family of
control displacements ``d_sel(μ)`` the interior fields ``W d_sel(μ)`` usually lie
close to a space of very few dimensions. :class:`PODReducer` finds that space
offline (proper orthogonal decomposition of snapshots) and, online, maps an input
displacement to the reduced coefficients with an N × D·N_in matrix, so that a new
parameter value costs O(N·N_in + N·N_out) instead of O(N_int·N_sel).

:class:`PODReducer` reduces any linear map from an input displacement (N_in, D) to
an output field (N_out, D) (D = 2 or 3: fields of 2-D or 3-D points) — an
:class:`~torchmorph.idw.IDW`, a
:class:`~torchmorph.morph.MeshMorph`, or a user's module — through a small protocol
(see :class:`PODReducer`); it never asks which class the map is. The maths lives in
:mod:`torchmorph.pod.functional` (:func:`pod_basis`, :func:`projection_matrix`,
:func:`paper_matrices`), re-exported here; its online phase and state are those of every
reducer (:mod:`torchmorph.pod._base`, shared with
:class:`~torchmorph.distributed.ShardedPOD`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, Literal

import torch
from torch import Tensor, nn

from torchmorph.pod._base import PODBase
from torchmorph.pod._protocol import (
    adjoint,
    check_online,
    evaluate_family,
    is_single_value,
    morph_snapshots,
    reference_tensor,
    relative_field_error,
    spread_modes,
    training_data,
    weights_of,
)
from torchmorph.pod.functional import (
    paper_matrices,
    pod_basis,
    projection_matrix,
)

__all__ = [
    "PODReducer",
    "paper_matrices",
    "pod_basis",
    "projection_matrix",
]

OnlineVariant = Literal["projection", "paper"]

Family = Callable[[Tensor], Tensor]


class PODReducer(PODBase):
    """POD-reduced morph: POD-(E)SIDW, Algorithm 3 of the paper.

    Construct with hyper-parameters only, then :meth:`fit` to a morph and training
    data; afterwards ``reducer(displacement)`` returns what ``morph(displacement)``
    would, computed from the N-dimensional POD space.

    Parameters
    ----------
    energy_tolerance : float, default 1e-5
        ε in (0, 1): the number of modes N is the smallest with
        ``sum_{i>N} σ_i² <= ε · sum_i σ_i²`` (the paper's relative energy criterion,
        eq. 12).
    num_modes : int, optional
        Keep exactly this many modes instead (``fit`` raises if the snapshots have
        fewer, or lower rank).
    online : {"projection", "paper"}, default "projection"
        How the coefficients β of ``d_red ≈ Z β`` are obtained online:
        ``"projection"``: ``β = Zᵀ L d`` through the precomputed P = Zᵀ L
        (N × D·N_in), the orthogonal projection of the full morph onto the POD space;
        ``"paper"``: solve ``A β = B d_sel`` of the paper's eq. 16 with
        A = Zᵀ(W⁺)ᵀW⁺Z and B = Zᵀ(W⁺)ᵀ (needs the pseudo-inverse of W offline).

    Attributes
    ----------
    modes_ : Tensor (N, N_red, D)
        (This and the following are set by ``fit``.) Orthonormal POD basis (``Z``),
        mode l as a displacement field of the reduced output rows ``reduced_rows_``.
    singular_values_ : Tensor (k,)
        Singular values of the snapshot matrix, descending (k = min(n_train, D·N_red));
        see :func:`pod_basis` for their accuracy.
    energy_captured_ : Tensor (k,)
        Cumulative energy fraction kept by 1, 2, ..., k modes.
    num_modes_ : int
        N, the number of modes kept.
    projection_ : Tensor (N, N_in, D)
        P for ``online="projection"`` (empty otherwise).
    system_matrix_, rhs_matrix_ : Tensor (N, N), (N, N_in, D)
        A and B of eq. 16 for ``online="paper"`` (empty otherwise); B is zero on
        input rows that W does not read.
    copied_output_rows_, copied_input_rows_ : Tensor (N_copy,)
        Output rows that the morph copies from input rows (a MeshMorph's boundary
        nodes); reproduced exactly, not reduced.
    reduced_rows_ : Tensor (N_red,)
        The other output rows, in increasing order: the rows of ``modes_``.
    offline_time_ : dict[str, float]
        Wall-clock seconds of the offline phase: ``"snapshots"``, ``"svd"``,
        ``"online_matrices"``, ``"total"``.
    family : callable or None
        The displacement family given to ``fit`` (not saved by ``state_dict``).

    Notes
    -----
    * **The morph protocol.** ``fit`` needs a linear map ``morph(d)``, ``d`` of shape
      (B, N_in, D) to (B, N_out, D), differentiable in ``d`` (or with an ``adjoint``
      method). Optional methods make it faster or exact: ``copied_rows()`` returns
      (output rows, input rows) that ``morph`` copies unchanged (not reduced, exact);
      a stored matrix ``weights`` (N_red, len(weight_columns)) gives P by one GEMM;
      else ``adjoint(fields)`` applies the transpose, (B, N_out, D) to (B, N_in, D);
      else autograd computes it from one vector-Jacobian product;
      ``weights_matrix()`` returns W with ``morph(d)[:, reduced_rows] =
      W @ d[:, weight_columns]`` per component, and the attribute ``weight_columns``
      (default: every input row), for ``online="paper"``. :class:`~torchmorph.idw.IDW`
      and :class:`~torchmorph.morph.MeshMorph` follow it; the map's dtype and device
      are those of its first floating buffer or parameter, D that of the training
      inputs (the morph's output must have it too). A map whose attribute
      ``num_global_outputs`` exceeds its rows is one rank's share of a sharded map
      (:mod:`torchmorph.distributed`): it is refused, its POD is
      :class:`~torchmorph.distributed.ShardedPOD`'s.
    * State is in buffers: ``state_dict()`` saves a fitted reducer (the morph and
      ``W`` are not part of it) and ``load_state_dict`` into any ``PODReducer``
      restores it, hyper-parameters, shapes and floating dtype included; a state
      whose parts do not fit together is refused before anything is loaded, with a
      ``ValueError`` naming the entry. ``.to(device, dtype)`` moves it.
    * ``forward`` checks shapes, dtype and device but not finiteness (that would
      cost more than the reduced product); NaN inputs give NaN outputs.
    * The reduced morph is exact only on the span of the training fields; check
      new parameter ranges with :meth:`relative_error`.
    * Offline cost: one batched morph of the training inputs, the POD basis (method
      of snapshots, milliseconds), and the transpose of the map applied to N modes
      (``projection``: one GEMM with a dense W, autograd through a matrix-free one)
      — seconds at case-B size. ``paper`` needs ``W⁺ Z``: a least-squares solve
      with the dense W, O(N_int·N_sel²), about 20 minutes at case-B size on 2 cores
      (extrapolated, benchmarks/README.md).
    * Online cost: one (B × D·N_in) · (D·N_in × N) product and one (B × N) ·
      (N × D·N_out) product (for ``paper`` also an N × N solve), plus the copy of
      the copied rows. When the copied and reduced rows form a few contiguous runs
      (any numbering that keeps them in blocks), the product is computed per run
      without the zero rows; otherwise one full product and an indexed copy. A
      large batch is bound by writing its output; pass ``out=`` to reuse one.
    * ``fit`` keeps a plain reference to the morph (for :meth:`relative_error`); it
      is not part of ``state_dict`` but is copied by ``copy.deepcopy`` / pickling.
    """

    _FITTED = (*PODBase._FITTED, "num_parameters_")
    _FIT_HINT = "call fit(morph, displacements) or fit(morph, family=..., parameters=...) first"

    def __init__(
        self,
        *,
        energy_tolerance: float = 1e-5,
        num_modes: int | None = None,
        online: OnlineVariant = "projection",
    ) -> None:
        super().__init__(energy_tolerance=energy_tolerance, num_modes=num_modes)
        self.online = check_online(online)
        self.family: Family | None = None
        self._family_batched: bool = True
        self._morph: Any = None

    # ---------------------------------------------------------------- offline phase

    def fit(
        self,
        morph: Callable[[Tensor], Tensor],
        displacements: Tensor | None = None,
        *,
        family: Family | None = None,
        parameters: Tensor | None = None,
        batched: bool = True,
    ) -> PODReducer:
        """Offline phase of Algorithm 3: snapshots, POD basis, online matrices.

        Parameters
        ----------
        morph : linear map
            The full morph, (B, N_in, D) -> (B, N_out, D), following the protocol in
            the class notes. For an :class:`~torchmorph.idw.IDW` the inputs are
            control displacements and the output the targets'. For a
            :class:`~torchmorph.morph.MeshMorph` the inputs are boundary
            displacements and the output every node's; the boundary rows are copied
            exactly and only the interior field ``W d_sel`` is reduced.
        displacements : Tensor, shape (n_train, N_in, D), optional
            Training inputs. Converted to the morph's dtype and device.
        family : callable, optional
            Instead of ``displacements``: ``family(mu)`` returns the input
            displacement for parameter value(s) ``mu``. Kept as ``self.family`` for
            :meth:`morph_parameters`.
        parameters : Tensor, shape (n_train,) or (n_train, P)
            Training parameter values for ``family``.
        batched : bool, default True
            How ``family`` is called. ``True``: once with all parameters, returning
            (n_train, N_in, D); an exception of the family propagates, and another
            shape is a ``ValueError``. ``False``: once per parameter value (a 0-d
            tensor or a (P,) tensor), returning (N_in, D); the results are stacked.
            Either way the morph is applied once, to the whole batch. (To vectorise
            a per-value family without a loop, pass ``torch.func.vmap(family)``.)
            :meth:`morph_parameters` calls the fitted family the same way.

        Returns
        -------
        PODReducer
            ``self``, fitted.

        Raises
        ------
        TypeError
            If ``morph`` is not callable.
        ValueError
            For missing / conflicting training data, wrong shapes, NaN or inf in the
            training data, a morph output that is not (n_train, N_out, D), all-zero
            snapshots, ``num_modes`` larger than the number or rank of the
            snapshots, ``online="paper"`` with a morph without
            ``weights_matrix()``, or a morph that returns one rank's rows of a
            sharded map (its ``num_global_outputs`` exceeds its rows: its POD needs
            every rank, :class:`~torchmorph.distributed.ShardedPOD`).
        """
        if not callable(morph):
            raise TypeError(f"morph must be a callable linear map, got {type(morph).__name__}")
        start = time.perf_counter()
        reference = reference_tensor(morph)
        with torch.no_grad():
            inputs, num_parameters = training_data(displacements, family, parameters, batched)
            if reference is not None:
                inputs = inputs.to(device=reference.device, dtype=reference.dtype)
            num_inputs = inputs.shape[1]

            # (b) snapshots: one batched application of the morph
            snapshots, rows, num_outputs = morph_snapshots(morph, inputs)
            whole = getattr(morph, "num_global_outputs", num_outputs)
            if whole != num_outputs:
                raise ValueError(
                    f"morph returns {num_outputs} of the {whole} rows of a sharded map: a "
                    "POD of one rank's rows is not the map's; fit a "
                    "torchmorph.distributed.ShardedPOD on every rank instead"
                )
            after_snapshots = time.perf_counter()

            # (c)-(d) POD basis
            modes, singular_values, energy_captured = pod_basis(
                snapshots, energy_tolerance=self.energy_tolerance, num_modes=self.num_modes
            )
            after_svd = time.perf_counter()

            # (e) online matrices
            matrices = {}
            reduced = rows[2]
            if self.online == "projection":
                fields = spread_modes(modes, reduced, num_outputs)
                matrices["projection"] = adjoint(morph, fields, num_inputs, reduced)
            else:
                weights, columns = weights_of(morph, num_inputs, reduced.numel())
                system, columns_rhs = paper_matrices(modes, weights)
                rhs = columns_rhs.new_zeros(modes.shape[0], num_inputs, modes.shape[-1])
                rhs.index_copy_(1, columns.to(rhs.device), columns_rhs)
                matrices.update(system_matrix=system, rhs_matrix=rhs)
            after_online = time.perf_counter()

        self._store_fit(
            modes=modes,
            singular_values=singular_values,
            energy_captured=energy_captured,
            copied_rows=rows,
            num_inputs=num_inputs,
            num_outputs=num_outputs,
            **matrices,
        )
        self.num_parameters_ = num_parameters
        self.family = family
        self._family_batched = batched
        self.__dict__["_morph"] = morph  # a reference, not a submodule: not in state_dict
        self.offline_time_ = {
            "snapshots": after_snapshots - start,
            "svd": after_svd - after_snapshots,
            "online_matrices": after_online - after_svd,
            "total": after_online - start,
        }
        return self

    # ---------------------------------------------------------------- online phase

    def morph_parameters(
        self, mu: Tensor | float, *, family: Family | None = None, batched: bool | None = None
    ) -> Tensor:
        """Reduced morph of parameter value(s): ``forward(family(mu))``, batched over μ.

        Parameters
        ----------
        mu : Tensor or float
            One value (a scalar, or shape (P,) for P parameters) or a batch, shape
            (B,) or (B, P). For a reducer fitted from displacements (no parameter
            shape known), a 1-D ``mu`` is a batch of scalars; pass one vector of P
            parameters as (1, P).
        family : callable, optional
            Defaults to the family given to ``fit`` (``self.family``).
        batched : bool, optional
            How the family is called (see :meth:`fit`). Default: as in ``fit`` for
            the fitted family, ``True`` for another one.

        Returns
        -------
        Tensor, shape (N_out, D) or (B, N_out, D)
            Differentiable with respect to ``mu`` when the family is.
        """
        self._check_fitted()
        family = self.family if family is None else family
        if family is None:
            raise RuntimeError(
                "no displacement family: fit with family=... or pass family= "
                "(a family is not saved by state_dict)"
            )
        if not isinstance(mu, Tensor):
            mu = torch.as_tensor(mu, dtype=self.modes_.dtype, device=self.modes_.device)
        single = is_single_value(mu, self.num_parameters_)
        batch = mu.unsqueeze(0) if single else mu
        if batched is None:
            batched = self._family_batched if family is self.family else True
        inputs = evaluate_family(family, batch, self.num_inputs_, batched, dim=self.dim)
        out = self(inputs)
        return out[0] if single else out

    # ---------------------------------------------------------------- a-posteriori check

    def relative_error(
        self,
        displacements: Tensor,
        *,
        morph: nn.Module | None = None,
        norm: Literal["nodal", "mass", "l2"] = "nodal",
        mesh: Any = None,
    ) -> Tensor:
        """Relative error of the reduced morph against the full one, per sample.

        Parameters
        ----------
        displacements : Tensor, shape (N_in, D) or (B, N_in, D)
            Inputs to compare on (fresh parameter values, not the training set).
        morph : linear map, optional
            The full morph; defaults to the one given to ``fit`` (needed after
            ``load_state_dict``, which does not restore it).
        norm : {"nodal", "mass"}
            ``"nodal"``: ``||d_pod - d_full||_F / ||d_full||_F`` over all output
            nodes. ``"mass"``: the L2(Ω_h) norm with the P1 mass matrix (the paper's
            Section 2.3.1) through :func:`torchmorph.mesh.quality.relative_l2_error`, for
            a map whose outputs are the nodes of a mesh. ``"l2"`` is a deprecated
            spelling of ``"mass"``.
        mesh : TetMesh, optional
            The reference mesh for ``norm="mass"``; defaults to
            ``TetMesh(morph.points, morph.tets)`` when the morph has both (a
            MeshMorph does).

        Returns
        -------
        Tensor, shape () or (B,)
            0 where both fields are zero, inf where only the reference is.
        """
        self._check_fitted()
        morph = self.__dict__.get("_morph") if morph is None else morph
        if morph is None:
            raise RuntimeError(
                "no full morph to compare with: pass morph= (load_state_dict does not restore it)"
            )
        batched = self._check_input(displacements, "displacements")
        inputs = displacements if batched else displacements.unsqueeze(0)
        with torch.no_grad():
            error = relative_field_error(self(inputs), morph(inputs), norm, mesh, morph)
        return error if batched else error[0]
