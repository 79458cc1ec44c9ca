"""Packet loss between the controller and the actuators of a closed loop.

In a networked control system the input ``u_{k−1}`` travels to the actuators over a network
of its own, and its packet may be lost (Schenato, Sinopoli, Franceschetti, Poolla & Sastry,
"Foundations of control and estimation over lossy networks", Proc. IEEE 95(1), 2007). With
``ν_k ∈ {0, 1}`` the arrival of the packet that drives the transition into ``x_k`` (per run,
or per actuator)::

    ū_{k−1} = ν_k (u_{k−1} + l_k a_k) + (1 − ν_k) ū_{k−2}     (the actuator holds: HOLD)
    ū_{k−1} = ν_k (u_{k−1} + l_k a_k)                         (it applies zero: ZERO)
    x_k     = f(x_{k−1}, ū_{k−1}) + w_k                        (ū_{−1} = 0)

with ``a_k`` an actuator attack (injected into the packet, so lost with it). What the
estimator knows of ``ū`` depends on the protocol:

* **acknowledged** (TCP-like): the actuator acknowledges each packet, so the estimator
  steps with ``û_{k−1} = ν_k u_{k−1} + (1 − ν_k) û_{k−2}`` (HOLD) or ``ν_k u_{k−1}`` (ZERO):
  the applied input as far as it can know it (exactly ``ū`` without an attack). A Kalman
  filter on that input is then the optimal estimator, as without loss.
* **unacknowledged** (UDP-like): the estimator steps with the sent ``u_{k−1}``, unaware of
  the loss: where a packet is lost the plant moved under another input than the model's.

:class:`InputLoss` is that channel, given to :func:`difffilter.loop.closed_loop` as
``input_loss=``; ``mask`` says which packets arrived, e.g. from
:class:`~difffilter.models.schedules.PacketLoss` or
:class:`~difffilter.models.schedules.BurstLoss` with ``dim = du`` (one packet per
actuator) or ``dim = 1`` (one packet for all).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from ._checks import Choice

__all__ = ["InputLoss", "OnLoss", "Delivery"]


class OnLoss(Choice):
    """What an actuator applies when its input packet is lost: its last applied input
    (``HOLD``, zero before the first one arrived) or zero (``ZERO``)."""

    HOLD = "hold"
    ZERO = "zero"


class Delivery(NamedTuple):
    """One step of the input channel: ``applied`` ``ū_{k−1} [B, du]`` (what drives the
    plant), ``known`` (what the estimator steps with), ``arrived`` ``ν_k`` ``[B, du]``
    (bool) and the actuator's and the estimator's memories for the next step (``None``
    under ``ZERO``)."""

    applied: Tensor
    known: Tensor
    arrived: Tensor
    held: Tensor | None
    known_held: Tensor | None


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

    The loop records the estimator's input as ``Trajectories.us``, what drove the plant as
    ``info["inputs_applied"]`` and the arrivals as ``info["input_mask"]`` ``[B, T, du]``; an
    actuator attack on a lost packet is no attack (zero in ``attack``, unflagged).
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
        if not isinstance(acknowledged, bool):
            raise ValueError(f"acknowledged must be True or False; got {acknowledged!r}")
        self.mask, self.on_loss, self.acknowledged = mask, OnLoss(on_loss), acknowledged

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

    def start(self, u0: Tensor) -> tuple[Tensor | None, Tensor | None]:
        """The actuator's and the estimator's memories before step 1 (``ū_{−1} = 0``;
        ``None`` under ``ZERO``, which keeps none)."""
        if self.on_loss is OnLoss.ZERO:
            return None, None
        zero = torch.zeros_like(u0)
        return zero, zero

    def deliver(self, k: int, attempted: Tensor, sent: Tensor, held: Tensor | None,
                known_held: Tensor | None) -> Delivery:  # fmt: skip
        """Step ``k``: ``attempted`` ``[B, du]`` is the packet's content (``u_{k−1}``, plus
        the attack where one acts on the actuators), ``sent`` the controller's ``u_{k−1}``;
        ``held`` and ``known_held`` the memories of step ``k − 1``."""
        arrived = self.mask[:, k - 1]
        arrived = arrived.unsqueeze(-1).expand_as(sent) if arrived.dim() == 1 else arrived
        if self.on_loss is OnLoss.HOLD:
            applied = torch.where(arrived, attempted, held)
            known = torch.where(arrived, sent, known_held) if self.acknowledged else sent
            return Delivery(applied, known, arrived, applied, known if self.acknowledged
                            else known_held)  # fmt: skip
        zero = torch.zeros((), dtype=sent.dtype, device=sent.device)
        applied = torch.where(arrived, attempted, zero)
        known = torch.where(arrived, sent, zero) if self.acknowledged else sent
        return Delivery(applied, known, arrived, None, None)

    def __repr__(self) -> str:
        return (f"InputLoss(mask {tuple(self.mask.shape)}, on_loss={self.on_loss.value!r}, "
                f"acknowledged={self.acknowledged})")  # fmt: skip
