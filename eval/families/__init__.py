"""Family-specific evaluation: extra estimators and report sections, one module per family.

A module here registers, when imported, the estimators its scenarios name
(:func:`difffilter.eval.estimators.register`) and the report sections of its family
(:func:`difffilter.eval.report.register_sections`). :func:`load_all` imports every module
of this package, so a new family adds a file and edits no list.
"""

from __future__ import annotations

import importlib
import pkgutil

__all__ = ["load_all"]

_LOADED = False


def load_all() -> None:
    """Import every family module once."""
    global _LOADED
    if _LOADED:
        return
    _LOADED = True
    for info in pkgutil.iter_modules(__path__):
        if not info.name.startswith("_"):
            importlib.import_module(f"{__name__}.{info.name}")
