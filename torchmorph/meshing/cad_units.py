"""The length unit a STEP or IGES file declares, so that a mesh keeps the file's numbers.

OpenCASCADE converts STEP and IGES coordinates to millimetres: a wing of 1.196 m span
stored in metres arrives as 1196 units, and sizes given in the file's unit
(``body_edge_length=0.05``) then ask for 10^10 elements. :func:`file_unit` reads the
unit from the file (STEP: the ``LENGTH_UNIT`` of the ``GLOBAL_UNIT_ASSIGNED_CONTEXT``;
IGES: the global section's unit flag); :func:`torchmorph.meshing.mesh_cad` meshes in
millimetres and scales sizes and points by :data:`MILLIMETRES`. (gmsh's
``Geometry.OCCTargetUnit`` would read the file in its unit, but it sets OpenCASCADE's
unit for the whole process, later imports and STEP writes included, and gmsh's scaling
of shapes turns planes and spheres into B-splines.) BREP files carry no unit: their
numbers are read as they are.
"""

from __future__ import annotations

import re
from pathlib import Path

__all__ = ["MILLIMETRES", "UNIT_NAMES", "file_unit"]

#: gmsh / OpenCASCADE unit names and what they are called in messages.
UNIT_NAMES = {
    "UM": "micrometres",
    "MM": "millimetres",
    "CM": "centimetres",
    "M": "metres",
    "KM": "kilometres",
    "INCH": "inches",
    "FT": "feet",
    "MI": "miles",
    "MIL": "thousandths of an inch",
    "UIN": "microinches",
}
#: Millimetres per unit (OpenCASCADE reads STEP and IGES files in millimetres).
MILLIMETRES = {
    "UM": 1e-3,
    "MM": 1.0,
    "CM": 10.0,
    "M": 1e3,
    "KM": 1e6,
    "INCH": 25.4,
    "FT": 304.8,
    "MI": 1609344.0,
    "MIL": 0.0254,
    "UIN": 2.54e-5,
}
_SI_PREFIX = {"$": "M", ".MILLI.": "MM", ".CENTI.": "CM", ".MICRO.": "UM", ".KILO.": "KM"}
_CONVERTED = {"INCH": "INCH", "FOOT": "FT", "MILE": "MI", "MIL": "MIL", "MICROINCH": "UIN"}
_IGES_FLAG = {
    1: "INCH",
    2: "MM",
    4: "FT",
    5: "MI",
    6: "M",
    7: "KM",
    8: "MIL",
    9: "UM",
    10: "CM",
    11: "UIN",
}
_IGES_NAME = {
    "IN": "INCH",
    "INCH": "INCH",
    "MM": "MM",
    "FT": "FT",
    "MI": "MI",
    "M": "M",
    "KM": "KM",
    "MIL": "MIL",
    "UM": "UM",
    "MICRON": "UM",
    "CM": "CM",
    "UIN": "UIN",
}


def _step_unit(text: str) -> str | None:
    entities = {
        match.group(1): match.group(2)
        for match in re.finditer(r"#(\d+)\s*=\s*((?:[^;']|'[^']*')*);", text)
    }
    units = set()
    for body in entities.values():
        if "GLOBAL_UNIT_ASSIGNED_CONTEXT" not in body:
            continue
        assigned = re.search(r"GLOBAL_UNIT_ASSIGNED_CONTEXT\s*\(\s*\(([^)]*)\)", body)
        for reference in re.findall(r"#(\d+)", assigned.group(1) if assigned else ""):
            unit = entities.get(reference, "")
            if "LENGTH_UNIT" not in unit:
                continue
            si = re.search(r"SI_UNIT\s*\(\s*([^,\s]+)\s*,\s*\.METRE\.\s*\)", unit)
            converted = re.search(r"CONVERSION_BASED_UNIT\s*\(\s*'([^']*)'", unit)
            if si:
                units.add(_SI_PREFIX.get(si.group(1).upper()))
            elif converted:
                units.add(_CONVERTED.get(converted.group(1).strip().upper()))
            else:
                units.add(None)
    return units.pop() if len(units) == 1 else None


def _iges_unit(text: str) -> str | None:
    lines = text.splitlines()
    section = "".join(line[:72] for line in lines if len(line) >= 73 and line[72] == "G")
    delimiter = ","
    if section.startswith("1H"):
        delimiter = section[2]
    fields: list[str] = []
    position = 0
    while position < len(section) and len(fields) < 15:
        hollerith = re.match(r"\s*(\d+)H", section[position:])
        if hollerith:
            start = position + hollerith.end()
            value = section[start : start + int(hollerith.group(1))]
            position = start + int(hollerith.group(1))
        else:
            end = min(
                (
                    i
                    for i in (section.find(delimiter, position), section.find(";", position))
                    if i >= 0
                ),
                default=len(section),
            )
            value, position = section[position:end].strip(), end
        fields.append(value)
        position += 1  # past the delimiter
    if len(fields) < 14:
        return None
    try:
        flag = int(float(fields[13]))
    except ValueError:
        return None
    if flag == 3 and len(fields) >= 15:
        return _IGES_NAME.get(fields[14].strip().upper())
    return _IGES_FLAG.get(flag)


def file_unit(path: str | Path) -> str | None:
    """The length unit ``path`` declares, as a key of :data:`UNIT_NAMES` (None: unknown).

    STEP (``.step``, ``.stp``) and IGES (``.iges``, ``.igs``) files are read as text; a
    file with several differing units, or none, gives None (OpenCASCADE's default, millimetres).
    """
    suffix = Path(path).suffix.lower()
    if suffix not in (".step", ".stp", ".iges", ".igs"):
        return None
    text = Path(path).read_text(encoding="latin-1", errors="replace")
    return _step_unit(text) if suffix in (".step", ".stp") else _iges_unit(text)
