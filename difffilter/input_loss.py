"""Packet loss between the controller and the actuators of a closed loop.

In a networked control system the input ``u_{k−1}`` travels to the actuators over a network
of its own, and its packet may be lost (Schenato, Sinopoli, Franceschetti, Poolla & Sastry,
"Foundations of control and estimation over lossy networks", Proc. IEEE 95(1), 2007). With
``ν_k ∈ {0, 1}`` the arrival of the packet that drives the transition into ``x_k`` (per run,
or per actuator)::

    ū_{k−1} = ν_k (u_{k−1} + l_k a_k) + (1 − ν_k) ū_{k−2}     (the actuator holds: HOLD)
    ū_{k−1} = ν_k (u_{k−1} + l_k a_k)                         (it applies zero: ZERO)
    x_k     = f(x_{k−1}, ū_{k−1}) + w_k                        (ū_{−1} = 0)

with ``a_k`` an actuator attack, injected into the packet: lost with it, and held with it
(the actuators that hold keep applying the attack they last received: the loop records
that attack, ``ū − û`` of the held inputs, as the step's). What the estimator knows of
``ū`` depends on the protocol:

* **acknowledged** (TCP-like): the actuator acknowledges each packet, so the estimator
  steps with ``û_{k−1} = ν_k u_{k−1} + (1 − ν_k) û_{k−2}`` (HOLD) or ``ν_k u_{k−1}`` (ZERO):
  the applied input as far as it can know it (exactly ``ū`` without an attack). A Kalman
  filter on that input is then the optimal estimator, as without loss.
* **unacknowledged** (UDP-like): the estimator steps with the sent ``u_{k−1}``, unaware of
  the loss: where a packet is lost the plant moved under another input than the model's.
  Schenato et al.'s UDP-like estimator, for ``ZERO``, knows the arrival rate ``ν̄`` and
  predicts with ``ν̄ B u`` and ``P⁻ + ν̄(1 − ν̄) B u uᵀ Bᵀ``:
  :class:`~difffilter.expected_input.ExpectedInputKalmanFilter`, given the sent ``u``
  (with ``on_loss="hold"``, the same estimator of the state and the held input).

:class:`InputLoss` is that channel, given to :func:`difffilter.loop.closed_loop` as
``input_loss=``; ``mask`` says which packets arrived, e.g. from
:class:`~difffilter.models.schedules.PacketLoss` or
:class:`~difffilter.models.schedules.BurstLoss` with ``dim = du`` (one packet per
actuator) or ``dim = 1`` (one packet for all: ``[B, T, 1]`` is taken as ``[B, T]``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import torch
from torch import Tensor

from ._checks import Choice

__all__ = ["InputLoss", "InputLossSchedule", "OnLoss", "Delivery", "InputMemory"]


class OnLoss(Choice):
    """What an actuator applies when its input packet is lost: its last applied input
    (``HOLD``, zero before the first one arrived) or zero (``ZERO``)."""

    HOLD = "hold"
    ZERO = "zero"


def on_loss_of(value) -> OnLoss:
    """``OnLoss(value)``, its error naming the argument ``on_loss``."""
    try:
        return OnLoss(value)
    except ValueError as error:
        raise ValueError(f"on_loss: {error}") from None


class InputMemory(NamedTuple):
    """What the input channel remembers between steps under ``HOLD`` (each ``[B, du]``): the
    input the actuators apply (``held``), the estimator's knowledge of it (``known_held``:
    the sent inputs that arrived, kept whether or not the estimator is told, so that a
    loop resumed acknowledged goes on from it), and the attack in it (``attack``, and
    ``held_attack``: bool, where the held input carries one): a held input keeps its
    attack."""

    held: Tensor
    known_held: Tensor
    attack: Tensor
    held_attack: Tensor


class Delivery(NamedTuple):
    """One step of the input channel: ``applied`` ``ū_{k−1} [B, du]`` (what drives the
    plant), ``known`` (what the estimator steps with), ``arrived`` ``ν_k`` ``[B, du]``
    (bool), ``attack`` (the attack in ``applied``: ``ū − u`` of the inputs held, zero where
    none; ``None`` without an attack), ``acting`` (bool ``[B, du]``, ``None`` without an
    attack: the attack's own flags, lost packet or not (the plant still carries what it
    injected before), and where a held input carries it beyond them) and the
    :class:`InputMemory` of the next step (``None`` under ``ZERO``)."""

    applied: Tensor
    known: Tensor
    arrived: Tensor
    attack: Tensor | None
    acting: Tensor | None
    memory: InputMemory | None


class InputLoss:
    """Loss of the input packets of a closed loop (module docstring).

    Args:
        mask: ``ν`` ``[B, T]`` (one packet per run and step: every actuator at once) or
            ``[B, T, du]`` (one per actuator), bool, ``True`` where the packet arrived;
            indexed by the absolute step: ``mask[:, k − 1]`` is the arrival of ``u_{k−1}``,
            the input of the transition into ``x_k``.
        on_loss: :class:`OnLoss` (or its name): ``"hold"`` (default) or ``"zero"``.
        acknowledged: ``True`` (default, TCP-like): the estimator steps with the input the
            actuator applied as far as the acknowledgements tell (the attack unseen);
            ``False`` (UDP-like): with the input sent.

    The loop records the estimator's input as ``Trajectories.us``, the controller's as
    ``info["inputs_sent"]``, what drove the plant as ``info["inputs_applied"]`` and the
    arrivals as ``info["input_mask"]`` ``[B, T, du]``. An actuator attack's ``attack`` is the
    attack in the applied input (zero where its packet was lost and the actuators apply
    zero, the held one where they hold); its ``flags`` are its own steps, lost packet or not
    (the plant carries what it injected before: a networked-control trial's study under
    ``"zero"`` had counted 102 attacks in 24 attacked runs, with false alarms in their
    gaps), and, under ``"hold"``, the steps after them where a held input still carries it.
    A covert attack's concealment assumes its packets arrive, so a loop refuses one under
    input loss.
    """

    def __init__(self, mask: Tensor, on_loss: OnLoss | str = OnLoss.HOLD, *,
                 acknowledged: bool = True):  # fmt: skip
        if not isinstance(mask, Tensor) or mask.dtype is not torch.bool:
            got = f"dtype {mask.dtype}" if isinstance(mask, Tensor) else type(mask).__name__
            raise ValueError(
                f"InputLoss's mask must be a bool tensor [B, T] or [B, T, du] (True where the "
                f"input packet arrived); got {got}"
            )
        if mask.dim() not in (2, 3):
            raise ValueError(
                f"InputLoss's mask must be [B, T] (one packet per step) or [B, T, du] (one per "
                f"actuator); got {tuple(mask.shape)}"
            )
        if mask.dim() == 3 and mask.shape[-1] == 1:  # one link: a schedule's mask(…, dim=1)
            mask = mask[..., 0]
        if not isinstance(acknowledged, bool):
            raise ValueError(f"acknowledged must be True or False; got {acknowledged!r}")
        self.mask, self.on_loss, self.acknowledged = mask, on_loss_of(on_loss), acknowledged

    def check(self, runs: int, du: int, end: int) -> None:
        """``ValueError`` unless the mask covers the loop's ``runs`` and steps ``1 … end`` and
        fits the plant's ``du`` inputs (``du = 0``: a plant without input has no packet)."""
        mask = self.mask
        if du == 0:
            raise ValueError(
                "input_loss: this loop has no input to lose (no controller, or a plant with "
                "dim_u = 0): give it a controller, or drop input_loss"
            )
        width = "" if mask.dim() == 2 else f", {du}"
        if (
            mask.shape[0] != runs
            or mask.shape[1] < end
            or (mask.dim() == 3 and mask.shape[2] != du)
        ):
            raise ValueError(
                f"InputLoss's mask must be [{runs}, T >= {end}{width}] (the runs, a row for every "
                f"step up to {end}, indexed by the absolute step"
                + ("" if mask.dim() == 2 else ", the plant's dim_u")
                + f"); got {tuple(mask.shape)}"
            )

    def start(self, u0: Tensor) -> InputMemory | None:
        """The memory before step 1 (``ū_{−1} = 0``, no attack; ``None`` under ``ZERO``,
        which keeps none)."""
        if self.on_loss is OnLoss.ZERO:
            return None
        zero = torch.zeros_like(u0)
        return InputMemory(zero, zero, zero, torch.zeros_like(u0, dtype=torch.bool))

    def deliver(self, k: int, sent: Tensor, attack: Tensor | None, flag: Tensor | None,
                memory: InputMemory | None) -> Delivery:  # fmt: skip
        """Step ``k``: ``sent`` is the controller's ``u_{k−1} [B, du]``, ``attack`` the value
        an actuator attack injects into its packet (``[B, du]``, zero where it does not act)
        and ``flag`` its flag (``[B]`` or ``[B, du]``), or both ``None``; ``memory`` that of
        step ``k − 1``."""
        arrived = self.mask[:, k - 1]
        arrived = arrived.unsqueeze(-1).expand_as(sent) if arrived.shape != sent.shape else arrived
        own = None
        if flag is not None:
            own = flag.unsqueeze(-1).expand_as(sent) if flag.shape != sent.shape else flag
        attempted = sent if attack is None else sent + attack
        if self.on_loss is OnLoss.HOLD:
            applied = torch.where(arrived, attempted, memory.held)
            known_held = torch.where(arrived, sent, memory.known_held)
            held_attack, carried = memory.attack, memory.held_attack
            if attack is not None:
                held_attack = torch.where(arrived, attack, memory.attack)
                carried = torch.where(arrived, own, memory.held_attack)
            memory = InputMemory(applied, known_held, held_attack, carried)
            known = known_held if self.acknowledged else sent
            if attack is None:
                return Delivery(applied, known, arrived, None, None, memory)
            return Delivery(applied, known, arrived, held_attack, own | carried, memory)
        zero = torch.zeros((), dtype=sent.dtype, device=sent.device)
        applied = torch.where(arrived, attempted, zero)
        known = torch.where(arrived, sent, zero) if self.acknowledged else sent
        if attack is not None:
            attack = torch.where(arrived, attack, zero)
        return Delivery(applied, known, arrived, attack, own, None)

    def __repr__(self) -> str:
        return (f"InputLoss(mask {tuple(self.mask.shape)}, on_loss={self.on_loss.value!r}, "
                f"acknowledged={self.acknowledged})")  # fmt: skip


@dataclass(frozen=True)
class InputLossSchedule:
    """A random input channel, drawn afresh for each study: the arrivals of the ``du``
    actuators' packets from ``schedule`` (an object with ``mask(batch_shape, num_steps, dim,
    generator, device=)``, e.g. :class:`~difffilter.models.schedules.PacketLoss`, whose
    ``packets`` send actuators together, or
    :class:`~difffilter.models.schedules.BurstLoss`), with ``on_loss`` and ``acknowledged``
    as in :class:`InputLoss`. A scenario's ``input_loss`` (YAML ``input_loss:``)."""

    schedule: Any
    on_loss: OnLoss | str = OnLoss.HOLD
    acknowledged: bool = True

    def __post_init__(self):
        if not callable(getattr(self.schedule, "mask", None)):
            raise TypeError(
                "InputLossSchedule's schedule must have mask(batch_shape, num_steps, dim, "
                "generator, device=) (e.g. difffilter.models.schedules.PacketLoss(0.1)); got "
                f"{type(self.schedule).__name__}"
            )
        object.__setattr__(self, "on_loss", on_loss_of(self.on_loss))
        if not isinstance(self.acknowledged, bool):
            raise ValueError(f"acknowledged must be True or False; got {self.acknowledged!r}")

    def draw(self, runs: int, steps: int, du: int, generator=None, *, device=None) -> InputLoss:
        """The :class:`InputLoss` of ``runs`` runs of ``steps`` steps (``mask [runs, steps,
        du]``) from ``generator``."""
        try:
            mask = self.schedule.mask((runs,), steps, du, generator, device=device)
        except (ValueError, IndexError) as error:  # (the schedule speaks of measurements:
            # "packets must cover the 1 measurement entries" for a plant of 2 sensors, 1 input)
            raise type(error)(f"input_loss: {error} (its entries here are the plant's {du} "
                              "input(s), not its measurements)") from error  # fmt: skip
        if mask is None:  # a schedule's "every entry arrives" (AllSensors: it had failed at
            # every simulation, in InputLoss's check, naming neither)
            mask = torch.ones(runs, steps, du, dtype=torch.bool, device=device)
        return InputLoss(mask, self.on_loss, acknowledged=self.acknowledged)
