"""The Kalman filter: an online step over one carry, and its whole-sequence run.

Equations (one step, ``k−1 → k``; the blocks of :mod:`difffilter.gaussian`)::

    predict   m⁻ = F m + B u                 P⁻ = F P Fᵀ + Q
    innovate  r  = y − H m⁻                  S  = H P⁻ Hᵀ + R
    gain      K  = P⁻ Hᵀ S⁻¹                 (Cholesky solve, S never inverted)
    update    m⁺ = m⁻ + K r                  P⁺ = (I − K H) P⁻ (I − K H)ᵀ + K R Kᵀ   (Joseph)
    evidence  log p(y_k | y_{1:k−1}) = log N(r; 0, S)

Covariances are symmetrised after every step. Unreceived measurement entries (``mask``)
are removed exactly (:func:`difffilter.linalg.masked_measurement`). Every function is
differentiable with respect to the model's tensors and broadcasts over leading batch
dimensions.

:class:`KalmanFilter` is the estimator object (``init``/``step``, run by the drivers of
:mod:`difffilter.loop`); :func:`kalman_step` is its step as a function of an explicit
model and :func:`kalman_filter` its whole-sequence run. When the model's matrices carry
no batch dimension and nothing is masked the covariance recursion does not depend on the
data: the step then reads it from a :class:`~difffilter.GainSchedule` computed once for
all runs, and the whole-sequence run takes the shared-covariance path
(:mod:`difffilter._shared_cov`) or, with ``method="parallel"``, the associative scan
(:mod:`difffilter.parallel_kalman`); both are tested equal to the composed steps.
"""

from __future__ import annotations

import contextlib
from typing import NamedTuple

import torch
from torch import Tensor

from . import _kf_host_step as _host_step
from ._checks import (
    Choice,
    NonFinite,
    _check_us,
    broadcast_or_none,
    broadcast_shapes,
    check_batch_shape,
    check_carry_fits_model,
    check_carry_tensor,
    check_model_batch,
    model_dtype_device,
    step_covariance,
)
from ._shared_cov import shared_covariance_applies, shared_covariance_kalman_filter
from .estimator import Estimator, output_of
from .gain_schedule import GainSchedule, OutputsWritten, shared_gains_apply
from .gaussian import (
    innovation_log_prob,
    linear_predict,
    masked_residual,
    measurement_moments,
    moments_update,
)
from .linalg import matvec, under_transform
from .loop import _step_through, open_loop
from .noise import Gaussian
from .parallel_kalman import parallel_kalman_filter
from .results import FilterResult, GaussianState, StepOutput
from .ssm import LinearGaussianModel, StateSpaceModel

__all__ = [
    "Method",
    "Prediction",
    "GaussianFilter",
    "KalmanFilter",
    "gaussian_init",
    "kalman_predict",
    "kalman_step",
    "kalman_filter",
]


class Method(Choice):
    """How :class:`KalmanFilter` runs a whole sequence: step by step (``SEQUENTIAL``, with
    the shared-covariance path when it applies) or by the associative scan of Särkkä &
    García-Fernández (``PARALLEL``: ``O(log T)`` batched operations, fastest for a few
    long runs; equal up to round-off on well-conditioned models:
    :mod:`difffilter.parallel_kalman`)."""

    SEQUENTIAL = "sequential"
    PARALLEL = "parallel"


def gaussian_init(model, batch_shape=()) -> GaussianState:
    """Prior state ``(m_0, P_0)`` of a Gaussian filter.

    ``mean`` is ``[*batch_shape, dx]``; ``cov`` keeps the prior's own shape
    ``[*, dx, dx]`` (broadcast lazily).
    """
    _check_zero_mean_noise(model)
    # an int too, as KalmanFilter().init takes it (a docs trial: gaussian_init(model, 32)
    # met "'int' object is not iterable")
    batch_shape = check_batch_shape(batch_shape, least=0)
    # the runs: a model of one parameter set per run makes that many (a function holding
    # per-run values met one prior mean [dx] in the EKF's Jacobian, "given x [2]": a trial)
    runs = check_model_batch(model, batch_shape, "batch_shape")
    mean = model.initial.mean
    mean = mean.expand(broadcast_shapes(runs, mean.shape[:-1]) + mean.shape[-1:])
    # own tensors, not views of the model's prior: a carry written in place (which is
    # followed) had written the prior, every run's start and every later init with it
    # (an aliasing trial: `carry.mean[0] = x` moved all runs and `model.simulate`)
    return GaussianState(mean.clone(), model.initial.cov.clone(), 0, model)


def _check_zero_mean_noise(model) -> None:
    """The Gaussian filters read a noise model's covariance alone: a noise of non-zero mean
    (``UniformBox(0, 2)``, a shifted mixture) was filtered as if it had mean 0, with a bias
    of the size of that mean (a user trial), while ``simulate`` and the particle filter
    honour it. Refused, and said how to write it."""
    for name in ("process_noise", "measurement_noise"):
        noise = getattr(model, name, None)
        cov = getattr(noise, "cov", None)
        prior = getattr(getattr(model, "initial", None), "mean", None)
        if isinstance(cov, Tensor) and isinstance(prior, Tensor) and cov.dtype != prior.dtype:
            # (the filters read the covariance alone: it failed deep in the update, "expected
            # m1 and m2 to have the same dtype")
            raise ValueError(
                f"model.{name}.cov is {cov.dtype} and the model is {prior.dtype}: give the "
                f"noise the model's dtype (model.{name} = model.{name}.to({prior.dtype}))"
            )
        # an exactly zero loc (the usual noise), cached against its version: nothing to read
        if type(noise) is Gaussian and noise.loc.device.type != "meta" and not under_transform():
            if noise._zero_loc():
                continue
        mean = getattr(noise, "mean", None)
        if not isinstance(mean, Tensor) or mean.device.type == "meta":
            continue
        # zero up to round-off on the noise's own scale (a symmetric box's float mean of
        # −2.8e-17 was refused)
        scale = cov.diagonal(dim1=-2, dim2=-1).sqrt() if isinstance(cov, Tensor) else 1.0
        tol = 64 * torch.finfo(mean.dtype).eps * scale if mean.is_floating_point() else 0
        if bool((mean.abs() > tol).any()):
            raise ValueError(
                f"model.{name} has mean {mean.tolist()}, and the Gaussian filters (KF, EKF, UKF, "
                "AdaptiveKalmanFilter, and AdaptiveParticleFilter, whose proposal is one) take "
                "every noise as zero-mean: put the mean into the model (f or h, or a known "
                "input) and give the noise mean 0, or use ParticleFilter, which samples the "
                "noise as it is"
            )


def kalman_predict(model, state: GaussianState, u: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """``m⁻ = F m + B u``, ``P⁻ = F P Fᵀ + Q`` for a linear model → ``([..., dx], [..., dx, dx])``.

    ``model`` must provide ``transition_matrix(k)``, ``control_matrix(k)`` and
    ``process_cov(k)`` (as :class:`~difffilter.LinearGaussianModel` does). The state and
    ``u`` are checked as :func:`kalman_step` checks them (another dtype, width or a numpy
    ``u`` had failed in torch's words: an apishapes trial).
    """
    _check_linear(model)
    KalmanFilter()._check_carry(state._replace(model=model, gains=None))
    if u is not None:
        dtype, device = model_dtype_device(model)
        u = _check_us(model, u, state.mean.shape[:-1], None, dtype, device)
    return _kalman_predict(model, state, u)


def _kalman_predict(model, state: GaussianState, u: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """:func:`kalman_predict` without its checks (the filters' own path)."""
    k = state.k
    return linear_predict(
        state.mean,
        state.cov,
        model.transition_matrix(k),
        step_covariance(model, "process_cov", k),
        model.control_matrix(k),
        u,
    )


def kalman_step(
    model, state: GaussianState, y: Tensor, u: Tensor | None = None, mask: Tensor | None = None
) -> tuple[GaussianState, StepOutput]:
    """One Kalman-filter step ``x_{k−1} → x_k`` with measurement ``y_k``.

    Args:
        model: a linear model (``transition_matrix``, ``observation_matrix``,
            ``control_matrix``, ``process_cov``, ``measurement_cov``).
        state: posterior of ``x_{k−1}`` (mean ``[..., dx]``, cov ``[..., dx, dx]``).
        y: ``y_k [..., dy]``; u: ``u_{k−1} [..., du]`` (the input of the transition into
            ``x_k``: ``us[..., t, :]`` with ``ys[..., t, :]``) or ``None``; mask: ``[..., dy]``
            bool or ``None``.

    The inputs are validated (:func:`difffilter._checks.check_step_inputs`): a NaN or Inf
    in a received entry of ``y`` raises ``ValueError`` instead of poisoning every later
    state. Returns the posterior of ``x_k`` and a :class:`~difffilter.results.StepOutput`.
    """
    return KalmanFilter().step(state._replace(model=model, gains=None), y, u, mask)


def _kalman_step(model, state, y, u=None, mask=None):
    """:func:`kalman_step` without input validation (the drivers validate whole sequences)."""
    filt = KalmanFilter()
    carry = state._replace(model=model, gains=None)
    return filt.update(carry, filt.predict(carry, u), y, mask)


class Prediction(NamedTuple):
    """A Gaussian filter's prediction of ``x_k``: ``mean`` ``m⁻ [..., dx]``, ``cov``
    ``P⁻ [..., dx, dx]`` (what :meth:`GaussianFilter.update` conditions on ``y_k``)."""

    mean: Tensor
    cov: Tensor


class GaussianFilter(Estimator):
    """A Gaussian filter as an estimator object: ``step = update ∘ predict``.

    Subclasses (:class:`KalmanFilter`, :class:`~difffilter.ExtendedKalmanFilter`,
    :class:`~difffilter.UnscentedKalmanFilter`) implement
    ``predict(carry, u) -> Prediction`` and ``update(carry, prediction, y, mask, *,
    evidence=True, moments=None) -> (carry, StepOutput)``, the two halves that the
    attack-aware estimators recombine (a gated filter keeps the prediction where its
    detector alarms; the learned estimator updates with a compensated measurement or
    predicts with a compensated input). ``evidence=False`` leaves the step's
    ``log_likelihood`` ``None`` (its density is not computed); ``moments`` is what
    :meth:`moments` returned for the same carry, prediction and mask (the part of the update
    that does not read ``y``: a wrapper that reads one measurement's innovation and then
    updates with another computes it once; ``None``: computed in the update).
    Carry: :class:`~difffilter.results.GaussianState`.
    """

    carry_type = GaussianState
    #: Whether a carry's ``mean`` and ``cov`` are the state's alone (``[..., dx]``): a
    #: wrapper that reports them reports the state. ``False`` for a filter whose carry holds
    #: more (:class:`~difffilter.ExpectedInputKalmanFilter` on held inputs: ``[x; z]``).
    carry_is_state = True
    #: Whether its update reports the innovation covariance ``S_k`` (``innovation_cov``), which
    #: a residual detector's statistic and a learned estimator's standardisation read.
    reports_innovation_cov = True

    def reported(self, model, mean: Tensor, cov: Tensor) -> tuple[Tensor, Tensor, dict]:
        """``(x̂ [..., dx], P [..., dx, dx], extras)``: what a step reports of a carry's
        ``mean`` and ``cov`` (a wrapper that chooses between the prediction and the update,
        as the gated filter, reports through it). The moments themselves here, no extras."""
        return mean, cov, {}

    def _init(self, model, batch_shape, generators):
        return gaussian_init(model, batch_shape)

    def predict(self, carry: GaussianState, u: Tensor | None) -> Prediction:
        raise NotImplementedError

    def update(self, carry, prediction: Prediction, y, mask, *, evidence=True, moments=None):
        raise NotImplementedError

    def moments(self, carry, prediction: Prediction, mask):
        """The part of :meth:`update` that does not read ``y`` under ``prediction`` and
        ``mask``, to pass to :meth:`update` and :meth:`innovation` as ``moments``; ``None``
        where this filter does not share it (each update computes its own)."""
        return None

    def residual(self, carry, prediction: Prediction, y):
        """``y − ŷ⁻ [..., dy]`` (unmasked) of a filter whose :meth:`moments` are shared."""
        raise NotImplementedError

    def innovation(self, carry, prediction: Prediction, y, mask, *, evidence: bool = True,
                   moments=None):  # fmt: skip
        """``(ν [..., dy], S [..., dy, dy], log N(ν; 0, S) [...] or None)`` of ``y`` under
        ``prediction`` without the update's posterior (what a compensating wrapper reads
        before it decides what to update with; ``evidence=False`` skips the density;
        ``moments`` as in :meth:`update`): from the moments where the filter shares them
        (no gain, no posterior), else the update's own."""
        if moments is None:
            moments = self.moments(carry, prediction, mask)
        if moments is None:
            _, out = self.update(carry, prediction, y, mask, evidence=evidence)
            return out.innovation, out.innovation_cov, out.log_likelihood
        nu = masked_residual(self.residual(carry, prediction, y), mask)
        S = moments.innovation_cov
        return nu, S, (innovation_log_prob(nu, S, moments.observed, moments.mask)
                         if evidence else None)  # fmt: skip

    def _moments_update(self, carry, prediction: Prediction, y, mask, evidence, moments):
        """The KF/EKF update (:func:`~difffilter.gaussian.moments_update`) from this filter's
        :meth:`moments` (computed here when ``None``) and :meth:`residual`."""
        if moments is None:
            moments = self.moments(carry, prediction, mask)
        mean, cov, residual, S, log_lik = moments_update(
            prediction.mean, prediction.cov, self.residual(carry, prediction, y), moments,
            evidence=evidence,
        )  # fmt: skip
        out = StepOutput(mean, cov, prediction.mean, prediction.cov, residual, S, log_lik)
        return GaussianState(mean, cov, carry.k + 1, carry.model), out

    def _step(self, carry, y, u, mask):
        return self.update(carry, self.predict(carry, u), y, mask)

    def _model_of(self, carry):
        return carry.model

    def batch_of(self, carry) -> torch.Size:
        """The runs of ``carry``: its mean's and its covariance's leading dimensions broadcast
        (a mean shared by a batch of covariances steps one run per covariance: its steps had
        refused measurements of those runs, an apishapes trial)."""
        own = super().batch_of(carry)
        cov = getattr(carry, "cov", None)
        if not isinstance(cov, Tensor) or cov.dim() < 2:
            return own
        return broadcast_or_none(own, cov.shape[:-2]) or own

    def _check_carry(self, carry):
        # a noise of non-zero mean assigned between steps (init refuses one) had its mean
        # dropped without a word (a KF trial: [1.51, 0.87] where [3.22, 2.95] is right)
        _check_zero_mean_noise(carry.model)
        dx = carry.model.dim_x
        check_carry_tensor(carry.mean, "mean", dim=dx)
        check_carry_tensor(carry.cov, "cov", dim=dx, covariance=True)
        # runs that broadcast with the mean's (a shared covariance, or one mean for a batch
        # of covariances): a cov of other runs had failed inside torch (an apishapes trial)
        if broadcast_or_none(carry.cov.shape[:-2], carry.mean.shape[:-1]) is None:
            raise ValueError(
                f"carry.cov {tuple(carry.cov.shape)} and carry.mean {tuple(carry.mean.shape)} "
                "must hold runs that broadcast together (one covariance per run, or shared)"
            )
        check_carry_fits_model(carry.model, mean=carry.mean, cov=carry.cov)


class KalmanFilter(GaussianFilter):
    """The Kalman filter of a linear-Gaussian model as an estimator object.

    Args:
        method: :class:`Method` (or its name) for whole sequences (:func:`kalman_filter`).

    Carry: :class:`~difffilter.results.GaussianState` ``(mean [..., dx], cov, k, model,
    gains)``; ``gains`` is the model's :class:`~difffilter.GainSchedule` when its
    covariances are shared by every run (an unbatched time-invariant model whose matrices
    require no gradients: the schedule is computed outside autograd), used by
    every unmasked step: the same numbers, the covariance recursion computed once for all
    runs (a masked step falls back to the general update and drops it, as does any step
    after a tensor of the model was written in place: its matrices, noise and prior, and
    every parameter or buffer of it, which a subclass may make its matrices from at each
    read; the schedule's moments are computed ahead, from the model as it was. A number
    changed mid-run, ``model.dt = 0.3``, is not seen: start a new carry).
    """

    def __init__(self, method: Method | str = Method.SEQUENTIAL):
        self.method = method

    def __setattr__(self, name, value):
        # read whenever set, as __init__ reads it: "parallel" assigned later was a string the
        # whole-sequence path never matched (it ran sequentially), "bogus" was taken (a trial)
        super().__setattr__(name, _method(value) if name == "method" else value)

    def _init(self, model, batch_shape, generators):
        _check_linear(model)
        _check_declared_time_varying(model)
        state = gaussian_init(model, batch_shape)
        # (the schedule is computed without a graph: under a torch.func transform an outer
        # reverse level would lose the gains' derivative, so a traced model steps in full)
        if shared_gains_apply(model) and not under_transform(*_model_tensors(model)):
            gains = GainSchedule(model)
            state = state._replace(cov=gains.initial_cov, gains=gains)
        return state

    def _step(self, carry, y, u, mask):
        gains = carry.gains
        if gains is None:
            return self._step_held(carry, y, u, mask)
        with gains.lock:  # (_schedule_held, inlined: the one-run online step's hot path)
            return self._step_held(carry, y, u, mask)

    def _step_held(self, carry, y, u, mask):
        carry = _live(carry, outputs=False)  # (the fused step checks those itself)
        if carry.gains is not None and mask is None:
            # the fused step of the shared gains: about eight tensor operations per step
            try:
                mean, pred, nu, log_lik, m = carry.gains.filter_step(carry.mean, y, u, carry.k + 1)
            except OutputsWritten:  # its P⁻ or S written through an output: the general update
                carry = carry._replace(gains=None)
            else:
                out = StepOutput(mean, m.cov, pred, m.pred_cov, nu, m.innovation_cov, log_lik)
                return GaussianState(mean, m.cov, carry.k + 1, carry.model, carry.gains), out
        if _own_update(self):  # one run where nothing is recorded: on host arrays
            stepped = _host_step.host_step(carry, y, u, mask)
            if stepped is not None:
                return stepped
        return self.update(carry, self.predict(carry, u), y, mask)

    def predict(self, carry, u):
        with _schedule_held(carry):
            carry = _live(carry)
            if carry.gains is not None:
                return Prediction(carry.gains.predict(carry.mean, u),
                                  carry.gains.moments(carry.k + 1).pred_cov)  # fmt: skip
        return Prediction(*_kalman_predict(carry.model, carry, u))

    def moments(self, carry, prediction, mask):
        carry = _live(carry)
        if carry.gains is not None and mask is None:
            return None  # the shared schedule holds them, computed once for all runs
        model, k = carry.model, carry.k + 1
        H, R = model.observation_matrix(k), step_covariance(model, "measurement_cov", k)
        return measurement_moments(prediction.cov, H, R, mask)

    def residual(self, carry, prediction, y):
        return y - matvec(carry.model.observation_matrix(carry.k + 1), prediction.mean)

    def update(self, carry, prediction, y, mask, *, evidence=True, moments=None):
        with _schedule_held(carry):
            carry = _live(carry)
            if carry.gains is not None and mask is None:
                return _shared_update(carry, prediction.mean, y, evidence)
        return self._moments_update(carry, prediction, y, mask, evidence, moments)

    def innovation(self, carry, prediction, y, mask, *, evidence: bool = True, moments=None):
        with _schedule_held(carry):
            carry = _live(carry)
            m = (
                None
                if carry.gains is None or mask is not None
                else carry.gains.moments(carry.k + 1)
            )
        if m is None:
            # the update's own ν and S (and density), without its gain and posterior
            return super().innovation(carry, prediction, y, mask, evidence=evidence,
                                      moments=moments)  # fmt: skip
        nu = carry.gains.innovation(prediction.mean, y)
        ell = -0.5 * matvec(m.whiten, nu).square().sum(-1) - m.log_norm if evidence else None
        return nu, m.innovation_cov, ell

    def _check_carry(self, carry):
        _check_linear(carry.model)  # (an EKF's carry on a nonlinear model: an AttributeError)
        super()._check_carry(carry)
        with _schedule_held(carry):
            self._check_schedule(carry)

    def _check_schedule(self, carry):
        if carry.gains is not None:
            if carry.gains.model is not carry.model:  # the step would filter with the other
                raise ValueError(
                    "carry.gains is the gain schedule of another model: drop the gains "
                    "(carry._replace(gains=None)) when changing the model"
                )
            gains = carry.gains
            if carry.k == 0:
                shared = gains.initial_cov
            elif gains.held(carry.k):
                shared = gains.moments(carry.k).cov
            else:  # dropped (KEEP): its step goes on without the schedule (_live)
                shared = None
            if shared is not None and carry.cov is not shared:
                raise ValueError(
                    "carry.cov is not the shared covariance of carry.gains: drop the gains "
                    "(carry._replace(gains=None)) when changing the covariance"
                )
            if carry.k and not carry.gains.intact(carry.k):
                raise ValueError(
                    "carry.cov was written in place, and it is the gain schedule's covariance, "
                    "shared by every run (and every later step once the gain has converged): "
                    "change a copy without the gains (carry._replace(cov=carry.cov.clone(), "
                    "gains=None))"
                )

    def _run(self, carry, ys, us, mask):
        model = carry.model
        if ys.numel() == 0:  # no runs or no steps: the steps' empty results
            return None
        if self.method is Method.PARALLEL:
            return output_of(parallel_kalman_filter(model, ys, us, mask))
        if shared_covariance_applies(model, mask) and not _forward_traced(model, ys, us):
            result = shared_covariance_kalman_filter(model, ys, us)
            return None if result is None else output_of(result)  # None: step by step
        schedule = None if mask is None else _one_schedule(mask)
        if schedule is not None:
            # every run received the same entries: the covariance recursion (which reads
            # the mask, never the data) is one [dx, dx] recursion for all runs, as without
            # a mask; steps with a [dy] mask broadcast it (a [B, dy] mask made it B of them)
            return _step_through(self, carry, ys, us, schedule, self.batch_of(carry), None)
        return None


def _one_schedule(mask: Tensor) -> Tensor | None:
    """The ``[T, dy]`` mask every run of ``mask [..., T, dy]`` shares, else ``None`` (and
    ``None`` under a ``torch.func`` transform or a dual level, whose tensors cannot be
    compared here)."""
    lead = mask.dim() - 2
    if lead == 0:
        return mask
    if under_transform() or mask.device.type == "meta":  # (meta tensors hold no values)
        return None
    first = mask[(0,) * lead]
    if all(s == 0 for s in mask.stride()[:lead]) or torch.equal(mask, first.expand_as(mask)):
        return first
    return None


def _model_tensors(model) -> tuple:
    """The tensors a time-invariant linear model's moments are made of."""
    return (model.transition_matrix(0), model.observation_matrix(1), model.control_matrix(0),
            model.process_cov(0), model.measurement_cov(1), model.initial.mean,
            model.initial.cov)  # fmt: skip


def _forward_traced(model, ys: Tensor, us: Tensor | None) -> bool:
    """Whether forward-mode AD or a ``torch.func`` transform traces this call in a way the
    shared-covariance path cannot serve (:func:`~difffilter.linalg.under_transform`). That
    path keeps a graph only where grad mode is on and its inputs require a gradient, and
    otherwise writes into preallocated tensors (forward mode cannot follow them) and
    computes the covariances without a graph (an outer level would lose them): it serves a
    traced call only under reverse-mode transforms alone (``grad``, ``jacrev``, nested or
    not) with grad mode on; a dual level, ``jvp``, ``jacfwd``, ``vmap``, any mix of them
    with ``grad``, or a transform under ``no_grad`` step through."""
    if not under_transform():  # no transform, no dual level: the model is not looked at
        return False
    if not under_transform(ys, us, *_model_tensors(model)):
        return False  # traced elsewhere: none of this call's tensors carries a derivative
    stack = torch._C._functorch.get_interpreter_stack() or ()
    reverse_only = torch.autograd.forward_ad._current_level < 0 and all(
        level.key() == torch._C._functorch.TransformType.Grad for level in stack
    )
    return not (reverse_only and torch.is_grad_enabled())


#: The methods whose numbers :func:`difffilter._kf_host_step.host_step` computes.
_UPDATE_METHODS = ("predict", "moments", "residual", "update", "_moments_update")


def _own_update(kf) -> bool:
    """Whether ``kf`` (a :class:`KalmanFilter` or a subclass, or the class itself) predicts and
    updates as the Kalman filter does: a subclass that overrides one of them (the
    expected-input filter's prediction) or an object given a method of its own
    (``kf.update = wrapper``) steps in torch, through it."""
    cls = kf if isinstance(kf, type) else type(kf)
    if (
        not isinstance(kf, type)
        and getattr(kf, "__dict__", None)
        and any(name in kf.__dict__ for name in _UPDATE_METHODS)
    ):
        return False
    return all(getattr(cls, name) is getattr(KalmanFilter, name) for name in _UPDATE_METHODS)


def _schedule_held(carry):
    """The lock of ``carry``'s gain schedule (a no-op context without one): a step's checks
    and its use of the schedule happen together, as the branches of one start carry,
    stepped from several threads, share it (:class:`~difffilter.GainSchedule`)."""
    gains = getattr(carry, "gains", None)
    return contextlib.nullcontext() if gains is None else gains.lock


def _live(carry: GaussianState, outputs: bool = True) -> GaussianState:
    """``carry`` without its gain schedule where the model was written in place since the
    schedule was made (:meth:`~difffilter.GainSchedule.current`): the general update reads
    the model as it is now, from the covariance the schedule had reached; or where the
    schedule no longer holds the carry's next step (a carry kept from thousands of steps
    before: :attr:`~difffilter.GainSchedule.KEEP`), from the covariance the carry holds; or
    where a step's output ``P⁻`` or ``S`` that the next step would share was written in place
    (:meth:`~difffilter.GainSchedule.outputs_intact`; ``outputs=False``: not checked here,
    where the fused step checks them, :class:`~difffilter.gain_schedule.OutputsWritten`): the
    general update computes its own. And where the schedule no longer holds the carry's own
    step (a carry kept from the step its trimming dropped last): its covariance cannot be
    told from the schedule's (a reset ``carry._replace(cov=3 I)`` there had been ignored, the
    mean 0.36 off: a red-team trial), so the step goes on from the one the carry holds."""
    gains = carry.gains
    if gains is not None and not (
        gains.current()
        and gains.held(carry.k + 1)
        and (carry.k == 0 or gains.held(carry.k))
        and (not outputs or gains.outputs_intact(carry.k + 1))
    ):
        return carry._replace(gains=None)
    return carry


def _shared_update(carry: GaussianState, pred_mean: Tensor, y: Tensor, evidence: bool = True):
    """The update with the covariances of ``carry.gains`` (no mask): the same numbers as
    the general update, with the data-independent part computed once for all runs."""
    gains: GainSchedule = carry.gains
    k = carry.k + 1
    m = gains.moments(k)
    innovation = gains.innovation(pred_mean, y)
    mean = pred_mean + matvec(m.gain, innovation)
    log_lik = None
    if evidence:
        white = matvec(m.whiten, innovation)
        log_lik = -0.5 * torch.linalg.vecdot(white, white) - m.log_norm
    out = StepOutput(mean, m.cov, pred_mean, m.pred_cov, innovation, m.innovation_cov, log_lik)
    return GaussianState(mean, m.cov, k, carry.model, gains), out


def _method(method) -> Method:
    try:
        return Method(method)
    except ValueError:
        raise ValueError(
            f"method must be one of {[m.value for m in Method]}; got {method!r}"
        ) from None


#: The methods of a linear model that take the step ``k``.
_OF_K = ("transition_matrix", "observation_matrix", "control_matrix", "process_cov",
         "measurement_cov")  # fmt: skip


#: The steps at which an undeclared time-varying model is looked for (each against k = 1;
#: 0: the transition into step 1 reads k = 0, where a model need not be defined).
_PROBED_STEPS = (0, 2, 3, 10, 100, 1000)
#: What the filters read at k = 0 (the transition into step 1; no measurement is taken at 0).
_READ_AT_0 = ("transition_matrix", "control_matrix", "process_cov")


def _methods_of_k_written(model) -> list[str]:
    """The methods of ``k`` (:data:`_OF_K`) that ``model`` has written itself: assigned on the
    object, or defined by its class over :class:`~difffilter.LinearGaussianModel`'s (its
    matrices as given) or :class:`~difffilter.StateSpaceModel`'s (the noise modules'
    covariances); every one a model of another kind has (any model with the matrix methods:
    a time-varying one written from ``StateSpaceModel``, or an instance's assigned
    ``transition_matrix``, had been filtered with the first step's ``F``, 16 nats off: a
    trial of time-varying models)."""
    cls, own = type(model), getattr(model, "__dict__", {})  # (a duck type may have slots)
    base = (LinearGaussianModel if isinstance(model, LinearGaussianModel)
            else StateSpaceModel if isinstance(model, StateSpaceModel) else None)  # fmt: skip
    return [name for name in _OF_K
            if name in own
            or (hasattr(cls, name)
                and (base is None or getattr(cls, name) is not getattr(base, name, None)))]  # fmt: skip


def _check_declared_time_varying(model) -> None:
    """``ValueError`` where a linear model's method of ``k`` that the model wrote itself
    (:func:`_methods_of_k_written`) differs at step 0, 2, 3, 10, 100 or 1,000 from step 1's
    while ``time_varying`` is false: the filters' fast paths would read the first step's
    matrices at every step (a user trial's rotating ``F`` was filtered as constant, 0.88
    nats off at T = 60; a closed-loop trial's ``F`` halved from step 5 on gave estimates
    1.30 off when only step 2 was compared). A matrix that changes only between the
    probed steps, or only after them, is not seen here."""
    if getattr(model, "time_varying", False):
        return
    cls = type(model)
    for name in _methods_of_k_written(model):
        method = getattr(model, name)
        try:
            with torch.no_grad():
                first = method(1)
        except Exception:  # noqa: BLE001 (a model of its own whose k-methods need more)
            continue
        for k in _PROBED_STEPS:
            if k == 0 and name not in _READ_AT_0:
                continue
            try:
                with torch.no_grad():
                    later = method(k)
            except Exception:  # noqa: BLE001 (e.g. a table of T steps, shorter than k)
                if k == 0:
                    continue
                break
            if first is None and later is None:
                continue
            # None (no input) at one step and a matrix at another differs too: the check had
            # stopped at a None, and B_0 was read at every step (a parallel-filter trial:
            # every input dropped, 117 nats off; the sequential filter failed in torch.pad)
            if (first is None or later is None or first.shape != later.shape
                    or not torch.equal(first, later)):  # fmt: skip
                raise ValueError(
                    f"{cls.__name__}.{name}(k) differs between k = 1 and k = {k}, but the "
                    "model's time_varying is False: the filters would cache the first step's "
                    "matrices and read them at every step; set time_varying = True on the class"
                    + (
                        " (or on this model, whose own it is)"
                        if name in getattr(model, "__dict__", {})
                        else ""
                    )
                )


def _check_linear(model) -> None:
    needed = ("transition_matrix", "observation_matrix", "control_matrix", "process_cov")
    missing = [name for name in needed if not hasattr(model, name)]
    if missing:
        raise TypeError(
            f"the Kalman filter needs a linear model (e.g. difffilter.LinearGaussianModel); "
            f"{type(model).__name__} lacks {', '.join(missing)}: use the EKF or UKF"
        )


def kalman_filter(
    model,
    ys: Tensor,
    us: Tensor | None = None,
    *,
    mask: Tensor | None = None,
    method: Method | str = Method.SEQUENTIAL,
    nonfinite: NonFinite | str = NonFinite.RAISE,
) -> FilterResult:
    """Kalman filter of a linear-Gaussian model over a whole sequence.

    Args:
        model: :class:`~difffilter.LinearGaussianModel` (or any model with its matrix
            methods).
        ys: measurements ``y_1 … y_T`` ``[..., T, dy]``.
        us: inputs ``u_0 … u_{T−1}`` ``[..., T, du]`` or ``None`` (no input: on a model
            with inputs, ``B u`` is left out, as zero inputs).
        mask: received entries ``[..., T, dy]`` (bool) or ``None`` (all received).
            Unreceived entries may be NaN.
        method: :class:`Method` or its name, ``"sequential"`` (the online step in a
            loop; Joseph form) or ``"parallel"`` (the associative-scan filter of Särkkä &
            García-Fernández, IEEE TAC 2021: ``O(log T)`` batched operations instead of
            ``T`` small ones, fastest for a few long runs; equal to the sequential filter
            up to round-off on well-conditioned models; on a strongly non-normal ``F``
            with a small R, where its scan loses the filter, it raises a ValueError:
            :mod:`difffilter.parallel_kalman`). The sequential filter picks the
            shared-covariance fast path
            (:mod:`difffilter._shared_cov`) by itself when the model's matrices have no
            batch dimension, the model is time-invariant and nothing is masked: the
            covariance recursion runs once for all runs and the covariances come back
            as expanded views ``[..., T, dx, dx]`` of one ``[T, dx, dx]`` tensor (where
            its means fail a check of one Kalman update a step, on a strongly non-normal
            ``F``, it steps through the sequence instead).
        nonfinite: :class:`~difffilter.NonFinite` ``RAISE`` (default): a NaN or
            ±Inf in a received entry of ``ys`` raises ``ValueError``; ``SKIP``: such
            entries are treated as unreceived
            (folded into ``mask``) and counted per run in
            ``result.nonfinite_skipped [...]``.

    Every input is validated first (shape, dtype, finiteness, mask dtype and shape,
    ``us`` batch; :func:`difffilter._checks.check_sequence_inputs`).

    Returns:
        :class:`~difffilter.results.FilterResult` (means ``[..., T, dx]``, covs
        ``[..., T, dx, dx]``, innovations, innovation covariances, log-likelihood ``[...]``).
    """
    out = open_loop(KalmanFilter(method), model, ys, us, mask=mask, nonfinite=nonfinite)
    return FilterResult.from_output(out)
