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

Scenarios from outside the repository, wherever a scenario name is taken (both command
lines, ``run_suite``, the training config's ``scenario``):

- ``"package.module:object"``: the module is imported and ``object`` (a dotted path in it)
  is a :class:`~difffilter.models.scenario.Scenario` or a function of no arguments that
  returns one (called once a process: every later ``get`` of the path, or an entry point
  naming the same function, gives that scenario); it is registered under its own name
  (:func:`get` returns it);
- ``"path/to/scenario.yaml"``: a scenario written in YAML (a linear plant's matrices, or a
  plant given by Python function paths; :mod:`difffilter.models.yaml_scenario`),
  registered under its ``name``;
- installed plug-ins: every entry point of the group ``difffilter.scenarios`` (in a
  package's ``pyproject.toml``: ``[project.entry-points."difffilter.scenarios"]
  my_plant = "my_package.scenarios"``) is loaded with the built-in families. A module
  registers its scenarios when imported; an object that is a scenario, a list of them, or
  a function returning either is registered. A plug-in that fails to load is reported
  with a warning, not an error, so the built-in scenarios keep working.
"""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import math
import pkgutil
import sys
import threading
import warnings
from collections.abc import Callable
from importlib.metadata import entry_points
from pathlib import Path

import torch

from difffilter._checks import add_note

from .scenario import CustomScenario, Scenario
from .yaml_scenario import import_object, is_yaml_path, scenario_file_digest, scenario_from_yaml

__all__ = [
    "Scenario",
    "register",
    "get",
    "names",
    "families",
    "all_scenarios",
    "nearest",
    "source_file",
]


_REGISTRY: dict[str, Scenario] = {}
#: Where each name was registered (the module, plug-in or file): a second definition of a
#: name is blamed on itself and names the first, wherever the import order put them.
_ORIGINS: dict[str, str] = {}
#: The YAML file each scenario registered from a file was read from (absolute) and its
#: digest as it was read: reports record both (:func:`source_file`).
_FILES: dict[str, tuple[Path, str | None]] = {}
#: Words both command lines read as selections, not scenario names (``all`` runs every
#: headline scenario, ``robustness`` their threats); a family's name selects the family.
RESERVED_NAMES = ("all", "robustness")


def register(scenario: Scenario, *, origin: str | None = None) -> Scenario:
    """Add ``scenario`` under its name; registering the same name twice is an error, and so
    is a name that the command lines would read as a selection (``all``, ``robustness``, a
    family's name) or a family named like a registered scenario or like those words. ``origin``: where it comes
    from, for that error (by default the module that calls this).

    A scenario registered from outside ``difffilter.models`` first loads the built-in
    families (:func:`_load_builtin`), so that its name is checked against theirs: a user's
    module registering a scenario named ``robot`` before anything had asked the registry
    was accepted, and every later call then failed blaming ``difffilter.models.robot``."""
    origin = origin or _caller_module()
    if not _LOADED and not origin.startswith(f"module {__package__}."):
        _load_builtin()
    name = scenario.name
    if (
        name in _REGISTRY
        and _REGISTRY[name] is not scenario
        and (_differ(_REGISTRY[name], scenario) or _unseen_difference(_REGISTRY[name], scenario))
    ):
        raise ValueError(
            f"scenario {name!r} is already registered, by {_ORIGINS.get(name, '?')}, as a "
            f"different scenario; {origin} registers another under that name (or a file "
            "edited since it was loaded): a name is registered once a process; give this one "
            "another name, or load the edited file in a new process"
        )
    clash = _selection_clash(scenario)
    if clash:
        raise ValueError(f"{origin}: {clash}")
    if name not in _REGISTRY:  # (the same scenario again keeps its first origin)
        _ORIGINS[name] = origin
    _REGISTRY[name] = scenario
    return scenario


def _differ(old: Scenario, new: Scenario) -> bool:
    """Whether two scenarios differ in their compared fields: by ``==``, or, where ``==``
    says no, by content (:func:`_same_content`): an attack without value equality (the
    library's ``Signal``, a plain class of one's own) compares by identity, so a YAML file
    read again unchanged with such an attack read as another scenario (a red-team trial)."""
    if old == new:
        return False
    if type(old) is not type(new) or not dataclasses.is_dataclass(old):
        return True
    return not all(
        _same_content(getattr(old, f.name), getattr(new, f.name))
        for f in dataclasses.fields(old)
        if f.compare
    )


def _same_content(a, b, depth: int = 0) -> bool:
    """Whether ``a`` and ``b`` hold the same values: ``==``, tensors by dtype, shape and
    values, sequences and mappings item by item, and objects whose class keeps identity
    equality (or whose ``==`` cannot answer, tensors inside) of one class by their
    attributes. Functions compare by identity: a fresh closure is another object (what it
    computes is not compared), so this errs towards "different", the refusal."""
    if a is b:
        return True
    if isinstance(a, torch.Tensor) or isinstance(b, torch.Tensor):
        return (isinstance(a, torch.Tensor) and isinstance(b, torch.Tensor)
                and a.dtype == b.dtype and a.shape == b.shape and torch.equal(a, b))  # fmt: skip
    if type(a) is not type(b) or depth > 8:  # (depth: a cycle of attributes reads "different")
        return False
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(_same_content(x, y, depth + 1) for x, y in zip(a, b))
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same_content(a[k], b[k], depth + 1) for k in a)
    try:
        if bool(a == b):
            return True
        asked = type(a).__eq__ is not object.__eq__
    except Exception:  # (e.g. a dataclass of tensors: "ambiguous")
        asked = False
    if asked or not hasattr(a, "__dict__"):  # its own equality said no: believe it
        return False
    return _same_content(vars(a), vars(b), depth + 1)


def _unseen_difference(old: Scenario, new: Scenario) -> bool:
    """Whether two scenarios that dataclass equality calls the same differ where it does not
    look: a :class:`CustomScenario`'s plant, known inputs and options (functions and
    mappings, left out of its ``==`` so that a YAML file read again, with fresh functions,
    is the same scenario). The plant is compared by its class and its tensors, the inputs
    by their values: a file whose matrices were edited since it was loaded replaced the
    plant under its name without a word (a review), where an edited ``steps`` was refused.
    Python functions a plant calls are not compared."""
    if not isinstance(old, CustomScenario) or not isinstance(new, CustomScenario):
        return False
    if dict(old.options) != dict(new.options):
        return True
    a, b = old.system(torch.float64), new.system(torch.float64)
    tensors_a, tensors_b = a.state_dict(), b.state_dict()
    if type(a) is not type(b) or tensors_a.keys() != tensors_b.keys():
        return True
    if any(not torch.equal(tensors_a[k], tensors_b[k]) for k in tensors_a):
        return True
    # every run of both tables: run i takes row i mod R, so the two agree on every run
    # iff they agree on lcm(R_a, R_b) runs (2 runs had missed an edit of a third row)
    runs = math.lcm(_input_rows(old), _input_rows(new))
    inputs_a, inputs_b = old.inputs(runs, torch.float64), new.inputs(runs, torch.float64)
    if inputs_a is None or inputs_b is None:
        return (inputs_a is None) != (inputs_b is None)
    return inputs_a.shape != inputs_b.shape or not torch.equal(inputs_a, inputs_b)


def _input_rows(scenario: CustomScenario) -> int:
    """The rows ``R`` of a scenario's known-inputs table ``[R, T, du]`` (1 for a table of
    every run ``[T, du]``, a function of ``k`` or none)."""
    known = scenario.known_inputs
    return known.shape[0] if isinstance(known, torch.Tensor) and known.dim() == 3 else 1


def _selection_clash(scenario: Scenario) -> str | None:
    """Why ``scenario`` could not be selected by its name, or ``None``: ``difffilter-eval
    NAME`` reads ``all``, ``robustness`` and every family's name as a selection first."""
    name, family = scenario.name, scenario.family
    known = {s.family: s.name for s in _REGISTRY.values()}
    if name in RESERVED_NAMES or name in known or name == family:
        what = (f"{name!r} is a word of the command lines ({' and '.join(RESERVED_NAMES)} "
                "select many scenarios)" if name in RESERVED_NAMES
                else f"{name!r} is the name of a family ({name!r} selects its scenarios)")  # fmt: skip
        return (f"scenario name {what}, so the scenario could never be run by name; give it "
                "another name")  # fmt: skip
    if family in RESERVED_NAMES:  # `difffilter-eval all` runs every family's headline
        return (f"scenario {name!r} is of family {family!r}, a word of the command lines "
                f"({' and '.join(RESERVED_NAMES)} select every family's headline scenarios, "
                "never this family alone); give the family another name")  # fmt: skip
    if family in _REGISTRY and family != name:
        return (f"scenario {name!r} is of family {family!r}, the name of a registered "
                f"scenario ({family!r} would select the family, never that scenario); give "
                "the family another name")  # fmt: skip
    return None


def _caller_module() -> str:
    """The module that called :func:`register` (outside this one)."""
    frame = sys._getframe(1)
    while frame is not None and frame.f_globals.get("__name__") == __name__:
        frame = frame.f_back
    module = frame.f_globals.get("__name__", "?") if frame is not None else "?"
    return f"module {module}"


_LOADED = False
#: Whether the built-in families are being imported (by the thread holding the lock): a
#: module that asks the registry while it loads finds it loading.
_LOADING = False
#: One loader: threads that make their first registry call together had found it marked
#: loaded while another was still importing the families ("known scenarios: (none)", a
#: concurrency trial); they now wait for it.
_LOAD_LOCK = threading.RLock()


def _load_builtin() -> None:
    """Import every module of ``difffilter.models`` once: family modules register their
    scenarios when imported, so a new family is one new file and no list to edit."""
    global _LOADED, _LOADING
    if _LOADED:
        return
    with _LOAD_LOCK:
        if _LOADED or _LOADING:  # (loaded by another thread meanwhile, or this one loading)
            return
        _LOADING = True
        try:
            _import_families()
            _LOADED = True
        finally:
            _LOADING = False


def _import_families() -> None:
    """The body of :func:`_load_builtin`: the built-in modules, then the plug-ins."""
    package = importlib.import_module("difffilter.models")
    for info in pkgutil.iter_modules(package.__path__):
        if info.name.startswith("_"):
            continue
        try:
            importlib.import_module(f"difffilter.models.{info.name}")
        except Exception as error:
            # a module that fails (a contributor's new family) fails every later call too,
            # named, instead of leaving the registries without the modules after it
            add_note(error, f"(while importing difffilter.models.{info.name}: every module of "
                           "difffilter.models is imported to register its scenarios)")  # fmt: skip
            raise
    for point in entry_points(group=PLUGIN_GROUP):
        # a module imported here for the first time that registers nothing was silently
        # absent from every list (its scenarios defined, register() never called)
        fresh, before = point.value.split(":")[0].strip() not in sys.modules, len(_REGISTRY)
        try:
            obj = point.load()
            _register_all(obj, f"entry point {point.name!r} ({point.value})")
        except Exception as error:  # a broken plug-in must not hide the built-in scenarios
            warnings.warn(
                f"difffilter: the scenario plug-in {point.name!r} ({point.value}) failed to "
                f"load: {type(error).__name__}: {error}",
                stacklevel=3,  # (the caller of _load_builtin)
            )
            continue
        if fresh and isinstance(obj, type(importlib)) and len(_REGISTRY) == before:
            warnings.warn(
                f"difffilter: the scenario plug-in {point.name!r} ({point.value}) registered no "
                "scenario: a module must call difffilter.models.registry.register(scenario) "
                "when imported, or the entry point may name its scenario (module:object)",
                stacklevel=3,  # (the caller of _load_builtin)
            )


#: The entry-point group of installed scenario plug-ins.
PLUGIN_GROUP = "difffilter.scenarios"


def _register_all(obj, where: str, *, one: bool = False) -> list[Scenario]:
    """Register what a plug-in or a ``module:object`` path gave: a scenario, a list of
    them, a function of no arguments returning either, or a module (already registered);
    ``one``: exactly one scenario, or ``ValueError`` before any is registered (a path names
    one: a function returning two had its first evaluated and the other dropped silently,
    a red-team trial)."""
    if isinstance(obj, type(importlib)):  # a module: it registered itself when imported
        return []
    if callable(obj) and not isinstance(obj, Scenario):
        obj = _called(obj, where)
    items = obj if isinstance(obj, (list, tuple)) else [obj]
    if one and len(items) != 1:
        raise ValueError(
            f"{where} gave {len(items)} scenarios; a path names one: name each on its own "
            "(e.g. package.module:first_plant), or register them in the module and name them"
        )
    bad = [type(s).__name__ for s in items if not isinstance(s, Scenario)]
    if bad:
        raise ValueError(
            f"{where} is not a difffilter scenario (a Scenario, e.g. CustomScenario, a list of "
            f"them, or a function returning one); got {', '.join(bad)}"
        )
    return [register(s, origin=where) for s in items]


#: What each function a path or a plug-in names returned, by the function's ``id`` (with
#: the function, so the id is not reused): it is called once a process. A scenario built
#: again need not equal itself (an attack without value equality, such as
#: :class:`~difffilter.models.attacks.Signal`, compares by identity), so a second call
#: read as another scenario under its name, "a file edited since it was loaded", and
#: difffilter-train, which asks the registry twice, stopped (a red-team trial).
_CALLED: dict[int, tuple[Callable, object]] = {}


def _called(function: Callable, where: str):
    """``function()``, once a process (:data:`_CALLED`); ``ValueError`` if it needs
    arguments."""
    known = _CALLED.get(id(function))
    if known is not None and known[0] is function:
        return known[1]
    try:
        inspect.signature(function).bind()
    except TypeError:  # (a model function dtype -> model, named by mistake)
        raise ValueError(
            f"{where} is a function that needs arguments; name a scenario (e.g. a "
            "CustomScenario), a list of them, or a function of no arguments returning one"
        ) from None
    except ValueError:  # no signature to read (a builtin): call it and see
        pass
    result = function()
    _CALLED[id(function)] = (function, result)
    return result


def _from_path(path: str) -> Scenario:
    """The scenario of ``"package.module:object"`` (module docstring), registered."""
    obj = import_object(path, f"scenario {path!r}")
    if isinstance(obj, type(importlib)) or isinstance(obj, (list, tuple)):
        raise ValueError(
            f"scenario {path!r}: name one scenario (module:object), not a module or list"
        )
    return _register_all(obj, f"scenario {path!r}", one=True)[0]


def get(name: str) -> Scenario:
    """The scenario called ``name``, or the one a ``"package.module:object"`` path names
    (module docstring); ``ValueError`` listing the known names otherwise."""
    _load_builtin()
    if is_yaml_path(name):
        # the digest of the file as read (taken just before it is: an edit during a study
        # had been recorded on the numbers of the file before it, a review)
        digest = scenario_file_digest(name)
        scenario = _register_all(scenario_from_yaml(name), f"scenario file {name!r}")[0]
        _FILES.setdefault(scenario.name, (Path(name).resolve(), digest))
        return scenario
    if ":" in name:
        return _from_path(name)
    try:
        return _REGISTRY[name]
    except KeyError:
        known = ", ".join(sorted(_REGISTRY)) or "(none)"
        # (difffilter-eval suggested the nearest names, difffilter-train did not: a docs trial)
        hint = nearest(name, sorted(_REGISTRY))
        raise ValueError(f"unknown scenario {name!r}; {hint}known scenarios: {known}") from None


def source_file(name: str) -> tuple[Path, str | None] | None:
    """The YAML file (absolute path) that the scenario registered as ``name`` was read from
    in this process and its :func:`~.yaml_scenario.scenario_file_digest` as it was read, or
    ``None`` for a built-in scenario or one a ``module:object`` path named."""
    return _FILES.get(name)


def nearest(name, candidates) -> str:
    """``"did you mean A or B? "``: the (at most three) ``candidates`` closest to ``name``,
    or ``""`` where none is close (a misspelt name in an error)."""
    import difflib

    close = difflib.get_close_matches(str(name), list(candidates), n=3, cutoff=0.6)
    return f"did you mean {' or '.join(close)}? " if close else ""


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
