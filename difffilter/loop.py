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

**Closed loop** (:func:`closed_loop`): plant → attack → channel and schedule → estimator
→ controller, one step at a time, so that the input depends on the estimate and the
attack may read the plant and the estimator::

    x_k    = f(x_{k−1}, ũ_{k−1}) + w_k,     ũ_{k−1} = u_{k−1} (+ l_k a_k: an actuator attack)
                   (with input_loss=: ũ_{k−1} held or zeroed where its packet is lost,
                    :mod:`difffilter.input_loss`)
    y_k    = h(x_k) + v_k
    A_k, a_k, l_k = attack.step(A_{k−1}, k, y=y_k, x=x_k, u=u_{k−1}, view=out_{k−1})
                   (an actuator attack steps before the transition it drives: x=x_{k−1}, no y)
    ỹ_k, m_k = channel(y_k, a_k, l_k), mask_k                 (sensor or replacement attack)
    ỹ_k = y_k + c_k,  A_k, c_k = attack.conceal(A_k, k, y_k, x_k)   (a covert actuator attack)
    E_k, out_k = estimator.step(E_{k−1}, ỹ_k, u_{k−1}, m_k)
    u_k    = controller(k, ỹ_k, out_k)        (or the known input u_k: the open loop's plant)

It returns the loop's own :class:`Trajectories` beside the estimator's output: what the
plant did is the truth that scoring reads (never the estimator's ``extras``). The noise
is drawn by the plant's noise models from a generator (:class:`DrawnNoise`) or replayed
from draws made beforehand (:class:`ReplayedNoise`), so every estimator's loop can run on
the same random numbers. Without an estimator it is the simulation of the plant (the
open loop's data); a loop may also be resumed from its :class:`LoopState` (truncated
backpropagation through time trains the learned estimator in chunks of steps).

A loop may keep :class:`LoopFork` s (``forks=``): its state after step ``k`` (tensors and
generators copied) and what it recorded up to there, from which other loops continue
(``fork=``). A loop without attack forked at the step before an attack's onset is the
attacked loop's first ``k`` steps, exactly: the evaluation runs every attack-free loop
once and each attacked loop only from its onset on (the attack must read nothing and
inject nothing up to ``k``: a :class:`~difffilter.attack.TabulatedAttack`, checked).
"""

from __future__ import annotations

import dataclasses
import linecache
import re
import traceback
from collections.abc import Callable, Mapping
from typing import Any, NamedTuple, Protocol

import torch
from torch import Tensor

from ._checks import (
    NonFinite,
    add_note,
    broadcast_or_none,
    broadcast_shapes,
    check_finite,
    check_model,
    check_model_batch,
    check_sequence_inputs,
    model_batch_shape,
)
from .attack import Attack, Channel, TabulatedAttack, attack_dim, inject
from .estimator import Estimator, EstimatorOutput, Generators, stack_steps
from .gain_schedule import _same
from .input_loss import InputLoss, OnLoss
from .results import GaussianState

__all__ = [
    "open_loop",
    "closed_loop",
    "Trajectories",
    "LoopResult",
    "LoopState",
    "LoopFork",
    "DrawnNoise",
    "ReplayedNoise",
    "Controller",
    "KnownInputs",
    "StateFeedback",
    "InputLoss",
]


class Trajectories(NamedTuple):
    """A batch of runs of a loop (time index ``t`` ↔ ``k = t + 1``).

    Attributes:
        x: true states ``x_1 … x_T`` ``[B, T, dx]``.
        y_true: measurements before any attack ``[B, T, dy]``.
        y_recv: what the estimator receives ``[B, T, dy]`` (attacked; unreceived
            entries are whatever ``mask`` says not to read).
        us: inputs the estimator knows ``u_0 … u_{T−1}`` ``[B, T, du]`` or ``None``.
        mask: received entries ``[B, T, dy]`` (bool) or ``None`` (all received).
        attack: the injected attack signal ``[B, T, da]`` (zero where none is injected and
            on entries not received; ``da = dy`` for sensor-side attacks, ``du`` for
            actuator attacks, ``0`` without an attack: ``[B, T, 0]``, so compare an attack
            estimate with it only under an attack).
        flags: attacked steps ``[B, T]`` (bool): an attacked entry was received (under a
            mask; an actuator attack's steps whatever the mask, and, under an input loss
            that holds, the steps after them where a held input still carries it).
        info: extras: ``"attack_values"`` ``[B, T, da]`` (what the attacker would inject
            at every step, also where it does not), ``"attack_flags"`` (the attack's own
            flags ``l_k``, ``[B, T]`` or per entry ``[B, T, da]``, before any mask: where it
            acts, injected value zero or not; under an attack only), ``"attack_channel"`` (its
            :class:`~difffilter.attack.Channel`, ``None`` attack-free),
            ``"attack_concealment"`` ``[B, T, dy]`` (a covert attack's sensor correction
            ``ỹ − y``, only under one), ``"x0"`` ``[B, dx]`` and what a
            scenario records beside them (the exogenous draws of a closed loop).
    """

    x: Tensor
    y_true: Tensor
    y_recv: Tensor
    us: Tensor | None
    mask: Tensor | None
    attack: Tensor
    flags: Tensor
    info: Mapping[str, Tensor] = {}

    def runs(self, count: int) -> Trajectories:
        """The first ``count`` runs (every batch-first tensor sliced)."""

        def cut(v):
            return v[:count] if isinstance(v, Tensor) else v

        return Trajectories(
            *(cut(v) for v in self[:-1]), info={k: cut(v) for k, v in self.info.items()}
        )


def open_loop(
    estimator: Estimator,
    model,
    ys: Tensor,
    us: Tensor | None = None,
    *,
    mask: Tensor | None = None,
    generator=None,
    carry=None,
    nonfinite: NonFinite | str = NonFinite.RAISE,
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
        nonfinite: :class:`~difffilter.NonFinite` (or its name): ``SKIP`` treats
            non-finite received entries as unreceived and counts them in
            ``extras["nonfinite_skipped"] [...]``; ``RAISE`` (default) raises.
        collect: ``collect(carry, out) → {name: tensor}`` after every step (what a run
            records beyond the step outputs, e.g. every particle): stacked into
            ``extras`` after the runs' dimensions (the measurements' batch broadcast with
            the carry's and the model's parameter sets, as the means are). Runs step by
            step (no fast path).

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
            batch = broadcast_shapes(batch, other.shape[:-2])
    result = None
    if carry is None:
        carry = estimator._init(model, batch, Generators.of(generator))
        if collect is None:
            result = estimator._run(carry, ys, us, mask)
            if result is not None:  # a fast path says what its attack estimate is on too
                result.attack_channel = estimator.attack_channel
    else:
        if not isinstance(carry, estimator.carry_type):
            raise TypeError(
                f"carry must be a {estimator.carry_type.__name__} from "
                f"{type(estimator).__name__}.init; got {type(carry).__name__}"
            )
        estimator._check_carry(carry)
        held = estimator._model_of(carry)
        if held is not None and held is not model:  # the steps filter with the carry's
            raise ValueError(
                "carry holds another model than the model given (its steps would filter with "
                "the carry's): give the carry's own, open_loop(estimator, carry.model, ys, "
                "carry=carry) (a carry made elsewhere, e.g. a study's start(B)), or start the "
                "carry from this model (estimator.init(model, …))"
            )
        both = broadcast_or_none(batch, estimator.batch_of(carry))
        if both is None:
            raise ValueError(
                f"the carry holds runs {tuple(estimator.batch_of(carry))} and the measurements "
                f"(ys, us, mask) runs {tuple(batch)}: they must broadcast (one carry per run of ys)"
            )
        batch = both
    if result is None:
        # the runs are the carry's too: a model of several parameter sets makes runs of
        # them (its steps' extras and collect's records had stacked time first there, the
        # means runs first: a review)
        batch = broadcast_or_none(batch, estimator._runs_of(carry)) or batch
        result = _step_through(estimator, carry, ys, us, mask, batch, collect)
    if skipped is not None:
        result.extras["nonfinite_skipped"] = skipped
    return result


def _step_through(estimator, carry, ys, us, mask, batch, collect) -> EstimatorOutput:
    outs, records, handed = [], {}, _HandedOut(estimator)
    for t in range(ys.shape[-2]):
        u = None if us is None else us[..., t, :]
        m = None if mask is None else mask[..., t, :]
        carry, out = estimator._step(carry, ys[..., t, :], u, m)
        outs.append(out)
        handed.add(t + 1, out)
        if collect is not None:
            for name, value in collect(carry, out).items():
                records.setdefault(name, []).append(value)
    handed.check()
    collected = {k: torch.stack(_per_run(k, v, batch), dim=len(batch)) for k, v in records.items()}
    return stack_steps(outs, batch, collected, estimator.attack_channel)


def _per_run(name: str, values: list, batch: torch.Size) -> list:
    """``collect``'s record ``name`` at every step as ``[*batch, …]``: leading dimensions
    of size 1 expanded to the runs'; a value without the runs' leading dimensions refused
    (a Kalman filter's covariance shared by the runs, ``[dx, dx]``, had been stacked as
    ``[dx, T, dx]``: row 0 of every step's matrix read as run 0's)."""
    n = len(batch)
    out = []
    for t, value in enumerate(values):
        lead = tuple(value.shape[:n]) if isinstance(value, Tensor) else None
        if lead is None or len(lead) < n or broadcast_or_none(lead, batch) != batch:
            got = tuple(value.shape) if isinstance(value, Tensor) else type(value).__name__
            raise ValueError(
                f"collect: its record {name!r} at step {t + 1} has shape {got}; each record "
                f"leads with the runs' dimensions {tuple(batch)} (a value shared by the runs, "
                f"e.g. a Kalman filter's shared covariance: value.expand(*{tuple(batch)}, "
                "*value.shape))"
            )
        out.append(value if lead == tuple(batch) else value.expand(*batch, *value.shape[n:]))
    return out


# ------------------------------------------------------------------------ the closed loop


class DrawnNoise:
    """Process and measurement noise drawn by the plant's own noise models from one
    generator, per step and in this order: ``x_k ~ p(x_k | x_{k−1}, u)`` then ``y_k ~ p(y_k
    | x_k)`` (:meth:`~difffilter.StateSpaceModel.sample_transition`,
    :meth:`~difffilter.StateSpaceModel.sample_measurement`)."""

    def __init__(self, generator: torch.Generator | None):
        self.generator = generator

    def transition(self, plant, x: Tensor, u: Tensor | None, t: int) -> Tensor:
        return plant.sample_transition(x, u, t, self.generator)

    def measure(self, plant, x: Tensor, t: int) -> Tensor:
        return plant.sample_measurement(x, t + 1, self.generator)


class ReplayedNoise:
    """Additive noise drawn beforehand: ``x_k = f(x_{k−1}, u) + w[:, t]``, ``y_k = h(x_k) +
    v[:, t]`` with ``process [B, T, dx]`` and ``measurement [B, T, dy]`` (``t = k − 1``): every
    estimator's loop replays the same draws (common random numbers)."""

    def __init__(self, process: Tensor, measurement: Tensor):
        for name, t in (("process", process), ("measurement", measurement)):
            # (NaN draws had run to NaN states, or been blamed on the plant: a trial)
            if not isinstance(t, Tensor) or not t.is_floating_point() or t.dim() != 3:
                got = tuple(t.shape) if isinstance(t, Tensor) else type(t).__name__
                raise ValueError(
                    f"ReplayedNoise: {name} noise must be a floating tensor [B, T, d]; got {got}"
                )
            check_finite(t, f"ReplayedNoise: {name} noise")
        if process.shape[:-1] != measurement.shape[:-1]:
            raise ValueError(
                f"process [B, T, dx] and measurement [B, T, dy] noise must share B and T; got "
                f"{tuple(process.shape)} and {tuple(measurement.shape)}"
            )
        self.process, self.measurement = process, measurement

    def transition(self, plant, x: Tensor, u: Tensor | None, t: int) -> Tensor:
        return plant.transition(x, u, t) + self.process[:, t]

    def measure(self, plant, x: Tensor, t: int) -> Tensor:
        return plant.observe(x, t + 1) + self.measurement[:, t]


class Controller(Protocol):
    """The input of the next step from what the loop has: ``init(batch_shape, dtype, device)
    → u_0 [B, du]`` (``None`` only for a plant without input, ``dim_u = 0``) and
    ``__call__(k, y, out) → u_k [B, du]`` after measurement ``k`` (``y`` the received
    ``ỹ_k``, ``out`` the estimator's :class:`~difffilter.results.StepOutput` or ``None``),
    in the plant's dtype, on its device; the loop checks each (a wrong shape, dtype or a
    NaN is named at the step it came from).

    Timing: ``u_k`` is computed from measurement ``k`` and drives the transition to
    ``x_{k+1}``, with no computation delay; for a delay of one step, return the input the
    previous call computed (keep it in the controller). Under a schedule (``mask``) ``y``
    holds values at the entries not received this step too (the loop's ``y_recv``): a
    controller that reads ``y`` itself, not ``out``, reads them. A controller may keep
    state of its own (an integrator, a delay line) in a loop run in one call; a loop
    resumed from a :class:`LoopState` or continued from a :class:`LoopFork` holds none of
    it (it holds the plant's, the attack's and the estimator's), so give the resumed loop a
    controller whose state is where it was at that step, or keep the controller a function
    of ``k``, ``y`` and ``out``.

    Optionally ``check(batch_shape, dtype, device)``: the checks ``init`` makes of the
    controller's own fields (raising ``ValueError``), which a resumed loop, calling no
    ``init``, makes when it starts: a field written between chunks is checked as a new
    loop checks it (a reference of another shape, a gain of another dtype had been taken)."""

    def init(self, batch_shape, dtype, device) -> Tensor | None: ...

    def __call__(self, k: int, y: Tensor, out) -> Tensor: ...


class KnownInputs:
    """The open loop's controller: the known inputs ``us [B, T, du]`` (``u_k = us[:, k]``)."""

    def __init__(self, us: Tensor):
        self.us = us

    def init(self, batch_shape, dtype, device) -> Tensor:
        return self.us[:, 0]

    def __call__(self, k: int, y: Tensor, out) -> Tensor:
        T = self.us.shape[1]
        if k > T:
            raise ValueError(
                f"the known inputs us [B, T, du] cover u_0 … u_{T - 1} (T = {T}); step {k} of "
                "the loop needs more: give us one row per step run"
            )
        if k == T:  # after the last step the loop asks for u_T, which the table lacks:
            # NaN, so that a loop resumed from this state is refused (closed_loop), where a
            # copy of u_{T−1} had driven step T + 1 (0.23 off in a trial)
            return torch.full_like(self.us[:, T - 1], float("nan"))
        return self.us[:, k]


class StateFeedback:
    """``u_k = −K (x̂_k − x_ref)`` on the estimator's mean: the controller of an LQG or
    observer-based design (``K`` from :func:`difffilter.control.dlqr`, or a parameter tuned
    by gradient through the loop, which is differentiable in ``K``).

    Args:
        gain: ``K [du, dx]`` for every run, or ``[B, du, dx]``, one per run (a sweep).
        reference: ``x_ref [dx]`` or ``[B, dx]`` (default 0).

    ``u_0 = 0`` (no estimate before the first measurement). It reads the estimator's
    output, so the loop needs an estimator.
    """

    def __init__(self, gain: Tensor, reference: Tensor | None = None):
        self._check(gain, reference)
        self.gain, self.reference = gain, reference

    @staticmethod
    def _check(gain, reference) -> None:
        """The constructor's checks, made again at ``init``: a reference assigned later of
        another shape (``[B, 1]``, 0-dim) had been broadcast over every state entry (an
        LQG trial)."""
        if not isinstance(gain, Tensor) or not gain.is_floating_point() or gain.dim() < 2:
            got = tuple(gain.shape) if isinstance(gain, Tensor) else type(gain).__name__
            raise ValueError(f"gain must be a floating tensor K [du, dx] or [B, du, dx]; got {got}")
        # a NaN gain had run, every input and so every state NaN from the first step (a trial)
        check_finite(gain, "gain")
        if reference is not None and (
            not isinstance(reference, Tensor) or reference.shape[-1:] != gain.shape[-1:]
        ):
            got = tuple(reference.shape) if isinstance(reference, Tensor) else reference
            raise ValueError(
                f"reference must be x_ref [{gain.shape[-1]}] or [B, {gain.shape[-1]}] (the "
                f"gain's dx); got {got!r}"
            )
        if reference is not None:
            check_finite(reference, "reference")

    def init(self, batch_shape, dtype, device) -> Tensor:
        self.check(batch_shape, dtype, device)
        return torch.zeros(*batch_shape, self.gain.shape[-2], dtype=dtype, device=device)

    def check(self, batch_shape, dtype, device) -> None:
        """The gain and reference as the constructor checks them, in the loop's dtype, on
        its device, for its runs (at ``init``, and when a loop resumes: a field assigned
        later is checked as a new one)."""
        self._check(self.gain, self.reference)
        runs = torch.Size(batch_shape)
        for name, t, event in (("gain", self.gain, 2), ("reference", self.reference, 1)):
            if t is None:
                continue
            if t.dtype != dtype or t.device != torch.device(device):
                raise ValueError(
                    f"StateFeedback's {name} is {t.dtype} on {t.device} and the loop "
                    f"{dtype} on {device}: give it the plant's ({name}.to(x0))"
                )
            own = t.shape[: t.dim() - event]
            if broadcast_or_none(own, runs) != runs:
                raise ValueError(
                    f"StateFeedback's {name} {tuple(t.shape)} holds {tuple(own)} runs, and the "
                    f"loop {tuple(runs)}: one for all runs, or one per run"
                )

    def __call__(self, k: int, y: Tensor, out) -> Tensor:
        if out is None:
            raise ValueError(
                "StateFeedback reads the estimator's mean, and this loop has no estimator: "
                "give closed_loop an estimator (e.g. difffilter.KalmanFilter())"
            )
        if out.mean.shape[-1] != self.gain.shape[-1]:  # (else a bare torch matmul error)
            raise ValueError(
                f"StateFeedback's gain K is {tuple(self.gain.shape)}, and the estimator's state has "
                f"{out.mean.shape[-1]} entries: K must be [du, dx] = [du, {out.mean.shape[-1]}]"
            )
        error = out.mean if self.reference is None else out.mean - self.reference
        return -(self.gain @ error.unsqueeze(-1)).squeeze(-1)


class LoopState(NamedTuple):
    """Where a closed loop stands after ``k`` steps: the plant's state ``x [B, dx]``, the
    next input ``u [B, du]`` (or ``None``), the attacker's state, the estimator's carry
    (or ``None``) and its last output ``view`` (what an adaptive attacker reads); under an
    :class:`~difffilter.input_loss.InputLoss` that holds, its
    :class:`~difffilter.input_loss.InputMemory` (the input the actuators hold, the
    estimator's knowledge of it, the attack in it), else ``None``; ``attacker``: the
    :class:`~difffilter.attack.Attack` whose state ``attack`` is (a loop resumed from it
    with another attack is refused: the other's name had stepped this one's tables)."""

    k: int
    x: Tensor
    u: Tensor | None
    attack: Any
    carry: Any
    view: Any
    inputs: Any = None
    attacker: Any = None

    def detach(self) -> LoopState:
        """The same state cut from the autograd graph (truncated backpropagation)."""
        return LoopState(self.k, *(_map_tensors(v, Tensor.detach) for v in self[1:]))

    def copy(self) -> LoopState:
        """The same state in new tensors and generators (a loop that updates its carry in
        place, or draws from its generators, can resume from it and leave it as it was).
        A generator held in several places stays one generator in the copy."""
        copies: dict[int, torch.Generator] = {}

        def copy_generator(g: torch.Generator) -> torch.Generator:
            if id(g) not in copies:
                copies[id(g)] = torch.Generator(device=g.device).set_state(g.get_state())
            return copies[id(g)]

        return LoopState(self.k, *(_map_tensors(v, Tensor.clone, copy_generator)
                                   for v in self[1:]))  # fmt: skip


def _map_tensors(value, on_tensor, on_generator=None):
    """``value`` (tensors in nested tuples, named tuples, lists and dicts) with ``on_tensor``
    applied to every tensor (and ``on_generator`` to every ``torch.Generator``, if given);
    anything else is kept as it is."""
    if isinstance(value, Tensor):
        return on_tensor(value)
    if on_generator is not None and isinstance(value, torch.Generator):
        return on_generator(value)
    if isinstance(value, GaussianState) and value.gains is not None:
        # the gain schedule's covariance is shared by the runs and the steps, never written
        # (the Kalman filter refuses a carry whose cov is not that very tensor: a copied
        # carry had been refused by KalmanFilter.step and open_loop, "changed")
        return type(value)(*(v if name == "cov" else _map_tensors(v, on_tensor, on_generator)
                             for name, v in zip(value._fields, value)))  # fmt: skip
    if isinstance(value, tuple) and not isinstance(value, torch.Size):
        items = [_map_tensors(v, on_tensor, on_generator) for v in value]
        return type(value)(*items) if hasattr(value, "_fields") else type(value)(items)
    if isinstance(value, list):
        return [_map_tensors(v, on_tensor, on_generator) for v in value]
    if isinstance(value, dict):
        return {k: _map_tensors(v, on_tensor, on_generator) for k, v in value.items()}
    return value


class LoopFork(NamedTuple):
    """A closed loop stopped after ``state.k`` steps, to be continued by other loops
    (:func:`closed_loop`'s ``fork``): its :class:`LoopState` (copied: the loop that kept
    the fork went on) and what it recorded at steps ``1 … k`` (``records``: the lists
    :func:`closed_loop` stacks into :class:`Trajectories`, with the schedule's rows under
    ``"mask"``, so that a continuation is checked to run under the same; ``outputs``: the
    estimator's step outputs; ``noise``: the :class:`ReplayedNoise` it ran on, so that a
    continuation is checked to replay the same draws at those steps)."""

    state: LoopState
    records: dict[str, list]
    outputs: list
    noise: ReplayedNoise | None = None


class LoopResult(NamedTuple):
    """A closed loop's own :class:`Trajectories`, the estimator's stacked
    :class:`~difffilter.EstimatorOutput` (``None`` without an estimator) and the
    :class:`LoopState` it ended in."""

    trajectories: Trajectories
    output: EstimatorOutput | None
    state: LoopState


def closed_loop(
    plant,
    steps: int,
    *,
    noise,
    x0: Tensor | None = None,
    estimator: Estimator | None = None,
    model=None,
    controller: Controller | None = None,
    attack: Attack | None = None,
    attack_generator: torch.Generator | None = None,
    mask: Tensor | None = None,
    generator=None,
    state: LoopState | None = None,
    horizon: int | None = None,
    progress: Callable[[int], None] | None = None,
    forks: dict[int, LoopFork | None] | None = None,
    fork: LoopFork | None = None,
    input_loss: InputLoss | None = None,
) -> LoopResult:
    """Run ``steps`` steps of plant → attack → channel → estimator → controller.

    Args:
        plant: the :class:`~difffilter.StateSpaceModel` that simulates the truth.
        steps: ``L ≥ 1`` steps to run (from ``state.k`` on when resuming).
        noise: :class:`DrawnNoise` or :class:`ReplayedNoise`.
        x0: initial states ``[B, dx]`` (a new loop).
        estimator, model: the :class:`~difffilter.estimator.Estimator` and its model (the
            plant's, or what the estimator believes; default the plant), or ``None``.
        controller: a :class:`Controller`, or ``None``: no input (a plant that has inputs
            runs with ``u = 0``, without a word, and ``Trajectories.us`` is ``None``).
        attack: an :class:`~difffilter.attack.Attack` or ``None``; attack_generator its
            draws (``None``: a random attack draws from torch's global generator, and two
            calls differ unless ``torch.manual_seed`` comes first; ``noise``'s generator
            is not used, so that the attack never shifts the plant's noise). One whose
            onset lies after the last step runs and never acts (training draws such onsets
            on purpose; ``difffilter.threats.check_attack_fits(attack, plant, T)`` refuses
            them, as the evaluation does for a scenario's own attack).
        mask: received entries ``[B, T, dy]`` (the schedule) or ``None``, indexed by the
            absolute step.
        generator: the estimator's draws (a ``torch.Generator`` or
            :class:`~difffilter.estimator.Generators`).
        state: resume from this :class:`LoopState` (``x0`` and the initial draws unused).
            The loop runs on it, not on a copy (a copy would split a generator it shares
            with the noise, and double a learner's memory at every chunk): an estimator
            that writes its carry in place (``EKFRule(donate=True)``) or draws from its
            generators consumes it, so resume two loops from one state (two what-ifs) each
            from a :meth:`LoopState.copy` made before the first (a consumed learner state
            is refused).
        horizon: the whole loop's length ``T`` when it runs in chunks (what the attacker
            tabulates for at the start; default ``steps``).
        progress: called with 1 after every step (e.g. a progress bar's ``update``).
        forks: ``{k: None}``: after step ``k`` the loop stores its :class:`LoopFork` there.
        fork: continue a :class:`LoopFork` (of a loop without attack, on the same noise):
            the result covers steps ``1 … fork.state.k + L``, the fork's steps as this
            loop's ``attack`` would have left them (a tabulated attack that flags none of
            them; ``ValueError`` otherwise). ``state`` must then be ``None``; the plant,
            noise, estimator, model and controller are the forked loop's (the fork holds
            no controller state: :class:`Controller`), and so is ``mask`` over the fork's
            steps (checked) and ``input_loss`` given or not as it was (checked).
        input_loss: an :class:`~difffilter.input_loss.InputLoss`: the controller's packets
            lost on the way to the actuators (held or zeroed there; the estimator told of
            each arrival or not), or ``None`` (every input arrives).

    Returns a :class:`LoopResult`: the trajectories of these ``L`` steps
    (``us`` = the inputs the estimator knew, ``attack``/``flags``/``info["attack_values"]``
    as the attack made them; under ``input_loss`` only ``attack`` is as it reached the plant
    (zero in a lost packet the actuators zero, the held attack where they hold), while
    ``flags`` stay the attack's own steps, lost packet or not, with, under ``"hold"``, the
    steps where a held input still carries it, and ``info["attack_values"]`` what the
    attacker would inject at every step: the plant still carries what it injected before,
    :class:`~difffilter.input_loss.InputLoss`; with ``info["inputs_applied"]``, what drove
    the plant, ``info["inputs_sent"]``, the controller's, and ``info["input_mask"]``, the
    arrivals), the estimator's output over them and the final state.
    Differentiable end to end (the loop records no tensor in place).
    """
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps must be an integer >= 1; got {steps!r}")
    given_model = model
    model = plant if model is None else model
    if not (
        callable(getattr(noise, "transition", None)) and callable(getattr(noise, "measure", None))
    ):
        raise TypeError(
            "noise must be a DrawnNoise(generator) or a ReplayedNoise(process, measurement) "
            f"(an object with transition and measure); got {type(noise).__name__}"
        )
    if horizon is not None and (isinstance(horizon, bool) or not isinstance(horizon, int)):
        raise ValueError(
            f"horizon must be an integer (the whole loop's T) or None; got {horizon!r}"
        )
    if attack_generator is not None and not isinstance(attack_generator, torch.Generator):
        raise TypeError(  # (torch's rand() named neither; the estimator's generator= takes both)
            "attack_generator must be a torch.Generator or None (the attack's own stream, "
            f"not difffilter.Generators); got {type(attack_generator).__name__}"
        )
    if (forks or fork) and not isinstance(noise, ReplayedNoise):
        raise ValueError("forks= and fork= need ReplayedNoise: drawn noise's generator is "
                         "not part of the loop's state, so a fork could not replay it")  # fmt: skip
    _check_parts(estimator, attack)
    if input_loss is not None and not isinstance(input_loss, InputLoss):
        drawn = (" (a scenario's InputLossSchedule: its .draw(runs, steps, du, generator))"
                 if callable(getattr(input_loss, "draw", None)) else "")  # fmt: skip
        raise TypeError(
            "input_loss must be a difffilter.loop.InputLoss(mask, on_loss, acknowledged=...) or "
            f"None; got {type(input_loss).__name__}{drawn}"
        )
    channel = None if attack is None else Channel(attack.channel)
    conceals = channel is Channel.ACTUATOR and bool(getattr(attack, "conceals", False))
    if input_loss is not None and conceals:
        raise ValueError(
            f"attack {type(attack).__name__} conceals its effect on the measurements by "
            "simulating it as if its packets arrived; under input_loss they may not (the "
            "concealment then shows: 0.12 off under hold in a review): run a covert attack "
            "without input_loss"
        )
    # only an attack that says it reads the estimator's output gets it (an open-loop
    # scenario hands such an attack nothing, so one that read it unannounced worked here
    # and silently read None there)
    reads = attack is not None and bool(attack.reads_view)
    # the true state only to an attack that declares it reads it (Attack.reads_state)
    shows_state = attack is not None and bool(attack.reads_state)
    if fork is not None and state is not None:
        raise ValueError("give a loop either state= or fork= to resume from, not both")
    if fork is not None or state is not None:
        _check_resumed(fork.state if fork is not None else state, "fork" if fork else "state",
                       estimator, given_model, plant, controller)  # fmt: skip
    if state is not None:
        _check_resumed_attack(state, attack)
    if fork is not None:
        end = fork.state.k + steps
        if horizon is not None and (isinstance(horizon, bool) or not isinstance(horizon, int)
                                    or horizon < end):  # fmt: skip
            # (horizon=0 had been taken for the default, one short of the fork's steps had
            # failed in torch's narrow: a trial of the resumed loops)
            raise ValueError(
                f"horizon (the whole loop's T) must be an integer >= {end} (the fork's step "
                f"{fork.state.k} + steps={steps}); got {horizon!r}"
            )
        state, rec, outs = _resume(fork, plant, attack, attack_generator, channel,
                                   end if horizon is None else horizon)  # fmt: skip
    else:
        if state is None:
            state = _start(plant, steps, horizon, x0, estimator, model, controller, attack,
                           attack_generator, generator)  # fmt: skip
        keys = ("x", "y", "recv", "u", "attack", "value", "flag", "concealment", "applied",
                "sent", "arrived", "acting", "mask", "input_channel")  # fmt: skip
        rec, outs = {key: [] for key in keys}, []
    _check_lengths(plant, noise, mask, state, steps)
    _check_attack_horizon(attack, state, steps)
    handed = _HandedOut(estimator)
    unreached = sorted(k for k in forks or () if not state.k < k <= state.k + steps)
    if unreached:  # (they stayed None, unsaid)
        raise ValueError(
            f"forks: its keys must be steps this loop runs ({state.k + 1} … {state.k + steps}), "
            f"after which it keeps a fork; got {unreached}"
        )
    if input_loss is not None:
        state = _with_input_memory(input_loss, plant, state, steps)
    if rec["x"] and bool(rec["applied"]) != (input_loss is not None):
        raise ValueError("fork: continue a fork with the input_loss of the loop that kept it "
                         "(or without one, as it was kept)")  # fmt: skip
    first = state.k - len(rec["x"])  # the step before the first one recorded
    if rec["x"]:
        _check_fork_mask(rec["mask"], mask, first)
        _check_fork_noise(fork.noise, noise, first, len(rec["x"]))
        if input_loss is not None:
            _check_fork_input_loss(rec, input_loss, first)
    k, x, u, a_state, carry, view, memory, attacker = state
    attacker = attacker if attack is None else attack  # (None: the kept attacker's state stays)
    _check_attackers_plant(attacker, plant)
    if channel is Channel.ACTUATOR and plant.dim_u == 0:  # (no controller could help it)
        raise ValueError(
            f"attack {type(attack).__name__} acts on the actuators, and the plant has no input "
            "(dim_u = 0): an actuator attack needs a model with inputs"
        )
    if channel is Channel.ACTUATOR and u is None:  # (it failed inside the step's checks)
        raise ValueError(
            f"attack {type(attack).__name__} acts on the actuators, and this loop has no input "
            "to attack: give it a controller (e.g. KnownInputs(us), us [B, T, du]; zeros for "
            "an uncontrolled plant)"
        )
    try:
        for _ in range(steps):
            k += 1
            m = None if mask is None else mask[:, k - 1]
            applied, a, value, flag = u, None, None, None
            if channel is Channel.ACTUATOR:
                seen = _Untouched(attack, x, u, view if reads else None)
                a_state, value, flag = _three(attack.step(
                    a_state, k, x=x if shows_state else None, u=u, view=view if reads else None,
                ), attack, k)  # fmt: skip
                seen.check(k, "step")
                value, flag = _checked_value(attack, value, flag, u, k, "u")
                applied, a = inject(channel, u, value, flag)
            known = u
            if input_loss is not None:
                sent = input_loss.deliver(k, u, a, flag, memory)
                applied, known, a, memory = sent.applied, sent.known, sent.attack, sent.memory
                rec["applied"].append(applied)
                rec["sent"].append(u)
                rec["arrived"].append(sent.arrived)
                rec["acting"].append(sent.acting)
                rec["input_channel"].append((input_loss.on_loss, input_loss.acknowledged))
            x = noise.transition(plant, x, applied, k - 1)
            y = noise.measure(plant, x, k - 1)
            received = y
            if conceals:
                seen = _Untouched(attack, x, y)
                a_state, correction = attack.conceal(a_state, k, y=y, x=x if shows_state else None)
                seen.check(k, "conceal")
                received = y + _checked_correction(attack, correction, y, k)
                rec["concealment"].append(correction)
            if channel is not None and channel is not Channel.ACTUATOR:
                seen = _Untouched(attack, x, y, u, view if reads else None)
                a_state, value, flag = _three(attack.step(
                    a_state, k, y=y, x=x if shows_state else None, u=u,
                    view=view if reads else None,
                ), attack, k)  # fmt: skip
                seen.check(k, "step")
                value, flag = _checked_value(attack, value, flag, y, k, "y")
                received, a = inject(channel, y, value, flag)
            if estimator is not None:
                step_input = _estimator_input(received, m, k, attack, known, controller)
                carry, view = estimator._step(carry, step_input, known, m)
                outs.append(view)
                handed.add(k, view)
            for key, val in (("x", x), ("y", y), ("recv", received), ("u", known), ("attack", a),
                             ("value", value), ("flag", flag), ("mask", m)):  # fmt: skip
                rec[key].append(val)
            if controller is not None:
                # (a controller's `e = view.mean; e -= ref` had been blamed on the estimator)
                # (every field: an adaptive filter's extras["attack_covs"] is its next carry's
                # own tensor, docs/python-api.md; checking the metrics' four alone let a
                # controller's `S += I` move every later estimate: a review)
                seen = _Untouched(controller, view, role="controller")
                u = controller(k, received, view)
                seen.check(k, "__call__")
                u = _checked_input(controller, u, x, plant, k)
            if progress is not None:
                progress(1)
            if forks is not None and k in forks:
                kept = LoopState(k, x, u, a_state, carry, view, memory, attacker).copy()
                records = {key: list(v) for key, v in rec.items()}
                forks[k] = LoopFork(kept, records, list(outs), noise)
    except (TypeError, AttributeError) as error:
        if attack is not None:
            hint = _undeclared_read(error, attack, shows_state, reads)
            if hint is not None:
                add_note(error, hint)
        raise
    handed.check()
    traj = _trajectories(rec, mask, first, k, channel)
    if estimator is None:
        _check_finite(traj, first, attack, controller, channel)
    batch = x.shape[:-1]
    output = stack_steps(outs, batch, attack_channel=estimator.attack_channel) if outs else None
    return LoopResult(traj, output, LoopState(k, x, u, a_state, carry, view, memory, attacker))


class _Untouched:
    """The version counters of what the loop hands an attack (``x``, ``y``, ``u`` and the
    estimator's :class:`~difffilter.results.StepOutput`) or a controller (the output),
    checked after its call: each reads them and acts only through what it returns. A
    trial's attack that wrote into them in place (``x.add_``, ``y.clamp_``, ``view.mean
    +=``) moved the plant's true state, the recorded measurement or the estimator's carry,
    while the loop recorded no attack and flagged no step (the runs scored against wrong
    labels); a controller's ``e = out.mean; e -= ref`` had been blamed on the estimator (a
    review). Inference tensors keep no counter and are not checked."""

    def __init__(self, owner, *values, role: str = "attack"):
        self.owner, self.role, self.stamps = owner, role, []
        for value in values:
            tensors = [value] if isinstance(value, Tensor) else _tensors_of(value)
            for t in tensors:
                if (version := _version_of(t)) is not None:
                    self.stamps.append((t, version))

    def check(self, k: int, call: str) -> None:
        if not any(t._version != version for t, version in self.stamps):
            return
        name = f"{self.role} {type(self.owner).__name__}.{call}"
        if self.role == "controller":
            raise ValueError(
                f"{name} wrote in place into the estimator's output the loop handed it at step "
                f"{k} (e.g. e = out.mean; e -= ref): that changes the estimates the loop "
                "records. Compute out of place (e = out.mean - ref) or on a copy"
            )
        raise ValueError(
            f"{name} wrote in place into a tensor the loop handed it at step {k} (the true "
            "state, the measurement, the input or the estimator's output): that changes the "
            "plant, the records or the estimator without being recorded as an attack. An "
            "attack acts only through what it returns: compute out of place (x + 1, not "
            "x.add_(1)) or on a copy"
        )


def _failing_source(tb) -> str:
    """The source of the expression a traceback entry was executing: its lines and columns
    where Python records them (a call over several lines reads ``x`` on a later one), else
    its line."""
    summary = traceback.extract_tb(tb, limit=1)[0]
    first, last = summary.lineno, getattr(summary, "end_lineno", None) or summary.lineno
    lines = [linecache.getline(summary.filename, n).encode() for n in range(first, last + 1)]
    start, end = getattr(summary, "colno", None), getattr(summary, "end_colno", None)
    if lines and start is not None and end is not None:  # (UTF-8 byte offsets: δ = x[…])
        lines[-1] = lines[-1][:end]
        lines[0] = lines[0][start:]
    return b"".join(lines).decode(errors="replace")


def _undeclared_read(error: BaseException, attack, shows_state: bool, reads: bool) -> str | None:
    """A note for a ``None`` error raised inside ``attack``'s ``step`` or ``conceal`` on a
    line that reads ``x`` it was handed as ``None`` (``reads_state`` False) or ``view``
    (``reads_view`` False), naming the declaration; ``None`` for any other error (an
    attack's own bug, another argument that was ``None``)."""
    if "NoneType" not in str(error):
        return None
    codes = {getattr(getattr(type(attack), name, None), "__code__", None)
             for name in ("step", "conceal")} - {None}  # fmt: skip
    tb, frame, text = error.__traceback__, None, ""
    while tb is not None:
        if tb.tb_frame.f_code in codes:
            frame, text = tb.tb_frame, _failing_source(tb)
        tb = tb.tb_next
    if frame is None:
        return None
    local = frame.f_locals
    undeclared = [f"{name}=None because {flag} = False" for name, flag, given in
                  (("x", "reads_state", shows_state), ("view", "reads_view", reads))
                  if not given and local.get(name, 0) is None
                  and _reads(name, text)]  # fmt: skip
    if undeclared:
        return (
            f"(attack {type(attack).__name__} was handed {' and '.join(undeclared)}: an attack "
            "reads the true state or the estimator's output only where its class declares it)"
        )
    return _empty_view(error, attack, local.get("view", 0), text) if reads else None


def _reads(name: str, text: str) -> bool:
    """Whether the source ``text`` reads the variable ``name`` (not an assignment to it)."""
    return re.search(rf"(?<![\w.]){name}\b(?!\s*=(?!=))", text) is not None


def _empty_view(error: BaseException, attack, view, text: str) -> str | None:
    """A note for an attack that declares ``reads_view`` and failed reading ``view`` where
    it was ``None`` (the first step: no output yet; the error is that attribute's or a
    subscript's, on an expression that reads it so) or using one of its fields that the
    estimator leaves ``None`` (``view.score`` of a filter without a detector; a field only
    tested with ``is``, ``view.score is None``, does not count); ``None`` otherwise (an
    attack's own bug beside a guarded read)."""
    name = type(attack).__name__
    if view is None:
        missing = re.search(r"has no attribute '(\w+)'", str(error))
        if (missing and re.search(rf"(?<![\w.])view\s*\.\s*{missing.group(1)}\b", text)) or (
            "not subscriptable" in str(error) and re.search(r"(?<![\w.])view\s*\[", text)
        ):
            return (
                f"(attack {name} was handed view=None: at the first step the estimator has "
                "no output yet (view is its output of the step before); check `view is None` "
                "there)"
            )
        return None
    empty = [f for f in getattr(view, "_fields", ()) if getattr(view, f, 0) is None
             and re.search(rf"(?<![\w.])view\.{f}\b(?!\s*is\b)", text)]  # fmt: skip
    if not empty:
        return None
    fields = ", ".join(f"view.{f}" for f in empty)
    return (
        f"(attack {name} read {fields}, which this estimator's output leaves None: an "
        "estimator without a detector has no score, alarm or threshold, and a filter that "
        "estimates no attack no attack; read what its StepOutput holds, or run it with an "
        "estimator that has one)"
    )


class _HandedOut:
    """The version counters of the means, covariances, attack estimates and scores an
    estimator handed the driver, checked before they are stacked. ``Estimator.step``
    leaves its carry's tensors as they were; a user's step that wrote its carry in place
    and handed that tensor out as its mean had every stacked ``means[:, t]`` read the last
    step's value, without a word (a trial: 3.46 off a hand run; the attack and score 0.66
    and 4.3, a review). The fields the metrics read, not every field (every field had
    cost a tenth of a Kalman step); inference tensors and ``torch.func`` wrappers keep no
    counter and are not checked."""

    FIELDS = ("mean", "cov", "attack", "score")

    def __init__(self, estimator):
        self.estimator, self.stamps = estimator, []

    def add(self, step: int, output) -> None:
        for name in self.FIELDS:
            value = getattr(output, name)
            if isinstance(value, Tensor) and (version := _version_of(value)) is not None:
                self.stamps.append((step, name, value, version))

    def check(self) -> None:
        for step, name, value, version in self.stamps:
            if value._version != version:
                raise RuntimeError(
                    f"{type(self.estimator).__name__}: the {name} it handed out at step {step} "
                    "was written in place by a later step (every step's output would read the "
                    "last one's values). A step leaves its carry's tensors as they were and "
                    "returns new ones: compute out of place (mean = 0.5 * mean + y, not "
                    "mean.mul_(0.5).add_(y)) or hand out a copy"
                )


def _version_of(t: Tensor) -> int | None:
    """``t``'s version counter (moved by every in-place write), or ``None`` where it keeps
    none (an inference tensor)."""
    try:
        return t._version
    except RuntimeError:
        return None


def _tensors_of(output) -> list[Tensor]:
    """The tensors of a step output (its fields and ``extras``), or none (``None``)."""
    if output is None:
        return []
    fields = [v for v in output if isinstance(v, Tensor)]
    extras = getattr(output, "extras", None) or {}
    return fields + [v for v in extras.values() if isinstance(v, Tensor)]


def _check_parts(estimator, attack) -> None:
    """The estimator and the attack are the library's objects, and an attack that reads the
    estimator's output (:attr:`~difffilter.attack.Attack.reads_view`) has one to read."""
    if estimator is not None and not isinstance(estimator, Estimator):
        raise TypeError(
            "estimator must be a difffilter.estimator.Estimator (e.g. difffilter.KalmanFilter()) "
            f"or None; got {type(estimator).__name__}"
        )
    if attack is None:
        return
    if not isinstance(attack, Attack):
        raise TypeError(
            "attack must be a difffilter.attack.Attack (e.g. difffilter.threats.Bias(...); "
            f"a dict names one only in a threat set: threat_from_dict) or None; got "
            f"{type(attack).__name__}"
        )
    if attack.reads_view and estimator is None:
        raise ValueError(
            f"attack {type(attack).__name__} reads the estimator's output (reads_view = True), "
            "and this loop has no estimator: it would read None at every step. Give the loop "
            "its estimator (closed_loop(..., estimator=...)); an open-loop scenario simulates "
            "its runs once for every estimator, without one, so an adaptive attack runs only "
            "in a loop of its own or a closed-loop scenario"
        )


def _three(returned, attack, k: int) -> tuple:
    """What ``attack.step`` returned at step ``k``, checked to be ``(state, value, flag)``
    (two values had failed as a bare "not enough values to unpack", naming no attack)."""
    if type(returned) is tuple and len(returned) == 3:
        return returned
    if isinstance(returned, tuple | list) and len(returned) == 3:  # a list, a namedtuple
        return tuple(returned)
    got = (
        f"{len(returned)} values" if isinstance(returned, tuple | list) else type(returned).__name__
    )
    raise ValueError(
        f"attack {type(attack).__name__}.step returned {got} at step {k}; it returns "
        "(state, value, flag): its state for the next step, the value a_k and the flag l_k"
    )


def _checked_value(attack, value: Tensor, flag: Tensor, signal: Tensor, k: int,
                   what: str = "y") -> tuple[Tensor, Tensor]:  # fmt: skip
    """The attack's value and flag at step ``k`` as the attacked signal's shape ``[..., d]``
    (the flag ``[...]`` or ``[..., d]``), after checking them: a value of the signal's
    entries and dtype that broadcasts to it (one value for every run, ``[d]``, is expanded:
    a flag ``[B]`` beside it was read per entry where ``B = d``), and a bool flag of the rank
    of ``[...]`` (per run) or ``[..., d]`` (per entry) whose sizes broadcast, expanded to it (a trial's
    flag ``[1]`` for two runs was recorded as ``[1, T]`` flags beside ``[2, T]`` runs).
    Shape checks only: nothing is read from the tensors."""
    shape = signal.shape
    if (type(value) is Tensor and type(flag) is Tensor and value.shape == shape
            and value.dtype == signal.dtype and flag.dtype is torch.bool
            and flag.shape in (shape, shape[:-1])):  # fmt: skip
        return value, flag  # the usual step, checked in a few comparisons (the loop's every step)
    name, shape = f"attack {type(attack).__name__}.step", tuple(shape)
    # one entry per entry of the signal: a [..., 1] value on a signal of two entries had
    # been broadcast to both (a trial's attack on one of two sensors hit both, silently)
    if (not isinstance(value, Tensor) or value.dim() == 0 or value.shape[-1] != shape[-1]
            or not _broadcasts(value.shape, signal.shape)):  # fmt: skip
        got = tuple(value.shape) if isinstance(value, Tensor) else type(value).__name__
        raise ValueError(
            f"{name} returned a value of shape {got} at step {k}; the signal it attacks is "
            f"{shape}: a value of its {shape[-1]} entries that broadcasts to that shape "
            f"([..., {shape[-1]}], or [{shape[-1]}] for every run; zeros where an entry is "
            "not attacked)"
        )
    if value.dtype != signal.dtype:
        raise ValueError(
            f"{name} returned a value of dtype {value.dtype} at step {k}; the signal it "
            f"attacks is {signal.dtype}: make it of that dtype (init's dtype=)"
        )
    if not isinstance(flag, Tensor) or flag.dtype is not torch.bool:
        got = f"dtype {flag.dtype}" if isinstance(flag, Tensor) else type(flag).__name__
        raise ValueError(
            f"{name} returned a flag of {got} at step {k}; a flag is a bool tensor, "
            f"{list(shape[:-1])} (per run) or {list(shape)} (per entry), e.g. "
            f"torch.full({what}.shape[:-1], True)"
        )
    per = flag.dim() - (len(shape) - 1)
    if per not in (0, 1) or not _broadcasts(flag.shape, shape[: flag.dim()]):
        # a flag of the entries' size one rank short reads as per run: where the runs are
        # as many as the entries it is taken so (a trial's [dy] flag left a run unattacked)
        every = [1] * (len(shape) - 1) + [shape[-1]]
        hint = (f"; a flag per entry for every run is {every}, not {list(flag.shape)} (a flag "
                "of one rank less than the signal is per run)"
                if per == 0 and flag.shape[-1:] == shape[-1:] else "")  # fmt: skip
        raise ValueError(
            f"{name} returned a flag of shape {tuple(flag.shape)} at step {k}; the signal it "
            f"attacks is {shape}: a flag {list(shape[:-1])} (per run) or {list(shape)} (per "
            f"entry){hint}"
        )
    value = value if value.shape == signal.shape else value.expand(shape)
    full = shape[: flag.dim()]
    return value, (flag if flag.shape == full else flag.expand(full))


def _checked_input(controller, u, x: Tensor, plant, k: int):
    """The controller's input ``u_k`` after checking it against the loop: ``[B, du]`` (the
    runs of ``x [B, dx]``, the plant's ``dim_u``) in ``x``'s dtype and on its device, or
    ``None`` for a plant without input (``dim_u = 0``). A ``[B, 1, du]`` grew the plant's
    state by an axis a step (memory ×B a step, then an error at the end naming nothing).
    Shape checks only: NaN is found with the next step's measurement
    (:func:`_estimator_input`; without an estimator, :func:`_check_finite` after the loop)."""
    du = plant.dim_u
    if type(u) is Tensor and u.dim() == 2 and u.shape[1] == du and u.shape[0] == x.shape[0] \
            and u.dtype == x.dtype and u.device == x.device:  # fmt: skip
        return u  # the usual step, in a few comparisons
    name = f"{type(controller).__name__}.{'init' if k == 0 else '__call__'}"
    when = "(u_0)" if k == 0 else f"at step {k} (u_{k})"
    if u is None:
        if du == 0:
            return None
        raise ValueError(
            f"{name} returned None {when}, and the plant has {du} input(s) (dim_u = {du}): "
            f"return u [{x.shape[0]}, {du}] (zeros for no input; the loop would record no "
            "input at that step)"
        )
    if du == 0:
        raise ValueError(
            f"{name} returned an input {when}, and the plant has none (dim_u = 0): return "
            "None, or give the loop a plant with inputs"
        )
    if not isinstance(u, Tensor):
        raise TypeError(
            f"{name} returned a {type(u).__name__} {when}; an input is a tensor "
            f"[{x.shape[0]}, {du}] (one row per run)"
        )
    if tuple(u.shape) != (x.shape[0], du):
        gain = getattr(controller, "gain", None)
        hint = (f" (its gain K is {tuple(gain.shape)}: K must be [du, dx] = [{du}, "
                f"{x.shape[-1]}])" if isinstance(gain, Tensor) else "")  # fmt: skip
        raise ValueError(
            f"{name} returned an input of shape {tuple(u.shape)} {when}; the loop needs "
            f"[{x.shape[0]}, {du}] (one row per run, the plant's dim_u = {du}){hint}"
        )
    raise ValueError(
        f"{name} returned an input of dtype {u.dtype} on {u.device} {when}; the loop's "
        f"state is {x.dtype} on {x.device}: return it in that dtype, on that device "
        "(init's dtype= and device=)"
    )


def _broadcasts(shape, target) -> bool:
    """``shape`` broadcasts to ``target`` without changing it."""
    try:
        return broadcast_shapes(shape, target) == torch.Size(target)
    except RuntimeError:
        return False


def _estimator_input(received: Tensor, mask: Tensor | None, k: int, attack,
                     u: Tensor | None = None, controller=None) -> Tensor:  # fmt: skip
    """Step ``k``'s measurement as the estimator's step takes it (unchecked): a NaN or Inf
    in a received entry raises, as :func:`open_loop` refuses it in ``ys``; one in an entry
    the schedule drops is replaced by zero, as there (``0 · NaN`` would still be NaN in the
    masked update). The input ``u = u_{k−1}`` the estimator reads beside it is checked in
    the same reduction: a controller's NaN was blamed on the plant a step later, or, on
    dropped entries, ran through the loop unnamed. One reduction a step; nothing is
    checked where values are unknown (the ``meta`` device)."""
    if received.device.type == "meta":
        return received
    finite = torch.isfinite(received)
    u_finite = None if u is None else torch.isfinite(u)
    if bool(finite.all() if u_finite is None else finite.all() & u_finite.all()):
        return received  # one host read a step
    if u_finite is not None and not bool(u_finite.all()):
        run = int((~u_finite).any(-1).nonzero()[0, 0])
        source = ("controller.init" if k == 1 else f"the controller at step {k - 1}"
                  ) if controller is not None else "the loop's state"  # fmt: skip
        raise ValueError(
            f"the input u_{k - 1} that drives step {k} contains NaN or Inf (first in run {run}): "
            f"{source} returned it ({type(controller).__name__})"
        )
    bad = ~finite if mask is None else ~finite & mask
    if bool(bad.any()):
        where = [int(i) for i in bad.nonzero()[0]]
        run = where[0] if len(where) == 2 else tuple(where[:-1])
        source = (
            "the plant" if attack is None else f"the attack ({type(attack).__name__}) or the plant"
        )
        raise ValueError(
            f"the measurement received at step {k} contains NaN or Inf (first in run {run}, "
            f"entry {where[-1]}): {source} produced it, and an estimator cannot take it "
            "(open_loop refuses the same in ys)"
        )
    return torch.where(
        mask, received, torch.zeros((), dtype=received.dtype, device=received.device)
    )


def _check_finite(
    traj: Trajectories, first: int, attack, controller, channel: Channel = Channel.SENSOR
) -> None:
    """Without an estimator, :func:`_estimator_input`'s checks of what the controller and
    the attacker put into the loop, made once on the records of steps ``first + 1 …`` (one
    reduction a loop, not a host read a step: ``scenario.simulate`` runs without an
    estimator), raising its error at the first step that fails: a controller's NaN input or
    an attacker's NaN in a received entry had passed silently into the states and the data
    (README, "Input validation"). A NaN the plant makes itself (its state, or its
    measurement before any attack) ends the checks: it is the simulation's truth, recorded
    for the caller, and ``scenario.simulate`` names the model's function that gave it at its
    step (a user trial), which the loop could only call "the plant". An attack on the
    actuators is checked on what reached the plant (``traj.attack``) before the states it
    made NaN are taken for the plant's own (a review: its NaN had passed as the plant's)."""
    recv, mask, us = traj.y_recv, traj.mask, traj.us
    if recv.device.type == "meta":
        return
    received = recv.new_ones((), dtype=torch.bool) if mask is None else mask
    own = (~torch.isfinite(traj.y_true) & received).any(-1) | (~torch.isfinite(traj.x)).any(-1)
    made = (~torch.isfinite(recv) & received & torch.isfinite(traj.y_true)).any(-1)
    bad = own | made
    if us is not None:
        bad = bad | (~torch.isfinite(us)).any(-1)
    pushed = None
    if channel is Channel.ACTUATOR and traj.attack is not None:
        pushed = (~torch.isfinite(traj.attack)).any(-1)
        bad = bad | pushed
    if not bool(bad.any()):
        return  # one host read a loop
    t = int(bad.any(0).nonzero()[0, 0])
    if pushed is not None and bool(pushed[:, t].any()):
        run = int(pushed[:, t].nonzero()[0, 0])
        raise ValueError(
            f"the attack ({type(attack).__name__}) put NaN or Inf into the input that drives "
            f"step {first + t + 1} (first in run {run}): an attack on the actuators must "
            "inject finite values"
        )
    u = None if us is None else us[:, t]
    if (u is None or bool(torch.isfinite(u).all())) and bool(own[:, t].any()):
        return  # the plant's own, first (its caller names it)
    _estimator_input(recv[:, t], None if mask is None else mask[:, t], first + t + 1, attack, u,
                     controller)  # fmt: skip


def _check_lengths(plant, noise, mask, state: LoopState, steps: int) -> None:
    """What the loop reads row by row (the schedule, replayed noise) covers its steps
    ``state.k + 1 … state.k + steps``, and replayed noise fits the plant and the runs."""
    end, B, dy = state.k + steps, state.x.shape[0], plant.dim_y
    if mask is not None:
        if not isinstance(mask, Tensor) or mask.dtype is not torch.bool:
            got = f"dtype {mask.dtype}" if isinstance(mask, Tensor) else type(mask).__name__
            raise ValueError(
                f"mask must be a bool tensor [B, T, dy] (True where an entry is received); "
                f"got {got} (a float mask was read as a weight: open_loop refuses it too)"
            )
        if mask.dim() != 3 or mask.shape[0] != B or mask.shape[1] < end or mask.shape[2] != dy:
            raise ValueError(
                f"mask must be [{B}, T >= {end}, {dy}] (the runs, a row for every step up to "
                f"{end}, indexed by the absolute step, and the plant's dim_y); got "
                f"{tuple(mask.shape)}"
            )
    if isinstance(noise, ReplayedNoise):
        dims = (plant.dim_x, plant.dim_y)
        for name, draws, dim in zip(
            ("process", "measurement"), (noise.process, noise.measurement), dims
        ):
            if (
                draws.dim() != 3
                or draws.shape[0] != B
                or draws.shape[1] < end
                or draws.shape[2] != dim
            ):
                raise ValueError(
                    f"ReplayedNoise's {name} noise must be [{B}, T >= {end}, {dim}] (the runs, "
                    f"a row for every step up to {end}, the plant's width); got "
                    f"{tuple(draws.shape)}"
                )  # fmt: skip
            if draws.dtype != state.x.dtype:
                raise ValueError(
                    f"ReplayedNoise's {name} noise is {draws.dtype}, the loop's state "
                    f"{state.x.dtype}: draw it in the plant's dtype"
                )


def _check_attack_horizon(attack, state: LoopState, steps: int) -> None:
    """The attacker's state reaches step ``state.k + steps``
    (:meth:`~difffilter.attack.Attack.last_step`: a tabulated attack's rows, drawn for the
    loop's ``horizon`` at its start); past it, torch's IndexError named neither."""
    if attack is None or state.attack is None:
        return
    last, end = attack.last_step(state.attack), state.k + steps
    if last is not None and end > last:
        raise ValueError(
            f"horizon: attack {type(attack).__name__} was tabulated for steps 1 … {last} when "
            f"the loop started (its horizon, default the first call's steps), and this call runs "
            f"to step {end}: start the loop with horizon={end} or more"
        )


def _with_input_memory(input_loss: InputLoss, plant, state: LoopState, steps: int) -> LoopState:
    """``state`` with the input channel's memories (the actuators' last applied input and
    the estimator's knowledge of it) after checking ``input_loss``'s mask against the loop:
    zero for a new loop; a loop resumed under a holding channel must have kept them."""
    u = state.u
    input_loss.check(state.x.shape[0], 0 if u is None else plant.dim_u, state.k + steps)
    if input_loss.mask.device != state.x.device:
        raise ValueError(
            f"InputLoss's mask is on {input_loss.mask.device} and the loop on "
            f"{state.x.device}: give it the plant's device"
        )
    if input_loss.on_loss is OnLoss.ZERO or state.inputs is not None:
        return state
    if state.k > 0:
        raise ValueError(
            "input_loss holds the last input that arrived, and the loop's state (state= or "
            "fork=) holds none: it comes from a loop without input_loss or with "
            "on_loss='zero'. Resume a loop run with a holding input_loss, or start this one "
            "from step 0"
        )
    return state._replace(inputs=input_loss.start(u))


def _check_resumed_attack(kept: LoopState, attack) -> None:
    """A loop resumed from ``state=`` goes on with the attack whose state it kept (none
    where it ran without one, then ``attack=None``), not another: the attacker's state is
    that attack's own tables, so another attack had stepped them under its name (a ramp
    resumed on a bias's state injected the bias), and an attack on a loop kept without one
    had no state to step (a bare ``TypeError`` on ``None``); and a loop kept under an
    attack is not resumed without one (``attack=None``, the default, had run the rest
    attack-free while the returned state still named the attacker: a closed-loop trial)."""
    if kept.k == 0:
        return
    if attack is None:
        if kept.attack is not None:
            name = type(kept.attacker).__name__ if kept.attacker is not None else "an attack"
            raise ValueError(
                f"state: the loop kept ran under {name} and this call gives attack=None: a "
                "resumed loop goes on with the attack it kept, so give it again (attack=, "
                "the same object or one equal to it); to end the attack, start a new loop "
                "or continue a fork of the loop without attack"
            )
        return
    if kept.attack is None:
        raise ValueError(
            f"state: the loop kept ran without attack, so attack {type(attack).__name__} has "
            "no state to go on from: start the loop with the attack (its onset after this "
            "chunk's first step), or continue a fork of the loop without attack (fork=, "
            "with ReplayedNoise)"
        )
    made = kept.attacker
    if made is not None and made is not attack and _differ(made, attack):
        raise ValueError(
            f"state: the loop kept ran under {type(made).__name__} and this call gives "
            f"{type(attack).__name__}: a resumed loop goes on with the attack it kept (its "
            "state is that attack's own), the same object or one equal to it; to change the "
            "attack, start a new loop or continue a fork of the loop without attack"
        )


def _differ(made, given) -> bool:
    """Whether ``given`` is shown to be another attack than ``made``: another class, or a
    dataclass of other field values (tensors compared by value). An attack of the same
    class whose values cannot be compared (an attack of one's own without ``__eq__``, a
    :class:`~difffilter.models.attacks.Signal` made anew from the same table) is taken for
    the same: a loop run in chunks may build its attack again for each."""
    if type(made) is not type(given):
        return True
    if not dataclasses.is_dataclass(made):
        return False
    return any(_values_differ(getattr(made, f.name), getattr(given, f.name))
               for f in dataclasses.fields(made))  # fmt: skip


def _values_differ(a, b) -> bool:
    """Whether two field values are shown to differ (``False`` where they cannot be told
    apart or compared)."""
    if isinstance(a, Tensor) or isinstance(b, Tensor):
        return not (isinstance(a, Tensor) and isinstance(b, Tensor) and _same(a, b))
    if isinstance(a, torch.nn.Module) and isinstance(b, torch.nn.Module):
        # by their tensors, as the loop compares its models: a module's == is identity, and a
        # covert attack's plant restored by torch.load or pickle (or built again for a chunk)
        # had refused the resume of its own loop (a serialisation trial)
        return not _same_model(a, b)
    if isinstance(a, (tuple, list)) and isinstance(b, (tuple, list)):
        return len(a) != len(b) or any(_values_differ(x, y) for x, y in zip(a, b))
    try:
        return not bool(a == b)
    except (RuntimeError, TypeError, ValueError):
        return False


def _checked_correction(attack, correction, y: Tensor, k: int) -> Tensor:
    """A covert attack's sensor correction at step ``k``: a floating tensor of ``y``'s shape
    ``[B, dy]`` (or one that broadcasts to it over the runs). A ``[B, 1]`` one had been spread
    over every sensor, an integer one taken, and others had failed in torch or blamed the
    controller (a trial of the adaptive attacks)."""
    fits = isinstance(correction, Tensor) and correction.is_floating_point()
    if fits:
        try:
            fits = (correction.shape[-1:] == y.shape[-1:]
                    and torch.broadcast_shapes(correction.shape, y.shape) == y.shape)  # fmt: skip
        except RuntimeError:
            fits = False
    if not fits:
        got = (f"{correction.dtype} {tuple(correction.shape)}" if isinstance(correction, Tensor)
               else type(correction).__name__)  # fmt: skip
        raise ValueError(
            f"attack {type(attack).__name__}'s conceal returned {got} at step {k}; it returns "
            f"the correction added to the measurement, a floating tensor [..., {y.shape[-1]}] "
            f"of y's shape {tuple(y.shape)}"
        )
    return correction


def _check_resumed(kept: LoopState, given: str, estimator, model, plant, controller) -> None:
    """A loop resumed from ``kept`` (``given``: ``"state"`` or ``"fork"``) runs its
    estimator on the carry kept (one exactly where the kept loop had an estimator), with
    ``model`` (where given) the model that carry filters with, and from a finite last input
    (:class:`KnownInputs` leaves NaN after its table's last row). Each had been taken
    unsaid or failed deep inside: a resumed estimator with no carry (an ``AttributeError``
    on ``None``), another ``model`` ignored (the carry's filtered on), the input after a
    known-inputs table a copy of its last row."""
    carry = kept.carry
    if (carry is None) != (estimator is None):
        had, has = ("no", "an") if carry is None else ("an", "no")
        raise ValueError(
            f"{given}: the loop kept had {had} estimator and this one has {has}: resume a "
            "loop with the estimator it ran (its carry is the estimator's state), or start a "
            "new loop"
        )
    if carry is not None and not isinstance(carry, estimator.carry_type):
        # (another kind of estimator had failed deep inside on the kept carry: "'GaussianState'
        # object has no attribute 'particles'", a trial of the resumed loops)
        raise TypeError(
            f"{given}: the loop kept ran another estimator (its carry is a "
            f"{type(carry).__name__}; {type(estimator).__name__} steps a "
            f"{estimator.carry_type.__name__}): resume with the estimator it ran"
        )
    check_model(plant, prior=False)
    x = kept.x
    if isinstance(x, Tensor) and x.shape[-1] != plant.dim_x:
        raise ValueError(
            f"{given}: the loop kept has states of {x.shape[-1]} entries and the plant "
            f"{plant.dim_x} (dim_x): resume a loop on its own plant"
        )
    held = None if carry is None else estimator._model_of(carry)
    if held is not None and isinstance(x, Tensor):
        # the plant against the carry's model, as a fresh start checks it (a plant of one
        # sensor had fed the estimator's two a broadcast measurement, silently)
        _check_estimator_model(held, plant, controller, x.shape[:-1])
    if model is not None and held is not None and not _same_model(held, model):
        raise ValueError(
            f"model: the {given}'s estimator carry filters with its own model, and another "
            "was given (its steps would have ignored it): resume with model=None (the "
            "carry's), or start a new loop on the new model"
        )
    check = getattr(controller, "check", None)
    if callable(check) and isinstance(x, Tensor):  # (fields written between chunks)
        check(x.shape[:-1], x.dtype, x.device)
    u = kept.u
    if isinstance(u, Tensor) and not bool(torch.isfinite(u).all()):
        raise ValueError(
            f"{given}: its last input u_{kept.k} is not finite: a KnownInputs(us) table ends "
            f"before step {kept.k + 1} (give the first chunk the whole table, us [B, horizon, "
            "du], so that it leaves the input of the next step)"
        )


def _same_model(a, b) -> bool:
    """Whether two models are one, or two modules of one type holding equal tensors (a
    chunked loop may build its model anew for every chunk); models that are not modules
    are not compared (no claim)."""
    if a is b or not (isinstance(a, torch.nn.Module) and isinstance(b, torch.nn.Module)):
        return True
    if type(a) is not type(b):
        return False
    sa, sb = a.state_dict(keep_vars=True), b.state_dict(keep_vars=True)
    return sa.keys() == sb.keys() and all(_same(sa[k], sb[k]) for k in sa)


def _check_attackers_plant(attack, plant) -> None:
    """An attack that runs a model of the plant (a covert one's ``plant``) has the loop
    plant's sizes (another had failed inside its step's matmul: a review; the same check
    as :func:`difffilter.threats.check_attack_fits`)."""
    theirs = getattr(attack, "plant", None)
    if theirs is None:
        return
    for what in ("dim_x", "dim_u", "dim_y"):
        a, b = getattr(theirs, what, None), getattr(plant, what, None)
        if a is not None and b is not None and a != b:
            raise ValueError(
                f"the covert attack's plant has {what} = {a} and the loop's plant {b}: give "
                f"{type(attack).__name__} a model of this plant"
            )


def _start(plant, steps, horizon, x0, estimator, model, controller, attack, attack_generator,
           generator) -> LoopState:  # fmt: skip
    """The state before step 1 (after checking the plant and ``x0``)."""
    check_model(plant)
    if not isinstance(x0, Tensor) or x0.dim() != 2 or x0.shape[-1] != plant.dim_x:
        got = tuple(x0.shape) if isinstance(x0, Tensor) else x0
        raise ValueError(
            f"x0 [B, {plant.dim_x}] (one initial state per run) is needed to start a loop (or "
            f"pass state= to resume); got {got!r}"
        )
    for what, m in (("the plant", plant), ("the estimator's model", model)):
        held = _dtype_of(m)
        if held is not None and held != x0.dtype:
            raise ValueError(
                f"x0 is {x0.dtype} and {what} is {held}: give the loop one dtype (x0 = "
                f"x0.to({held}), or the model in x0's dtype)"
            )
    if horizon is not None and horizon < steps:
        raise ValueError(f"horizon (the whole loop's T) must be >= steps={steps}; got {horizon!r}")
    steps = horizon or steps
    _check_controller(controller)
    # the runs: x0's broadcast with a sweep's parameter sets (x0 [1, dx] on a plant of 3 sets
    # makes 3 runs), so the controller, the attack and the estimator start with every run
    # (the controller's u_0 of x0's one run failed in a torch stack after the last step)
    runs = check_model_batch(plant, x0.shape[:-1], "x0's runs")
    _one_axis_of_runs(plant, runs, "the plant")
    x0 = x0.expand(*runs, plant.dim_x) if runs != x0.shape[:-1] else x0
    if estimator is not None:
        _check_estimator_model(model, plant, controller, runs)
    batch, dtype, device = x0.shape[:-1], x0.dtype, x0.device
    u = None
    if controller is not None:
        u = _checked_input(controller, controller.init(batch, dtype, device), x0, plant, 0)
    a_state = None
    if attack is not None:
        _check_attackers_plant(attack, plant)
        dim = attack_dim(plant, attack.channel)
        a_state = attack.init(batch, steps, dim, attack_generator, dtype=dtype, device=device)
    carry = None
    if estimator is not None:
        carry = estimator._init(model, batch, Generators.of(generator))
    return LoopState(0, x0, u, a_state, carry, None, None, attack)


def _check_controller(controller) -> None:
    """``controller`` is ``None`` or keeps the :class:`Controller` protocol (a plain function
    or a gain tensor failed with "'function' object has no attribute 'init'")."""
    if controller is None or (callable(getattr(controller, "init", None)) and callable(controller)):
        return
    raise TypeError(
        "controller must be a difffilter.loop.Controller: an object with init(batch_shape, "
        "dtype, device) -> u_0 [B, du] and __call__(k, y, out) -> u_k [B, du] (e.g. "
        "difffilter.loop.KnownInputs(us), or a class of your own holding a gain K); got "
        f"{type(controller).__name__}"
    )


def _check_estimator_model(model, plant, controller, runs: torch.Size) -> None:
    """The estimator's model fits the loop: it measures the plant's entries, knows the
    plant's inputs where a controller sets them, and takes its runs (a model of another
    ``dim_y`` was fed a broadcast measurement and estimated silently wrong; one without an
    input ignored every ``u``; one of another ``dim_u`` or ``dim_x`` failed inside torch)."""
    if model is not plant:
        check_model(model)
    if model.dim_y != plant.dim_y:
        raise ValueError(
            f"model (the estimator's) measures {model.dim_y} entries and the plant "
            f"{plant.dim_y}: the estimator receives the plant's measurements [B, {plant.dim_y}]"
        )
    if controller is not None and model.dim_u != plant.dim_u:
        raise ValueError(
            f"model (the estimator's) has {model.dim_u} input(s) (dim_u) and the plant "
            f"{plant.dim_u}: the estimator is given the controller's u [B, {plant.dim_u}] at "
            f"every step; give its model the plant's B [dx, {plant.dim_u}] (zero columns for "
            "inputs it should not know)"
        )
    both = check_model_batch(model, runs, "the loop's runs (x0 broadcast with the plant's sets)")
    _one_axis_of_runs(model, both, "model (the estimator's)")


def _one_axis_of_runs(model, runs: torch.Size, what: str) -> None:
    """The loop's runs are one axis ``B``: its records (``[B, T, …]``), the schedule, replayed
    noise and the controller's inputs are laid out so. A model of a 2-D batch of parameter
    sets (``F [2, 3, dx, dx]``) had made runs ``(2, 3)`` that were recorded with time between
    the two run axes (``x [2, T, 3, dx]`` beside the estimator's ``[2, 3, T, dx]``), scored
    silently on misaligned axes."""
    if len(runs) <= 1:
        return
    own = tuple(model_batch_shape(model))
    raise ValueError(
        f"{what} has parameter sets of batch shape {own}, which makes the loop's runs "
        f"{tuple(runs)}: closed_loop runs one axis of runs, x0 [B, dx] with a model of B "
        "parameter sets (F [B, dx, dx], …) or of one. Flatten the sets to one axis "
        "(F.reshape(-1, dx, dx), and the other parameters alike) and reshape the results"
    )


def _dtype_of(model) -> torch.dtype | None:
    """The dtype of ``model``'s initial mean (a :class:`~difffilter.StateSpaceModel`'s), or
    ``None`` where it has none to read."""
    mean = getattr(getattr(model, "initial", None), "mean", None)
    return mean.dtype if isinstance(mean, Tensor) else None


def _resume(fork: LoopFork, plant, attack, attack_generator, channel, horizon):
    """``(state, records, outputs)`` to continue ``fork`` with ``attack``: its first
    ``fork.state.k`` steps recorded as the attack would have made them."""
    if fork.records["attack"] and fork.records["attack"][0] is not None:
        raise ValueError("fork: a loop resumes only the fork of a loop without attack")
    state = fork.state.copy()
    records = {key: list(v) for key, v in fork.records.items()}
    if attack is None:
        return state, records, list(fork.outputs)
    if not isinstance(attack, TabulatedAttack) or getattr(attack, "conceals", False):
        raise ValueError(
            "fork: the attack must read nothing (a TabulatedAttack without concealment) to "
            f"continue a loop without attack; got {type(attack).__name__}"
        )
    x = state.x
    dim = attack_dim(plant, channel)
    a_state = attack.init(x.shape[:-1], horizon, dim, attack_generator, dtype=x.dtype,
                          device=x.device)  # fmt: skip
    k, time = state.k, a_state[0].dim() - 2  # the tables' first k rows are steps 1 … k
    values, flags = (table.narrow(time, 0, k) for table in a_state)  # TabulatedAttack.step
    acting = flags.movedim(time, 0).reshape(k, -1).any(-1)
    if bool(acting.any()):
        raise ValueError(f"fork: the attack acts at step {int(acting.nonzero()[0]) + 1}, at or "
                         f"before the fork's step {k}: those steps are not the loop's without attack")  # fmt: skip
    # the fork recorded the steps of its own loop, first + 1 … k (a loop resumed in chunks
    # records from its chunk's first step: all k rows had been stacked beside them)
    recorded = len(records["x"])
    values, flags = (table.narrow(time, k - recorded, recorded) for table in (values, flags))
    signal = torch.stack(records["u" if channel is Channel.ACTUATOR else "y"], time)
    _, injected = inject(channel, signal, values, flags)  # every step before the fork at once
    for key, table in (("attack", injected), ("value", values), ("flag", flags)):
        records[key] = list(table.unbind(time))
    if channel is Channel.ACTUATOR and records["arrived"]:  # (under input_loss: none acted)
        records["acting"] = [torch.zeros_like(arrived) for arrived in records["arrived"]]
    return state._replace(attack=a_state, attacker=attack), records, list(fork.outputs)


def _check_fork_input_loss(kept: dict, input_loss, first: int) -> None:
    """A fork kept under an :class:`~difffilter.input_loss.InputLoss` is continued under the
    same channel: its arrivals at the fork's steps ``first + 1 …`` and what a loss does
    (``on_loss``, ``acknowledged``). Another had been taken: the result stitched the fork's
    steps from one channel to the rest from another (a trial: 20 of 20 recorded arrival
    rows not the channel's given, lost packets of a "zero" channel holding an input)."""
    end = first + len(kept["arrived"])
    channel = (input_loss.on_loss, input_loss.acknowledged)
    if kept.get("input_channel") and kept["input_channel"][0] != channel:
        was = kept["input_channel"][0]
        raise ValueError(
            f"fork: input_loss (on_loss={channel[0].value!r}, acknowledged={channel[1]}) is not "
            f"the channel of the loop that kept the fork (on_loss={was[0].value!r}, "
            f"acknowledged={was[1]}): continue it with that loop's"
        )
    rows = input_loss.mask[:, first:end]
    arrived = torch.stack(kept["arrived"], 1)
    rows = rows.unsqueeze(-1).expand_as(arrived) if rows.shape != arrived.shape else rows
    if rows.shape != arrived.shape or not torch.equal(rows, arrived):
        raise ValueError(
            f"fork: input_loss's arrivals differ from those of the loop that kept the fork at "
            f"steps {first + 1} … {end} (the fork's steps): continue it with that loop's"
        )


def _check_fork_mask(kept: list, mask: Tensor | None, first: int) -> None:
    """A fork is continued under the schedule of the loop that kept it: ``kept`` (its rows
    ``m_k`` of steps ``first + 1 …``, ``None`` without a schedule) are ``mask``'s. A fork
    kept under a mask and continued without it (or under another) had filtered its steps
    with entries dropped while the result said all were received (``Trajectories.mask``
    ``None``): two loops stacked as one, as with ``input_loss`` (refused beside it)."""
    if kept[0] is None and mask is None:
        return
    if kept[0] is None or mask is None:
        raise ValueError(
            "fork: continue a fork with the mask of the loop that kept it (or without one, as "
            f"it was kept); the fork was kept {'without' if kept[0] is None else 'under'} a "
            f"mask and this loop is given {'none' if mask is None else 'one'}"
        )
    end = first + len(kept)
    rows = mask[:, first:end]
    if rows.shape[0] != kept[0].shape[0] or not torch.equal(torch.stack(kept, 1), rows):
        raise ValueError(
            f"fork: mask differs from the mask of the loop that kept the fork at steps "
            f"{first + 1} … {end} (the fork's steps): continue it with that loop's mask"
        )


def _check_fork_noise(
    kept: ReplayedNoise | None, noise: ReplayedNoise, first: int, steps: int
) -> None:
    """A fork is continued on the draws of the loop that kept it (``kept``) at its steps
    ``first + 1 … first + steps``: a continuation given other noise had joined the fork's
    steps to steps on other draws, and the result read as one loop (a closed-loop trial)."""
    if kept is None or kept is noise:  # (None: a fork made by hand, nothing to compare)
        return
    end = first + steps
    for name in ("process", "measurement"):
        mine, given = getattr(kept, name)[:, first:end], getattr(noise, name)[:, first:end]
        if mine.shape != given.shape or not torch.equal(mine, given.to(mine)):
            raise ValueError(
                f"fork: noise differs from the ReplayedNoise of the loop that kept the fork "
                f"({name} noise at steps {first + 1} … {end}, the fork's steps): continue it "
                "on that loop's noise"
            )


def _trajectories(rec, mask, k0, k1, channel) -> Trajectories:
    """Stack the recorded steps ``k0 + 1 … k1`` into :class:`Trajectories`."""
    x, y, recv = (torch.stack(rec[key], 1) for key in ("x", "y", "recv"))
    us = None if rec["u"][0] is None else torch.stack(rec["u"], 1)
    B, T = x.shape[:2]
    m = None if mask is None else mask[:, k0:k1]
    if channel is None:
        attack = y.new_zeros(B, T, 0)
        flags = torch.zeros(B, T, dtype=torch.bool, device=y.device)
        values = attack
    else:
        attack, values = torch.stack(rec["attack"], 1), torch.stack(rec["value"], 1)
        own_flags = torch.stack(rec["flag"], 1)
        entrywise = own_flags.dim() == 3
        if channel is not Channel.ACTUATOR and m is not None:
            # an attack on a packet never sent is none: entry by entry (an attack on a
            # sensor whose reading was lost this step is not one, whatever else arrived)
            seen = own_flags & m if entrywise else own_flags.unsqueeze(-1) & m
            flags = seen.any(-1)
            attack = torch.where(m, attack, torch.zeros_like(attack))
        else:
            flags = own_flags.any(-1) if entrywise else own_flags
            if channel is Channel.ACTUATOR and rec["acting"]:
                # input_loss: the attack's own steps, lost packet or not (the plant carries
                # what it injected before), and those where a held input carries it
                flags = torch.stack(rec["acting"], 1).any(-1)
    info = {"attack_values": values, "attack_channel": channel}
    if channel is not None:
        info["attack_flags"] = own_flags
    if rec["concealment"]:
        info["attack_concealment"] = torch.stack(rec["concealment"], 1)
    if rec["applied"]:
        info["inputs_applied"] = torch.stack(rec["applied"], 1)
        info["inputs_sent"] = torch.stack(rec["sent"], 1)
        info["input_mask"] = torch.stack(rec["arrived"], 1)
    return Trajectories(x, y, recv, us, m, attack, flags, info)
