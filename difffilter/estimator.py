"""The estimator contract: what every attack-aware filter and detector returns.

Every FDI estimator of :mod:`difffilter.fdi` is a function
``(model, ys, us=None, *, mask=None, ...) -> EstimatorOutput`` over a batch of runs:

* ``ys [B, T, dy]`` — received measurements ``ỹ_1 … ỹ_T`` (possibly attacked);
* ``us [B, T, du]`` or ``None`` — the inputs ``u_0 … u_{T−1}`` the estimator knows;
* ``mask [B, T, dy]`` (bool) or ``None`` — which entries were received (Round-Robin
  scheduling, packet loss); unreceived entries carry no information.

and returns the state estimate, optionally its covariance, optionally an estimate of the
injected attack signal, and optionally a per-step detection. Evaluation, training and
reports consume this one type, whatever the algorithm behind it; what a filter records
beyond it (the PF's ESS, the modified PF's ``ζ_k``, the NIS of a gated EKF) goes into
``extras`` under documented keys.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from dataclasses import dataclass, field, fields, replace
from typing import Any, NamedTuple

import torch
from torch import Tensor

from ._checks import (
    broadcast_or_none,
    broadcast_shapes,
    check_batch_shape,
    check_carry_batch,
    check_model,
    check_step_inputs,
    model_batch_shape,
    model_dtype_device,
    values_known,
)
from ._vouched import Established, hold_whole, vouch, vouched
from .attack import Channel
from .noise import Gaussian
from .results import FilterResult, StepOutput

__all__ = [
    "Detection",
    "EstimatorOutput",
    "Estimator",
    "Generators",
    "stack_steps",
    "output_of",
]


@dataclass
class Detection:
    """A per-step attack decision.

    Attributes:
        scores: ``[..., T]`` real; higher means "more likely attacked" (the statistic the
            detector thresholds: NIS, CUSUM sum, probability of attack, …). Used for ROC
            curves, so it must be comparable across steps.
        alarms: ``[..., T]`` bool, the decision ``l̂_k``.
        threshold: the threshold the alarms came from: a number, or ``[..., T]`` when it
            changes with the step (windowed χ², Remark 6's running ``ζ_k``). ``None``
            when the decision is not a threshold of ``scores``.
        statistic: what ``scores`` are, in words (e.g. ``"attack probability"``), where a
            detector can score more than one statistic; ``None`` otherwise. A threshold
            calibrated for one statistic is recorded with its name
            (``difffilter-train calibrate``).
    """

    scores: Tensor
    alarms: Tensor
    threshold: Tensor | float | None = None
    statistic: str | None = None

    def __post_init__(self):
        for name in ("scores", "alarms"):
            if not isinstance(getattr(self, name), torch.Tensor):  # numpy's said "got bool"
                raise TypeError(f"{name} must be a torch tensor (torch.as_tensor(array) for "
                                f"a numpy array); got {type(getattr(self, name)).__name__}")  # fmt: skip
        if self.scores.shape != self.alarms.shape:
            raise ValueError(
                f"scores and alarms must have the same shape [..., T]; got "
                f"{tuple(self.scores.shape)} and {tuple(self.alarms.shape)}"
            )
        if self.alarms.dtype != torch.bool:
            raise ValueError(f"alarms must be a bool tensor; got {self.alarms.dtype}")
        if self.scores.is_complex():  # (scoring cast them to real with a warning of torch's)
            raise ValueError(f"scores must be real; got {self.scores.dtype}")
        self._check_threshold()

    def _check_threshold(self) -> None:
        """A number, a tensor of one number or of ``scores``' shape (one threshold per run
        and step, or broadcast to it), or ``None``: a trial's ``"25"`` was read as 25.0 and
        a list or a ``[B]`` tensor (one per run) was taken without a word."""
        th = self.threshold
        if isinstance(th, numbers.Real) and not isinstance(th, bool) and math.isnan(th):
            # (taken, it compared false with every score and was reported as null)
            raise ValueError("threshold must be a number, not NaN (None: no threshold)")
        if th is None or (isinstance(th, numbers.Real) and not isinstance(th, bool)):
            return
        if isinstance(th, torch.Tensor) and not th.is_complex() and th.dtype != torch.bool:
            if values_known(th) and bool(torch.isnan(th).any()):  # (as a number: a review)
                raise ValueError("threshold must not hold NaN (None: no threshold)")
            if th.dim() == 0:
                return
            try:
                fits = torch.broadcast_shapes(th.shape, self.scores.shape) == self.scores.shape
            except RuntimeError:
                fits = False
            if fits:
                return
            raise ValueError(
                f"threshold must be a number or a tensor of the scores' shape "
                f"{tuple(self.scores.shape)} [..., T] (or one that broadcasts to it); got shape "
                f"{tuple(th.shape)}"
            )
        raise TypeError(
            "threshold must be a number, a real tensor [..., T] like scores, or None (a "
            f"decision that is not a threshold of the scores); got {th!r}"
        )


@dataclass
class EstimatorOutput:
    """Output of an estimator over ``T`` steps of a batch of runs (time index ``t`` ↔ ``k = t + 1``).

    Attributes:
        means: state estimates ``x̂_k`` ``[..., T, dx]`` (after attack compensation where
            the estimator compensates).
        covs: their covariances ``[..., T, dx, dx]`` or ``None``.
        attack: estimate of the injected attack signal ``[..., T, da]`` (zero where the
            estimator believes there is none) or ``None`` for estimators that do not
            estimate it.
        detection: a :class:`Detection` or ``None`` for plain filters.
        extras: named per-run or per-step records of the algorithm (documented by each
            estimator), for example ``"ess" [..., T]``; where the steps report them (a
            Gaussian filter's), ``"innovations" [..., T, dy]``, ``"innovation_covs"
            [..., T, dy, dy]``, ``"pred_means"``, ``"pred_covs"``,
            ``"log_likelihood_increments" [..., T]`` and ``"log_likelihood"`` (a step's
            ``innovation`` is ``extras["innovations"]`` here: :func:`stack_steps`).
        attack_channel: the :class:`~difffilter.attack.Channel` ``attack`` estimates:
            the sensors (default; a replacement attack is measured on the same side, as
            ``ỹ − y``) or the actuators (``ũ − u``). Scoring compares an estimate only with
            an attack on the same side (:func:`difffilter.attack.same_side`).
    """

    means: Tensor
    covs: Tensor | None = None
    attack: Tensor | None = None
    detection: Detection | None = None
    extras: dict[str, Tensor] = field(default_factory=dict)
    attack_channel: Channel = Channel.SENSOR

    def __getattr__(self, name: str):
        # (only for names the class lacks: a trial asked for .innovation, a step's field, and
        # got a bare AttributeError)
        stacked = {**_STATISTICS, **_MATRICES, "log_likelihood": "log_likelihood"}
        if name in stacked:
            raise AttributeError(
                f"'EstimatorOutput' has no attribute {name!r}: the steps' {name} values are "
                f"stacked in extras[{stacked[name]!r}] (where the estimator's steps report them)"
            )
        if name in ("mean", "cov"):  # a step's field names (StepOutput.mean): stacked here
            raise AttributeError(
                f"'EstimatorOutput' has no attribute {name!r}: the steps' {name} values are "
                f"stacked in .{name}s [..., T, ...]"
            )
        raise AttributeError(f"'EstimatorOutput' object has no attribute {name!r}")

    def __post_init__(self):
        self.attack_channel = Channel(self.attack_channel)
        if not isinstance(self.means, Tensor):  # (None had raised a bare AttributeError)
            raise TypeError(
                f"means must be a torch tensor [..., T, dx]; got {type(self.means).__name__} "
                "(an estimator that only detects reports the means of the filter it scores)"
            )
        if self.means.dim() < 2:
            raise ValueError(f"means must have shape [..., T, dx]; got {tuple(self.means.shape)}")
        lead = self.means.shape[:-1]
        if self.attack is not None and self.attack.shape[:-1] != lead:
            raise ValueError(
                f"attack must have shape [{', '.join(map(str, lead))}, da] like means; "
                f"got {tuple(self.attack.shape)}"
            )
        dx, covs = self.means.shape[-1], self.covs
        if covs is not None and (
            not isinstance(covs, Tensor)
            or covs.dim() < 2
            or not covs.shape[-1] == covs.shape[-2] <= dx
            or broadcast_or_none(covs.shape[:-2], lead) != lead
        ):  # (any shape had been taken: [B, T, dx], or [5, 5] beside dx = 2; an API trial)
            got = tuple(covs.shape) if isinstance(covs, Tensor) else type(covs).__name__
            raise ValueError(
                f"covs must have shape [{', '.join(map(str, lead))}, {dx}, {dx}] (one dx × dx "
                "covariance per run and step, or a shared one broadcasting to them; a particle "
                f"filter's cov_dims = c: the leading c × c block); got {got}"
            )
        if self.detection is not None and self.detection.scores.shape != lead:
            raise ValueError(
                f"detection scores must have shape {tuple(lead)} (means without dx); "
                f"got {tuple(self.detection.scores.shape)}"
            )

    @property
    def alarms(self) -> Tensor | None:
        """Shortcut for ``detection.alarms`` (``None`` without a detection)."""
        return None if self.detection is None else self.detection.alarms

    @property
    def scores(self) -> Tensor | None:
        """Shortcut for ``detection.scores`` (``None`` without a detection)."""
        return None if self.detection is None else self.detection.scores

    def detach(self) -> EstimatorOutput:
        """A copy whose tensors are detached from the autograd graph."""

        def d(v):
            return v.detach() if isinstance(v, Tensor) else v

        det = self.detection
        if det is not None:
            det = Detection(d(det.scores), d(det.alarms), d(det.threshold), det.statistic)
        values = {f.name: d(getattr(self, f.name)) for f in fields(self)}
        values.update(detection=det, extras={k: d(v) for k, v in self.extras.items()})
        return replace(self, **values)


# ------------------------------------------------------------------ the online estimator


@hold_whole  # a carry's generators: one leaf, by identity
class Generators(NamedTuple):
    """The random streams of an estimator's draws: ``init`` (its initial state, e.g. the
    prior particles), ``propagate`` (proposals, process noise) and ``resample``.

    Separate streams keep common random numbers aligned across estimators
    (:class:`difffilter.models.streams.Streams` hands out one per purpose);
    :meth:`of` turns one generator into all three.
    """

    init: torch.Generator | None = None
    propagate: torch.Generator | None = None
    resample: torch.Generator | None = None

    @classmethod
    def of(cls, generator) -> Generators:
        """``None`` → no generators; a ``torch.Generator`` → that one for every purpose;
        a :class:`Generators` → itself. ``TypeError`` otherwise."""
        if isinstance(generator, Generators):
            for name, value in zip(generator._fields, generator):
                if value is not None and not isinstance(value, torch.Generator):
                    raise TypeError(
                        f"Generators.{name} must be a torch.Generator or None; got "
                        f"{type(value).__name__}"
                    )
            return generator
        if generator is None:
            return cls()
        if isinstance(generator, torch.Generator):
            return cls(generator, generator, generator)
        raise TypeError(
            "generator must be a torch.Generator or difffilter.Generators(init=, propagate=, "
            f"resample=); got {type(generator).__name__}"
        )


class Estimator:
    """Every estimator of the library: a pure step over one carry.

    ``init(model, batch_shape=(), generator=None) -> carry`` and
    ``step(carry, y, u=None, mask=None) -> (carry, StepOutput)``. The carry (a
    ``NamedTuple`` whose ``model`` field is the model being filtered) holds *all* of the
    estimator's state: moments or particles, detector statistics, histories, weights
    learned online, the random generators it draws from. The estimator object holds only
    its options, so the same object runs any number of independent carries, and the
    step is a function of ``(carry, y_k, u_{k−1}, mask_k)``: what lets the closed loop
    (:func:`difffilter.loop.closed_loop`) put it between a plant and a controller.

    Shapes: ``y [..., dy]``, ``u [..., du]`` or ``None``, ``mask [..., dy]`` (bool) or
    ``None``, with ``...`` the carry's batch shape (or broadcasting to it).
    :func:`difffilter.loop.open_loop` runs it over whole sequences into an
    :class:`EstimatorOutput`.

    ``init`` and ``step`` validate their inputs and name the offending argument; the
    drivers validate whole sequences once and call the unchecked ``_init``/``_step``.
    A carry is validated once: ``init`` validates the carry it makes, and the carries
    ``init`` and ``step`` return are vouched for (:mod:`difffilter._vouched`), so a step
    re-checks only ``y``, ``u`` and ``mask`` (shape, dtype, device, finiteness) unless
    :attr:`full_checks` is set.
    Subclasses implement ``_init(model, batch_shape, generators)``,
    ``_step(carry, y, u, mask)`` and ``_check_carry(carry)`` (what a valid carry is),
    :meth:`batch_of` where the carry has no ``mean [..., dx]`` (a wrapper whose carry holds
    its filter's as ``inner``), and may provide a whole-sequence fast path
    ``_run(carry, ys, us, mask)`` returning an
    :class:`EstimatorOutput` (or ``None`` where it does not apply), tested equal to the
    composed steps.
    """

    #: The carry type ``_init`` returns (checked by :meth:`step`).
    carry_type: type = tuple
    #: ``True``: :meth:`step` validates every carry and input in full, as if it had never
    #: seen the carry (``estimator.full_checks = True``, or on a subclass). ``False``
    #: (default): a carry the object's own ``step`` returned is trusted while unchanged.
    full_checks: bool = False
    #: The channel of the attack the step estimates (``StepOutput.attack``), marked on the
    #: stacked :class:`EstimatorOutput`: the sensors unless the estimator says otherwise.
    attack_channel: Channel = Channel.SENSOR

    def init(self, model, batch_shape=(), generator=None):
        """The carry of ``batch_shape`` independent runs before the first measurement."""
        check_model(model)
        batch = check_batch_shape(batch_shape)
        carry = self._init(model, batch, Generators.of(generator))
        # Validated once, here (a model's own prior of the wrong shape is named now, not
        # at the first step), and vouched for: the first step, like every later one, checks
        # only its inputs, against the model's dtype and device (a model holding no tensors
        # fixes neither: the first step then establishes them from ``y``).
        self._check_carry(carry)
        dtype, device = model_dtype_device(model)
        if dtype is not None:
            self._vouch(carry, dtype, device)
        return carry

    def step(self, carry, y: Tensor, u: Tensor | None = None, mask: Tensor | None = None):
        """One step ``k−1 → k`` with ``y_k``, ``u_{k−1}`` and ``mask_k``; returns
        ``(carry, StepOutput)``. The carry's tensors are not modified; the generators a
        random estimator's carry holds (a particle filter's) are advanced by its draws, so
        two steps from one carry draw differently unless each has generators of its own
        (:meth:`difffilter.loop.LoopState.copy`).

        A carry this estimator object returned (from ``init`` or an earlier ``step``),
        unchanged since, is not validated again: only ``y``, ``u`` and ``mask`` are,
        against the shapes, dtype and device established for it (the model's, the runs'
        batch: :mod:`difffilter._vouched`). Any other carry, and inputs of another shape or
        dtype, get the full checks and their errors; set :attr:`full_checks` to run them at
        every step.
        """
        established = None if self.full_checks else vouched(self, carry)
        if established is not None:
            fit = established.admits(y, u, mask)
            if fit is not None:
                new, out = self._step(carry, *fit)
                vouch(new, established)
                return new, out
        if not isinstance(carry, self.carry_type):
            raise TypeError(
                f"carry must be a {self.carry_type.__name__} (from {type(self).__name__}.init); "
                f"got {type(carry).__name__}"
            )
        model = carry.model
        check_model(model, prior=False)  # (a noise assigned since init may be of another dtype)
        _check_step_index(carry)
        self._check_carry(carry)
        y, u, mask = check_step_inputs(model, None, y, u, mask)
        check_carry_batch(self._runs_of(carry), y, u, mask)
        new, out = self._step(carry, y, u, mask)
        self._vouch(new, y.dtype, y.device)
        return new, out

    def _vouch(self, carry, dtype: torch.dtype, device) -> None:
        """Vouch for ``carry`` (validated, or made from validated inputs): later steps
        from it check only measurements of ``dtype`` on ``device`` for its runs
        (:mod:`difffilter._vouched`); nothing under :attr:`full_checks`."""
        if not self.full_checks:
            model = carry.model
            vouch(carry, Established(self, dtype, device, self.batch_of(carry), model.dim_y,
                                     model.dim_u, self._watched(model)))  # fmt: skip

    def _watched(self, model) -> tuple[Tensor, ...]:
        """The model's tensors whose values the full validation reads (not only their
        shapes, dtype and device): a vouched carry is validated in full again once one of
        them is written in place (:mod:`difffilter._vouched`). By default its noise models'
        (the Gaussian filters refuse a noise of non-zero mean, and so do the estimators
        built on them: a Gaussian noise's ``loc``, every parameter and buffer of another
        noise model)."""
        tensors = []
        for name in ("process_noise", "measurement_noise"):
            noise = getattr(model, name, None)
            if type(noise) is Gaussian:
                tensors.append(noise.loc)
            elif isinstance(noise, torch.nn.Module):
                tensors += [*noise.parameters(), *noise.buffers()]
        return tuple(tensors)

    def batch_of(self, carry) -> torch.Size:
        """The batch shape of the runs a carry holds: its ``mean [..., dx]``'s leading
        dimensions; a subclass whose carry has no ``mean`` overrides it (a bare
        ``AttributeError`` had named neither the method nor the fix: a plug-in trial)."""
        mean = getattr(carry, "mean", None)
        if not isinstance(mean, Tensor):
            raise TypeError(
                f"{type(self).__name__}.batch_of: the default reads the carry's mean "
                f"[..., dx], and its {type(carry).__name__} has none; override "
                "batch_of(carry) to return the runs' batch shape (e.g. "
                "carry.inner.mean.shape[:-1])"
            )
        return mean.shape[:-1]

    def _runs_of(self, carry) -> torch.Size:
        """The runs a step from ``carry`` makes: its own batch broadcast with its model's
        parameter sets (a carry of ``init(model, ())`` on a model of 3 sets steps 3 runs,
        so it takes one measurement per run as well as one for all)."""
        own = self.batch_of(carry)
        return broadcast_or_none(own, model_batch_shape(carry.model)) or own

    # -- what a subclass provides ------------------------------------------------------
    def _init(self, model, batch_shape: torch.Size, generators: Generators):
        raise NotImplementedError

    def _step(self, carry, y, u, mask) -> tuple[Any, StepOutput]:
        raise NotImplementedError

    def _model_of(self, carry):
        """The model ``carry``'s steps filter with, where it is the model the estimator was
        started from (``open_loop`` refuses a carry of another one); ``None``: not said (an
        estimator whose carry holds a model made from it, a view or a grouping)."""
        return None

    def _check_carry(self, carry) -> None:
        """``ValueError`` naming what is wrong with a carry built elsewhere (default: none)."""

    def _run(self, carry, ys, us, mask) -> EstimatorOutput | None:
        """A private whole-sequence fast path, or ``None`` (the default: step by step)."""
        return None


# ---------------------------------------------------------------- stacking step outputs

#: StepOutput fields stacked into EstimatorOutput.extras, and the name each gets there.
_STATISTICS = {
    "pred_mean": "pred_means",
    "innovation": "innovations",
}
_MATRICES = {"pred_cov": "pred_covs", "innovation_cov": "innovation_covs"}


def _common(shapes, *more) -> torch.Size:
    """The broadcast of ``shapes`` (one per step: most are equal, so each distinct one once)."""
    return broadcast_shapes(*more, *set(shapes))


def _stack(values: Sequence[Tensor], shape: torch.Size, dim: int) -> Tensor:
    if all(v.shape == shape for v in values):
        return torch.stack(values, dim=dim)
    return torch.stack([v.expand(shape) for v in values], dim=dim)


def _stack_vectors(values: Sequence[Tensor], batch: torch.Size) -> Tensor:
    """``[..., d]`` per step → ``[*batch, T, d]`` (each broadcast to ``batch``)."""
    lead = _common((v.shape[:-1] for v in values), batch)
    return _stack(values, lead + values[0].shape[-1:], -2)


def _stack_matrices(values: Sequence[Tensor], batch: torch.Size) -> Tensor:
    """``[..., d, d]`` per step → ``[*batch, T, d, d]``; matrices shared by the runs are
    stacked once and expanded (a view, no copy per run)."""
    lead = _common(v.shape[:-2] for v in values)
    stacked = _stack(values, lead + values[0].shape[-2:], -3)
    full = broadcast_shapes(batch, stacked.shape[:-3])
    return stacked.expand(full + stacked.shape[-3:])


def _stack_scalars(values: Sequence[Tensor], batch: torch.Size) -> Tensor:
    """``[...]`` per step → ``[*batch, T]``."""
    return _stack(values, _common((v.shape for v in values), batch), -1)


def _stack_thresholds(values: Sequence, batch: torch.Size, like: Tensor):
    """A number when every step used the same one, else ``[*batch, T]`` (``None``: none).

    A threshold that requires grad (a learnable one) stays a tensor: ``float`` would cut
    its gradient."""
    if values[0] is None:
        return None
    numbers = [v for v in values if not isinstance(v, Tensor) or v.dim() == 0]
    learnable = any(isinstance(v, Tensor) and v.requires_grad for v in values)
    if len(numbers) == len(values) and not learnable:
        first = float(values[0])
        if all(float(v) == first for v in values):
            return first
    tensors = [torch.as_tensor(v, dtype=like.dtype, device=like.device) for v in values]
    return _stack_scalars(tensors, batch)


def _stack_extra(key: str, outs: Sequence[StepOutput], batch: torch.Size) -> Tensor:
    """The steps' ``extras[key]`` stacked after the batch dimensions: every step must give
    it, as a tensor (the keys of the first step alone had been stacked, a record a hook
    began at step 3 dropped without a word, one that stopped a bare ``KeyError``, and a
    number a failure in ``torch.stack``: a trial of the plug-ins)."""
    values = []
    for t, out in enumerate(outs, start=1):
        value = (out.extras or {}).get(key)
        if not isinstance(value, Tensor):
            got = "nothing" if value is None else type(value).__name__
            raise ValueError(
                f"the step outputs' extras[{key!r}] must be a tensor at every step (a record "
                f"of a hook or likelihood: give it at every step); step {t} of {len(outs)} "
                f"gave {got}"
            )
        values.append(value)
    return torch.stack(values, dim=len(batch))


def _field(outs: Sequence[StepOutput], name: str) -> list | None:
    """The steps' values of the optional field ``name``, or ``None`` where no step gives
    it; every step or none must (the first step's fields alone had decided: a detector
    that began scoring at step 2 came out without its detection, scored as a plain filter,
    and a field that stopped failed in torch's words: an estimator-API trial)."""
    values = [getattr(o, name) for o in outs]
    given = [v is not None for v in values]
    if all(given):
        return values
    if any(given):
        t = given.index(not given[0]) + 1
        raise ValueError(
            f"the step outputs' {name} is {'given' if given[0] else 'None'} at step 1 and "
            f"{'None' if given[0] else 'given'} at step {t} of {len(outs)}: an estimator "
            f"reports a field at every step or at none (a detector warming up scores those "
            "steps too, e.g. 0 with alarm False)"
        )
    return None


def stack_steps(
    outs: Sequence[StepOutput],
    batch: torch.Size,
    collected: dict | None = None,
    attack_channel: Channel | str = Channel.SENSOR,
) -> EstimatorOutput:
    """The :class:`EstimatorOutput` of ``T`` step outputs of runs of shape ``batch``
    (``attack_channel``: the channel of the steps' attack estimate, the estimator's
    :attr:`Estimator.attack_channel`).

    ``means [*batch, T, dx]``, ``covs`` (shared matrices stay expanded views), ``attack``,
    a :class:`Detection` when the steps scored, and ``extras``: the stacked filter
    statistics (``"pred_means"``, ``"pred_covs"``, ``"innovations"``,
    ``"innovation_covs"``, ``"log_likelihood_increments" [*batch, T]`` and their sum
    ``"log_likelihood" [*batch]``, where the steps reported them), every key of the steps'
    own ``extras`` stacked after the batch dimensions, and ``collected`` (already stacked
    by the driver).
    """
    if not outs:
        raise ValueError("outs must hold at least one step output (T >= 1)")
    extras: dict[str, Tensor] = {}
    for name, key in _STATISTICS.items():
        if (values := _field(outs, name)) is not None:
            extras[key] = _stack_vectors(values, batch)
    for name, key in _MATRICES.items():
        if (values := _field(outs, name)) is not None:
            extras[key] = _stack_matrices(values, batch)
    if (values := _field(outs, "log_likelihood")) is not None:
        increments = _stack_scalars(values, batch)
        extras["log_likelihood_increments"] = increments
        extras["log_likelihood"] = increments.sum(-1)
    for key in dict.fromkeys(k for o in outs if o.extras for k in o.extras):
        extras[key] = _stack_extra(key, outs, batch)
    extras.update(collected or {})
    means = _stack_vectors([o.mean for o in outs], batch)
    covs = None if (values := _field(outs, "cov")) is None else _stack_matrices(values, batch)
    attack = None if (values := _field(outs, "attack")) is None else _stack_vectors(values, batch)
    detection = None
    scores, alarms = _field(outs, "score"), _field(outs, "alarm")
    if (scores is None) != (alarms is None):
        raise ValueError(
            "the step outputs give a score without an alarm or an alarm without a score: a "
            "detector reports both at every step (alarm = score > threshold)"
        )
    if scores is not None:
        lead = means.shape[:-2]
        scores, alarms = _stack_scalars(scores, lead), _stack_scalars(alarms, lead)
        threshold = _stack_thresholds([o.threshold for o in outs], lead, scores)
        detection = Detection(scores, alarms, threshold)
    return EstimatorOutput(means, covs, attack=attack, detection=detection, extras=extras,
                           attack_channel=attack_channel)  # fmt: skip


def output_of(result: FilterResult) -> EstimatorOutput:
    """A filter's whole-sequence :class:`~difffilter.results.FilterResult` as the
    :class:`EstimatorOutput` that :func:`stack_steps` would give (no copies)."""
    extras = {
        "pred_means": result.pred_means,
        "pred_covs": result.pred_covs,
        "innovations": result.innovations,
        "innovation_covs": result.innovation_covs,
        "log_likelihood_increments": result.log_likelihood_increments,
        "log_likelihood": result.log_likelihood,
        # (the count of a nonfinite="skip" run: open_loop's own result had it, this one
        # had dropped it; a results trial)
        "nonfinite_skipped": getattr(result, "nonfinite_skipped", None),
        # a particle filter's records, as its steps give them (they had been dropped: an
        # estimator-API trial)
        "ess": getattr(result, "ess", None),
        "resampled": getattr(result, "resampled", None),
        "degenerate": getattr(result, "degenerate", None),
        **(getattr(result, "records", None) or {}),
    }
    extras = {k: v for k, v in extras.items() if v is not None}
    return EstimatorOutput(result.means, result.covs, extras=extras)


def _check_step_index(carry, name: str = "carry") -> None:
    """A carry's step index ``k`` (where it has one) is an integer ``≥ 0``, and so is that of
    a carry it wraps (``carry.inner``, ``carry.plain``: a gated or learned estimator's): a
    hand-built ``k = 0.5`` or ``-3`` had read a time-varying model at that step without a
    word (two apishapes trials)."""
    k = getattr(carry, "k", 0)
    if isinstance(k, bool) or not isinstance(k, numbers.Integral) or k < 0:
        raise ValueError(f"{name}.k must be an integer step index >= 0; got {k!r}")
    for part in ("inner", "plain"):
        wrapped = getattr(carry, part, None)
        if isinstance(wrapped, tuple) and hasattr(wrapped, "_fields"):
            _check_step_index(wrapped, f"{name}.{part}")
