"""``IDW(mode="tree")``: the tree operator of the module's stored geometry, built once and
again only when that geometry changes (a loaded state, a new dtype): with
``error_control="certified"`` the quadrupole traversal with its bound
(:class:`~torchmorph.idw.tree.TreeIDW`), with ``"sampled"`` the interpolating treecode
(:class:`~torchmorph.idw.treecode.TreecodeIDW`), 1.4–3× faster than TreeIDW's sampled
mode at 10^6 × 10^5 (``benchmarks/README.md``, "Tree-approximated IDW")."""

from __future__ import annotations

from typing import TYPE_CHECKING

from torch import Tensor

from torchmorph.idw._geometry import check_error_control

if TYPE_CHECKING:
    from torchmorph.idw.tree import TreeIDW
    from torchmorph.idw.treecode import TreecodeIDW

__all__ = ["AUTO_TREE_PAIRS", "TreeOperator", "tree_pays"]

AUTO_TREE_PAIRS: tuple[tuple[float, float], ...] = ((1e-5, 1e9), (1e-7, 1e10))
"""``IDW(mode="auto", tolerance=...)`` takes the tree (sampled error control) from this many
target–control pairs on, by the tolerance: (the smallest tolerance, the pairs). Measured
at p = 4 in 3-D, controls on a sphere and targets graded towards it, one thread
(``benchmarks/README.md``, "When auto takes the tree"): at 10^5 × 10^4 and 1e-4 the
tree's first call (the build and the threshold's tuning) costs what the exact sum's does
and the later ones a third of it, in float32 and float64; at 1e-6 the tree pays from
3·10^5 × 3·10^4 on. Below 1e-7, the exact modes only. Measured with ``TreeIDW``; the
treecode ``auto`` now builds (:class:`~torchmorph.idw.treecode.TreecodeIDW`) is faster
at every size of that table (at 10^5 × 10^4, 1e-4, float32: build and first call 0.37 s,
later calls 0.12 s, against 0.51 s exact), so these thresholds stay on the safe side."""


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
        self.error_control = check_error_control(
            "certified" if error_control is None else error_control
        )
        self._cache: tuple[tuple, TreeIDW | TreecodeIDW] | None = None

    def operator(self, controls: Tensor, targets: Tensor) -> TreeIDW | TreecodeIDW:
        """The TreeIDW (certified) or TreecodeIDW (sampled) of ``controls`` and
        ``targets`` (the module's buffers), built on the first call and after they
        change.

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
            from torchmorph.idw.treecode import TreecodeIDW

            options = {
                "power": self.power,
                "tolerance": self.tolerance,
                "coincidence_tolerance": self.coincidence_tolerance,
            }
            tree: TreeIDW | TreecodeIDW = (
                TreeIDW(controls, targets, error_control="certified", **options)  # type: ignore[arg-type]
                if self.error_control == "certified"
                else TreecodeIDW(controls, targets, **options)
            )
            self._cache = (key, tree)
        return self._cache[1]


def tree_pays(pairs: int, *, tolerance: float, power: float, dim: int) -> bool:
    """Whether ``mode="auto"`` takes the tree for ``pairs`` target–control pairs at the
    relative ``tolerance`` (:data:`AUTO_TREE_PAIRS`), where the fused CPU kernels run.

    Only where it was measured faster than the exact sum: p = 4 (at 10^5 × 10^4, 1e-4,
    float32, a settled tree call took 1.3–4.4 times an exact call at p = 2, 3, 5, 6 and 8,
    against 0.36 times at p = 4) and three dimensions."""
    if power != 4.0 or dim != 3:
        return False
    return any(tolerance >= least and pairs >= most for least, most in AUTO_TREE_PAIRS)
