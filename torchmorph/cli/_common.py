"""Shared pieces of the ``torchmorph`` command: exit codes, errors, option parsers, output
lines and progress, reading meshes and displacement files. See :mod:`torchmorph.cli`."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from torchmorph.mesh.model import Mesh

EXIT_OK = 0
EXIT_ERROR = 1
EXIT_USAGE = 2
EXIT_INVERTED = 3
EXIT_INTERRUPTED = 130

#: The MESH argument's help: the formats :func:`torchmorph.mesh.io.read_mesh` reads.
MESH_HELP = (
    "mesh file (.vtu, .vtk, .xdmf, .msh, .su2, .inp, .mesh, .cgns, .exo, .bdf, .med) or "
    "OpenFOAM case directory"
)
#: Displacement file extensions understood by ``morph --displacement``.
DISPLACEMENT_FORMATS = (".npy", ".npz", ".csv", ".txt", ".dat")


class CommandError(Exception):
    """A failure reported to the user as one line on stderr, with an exit code."""

    def __init__(self, message: str, code: int = EXIT_ERROR) -> None:
        super().__init__(message)
        self.code = code


def _positive_float(text: str) -> float:
    try:
        number = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not (np.isfinite(number) and number > 0):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text!r}")
    return number


def _positive_int(text: str) -> int:
    try:
        number = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if number < 1:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {text!r}")
    return number


def _float_list(*counts: int):
    """A parser of comma-separated numbers, as many as one of ``counts``."""

    def parse(text: str) -> tuple[float, ...]:
        try:
            numbers = tuple(float(part) for part in text.split(","))
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"expected numbers separated by commas, got {text!r}"
            ) from None
        if len(numbers) not in counts:
            expected = " or ".join(str(count) for count in counts)
            raise argparse.ArgumentTypeError(f"expected {expected} number(s), got {text!r}")
        if not np.isfinite(numbers).all():
            raise argparse.ArgumentTypeError(f"expected finite numbers, got {text!r}")
        return numbers

    return parse


def _progress_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--progress",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="progress bars on stderr (default: when stderr is a terminal)",
    )


class _Stages:
    """A progress bar over the named steps of a command (on stderr)."""

    def __init__(self, total: int, enabled: bool | None) -> None:
        from tqdm.auto import tqdm

        self._bar = tqdm(
            total=total,
            file=sys.stderr,
            disable=None if enabled is None else not enabled,
            leave=False,
            unit="step",
            bar_format="{desc:<32} {bar} {n_fmt}/{total_fmt} [{elapsed}]",
        )

    @contextmanager
    def step(self, name: str) -> Iterator[None]:
        self._bar.set_description_str(name)
        self._bar.refresh()
        yield
        self._bar.update(1)

    def close(self) -> None:
        self._bar.close()


def _line(label: str, text: str) -> None:
    print(f"{label:<16}{text}")


def _warn(command: str, message: str) -> None:
    print(f"torchmorph {command}: WARNING: {message}", file=sys.stderr)


def _seconds(value: float) -> str:
    return f"{value:.3g} s" if value >= 1e-3 else f"{value * 1e3:.3g} ms"


def _read(path_text: str, what: str = "mesh") -> tuple[Mesh, dict, dict]:
    """A mesh file, deck or OpenFOAM case directory with its point and cell data."""
    from torchmorph.mesh.io import read_mesh

    path = Path(path_text)
    if not path.exists():
        raise CommandError(f"{what} file {path_text!r} does not exist")
    if (
        not path.is_file()
        and not (path / "constant" / "polyMesh").is_dir()
        and path.name != "polyMesh"
    ):
        raise CommandError(
            f"{what} {path_text!r} is neither a file nor an OpenFOAM case (no constant/polyMesh)"
        )
    try:
        return read_mesh(path, return_data=True)
    except ValueError as error:
        message = str(error).removeprefix("path: ").rstrip()
        if message.endswith(":"):  # parsers that raise without a message
            message += " the file is not a valid mesh in that format"
        raise CommandError(message) from error


def _check_names(mesh: Mesh, names: Sequence[str], option: str) -> None:
    known = mesh.markers
    for name in names:
        if name not in known:
            listing = ", ".join(known) if known else "none (the mesh has no markers)"
            raise CommandError(f"unknown marker {name!r} in {option}; known: {listing}")


def _load_displacement(path_text: str) -> np.ndarray:
    path = Path(path_text)
    suffix = path.suffix.lower()
    if suffix not in DISPLACEMENT_FORMATS:
        raise CommandError(
            f"displacement file {path_text!r}: unsupported extension {suffix or '(none)'!r}; "
            f"supported: {', '.join(DISPLACEMENT_FORMATS)}"
        )
    if not path.is_file():
        raise CommandError(f"displacement file {path_text!r} does not exist")
    try:
        if suffix == ".npy":
            array = np.load(path, allow_pickle=False)
        elif suffix == ".npz":
            with np.load(path, allow_pickle=False) as archive:
                if "displacement" in archive.files:
                    array = archive["displacement"]
                elif len(archive.files) == 1:
                    array = archive[archive.files[0]]
                else:
                    names = ", ".join(archive.files) or "none"
                    raise CommandError(
                        f"displacement file {path_text!r} holds several arrays ({names}) and "
                        "none named 'displacement'"
                    )
        else:
            delimiter = "," if suffix == ".csv" else None
            array = np.loadtxt(path, delimiter=delimiter, comments="#")
    except CommandError:
        raise
    except (OSError, ValueError, EOFError) as error:
        raise CommandError(
            f"could not read displacement file {path_text!r}: {type(error).__name__}: {error}"
        ) from error
    if array.dtype.kind not in "fiu":
        raise CommandError(
            f"displacement file {path_text!r} must hold numbers, got dtype {array.dtype}"
        )
    array = array.astype(np.float64)
    if not np.isfinite(array).all():
        raise CommandError(f"displacement file {path_text!r} holds NaN or infinite values")
    return array


def _boundary_rows(
    array: np.ndarray,
    *,
    source: str,
    num_nodes: int,
    boundary_nodes: np.ndarray,
    moving_nodes: np.ndarray | None,
    moving_label: str,
    batch_index: int | None,
    dim: int = 3,
) -> tuple[np.ndarray, str, float]:
    """The (N_b, D) boundary displacement a file's array stands for (D = ``dim``).

    Returns the rows, a description of the layout used and the largest
    absolute value of the rows that were dropped because they belong to
    boundary nodes outside the moving sets (0 when none).
    """
    num_boundary = boundary_nodes.size
    accepted = []
    if moving_nodes is not None:
        accepted.append(
            f"({moving_nodes.size}, {dim}) for the {moving_nodes.size} moving nodes "
            f"of {moving_label} in ascending node id"
        )
    accepted.append(f"({num_boundary}, {dim}) for the boundary nodes in ascending node id")
    accepted.append(f"({num_nodes}, {dim}) for every node")
    if moving_nodes is not None:
        accepted.append(f"({dim},) for one translation of the moving nodes")
    accepted.append("any of these with a leading batch axis and --batch-index")

    def wrong_shape(extra: str = "") -> CommandError:
        return CommandError(
            f"displacement file {source!r} has shape {tuple(array.shape)}{extra}; accepted "
            f"shapes: {'; '.join(accepted)}"
        )

    if array.ndim == 3:
        count = array.shape[0]
        if batch_index is None:
            if count != 1:
                raise CommandError(
                    f"displacement file {source!r} holds a batch of {count} fields (shape "
                    f"{tuple(array.shape)}); choose one with --batch-index I (0 <= I < {count})"
                )
            batch_index = 0
        if not -count <= batch_index < count:
            raise CommandError(
                f"--batch-index {batch_index} is out of range for a batch of {count} fields "
                f"in {source!r}"
            )
        field = array[batch_index]
    elif batch_index is not None:
        raise CommandError(
            f"--batch-index was given but displacement file {source!r} holds one field, shape "
            f"{tuple(array.shape)}, not a batch (B, ..., {dim})"
        )
    else:
        field = array

    if field.ndim == 1 and field.shape == (dim,) and moving_nodes is not None:
        rows = np.zeros((num_boundary, dim))
        rows[np.searchsorted(boundary_nodes, moving_nodes)] = field
        return rows, f"one translation {tuple(float(v) for v in field)}", 0.0
    if field.ndim != 2 or field.shape[1] != dim:
        extra = (
            f" (a {dim}-D mesh takes {dim}-D displacements)"
            if field.ndim == 2 and field.shape[1] in (2, 3)
            else ""
        )
        raise wrong_shape(extra)
    count = field.shape[0]
    if moving_nodes is not None and count == moving_nodes.size:
        rows = np.zeros((num_boundary, dim))
        rows[np.searchsorted(boundary_nodes, moving_nodes)] = field
        return rows, f"moving-node rows ({count}, {dim})", 0.0
    if count == num_boundary:
        rows, layout = field.copy(), f"boundary-node rows ({count}, {dim})"
    elif count == num_nodes:
        rows, layout = field[boundary_nodes], f"nodal field ({count}, {dim}), boundary rows used"
    else:
        raise wrong_shape(
            ""
            if moving_nodes is not None
            else " (to give only the rows of the moving nodes, name their node sets with --moving)"
        )
    dropped = 0.0
    if moving_nodes is not None:
        keep = np.zeros(num_boundary, dtype=bool)
        keep[np.searchsorted(boundary_nodes, moving_nodes)] = True
        if (~keep).any():
            dropped = float(np.abs(rows[~keep]).max())
        rows[~keep] = 0.0
    return rows, layout, dropped
