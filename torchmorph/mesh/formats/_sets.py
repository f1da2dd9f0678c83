"""Checks of node sets and fields on writing, and the rule for node sets named like face
sets on reading, shared by the CGNS and MED formats (as the Exodus format applies them)."""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np

__all__ = ["checked_fields", "checked_points", "connectivity", "node_rows", "separate_node_sets"]


def node_rows(rows: Any, argument: str, num_points: int, source: str) -> np.ndarray:
    """A node set's rows, sorted and unique; ``ValueError`` naming ``argument`` unless they
    are integers in [0, ``num_points``)."""
    array = np.asarray(rows)
    if array.size == 0:
        return np.zeros(0, dtype=np.int64)
    if array.dtype.kind not in "iu":
        raise ValueError(
            f"{argument}: node rows must be integers, got {array.dtype} (writing {source!r})"
        )
    array = np.unique(array.astype(np.int64).ravel())
    if array[0] < 0 or array[-1] >= num_points:
        raise ValueError(f"{argument}: rows outside [0, {num_points}) (writing {source!r})")
    return array


def checked_points(points: Any, source: str) -> np.ndarray:
    """``data.points`` as float64 (N, 2) or (N, 3); ``ValueError`` unless finite."""
    array = np.asarray(points, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] not in (2, 3) or not np.isfinite(array).all():
        raise ValueError(
            f"data.points: must be finite, of shape (N, 2) or (N, 3), got {array.shape} "
            f"(writing {source!r})"
        )
    return array


def connectivity(
    nodes: Any, kind: str, expected: int, num_points: int, argument: str, source: str
) -> np.ndarray:
    """A block's connectivity as int64 (M, ``expected``); ``ValueError`` naming ``argument``
    if its shape is another or a node number lies outside [0, ``num_points``)."""
    array = np.asarray(nodes)
    if array.ndim != 2 or array.shape[1] != expected:
        raise ValueError(
            f"{argument}: {kind!r} connectivity must have shape (M, {expected}), got "
            f"{array.shape} (writing {source!r})"
        )
    if array.size and (array.min() < 0 or array.max() >= num_points):
        raise ValueError(
            f"{argument}: node numbers must be in 0..{num_points - 1} (writing {source!r})"
        )
    return array.astype(np.int64)


def checked_fields(
    fields: dict, argument: str, sizes: list[int], source: str, *, nodal: bool = False
) -> dict[str, list[np.ndarray]]:
    """Fields as arrays of numbers, one per block (one for ``nodal`` fields), each of shape
    (size,) or (size, k) with one k for all blocks; ``ValueError`` naming the field
    otherwise."""
    result: dict[str, list[np.ndarray]] = {}
    for key, value in fields.items():
        where = f"{argument}[{key!r}]"
        arrays = [np.asarray(value)] if nodal else [np.asarray(a) for a in value]
        if len(arrays) != len(sizes):
            raise ValueError(
                f"{where}: {len(arrays)} arrays for {len(sizes)} cell blocks (writing {source!r})"
            )
        for array, size in zip(arrays, sizes, strict=True):
            if array.dtype.kind not in "fiub" or array.ndim not in (1, 2) or len(array) != size:
                raise ValueError(
                    f"{where}: must be numbers of shape ({size},) or ({size}, k), got "
                    f"{array.dtype} {array.shape} (writing {source!r})"
                )
        if len({a.shape[1:] for a in arrays}) > 1:
            raise ValueError(f"{where}: the blocks' arrays differ in width (writing {source!r})")
        result[key] = arrays
    return result


def separate_node_sets(
    node_sets: dict[str, np.ndarray],
    face_sets: dict[str, list[tuple[str, np.ndarray]]],
    what: str,
    source: str,
    *,
    taken: set[str] | frozenset[str] = frozenset(),
    stacklevel: int = 4,
) -> dict[str, np.ndarray]:
    """Node sets named like a face set: kept where they hold the face set's nodes (the face
    set carries the marker), renamed ``<name>_nodes`` with a warning where they hold other
    nodes (a mesh drops the node sets named like face sets: they would be lost); an error
    where that name is in ``node_sets``, ``face_sets`` or ``taken`` already."""
    result: dict[str, np.ndarray] = {}
    for name, nodes in node_sets.items():
        if name in face_sets:
            blocks = face_sets[name]
            of_faces = np.unique(np.concatenate([n.ravel() for _, n in blocks] or [nodes[:0]]))
            if not np.array_equal(of_faces, nodes):
                renamed = f"{name}_nodes"
                if renamed in node_sets or renamed in face_sets or renamed in taken:
                    raise ValueError(
                        f"path: {source!r}: {what} {name!r} is named like a face set but holds "
                        f"other nodes, and {renamed!r} is taken"
                    )
                warnings.warn(
                    f"path: {source!r}: {what} {name!r} is named like a face set but holds "
                    f"other nodes; it is read as the node set {renamed!r}",
                    UserWarning,
                    stacklevel=stacklevel,
                )
                name = renamed
        result[name] = nodes
    return result
