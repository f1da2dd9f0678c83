"""The saved state of a :class:`~torchmorph.morph.MeshMorph`: its version, the upgrade of
older versions, and the consistency checks run before anything is loaded."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn

from torchmorph._state import check_saved_hyperparameters
from torchmorph.mesh.cells import cell_kind
from torchmorph.rbf.module import RBF

__all__ = [
    "STATE_VERSION",
    "check_interpolant_state",
    "check_morph_state",
    "check_variant",
    "upgraded_state",
]

#: The version of MeshMorph's extra state. 1: tetrahedra only, a "tets" buffer; 2: cell
#: blocks, IDW only; 3: the method ("idw" or "rbf") in the extra state. All still load.
STATE_VERSION = 3


def upgraded_state(state_dict, prefix: str):
    """A state saved by an earlier version in this version's form (other states as they
    are): version 1's ``tets`` buffer as ``cell_nodes``, ``cell_orientation`` and the
    blocks in the extra state; versions 1 and 2 (IDW only) with ``method="idw"``."""
    extra = state_dict.get(prefix + "_extra_state")
    if isinstance(extra, dict) and extra.get("version") == 1:
        state_dict = _upgraded_from_1(state_dict, prefix, extra)
        extra = state_dict.get(prefix + "_extra_state")
    if isinstance(extra, dict) and extra.get("version") == 2:
        state_dict = dict(state_dict)
        state_dict[prefix + "_extra_state"] = {**extra, "version": 3, "method": "idw"}
    return state_dict


def _upgraded_from_1(state_dict, prefix: str, extra: dict):
    """Version 1 (a ``tets`` buffer) in version 2's form."""
    tets = state_dict.get(prefix + "tets")
    if not isinstance(tets, Tensor):
        return state_dict
    if tets.ndim != 2 or tets.shape[1] != 4:
        raise ValueError(f"state_dict[{prefix + 'tets'!r}]: must have shape (M, 4)")
    upgraded = {key: value for key, value in state_dict.items() if key != prefix + "tets"}
    upgraded[prefix + "cell_nodes"] = tets.reshape(-1)
    upgraded[prefix + "cell_orientation"] = torch.ones(
        tets.shape[0], dtype=torch.int8, device=tets.device
    )
    upgraded[prefix + "_extra_state"] = {
        **extra,
        "version": 2,
        "cell_blocks": [["tetra", int(tets.shape[0])]],
    }
    return upgraded


def check_morph_state(state_dict, prefix: str) -> None:
    """Raise ``ValueError`` naming the field if a MeshMorph state is inconsistent.

    Runs before anything is loaded, so a rejected state leaves the module as it was.
    Missing entries are left to ``load_state_dict``'s own missing-key report.
    """

    def entry(name: str) -> Any:
        return state_dict.get(prefix + name)

    def fail(name: str, message: str) -> None:
        raise ValueError(f"state_dict[{prefix + name!r}]: {message}")

    def index(name: str, size: int | None = None) -> Tensor | None:
        value = entry(name)
        if value is None:
            return None
        if (
            not isinstance(value, Tensor)
            or value.ndim != 1
            or value.is_floating_point()
            or value.dtype == torch.bool
        ):
            fail(name, "must be a 1-D integer tensor")
        if (
            size is not None
            and value.numel()
            and (int(value.min()) < 0 or int(value.max()) >= size)
        ):
            fail(name, f"holds indices outside [0, {size})")
        return value

    extra = entry("_extra_state")
    if extra is not None:
        if (
            not isinstance(extra, dict)
            or not isinstance(extra.get("node_set_names"), list)
            or not all(isinstance(n, str) and n for n in extra["node_set_names"])
        ):
            fail("_extra_state", "must hold 'node_set_names', a list of non-empty strings")
        if extra.get("version") != STATE_VERSION:
            fail(
                "_extra_state",
                f"version {extra.get('version')!r} is not {STATE_VERSION}",
            )
        if extra.get("method") not in ("idw", "rbf"):
            fail("_extra_state", f"method {extra.get('method')!r} is not 'idw' or 'rbf'")
        blocks = extra.get("cell_blocks")
        if not isinstance(blocks, list) or not all(
            isinstance(b, (list, tuple)) and len(b) == 2 and isinstance(b[1], int) and b[1] >= 0
            for b in blocks
        ):
            fail("_extra_state", "must hold 'cell_blocks', a list of [kind, count] pairs")
        try:
            width = sum(cell_kind(kind).num_nodes * count for kind, count in blocks)
        except ValueError as error:
            fail("_extra_state", str(error))
        nodes = entry("cell_nodes")
        if isinstance(nodes, Tensor) and nodes.numel() != width:
            fail("cell_nodes", f"holds {nodes.numel()} entries but the cell blocks need {width}")
        orientation = entry("cell_orientation")
        count = sum(count for _, count in blocks)
        if isinstance(orientation, Tensor) and orientation.numel() != count:
            fail("cell_orientation", f"holds {orientation.numel()} entries for {count} cells")
    points = entry("points")
    if points is None:
        return
    if (
        not isinstance(points, Tensor)
        or points.ndim != 2
        or points.shape[1] not in (2, 3)
        or not points.is_floating_point()
    ):
        fail(
            "points",
            f"must be a floating tensor (N, 2 or 3), got {getattr(points, 'shape', points)}",
        )
    num_nodes = points.shape[0]
    index("cell_nodes", num_nodes)
    boundary = index("boundary_nodes", num_nodes)
    interior = index("interior_nodes", num_nodes)
    if boundary is not None and interior is not None:
        together = torch.cat([boundary, interior]).cpu()
        if together.numel() != num_nodes or not torch.equal(
            torch.sort(together).values, torch.arange(num_nodes)
        ):
            fail(
                "interior_nodes",
                f"boundary_nodes and interior_nodes must split the {num_nodes} nodes into two sets",
            )
    selected = index("selected", None if boundary is None else boundary.numel())
    controls = index("control_nodes", num_nodes)
    if (
        selected is not None
        and controls is not None
        and boundary is not None
        and not torch.equal(boundary.cpu()[selected.cpu()], controls.cpu())
    ):
        fail("control_nodes", "must equal boundary_nodes[selected]")
    members = index("node_set_members", num_nodes)
    offsets = index("node_set_offsets")
    if members is not None and offsets is not None:
        steps = offsets.cpu().diff()
        if (
            offsets.numel() == 0
            or int(offsets[0]) != 0
            or int(offsets[-1]) != members.numel()
            or bool((steps < 0).any())
        ):
            fail("node_set_offsets", "must rise from 0 to the number of node_set_members")
        if extra is not None and offsets.numel() != len(extra["node_set_names"]) + 1:
            fail(
                "node_set_offsets",
                f"holds {offsets.numel() - 1} node sets but the names are "
                f"{len(extra['node_set_names'])}",
            )
    for name, expected in (
        (f"{method}.{part}", None if rows is None else rows.numel())
        for method in ("idw", "rbf")
        for part, rows in (("controls", controls), ("targets", interior))
    ):
        value = entry(name)
        if expected is not None and isinstance(value, Tensor) and value.shape[0] != expected:
            fail(name, f"has {value.shape[0]} rows but the morph's state needs {expected}")


def check_interpolant_state(state_dict, prefix: str, interpolant: nn.Module) -> None:
    """Raise ``ValueError`` naming the field if the RBF state under ``prefix`` was saved
    with other hyper-parameters than ``interpolant``'s, before anything is loaded (an
    IDW checks its own when it loads)."""
    extra = state_dict.get(prefix + "_extra_state")
    if extra is None or not isinstance(interpolant, RBF):
        return
    current = {
        "kernel": interpolant.kernel,
        "epsilon": interpolant.epsilon,
        "degree": interpolant.degree,
        "support_radius": interpolant.support_radius,
    }
    check_saved_hyperparameters("RBF", extra, current)


def check_variant(extra: dict[str, Any], stiffening: list[float] | None, solver: str) -> None:
    """Raise ``ValueError`` naming the argument if a MeshMorph state was saved with
    another near-wall stiffening (``[stiffening_power, stiffening_length]`` or None) or
    another RBF fit (``solver``: "dense", "partition" or "sparse") than the morph it
    loads into. States saved before these existed are plain IDW and dense RBF; those
    saved before the sparse fit say ``partition`` (True or False)."""
    saved = extra.get("solver", "partition" if extra.get("partition", False) else "dense")
    if saved != solver:
        raise ValueError(
            f"solver: the state was saved with the {saved} RBF fit but this MeshMorph has "
            f"the {solver} one; build the morph with the saved solver"
        )
    saved_stiffening = extra.get("stiffening")
    if saved_stiffening != stiffening:
        raise ValueError(
            f"stiffening: the state was saved with near-wall stiffening {saved_stiffening!r} "
            f"([stiffening_power, stiffening_length], None: none) but this MeshMorph has "
            f"{stiffening!r}; build the morph with the saved values"
        )
