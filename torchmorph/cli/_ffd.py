"""``torchmorph morph --ffd LATTICE``: the boundary moved by a free-form deformation
lattice (:class:`~torchmorph.ffd.FFD`) instead of a displacement file, the volume then by
IDW or RBF — the pipeline of shape optimisation codes (FFD parametrises the surface, the
mesh morph follows).

The lattice file is a ``.npz`` archive with

- ``origin`` (D,) and ``lengths`` (D,): the box (in the mesh's units);
- ``displacements`` (n_1, …, n_D, D): the control points' displacements, physical units;
- optionally ``basis`` (``"bernstein"``, default, or ``"bspline"``), ``degree`` (B-spline
  only) and ``rotation`` (D, D): as :class:`~torchmorph.ffd.FFD` takes them.

Boundary nodes outside the box do not move; with ``--moving`` only the named sets take
the lattice's motion and every other boundary node is fixed.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from torchmorph.cli._common import CommandError

__all__: list[str] = []

_REQUIRED = ("origin", "lengths", "displacements")
_OPTIONAL = ("basis", "degree", "rotation")


def load_lattice(path_text: str) -> dict[str, Any]:
    """The lattice archive's arrays, checked for presence (values are checked by FFD)."""
    path = Path(path_text)
    if path.suffix.lower() != ".npz":
        raise CommandError(f"--ffd {path_text!r}: expected a .npz archive ({', '.join(_REQUIRED)})")
    if not path.is_file():
        raise CommandError(f"--ffd {path_text!r} does not exist")
    try:
        with np.load(path, allow_pickle=False) as archive:
            arrays = {name: archive[name] for name in archive.files}
    except (OSError, ValueError, EOFError) as error:
        raise CommandError(f"--ffd {path_text!r}: cannot read it ({error})") from error
    missing = [name for name in _REQUIRED if name not in arrays]
    if missing:
        raise CommandError(
            f"--ffd {path_text!r}: the archive lacks {', '.join(missing)} (it holds "
            f"{', '.join(arrays) or 'nothing'}); needed: {', '.join(_REQUIRED)}"
        )
    unknown = sorted(set(arrays) - set(_REQUIRED) - set(_OPTIONAL))
    if unknown:
        raise CommandError(
            f"--ffd {path_text!r}: unknown array(s) {', '.join(unknown)}; the archive takes "
            f"{', '.join(_REQUIRED + _OPTIONAL)}"
        )
    return arrays


def ffd_rows(
    path_text: str, points: np.ndarray, boundary: np.ndarray, moving: np.ndarray | None
) -> tuple[np.ndarray, str]:
    """Boundary displacement rows (N_b, D) from the lattice of ``path_text`` at the
    mesh's ``points`` (N, D), and a line for the report. ``moving``: the global ids of
    the nodes that may move (None: every boundary node)."""
    import torch

    from torchmorph.ffd import FFD

    arrays = load_lattice(path_text)
    dim = points.shape[1]
    displacements = np.asarray(arrays["displacements"], dtype=np.float64)
    if displacements.ndim != dim + 1 or displacements.shape[-1] != dim:
        raise CommandError(
            f"--ffd {path_text!r}: displacements must have shape (n_1, ..., n_{dim}, {dim}) for "
            f"a {dim}-D mesh, got {displacements.shape}"
        )
    options: dict[str, Any] = {}
    if "basis" in arrays:
        options["basis"] = str(arrays["basis"])
    if "degree" in arrays:
        options["degree"] = int(arrays["degree"])
    if "rotation" in arrays:
        options["rotation"] = torch.as_tensor(np.asarray(arrays["rotation"], dtype=np.float64))
    nodes = boundary if moving is None else np.intersect1d(boundary, moving)
    try:
        ffd = FFD(
            torch.as_tensor(points[nodes], dtype=torch.float64),
            origin=torch.as_tensor(np.asarray(arrays["origin"], dtype=np.float64)),
            lengths=torch.as_tensor(np.asarray(arrays["lengths"], dtype=np.float64)),
            shape=displacements.shape[:-1],
            **options,
        )
        moved = ffd(torch.as_tensor(displacements)).numpy()
    except (ValueError, TypeError) as error:
        raise CommandError(f"--ffd {path_text!r}: {error}") from error
    rows = np.zeros((boundary.shape[0], dim))
    rows[np.searchsorted(boundary, nodes)] = moved
    lattice = " x ".join(str(n) for n in displacements.shape[:-1])
    summary = (
        f"FFD lattice {lattice} ({ffd.basis}): {ffd.num_inside:,} of {nodes.shape[0]:,} "
        f"{'moving' if moving is not None else 'boundary'} nodes in the box"
    )
    if ffd.num_inside == 0:
        raise CommandError(
            f"--ffd {path_text!r}: no {'moving' if moving is not None else 'boundary'} node "
            "lies in the lattice's box, so nothing would move; check origin and lengths"
        )
    return rows, summary
