"""From what :mod:`._abaqus_parse` read to the deck's tables: nodes in number order, every
element's nodes checked, and the node and element sets resolved as CalculiX resolves them
(``noelsets.f``): ``NSET=``/``ELSET=`` on ``*NODE``/``*ELEMENT`` first, then ``*ELSET``
and ``*NSET`` keywords in the deck's order, a set name as a member standing for that set's
members at that point, ``GENERATE`` ranges taking the defined numbers in the range, and
numbers no node (element) has left out with a warning."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from torchmorph.mesh.formats._abaqus_parse import ParsedDeck, SetDefinition, is_network_type

__all__ = ["DeckTables", "find", "resolve"]


@dataclass
class DeckTables:
    """Nodes in number order with where their lines are, and the resolved sets."""

    node_ids: np.ndarray  # (N,) int64, ascending
    points: np.ndarray  # (N, 3) float64
    node_files: np.ndarray  # (N,) int64
    node_lines: np.ndarray  # (N,) int64
    node_sets: dict[str, np.ndarray]  # name -> node numbers, ascending
    element_sets: dict[str, np.ndarray]  # name -> element numbers, ascending
    warnings: list[str]


def _members_of(pool: np.ndarray, first: int, last: int, step: int) -> np.ndarray:
    """The numbers of the sorted ``pool`` in ``first, first + step, … <= last``."""
    inside = pool[np.searchsorted(pool, first) : np.searchsorted(pool, last, side="right")]
    return inside[(inside - first) % step == 0]


def find(sorted_ids: np.ndarray, wanted: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions of ``wanted`` in ``sorted_ids`` and whether each is there."""
    if not len(sorted_ids):
        return np.zeros(wanted.shape, dtype=np.int64), np.zeros(wanted.shape, dtype=bool)
    positions = np.minimum(np.searchsorted(sorted_ids, wanted), len(sorted_ids) - 1)
    return positions, sorted_ids[positions] == wanted


def _nodes_table(parsed: ParsedDeck) -> tuple[np.ndarray, np.ndarray]:
    order = np.argsort(parsed.node_ids, kind="stable")
    sorted_ids = parsed.node_ids[order]
    repeated = np.flatnonzero(sorted_ids[1:] == sorted_ids[:-1])
    if repeated.size:
        first, second = order[repeated[0]], order[repeated[0] + 1]
        files = parsed.files
        raise ValueError(
            f"{files[parsed.node_files[second]].where(int(parsed.node_lines[second]))}: node "
            f"{sorted_ids[repeated[0]]} is defined a second time (first at "
            f"{files[parsed.node_files[first]].where(int(parsed.node_lines[first]))})"
        )
    return order, sorted_ids


def _check_elements(parsed: ParsedDeck, node_ids: np.ndarray) -> np.ndarray:
    """Every element's nodes are defined (``0`` allowed at a network element's ends);
    element numbers are unique. Returns the element numbers, ascending."""
    for block in parsed.blocks:
        wanted = block.nodes.ravel()
        _, found = find(node_ids, wanted)
        if is_network_type(block.type):
            found |= wanted == 0
        if not found.all():
            bad = int(np.flatnonzero(~found)[0])
            row = bad // block.nodes.shape[1]
            where = parsed.files[block.element_files[row]].where(int(block.element_lines[row]))
            raise ValueError(
                f"{where}: element {block.ids[row]} (TYPE={block.type}) refers to node "
                f"{wanted[bad]}, which no *NODE line defines"
            )
    all_ids = np.concatenate([b.ids for b in parsed.blocks]) if parsed.blocks else np.zeros(0, int)
    order = np.argsort(all_ids, kind="stable")
    sorted_ids = all_ids[order].astype(np.int64)
    repeated = np.flatnonzero(sorted_ids[1:] == sorted_ids[:-1])
    if repeated.size:
        files = np.concatenate([b.element_files for b in parsed.blocks])[order]
        lines = np.concatenate([b.element_lines for b in parsed.blocks])[order]
        second = repeated[0] + 1
        raise ValueError(
            f"{parsed.files[files[second]].where(int(lines[second]))}: element "
            f"{sorted_ids[second]} is defined a second time (first at "
            f"{parsed.files[files[second - 1]].where(int(lines[second - 1]))})"
        )
    return sorted_ids


class _Sets:
    """One namespace of sets (node or element), names compared case-insensitively."""

    def __init__(self) -> None:
        self.names: dict[str, str] = {}  # upper-case -> the name as first written
        self.members: dict[str, np.ndarray] = {}

    def add(self, name: str, members: np.ndarray) -> None:
        key = name.upper()
        self.names.setdefault(key, name)
        current = self.members.get(key)
        joined = members if current is None else np.concatenate([current, members])
        self.members[key] = np.unique(joined.astype(np.int64))

    def get(self, name: str) -> np.ndarray | None:
        return self.members.get(name.upper())

    def result(self) -> dict[str, np.ndarray]:
        return {self.names[key]: members for key, members in self.members.items()}


def _resolve_definition(
    parsed: ParsedDeck,
    definition: SetDefinition,
    pool: np.ndarray,
    sets: _Sets,
    element_sets: _Sets,
    warnings: list[str],
) -> None:
    kind = definition.kind
    where = parsed.files[definition.file].where(definition.line)
    pieces = [np.zeros(0, dtype=np.int64)]
    explicit = np.asarray(definition.ids, dtype=np.int64)
    _, found = find(pool, explicit)
    if not found.all():
        missing = explicit[~found]
        warnings.append(
            f"{where}: {missing.size} members of {kind} set {definition.name!r} are not "
            f"defined {kind}s (e.g. {missing[0]}); they are left out, as CalculiX leaves them"
        )
    pieces.append(explicit[found])
    for first, last, step in definition.ranges:
        pieces.append(_members_of(pool, first, last, step))
    for name, file, line in definition.names:
        members = sets.get(name)
        if members is None:
            raise ValueError(
                f"{parsed.files[file].where(line)}: {kind} set {name!r} is not defined "
                "before this line (a member that is not a number names a set)"
            )
        pieces.append(members)
    if definition.of_elements is not None:
        elements = element_sets.get(definition.of_elements)
        if elements is None:
            raise ValueError(f"{where}: element set {definition.of_elements!r} is not defined")
        for block in parsed.blocks:
            chosen = block.nodes[np.isin(block.ids, elements)].ravel()
            pieces.append(chosen[chosen > 0])
    sets.add(definition.name, np.concatenate(pieces))


def resolve(parsed: ParsedDeck) -> DeckTables:
    """Check what ``parsed`` holds and build its tables (see the module's docstring)."""
    warnings = list(parsed.warnings)
    order, node_ids = _nodes_table(parsed)
    element_ids = _check_elements(parsed, node_ids)
    node_sets, element_sets = _Sets(), _Sets()
    definitions = parsed.set_definitions
    sequence = [d for d in definitions if not d.keyword] + [
        d for kind in ("element", "node") for d in definitions if d.keyword and d.kind == kind
    ]
    for definition in sequence:
        if definition.kind == "node":
            _resolve_definition(parsed, definition, node_ids, node_sets, element_sets, warnings)
        else:
            _resolve_definition(
                parsed, definition, element_ids, element_sets, element_sets, warnings
            )
    return DeckTables(
        node_ids,
        parsed.coordinates[order],
        parsed.node_files[order],
        parsed.node_lines[order],
        node_sets.result(),
        element_sets.result(),
        warnings,
    )
