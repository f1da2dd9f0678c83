"""``IDW(mode="tree")``: the :class:`~torchmorph.idw.tree.TreeIDW` of the module's stored
geometry, built once and again only when that geometry changes (a loaded state, a new
dtype)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from torch import Tensor

if TYPE_CHECKING:
    from torchmorph.idw.tree import TreeIDW

__all__ = ["TreeOperator"]


class TreeOperator:
    """The tree of an :class:`~torchmorph.idw.IDW` in tree mode.

    Parameters
    ----------
    power, coincidence_tolerance : float
        The module's (already checked).
    tolerance : float, optional
        The relative error of :class:`~torchmorph.idw.tree.TreeIDW`; ``None`` for its
        default, :data:`~torchmorph.idw.tree.DEFAULT_TOLERANCE`.
    error_control : {"certified", "sampled"}, optional
        TreeIDW's (default ``"certified"``).

    Notes
    -----
    Not an ``nn.Module`` on purpose: the trees are derived from the module's buffers, so
    the module's state (and its keys) are those of the exact modes.
    """

    def __init__(
        self,
        power: float,
        coincidence_tolerance: float,
        tolerance: float | None,
        error_control: str | None = None,
    ) -> None:
        from torchmorph.idw.tree import DEFAULT_TOLERANCE, _check_tolerance

        self.power = power
        self.coincidence_tolerance = coincidence_tolerance
        self.tolerance = _check_tolerance(DEFAULT_TOLERANCE if tolerance is None else tolerance)
        self.error_control = "certified" if error_control is None else error_control
        if self.error_control not in ("certified", "sampled"):
            raise ValueError(
                f"error_control must be 'certified' or 'sampled', got {error_control!r}"
            )
        self._cache: tuple[tuple, TreeIDW] | None = None

    def operator(self, controls: Tensor, targets: Tensor) -> TreeIDW:
        """The TreeIDW of ``controls`` and ``targets`` (the module's buffers), built on
        the first call and after they change.

        Raises
        ------
        ValueError
            If they are off the CPU (naming the device) or require grad.
        """
        for name, points in (("controls", controls), ("targets", targets)):
            if points.device.type != "cpu":
                raise ValueError(
                    f"{name}: mode='tree' runs on the CPU only (the tree has no CUDA "
                    f"kernels), and the module's points are on {points.device}; use "
                    "mode='dense' or 'matrix_free' there"
                )
            if points.requires_grad:
                raise ValueError(
                    f"{name} requires grad: mode='tree' gives gradients to the "
                    "displacements only; use mode='dense' or 'matrix_free' for gradients "
                    "to the points"
                )
        key = (
            controls.data_ptr(),
            targets.data_ptr(),
            controls._version,
            targets._version,
            controls.dtype,
            tuple(controls.shape),
            tuple(targets.shape),
        )
        if self._cache is None or self._cache[0] != key:
            from torchmorph.idw.tree import TreeIDW

            tree = TreeIDW(
                controls,
                targets,
                power=self.power,
                tolerance=self.tolerance,
                coincidence_tolerance=self.coincidence_tolerance,
                error_control=self.error_control,  # type: ignore[arg-type]
            )
            self._cache = (key, tree)
        return self._cache[1]
