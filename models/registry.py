"""Scenario registry: one name per (system, attack, protocol) combination.

A scenario is a frozen dataclass deriving from :class:`~difffilter.models.scenario.Scenario`;
each family (four-tank, load-frequency control, …) is one module of ``models/`` that
defines its own subclass with the settings it needs and registers instances by name
when imported (every module of the package is imported on first use)::

    register(FourTankScenario(name="four_tank_bias", ...))
    get("four_tank_bias")            # -> the scenario object
    names(family="lfc")              # -> ["lfc_sawtooth", ...]

Values that a paper leaves open are marked ``[DEF]`` in the scenario's ``notes``; change
them here, in one place, and nowhere else.
"""

from __future__ import annotations

import importlib
import pkgutil

from .scenario import Scenario

__all__ = ["Scenario", "register", "get", "names", "families", "all_scenarios"]


_REGISTRY: dict[str, Scenario] = {}


def register(scenario: Scenario) -> Scenario:
    """Add ``scenario`` under its name; registering the same name twice is an error."""
    if scenario.name in _REGISTRY and _REGISTRY[scenario.name] != scenario:
        raise ValueError(f"scenario {scenario.name!r} is already registered")
    _REGISTRY[scenario.name] = scenario
    return scenario


_LOADED = False


def _load_builtin() -> None:
    """Import every module of ``difffilter.models`` once: family modules register their
    scenarios when imported, so a new family is one new file and no list to edit."""
    global _LOADED
    if _LOADED:
        return
    _LOADED = True
    package = importlib.import_module("difffilter.models")
    for info in pkgutil.iter_modules(package.__path__):
        if not info.name.startswith("_"):
            importlib.import_module(f"difffilter.models.{info.name}")


def get(name: str) -> Scenario:
    """The scenario called ``name``; ``ValueError`` listing the known names otherwise."""
    _load_builtin()
    try:
        return _REGISTRY[name]
    except KeyError:
        known = ", ".join(sorted(_REGISTRY)) or "(none)"
        raise ValueError(f"unknown scenario {name!r}; known scenarios: {known}") from None


def names(family: str | None = None, *, headline_only: bool = False) -> list[str]:
    """Sorted names of the registered scenarios (of one ``family`` when given; only those
    marked ``headline`` — the ones ``difffilter-eval all`` runs — with ``headline_only``)."""
    _load_builtin()
    return sorted(
        n
        for n, s in _REGISTRY.items()
        if family in (None, s.family) and (s.headline or not headline_only)
    )


def families() -> list[str]:
    """Sorted names of the registered families."""
    _load_builtin()
    return sorted({s.family for s in _REGISTRY.values()})


def all_scenarios() -> list[Scenario]:
    _load_builtin()
    return [_REGISTRY[n] for n in sorted(_REGISTRY)]
