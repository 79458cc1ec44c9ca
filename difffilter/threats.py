"""The threat library: attacks of the FDI literature as step objects, with a window.

Every attack here is an :class:`~difffilter.attack.Attack` for the loops of
:mod:`difffilter.loop`. The shaped ones (:class:`Shaped`) read nothing, so ``init``
tabulates the whole batch at once; what they share is *when and on whom* they act::

    on_k = onset ≤ k < onset + duration          (duration None: until the end)
    r    ~ Bernoulli(share) per run               (the runs attacked; drawn first)
    l_k  = on_k ∧ r                               flag; per entry when ``entries`` is given
    a_k  = shape(s),  s = k − onset               (s = 0 at the onset)

and the loop applies ``a_k`` on the attack's channel (sensor: ``ỹ = y + l a``; replacement:
``ỹ = a`` where ``l``; actuator: ``ũ = u + l a``). Outside ``entries`` the value is zero.

The shapes (``s`` as above, ``Δt`` the sampling period, ``ε ~ N(0, 1)``):

==================  ==========================================  ======================
class               ``a_k``                                     source
==================  ==========================================  ======================
:class:`Bias`       ``b``                                       Mo & Sinopoli 2010
:class:`KSigmaBias` ``k σ``, ``σ = √diag R``                    a bias scaled to noise
:class:`Ramp`       ``c (s + 1)``                               Urbina et al. 2016
:class:`RandomWalk` ``a_{k−1} + σ_w ε_k`` (``a = 0`` before)    Urbina et al. 2016
:class:`Pulses`     ``A`` where ``s mod P < W``, else 0          Sridhar & Govindarasu 2014
:class:`Sinusoid`   ``A sin(ω s Δt + φ)``                        Sridhar & Govindarasu 2014
:class:`Chirp`      ``A sin(2π (f₀ t + (f₁ − f₀) t² / 2τ))``,    a frequency sweep
                    ``t = s Δt``, ``τ`` the sweep's length
:class:`Replay`     ``y_{k−d}``, the last ``d`` measurements     Mo & Sinopoli 2009
                    before the onset, cyclically
                    (replacement channel)
:class:`Covert`     a shaped actuator attack whose effect on    Smith 2015
                    the sensors is subtracted from them
==================  ==========================================  ======================

Vectors (``b``, ``c``, ``A``, ``σ_w``) are one number for every entry or one per entry of
the channel. :func:`threat_from_dict` builds any of them from plain data (a YAML
entry), by the names of :data:`THREATS`.
"""

from __future__ import annotations

import copy
import inspect
import math
import numbers
from dataclasses import dataclass, field, fields, replace
from typing import Any

import torch
from torch import Tensor

from ._checks import broadcast_or_none, check_finite_number
from .attack import Attack, Channel, TabulatedAttack
from .ssm import StateSpaceModel

__all__ = [
    "Shaped",
    "Bias",
    "KSigmaBias",
    "Ramp",
    "RandomWalk",
    "Pulses",
    "Sinusoid",
    "Chirp",
    "Replay",
    "Covert",
    "THREATS",
    "check_attack_fits",
    "threat_from_dict",
    "with_sampling_period",
]


def _one_number(item) -> float:
    """One entry of a vector field as a ``float``: a real number (numpy's and 0-d arrays
    and tensors too), never a bool or a string, which ``float`` would take (YAML reads
    ``yes`` as true: ``[yes, 0.5]`` is not the vector (1, 0.5)); TypeError otherwise."""
    if getattr(item, "ndim", None) == 0 and not isinstance(item, (str, bytes)):
        item = item.item()
    if isinstance(item, bool) or not isinstance(item, numbers.Real):
        raise TypeError(item)
    return float(item)


def _numbers(value, name: str) -> tuple[float, ...]:
    """One finite number (numpy's and 0-d arrays and tensors too) or a non-empty sequence of
    them, as a tuple."""
    if getattr(value, "ndim", None) == 0 and not isinstance(value, (str, bytes)):
        value = value.item()  # np.int64(2), torch.tensor(0.5): one number, not "not a sequence"
    one = isinstance(value, numbers.Real) and not isinstance(value, bool)
    seq = (value,) if one else value
    if isinstance(seq, (str, bytes)):  # iterable, but "10" is not the vector (1, 0)
        raise ValueError(f"{name} must be a number or a sequence of numbers; got {value!r}")
    try:
        out = tuple(_one_number(v) for v in seq)
    except (TypeError, ValueError):
        raise ValueError(
            f"{name} must be a number or a sequence of numbers; got {value!r}"
        ) from None
    if not out or not all(math.isfinite(v) for v in out):
        raise ValueError(f"{name} must be finite numbers (at least one); got {value!r}")
    return out


def _scalar(value, name: str, *, positive: bool = False, nonnegative: bool = False) -> float:
    """One finite real number (a string from YAML, ``None`` or a list is named, not left
    to fail at sampling), as a ``float``."""
    try:
        return check_finite_number(value, name, positive=positive, nonnegative=nonnegative)
    except TypeError:
        raise ValueError(f"{name} must be a finite number; got {value!r}") from None


def _count(value, name: str, minimum: int) -> int:
    """``value`` as an ``int`` ``>= minimum`` (a numpy integer too: ``np.int64(3)``, from an
    array of onsets, was refused as "not an integer")."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}; got {value!r}")
    return int(value)


def _set_counts(attack, minimum: int, *names: str) -> None:
    """Check and store each of the frozen dataclass ``attack``'s fields ``names`` as an
    ``int >= minimum`` (:func:`_count`)."""
    for name in names:
        object.__setattr__(attack, name, _count(getattr(attack, name), name, minimum))


def _share(value) -> float:
    """``value`` as a share of runs: a number in ``[0, 1]`` (a string such as YAML's
    quoted ``"0.5"`` failed only at sampling, with a message that did not name it)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not 0.0 <= value <= 1.0:
        raise ValueError(f"share must be a number in [0, 1] (a share of runs); got {value!r}")
    return float(value)


def _batch(batch_shape) -> torch.Size:
    return torch.Size((batch_shape,) if isinstance(batch_shape, int) else batch_shape)


@dataclass(frozen=True, kw_only=True)
class Shaped(TabulatedAttack):
    """A shaped attack's window (module docstring): ``onset`` (first attacked measurement,
    1-based), ``duration`` (steps, ``None``: to the end), ``share`` (probability that a run
    is attacked), ``entries`` (attacked entries of the channel, ``None``: all) and
    ``channel`` (:class:`~difffilter.attack.Channel`, default the sensors).

    Subclasses implement :meth:`shape`.
    """

    onset: int = 1
    duration: int | None = None
    share: float = 1.0
    entries: tuple[int, ...] | None = None
    channel: Channel = Channel.SENSOR

    def __post_init__(self):
        _set_counts(self, 1, "onset", *(() if self.duration is None else ("duration",)))
        object.__setattr__(self, "share", _share(self.share))
        object.__setattr__(self, "channel", Channel(self.channel))
        if self.entries is not None:
            if isinstance(self.entries, (str, bytes)) or not hasattr(self.entries, "__iter__"):
                raise ValueError(
                    f"entries must be None or a list of indices >= 0 (e.g. [0, 2]); got "
                    f"{self.entries!r}"
                )
            entries = tuple(self.entries)
            if not entries or any(isinstance(i, bool) or not isinstance(i, numbers.Integral)
                                  or i < 0 for i in entries):  # fmt: skip
                raise ValueError(
                    f"entries must be None or a non-empty list of integer indices >= 0; got "
                    f"{self.entries!r}"
                )
            if len(set(entries)) != len(entries):  # ([0, 0], a typo for [0, 1], attacked 0)
                raise ValueError(f"entries must be distinct indices; got {self.entries!r}")
            object.__setattr__(self, "entries", tuple(int(i) for i in entries))

    def shape(self, s: Tensor, dim: int, batch: torch.Size, generator, dtype) -> Tensor:
        """``a`` at the steps since the onset ``s [T]`` (negative before it): ``[T, dim]``
        or ``[*batch, T, dim]``."""
        raise NotImplementedError

    def _vector(self, value: tuple[float, ...], dim: int, name: str, dtype, device) -> Tensor:
        if len(value) not in (1, dim):
            raise ValueError(f"{name} has {len(value)} entries; the channel has {dim}")
        return torch.tensor(value, dtype=dtype, device=device).expand(dim)

    def sample(self, batch_shape, num_steps, dim, generator=None, *, dtype, device=None):
        _count(num_steps, "num_steps", 1)
        shape = _batch(batch_shape)
        runs = torch.rand(shape, generator=generator, dtype=torch.float64, device=device)
        attacked_run = runs < self.share
        k = torch.arange(1, num_steps + 1, device=device)
        on = k >= self.onset
        if self.duration is not None:
            on = on & (k < self.onset + self.duration)
        s = (k - self.onset).to(dtype)
        values = self.shape(s, dim, shape, generator, dtype)
        want = (num_steps, dim)
        full = torch.Size((*shape, *want))
        if not isinstance(values, Tensor) or broadcast_or_none(values.shape, full) != full:
            # (an attack of one's own: a raw expand error had escaped, naming nothing)
            got = tuple(values.shape) if isinstance(values, Tensor) else type(values).__name__
            raise ValueError(
                f"{type(self).__name__}.shape returned {got}; it must return the attack's "
                f"values [T, dim] = {list(want)} (one row per step, one column per entry of the "
                f"channel) or [*batch, T, dim] = {[*shape, *want]}, or a shape that broadcasts "
                "to them"
            )
        values = torch.where(on.unsqueeze(-1), values.to(device),
                             torch.zeros((), dtype=dtype, device=device))  # fmt: skip
        flags = attacked_run.unsqueeze(-1) & on
        if self.entries is not None:
            if max(self.entries) >= dim:
                raise ValueError(f"entries {self.entries} name entries beyond the channel's {dim}")
            picked = torch.zeros(dim, dtype=torch.bool, device=device)
            picked[list(self.entries)] = True
            values = values * picked.to(dtype)
            flags = flags.unsqueeze(-1) & picked
        return values.expand(*shape, num_steps, dim), flags


@dataclass(frozen=True)
class Bias(Shaped):
    """A constant bias ``a_k = b`` (Mo & Sinopoli 2010, the simplest FDI attack)."""

    value: Any = 1.0

    def __post_init__(self):
        super().__post_init__()
        object.__setattr__(self, "value", _numbers(self.value, "value"))

    def shape(self, s, dim, batch, generator, dtype):
        b = self._vector(self.value, dim, "value", dtype, s.device)
        return b.expand(s.shape[0], dim)


@dataclass(frozen=True)
class KSigmaBias(Shaped):
    """A bias of ``k`` noise standard deviations on each attacked entry, ``a = k σ`` with
    ``σ = √diag R`` (given as ``sigma``; :meth:`of` reads it from a model)."""

    k: float = 1.5
    sigma: Any = 1.0

    def __post_init__(self):
        super().__post_init__()
        object.__setattr__(self, "k", _scalar(self.k, "k"))
        sigma = _numbers(self.sigma, "sigma")
        if any(v <= 0 for v in sigma):
            raise ValueError(f"sigma must be positive; got {self.sigma!r}")
        object.__setattr__(self, "sigma", sigma)

    @classmethod
    def of(cls, model, k: float, **window) -> KSigmaBias:
        """``k σ`` with ``σ = √diag R`` of ``model``'s measurement noise at step 1: a bias on
        the sensors (on the actuators give ``sigma``, the inputs' σ: ``ValueError``)."""
        try:
            actuator = Channel(window.get("channel", Channel.SENSOR)) is Channel.ACTUATOR
        except ValueError:
            actuator = False  # (the class names a bad channel)
        if actuator:  # (√diag R, the sensors' noise, had been taken for the inputs' σ)
            raise ValueError(
                "ksigma_bias on the actuators needs sigma (the inputs' σ): without it σ is "
                "√diag R, the measurement noise's"
            )
        sigma = model.measurement_cov(1).diagonal(dim1=-2, dim2=-1).sqrt()
        rows = sigma.reshape(-1, sigma.shape[-1])
        if not bool((rows == rows[:1]).all()):
            # one σ for every run: the first run's had been taken for all (2 σ in run 0, 0.67 σ
            # in run 2 of a model of one R per run: a red-team trial)
            raise ValueError(
                "KSigmaBias.of: the model's measurement noise differs between its runs (an R "
                "per run), and a KSigmaBias is one bias for every run: give sigma explicitly "
                "(KSigmaBias(k=..., sigma=[...]))"
            )
        return cls(k=k, sigma=tuple(float(v) for v in rows[0]), **window)

    def shape(self, s, dim, batch, generator, dtype):
        sigma = self._vector(self.sigma, dim, "sigma", dtype, s.device)
        return (float(self.k) * sigma).expand(s.shape[0], dim)


@dataclass(frozen=True)
class Ramp(Shaped):
    """A ramp ``a_k = c (s + 1)``: ``c`` per step at the onset, growing linearly
    (Urbina et al. 2016's slowly growing bias)."""

    slope: Any = 0.01

    def __post_init__(self):
        super().__post_init__()
        object.__setattr__(self, "slope", _numbers(self.slope, "slope"))

    def shape(self, s, dim, batch, generator, dtype):
        c = self._vector(self.slope, dim, "slope", dtype, s.device)
        return (s + 1).unsqueeze(-1) * c


@dataclass(frozen=True)
class RandomWalk(Shaped):
    """A random walk from zero at the onset, ``a_k = a_{k−1} + σ_w ε_k`` (one walk per run,
    ``ε`` drawn from the attack's generator after the run selection, one ``[*batch, T, dim]``
    block: a loop of another length ``T`` draws the runs after the first another walk)."""

    step_std: Any = 0.01

    def __post_init__(self):
        super().__post_init__()
        std = _numbers(self.step_std, "step_std")
        if any(v < 0 for v in std):
            raise ValueError(f"step_std must be >= 0; got {self.step_std!r}")
        object.__setattr__(self, "step_std", std)

    def shape(self, s, dim, batch, generator, dtype):
        std = self._vector(self.step_std, dim, "step_std", dtype, s.device)
        eps = torch.randn(*batch, s.shape[0], dim, generator=generator, dtype=dtype,
                          device=s.device)  # fmt: skip
        steps = eps * std * (s >= 0).to(dtype).unsqueeze(-1)  # nothing moves before the onset
        return steps.cumsum(-2)


@dataclass(frozen=True)
class Pulses(Shaped):
    """A pulse train: ``a_k = A`` for the first ``width`` of every ``period`` steps after
    the onset, else 0 (a pulse or square-wave attack)."""

    amplitude: Any = 1.0
    period: int = 10
    width: int = 5

    def __post_init__(self):
        super().__post_init__()
        object.__setattr__(self, "amplitude", _numbers(self.amplitude, "amplitude"))
        _set_counts(self, 1, "period", "width")
        if self.width > self.period:
            raise ValueError(
                f"width must be <= period; got width={self.width}, period={self.period}"
            )

    def shape(self, s, dim, batch, generator, dtype):
        amp = self._vector(self.amplitude, dim, "amplitude", dtype, s.device)
        high = torch.remainder(s, self.period) < self.width
        return high.to(dtype).unsqueeze(-1) * amp


@dataclass(frozen=True)
class Sinusoid(Shaped):
    """A sinusoid ``a_k = A sin(ω s Δt + φ)`` (``ω`` in rad per unit of ``dt``)."""

    amplitude: Any = 1.0
    omega: float = 1.0
    phase: float = 0.0
    dt: float = 1.0

    def __post_init__(self):
        super().__post_init__()
        object.__setattr__(self, "amplitude", _numbers(self.amplitude, "amplitude"))
        for name in ("omega", "phase"):
            object.__setattr__(self, name, _scalar(getattr(self, name), name))
        object.__setattr__(self, "dt", _scalar(self.dt, "dt", positive=True))

    def shape(self, s, dim, batch, generator, dtype):
        amp = self._vector(self.amplitude, dim, "amplitude", dtype, s.device)
        return torch.sin(self.omega * self.dt * s + self.phase).unsqueeze(-1) * amp


@dataclass(frozen=True)
class Chirp(Shaped):
    """A linear chirp: the frequency sweeps from ``f0`` to ``f1`` (cycles per unit of
    ``dt``) over ``sweep`` steps and stays at ``f1`` after,
    ``a = A sin(2π (f₀ t + (f₁ − f₀) t² / 2τ))``, ``t = s Δt``, ``τ = sweep Δt``."""

    amplitude: Any = 1.0
    f0: float = 0.01
    f1: float = 0.2
    sweep: int = 100
    dt: float = 1.0

    def __post_init__(self):
        super().__post_init__()
        object.__setattr__(self, "amplitude", _numbers(self.amplitude, "amplitude"))
        _set_counts(self, 1, "sweep")
        for name in ("f0", "f1"):
            object.__setattr__(self, name, _scalar(getattr(self, name), name, nonnegative=True))
        object.__setattr__(self, "dt", _scalar(self.dt, "dt", positive=True))

    def phase(self, s: Tensor) -> Tensor:
        """``2π ∫ f`` at ``s`` steps after the onset (continuous past the sweep)."""
        tau = self.sweep * self.dt
        t = (s * self.dt).clamp_min(0)
        inside = t.clamp_max(tau)
        cycles = self.f0 * inside + (self.f1 - self.f0) * inside.square() / (2 * tau)
        return 2 * math.pi * (cycles + self.f1 * (t - inside))

    def shape(self, s, dim, batch, generator, dtype):
        amp = self._vector(self.amplitude, dim, "amplitude", dtype, s.device)
        return torch.sin(self.phase(s)).unsqueeze(-1) * amp


@dataclass(frozen=True)
class Replay(Attack):
    """Replay (Mo & Sinopoli 2009): record, then replay. The attacker records the plant's
    last ``d`` true measurements before ``onset`` and, from ``onset`` on, hands the receiver
    those recordings in order, again from the first if the replay outlasts them (the
    replacement channel: the loop records ``ỹ_k − y_k``)::

        ỹ_k = y_{k₀ − d + ((k − k₀) mod d)}          k₀ = onset

    so ``ỹ_k = y_{k−d}`` over the first ``d`` replayed steps. The plant meanwhile may do
    anything. With ``live=True`` the attacker keeps recording during the replay and hands
    ``ỹ_k = y_{k−d}`` throughout (a time-delay attack): after ``d`` steps it replays what
    the plant did under the attack itself. Needs ``onset > delay`` (there is nothing to
    replay before).

    **A seamless splice** (``loop=(Φ, C)``). Where the loop has modes that decay slowly or
    not at all, the state wanders, and a recording seconds old starts from another level
    than the live measurement it replaces: the switch is a jump that the innovations show
    until the observer has followed it. An attacker who knows the closed loop (Kerckhoffs:
    ``Φ = A − BK`` and ``C`` of the defender's model) hides it: it estimates the state gap
    ``δ`` between the end and the start of its recording from their ``w``-step means, and
    replays the recording plus the gap's free response through the loop::

        g   = Φ C⁺ mean(r_{d−w} … r_{d−1}) − C⁺ mean(r_0 … r_{w−1})   (r_{d−1} = y_{k₀−1})
        δ_k = Φ δ_{k−1} (+ g at the start of every pass),   ỹ_k = r_k + C δ_k

    The offset is what the closed loop would do from that gap on its own, so an observer
    that predicts with ``Φ`` finds it consistent (innovations zero up to the error of
    ``g``): only the error of the gap's estimate shows at the splice. On a noise-free loop
    ``x_{k+1} = Φ x_k`` with ``w = 1`` and ``C`` of full column rank (the gap's state is
    then ``C⁺`` of its measurements) the replay continues the live trajectory exactly; a
    ``C`` that sees part of the state leaves the unseen part of the gap out (0.25 off with
    ``C = [1 0 0]``: a stealthy trial).

    Args:
        delay: ``d ≥ 1`` steps (the length of the recording).
        onset: first replayed measurement ``k₀`` (1-based, ``k₀ > d``).
        duration: replayed steps (``None``: until the end).
        share: probability that a run is attacked (drawn at ``init``).
        live: keep recording during the replay (default ``False``).
        loop: ``(Φ [n, n], C [dy, n])``, the attacker's model of the closed loop, for a
            seamless splice (default ``None``: Mo & Sinopoli's plain replay); needs
            ``live=False``.
        level_window: ``w``, the frames averaged to estimate the gap (``≤ d``), with
            ``loop`` only (default ``None``: 5 with ``loop``, which needs ``d ≥ 5``; without
            one it would do nothing, and is refused).
    """

    delay: int
    onset: int
    duration: int | None = None
    share: float = 1.0
    live: bool = False
    loop: Any = field(default=None, repr=False, compare=False)
    level_window: int | None = None
    channel = Channel.REPLACEMENT
    reads_state = False  # (what it intercepts: the measurements)

    def __post_init__(self):
        _set_counts(self, 1, "delay", "onset")
        if self.onset <= self.delay:
            raise ValueError(
                f"onset must exceed delay (y_(k-d) must exist); got onset={self.onset}, "
                f"delay={self.delay}"
            )
        if self.duration is not None:
            _set_counts(self, 1, "duration")
        object.__setattr__(self, "share", _share(self.share))
        if not isinstance(self.live, bool):
            raise ValueError(f"live must be True or False; got {self.live!r}")
        if self.loop is None:
            if self.level_window is not None:  # (it had been taken and done nothing)
                raise ValueError(
                    f"level_window={self.level_window!r} sets the frames of a seamless splice, "
                    "which needs loop=(Φ, C); a plain replay has no splice: leave it out"
                )
            return
        defaulted = self.level_window is None
        if defaulted:
            object.__setattr__(self, "level_window", 5)
        _set_counts(self, 1, "level_window")
        if defaulted and self.level_window > self.delay:
            # (said as the default's: it had named a level_window the caller never set; and
            # a window of the whole recording would estimate no gap at all, a review)
            raise ValueError(
                f"the seamless replay's default level_window (5 frames) needs delay >= 5; got "
                f"delay={self.delay}: give level_window=w with w < delay (1 for a noise-free "
                "loop)"
            )
        self._check_loop()

    def _check_loop(self):
        if self.live:
            raise ValueError("loop needs live=False (a live replay has no splice to hide)")
        if self.level_window > self.delay:
            raise ValueError(
                f"level_window must be at most delay (frames of the recording); got "
                f"level_window={self.level_window}, delay={self.delay}"
            )
        try:
            phi, c = (torch.as_tensor(m) for m in self.loop)
        except (TypeError, ValueError) as error:
            raise ValueError(f"loop must be a pair (Φ [n, n], C [dy, n]); {error}") from None
        n = phi.shape[0] if phi.dim() == 2 else -1
        if phi.shape != (n, n) or c.dim() != 2 or c.shape[1] != n:
            raise ValueError(
                f"loop must be (Φ [n, n], C [dy, n]); got shapes {tuple(phi.shape)} and "
                f"{tuple(c.shape)}"
            )

    def init(self, batch_shape, num_steps, dim, generator=None, *, dtype, device=None):
        """``(recording [..., d, dim], attacked run [...], loop offset δ [..., n] or None)``."""
        shape = _batch(batch_shape)
        runs = torch.rand(shape, generator=generator, dtype=torch.float64, device=device)
        recording = torch.zeros(shape + (self.delay, dim), dtype=dtype, device=device)
        return recording, runs < self.share, None

    def _splice_gap(self, recording: Tensor) -> Tensor:
        """``g = C⁺ (end level − start level)`` of the recording ``[..., n]``."""
        phi, c = (torch.as_tensor(m, dtype=recording.dtype, device=recording.device)
                  for m in self.loop)  # fmt: skip
        if c.shape[0] != recording.shape[-1]:
            raise ValueError(
                f"loop's C has {c.shape[0]} rows but the measurement has "
                f"{recording.shape[-1]} channels"
            )
        w, to_state = self.level_window, torch.linalg.pinv(c).mT
        end = recording[..., -w:, :].mean(-2) @ to_state
        start = recording[..., :w, :].mean(-2) @ to_state
        return end @ phi.mT - start

    def step(self, state, k, *, y=None, x=None, u=None, view=None):
        buffer, attacked_run, offset = state
        old = buffer[..., 0, :]  # the oldest recorded: y_{k−d} while recording
        last = None if self.duration is None else self.onset + self.duration - 1
        on = k >= self.onset and (last is None or k <= last)
        # while replaying, a recording attacker cycles through its recording; otherwise
        # (and a live one always) it records the true measurement
        newest = y if self.live or not on else old
        flag = attacked_run.expand(y.shape[:-1]) & on
        if self.loop is not None and on:
            phi, c = (torch.as_tensor(m, dtype=y.dtype, device=y.device) for m in self.loop)
            if (k - self.onset) % self.delay == 0:  # a pass starts: add the gap it opens
                gap = self._splice_gap(buffer)
                offset = gap if offset is None else offset @ phi.mT + gap
            else:
                offset = offset @ phi.mT
            old = old + offset @ c.mT
        buffer = torch.cat([buffer[..., 1:, :], newest.unsqueeze(-2)], dim=-2)
        return (buffer, attacked_run, offset), old, flag


@dataclass(frozen=True)
class Covert(Attack):
    """The covert attack (Smith 2015; the "covert" attack of Teixeira et al. 2015): a shaped
    attack ``a_k`` on the actuators, and on the sensors the attacker subtracts the effect it
    predicts, so that the receiver sees the plant that was not attacked.

    The attacker runs two noise-free copies of its model of the plant, one driven by what
    it injects and one by the commanded input, and hides their difference::

        x̄ᵃ_k = f(x̄ᵃ_{k−1}, u_{k−1} + l_k a_k),   x̄ⁿ_k = f(x̄ⁿ_{k−1}, u_{k−1})
        ỹ_k  = y_k + h(x̄ⁿ_k) − h(x̄ᵃ_k)

    Until it first injects, both copies are reset to the true state ``x_{k−1}`` (which the
    attacker reads). On a linear plant ``x̄ᵃ − x̄ⁿ = Σ_j A^j B l a`` is exactly the
    deviation the attack causes, so ``ỹ`` *is* the attack-free measurement, bit for bit up
    to rounding, in the open loop and in a closed loop (the controller sees what it would
    have seen, and commands what it would have commanded): no detector that reads ``ỹ`` and
    ``u`` can see it, while the plant drifts by the deviation. On a nonlinear plant the
    copies propagate without the noise the plant meets, so the concealment is first order.

    Args:
        signal: the actuator attack (a :class:`Shaped` on ``Channel.ACTUATOR``: its window,
            share and entries are the covert attack's).
        plant: the attacker's model of the plant (``transition(x, u, t)``, ``observe(x, k)``:
            any :class:`~difffilter.StateSpaceModel`); Kerckhoffs' worst case gives it the
            defender's.
    """

    signal: Shaped
    plant: Any = field(repr=False, compare=False)
    channel = Channel.ACTUATOR
    conceals = True
    reads_state = True  # (its copies start from the true state)

    def __post_init__(self):
        if not isinstance(self.signal, Shaped):
            raise ValueError(
                f"signal must be a shaped attack of difffilter.threats (Bias, Ramp, …); got "
                f"{type(self.signal).__name__}"
            )
        if Channel(self.signal.channel) is not Channel.ACTUATOR:
            raise ValueError(
                f"signal must act on the actuators (channel='actuator'); got "
                f"{Channel(self.signal.channel).value}"
            )
        if not (callable(getattr(self.plant, "transition", None))
                and callable(getattr(self.plant, "observe", None))):  # fmt: skip
            raise ValueError(
                "plant must be a model with transition(x, u, t) and observe(x, k) (a "
                f"difffilter StateSpaceModel); got {type(self.plant).__name__}"
            )
        if getattr(self.plant, "dim_u", 1) == 0:
            raise ValueError("a covert attack needs a plant with inputs (dim_u > 0)")

    def init(self, batch_shape, num_steps, dim, generator=None, *, dtype, device=None):
        """``(signal's table, x̄ᵃ, x̄ⁿ, injected so far [...], the attacker's model)``; the
        copies start at step 1. The model is ``plant``, or a copy of it converted to the
        loop's dtype and device where it is an ``nn.Module`` of others (a YAML scenario's
        attacker is built from the float64 plant, and the suite and the training run
        float32 loops: every one had stopped on the dtype)."""
        table = self.signal.init(batch_shape, num_steps, dim, generator, dtype=dtype,
                                 device=device)  # fmt: skip
        return table, None, None, None, self._plant_in(dtype, device)

    def _plant_in(self, dtype, device):
        plant = self.plant
        mean = getattr(getattr(plant, "initial", None), "mean", None)
        if not isinstance(mean, Tensor):
            return plant
        device = mean.device if device is None else torch.device(device)
        if mean.dtype == dtype and mean.device == device:
            return plant
        try:
            if isinstance(plant, torch.nn.Module):
                return copy.deepcopy(plant).to(dtype=dtype, device=device)
            reason = "it is not an nn.Module, which could be converted"
        except (RuntimeError, TypeError) as error:  # (a non-leaf tensor cannot be deep-copied)
            reason = f"it could not be converted: {error}"
        # (torch's "m1 and m2 must have the same dtype" otherwise)
        raise ValueError(
            f"plant (the covert attacker's model) is {mean.dtype} on {mean.device} and the loop "
            f"{dtype} on {device}, and {reason}: give the attacker its model in the loop's dtype"
        )

    def last_step(self, state) -> int | None:
        return self.signal.last_step(state[0])

    def step(self, state, k, *, y=None, x=None, u=None, view=None):
        table, attacked, nominal, injected, plant = state
        table, value, flag = self.signal.step(table, k)
        if injected is None:  # step 1: both copies start at x_0
            attacked, nominal = x, x
            injected = torch.zeros(x.shape[:-1], dtype=torch.bool, device=x.device)
        else:  # a run not attacked yet: the copies follow its true state x_{k−1}
            fresh = ~injected.unsqueeze(-1)
            attacked, nominal = torch.where(fresh, x, attacked), torch.where(fresh, x, nominal)
        on = flag if flag.dim() == value.dim() else flag.unsqueeze(-1)
        attacked = plant.transition(attacked, u + on.to(value.dtype) * value, k - 1)
        nominal = plant.transition(nominal, u, k - 1)
        return (table, attacked, nominal, injected | on.any(-1), plant), value, flag

    def conceal(self, state, k, *, y, x):
        _, attacked, nominal, _, plant = state
        residual = getattr(type(plant), "measurement_residual", None)  # (a duck-typed plant)
        if residual is None or residual is StateSpaceModel.measurement_residual:
            return state, plant.observe(nominal, k) - plant.observe(attacked, k)
        # angles (a model whose residual wraps them): the attack-free prediction plus this
        # measurement's own deviation from the attacked one (its residual), wrapped as the
        # model wraps a residual (against 0), minus y; the difference of the two predictions
        # had sent bearings 2π outside (−π, π] (93 of 4,800 on the robot; a trial)
        deviation = plant.measurement_residual(y, plant.observe(attacked, k))
        received = plant.observe(nominal, k) + deviation
        received = plant.measurement_residual(received, torch.zeros_like(received))
        return state, received - y


def _at_first_step(signal: TabulatedAttack) -> tuple[TabulatedAttack, int]:
    """``(signal, steps)`` to tabulate ``signal`` through its onset: a :class:`Shaped` one
    moved to onset 1 and one step (its shape reads ``s = k − onset`` alone, so the onset
    step is the same), another to its onset (a class whose fields ``replace`` cannot copy,
    too)."""
    onset = getattr(signal, "onset", None)
    if isinstance(signal, Shaped) and onset != 1:
        try:
            return replace(signal, onset=1), 1
        except TypeError:  # (a subclass of one's own with an __init__ of its own)
            pass
    return signal, max(onset or 1, 1)


def check_attack_fits(attack: Attack | None, model, num_steps: int | None = None) -> None:
    """Raise ``ValueError`` where ``attack`` cannot act on ``model`` over ``num_steps``
    measurements: what would otherwise fail (or do nothing) only when a run is simulated.

    - an actuator attack (a covert attack's signal included) on a model without inputs;
    - a tabulated attack (a :class:`Shaped` one, a covert attack's signal) whose values or
      ``entries`` do not fit its channel's width (``dy`` on the sensors, ``du`` on the
      actuators): tabulated once, one run, through its onset (a :class:`Shaped` one at
      onset 1, one step: :func:`_at_first_step`; tabulated to an onset of 2**62, it had
      asked for 7e18 bytes);
    - with ``num_steps``: a first attacked step (``onset``, 1-based, or a paper attack's
      0-based ``start``) after the last step (it would never act);
    - a seamless replay whose loop ``C`` has another number of rows than the measurements.
    """
    if attack is None:
        return
    if isinstance(attack, Replay) and attack.loop is not None:  # (it failed at the first
        rows = torch.as_tensor(attack.loop[1]).shape[0]  # replayed step, unnamed, after the
        if rows != model.dim_y:  # calibration and every threat before it had run)
            raise ValueError(
                f"the replay's loop C has {rows} rows; the model has {model.dim_y} measurements"
            )
    if isinstance(attack, Covert):  # (another size had failed in Covert.step's matmul)
        from .loop import _check_attackers_plant  # (here: the loop module is the heavier one)

        _check_attackers_plant(attack, model)
    signal = attack.signal if isinstance(attack, Covert) else attack
    onset, start = getattr(signal, "onset", None), getattr(signal, "start", None)
    first = onset if onset is not None else None if start is None else start + 1
    if num_steps is not None and first is not None and first > num_steps:
        raise ValueError(f"it starts at step {first}, after the last step ({num_steps}): it "
                         "would never act")  # fmt: skip
    if not isinstance(signal, TabulatedAttack):
        return
    actuator = Channel(signal.channel) is Channel.ACTUATOR
    dim = model.dim_u if actuator else model.dim_y
    if actuator and not dim:
        raise ValueError("an actuator attack needs a model with inputs (dim_u > 0)")
    steps = num_steps
    if num_steps is None:
        signal, steps = _at_first_step(signal)
    signal.sample((1,), steps, dim, torch.Generator().manual_seed(0), dtype=torch.float64)


#: The threat library by name (the ``kind`` of a YAML entry, :func:`threat_from_dict`).
THREATS: dict[str, type[Attack]] = {
    "bias": Bias,
    "ksigma_bias": KSigmaBias,
    "ramp": Ramp,
    "random_walk": RandomWalk,
    "pulses": Pulses,
    "sinusoid": Sinusoid,
    "chirp": Chirp,
    "replay": Replay,
    "covert": Covert,
}


def with_sampling_period(spec: dict, dt: float | None) -> dict:
    """``spec`` (``{"kind", **fields}``) with ``dt`` where its kind takes one (a sinusoid's,
    a chirp's; a covert attack's nested signal too) and the spec sets none: the scenario's
    sampling period, so that ``omega`` and ``f0``/``f1`` are in the file's time unit, as its
    inputs' frequencies are (a trial: ``omega: π`` at a scenario's ``dt: 0.01`` had been
    read per step, ``A sin(π s)``, zero at every step: an attack that injected nothing).
    Unchanged for ``dt=None`` or a kind without ``dt``."""
    if dt is None or not isinstance(spec, dict):
        return spec
    kind = spec.get("kind")
    cls = THREATS.get(kind) if isinstance(kind, str) else None
    out = dict(spec)
    if cls is not None and "dt" in {f.name for f in fields(cls)} and "dt" not in spec:
        out["dt"] = dt
    signal = spec.get("signal")
    if kind == "covert" and isinstance(signal, dict):
        if isinstance(signal.get("choice"), list):  # a signal drawn from several (training)
            out["signal"] = {**signal, "choice": [with_sampling_period(o, dt)
                                                  for o in signal["choice"]]}  # fmt: skip
        else:
            out["signal"] = with_sampling_period(signal, dt)
    return out


def threat_from_dict(spec: dict, model=None) -> Attack:
    """An attack of :data:`THREATS` from plain data: ``{"kind": name, **fields}``, or an
    attack of one's own: ``{"kind": "package.module:object", **arguments}``
    (:func:`_attack_of_ones_own`).

    ``ksigma_bias`` without ``sigma`` reads ``σ = √diag R`` from ``model``; ``covert`` takes
    ``model`` as the attacker's plant and its ``signal`` as a nested mapping (put on the
    actuators). Unknown kinds and fields are named in the error with the valid ones.
    """
    if not isinstance(spec, dict) or "kind" not in spec:
        raise ValueError(f"a threat must be a mapping with a 'kind'; got {spec!r}")
    params = dict(spec)
    kind = params.pop("kind")
    if kind == "stealthy":  # a threat set's entry, not a library attack
        raise ValueError(
            "a 'stealthy' threat is crafted against an estimator when a robustness study runs "
            "(an entry of a threat set: difffilter.eval.stealthy.StealthySpec), or by "
            "difffilter.stealthy.craft_stealthy_attack; it is not built from data here"
        )
    if isinstance(kind, str) and ":" in kind:
        return _attack_of_ones_own(kind, params, model)
    if not isinstance(kind, str) or kind not in THREATS:  # (a list failed as "unhashable")
        raise ValueError(
            f"unknown threat kind {kind!r}; valid: {', '.join(sorted(THREATS))} (in a threat "
            "set also stealthy), or an attack of your own as package.module:object"
        )
    cls = THREATS[kind]
    valid = {f.name for f in fields(cls)}
    unknown = sorted(set(params) - valid)
    if unknown:
        raise ValueError(
            f"threat {kind!r} has no field(s) {', '.join(unknown)}; valid: {', '.join(sorted(valid))}"
        )
    if cls is Covert:
        if "plant" in params:  # (it was silently replaced by the model)
            raise ValueError(
                "a covert threat's plant is the model of the scenario it runs on, given by the "
                "caller (Kerckhoffs: the defender's); remove plant from the threat"
            )
        if model is None:
            raise ValueError("a covert threat needs the model (the attacker's model of the plant)")
        signal = params.get("signal")
        if not isinstance(signal, dict):
            raise ValueError(
                f"a covert threat needs signal: a shaped threat's mapping (e.g. {{kind: bias, "
                f"value: 0.1}}); got {signal!r}"
            )
        shaped = sorted(k for k, c in THREATS.items() if issubclass(c, Shaped))
        own = isinstance(signal.get("kind"), str) and ":" in signal["kind"]  # (Covert checks)
        if not own and signal.get("kind") not in shaped:  # (a replay's: "no field(s) channel")
            raise ValueError(
                f"a covert threat's signal must be a shaped threat, one of {', '.join(shaped)} "
                f"(it is put on the actuators); got kind {signal.get('kind')!r}"
            )
        try:  # (it was moved there silently; any spelling a Channel takes is read as one)
            on_actuators = Channel(signal.get("channel", "actuator")) is Channel.ACTUATOR
        except ValueError:
            on_actuators = False
        if not on_actuators:
            raise ValueError(
                "a covert threat's signal acts on the actuators: leave its channel out (or "
                f"write actuator); got channel {signal['channel']!r}"
            )
        inner = threat_from_dict({**signal, "channel": "actuator"}, model)
        return Covert(inner, model)
    if cls is KSigmaBias and "sigma" not in params:
        if model is None:
            raise ValueError("ksigma_bias without sigma needs the model (sigma = sqrt(diag R))")
        k = params.pop("k", KSigmaBias.k)  # the class default, said once
        return KSigmaBias.of(model, k, **params)
    return cls(**params)


def _attack_of_ones_own(path: str, arguments: dict, model) -> Attack:
    """The attack a ``package.module:object`` path names, made from ``arguments``: an
    :class:`~difffilter.attack.Attack` subclass or a function returning an attack, called
    with the arguments (and ``model=`` the scenario's model where it takes ``model`` and the
    arguments do not give it), or an attack object (no arguments)."""
    from ._imports import import_object

    where = f"threat kind {path!r}"
    obj = import_object(path, where)
    if isinstance(obj, Attack):
        if arguments:
            raise ValueError(f"{where} is an attack object: it takes no fields; got "
                             f"{', '.join(sorted(arguments))}")  # fmt: skip
        return obj
    if not callable(obj):
        raise ValueError(f"{where} is a {type(obj).__name__}: name an Attack subclass, a "
                         "function returning an attack, or an attack object")  # fmt: skip
    try:
        takes_model = "model" in inspect.signature(obj).parameters
    except (TypeError, ValueError):  # (no signature to read)
        takes_model = False
    if takes_model and "model" not in arguments:
        arguments = {**arguments, "model": model}
    try:
        attack = obj(**arguments)
    except TypeError as exc:
        raise ValueError(f"{where}: {exc}") from None
    if not isinstance(attack, Attack):
        raise ValueError(f"{where} made a {type(attack).__name__}, not a difffilter.attack.Attack")
    return attack
