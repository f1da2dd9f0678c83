"""The one interface every IDW backend implements (:class:`Backend`), and the one
spelling of the power shared by the kernels (:func:`power_code`)."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from torch import Tensor

__all__ = ["Backend", "power_code"]


def power_code(power: float) -> int:
    """A compile-time code for the ratio power ``(m/d²)^(p/2)``: ``p`` itself for the
    integers 1 to 8 (products and at most one square root in every kernel), 0 for any
    other ``p`` (the general power: a logarithm and an exponential)."""
    power = float(power)
    return int(power) if power in _INTEGER_POWERS else 0


_INTEGER_POWERS = frozenset(float(k) for k in range(1, 9))


@runtime_checkable
class Backend(Protocol):
    """Kernel work of IDW over normalised points (the paper's eq. 2 in ratio form).

    Every method takes the points in the backend's :meth:`layout` and returns tensors of
    their dtype and device. ``power`` is p > 0, ``radius2`` the squared coincidence
    radius in the normalised units, ``nearest2`` (N_t,) the squared distance from each
    target to its nearest control (floored at the dtype's smallest normal), ``sums``
    (N_t,) the row sums ``s_i`` of the unnormalised weights. Nothing validates its
    input: :mod:`torchmorph.idw.functional` and :mod:`torchmorph.idw.module` do.

    ``differentiable``: the backend's results carry autograd graphs of their own (the
    torch backend); the others are wrapped by the autograd functions of
    :mod:`torchmorph.idw._dispatch`, whose backward passes call :meth:`apply_transposed`
    and :meth:`position_gradients`.
    """

    name: str
    differentiable: bool

    def layout(self, points: Tensor) -> Tensor:
        """``points`` (N, D) in the layout the kernels read."""
        ...

    def nearest(self, targets: Tensor, controls: Tensor) -> Tensor:
        """``nearest2``, shape (N_t,)."""
        ...

    def needs_nearest(self, columns: int) -> bool:
        """Whether :meth:`apply` with this many value columns reads ``nearest2``."""
        ...

    def apply(
        self,
        targets: Tensor,
        controls: Tensor,
        values: Tensor,
        power: float,
        radius2: float,
        nearest2: Tensor | None,
    ) -> tuple[Tensor, Tensor | None]:
        """``(W @ values, sums)`` for ``values`` (N_c, K), W never stored; ``sums`` is None
        where the backend did not compute them (then :meth:`apply_transposed` finds its own)."""
        ...

    def apply_transposed(
        self,
        targets: Tensor,
        controls: Tensor,
        grad: Tensor,
        power: float,
        radius2: float,
        nearest2: Tensor | None,
        sums: Tensor | None,
    ) -> Tensor:
        """``Wᵀ @ grad`` for ``grad`` (N_t, K): the gradient of :meth:`apply` to its values."""
        ...

    def weights(
        self,
        targets: Tensor,
        controls: Tensor,
        power: float,
        radius2: float,
        out: Tensor | None = None,
    ) -> Tensor:
        """Dense W, shape (N_t, N_c), row-major (into ``out`` when given)."""
        ...

    def dense_columns(self) -> int:
        """Up to how many value columns :meth:`dense_apply` beats the BLAS product."""
        ...

    def dense_apply(self, weights: Tensor, values: Tensor) -> Tensor:
        """``weights @ values`` for a stored W, reading W once."""
        ...

    def position_gradients_for(self, dim: int, columns: int) -> bool:
        """Whether :meth:`position_gradients` handles points of ``dim`` dimensions and this
        many value columns."""
        ...

    def position_gradients(
        self,
        targets: Tensor,
        controls: Tensor,
        values: Tensor,
        grad: Tensor,
        out: Tensor,
        nearest2: Tensor,
        sums: Tensor,
        power: float,
        radius2: float,
        need_targets: bool,
        need_controls: bool,
    ) -> tuple[Tensor | None, Tensor | None]:
        """Gradients of ``<grad, W @ values>`` to the target and control positions (in the
        backend's layout), each None unless asked for."""
        ...
