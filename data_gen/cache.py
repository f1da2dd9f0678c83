"""On-disk cache of generated meshes.

A mesh is stored as one ``.npz`` file (points, tets, node sets and a JSON
record of how it was built) named ``<case>-<size>-<mesher>-<key>.npz``, where
``<key>`` hashes everything that determines the mesh: case, mesher, every
meshing parameter, the random seed and :data:`FORMAT_VERSION`. The directory is
``cache_dir`` if given, else ``$TORCHMORPH_CACHE``, else
``~/.cache/torchmorph/meshes``.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import warnings
import zipfile
from pathlib import Path

import numpy as np

from data_gen._arrays import MeshArrays
from torchmorph.mesh import atomic_output

__all__ = ["FORMAT_VERSION", "cache_key", "default_cache_dir", "load", "load_or_none", "save"]

#: Bumped whenever a change to the builders changes the meshes they make, so
#: that stale cache entries are not reused.
FORMAT_VERSION = 3
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


def save(path: Path, mesh: MeshArrays) -> bool:
    """Write ``mesh`` to ``path`` atomically; a failure is a warning, not an error.

    The file is written beside its final name and renamed over it when complete
    (:func:`torchmorph.mesh.atomic_output`), with the permissions of a normally
    created file (``0o644`` under the usual umask), so other users of a shared cache
    can read it. If the directory cannot be created or written (a read-only cache, a
    full disk), a :class:`RuntimeWarning` names the path and the reason, and False is
    returned: the caller keeps the mesh it built.
    """
    arrays = {"points": mesh.points, "tets": mesh.tets, "info": np.array(json.dumps(mesh.info))}
    for name, nodes in mesh.node_sets.items():
        arrays[_SET_PREFIX + name] = nodes
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_output(path) as temporary, open(temporary, "wb") as stream:
            # numpy's stubs let the names fill allow_pickle (a bool): none is that name
            np.savez_compressed(stream, **arrays)  # type: ignore[arg-type]
    except OSError as error:
        warnings.warn(
            f"could not write the mesh cache entry {str(path)!r} "
            f"({type(error).__name__}: {error}); the mesh is not cached",
            RuntimeWarning,
            stacklevel=2,
        )
        return False
    return True


def load(path: Path) -> MeshArrays:
    """Read a mesh written by :func:`save`.

    Raises
    ------
    ValueError
        If the file is not a complete cache entry (truncated, corrupt, or missing
        arrays), naming the path.
    """
    try:
        with np.load(path, allow_pickle=False) as data:
            sets = {
                key[len(_SET_PREFIX) :]: data[key].astype(np.int64)
                for key in data.files
                if key.startswith(_SET_PREFIX)
            }
            mesh = MeshArrays(
                points=data["points"].astype(np.float64),
                tets=data["tets"].astype(np.int64),
                node_sets=sets,
                info=json.loads(str(data["info"])),
            )
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as error:
        raise ValueError(
            f"mesh cache entry {str(path)!r} is unreadable ({type(error).__name__}: {error})"
        ) from error
    if (
        mesh.points.ndim != 2
        or mesh.points.shape[1:] != (3,)
        or mesh.tets.ndim != 2
        or mesh.tets.shape[1:] != (4,)
    ):
        raise ValueError(f"mesh cache entry {str(path)!r} holds arrays of the wrong shape")
    return mesh


def load_or_none(path: Path) -> MeshArrays | None:
    """The cached mesh at ``path``, or None if there is none or it is unreadable.

    An unreadable entry (a crash while it was written by an older version, a
    truncated copy, bit rot) is reported with a :class:`RuntimeWarning` and removed
    if possible, so that the caller builds the mesh anew and caches it again.
    """
    if not path.exists():
        return None
    try:
        return load(path)
    except ValueError as error:
        warnings.warn(f"{error}; building the mesh again", RuntimeWarning, stacklevel=2)
        with contextlib.suppress(OSError):
            path.unlink()
        return None
