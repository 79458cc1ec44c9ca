"""The attacks of the scenarios: sensor bias, actuator injection, replacement, a known
signal and replay, each an :class:`~difffilter.attack.Attack` step object.

Bias injection attack of the modified-PF paper (Sadeghzadeh-Nokhodberiz et al., IEEE
Access 2022, eqs 3–4)::

    ỹ_k     = y_k + l_k γ_k,                 l_k ~ Bernoulli(p_l) i.i.d.     (3)
    γ_{k+1} = τ γ_k + (1 − τ) γ̄,             γ_0 = 0, 0 < τ < 1              (4)

so ``γ_k = (1 − τ^k) γ̄`` converges slowly to the bias ``γ̄`` (a stealthy, low-pass
attack). The attack value evolves at every step whether or not it is injected; the
Bernoulli flag only decides whether the packet of step ``k`` carries it.

Time convention (as everywhere in difffilter, :mod:`difffilter.ssm`): a measurement
sequence ``ys [..., T, dy]`` holds ``y_1 … y_T``, so ``gammas[..., t, :] = γ_{t+1}`` and
``flags[..., t] = l_{t+1}``.

Every attack here runs inside the loop of :mod:`difffilter.loop` (the attack interface is
:mod:`difffilter.attack`): those that read nothing are tabulated for the whole batch when
the loop starts (:class:`~difffilter.attack.TabulatedAttack`), :class:`Replay` reads the
true measurement step by step (it lives in the threat library, :mod:`difffilter.threats`,
and is re-exported here).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Iterable
from dataclasses import dataclass

import torch
from torch import Tensor

from difffilter._checks import check_finite_number
from difffilter.attack import Channel, TabulatedAttack
from difffilter.threats import Replay

from .schedules import check_groups_cover


def _numbers(values, name: str, want: str) -> tuple[float, ...]:
    """``values`` (a number, or a sequence of numbers) as a tuple of finite floats;
    ``ValueError`` naming ``name`` and ``want`` otherwise (strings, booleans, NaN)."""
    items = values if isinstance(values, (list, tuple)) else (values,)
    try:
        out = tuple(check_finite_number(v, name) for v in items)
    except (TypeError, ValueError):
        out = ()
    if not out:
        raise ValueError(f"{name} must be {want}; got {values!r}")
    return out


__all__ = [
    "BiasAttack",
    "SensorBias",
    "ActuatorInjection",
    "Replacement",
    "Signal",
    "Replay",
]


@dataclass(frozen=True)
class SensorBias(TabulatedAttack):
    """The bias FDI attack of eqs (3)–(4), on the sensor channel: ``values[t] = γ_{t+1}``
    (eq. 4), ``flags ~ Bernoulli(p_l)`` (eq. 3), and the loop adds ``l_k γ_k`` to the
    measurement.

    Args:
        gamma_bar: steady-state bias ``γ̄`` (``dy`` numbers).
        tau: convergence factor ``τ ∈ (0, 1)`` of eq. (4).
        p_l: probability ``p_l ∈ [0, 1]`` that a packet is attacked (eq. 3).
    """

    gamma_bar: tuple[float, ...]
    tau: float = 0.9
    p_l: float = 0.5
    channel = Channel.SENSOR

    def __post_init__(self):
        # numbers, checked here: a quoted '0.9' (YAML) or a bare 0.3 had passed, to fail at
        # the first draw in torch's or Python's words (a trial); one number is one entry
        gb = _numbers(self.gamma_bar, "gamma_bar", "a non-empty sequence of finite numbers")
        object.__setattr__(self, "gamma_bar", gb)
        tau, p_l = check_finite_number(self.tau, "tau"), check_finite_number(self.p_l, "p_l")
        if not 0.0 < tau < 1.0:
            raise ValueError(f"tau must lie in (0, 1) (eq. 4); got {self.tau!r}")
        if not 0.0 <= p_l <= 1.0:
            raise ValueError(f"p_l must lie in [0, 1] (a Bernoulli probability); got {self.p_l!r}")
        object.__setattr__(self, "tau", tau)
        object.__setattr__(self, "p_l", p_l)

    @property
    def dim(self) -> int:
        """Measurement dimension ``dy``."""
        return len(self.gamma_bar)

    def values(self, num_steps: int, *, dtype=torch.float64, device=None) -> Tensor:
        """``γ_1 … γ_T`` of eq. (4) by the recursion itself, ``[T, dy]``.

        The recursion runs in float64 and is cast at the end, so it equals the closed
        form ``(1 − τ^k) γ̄`` to round-off in any dtype.
        """
        if isinstance(num_steps, bool) or not isinstance(num_steps, int) or num_steps < 1:
            raise ValueError(f"num_steps must be an integer >= 1; got {num_steps!r}")
        gamma_bar = torch.tensor(self.gamma_bar, dtype=torch.float64)
        gamma = torch.zeros_like(gamma_bar)  # γ_0 = 0
        out = []
        for _ in range(num_steps):
            gamma = self.tau * gamma + (1.0 - self.tau) * gamma_bar
            out.append(gamma)
        return torch.stack(out).to(dtype=dtype, device=device)

    def sample_flags(
        self, batch_shape, num_steps: int, generator: torch.Generator | None = None, *, device=None
    ) -> Tensor:
        """Bernoulli flags ``l_1 … l_T`` ``[*batch_shape, T]`` (bool) from ``generator``.

        ``l_k = 1`` iff ``u_k < p_l`` with ``u_k ~ U[0, 1)`` drawn in float64, so the same
        generator state gives nested attack sets for increasing ``p_l``.
        """
        if isinstance(num_steps, bool) or not isinstance(num_steps, int) or num_steps < 1:
            raise ValueError(f"num_steps must be an integer >= 1; got {num_steps!r}")
        shape = torch.Size((batch_shape,) if isinstance(batch_shape, int) else batch_shape)
        u = torch.rand(
            shape + (num_steps,), generator=generator, dtype=torch.float64, device=device
        )
        return u < self.p_l

    def sample(self, batch_shape, num_steps, dim, generator=None, *, dtype, device=None):
        if dim != self.dim:
            raise ValueError(f"gamma_bar has {self.dim} entries but the measurement has {dim}")
        flags = self.sample_flags(batch_shape, num_steps, generator, device=device)
        values = self.values(num_steps, dtype=dtype, device=device)
        return values.expand(flags.shape + (dim,)), flags


#: The name the four-tank paper's attack had before it joined the loop (the same class).
BiasAttack = SensorBias


# ------------------------------------------------------------------ the attacks in the loop
#
# A tabulated attack has ``channel`` (:class:`difffilter.attack.Channel`) and
# ``sample(batch_shape, T, dim, generator, dtype=, device=) -> (values [*, T, dim],
# flags [*, T])``: ``values`` are what the attacker would inject at every step, ``flags``
# where it does; the loop applies them on the channel (:func:`difffilter.attack.inject`).


def _check_steps(num_steps) -> None:
    if isinstance(num_steps, bool) or not isinstance(num_steps, int) or num_steps < 1:
        raise ValueError(f"num_steps must be an integer >= 1; got {num_steps!r}")


@dataclass(frozen=True)
class ActuatorInjection(TabulatedAttack):
    """A constant false input ``a`` added to the applied control from step ``start`` on.

    ``u_applied,k = u_k + a`` for ``k ≥ start`` (0-based index of ``u_k``); the estimator
    knows only the commanded ``u_k``. ``values [*, T, du]`` is ``a`` at every step.

    Args:
        value: ``a`` (``du`` numbers; a number alone for ``du = 1``).
        start: first attacked step index (``0 ≤ start``).
    """

    value: tuple[float, ...]
    start: int = 0
    channel = Channel.ACTUATOR

    def __post_init__(self):
        # a number alone is one value, of a plant with one input (it failed as "'float'
        # object is not iterable", a YAML scenario's trial)
        # (a string had been split into its characters: "20" → (2, 0); booleans taken)
        value = self.value
        if not isinstance(value, (str, bytes, numbers.Real)) and isinstance(value, Iterable):
            value = tuple(value)  # a tensor's or an array's entries
        v = _numbers(value, "value", "a non-empty sequence of finite numbers")
        if isinstance(self.start, bool) or not isinstance(self.start, int) or self.start < 0:
            raise ValueError(f"start must be an integer >= 0; got {self.start!r}")
        object.__setattr__(self, "value", v)

    def sample(self, batch_shape, num_steps, dim, generator=None, *, dtype, device=None):
        _check_steps(num_steps)
        if len(self.value) != dim:  # (one number is not spread over several inputs)
            raise ValueError(f"value has {len(self.value)} entries but the input has {dim}")
        shape = torch.Size((batch_shape,) if isinstance(batch_shape, int) else batch_shape)
        flags = (torch.arange(num_steps, device=device) >= self.start).expand(shape + (num_steps,))
        values = torch.tensor(self.value, dtype=dtype, device=device)
        return values.expand(flags.shape + (dim,)), flags


@dataclass(frozen=True)
class Replacement(TabulatedAttack):
    """Deception by replacement: with probability ``rate`` per step the received
    measurement is replaced by ``ξ_k ~ U(low, high)`` (the RRP paper, eqs 4–6).

    ``values [*, T, dy]`` holds the draws ``ξ_k``; on the replacement channel the loop
    delivers ``ξ_k`` where flagged and ``y_k`` elsewhere (and records ``ξ_k − y_k``).
    """

    rate: float
    low: tuple[float, ...]
    high: tuple[float, ...]
    channel = Channel.REPLACEMENT

    def __post_init__(self):
        rate = check_finite_number(self.rate, "rate")  # (a quoted '0.1' failed at the first draw)
        if not 0.0 <= rate <= 1.0:
            raise ValueError(f"rate must lie in [0, 1] (a probability); got {self.rate!r}")
        object.__setattr__(self, "rate", rate)
        want = "lists of finite numbers, one bound per entry (finite boxes, low < high)"
        lo, hi = _numbers(self.low, "low", want), _numbers(self.high, "high", want)
        # finite: U(−∞, ∞) drew NaN measurements (a review), as SensorBias and
        # ActuatorInjection refuse non-finite values
        if (len(lo) != len(hi) or not lo or not all(a < b for a, b in zip(lo, hi))
                or not all(math.isfinite(v) for v in lo + hi)):  # fmt: skip
            raise ValueError(
                f"low and high must be equal-length finite boxes with low < high; got {lo}, {hi}"
            )
        object.__setattr__(self, "low", lo)
        object.__setattr__(self, "high", hi)

    def sample(self, batch_shape, num_steps, dim, generator=None, *, dtype, device=None):
        _check_steps(num_steps)
        if dim != len(self.low):
            raise ValueError(f"the box has {len(self.low)} entries but the measurement has {dim}")
        shape = torch.Size((batch_shape,) if isinstance(batch_shape, int) else batch_shape)
        u = torch.rand(
            shape + (num_steps,), generator=generator, dtype=torch.float64, device=device
        )
        lo = torch.tensor(self.low, dtype=dtype, device=device)
        hi = torch.tensor(self.high, dtype=dtype, device=device)
        box = torch.rand(shape + (num_steps, dim), generator=generator, dtype=dtype, device=device)
        return lo + (hi - lo) * box, u < self.rate

    def sample_groups(
        self, batch_shape, num_steps, groups, generator=None, *, dtype, device=None
    ) -> tuple[Tensor, Tensor]:
        """Independent attacks per sensor group (each group's packet replaced at ``rate``).

        ``groups``: the measurement entries of each sensor (as in
        :class:`~difffilter.models.schedules.RoundRobin`). Returns ``values [*, T, dy]``
        (the ``ξ`` draws, as :meth:`sample`) and ``flags [*, T, G]`` (bool, one Bernoulli
        per group and step); draws the uniforms of the flags first, then the box, from
        ``generator``. Apply with :meth:`inject_groups`.
        """
        _check_steps(num_steps)
        dim = len(self.low)
        # (as the schedules require: a group list of another box drew flags of no entry, one
        # that skipped an entry gave it to group 0, one past the box raised an IndexError)
        check_groups_cover(groups, dim, "groups")
        shape = torch.Size((batch_shape,) if isinstance(batch_shape, int) else batch_shape)
        u = torch.rand(
            shape + (num_steps, len(groups)),
            generator=generator,
            dtype=torch.float64,
            device=device,
        )
        lo = torch.tensor(self.low, dtype=dtype, device=device)
        hi = torch.tensor(self.high, dtype=dtype, device=device)
        box = torch.rand(shape + (num_steps, dim), generator=generator, dtype=dtype, device=device)
        return lo + (hi - lo) * box, u < self.rate

    @staticmethod
    def entry_flags(flags: Tensor, groups) -> Tensor:
        """Group flags ``[*, T, G]`` → entry flags ``[*, T, dy]`` (each entry its group's flag)."""
        check_groups_cover(groups, sum(len(g) for g in groups), "groups")
        owner = [0] * sum(len(g) for g in groups)
        for j, g in enumerate(groups):
            for i in g:
                owner[i] = j
        return flags[..., torch.tensor(owner, device=flags.device)]

    def inject_groups(self, signal: Tensor, values: Tensor, flags: Tensor, groups) -> Tensor:
        """``signal [*, T, dy]`` with each flagged group's entries replaced by ``values``."""
        return torch.where(self.entry_flags(flags, groups), values, signal)


class Signal(TabulatedAttack):
    """A known, deterministic attack signal: ``values [T, dim]`` (the same for every run)
    or ``[B, T, dim]`` (one per run), ``a_k = values[..., k − 1, :]``, flagged entry by
    entry where it is non-zero, on ``channel`` (default the sensor channel).

    The LFC scenarios' attacks (steps, sinusoids, sawtooth pulse trains of eqs 44–47)
    are such signals, and so are the random attacks the LFC estimator is trained on.
    """

    def __init__(self, values: Tensor, channel: Channel = Channel.SENSOR):
        if not isinstance(values, Tensor) or values.dim() not in (2, 3):
            raise ValueError(
                f"values must be a tensor [T, dim] or [B, T, dim]; got "
                f"{getattr(values, 'shape', values)!r}"
            )
        if not bool(torch.isfinite(values).all()):
            raise ValueError("values must be finite")
        self.values, self.channel = values, Channel(channel)

    def sample(self, batch_shape, num_steps, dim, generator=None, *, dtype, device=None):
        _check_steps(num_steps)
        shape = torch.Size((batch_shape,) if isinstance(batch_shape, int) else batch_shape)
        # a value per step and entry, exactly: a [1, dim] signal or a [T, 1] one would
        # broadcast to a constant attack or onto every entry, which nobody meant; the batch
        # dimensions may broadcast (one signal for every run)
        if tuple(self.values.shape[-2:]) != (num_steps, dim):
            raise self._shape_error(shape, num_steps, dim)
        try:
            values = self.values.to(dtype=dtype, device=device).expand(shape + (num_steps, dim))
        except RuntimeError:
            raise self._shape_error(shape, num_steps, dim) from None
        # flagged entry by entry: under a schedule a step whose attacked entries were all
        # lost is attack-free for the estimator (one flag per step had labelled a Round-Robin
        # step that received only clean entries as attacked: a red-team trial)
        return values, values != 0

    def _shape_error(self, shape: torch.Size, num_steps: int, dim: int) -> ValueError:
        return ValueError(
            f"the signal has shape {tuple(self.values.shape)}; the loop needs "
            f"[{num_steps}, {dim}] or {list(shape) + [num_steps, dim]}"
        )
