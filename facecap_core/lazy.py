"""Modules imported at their first use instead of at the importer's import.

open3d (with the dash and plotly it loads) and trimesh take about 1.5 and 1 s to import.
Every stage module is imported to compute the stages' keys, so a rerun whose every
artifact is stored would pay that for nothing; a :class:`LazyModule` loads them only when
a stage computes.
"""

from __future__ import annotations

import importlib
from types import ModuleType


class LazyModule:
    """Stands for the module ``name``: the first attribute read imports it (through the
    import system, whose lock makes that safe from several threads)."""

    def __init__(self, name: str):
        self._name = name
        self._module: ModuleType | None = None

    def __getattr__(self, attr: str):
        if attr.startswith("__") or attr in ("_name", "_module"):
            # copy, pickle and inspect probe dunders; an instance copied without __init__
            # has neither field (and would recurse here for them)
            raise AttributeError(attr)
        module = self._module
        if module is None:
            module = self._module = importlib.import_module(self._name)
        return getattr(module, attr)

    def __repr__(self) -> str:
        state = "loaded" if self._module is not None else "not loaded yet"
        return f"<lazy module {self._name!r}, {state}>"
