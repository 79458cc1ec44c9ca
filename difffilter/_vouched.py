"""The carries an online step has validated: what lets :meth:`Estimator.step` stay lean.

:meth:`~difffilter.Estimator.step` validates a carry it has not seen (its tensors finite,
of the model's shapes; a covariance symmetric) and the measurement, input and mask against
the model (dtype, device, shape, finiteness). What that established holds for the carry
the step returns as well, so the step *vouches* for it here: the next step, given that
carry unchanged, re-checks only what is new (``y``, ``u`` and ``mask`` against the shapes,
dtype and device already established, and their finiteness) and goes straight to the
unchecked ``_step``. :meth:`~difffilter.Estimator.init` validates the carry it makes and
vouches for it under the model's dtype and device, so even the first step checks only its
inputs. An online estimator deployed on one plant then pays a handful of Python
comparisons per step instead of the whole validation (about 6 µs: what a carry of given
field types is made of is cached, :class:`_Layout`, so no field is asked ``isinstance`` of
torch's tensor metaclass at every step).

"Unchanged" is exact: the carry's leaves (its fields, through nested tuples, lists and
dicts) must be the very objects vouched for (by identity), and its tensors, and those of
its model whose values the full validation reads (its noise models', whose means the
Gaussian filters read: :meth:`~difffilter.Estimator._watched`), must not have been modified in place since
(their autograd version counters). ``carry._replace(mean=…)``,
a carry built by hand, a tensor written in place, or a carry of another estimator object:
each is validated in full again, with the same errors as before. One exception: the
inference tensors of ``torch.inference_mode()`` keep no version counter, so there identity
alone is checked, and a carry written in place is not validated again (the speed inference
mode is chosen for; ``full_checks = True`` validates every step).

The registry holds weak references to the tensors (a vouched carry keeps no particle
cloud and no autograd graph alive) and to every other leaf that takes one (models, gain
schedules, generators: a deployment trial's process that rebuilt 40 MB models kept the
last 64 alive, 1.2 GB, through this registry), and plain references to the rest (step
indices, ``None``, tuples); it keeps the last :data:`_LIMIT` carries, so an estimator
stepping more independent carries than that in turn just validates them in full.
"""

from __future__ import annotations

import functools
import itertools
import math
import operator
import weakref
from math import isfinite

import torch
from torch import Tensor

from ._assignments import assignments

__all__ = ["Established", "hold_whole", "vouch", "vouched"]

#: How many vouched carries the registry keeps (the oldest go first).
_LIMIT = 64

#: ``id(carry) → (Established, leaf ids, tensor weak references, tensor versions, other
#: leaves)``. Keyed by ``id``: tuples cannot be referenced weakly. An ``id`` reused by
#: another tuple is harmless: its leaves are compared by identity before any trust.
_VOUCHED: dict[int, tuple] = {}


class Established:
    """What a full validation of one step established, for the steps that follow.

    ``owner``: a weak reference to the estimator object that validated; ``dtype``,
    ``device``: of the measurements (the model's); ``y_shape`` ``[*batch, dy]`` and
    ``u_shape`` ``[*batch, du]`` (``None``: no input allowed) the exact shapes a lean step
    accepts; ``known``: whether tensors hold values (``False`` on the meta device, where
    finiteness is not checked).
    """

    __slots__ = ("owner", "dtype", "device", "y_shape", "u_shape", "known", "_host_sum",
                 "assigned", "model_refs", "model_versions")  # fmt: skip

    def __init__(self, owner, dtype: torch.dtype, device, batch, dim_y: int, dim_u: int,
                 watched=()):  # fmt: skip
        self.owner = weakref.ref(owner)
        # models' tensor assignments so far: after one (``model.to(torch.float32)``, ``model.F
        # = …``) a step validates in full again (its carry may no longer fit its model)
        self.assigned = assignments()
        # and the versions of the model's tensors whose values the full checks read
        # (``watched``: the noise models', whose means the Gaussian filters read; a mean
        # written in place, ``noise.loc.add_(5)``, is refused there, and the lean step had
        # dropped it without a word: an online-step trial). Inference tensors keep no
        # version and cannot be written in place outside inference mode: left out (within
        # it, identity alone is checked, as for the carry)
        tensors = [t for t in watched if not t.is_inference()]
        self.model_refs = tuple(map(weakref.ref, tensors))
        self.model_versions = tuple(map(_VERSIONS, tensors))
        self.dtype, self.device = dtype, torch.device(device)
        self.y_shape = tuple(batch) + (dim_y,)
        self.u_shape = tuple(batch) + (dim_u,) if dim_u > 0 else None
        self.known = self.device.type != "meta"
        # one run's small y and u on the CPU: summed on the host, no question asked of them
        self._host_sum = (self.device.type == "cpu" and len(self.y_shape) == 1
                          and max(dim_y, dim_u) <= _HOST_SUM)  # fmt: skip

    def admits(self, y, u, mask) -> tuple[Tensor, Tensor | None, Tensor | None] | None:
        """``(y, u, mask)`` ready for the unchecked step (``y`` zeroed where unreceived) when
        they have exactly the established shapes, dtype and device and every received
        entry is finite; ``None`` when anything differs (the caller validates in full and
        raises the error that names the argument)."""
        if not isinstance(y, Tensor) or y.shape != self.y_shape:
            return None
        if y.dtype != self.dtype or y.device != self.device:
            return None
        if u is not None:
            if not isinstance(u, Tensor) or u.shape != self.u_shape:
                return None
            if u.dtype != self.dtype or u.device != self.device:
                return None
        if mask is not None:
            if (
                not isinstance(mask, Tensor)
                or mask.dtype is not torch.bool
                or mask.shape != y.shape
                or mask.device != self.device  # (torch's bare device error otherwise)
            ):
                return None
            # unreceived entries are never read, but 0·NaN would still be NaN in an update
            y = y.where(mask, 0.0)
        try:
            if self._host_sum:  # [dy] and [du]: their lists summed (one read each)
                if not (isfinite(sum(y.tolist())) and (u is None or isfinite(sum(u.tolist())))):
                    return None
            elif self.known and not (_finite(y) and (u is None or _finite(u))):
                return None
        except RuntimeError:
            # values that cannot be read (torch.func.vmap's batched y: "Cannot access data
            # pointer of Tensor that doesn't have storage", a trial): the full checks name it
            return None
        return y, u, mask


def _finite(t: Tensor) -> bool:
    """Whether every entry of ``t`` is finite: a finite sum proves it. A non-finite sum (a
    bad entry, or an overflow of large finite entries) says "not proven": the caller then
    validates in full, which tells the two apart. A small CPU tensor (one run's
    measurement) is summed on the host: one read instead of a reduction and a read."""
    if t.numel() <= _HOST_SUM and t.device.type == "cpu":
        return math.isfinite(sum(t.tolist() if t.dim() == 1 else t.reshape(-1).tolist()))
    return math.isfinite(t.detach().sum().item())


#: Entries up to which :func:`_finite` sums on the host.
_HOST_SUM = 64
_CONTAINERS = (tuple, list, dict)
#: Tuple types a carry holds whole, compared by identity like any other non-tensor leaf
#: (immutable tuples without tensors, e.g. the estimators' ``Generators``): flattening
#: them would only cost time (:func:`hold_whole`).
_WHOLE: frozenset = frozenset()


def hold_whole(cls: type) -> type:
    """Treat instances of the tuple type ``cls`` as one leaf of a carry (module docstring)."""
    global _WHOLE
    _WHOLE = _WHOLE | {cls}
    _LAYOUTS.clear()  # a cached layout may have flattened it
    return cls


class _Layout:
    """What a carry of given field types is made of: whether it is *flat* (no field a
    container to flatten) and, if so, getters of its tensor fields and of the others. Keyed
    by the fields' types (``tuple(map(type, carry))``: one C call), so a step asks no
    ``isinstance`` of each field (each is a Python-level check against torch's tensor
    metaclass, ~0.3 µs)."""

    __slots__ = ("flat", "tensors", "others")

    def __init__(self, types: tuple[type, ...]):
        self.flat = not any(map(_is_container, types))
        self.tensors = _getter([i for i, t in enumerate(types) if issubclass(t, Tensor)])
        self.others = _getter([i for i, t in enumerate(types) if not issubclass(t, Tensor)])


def _getter(indices: list[int]):
    """``carry → tuple`` of the fields at ``indices`` (C-level ``itemgetter``, which gives
    the field itself, not a 1-tuple, for one index)."""
    if not indices:
        return lambda carry: ()
    if len(indices) == 1:
        get = operator.itemgetter(indices[0])
        return lambda carry: (get(carry),)
    return operator.itemgetter(*indices)


#: ``_Layout`` by the carry's field types (a few per carry type: optional fields ``None``).
_LAYOUTS: dict[tuple[type, ...], _Layout] = {}


def _layout(carry) -> _Layout:
    types = tuple(map(type, carry))
    layout = _LAYOUTS.get(types)
    if layout is None:
        layout = _LAYOUTS[types] = _Layout(types)
    return layout


_VERSIONS = operator.attrgetter("_version")


def _is_container(cls: type) -> bool:
    """Whether a leaf of type ``cls`` is flattened: a tuple, list or dict that is neither a
    tensor nor held whole (:func:`hold_whole`)."""
    return issubclass(cls, _CONTAINERS) and not issubclass(cls, Tensor) and cls not in _WHOLE


def _leaves(obj, out: list) -> list:
    for v in obj.values() if isinstance(obj, dict) else obj:
        if _is_container(type(v)):
            _leaves(v, out)
        else:
            out.append(v)
    return out


def _flat_leaves(carry) -> tuple:
    """The carry's leaves: the carry itself when none of its fields is a container (the
    filters' carries), else its fields flattened through tuples, lists and dicts."""
    if any(map(_is_container, map(type, carry))):
        return tuple(_leaves(carry, []))
    return carry


def _versions(tensors) -> tuple:
    if torch.is_inference_mode_enabled():  # its tensors keep no version counter: identity
        return tuple(-1 if t.is_inference() else t._version for t in tensors)
    try:
        return tuple(map(_VERSIONS, tensors))
    except RuntimeError:  # an inference tensor made earlier (raising costs ~30 µs)
        return tuple(-1 if t.is_inference() else t._version for t in tensors)


def vouch(carry, established: Established) -> None:
    """Record that ``carry`` (a step's output, or a carry just validated in full) is valid
    under ``established``."""
    # the filters' carries (tuples without containers): getters made once per layout
    layout = _layout(carry) if isinstance(carry, tuple) else None
    flat = layout is not None and layout.flat
    if flat:
        leaves, tensors, others = carry, layout.tensors(carry), layout.others(carry)
    else:
        leaves = _flat_leaves(carry)
        tensors = [v for v in leaves if isinstance(v, Tensor)]
        others = [v for v in leaves if not isinstance(v, Tensor)]
    weak, held = _split(others)
    entry = (
        established,
        tuple(map(id, leaves)),
        # the model's watched tensors beside the carry's (unchanged since the full check:
        # a lean step runs only then), compared with them in one pass by vouched()
        tuple(map(weakref.ref, tensors)) + established.model_refs,
        _versions(tensors) + established.model_versions,
        held,  # held: their ids stay theirs
        flat,
        tuple(map(weakref.ref, weak)),  # alive, or the entry is void: their ids may be reused
    )
    key = id(carry)
    _VOUCHED.pop(key, None)  # re-inserted at the end: the oldest entries go first
    _VOUCHED[key] = entry
    if len(_VOUCHED) > _LIMIT:
        try:
            del _VOUCHED[next(iter(_VOUCHED))]
        except (KeyError, RuntimeError, StopIteration):  # another thread got there first
            pass


def vouched(owner, carry) -> Established | None:
    """The :class:`Established` of ``carry`` when ``owner`` vouched for it and it is
    unchanged since (same leaves by identity, tensors not written in place); else ``None``."""
    entry = _VOUCHED.get(id(carry))
    if entry is None:
        return None
    established, ids, refs, versions, _, flat, weak = entry
    if established.assigned != assignments():  # a model was assigned to since: check in full
        return None
    # a flat entry's fields, if the same objects, are as flat as they were
    leaves = carry if flat else _flat_leaves(carry)
    if established.owner() is not owner or tuple(map(id, leaves)) != ids:
        return None
    # equal ids name the vouched tensors only while those are alive (the others are held)
    tensors = tuple(map(_DEREF, refs))
    if any(map(operator.is_, tensors, _NONES)):  # one was freed: its id may be another's
        return None
    if weak and any(map(operator.is_, map(_DEREF, weak), _NONES)):
        return None
    return established if _versions(tensors) == versions else None


_DEREF = weakref.ReferenceType.__call__


def _split(others) -> tuple[list, list]:
    """``(weakly, strongly)``: the leaves whose type takes a weak reference, and the rest."""
    weak, held = [], []
    for v in others:
        (weak if _weakly(type(v)) else held).append(v)
    return weak, held


@functools.cache
def _weakly(cls: type) -> bool:
    """Whether instances of ``cls`` take weak references (asked once per type)."""
    return bool(getattr(cls, "__weakrefoffset__", 0))


_NONES = itertools.repeat(None)
