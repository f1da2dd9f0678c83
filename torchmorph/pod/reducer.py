"""POD-reduced morphing: POD-(E)SIDW, Algorithm 3 of Ballarin et al. (2017), section 3.

The IDW (or selective IDW) map ``d_int = W d_sel`` is linear, but ``W`` is large:
N_int × N_sel entries, read once per parameter value. For a parametrized family of
control displacements ``d_sel(μ)`` the interior fields ``W d_sel(μ)`` usually lie
close to a space of very few dimensions. :class:`PODReducer` finds that space
offline (proper orthogonal decomposition of snapshots) and, online, maps an input
displacement to the reduced coefficients with an N × 3N_in matrix, so that a new
parameter value costs O(N·N_in + N·N_out) instead of O(N_int·N_sel).

:class:`PODReducer` reduces any linear map from an input displacement (N_in, 3) to
an output field (N_out, 3) — an :class:`~torchmorph.idw.IDW`, a
:class:`~torchmorph.morph.MeshMorph`, or a user's module — through a small protocol
(see :class:`PODReducer`); it never asks which class the map is. The maths lives in
:mod:`torchmorph.pod.functional` (:func:`pod_basis`, :func:`projection_matrix`,
:func:`paper_matrices`), re-exported here.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, Literal

import torch
from torch import Tensor, nn

from torchmorph._checks import check_finite, check_same_device_dtype, is_traced
from torchmorph._state import (
    NotFittedError,
    check_saved_hyperparameters,
    resize_buffers_for_load,
)
from torchmorph.pod._protocol import (
    adjoint,
    check_online,
    check_out,
    check_reducer_state,
    copied_rows,
    evaluate_family,
    expand,
    expand_by_runs,
    index_runs,
    is_single_value,
    reference_tensor,
    relative_field_error,
    training_data,
    weights_of,
)
from torchmorph.pod.functional import (
    check_energy_tolerance,
    check_num_modes,
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


class PODReducer(nn.Module):
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
        (N × 3N_in), the orthogonal projection of the full morph onto the POD space;
        ``"paper"``: solve ``A β = B d_sel`` of the paper's eq. 16 with
        A = Zᵀ(W⁺)ᵀW⁺Z and B = Zᵀ(W⁺)ᵀ (needs the pseudo-inverse of W offline).

    Attributes
    ----------
    modes_ : Tensor (N, N_red, 3)
        (This and the following are set by ``fit``.) Orthonormal POD basis (``Z``),
        mode l as a displacement field of the reduced output rows ``reduced_rows_``.
    singular_values_ : Tensor (k,)
        Singular values of the snapshot matrix, descending (k = min(n_train, 3N_red));
        see :func:`pod_basis` for their accuracy.
    energy_captured_ : Tensor (k,)
        Cumulative energy fraction kept by 1, 2, ..., k modes.
    num_modes_ : int
        N, the number of modes kept.
    projection_ : Tensor (N, N_in, 3)
        P for ``online="projection"`` (empty otherwise).
    system_matrix_, rhs_matrix_ : Tensor (N, N), (N, N_in, 3)
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
      (B, N_in, 3) to (B, N_out, 3), differentiable in ``d`` (or with an ``adjoint``
      method). Optional methods make it faster or exact: ``copied_rows()`` returns
      (output rows, input rows) that ``morph`` copies unchanged (not reduced, exact);
      a stored matrix ``weights`` (N_red, len(weight_columns)) gives P by one GEMM;
      else ``adjoint(fields)`` applies the transpose, (B, N_out, 3) to (B, N_in, 3);
      else autograd computes it from one vector-Jacobian product;
      ``weights_matrix()`` returns W with ``morph(d)[:, reduced_rows] =
      W @ d[:, weight_columns]`` per component, and the attribute ``weight_columns``
      (default: every input row), for ``online="paper"``. :class:`~torchmorph.idw.IDW`
      and :class:`~torchmorph.morph.MeshMorph` follow it; the map's dtype and device
      are those of its first floating buffer or parameter.
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
    * Online cost: one (B × 3N_in) · (3N_in × N) product and one (B × N) ·
      (N × 3N_out) product (for ``paper`` also an N × N solve), plus the copy of
      the copied rows. When the copied and reduced rows form a few contiguous runs
      (any numbering that keeps them in blocks), the product is computed per run
      without the zero rows; otherwise one full product and an indexed copy. A
      large batch is bound by writing its output; pass ``out=`` to reuse one.
    * ``fit`` keeps a plain reference to the morph (for :meth:`relative_error`); it
      is not part of ``state_dict`` but is copied by ``copy.deepcopy`` / pickling.
    """

    _FLOAT_BUFFERS = (
        "modes_",
        "singular_values_",
        "energy_captured_",
        "projection_",
        "system_matrix_",
        "rhs_matrix_",
    )
    _INDEX_BUFFERS = ("copied_output_rows_", "copied_input_rows_", "reduced_rows_")
    _STATE_VERSION = 2

    def __init__(
        self,
        *,
        energy_tolerance: float = 1e-5,
        num_modes: int | None = None,
        online: OnlineVariant = "projection",
    ) -> None:
        super().__init__()
        self.energy_tolerance = check_energy_tolerance(energy_tolerance)
        self.num_modes = check_num_modes(num_modes)
        self.online = check_online(online)
        for name in self._FLOAT_BUFFERS:
            self.register_buffer(name, torch.empty(0))
        for name in self._INDEX_BUFFERS:
            self.register_buffer(name, torch.empty(0, dtype=torch.int64))
        # derived from the buffers above (rebuilt by fit and load_state_dict, moved by .to):
        # the online matrix over the input rows and the basis over the output rows
        self.register_buffer("_input_matrix", torch.empty(0), persistent=False)
        self.register_buffer("_output_basis", torch.empty(0), persistent=False)
        self.num_modes_: int | None = None
        self.num_inputs_: int | None = None
        self.num_outputs_: int | None = None
        self.num_parameters_: int | None = None
        self.offline_time_: dict[str, float] = {}
        self.family: Family | None = None
        self._family_batched: bool = True
        # contiguous runs of (output row, source row, length) for slice copies, or None
        self._runs: tuple[list[tuple[int, int, int]], list[tuple[int, int, int]]] | None = None
        self._morph: Any = None

    # ---------------------------------------------------------------- fitted state

    @property
    def is_fitted(self) -> bool:
        """Whether :meth:`fit` (or ``load_state_dict`` of a fitted reducer) has run."""
        return self.num_modes_ is not None

    def _check_fitted(self) -> None:
        if not self.is_fitted:
            raise NotFittedError(
                "this PODReducer is not fitted yet: call fit(morph, displacements) or "
                "fit(morph, family=..., parameters=...) first, or load a fitted state_dict"
            )

    @property
    def num_inputs(self) -> int:
        """Rows of an input displacement: control points (IDW) or boundary nodes (mesh)."""
        self._check_fitted()
        return int(self.num_inputs_)

    @property
    def num_outputs(self) -> int:
        """Rows of an output field: targets (IDW) or all mesh nodes (mesh)."""
        self._check_fitted()
        return int(self.num_outputs_)

    _FITTED = ("num_modes_", "num_inputs_", "num_outputs_", "num_parameters_")

    def _hyperparameters(self) -> dict[str, Any]:
        return {name: getattr(self, name) for name in ("energy_tolerance", "num_modes", "online")}

    def get_extra_state(self) -> dict[str, Any]:
        fitted = {name: getattr(self, name) for name in self._FITTED}
        return {"version": self._STATE_VERSION, **self._hyperparameters(), **fitted} | {
            "offline_time_": dict(self.offline_time_)
        }

    def set_extra_state(self, state: dict[str, Any]) -> None:
        check_saved_hyperparameters("PODReducer", state, self._hyperparameters())
        for name in self._FITTED:
            setattr(self, name, state[name])
        self.offline_time_ = dict(state["offline_time_"])

    def _load_from_state_dict(
        self,
        state_dict,
        prefix,
        local_metadata,
        strict,
        missing_keys,
        unexpected_keys,
        error_msgs,
    ) -> None:
        check_reducer_state(state_dict, prefix, self._STATE_VERSION)
        check_saved_hyperparameters(
            "PODReducer", state_dict[prefix + "_extra_state"], self._hyperparameters()
        )
        # the buffers' shapes are only known after fit: take the incoming shape and
        # (floating) dtype, keep this module's device
        resize_buffers_for_load(
            self, state_dict, prefix, (*self._FLOAT_BUFFERS, *self._INDEX_BUFFERS), take_dtype=True
        )
        super()._load_from_state_dict(
            state_dict,
            prefix,
            local_metadata,
            strict,
            missing_keys,
            unexpected_keys,
            error_msgs,
        )
        if self.is_fitted and not error_msgs:
            self._build_online_cache()

    def _build_online_cache(self) -> None:
        """Spread the basis over all output rows (zeros on the copied rows) and find the
        contiguous runs of the copied and reduced rows, for the online phase."""
        self._input_matrix = self.projection_ if self.online == "projection" else self.rhs_matrix_
        count, reduced = self.num_modes_, self.reduced_rows_
        whole = reduced.numel() == self.num_outputs_ and self.copied_output_rows_.numel() == 0
        if whole and bool((reduced == torch.arange(reduced.numel(), device=reduced.device)).all()):
            self._output_basis, self._runs = self.modes_, None
            return
        basis = self.modes_.new_zeros(count, self.num_outputs_, 3)
        self._output_basis = basis.index_copy_(1, reduced, self.modes_)
        copied_runs = index_runs(self.copied_output_rows_, self.copied_input_rows_)
        reduced_runs = index_runs(reduced, torch.arange(reduced.numel()))
        self._runs = (
            None if copied_runs is None or reduced_runs is None else (copied_runs, reduced_runs)
        )

    def extra_repr(self) -> str:
        text = (
            f"energy_tolerance={self.energy_tolerance:g}, num_modes={self.num_modes}, "
            f"online={self.online!r}"
        )
        if self.is_fitted:
            text += (
                f", num_modes_={self.num_modes_}, num_inputs_={self.num_inputs_}, "
                f"num_outputs_={self.num_outputs_}"
            )
        return text

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
            The full morph, (B, N_in, 3) -> (B, N_out, 3), following the protocol in
            the class notes. For an :class:`~torchmorph.idw.IDW` the inputs are
            control displacements and the output the targets'. For a
            :class:`~torchmorph.morph.MeshMorph` the inputs are boundary
            displacements and the output every node's; the boundary rows are copied
            exactly and only the interior field ``W d_sel`` is reduced.
        displacements : Tensor, shape (n_train, N_in, 3), optional
            Training inputs. Converted to the morph's dtype and device.
        family : callable, optional
            Instead of ``displacements``: ``family(mu)`` returns the input
            displacement for parameter value(s) ``mu``. Kept as ``self.family`` for
            :meth:`morph_parameters`.
        parameters : Tensor, shape (n_train,) or (n_train, P)
            Training parameter values for ``family``.
        batched : bool, default True
            How ``family`` is called. ``True``: once with all parameters, returning
            (n_train, N_in, 3); an exception of the family propagates, and another
            shape is a ``ValueError``. ``False``: once per parameter value (a 0-d
            tensor or a (P,) tensor), returning (N_in, 3); the results are stacked.
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
            training data, a morph output that is not (n_train, N_out, 3), all-zero
            snapshots, ``num_modes`` larger than the number or rank of the
            snapshots, or ``online="paper"`` with a morph without
            ``weights_matrix()``.
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
            outputs = morph(inputs)
            if (
                not isinstance(outputs, Tensor)
                or outputs.ndim != 3
                or outputs.shape[0] != inputs.shape[0]
                or outputs.shape[2] != 3
            ):
                got = (
                    tuple(outputs.shape) if isinstance(outputs, Tensor) else type(outputs).__name__
                )
                raise ValueError(
                    f"morph(displacements) must return shape "
                    f"({inputs.shape[0]}, N_out, 3), got {got}"
                )
            num_outputs = outputs.shape[1]
            copied_out, copied_in, reduced = copied_rows(
                morph, num_inputs, num_outputs, outputs.device
            )
            snapshots = outputs if copied_out.numel() == 0 else outputs.index_select(1, reduced)
            check_finite(snapshots, "snapshots (the morph of the training data)")
            after_snapshots = time.perf_counter()

            # (c)-(d) POD basis
            modes, singular_values, energy_captured = pod_basis(
                snapshots, energy_tolerance=self.energy_tolerance, num_modes=self.num_modes
            )
            after_svd = time.perf_counter()

            # (e) online matrices
            empty = modes.new_empty(0)
            if self.online == "projection":
                spread = (
                    modes
                    if copied_out.numel() == 0
                    else modes.new_zeros(modes.shape[0], num_outputs, 3).index_copy_(
                        1, reduced, modes
                    )
                )
                projection = adjoint(morph, spread, num_inputs, reduced)
                system, rhs = empty, empty
            else:
                weights, columns = weights_of(morph, num_inputs, reduced.numel())
                system, columns_rhs = paper_matrices(modes, weights)
                rhs = columns_rhs.new_zeros(modes.shape[0], num_inputs, 3)
                rhs.index_copy_(1, columns.to(rhs.device), columns_rhs)
                projection = empty
            after_online = time.perf_counter()

        self.modes_ = modes
        self.singular_values_ = singular_values
        self.energy_captured_ = energy_captured
        self.projection_ = projection
        self.system_matrix_ = system
        self.rhs_matrix_ = rhs
        self.copied_output_rows_ = copied_out
        self.copied_input_rows_ = copied_in
        self.reduced_rows_ = reduced
        self.num_modes_ = int(modes.shape[0])
        self.num_inputs_ = int(num_inputs)
        self.num_outputs_ = int(num_outputs)
        self.num_parameters_ = num_parameters
        self.family = family
        self._family_batched = batched
        self.__dict__["_morph"] = morph  # a reference, not a submodule: not in state_dict
        self._build_online_cache()
        self.offline_time_ = {
            "snapshots": after_snapshots - start,
            "svd": after_svd - after_snapshots,
            "online_matrices": after_online - after_svd,
            "total": after_online - start,
        }
        return self

    # ---------------------------------------------------------------- online phase

    def _check_input(self, displacement: Tensor, name: str) -> bool:
        self._check_fitted()
        if not isinstance(displacement, Tensor):
            raise TypeError(f"{name} must be a torch.Tensor, got {type(displacement).__name__}")
        count = self.num_inputs_
        if displacement.ndim not in (2, 3) or displacement.shape[-2:] != (count, 3):
            raise ValueError(
                f"{name} must have shape ({count}, 3) or (B, {count}, 3) for the {count} "
                f"input rows of the fitted morph, got {tuple(displacement.shape)}"
            )
        check_same_device_dtype(self.modes_, "the reducer", displacement, name)
        return displacement.ndim == 3

    def coefficients(self, displacement: Tensor) -> Tensor:
        """Reduced coefficients β of ``Z β ≈ L d`` (online step (f)).

        Parameters
        ----------
        displacement : Tensor, shape (N_in, 3) or (B, N_in, 3)
            Control displacements (IDW) or boundary displacements (mesh).

        Returns
        -------
        Tensor, shape (N,) or (B, N)
        """
        batched = self._check_input(displacement, "displacement")
        beta = self._coefficients(displacement if batched else displacement.unsqueeze(0))
        return beta if batched else beta[0]

    def _coefficients(self, displacement: Tensor) -> Tensor:
        """(B, N_in, 3) -> (B, N): one GEMM (plus an N × N solve for ``paper``)."""
        count = self.num_modes_
        flat = displacement.reshape(displacement.shape[0], -1)
        rhs = flat @ self._input_matrix.reshape(count, -1).mT  # P d, or B d of eq. 16
        if self.online == "projection":
            return rhs
        return torch.linalg.solve(self.system_matrix_, rhs.mT).mT

    def forward(self, displacement: Tensor, *, out: Tensor | None = None) -> Tensor:
        """Reduced morph: what the fitted morph's ``forward`` returns, from N modes.

        Parameters
        ----------
        displacement : Tensor, shape (N_in, 3) or (B, N_in, 3)
            Control displacements (IDW: N_in = N_c) or boundary displacements
            (MeshMorph: N_in = N_b), in the reducer's dtype and device.
        out : Tensor, shape (N_out, 3) or (B, N_out, 3), optional
            Contiguous tensor to write the result into (no autograd). Reusing one
            output for many batches saves the page faults of a fresh allocation,
            which dominate a large batch (3x at case-B size, see benchmarks).

        Returns
        -------
        Tensor, shape (N_out, 3) or (B, N_out, 3)
            IDW: the targets' displacement ``Z β``. MeshMorph: the full nodal field,
            boundary nodes exactly ``displacement``, interior nodes ``Z β``.
            Differentiable with respect to ``displacement`` (without ``out``).

        Raises
        ------
        RuntimeError
            If the reducer is not fitted.
        ValueError
            On a wrong shape, dtype or device of ``displacement`` or ``out``, or
            ``out`` with a ``displacement`` that requires grad.
        """
        batched = self._check_input(displacement, "displacement")
        inputs = displacement if batched else displacement.unsqueeze(0)
        if out is not None:
            out = check_out(out, displacement, self.num_outputs_, self.modes_)
            out = out if batched else out.unsqueeze(0)
        beta = self._coefficients(inputs)
        # the slice copies write into out= tensors: not for autograd, vmap, jvp or compile
        slices = (
            self._runs is not None
            and not is_traced(beta)
            and not (torch.is_grad_enabled() and beta.requires_grad)
        )
        if slices:
            result = expand_by_runs(beta, self.modes_, inputs, self._runs, self.num_outputs_, out)
        else:
            result = expand(
                beta,
                self._output_basis,
                inputs,
                self.copied_output_rows_,
                self.copied_input_rows_,
                out,
            )
        return result if batched else result[0]

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
        Tensor, shape (N_out, 3) or (B, N_out, 3)
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
        inputs = evaluate_family(family, batch, self.num_inputs_, batched)
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
        displacements : Tensor, shape (N_in, 3) or (B, N_in, 3)
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
