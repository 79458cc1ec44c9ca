"""Calibrations kept on disk, per scenario, seed and model parameters.

A detector calibrated on attack-free runs (the CUSUM threshold τ of
:meth:`~difffilter.models.estimators.SuiteContext.cusum`: 50 runs through a filter) gives
the same number every time for the same scenario, seed, runs, filter, rate and model, so
it is computed once and kept: in memory for the process, and as a small JSON file under
the cache folder for every later process.

The folder is ``$DIFFFILTER_CACHE`` if set (``off`` turns the disk cache off), else
``$XDG_CACHE_HOME/difffilter``, else ``~/.cache/difffilter``; each calibration is
``calibrations/<kind>-<sha256>.json``. The file name hashes the key, the library's own
code (:func:`library_fingerprint`: a new version calibrates again) and a fingerprint of
the model: its type, every tensor or numpy array it holds (matrices, noise covariances,
the prior), the code of the methods its class and their bases define (a plant subclass's
``transition`` and ``observe``), and the code, constants, default arguments and closures of
the functions it holds (a nonlinear
plant's ``f`` and ``h``) with the module-level values and helper functions they read by
name, so editing the plant gives a new file, never a stale number. The module-level values
a method reads are not seen (as for a module, below). A module is hashed by
its name only: a constant read through one (``params.G``) is not seen, and after editing
one the folder should be deleted. Deleting the folder is always safe.
"""

from __future__ import annotations

import decimal
import fractions
import functools
import hashlib
import json
import os
import threading
import types
import weakref
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from .atomic_write import write_atomically

__all__ = ["cache_folder", "model_fingerprint", "library_fingerprint", "cached", "FORMAT"]

#: Bumped when what a calibration computes, or how its key is read, changes: older files
#: are then ignored (2: nested groups read apart; 3: a repeat names what it repeats).
FORMAT = 3


def cache_folder() -> Path | None:
    """The cache folder (module docstring), or ``None`` when ``DIFFFILTER_CACHE=off``."""
    env = os.environ.get("DIFFFILTER_CACHE")
    if env is not None:
        return None if env.strip().lower() in ("off", "0", "false", "") else Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "difffilter"


def _feed(digest, value: Any, seen: dict[int, tuple[int, Any]], depth: int = 0) -> None:
    """Hash what determines a model's numbers: tensors by value, functions by code."""
    # (deep enough for a model inside a tuple: tuple → model → modules → noise → buffers)
    if depth > 16:
        # a network nested deeper (blocks of blocks of layers) by its weights, not skipped:
        # another network loaded under the same name had kept the old CUSUM τ (a trial);
        # the walk meets it as a module or in a module's `_modules`, and a module met at
        # depth 15-16 as its `_parameters` and `_buffers` (tensors: they had been dropped,
        # its weights never hashed, a stale τ served; a calibration-cache trial)
        items = value.values() if isinstance(value, dict) else value
        group = items if isinstance(value, (dict, list, tuple)) else (value,)
        for module in group:
            if isinstance(module, (torch.Tensor, np.ndarray, np.generic)):
                _feed(digest, module, seen, 0)
            elif isinstance(module, torch.nn.Module) and id(module) not in seen:
                seen[id(module)] = (len(seen), module)
                digest.update(f"module {type(module).__qualname__}".encode())
                for name, tensor in module.state_dict().items():
                    digest.update(name.encode())
                    _feed(digest, tensor, seen, 0)
        return
    met = seen.get(id(value))
    if met is not None:  # met before: a mark naming which, so that (a, a) and (a,) read
        # apart, and (a, b, a) and (a, b, b) too (a bare mark had read them alike: a plant
        # reading [SLOW, FAST, SLOW] edited to [SLOW, FAST, FAST] kept its CUSUM τ, a trial)
        digest.update(f"<again {met[0]}>".encode())
        return
    if isinstance(value, torch.Tensor):
        digest.update(str((value.dtype, tuple(value.shape))).encode())
        digest.update(_tensor_bytes(value))
        return
    if isinstance(value, (np.ndarray, np.generic)):  # (a plant's constants in numpy)
        array = np.ascontiguousarray(value)
        digest.update(str((array.dtype, array.shape)).encode())
        digest.update(array.tobytes())
        return
    if isinstance(value, (int, float, complex, str, bytes, bool, type(None), range,
                          fractions.Fraction, decimal.Decimal)):  # fmt: skip
        # (by repr: complex, Fraction and Decimal values had been hashed by type alone)
        digest.update(f"{type(value).__name__}:{value!r}".encode())
        return
    # its order of first meeting, and the object itself: held, so that its id is not
    # reused by an object made while hashing (a bound method read twice is two objects)
    seen[id(value)] = (len(seen), value)
    if isinstance(value, (list, tuple)):
        # its type and length first: nested groups had flattened alike (((0, 1), (2,)) and
        # ((0,), (1, 2)), two schedules, got one cached threshold: a trial)
        digest.update(f"{type(value).__name__}[{len(value)}]".encode())
        for item in value:
            _feed(digest, item, seen, depth + 1)
        return
    if isinstance(value, (set, frozenset)):  # in a stable order (a set's own is per process)
        digest.update(type(value).__name__.encode())
        for item in sorted(value, key=repr):
            _feed(digest, item, seen, depth + 1)
        return
    if isinstance(value, types.MethodType):  # a bound method: the object it is bound to too
        _feed(digest, value.__self__, seen, depth + 1)
        _feed(digest, value.__func__, seen, depth + 1)
        return
    if isinstance(value, functools.partial):  # its function and the arguments it binds
        digest.update(b"partial")
        for part in (value.func, value.args, value.keywords):
            _feed(digest, part, seen, depth + 1)
        return
    if isinstance(value, dict):
        digest.update(f"dict[{len(value)}]".encode())
        for key in sorted(value, key=repr):
            digest.update(repr(key).encode())
            _feed(digest, value[key], seen, depth + 1)
        return
    if isinstance(value, (types.BuiltinFunctionType, types.BuiltinMethodType)):
        # by name: torch.sin and torch.cos have no code to hash, and had both been hashed
        # as their type (a plant reading ACT = torch.sin edited to torch.cos kept its τ)
        owner = getattr(value, "__self__", None)
        where = getattr(value, "__module__", None) or type(owner).__qualname__
        digest.update(f"builtin {where}.{getattr(value, '__qualname__', value.__name__)}".encode())
        if owner is not None and not isinstance(owner, (types.ModuleType, type)):
            _feed(digest, owner, seen, depth + 1)  # bound to an object: its values too (x.add)
        return
    code = getattr(value, "__code__", None)
    if code is not None:  # a function: its code, constants, defaults, closure and globals
        _feed_code(digest, code)
        _feed(digest, getattr(value, "__defaults__", None), seen, depth + 1)
        _feed(digest, getattr(value, "__kwdefaults__", None), seen, depth + 1)
        for cell in getattr(value, "__closure__", None) or ():
            try:
                _feed(digest, cell.cell_contents, seen, depth + 1)
            except ValueError:  # an empty cell
                pass
        # the module-level names it reads: a plant's constants (G = 9.81) and the helpers
        # it calls (a user trial edited both and read a stale CUSUM threshold)
        namespace = getattr(value, "__globals__", None) or {}
        for name in sorted(_global_names(code)):
            if name in namespace:
                digest.update(name.encode())
                _feed_global(digest, namespace[name], seen, depth + 1)
        return
    digest.update(type(value).__qualname__.encode())
    digest.update(_class_code(type(value)))
    attributes = dict(getattr(value, "__dict__", None) or {})
    for klass in type(value).__mro__:  # the values of ``__slots__`` (no ``__dict__`` entry)
        slots = vars(klass).get("__slots__", ())
        for slot in (slots,) if isinstance(slots, str) else slots:
            if slot not in ("__dict__", "__weakref__") and hasattr(value, slot):
                attributes.setdefault(slot, getattr(value, slot))
    # less the memos of derived values (``*_cache``: addresses)
    for key in sorted(attributes, key=repr):
        if not str(key).endswith("_cache"):
            digest.update(repr(key).encode())
            _feed(digest, attributes[key], seen, depth + 2)


def _tensor_bytes(tensor: torch.Tensor) -> bytes:
    """A tensor's values as bytes, for every dtype: numpy has no bfloat16 or float8, so those
    are read as their raw bytes (a plant holding a bfloat16 tensor had crashed the
    fingerprint, and with it the evaluation)."""
    values = tensor.detach().cpu().contiguous()
    try:
        return values.numpy().tobytes()
    except TypeError:  # (no numpy dtype: the same bytes through uint8)
        return values.reshape(-1).view(torch.uint8).numpy().tobytes()


def _class_code(cls: type) -> bytes:
    """A digest of the code of the methods ``cls`` and its bases define (torch's and the
    builtins' aside): a plant subclass's ``observe`` or ``transition`` edited gives a new
    file (a trial: ``h = x³`` edited to ``4x³`` had read the old CUSUM threshold, 708
    against 3366). Their code, constants and defaults; not the module-level values they
    read (as for a module: delete the cache folder after editing one). What the code gives
    is kept for the class while its members are the same objects; the constants are read
    again at every call (a tensor or list edited in place is the same object:
    ``Plant.A[0, 0] = 0.5`` had kept the digest, and the suite's in-process CUSUM τ, for
    the process; a cache trial). The digest is the same stream of bytes either way."""
    members = _members(cls)
    memo = _CLASS_CODE.get(cls)
    known = None
    if memo is not None and len(memo[0]) == len(members):
        if all(map(_still, memo[0], members)):
            known = memo[1]
    if known is None:
        # (a default of the class itself: no recursion). The mark is this thread's: kept in
        # the shared memo, another thread fingerprinting a model of the class meanwhile had
        # taken it for the class's code (a concurrency trial: 33 of 80 digests wrong)
        busy = _classes_being_hashed()
        if cls in busy:
            return _IN_PROGRESS_MARK
        busy.add(cls)
        try:
            known = _class_segments(cls)
        finally:
            busy.discard(cls)
        _CLASS_CODE[cls] = (tuple(map(_hold_weakly, members)), known)
    digest = hashlib.sha256()
    for segment in known:
        if isinstance(segment, bytes):
            digest.update(segment)
        else:  # a constant, by its value now
            _feed(digest, segment[0], {})
    return digest.digest()


#: What a class met again while it is being hashed (its own default) reads as.
_IN_PROGRESS_MARK = b"(in progress)"

_HASHING = threading.local()


def _classes_being_hashed() -> set:
    """The classes this thread is hashing (:func:`_class_code`)."""
    busy = getattr(_HASHING, "classes", None)
    if busy is None:
        busy = _HASHING.classes = set()
    return busy


def _class_segments(cls: type) -> list:
    """The segments :func:`_class_code` digests: the code of ``cls``'s methods and its
    constants, base by base."""
    digest = _ByteStream()
    for klass in cls.__mro__:
        if klass.__module__.split(".")[0] in _SKIPPED_MODULES:
            continue
        digest.update(klass.__qualname__.encode())
        for name, attr in sorted(vars(klass).items()):
            if isinstance(attr, (staticmethod, classmethod)):
                attr = attr.__func__
            elif isinstance(attr, property):
                attr = attr.fget
            code = getattr(attr, "__code__", None)
            if code is not None:
                digest.update(name.encode())
                _feed_code(digest, code)
                # defaults by value, keyword-only ones too (a repr holds an address
                # where the default is a function: a new digest in every process)
                _feed(digest, getattr(attr, "__defaults__", None), {})
                _feed(digest, getattr(attr, "__kwdefaults__", None), {})
            elif not name.startswith("__") and _plain_value(attr):
                # a constant of the class (G = 9.81 read as self.G): edited, it had kept
                # its CUSUM τ; numbers, strings and tensors, and groups of them
                digest.update(name.encode())
                digest.constant(attr)
    return digest.segments()


class _ByteStream:
    """What :func:`_class_code` feeds a digest, kept as segments: the bytes of the code, and
    the class's constants as objects (``(value,)``), to be hashed by value at each use."""

    def __init__(self):
        self._segments: list = [bytearray()]

    def update(self, data: bytes) -> None:
        self._segments[-1] += data

    def constant(self, value) -> None:
        self._segments += [(value,), bytearray()]

    def segments(self) -> list:
        return [bytes(s) if isinstance(s, bytearray) else s for s in self._segments]


def _plain_value(value) -> bool:
    """Whether a class attribute is a constant to hash by value: a number, string, tensor
    or array, or a tuple, list or dict of them (not a class, descriptor or object, whose
    hashing is the generic one's)."""
    if isinstance(value, (int, float, complex, str, bytes, bool, type(None), torch.Tensor,
                          np.ndarray, np.generic)):  # fmt: skip
        return True
    if isinstance(value, (tuple, list)):
        return all(_plain_value(v) for v in value)
    if isinstance(value, dict):
        return all(_plain_value(v) for v in value.values())
    return False


def _members(cls: type) -> tuple:
    """The attributes ``cls`` and its bases define (torch's and the builtins' aside), as
    objects: a memo of :func:`_class_code` holds for a class whose members are these very
    ones (a method replaced on the class, in a notebook or by a monkeypatch, had kept the
    old digest for the process: a cache trial)."""
    return tuple(attr for klass in cls.__mro__
                 if klass.__module__.split(".")[0] not in _SKIPPED_MODULES
                 for _, attr in sorted(vars(klass).items()))  # fmt: skip


_SKIPPED_MODULES = ("builtins", "torch", "typing", "abc")

#: :func:`_class_code` by class, with the members it was computed from (a class edited and
#: re-created is another object). Weak on both: a class made per call (a factory, a
#: notebook cell run again) had been kept for the process with its data, its methods'
#: ``__class__`` cells pointing back at it from the members (a memory trial: 20 classes of
#: 8 MB each, all alive after ``gc.collect()``).
_CLASS_CODE: weakref.WeakKeyDictionary[type, tuple[tuple, list | bytes]] = (
    weakref.WeakKeyDictionary()
)


def _hold_weakly(member):
    """A token of ``member`` that does not hold its class alive: a weak reference where it
    takes one (functions, tensors, classes); a static/class method or property by a weak
    reference to the function it wraps; a slot or ``__dict__``/``__weakref__`` descriptor
    (which points at its class; a plain class's own: a review) by its type and name; the
    member itself else (numbers, strings, groups of them)."""
    if isinstance(member, (staticmethod, classmethod)):
        return _Wrapped(type(member), _weakly(member.__func__))
    if isinstance(member, property):
        return _Wrapped(property, None if member.fget is None else _weakly(member.fget))
    if isinstance(member, (types.GetSetDescriptorType, types.MemberDescriptorType)):
        return _Descriptor(type(member), member.__name__)
    return _weakly(member)


def _weakly(obj):
    """A weak reference to ``obj``, or ``obj`` itself where it takes none (a number, an
    ``operator.itemgetter``, ``dict.get``: a property of one had failed in weakref, a
    review)."""
    try:
        return weakref.ref(obj)
    except TypeError:
        return obj


def _deref(token):
    """What :func:`_weakly` kept (``_GONE`` once a weakly held object is gone)."""
    if type(token) is not weakref.ref:
        return token
    held = token()
    return _GONE if held is None else held


#: What a dead weak reference reads as: no member is it (``None`` had been, a review).
_GONE = object()


class _Wrapped(NamedTuple):
    kind: type
    function: weakref.ref | None


class _Descriptor(NamedTuple):
    kind: type
    name: str


def _still(token, member) -> bool:
    """Whether ``member`` is the one :func:`_hold_weakly` made ``token`` of (a member gone
    is none: a dead reference had read as ``None``, and a member set to ``None`` kept the
    old digest, a review)."""
    kind = type(token)
    if kind is _Wrapped:
        if type(member) is not token.kind:
            return False
        inner = member.fget if token.kind is property else member.__func__
        if token.function is None:
            return inner is None
        return _deref(token.function) is inner
    if kind is _Descriptor:
        return type(member) is token.kind and member.__name__ == token.name
    return _deref(token) is member


def _global_names(code) -> set[str]:
    """The global (and attribute) names a code object and its nested functions read."""
    names = set(code.co_names)
    for const in code.co_consts:
        if hasattr(const, "co_code"):
            names |= _global_names(const)
    return names


def _feed_global(digest, value: Any, seen: dict[int, tuple[int, Any]], depth: int) -> None:
    """A module-level value a function reads: a module or a class by its name (an edit
    inside an imported module of one's own, read as ``params.G``, is not seen: delete the
    cache folder, or pass the value as an argument), anything else as :func:`_feed` does."""
    if isinstance(value, (types.ModuleType, type)):
        digest.update(f"{getattr(value, '__name__', '')}".encode())
        return
    _feed(digest, value, seen, depth)


def _feed_code(digest, code) -> None:
    """A code object by its bytecode and constants, nested functions' code included (their
    ``repr`` holds a memory address, which would change the hash in every process)."""
    digest.update(code.co_code)
    # the names it reads (torch.sin and torch.cos are the same bytecode, another name)
    digest.update(repr(code.co_names).encode())
    for const in code.co_consts:
        if hasattr(const, "co_code"):
            _feed_code(digest, const)
        else:
            digest.update(repr(const).encode())


def model_fingerprint(model) -> str:
    """A hash of everything that determines ``model``'s numbers (module docstring)."""
    digest = hashlib.sha256()
    _feed(digest, model, {})
    return digest.hexdigest()


def library_fingerprint() -> str:
    """A hash of the library's own code: every ``.py`` file of ``difffilter``,
    ``difffilter.models`` (the filters, detectors and scenarios a calibration runs),
    ``difffilter.eval`` (the suite, scoring and calibration a sweep's cached baselines
    come from) and ``difffilter.train`` (the sweep that computes those baselines), by
    package, path and content, with the versions of torch and numpy that compute the
    numbers, read once per process. In a calibration's
    file name, so a threshold computed by an older version (a ``git pull``, an upgrade, a
    local fix) is not reused: a trial edited ``cusum_detector_for`` and read the old τ,
    10.74 against 12.42; in a development checkout ``eval/`` lies outside ``difffilter/``,
    and a fix of a metric had left the sweep's baselines of before in use (a trial)."""
    global _LIBRARY_FINGERPRINT
    if _LIBRARY_FINGERPRINT is None:
        import difffilter
        import difffilter.eval
        import difffilter.models
        import difffilter.train

        digest = hashlib.sha256()
        # another torch or numpy can round otherwise (an upgrade calibrates again)
        digest.update(f"torch {torch.__version__} numpy {np.__version__}".encode())
        for package in (difffilter, difffilter.models, difffilter.eval, difffilter.train):
            digest.update(package.__name__.encode())
            for root in package.__path__:
                for path in sorted(Path(root).rglob("*.py")):
                    digest.update(path.relative_to(root).as_posix().encode())
                    digest.update(path.read_bytes())
        _LIBRARY_FINGERPRINT = digest.hexdigest()
    return _LIBRARY_FINGERPRINT


_LIBRARY_FINGERPRINT: str | None = None


def cached(kind: str, key: tuple, model, compute, valid=None):
    """``compute()`` (a JSON-able mapping) for ``key`` and ``model``, read from the cache
    folder when an earlier process of the same library code computed it, else computed and
    written there. ``valid(value) -> bool`` vets a value read from disk: a file that fails
    it (edited by hand, or by another tool) is computed again and replaced, as is one that
    is half-written or not JSON."""
    folder = cache_folder()
    if folder is None:
        return compute()
    name = hashlib.sha256(
        repr((FORMAT, kind, key, model_fingerprint(model), library_fingerprint())).encode()
    )
    path = folder / "calibrations" / f"{kind}-{name.hexdigest()[:32]}.json"
    try:
        value = json.loads(path.read_text(encoding="utf-8"))["value"]
        if valid is None or valid(value):
            return value
    except (OSError, ValueError, KeyError, TypeError):
        pass  # absent, unreadable, half-written or not a mapping: compute it again
    value = compute()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        text = json.dumps({"kind": kind, "key": repr(key), "value": value})
        # atomic: a reader never sees half a file
        write_atomically(path, text)
    except OSError:
        pass  # a read-only home: the calibration still holds for this process
    return value
