"""A distribution over threats: what a learned estimator is trained across.

Plain data (a YAML mapping) names the threats of the library (:data:`~difffilter.threats.
THREATS`), each with a weight, and lets any field be drawn at random::

    own:    {weight: 0.3}                                  # the scenario's own attack
    none:   {weight: 0.1}                                  # an attack-free run
    bias:   {weight: 0.2, kind: bias, value: {uniform: [0.05, 1.5], signed: true},
             entries: {choice: [[0], [1], [2, 3], null]}, onset: {randint: [5, 60]}}
    ramp:   {weight: 0.2, kind: ramp, slope: {uniform: [0.002, 0.02]}, onset: 21}

A field is a constant, or one of

- ``{uniform: [lo, hi]}``: ``U(lo, hi)``, times a random sign with ``signed: true``;
- ``{loguniform: [lo, hi]}``: ``exp U(log lo, log hi)`` (``0 < lo ≤ hi``), ``signed`` too;
- ``{randint: [lo, hi]}``: an integer of ``lo … hi`` (both included);
- ``{choice: [v₀, v₁, …]}``: one of the values, equally likely.

:meth:`ThreatDistribution.sample` draws a threat name by weight, then its fields, from a
``torch.Generator``: the same generator state gives the same threat. ``own`` and ``none``
are reserved names (the scenario's attack, which the caller supplies, and no attack).

:meth:`ThreatDistribution.covers` says how a threat written as plain data stands to the
distribution: ``"within"`` (it could be drawn), ``"kind only"`` (its kind is drawn, with
other fields) or ``"held out"`` (its kind never is): what a robustness study reports for a
network trained across threats.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import MISSING, dataclass, fields
from typing import Any

import torch

from .attack import Attack, Channel
from .threats import THREATS, check_attack_fits, threat_from_dict

__all__ = ["ThreatDistribution", "WITHIN", "KIND_ONLY", "HELD_OUT", "threat_spec"]

#: How a threat stands to a distribution (:meth:`ThreatDistribution.covers`).
WITHIN, KIND_ONLY, HELD_OUT = "within", "kind only", "held out"

_DRAWS = ("uniform", "loguniform", "randint", "choice")
_RESERVED = ("own", "none")


def _is_draw(value) -> bool:
    return isinstance(value, dict) and any(k in value for k in _DRAWS)


def _near(mapping: dict, names) -> str:
    """`` (did you mean 'weight' for 'wieght'?)`` for a key of ``mapping`` close to one of
    ``names`` that it lacks, else ``""``."""
    import difflib

    for key in mapping:
        if isinstance(key, str) and key not in names:
            close = difflib.get_close_matches(key, names, n=1, cutoff=0.6)
            if close:
                return f" (did you mean {close[0]!r} for {key!r}?)"
    return ""


def _never_above_zero(value) -> bool:
    """Whether a field (a number or a draw) is 0 in every draw: a constant 0, a choice of
    zeros, or a uniform, loguniform or randint range [0, 0]."""
    if not _is_draw(value):
        return isinstance(value, (int, float)) and not isinstance(value, bool) and value == 0
    options = (value.get("choice") or value.get("uniform") or value.get("loguniform")
               or value.get("randint") or ())  # fmt: skip
    numbers = [o for o in options if isinstance(o, (int, float)) and not isinstance(o, bool)]
    return bool(numbers) and len(numbers) == len(options) and all(o == 0 for o in numbers)


#: The integers ``randint`` may give: torch draws them as int64, ``hi + 1`` included (out of
#: range, torch's "Overflow when unpacking long long" had named neither entry nor field).
_RANDINT_RANGE = (-(2**63), 2**63 - 2)


def _check_draw(where: str, value: dict) -> None:
    kinds = [k for k in _DRAWS if k in value]
    extra = sorted(set(value) - set(_DRAWS) - {"signed"})
    if len(kinds) != 1 or extra:
        raise ValueError(
            f"{where}: a random field is one of {{uniform|loguniform|randint|choice: ...}} "
            f"(uniform and loguniform may add signed: true); got {value!r}"
        )
    kind, args = kinds[0], value[kinds[0]]
    # before choice's return: {choice: [0.5, 1], signed: true} had been taken and drawn
    # unsigned (a threats trial: no negative value in 2,000 draws)
    if "signed" in value and kind not in ("uniform", "loguniform"):
        raise ValueError(f"{where}: signed applies to uniform and loguniform only; got {value!r}")
    if kind == "choice":
        if not isinstance(args, list) or not args:
            raise ValueError(f"{where}: choice needs a non-empty list of values; got {args!r}")
        return
    if not (isinstance(args, list) and len(args) == 2
            and all(isinstance(a, (int, float)) and not isinstance(a, bool) for a in args)):  # fmt: skip
        raise ValueError(f"{where}: {kind} needs [lo, hi], two numbers; got {args!r}")
    lo, hi = args
    if lo > hi or (kind == "loguniform" and lo <= 0) or (kind == "randint" and
                                                           not all(isinstance(a, int) for a in args)):  # fmt: skip
        raise ValueError(
            f"{where}: {kind} needs lo <= hi"
            + (" and lo > 0" if kind == "loguniform" else "")
            + (" as integers" if kind == "randint" else "")
            + f"; got {args!r}"
        )
    if kind == "randint" and not _RANDINT_RANGE[0] <= lo <= hi <= _RANDINT_RANGE[1]:
        raise ValueError(
            f"{where}: randint needs lo and hi within [{_RANDINT_RANGE[0]}, "
            f"{_RANDINT_RANGE[1]}] (torch draws int64); got {args!r}"
        )
    if not isinstance(value.get("signed", False), bool):  # ("no" was read as true)
        raise ValueError(f"{where}: signed must be true or false; got {value['signed']!r}")


def _is_threat(value) -> bool:
    """Whether a field is a threat of its own (a mapping with a ``kind``: a covert attack's
    ``signal``), whose fields may be drawn as well."""
    return isinstance(value, dict) and "kind" in value and not _is_draw(value)


def _share_never_above_zero(entry: dict) -> str:
    """The path of ``entry``'s share that is 0 in every draw (``"share"``; a covert attack's
    ``"signal.share"``, with a signal drawn by ``choice``: every option's), else ``""``.
    (A covert signal's ``share: 0`` had passed: its runs trained attack-free, counted as
    trained on.)"""
    if _never_above_zero(entry.get("share")):
        return "share"
    signal = entry.get("signal")
    options = signal["choice"] if _is_draw(signal) and "choice" in signal else [signal]
    if options and all(_is_threat(o) and _never_above_zero(o.get("share")) for o in options):
        return "signal.share"
    return ""


def _check_fields(where: str, entry: dict) -> None:
    """Each random field of ``entry`` is a well-formed draw (:func:`_check_draw`), the
    fields of a nested threat (a covert attack's ``signal``) too, and no other mapping
    stands where a field goes (a misspelt draw read "must be a number")."""
    for field, value in entry.items():
        if _is_draw(value):
            _check_draw(f"{where}.{field}", value)
            for i, option in enumerate(value.get("choice", ())):  # a choice of signals
                if _is_threat(option):
                    _check_fields(f"{where}.{field}.choice[{i}]", option)
        elif _is_threat(value):
            _check_fields(f"{where}.{field}", value)
        elif isinstance(value, dict):
            raise ValueError(
                f"{where}.{field}: a mapping is a random draw, one of {{uniform|"
                f"loguniform|randint|choice: ...}}{_near(value, _DRAWS)}; got {value!r}"
            )


def _extremes(value) -> list:
    """The values of a random field that bound what it can draw (every ``choice``; ``lo``
    and ``hi`` of a range, negated too with ``signed``), so that construction checks a
    threat with each of them, not only with one draw (a constant has none). A ``uniform``'s
    or ``loguniform``'s as floats, as it draws them: an integer field drawn so is refused
    in every option of a choice of signals (written ``[20, 40]``, the ints had passed, and
    the option the one seed-0 check did not draw failed mid-training)."""
    if not _is_draw(value):
        return []
    if "choice" in value:  # a choice of signals: each one at its own fields' extremes
        return [c for o in value["choice"] for c in (_corners(o) if _is_threat(o) else [o])]
    if "randint" in value:
        bounds = list(value["randint"])
    else:
        bounds = [float(b) for b in value.get("uniform") or value["loguniform"]]
    return bounds + [-b for b in bounds] if value.get("signed") else bounds


#: Above this many combinations of extremes, construction checks each field's extremes
#: alone (the others at one draw) instead of every combination.
_MAX_CORNERS = 4096


def _corners(entry: dict) -> list[dict]:
    """``entry`` at every combination of its random fields' extremes (:func:`_extremes`;
    a nested threat's, a covert signal's, as fields of their own): two fields that
    constrain each other (a replay's ``onset > delay``, pulses' ``width ≤ period``) are
    checked together, where one at a time let 5 % of the draws fail mid-training."""
    random = {(k,): _extremes(v) for k, v in entry.items() if _extremes(v)}
    for k, v in entry.items():
        if _is_threat(v):
            random.update({(k, f): _extremes(x) for f, x in v.items() if _extremes(x)})
    if math.prod(len(v) for v in random.values()) > _MAX_CORNERS:
        corners = [{path: x} for path, values in random.items() for x in values]
    else:
        corners = [dict(zip(random, combo)) for combo in itertools.product(*random.values())]
    return [_with_values(entry, corner) for corner in corners]


def _with_values(entry: dict, values: dict) -> dict:
    """``entry`` with the fields at the paths of ``values`` (``(field,)`` or ``(field,
    nested field)``) replaced."""
    out = dict(entry)
    for path, x in values.items():
        if len(path) == 1:
            out[path[0]] = x
        else:
            out[path[0]] = {**out[path[0]], path[1]: x}
    return out


def _draw(value, generator: torch.Generator):
    """One value of a field (a constant is itself; a nested threat, its fields drawn in
    their order; a choice of nested threats, the one chosen with its fields drawn)."""
    if _is_threat(value):
        return {k: _draw(v, generator) for k, v in value.items()}
    if not _is_draw(value):
        return value
    u = lambda: float(torch.rand((), generator=generator, dtype=torch.float64))  # noqa: E731
    if "choice" in value:
        options = value["choice"]
        chosen = options[int(torch.randint(len(options), (), generator=generator))]
        # (a chosen signal's own draws had been passed on as they were, and refused as
        # "onset must be an integer >= 1; got {'randint': ...}")
        return _draw(chosen, generator) if _is_threat(chosen) else chosen
    if "randint" in value:
        lo, hi = value["randint"]
        return int(torch.randint(lo, hi + 1, (), generator=generator))
    lo, hi = value.get("uniform") or value["loguniform"]
    if "uniform" in value:
        x = lo + (hi - lo) * u()
    else:
        x = math.exp(math.log(lo) + (math.log(hi) - math.log(lo)) * u())
    if value.get("signed"):
        x = x if u() < 0.5 else -x
    return x


@dataclass(frozen=True)
class ThreatDistribution:
    """Threats drawn by weight, their fields at random (module docstring).

    Args:
        spec: ``{name: {weight, kind, fields...}}`` (``own``, ``none``: reserved names with
            a weight only).
        model: the defender's model, for the threats that read it (``ksigma_bias``,
            ``covert``: :func:`~difffilter.threats.threat_from_dict`).
        own: what ``sample`` returns for ``own`` (the scenario's attack or a marker).
    """

    spec: dict
    model: Any = None
    own: Any = None

    def __post_init__(self):
        if not isinstance(self.spec, dict) or not self.spec:
            raise ValueError(
                f"threats must be a non-empty mapping of name: threat; got {self.spec!r}"
            )
        for name, entry in self.spec.items():
            where = f"threats.{name}"
            if not isinstance(entry, dict) or "weight" not in entry:
                near = _near(entry, ("weight",)) if isinstance(entry, dict) else ""
                raise ValueError(f"{where}: needs a mapping with a weight{near}; got {entry!r}")
            w = entry["weight"]
            if isinstance(w, bool) or not isinstance(w, (int, float)) or not 0 <= w < math.inf:
                raise ValueError(f"{where}.weight must be a finite number >= 0; got {w!r}")
            if name in _RESERVED:
                if set(entry) != {"weight"}:
                    raise ValueError(f"{where}: the reserved name {name!r} takes a weight only")
                continue
            kind = entry.get("kind")
            if not isinstance(kind, str) or kind not in THREATS:  # (a list: "unhashable")
                raise ValueError(
                    f"{where}.kind must be one of {', '.join(sorted(THREATS))} (or the name own "
                    f"or none); got {kind!r}"
                )
            _check_fields(where, entry)
            silent = _share_never_above_zero(entry)
            if float(entry["weight"]) > 0 and silent:
                raise ValueError(  # (a trial's entry attacked no run and counted as trained on)
                    f"{where}.{silent} is 0: the threat attacks no run, so it never acts; give "
                    "it a share above 0, or weight 0"
                )
            self._build(name, entry, torch.Generator().manual_seed(0), check=True)  # fields now
            for corner in _corners(entry):  # ... and the random ones at their extremes, together
                self._build(name, corner, torch.Generator().manual_seed(0), check=True)
        if sum(float(e["weight"]) for e in self.spec.values()) <= 0:
            raise ValueError("threats: the weights must not all be 0")

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self.spec)

    def _build(
        self, name: str, entry: dict, generator: torch.Generator, check: bool = False
    ) -> Attack:
        """The threat ``name`` with its fields drawn; ``check``: and, with :attr:`model`, that
        it fits the model (:func:`~difffilter.threats.check_attack_fits`: its width and
        entries against the channel's, inputs for an actuator attack)."""
        fields = {k: _draw(v, generator) for k, v in entry.items() if k != "weight"}
        try:
            attack = threat_from_dict(fields, model=self.model)
            if check and self.model is not None:
                check_attack_fits(attack, self.model)
            return attack
        except (TypeError, ValueError) as error:
            hint, drawn = "", entry.get(str(error).split(" ", 1)[0])
            if (
                "must be an integer" in str(error)
                and _is_draw(drawn)
                and ("uniform" in drawn or "loguniform" in drawn)
            ):  # the field named, drawn so
                hint = " (an integer field is drawn with randint: [first, last], both included)"
            raise ValueError(f"threats.{name}: {error}{hint}") from None

    def covers(self, spec: dict) -> str:
        """How threat ``spec`` (``{"kind", **fields}``, as the threat sets write it) stands
        to this distribution: :data:`WITHIN` where a component of positive weight has its
        kind and could draw every one of its fields, :data:`KIND_ONLY` where components
        draw its kind but not those fields, :data:`HELD_OUT` where none draws its kind.

        A field drawable by a component: a constant equal to it (numbers to 1e-9), a
        ``uniform``/``loguniform`` interval holding it (its magnitude with ``signed``; a
        vector only with every entry equal, as a drawn number is the same on every
        entry), a ``randint`` range holding the integer, a ``choice`` listing it. A field
        that one side leaves out is the threat class's default on that side (``ksigma_bias``'s
        ``sigma``: the model's; a sinusoid's or chirp's ``dt``: give both sides the
        scenario's first, :func:`~difffilter.threats.with_sampling_period`, as
        :func:`~difffilter.eval.coverage.training_coverage` does). A number equals the vector
        of it on every entry. A channel drawn by ``choice``: each option in turn. The reserved
        ``own`` counts as :attr:`own` where that is a threat of the library
        (:func:`threat_spec`)."""
        kind = spec.get("kind")
        same_kind = [entry for name, entry in self.spec.items()
                     if name not in _RESERVED and entry.get("kind") == kind
                     and float(entry["weight"]) > 0]  # fmt: skip
        own = threat_spec(self.own)  # ``own``: the scenario's attack, where the library's
        if own is not None and own["kind"] == kind and float(self.spec.get("own", {}).get(
                "weight", 0)) > 0:  # fmt: skip
            same_kind.append(own)
        if not same_kind:
            return HELD_OUT
        return WITHIN if any(self._could_draw(entry, spec) for entry in same_kind) else KIND_ONLY

    def _could_draw(self, entry: dict, spec: dict) -> bool:
        """Whether component ``entry`` could draw threat ``spec`` (:meth:`covers`): the same
        kind and every field drawable, a field left out on one side being the class's
        default; a covert attack's ``signal`` field by field in turn (it had been compared
        as one mapping: a distribution of random signals covered none, nor ``value: [0.1]``
        its ``0.1``, and a network trained across covert attacks was reported as never
        having met one)."""
        kind = spec.get("kind")
        if entry.get("kind") != kind:
            return False
        channel = entry.get("channel")
        if _is_draw(channel) and "choice" in channel:  # each channel it draws, with its width
            # (read as one Channel, the mapping had failed: a robustness study died at its end)
            return any(self._could_draw({**entry, "channel": option}, spec)
                       for option in channel["choice"])  # fmt: skip
        # one channel spelt any way it is accepted ("SENSOR", "Sensor", left out: the same
        # attack; compared as written, "SENSOR" had read "kind only" for a sensor threat
        # the distribution draws: a red-team trial)
        spec, entry = _channel_named(spec), _channel_named(entry)
        library = isinstance(kind, str) and kind in THREATS  # (else an attack of one's own,
        if library:  # whose defaults are unknown here: a field on one side only differs)
            spec, entry = (_entries_sorted(self._entries_listed(x)) for x in (spec, entry))
        for f in (set(spec) | set(entry)) - {"kind", "weight"}:
            default = _default(kind, f) if library else _NO_DEFAULT
            drawn, value = entry.get(f, default), spec.get(f, default)
            if kind == "covert" and f == "signal":
                if not self._signal_drawable(drawn, value):
                    return False
            elif not _drawable(drawn, value):
                return False
        return True

    def _signal_drawable(self, drawn, signal) -> bool:
        """Whether a covert component's ``signal`` (a threat mapping, or a ``choice`` of
        them) can give the covert threat's ``signal``; both on the actuators, where a
        covert signal always acts (``channel: actuator`` spelt out or not)."""
        if not _is_threat(signal):
            return _drawable(drawn, signal)
        options = drawn["choice"] if _is_draw(drawn) and "choice" in drawn else [drawn]
        on_actuators = {**signal, "channel": Channel.ACTUATOR.value}
        return any(self._could_draw({**o, "channel": Channel.ACTUATOR.value}, on_actuators)
                   for o in options if _is_threat(o))  # fmt: skip

    def _entries_listed(self, spec: dict) -> dict:
        """``spec`` with ``entries: null`` (every entry of the channel) written as the list
        of them, where :attr:`model` gives the channel's width: ``[0, 1, 2, 3]`` and
        ``null`` are the same attack on the four-tank's sensors (a trial read them as
        another); a ``ksigma_bias`` without ``sigma`` given the model's ``√diag R``, as it
        is built. Unchanged without a model."""
        if self.model is None or spec.get("kind") in (None, "covert"):
            return spec
        if spec["kind"] == "ksigma_bias" and "sigma" not in spec:
            # σ = √diag R of the model, as training and the study fill it (compared with the
            # class's default instead, the model's own σ had read "kind only", σ = 1 "within")
            sigma = self.model.measurement_cov(1).diagonal(dim1=-2, dim2=-1).sqrt()
            spec = {**spec, "sigma": [float(s) for s in sigma.detach().reshape(-1)]}
        actuator = Channel(spec.get("channel", Channel.SENSOR)) is Channel.ACTUATOR
        width = self.model.dim_u if actuator else self.model.dim_y
        every = list(range(width))
        value = spec.get("entries", _default(spec["kind"], "entries"))
        if value is _NO_DEFAULT:
            return spec
        if _is_draw(value) and "choice" in value:
            value = {**value, "choice": [every if o is None else o for o in value["choice"]]}
        elif value is None:
            value = every
        return {**spec, "entries": value}

    def channels(self) -> dict[str, frozenset[Channel]]:
        """``{name: channels}`` of every component of positive weight but ``none`` (``own``:
        :attr:`own`'s, where it is an attack): what each can attack, the measurements (sensor,
        replacement) or the inputs (actuator); every option of a ``channel`` drawn by
        ``choice``."""
        out = {}
        for name, entry in self.spec.items():
            if float(entry["weight"]) <= 0 or name == "none":
                continue
            if name == "own":  # (a marker for the scenario's attack has no channel of its own)
                if isinstance(self.own, Attack):
                    out[name] = frozenset({Channel(self.own.channel)})
                continue
            drawn = entry.get("channel")
            options = drawn["choice"] if _is_draw(drawn) and "choice" in drawn else [drawn]
            found = set()
            for option in options:
                fixed = entry if option is drawn else {**entry, "channel": option}
                attack = self._build(name, fixed, torch.Generator().manual_seed(0))
                found.add(Channel(getattr(attack, "channel", Channel.SENSOR)))
            out[name] = frozenset(found)
        return out

    def onsets_past(self, steps: int) -> dict[str, float]:
        """``{name: share}``: the components of positive weight whose ``onset`` (the first
        attacked measurement, 1-based; a covert attack's, its signal's) can fall after the
        last of ``steps`` measurements,
        with the share of their draws that do. Such a draw acts on nothing: its run trains
        as an attack-free one (a horizon shortened with ``--data.steps``, say)."""
        past = {}
        for name, entry in self.spec.items():
            if name in _RESERVED or float(entry["weight"]) <= 0:
                continue
            share = _share_past(entry, steps)
            if share > 0:
                past[name] = share
        return past

    def sample(self, generator: torch.Generator) -> tuple[str, Any]:
        """``(name, attack)``: a threat by weight and its drawn fields; ``own`` gives
        :attr:`own`, ``none`` gives ``None``."""
        if not isinstance(generator, torch.Generator):  # (torch's multinomial() named neither)
            raise TypeError(
                f"generator must be a torch.Generator (e.g. torch.Generator().manual_seed(0)); "
                f"got {type(generator).__name__}"
            )
        names = list(self.spec)
        weights = torch.tensor([float(self.spec[n]["weight"]) for n in names], dtype=torch.float64)
        # over their largest: finite weights whose sum overflows (three of 1e308) had drawn
        # shares of 0.47, 0.31 and 0.22 for a third each
        weights = weights / weights.max()
        name = names[int(torch.multinomial(weights, 1, generator=generator))]
        if name == "own":
            return name, self.own
        if name == "none":
            return name, None
        return name, self._build(name, self.spec[name], generator)


_NO_DEFAULT = object()


def _share_past(entry: dict, steps: int) -> float:
    """The share of ``entry``'s draws whose onset falls after ``steps`` (0 for a threat
    without an onset). A covert attack acts from its signal's onset (it has none of its
    own), a signal drawn by ``choice`` from each option's equally."""
    if entry.get("kind") == "covert":
        signal = entry.get("signal")
        if _is_draw(signal) and "choice" in signal:
            options = signal["choice"]
            return sum(_share_past(o, steps) for o in options if _is_threat(o)) / len(options)
        return _share_past(signal, steps) if _is_threat(signal) else 0.0
    if entry.get("kind") not in THREATS:  # (an attack of one's own: no onset it declares)
        return 0.0
    onset = entry.get("onset", _default(entry["kind"], "onset"))
    if onset is _NO_DEFAULT:
        return 0.0
    if not _is_draw(onset):
        return float(onset > steps)
    if "choice" in onset:
        return sum(o > steps for o in onset["choice"]) / len(onset["choice"])
    lo, hi = onset["randint"]  # both included
    return max(0, hi - max(lo, steps + 1) + 1) / (hi - lo + 1)


def _entries_sorted(spec: dict) -> dict:
    """``spec`` with its ``entries`` (each option of a ``choice`` too) sorted: a shaped
    attack reads them as a set, so ``[3, 2]`` and ``[2, 3]`` are one attack (a trial's
    ``[3, 2]`` read "kind only" where ``[2, 3]`` was drawn). Lists of other than integers
    stay as they are (the threat refuses them when it is built)."""

    def _sorted(value):
        if (
            isinstance(value, (list, tuple))
            and value
            and all(isinstance(i, int) and not isinstance(i, bool) for i in value)
        ):
            return sorted(set(value))
        return value

    value = spec.get("entries")
    if _is_draw(value) and "choice" in value:
        return {**spec, "entries": {**value, "choice": [_sorted(o) for o in value["choice"]]}}
    return {**spec, "entries": _sorted(value)} if "entries" in spec else spec


def threat_spec(attack) -> dict | None:
    """``{"kind", **fields}`` of a threat of the library (exactly one of its classes, as
    :func:`~difffilter.threats.threat_from_dict` builds from that data), for
    :meth:`ThreatDistribution.covers`; ``None`` for anything else (``None``, a paper's
    attack, a covert attack, whose fields hold a model, an attack of one's own)."""
    kinds = {cls: kind for kind, cls in THREATS.items() if kind != "covert"}
    kind = kinds.get(type(attack))
    if kind is None:
        return None
    return {"kind": kind, **{f.name: _plain(getattr(attack, f.name)) for f in fields(attack)}}


def _plain(value):
    """A field's value as plain data (tuples as lists, tensors as nested lists)."""
    if isinstance(value, torch.Tensor):
        return value.tolist()
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def _default(kind: str, name: str):
    """The default of field ``name`` of threat class ``kind`` (:data:`_NO_DEFAULT` if none)."""
    for f in fields(THREATS[kind]):
        if f.name == name:
            if f.default is not MISSING:
                return f.default
            if f.default_factory is not MISSING:
                return f.default_factory()
    return _NO_DEFAULT


def _floats(value) -> tuple | None:
    """``value`` as a tuple of floats (a number is a 1-tuple), ``None`` if it is not numeric."""
    items = value if isinstance(value, (list, tuple)) else (value,)
    if not items or any(isinstance(v, bool) or not isinstance(v, (int, float)) for v in items):
        return None
    return tuple(float(v) for v in items)


def _channel_named(spec: dict) -> dict:
    """``spec`` with a constant ``channel`` read as the :class:`Channel` it names (a name
    that names none is left as written: it then differs)."""
    channel = spec.get("channel")
    if channel is None or _is_draw(channel) or isinstance(channel, Channel):
        return spec
    try:
        return {**spec, "channel": Channel(channel)}
    except ValueError:
        return spec


def _same(a, b) -> bool:
    """``a == b`` for plain data, numbers to 1e-9 (a number equals its 1-tuple)."""
    x, y = _floats(a), _floats(b)
    if x is not None and y is not None:
        if len(x) != len(y) and 1 in (len(x), len(y)):  # a number and the vector of it on
            x, y = (x * len(y), y) if len(x) == 1 else (x, y * len(x))  # every entry: one attack
        return len(x) == len(y) and all(math.isclose(u, v, rel_tol=1e-9, abs_tol=1e-12)
                                        for u, v in zip(x, y))  # fmt: skip
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_same(u, v) for u, v in zip(a, b))
    return a == b


def _drawable(field_spec, value) -> bool:
    """Whether a component's field (a constant or a draw) can give ``value``."""
    if value is _NO_DEFAULT or field_spec is _NO_DEFAULT:
        return False
    if not _is_draw(field_spec):
        return _same(field_spec, value)
    if "choice" in field_spec:
        return any(_same(option, value) for option in field_spec["choice"])
    numbers = _floats(value)
    if numbers is None or len(set(numbers)) != 1:  # a drawn number is one number
        return False
    x = numbers[0]
    if "randint" in field_spec:
        lo, hi = field_spec["randint"]
        return x == int(x) and lo <= x <= hi
    lo, hi = field_spec.get("uniform") or field_spec["loguniform"]
    slack = 1e-9 * max(abs(lo), abs(hi), 1.0)
    # signed: the draw from [lo, hi] or its negative (a magnitude test held only for lo >= 0)
    candidates = (x, -x) if field_spec.get("signed") else (x,)
    return any(lo - slack <= c <= hi + slack for c in candidates)
