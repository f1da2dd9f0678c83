"""On-disk cache of generated meshes.

A mesh is stored as one ``.npz`` file (points, tets, node sets and a JSON
record of how it was built) named ``<case>-<size>-<mesher>-<key>.npz``, where
``<key>`` hashes everything that determines the mesh: case, mesher, every
meshing parameter, the random seed and :data:`FORMAT_VERSION`. The directory is
``cache_dir`` if given, else ``$TORCHMORPH_CACHE``, else
``~/.cache/torchmorph/meshes``.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from pathlib import Path

import numpy as np

from data_gen._arrays import MeshArrays

__all__ = ["FORMAT_VERSION", "cache_key", "default_cache_dir", "load", "save"]

#: Bumped whenever a change to the builders changes the meshes they make, so
#: that stale cache entries are not reused.
FORMAT_VERSION = 2
_SET_PREFIX = "set:"


def default_cache_dir() -> Path:
    """``$TORCHMORPH_CACHE`` if set, else ``~/.cache/torchmorph/meshes``."""
    env = os.environ.get("TORCHMORPH_CACHE")
    if env:
        return Path(env).expanduser()
    return Path.home() / ".cache" / "torchmorph" / "meshes"


def cache_key(record: dict) -> str:
    """A short stable hash of a JSON-serialisable build record."""
    text = json.dumps({"format": FORMAT_VERSION, **record}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def save(path: Path, mesh: MeshArrays) -> None:
    """Write ``mesh`` to ``path`` atomically (a temporary file, then a rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = {"points": mesh.points, "tets": mesh.tets, "info": np.array(json.dumps(mesh.info))}
    for name, nodes in mesh.node_sets.items():
        arrays[_SET_PREFIX + name] = nodes
    handle, temporary = tempfile.mkstemp(dir=path.parent, suffix=".npz.tmp")
    try:
        with os.fdopen(handle, "wb") as stream:
            np.savez_compressed(stream, **arrays)
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def load(path: Path) -> MeshArrays:
    """Read a mesh written by :func:`save`."""
    with np.load(path, allow_pickle=False) as data:
        sets = {
            key[len(_SET_PREFIX) :]: data[key].astype(np.int64)
            for key in data.files
            if key.startswith(_SET_PREFIX)
        }
        return MeshArrays(
            points=data["points"].astype(np.float64),
            tets=data["tets"].astype(np.int64),
            node_sets=sets,
            info=json.loads(str(data["info"])),
        )
