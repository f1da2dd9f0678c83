"""Atomic file output: a file is either written completely or left as it was.

Every writer in torchmorph (meshes, reports, pictures, caches) goes through
:func:`atomic_output`: the data is written to a temporary file in the target's own
directory (same file system), flushed to disk, and only then renamed over the
target with :func:`os.replace`, which is atomic on POSIX and Windows. If the writer
raises, the temporary file is removed and an existing target is untouched.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

__all__ = ["atomic_output"]


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike, *, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path to write to; on success it replaces ``path`` atomically.

    Parameters
    ----------
    path : str or PathLike
        The file to create or overwrite.
    suffix : str, optional
        Suffix of the temporary file (default: ``path``'s own suffix, so that
        writers choosing a format by extension see the right one).

    Yields
    ------
    Path
        A not-yet-existing file next to ``path``; write it completely.

    Notes
    -----
    The new file gets the permissions of a normally created file (``0o666`` less
    the umask), not the ``0o600`` of :mod:`tempfile`. A writer that creates side
    files (XDMF's ``.h5``) must write those through their own ``atomic_output``
    first, then the file that refers to them.
    """
    target = Path(path)
    directory = target.parent if str(target.parent) else Path(".")
    if not directory.is_dir():
        raise FileNotFoundError(f"path: directory {str(directory)!r} does not exist")
    handle, name = tempfile.mkstemp(
        prefix=f".{target.name}.", suffix=target.suffix if suffix is None else suffix, dir=directory
    )
    os.close(handle)
    temporary = Path(name)
    temporary.unlink()  # the writer creates it; some writers refuse an existing file
    try:
        yield temporary
        if not temporary.exists():
            raise RuntimeError(f"nothing was written for {str(target)!r}")
        with open(temporary, "rb+") as written:
            os.fsync(written.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(temporary, 0o666 & ~umask)
        os.replace(temporary, target)
    finally:
        with contextlib.suppress(FileNotFoundError):
            temporary.unlink()
