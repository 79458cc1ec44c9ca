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

__all__ = ["CountsAssignments", "assignments", "note_assignment"]

_COUNT = [0]


def assignments() -> int:
    """How many tensors and modules have been assigned to models so far (in this process)."""
    return _COUNT[0]


def note_assignment() -> None:
    """Count one assignment that changes what a carry was made for (an estimator's own
    setting: a particle filter's ``num_particles``), so that the next step of every carry
    validates it in full (:mod:`difffilter._vouched`)."""
    _COUNT[0] += 1


class CountsAssignments(nn.Module):
    """An ``nn.Module`` whose tensor and module assignments in place of an attribute it
    holds, and ``_apply``, bump the count. A first assignment (what ``__init__`` does) does
    not: building a model changes no other model (an estimator that builds a view of its
    model at its first step had every carry validated in full again)."""

    def __setattr__(self, name: str, value) -> None:
        replacing = isinstance(value, (Tensor, nn.Module)) and _holds(self, name)
        super().__setattr__(name, value)
        if replacing:
            _COUNT[0] += 1

    def __delattr__(self, name: str) -> None:
        # a deletion changes the model too (``del model.F; model.F = F2``: the second is a
        # first assignment, which is not counted)
        super().__delattr__(name)
        _COUNT[0] += 1

    def _apply(self, fn, *args, **kwargs):
        out = super()._apply(fn, *args, **kwargs)
        _COUNT[0] += 1
        return out


def _holds(module: nn.Module, name: str) -> bool:
    """Whether ``module`` already has an attribute, parameter, buffer or submodule ``name``."""
    own = module.__dict__
    return name in own or any(
        name in own.get(table, ()) for table in ("_parameters", "_buffers", "_modules")
    )
