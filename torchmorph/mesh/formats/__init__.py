"""Mesh files, formats and solver cases: every reader returns a :class:`MeshData` (plain
arrays with the file's markers); formats whose other content must survive a morph
(OpenFOAM cases, CalculiX/Abaqus decks, Exodus II files) are written back with only their coordinates
changed."""

from torchmorph.mesh.formats._data import MeshData

__all__ = ["MeshData"]
