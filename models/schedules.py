"""Communication schedules: which measurement entries reach the estimator at each step.

A schedule turns ``(batch_shape, T, dy)`` into a received-entries mask ``[*, T, dy]``
(bool) or ``None`` when everything is received; every filter of the library takes that
mask and removes the unreceived entries exactly.

* :class:`AllSensors` — every entry at every step (``None``);
* :class:`RoundRobin` — sensor group ``(k − 1 + start) mod n`` (0-based) at step ``k`` (the RRP paper, eq. 3);
* :class:`PacketLoss` — each entry (or each packet of entries sent together) lost
  independently with probability ``rate``;
* :class:`BurstLoss` — losses that come in bursts: the Gilbert–Elliott channel, a
  two-state Markov chain per link (good, bad) with a loss probability in each state.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["AllSensors", "RoundRobin", "PacketLoss", "BurstLoss"]


def _entry_groups(groups, name: str) -> tuple[tuple[int, ...], ...]:
    """``groups`` as disjoint, non-empty tuples of entry indices (integers ``>= 0``): a float
    (1.7), a bool or a string had been cast to an index silently, a flat list failed with
    "'int' object is not iterable"."""

    def bad(why: str):
        return ValueError(f"{name} must be non-empty, disjoint groups (lists) of entry indices "
                          f"(integers >= 0), e.g. [[0, 1], [2]]: {why}; got {groups!r}")  # fmt: skip

    if isinstance(groups, (str, bytes)) or not isinstance(groups, (list, tuple)) or not groups:
        raise bad("not a list of groups")
    out, seen = [], set()
    for group in groups:
        if isinstance(group, (str, bytes)) or not isinstance(group, (list, tuple)) or not group:
            raise bad(f"the group {group!r} is not a non-empty list")
        for i in group:
            if isinstance(i, bool) or not isinstance(i, numbers.Integral) or i < 0:
                raise bad(f"the entry {i!r} is not an integer >= 0")
            if i in seen:
                raise bad(f"the entry {i} is in two groups")
            seen.add(int(i))
        out.append(tuple(int(i) for i in group))
    return tuple(out)


def check_groups_cover(groups, dim: int, name: str) -> None:
    """``ValueError`` naming ``name`` unless the ``groups`` (lists of measurement entries) hold
    the ``dim`` entries exactly once each (the schedules' groups and packets, the papers'
    replacement attack's sensor groups)."""
    if sorted(int(i) for g in groups for i in g) != list(range(dim)):
        raise ValueError(
            f"{name} must cover the {dim} measurement entries exactly once; got {groups!r}"
        )


def _membership(groups, dim: int, name: str, device) -> Tensor:
    """``[G, dim]`` bool: which of the ``dim`` measurement entries each group holds; every
    entry in exactly one group."""
    check_groups_cover(groups, dim, name)
    table = torch.zeros(len(groups), dim, dtype=torch.bool, device=device)
    for j, g in enumerate(groups):
        table[j, list(g)] = True
    return table


def _shape(batch_shape) -> torch.Size:
    return torch.Size((batch_shape,) if isinstance(batch_shape, int) else batch_shape)


@dataclass(frozen=True)
class AllSensors:
    """Every entry is received at every step: the mask is ``None``."""

    def mask(self, batch_shape, num_steps: int, dim: int, generator=None, *, device=None):
        return None


@dataclass(frozen=True)
class RoundRobin:
    """Round-Robin scheduling: at step ``k`` (1-based) only group ``(k − 1 + start) mod n`` transmits.

    Eq. (3) of the RRP paper, ``γ_k = mod(k + γ_ini − 2, n) + 1``, with ``start = γ_ini − 1``.

    Args:
        groups: the measurement entries of each group, e.g. ``((0, 1), (2, 3))`` for two
            range-bearing sensors; every entry must belong to exactly one group.
        start: the (0-based) group granted access at ``k = 1`` (default 0).
    """

    groups: tuple[tuple[int, ...], ...]
    start: int = 0

    def __post_init__(self):
        object.__setattr__(self, "groups", _entry_groups(self.groups, "groups"))
        n = len(self.groups)
        # a group's index, 0 … n − 1: a 1-based γ_ini of 2 over two groups had wrapped to
        # group 0 unsaid (numpy's integers taken, as in groups)
        if (isinstance(self.start, bool) or not isinstance(self.start, numbers.Integral)
                or not 0 <= self.start < n):  # fmt: skip
            raise ValueError(f"start must be the 0-based index of a group, 0 … {n - 1} (γ_ini − 1, "
                             f"γ_ini the paper's 1-based one); got {self.start!r}")  # fmt: skip
        object.__setattr__(self, "start", int(self.start))

    def scheduled(self, num_steps: int, *, device=None) -> Tensor:
        """The (0-based) group transmitting at each step ``k = 1 … T``, ``[T]`` (long)."""
        return (torch.arange(num_steps, device=device) + self.start) % len(self.groups)

    def mask(self, batch_shape, num_steps: int, dim: int, generator=None, *, device=None):
        table = _membership(self.groups, dim, "groups", device)
        return table[self.scheduled(num_steps, device=device)].expand(
            _shape(batch_shape) + (num_steps, dim)
        )


@dataclass(frozen=True)
class PacketLoss:
    """Each measurement entry is lost independently with probability ``rate`` (Bernoulli),
    or, with ``packets``, each packet: the entries a sensor sends together (e.g.
    ``((0, 1), (2, 3))`` for two range-bearing sensors) are lost together, one draw per
    packet and step; every entry must belong to exactly one packet."""

    rate: float
    packets: tuple[tuple[int, ...], ...] | None = None

    def __post_init__(self):
        rate = self.rate  # a number: a string passed float() here and failed in mask()
        if isinstance(rate, bool) or not isinstance(rate, numbers.Real) or not 0.0 <= rate < 1.0:
            raise ValueError(f"rate must be a number in [0, 1); got {self.rate!r}")
        if self.packets is not None:
            object.__setattr__(self, "packets", _entry_groups(self.packets, "packets"))

    def mask(self, batch_shape, num_steps: int, dim: int, generator=None, *, device=None) -> Tensor:
        links, packet_of = _links(self.packets, dim, device)
        shape = _shape(batch_shape) + (num_steps, links)
        _seeded(generator, shape, "PacketLoss")
        arrived = (
            torch.rand(shape, generator=generator, dtype=torch.float64, device=device) >= self.rate
        )
        return arrived if packet_of is None else arrived[..., packet_of]


def _seeded(generator, shape, who: str) -> None:
    """Every random draw from a generator of its own: a loss schedule drawn without one had
    drawn from torch's global generator, silently (a trial: a scenario's input losses, two
    identical calls 0.038 apart in the state)."""
    if generator is None and math.prod(shape) > 0:
        raise ValueError(
            f"{who} draws its losses from generator: give one (a scenario's simulate reads "
            "'schedule' and 'input_schedule' from its generators: "
            "difffilter.models.streams.Streams(seed).simulation() holds both)"
        )


def _links(packets, dim: int, device) -> tuple[int, Tensor | None]:
    """``(links, packet_of)``: one link per entry (``packet_of`` ``None``), or one per packet
    with ``packet_of [dim]`` the packet each entry travels in."""
    if packets is None:
        return dim, None
    return len(packets), _membership(packets, dim, "packets", device).long().argmax(0)


def _probability(value, name: str, *, open_low: bool = False) -> float:
    """``value`` as a probability in ``[0, 1]`` (``(0, 1]`` with ``open_low``), else a
    ValueError naming ``name``."""
    interval = "(0, 1]" if open_low else "[0, 1]"
    number = not isinstance(value, bool) and isinstance(value, numbers.Real)
    if not number or not (0.0 < value <= 1.0 if open_low else 0.0 <= value <= 1.0):
        raise ValueError(f"{name} must be a probability in {interval}; got {value!r}")
    return float(value)


@dataclass(frozen=True)
class BurstLoss:
    """Losses in bursts: the Gilbert–Elliott channel, one per link (each measurement entry,
    or with ``packets`` each packet of entries sent together, as :class:`PacketLoss`).

    Each link is a Markov chain over two states, good ``G`` and bad ``B``, stepping before
    every measurement::

        P(B at k | G at k−1) = to_bad,   P(G at k | B at k−1) = to_good

    and a measurement is lost with probability ``loss_good`` in ``G``, ``loss_bad`` in ``B``
    (defaults 0 and 1: the simplified Gilbert channel, every loss in a burst). The chain starts in its
    stationary law, ``P(B) = π_B = to_bad / (to_bad + to_good)``, so the loss rate is the
    same at every step: ``π_B · loss_bad + (1 − π_B) · loss_good``; with the defaults a
    burst lasts ``1 / to_good`` steps on average (geometric) and a loss follows a loss with
    probability ``1 − to_good`` (against the rate itself for :class:`PacketLoss`). Every
    draw from ``generator``; runs and links independent; the time loop is the only loop.

    Args:
        to_bad: ``P(G → B)`` per step, in ``(0, 1]``.
        to_good: ``P(B → G)`` per step, in ``(0, 1]``.
        loss_good, loss_bad: the loss probability in each state, in ``[0, 1]``, with
            ``loss_good < 1`` (some measurement must get through).
        packets: the entries sent together, e.g. ``((0, 1), (2, 3))`` (default: each entry
            its own link).
    """

    to_bad: float
    to_good: float
    loss_good: float = 0.0
    loss_bad: float = 1.0
    packets: tuple[tuple[int, ...], ...] | None = None

    def __post_init__(self):
        _probability(self.to_bad, "to_bad", open_low=True)
        _probability(self.to_good, "to_good", open_low=True)
        _probability(self.loss_good, "loss_good")
        _probability(self.loss_bad, "loss_bad")
        if self.loss_good >= 1.0:
            raise ValueError(
                f"loss_good must be below 1 (nothing would arrive); got {self.loss_good!r}"
            )
        if self.packets is not None:
            object.__setattr__(self, "packets", _entry_groups(self.packets, "packets"))

    @property
    def bad_share(self) -> float:
        """``π_B = to_bad / (to_bad + to_good)``: the stationary share of steps in ``B``."""
        return self.to_bad / (self.to_bad + self.to_good)

    @property
    def rate(self) -> float:
        """The stationary loss rate ``π_B · loss_bad + (1 − π_B) · loss_good``."""
        return self.bad_share * self.loss_bad + (1.0 - self.bad_share) * self.loss_good

    def mask(self, batch_shape, num_steps: int, dim: int, generator=None, *, device=None) -> Tensor:
        links, packet_of = _links(self.packets, dim, device)
        shape = _shape(batch_shape) + (num_steps, links)
        _seeded(generator, shape, "BurstLoss")
        # two uniforms per link and step: the chain's move, then the loss in its state
        move = torch.rand(shape, generator=generator, dtype=torch.float64, device=device)
        lose = torch.rand(shape, generator=generator, dtype=torch.float64, device=device)
        bad = torch.empty(shape, dtype=torch.bool, device=device)
        if num_steps == 0:  # (no step: an empty mask, as PacketLoss gives)
            return bad if packet_of is None else bad[..., packet_of]
        state = move[..., 0, :] < self.bad_share  # the stationary law at the first step
        bad[..., 0, :] = state
        for k in range(1, num_steps):
            u = move[..., k, :]
            state = torch.where(state, u >= self.to_good, u < self.to_bad)
            bad[..., k, :] = state
        loss = torch.where(bad, torch.tensor(self.loss_bad, dtype=torch.float64, device=device),
                           torch.tensor(self.loss_good, dtype=torch.float64, device=device))  # fmt: skip
        arrived = lose >= loss
        return arrived if packet_of is None else arrived[..., packet_of]
