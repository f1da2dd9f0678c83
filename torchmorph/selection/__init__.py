"""Selection of control points: Algorithm 1 of the paper (SIDW) in
:mod:`torchmorph.selection.sidw`, and per-region selection plans with enrichment (ESIDW,
Algorithm 2 steps (i)–(ii)) in :mod:`torchmorph.selection.plan`."""

from torchmorph.selection.plan import (
    Region,
    RegionOverlapError,
    SelectionPlan,
    UncoveredNodesError,
)
from torchmorph.selection.sidw import DEFAULT_SEED, STRATEGIES, select_control_points

__all__ = [
    "DEFAULT_SEED",
    "STRATEGIES",
    "Region",
    "RegionOverlapError",
    "SelectionPlan",
    "UncoveredNodesError",
    "select_control_points",
]
