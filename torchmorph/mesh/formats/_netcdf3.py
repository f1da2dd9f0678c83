"""The length a classic netCDF file (CDF-1, CDF-2 or CDF-5) must have, from its header.

The netCDF library reads the missing end of a truncated classic file as zeros (or fill
values) without an error; :func:`shortfall` compares the file's length with the end of its
last variable, as the header places the variables (the netCDF "Classic Format
Specification": magic, numrecs, dim_list, gatt_list, var_list, each variable with its
dimensions, type, vsize and begin offset).
"""

from __future__ import annotations

import os

__all__ = ["shortfall"]

_ABSENT, _DIMENSION, _VARIABLE, _ATTRIBUTE = 0, 10, 11, 12
#: Bytes of each external type (NC_BYTE … NC_UINT64).
_TYPE_SIZES = {1: 1, 2: 1, 3: 2, 4: 4, 5: 4, 6: 8, 7: 1, 8: 2, 9: 4, 10: 8, 11: 8}
_STREAMING = 0xFFFFFFFF


class _Header:
    def __init__(self, data: bytes, version: int) -> None:
        self.data, self.at = data, 4
        self.wide = version == 5  # CDF-5: 64-bit counts and lengths
        self.offsets = 8 if version in (2, 5) else 4

    def integer(self, size: int) -> int:
        if self.at + size > len(self.data):
            raise EOFError
        value = int.from_bytes(self.data[self.at : self.at + size], "big")
        self.at += size
        return value

    def count(self) -> int:
        return self.integer(8 if self.wide else 4)

    def skip(self, size: int) -> None:
        self.at += (size + 3) // 4 * 4
        if self.at > len(self.data):
            raise EOFError

    def name(self) -> None:
        self.skip(self.count())

    def attributes(self) -> None:
        tag, count = self.integer(4), self.count()
        if tag not in (_ABSENT, _ATTRIBUTE):
            raise EOFError
        for _ in range(count):
            self.name()
            kind = self.integer(4)
            self.skip(_TYPE_SIZES.get(kind, 1) * self.count())


def shortfall(path: str | os.PathLike) -> str | None:
    """How a classic netCDF file is shorter than its header says (``None`` where it is
    not, or is no classic netCDF file, or its header cannot be followed)."""
    with open(path, "rb") as stream:
        head = stream.read(4)
        if len(head) < 4 or head[:3] != b"CDF" or head[3] not in (1, 2, 5):
            return None
        length = stream.seek(0, os.SEEK_END)
        stream.seek(0)
        data = stream.read(min(length, 1 << 26))
    try:
        records, variables = _layout(_Header(data, head[3]))
    except (EOFError, IndexError):
        return None
    record_variables = [v for v in variables if v[3]]
    if len(record_variables) == 1:  # one record variable: records are not padded
        record_size = record_variables[0][1]
    else:
        record_size = sum(vsize for _, _, vsize, record, _ in record_variables)
    end, last = 0, ""
    for name, size, _, record, begin in variables:
        if record:
            if records in (0, _STREAMING):
                continue
            begin += (records - 1) * record_size
        if begin + size > end:
            end, last = begin + size, name
    if length >= end:
        return None
    return f"the file has {length} bytes, its header places variable {last!r} up to byte {end}"


def _layout(header: _Header) -> tuple[int, list[tuple[str, int, int, bool, int]]]:
    """numrecs and each variable's (name, bytes (of one record), vsize, record?, begin)."""
    records = header.count()
    tag, count = header.integer(4), header.count()
    if tag not in (_ABSENT, _DIMENSION):
        raise EOFError
    sizes = []
    for _ in range(count):
        header.name()
        sizes.append(header.count())
    header.attributes()
    tag, count = header.integer(4), header.count()
    if tag not in (_ABSENT, _VARIABLE):
        raise EOFError
    variables = []
    for _ in range(count):
        start = header.at
        header.name()
        name = header.data[start + (8 if header.wide else 4) : header.at].rstrip(b"\0")
        shape = [sizes[header.count()] for _ in range(header.count())]
        header.attributes()
        size = _TYPE_SIZES.get(header.integer(4), 1)
        vsize, begin = header.count(), header.integer(header.offsets)
        record = bool(shape) and shape[0] == 0
        for extent in shape[1:] if record else shape:
            size *= extent
        variables.append((name.decode("latin-1"), size, vsize, record, begin))
    return records, variables
