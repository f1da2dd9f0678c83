"""HDF5 helpers shared by the CGNS and MED formats."""

from __future__ import annotations

import numpy as np

__all__ = ["set_text_attribute"]


def set_text_attribute(node, key: str, value: str, size: int | None = None) -> None:
    """Set a scalar string attribute as the CGNS and MED libraries write them: ``size``
    bytes (the text's length + 1 by default), NUL-terminated. Readers built on those
    libraries misread the NUL-padded strings that h5py writes by default."""
    import h5py

    encoded = value.encode("utf-8")
    size = len(encoded) + 1 if size is None else size
    if len(encoded) > size - 1:
        raise ValueError(
            f"{key}: {value!r} holds {len(encoded)} bytes; the attribute holds at most {size - 1}"
        )
    string_type = h5py.h5t.C_S1.copy()
    string_type.set_size(size)
    string_type.set_strpad(h5py.h5t.STR_NULLTERM)
    if key in node.attrs:
        del node.attrs[key]
    space = h5py.h5s.create(h5py.h5s.SCALAR)
    attribute = h5py.h5a.create(node.id, key.encode(), string_type, space)
    attribute.write(np.array(encoded.ljust(size, b"\0"), dtype=f"S{size}"), mtype=string_type)
