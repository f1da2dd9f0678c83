"""Public modules of torchmorph 0.1.0 that moved into the concept subpackages in 0.2.0.

Importing one by its old name still works, with a ``DeprecationWarning`` naming the new
place; its names are those of the new module. The old names will be removed in 0.3.0.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import sys
import types
import warnings

__all__ = ["MOVED"]

#: old module name -> the new modules that hold its names
MOVED = {
    "torchmorph.io": ("torchmorph.mesh.io",),
    "torchmorph.quality": ("torchmorph.mesh.quality", "torchmorph.mesh.norms"),
    "torchmorph.pod_functional": ("torchmorph.pod.functional",),
}


class _MovedModules(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Finds the old names and loads each as a thin module forwarding to the new one."""

    def find_spec(self, name, path=None, target=None):
        if name in MOVED:
            return importlib.machinery.ModuleSpec(name, self)
        return None

    def create_module(self, spec):
        targets = MOVED[spec.name]
        module = types.ModuleType(spec.name, f"Moved to {', '.join(targets)} (deprecated alias).")

        def forward(attribute: str):
            for target in targets:
                found = getattr(importlib.import_module(target), attribute, None)
                if found is not None:
                    return found
            raise AttributeError(f"module {spec.name!r} has no attribute {attribute!r}")

        module.__getattr__ = forward  # type: ignore[method-assign]
        return module

    def exec_module(self, module) -> None:
        targets = MOVED[module.__name__]
        module.__all__ = [
            name
            for target in targets
            for name in getattr(importlib.import_module(target), "__all__", [])
        ]
        warnings.warn(
            f"{module.__name__} moved to {' and '.join(targets)} in torchmorph 0.2.0; import it "
            "from there (the old name will be removed in 0.3.0)",
            DeprecationWarning,
            stacklevel=2,
        )


if not any(isinstance(finder, _MovedModules) for finder in sys.meta_path):
    sys.meta_path.append(_MovedModules())
