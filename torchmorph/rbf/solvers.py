"""Which RBF fit for how many controls: :func:`build_rbf` picks the dense
:class:`~torchmorph.rbf.RBF`, the :class:`~torchmorph.rbf.SparseRBF` of a compactly
supported kernel or the partition-of-unity :class:`~torchmorph.rbf.PartitionRBF`."""

from __future__ import annotations

from typing import Literal

from torch import Tensor

from torchmorph._checks import as_points, check_choice, check_positive
from torchmorph.rbf.functional import dim_of
from torchmorph.rbf.kernels import WENDLAND
from torchmorph.rbf.module import RBF
from torchmorph.rbf.partition import PartitionRBF
from torchmorph.rbf.sparse import SPARSE_NEIGHBOURS, SparseRBF, mean_neighbours

__all__ = ["PARTITION_CONTROLS", "Solver", "build_rbf", "sparse_fits"]

#: :func:`build_rbf` with ``solver="auto"`` fits the dense :class:`~torchmorph.rbf.RBF`
#: up to this many controls, the :class:`PartitionRBF` beyond. Measured on two cores
#: (``benchmarks/rbf_scale.py``): the dense fit took 8.7 s at 10⁴ controls and 368 s at
#: 3·10⁴ (O(N³), 7.2 GB of kernel matrix), the partition 9-13 s at either.
PARTITION_CONTROLS = 20_000

Solver = Literal["auto", "dense", "partition", "sparse"]


def sparse_fits(controls: Tensor, options: dict) -> bool:
    """Whether ``solver="auto"`` takes the sparse fit: a Wendland kernel whose support
    holds at most :data:`~torchmorph.rbf.sparse.SPARSE_NEIGHBOURS` controls on average."""
    radius = options.get("support_radius")
    if options.get("kernel") not in WENDLAND or radius is None:
        return False
    return mean_neighbours(as_points(controls, "controls", dim=dim_of(controls)),
                           check_positive(radius, "support_radius")) <= SPARSE_NEIGHBOURS  # fmt: skip


def build_rbf(
    controls: Tensor,
    targets: Tensor,
    *,
    solver: Solver = "auto",
    **options,
) -> RBF | PartitionRBF | SparseRBF:
    """An RBF morph of ``targets`` by ``controls``: the dense :class:`~torchmorph.rbf.RBF`
    (``solver="dense"``), the :class:`PartitionRBF` (``"partition"``) or the
    :class:`~torchmorph.rbf.SparseRBF` (``"sparse"``, compactly supported kernels);
    ``"auto"``: dense up to :data:`PARTITION_CONTROLS` controls, beyond that the sparse
    fit for a Wendland kernel with at most
    :data:`~torchmorph.rbf.sparse.SPARSE_NEIGHBOURS` controls within the support of a
    control on average (the global fit, to rounding) and the partition of unity otherwise (exact at the controls, a few 1e-3 of relative 2-norm from the global fit
    over volume targets, see :class:`PartitionRBF`'s notes). ``options`` go to the chosen
    class (``TypeError`` for one it does not take)."""
    check_choice(solver, "solver", ("auto", "dense", "partition", "sparse"))
    count = len(controls)
    if solver == "auto":
        if count <= PARTITION_CONTROLS:
            solver = "dense"
        else:
            solver = "sparse" if sparse_fits(controls, options) else "partition"
    if solver == "dense":
        return RBF(controls, targets, **options)
    if solver == "sparse":
        return SparseRBF(controls, targets, **options)
    return PartitionRBF(controls, targets, **options)
