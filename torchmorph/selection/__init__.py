"""Selection of control points: Algorithm 1 of the paper (SIDW) in
:mod:`torchmorph.selection.sidw`, per-region selection plans with enrichment (ESIDW,
Algorithm 2 steps (i)–(ii)) in :mod:`torchmorph.selection.plan`, and the error-driven
selection (the greedy loop of :mod:`torchmorph.selection.greedy` with the IDW error
of :mod:`torchmorph.selection.adaptive`, started from the count-stratified order of
:mod:`torchmorph.selection.stratified`)."""

from torchmorph.selection.adaptive import IDWErrorOracle, select_adaptive
from torchmorph.selection.greedy import ErrorOracle, GreedySelection, greedy_selection
from torchmorph.selection.plan import (
    AdaptivePlan,
    Region,
    RegionOverlapError,
    SelectionPlan,
    UncoveredNodesError,
)
from torchmorph.selection.sidw import DEFAULT_SEED, STRATEGIES, select_control_points
from torchmorph.selection.stratified import nested_order

__all__ = [
    "DEFAULT_SEED",
    "STRATEGIES",
    "AdaptivePlan",
    "ErrorOracle",
    "GreedySelection",
    "IDWErrorOracle",
    "Region",
    "RegionOverlapError",
    "SelectionPlan",
    "UncoveredNodesError",
    "greedy_selection",
    "nested_order",
    "select_adaptive",
    "select_control_points",
]
