"""The two time loops of the project: the open loop and the closed loop.

Every estimator is an object with a pure step over one carry
(:class:`~difffilter.estimator.Estimator`); every study runs in one of two drivers.

**Open loop** (:func:`open_loop`): the plant does not depend on the estimate, so what the
estimator receives, ``ỹ_1 … ỹ_T`` (with the known inputs ``u_0 … u_{T−1}`` and the
received-entry mask), is known before it runs, and the estimator steps over it::

    E_0 = estimator.init(model, batch, generator)
    E_k, out_k = estimator.step(E_{k−1}, ỹ_k, u_{k−1}, m_k)        k = 1 … T

stacked into one :class:`~difffilter.estimator.EstimatorOutput`. An estimator may run a
private whole-sequence fast path instead (the shared-covariance Kalman filter, the
parallel-in-time scan, the fused modified PF), tested equal to the composed steps.

**Closed loop** (:func:`closed_loop`, in :mod:`difffilter.closed_loop`): plant → attack →
channel and schedule → estimator → controller, one step at a time, so that the input
depends on the estimate and the attack may read the plant and the estimator.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from ._checks import check_model, check_sequence_inputs
from .estimator import Estimator, EstimatorOutput, Generators, stack_steps

__all__ = ["open_loop"]


def open_loop(
    estimator: Estimator,
    model,
    ys: Tensor,
    us: Tensor | None = None,
    *,
    mask: Tensor | None = None,
    generator=None,
    carry=None,
    nonfinite: str = "raise",
    collect: Callable | None = None,
) -> EstimatorOutput:
    """Run ``estimator`` on ``model`` over received measurements ``ys [..., T, dy]``.

    Args:
        estimator: an :class:`~difffilter.estimator.Estimator`.
        model: the estimator's model (a :class:`~difffilter.StateSpaceModel`).
        ys: ``ỹ_1 … ỹ_T`` ``[..., T, dy]``; us: the known inputs ``u_0 … u_{T−1}``
            ``[..., T, du]`` or ``None``; mask: received entries ``[..., T, dy]`` or ``None``.
        generator: a ``torch.Generator`` or :class:`~difffilter.estimator.Generators`
            for the estimator's draws.
        carry: start from this carry (default ``estimator.init(model, batch, generator)``).
        nonfinite: ``"raise"`` or ``"skip"`` (non-finite received entries treated as
            unreceived and counted in ``extras["nonfinite_skipped"] [...]``).
        collect: ``collect(carry, out) → {name: tensor}`` after every step (what a run
            records beyond the step outputs, e.g. every particle): stacked into
            ``extras`` after the batch dimensions. Runs step by step (no fast path).

    Every input is validated once (:func:`difffilter._checks.check_sequence_inputs`); the
    steps then run unchecked. The Python loop over time is the only loop.
    """
    if not isinstance(estimator, Estimator):
        raise TypeError(
            f"estimator must be a difffilter Estimator object (init/step); got "
            f"{type(estimator).__name__}"
        )
    check_model(model)
    ys, us, mask, skipped = check_sequence_inputs(model, ys, us, mask, nonfinite=nonfinite)
    batch = ys.shape[:-2]
    for other in (us, mask):
        if other is not None:
            batch = torch.broadcast_shapes(batch, other.shape[:-2])
    result = None
    if carry is None:
        carry = estimator._init(model, batch, Generators.of(generator))
        if collect is None:
            result = estimator._run(carry, ys, us, mask)
    else:
        if not isinstance(carry, estimator.carry_type):
            raise TypeError(
                f"carry must be a {estimator.carry_type.__name__} from "
                f"{type(estimator).__name__}.init; got {type(carry).__name__}"
            )
        estimator._check_carry(carry)
        batch = torch.broadcast_shapes(batch, estimator.batch_of(carry))
    if result is None:
        result = _step_through(estimator, carry, ys, us, mask, batch, collect)
    if skipped is not None:
        result.extras["nonfinite_skipped"] = skipped
    return result


def _step_through(estimator, carry, ys, us, mask, batch, collect) -> EstimatorOutput:
    outs, records = [], {}
    for t in range(ys.shape[-2]):
        u = None if us is None else us[..., t, :]
        m = None if mask is None else mask[..., t, :]
        carry, out = estimator._step(carry, ys[..., t, :], u, m)
        outs.append(out)
        if collect is not None:
            for name, value in collect(carry, out).items():
                records.setdefault(name, []).append(value)
    collected = {k: torch.stack(v, dim=len(batch)) for k, v in records.items()}
    return stack_steps(outs, batch, collected)
