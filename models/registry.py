"""Scenario registry: one name per (system, attack, protocol) combination.

A scenario is a frozen dataclass deriving from :class:`Scenario`; each family (four-tank,
load-frequency control, …) defines its own subclass with the settings it needs and
registers instances by name::

    register(FourTankScenario(name="four_tank_bias", ...))
    get("four_tank_bias")            # -> the scenario object
    names(family="lfc")              # -> ["lfc_sawtooth", ...]

Values that a paper leaves open are marked ``[DEF]`` in the scenario's ``notes``; change
them here, in one place, and nowhere else.
"""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["Scenario", "register", "get", "names", "all_scenarios"]


@dataclass(frozen=True)
class Scenario:
    """Common fields of every scenario.

    Attributes:
        name: stable snake_case identifier used by the CLIs and in reports.
        family: which system/paper the scenario belongs to (``"four_tank"``, ``"lfc"``).
        description: one line for ``difffilter-eval --list`` and report headers.
        paper: short citation of the paper the scenario reproduces.
        notes: provenance of non-paper values (``[DEF]`` defaults) for the report.
    """

    name: str
    family: str
    description: str
    paper: str = ""
    notes: tuple[str, ...] = field(default_factory=tuple)


_REGISTRY: dict[str, Scenario] = {}


def register(scenario: Scenario) -> Scenario:
    """Add ``scenario`` under its name; registering the same name twice is an error."""
    if scenario.name in _REGISTRY and _REGISTRY[scenario.name] != scenario:
        raise ValueError(f"scenario {scenario.name!r} is already registered")
    _REGISTRY[scenario.name] = scenario
    return scenario


def _load_builtin() -> None:
    # Importing the family modules registers their scenarios (import side effect kept
    # in one place so that `get` always sees every built-in scenario).
    import importlib

    for module in ("four_tank", "lfc"):
        try:
            importlib.import_module(f"difffilter.models.{module}")
        except ModuleNotFoundError as exc:  # a family not built yet
            if exc.name != f"difffilter.models.{module}":
                raise


def get(name: str) -> Scenario:
    """The scenario called ``name``; ``ValueError`` listing the known names otherwise."""
    _load_builtin()
    try:
        return _REGISTRY[name]
    except KeyError:
        known = ", ".join(sorted(_REGISTRY)) or "(none)"
        raise ValueError(f"unknown scenario {name!r}; known scenarios: {known}") from None


def names(family: str | None = None) -> list[str]:
    """Sorted names of the registered scenarios (of one ``family`` when given)."""
    _load_builtin()
    return sorted(n for n, s in _REGISTRY.items() if family is None or s.family == family)


def all_scenarios() -> list[Scenario]:
    _load_builtin()
    return [_REGISTRY[n] for n in sorted(_REGISTRY)]
