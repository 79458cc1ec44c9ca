"""Family-specific report sections, one module per family.

A family's scenarios and estimators live in ``difffilter.models`` (its module registers
them when imported, with :func:`difffilter.models.estimators.register`); a module here
registers the family's report sections (:func:`difffilter.eval.report.register_family`).
:func:`load_all` imports every module of ``difffilter.models`` and of this package, so a
new family adds files and edits no list.
"""

from __future__ import annotations

import functools
import importlib
import pkgutil

__all__ = ["load_all"]


@functools.cache
def load_all() -> None:
    """Import every module of ``difffilter.models``, then every family module here, once."""
    from difffilter.models.registry import all_scenarios

    all_scenarios()
    for info in pkgutil.iter_modules(__path__):
        if not info.name.startswith("_"):
            importlib.import_module(f"{__name__}.{info.name}")
