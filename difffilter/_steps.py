"""Recording per-step values of a filter's time loop and stacking them along time."""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["StepRecorder"]


class StepRecorder:
    """Collects named tensors once per step; :meth:`stack` puts time after the batch dims.

    ``rec.add(mean=m, alarm=a)`` at every step, then ``rec.stack(len(batch))`` gives
    ``{"mean": [..., T, dx], "alarm": [..., T]}`` (time inserted at position
    ``batch_dims``, i.e. right after the leading batch dimensions).
    """

    def __init__(self):
        self._values: dict[str, list[Tensor]] = {}

    def add(self, **values: Tensor) -> None:
        for name, value in values.items():
            self._values.setdefault(name, []).append(value)

    def stack(self, batch_dims: int) -> dict[str, Tensor]:
        return {name: torch.stack(vals, dim=batch_dims) for name, vals in self._values.items()}
