"""``package.module:object`` paths, as both command lines and YAML files take them: a
scenario, a plant's functions, an attack of one's own."""

from __future__ import annotations

import importlib
import os
import sys

__all__ = ["import_object", "import_plugin"]


def _import_module(name: str):
    """``importlib.import_module``, also from the folder the command runs in: a console
    script's ``sys.path`` starts at its own folder, not the working one (``python -m`` and
    ``python script.py`` put the working folder first), so ``my_plants:vdp`` beside the user
    was not found. The working folder is tried last, only for a module not found elsewhere.
    A file's path (``./my_plants``, ``plants/my_plants``) is an ``ImportError``: importlib's
    own ``TypeError`` for a leading dot ("the 'package' argument is required") had reached
    the user as a traceback naming no file or field (an adding-a-scenario trial)."""
    if _reads_as_path(name):
        raise ImportError("a file's path, not a module's name")
    try:
        return importlib.import_module(name)
    except ModuleNotFoundError as error:
        here = os.getcwd()
        missing = error.name or ""
        if name.split(".")[0] != missing.split(".")[0] or here in sys.path or "" in sys.path:
            raise
        sys.path.append(here)
        try:
            return importlib.import_module(name)
        except ModuleNotFoundError as again:
            sys.path.remove(here)
            if again.name != error.name:
                # the working folder took it further (``mine`` found, ``mine.none_such`` not;
                # or a module it imports missing): name what is missing now, not ``mine``
                raise
            raise error from None


def import_object(path: str, where: str):
    """The object a ``package.module:object`` path names (``object`` may be dotted); a
    ``ValueError`` starting with ``where`` if the module or the object is missing."""
    module_name, _, attribute = path.partition(":")
    try:
        obj = _import_module(module_name)
    except ImportError as error:
        raise ValueError(
            f"{where}: cannot import {module_name!r} ({error}){_path_hint(module_name)}"
        ) from None
    for part in attribute.split("."):
        if not hasattr(obj, part):
            raise ValueError(f"{where}: {module_name} has no {attribute!r}")
        obj = getattr(obj, part)
    return obj


def import_plugin(name: str, where: str):
    """Import module ``name`` for what it registers at import (estimators, scenarios), from
    the working folder too (:func:`_import_module`); a ``ValueError`` starting with
    ``where`` if it cannot be imported."""
    try:
        return _import_module(name)
    except ImportError as error:
        raise ValueError(f"{where}: cannot import {name!r} ({error}){_path_hint(name)}") from None


def _path_hint(name: str) -> str:
    """What a module's name is, where ``name`` reads as a file's path ('trial/my_detectors.py',
    './my_plants'), else ``""``."""
    if not (name.endswith(".py") or _reads_as_path(name)):
        return ""
    stem = os.path.splitext(name)[0] if name.endswith(".py") else name
    parts = [p for p in stem.replace(os.sep, "/").split("/") if p not in ("", ".", "..")]
    dotted = ".".join(parts) or stem
    return ("; give a module's name, not a file's path: from the file's folder "
            f"{parts[-1] if parts else stem!r}, or a dotted name from the working folder "
            f"({dotted})")  # fmt: skip


def _reads_as_path(name: str) -> bool:
    """Whether ``name`` is written as a file's path (``./x``, ``plants/x``), which no
    module's name is."""
    return name.startswith(".") or "/" in name or os.sep in name
