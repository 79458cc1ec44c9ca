"""A process-wide count of the tensors and modules assigned to models and noise models.

A cache computed from a model (a Kalman filter's :class:`~difffilter.GainSchedule`) checks
the version counters of the tensors it read, which catches a tensor written in place but
not one replaced: ``model.F = new_F``, ``model.measurement_noise = Gaussian(…)`` or
``model.to(torch.float32)`` leave the old tensors as they were, and an online filter went
on with the old matrices without a word (a deployment trial). Every such assignment on a
:class:`~difffilter.StateSpaceModel` or a :class:`~difffilter.noise.NoiseModel` (and every
``_apply``: ``.to``, ``.double``, …) bumps this count; a cache compares it with the count
it was made at (one integer, on every step) and reads the model again only where it
moved (:meth:`difffilter.GainSchedule.current`).
"""

from __future__ import annotations

from torch import Tensor, nn

__all__ = ["CountsAssignments", "assignments"]

_COUNT = [0]


def assignments() -> int:
    """How many tensors and modules have been assigned to models so far (in this process)."""
    return _COUNT[0]


class CountsAssignments(nn.Module):
    """An ``nn.Module`` whose tensor and module assignments, and ``_apply``, bump the count."""

    def __setattr__(self, name: str, value) -> None:
        super().__setattr__(name, value)
        if isinstance(value, (Tensor, nn.Module)):
            _COUNT[0] += 1

    def _apply(self, fn, *args, **kwargs):
        out = super()._apply(fn, *args, **kwargs)
        _COUNT[0] += 1
        return out
