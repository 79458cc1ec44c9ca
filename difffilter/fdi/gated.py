"""Residual detectors run online on a Gaussian filter, gating its measurement update.

At each step the filter (KF, EKF or UKF: any online step of the library) predicts, the
detector sees the normalised innovation squared ``g_k = r_kᵀ S_k⁻¹ r_k``
(``r_k = ỹ_k − ŷ_{k|k−1}``, ``S_k`` its covariance) and::

    alarm  → x̂_k = x̂_{k|k−1}, P_k = P_{k|k−1}      (the measurement is dropped)
    else   → the usual update

so an alarmed packet never biases the state estimate; a missed one does (``gate=False``
keeps every update and only reports the alarms). :class:`GatedFilter` is the estimator
object (its carry holds the filter's and the detector's state); the functions run it in
the open loop. Detectors:
:class:`~difffilter.fdi.detectors.ChiSquareDetector` (``g_k`` or its window sum against a
``χ²`` quantile) and :class:`~difffilter.fdi.detectors.CusumDetector` (``S_k = max(0,
S_{k−1} + g_k − b)`` against ``τ``, reset after an alarm), both through their online
``init``/``step`` methods.

With a measurement ``mask`` only the received entries count: ``g_k`` then has
``m_k = #received`` degrees of freedom. The χ² detector compares its window with the
quantile of the degrees of freedom the window received and scores the statistic's
full-window equivalent (:func:`~difffilter.fdi.detectors.chi_square_equivalent`), so
the scores take one threshold for one false-alarm rate; for CUSUM, whose drift ``b`` is
set for ``m`` degrees of freedom, ``g_k + (m − m_k)`` keeps the attack-free mean at ``m``
(each missing entry counts its expectation, 1).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import torch
from torch import Tensor

from .._assignments import note_assignment
from .._checks import (
    NonFinite,
    broadcast_shapes,
    check_flag,
    check_model_batch,
    check_one_model,
    check_positive_int,
)
from ..estimator import Estimator, EstimatorOutput
from ..extended import ExtendedKalmanFilter
from ..kalman import GaussianFilter
from ..loop import open_loop
from ..results import GaussianState
from .detectors import (
    ChiSquareDetector,
    CusumDetector,
    _nis,
    missing_entries_counted,
    normalized_innovation_squared,
)

__all__ = [
    "GatedFilter",
    "GatedState",
    "gated_gaussian_filter",
    "gated_extended_kalman_filter",
    "cusum_detector_for",
]


class GatedState(NamedTuple):
    """Carry of :class:`GatedFilter`: the filter's ``inner`` carry (a
    :class:`~difffilter.results.GaussianState`), the detector's online state and the model."""

    inner: GaussianState
    detector: Any
    model: Any


def _check_detector_dim(det, dy: int) -> None:
    """A χ² detector tests the model's ``dy``-entry innovation: its quantile's degrees of
    freedom (3 on a 1-sensor model alarmed 0.09 % for 1 %)."""
    if isinstance(det, ChiSquareDetector) and det.dim != dy:
        raise ValueError(
            f"detector: ChiSquareDetector(dim={det.dim}) tests a {det.dim}-entry innovation, "
            f"and the model measures {dy} entries: ChiSquareDetector({dy}, "
            f"{det.false_alarm_rate})"
        )


class GatedFilter(Estimator):
    """A Gaussian filter whose update is skipped where a residual detector alarms.

    Args:
        filter: the Gaussian filter (:class:`~difffilter.KalmanFilter`,
            :class:`~difffilter.ExtendedKalmanFilter` (default) or
            :class:`~difffilter.UnscentedKalmanFilter`).
        detector: a :class:`ChiSquareDetector` or a calibrated :class:`CusumDetector`.
        gate: drop alarmed measurements (default) or only report the alarms.

    Step output: the filter's moments after gating, ``score`` the detector statistic (under
    a mask the χ² window's full-window equivalent), ``alarm``, ``threshold`` (a number: the
    χ² quantile of the step's full window, ``m·min(k, W)`` degrees of freedom, or CUSUM's
    ``τ``) and ``extras["nis"]`` ``g_k``.
    """

    carry_type = GatedState

    def __init__(
        self,
        detector: ChiSquareDetector | CusumDetector,
        filter: GaussianFilter | None = None,
        *,
        gate: bool = True,
    ):
        self.detector, self.filter, self.gate = detector, filter, gate

    def __setattr__(self, name, value):
        # checked whenever set, as the constructor checks them: a PoADetector or a filter of
        # None assigned later had failed at the first step on "has no attribute 'init'" or
        # "'_init'" (a red-team trial); a replacement has the next step validate its carry
        if name == "detector":
            value = _checked_detector(value)
        elif name == "filter":
            value = _checked_filter(value)
        elif name == "gate":
            value = check_flag(value, "gate")
        replacing = name in ("detector", "filter") and name in self.__dict__
        super().__setattr__(name, value)
        if replacing:
            note_assignment()

    def batch_of(self, carry):
        return carry.inner.mean.shape[:-1]

    def _init(self, model, batch_shape, generators):
        _check_detector_dim(self.detector, model.dim_y)
        inner = self.filter._init(model, batch_shape, generators)
        dtype, device = inner.mean.dtype, inner.mean.device
        # one window per run: a model with a parameter set per run makes runs of unbatched ys
        runs = check_model_batch(model, torch.Size(batch_shape), "batch_shape")
        return GatedState(inner, self.detector.init(runs, dtype=dtype, device=device), model)

    def _check_carry(self, carry):
        self.filter._check_carry(carry.inner)
        # the detector's online state too: a NaN CUSUM S or χ² window had scored NaN and never
        # alarmed, a negative one lowered the score (an apishapes trial)
        check_state = getattr(self.detector, "check_state", None)
        if check_state is not None:
            check_state(carry.detector, carry.inner.mean.dtype, "carry.detector")

    def _detect(self, det_state, g: Tensor, mask: Tensor | None, dy: int):
        """``(detector state, score, alarm, threshold)`` of the step's NIS ``g [...]``."""
        det = self.detector
        if isinstance(det, ChiSquareDetector):
            # (at every step: a detector, or its dim, assigned since init had tested a 2-entry
            # statistic against χ²₅, a gate far below its rate: an options trial)
            _check_detector_dim(det, dy)
            # under a mask the step judges the degrees of freedom received and scores the
            # statistic's full-window equivalent (ChiSquareDetector.step): one threshold
            threshold = det.quantile(det.dim * min(det_state[1] + 1, det.window))
            det_state, score, alarm = det.step(det_state, g, mask)
            return det_state, score, alarm, threshold
        if mask is not None:  # CUSUM: missing entries count their mean (see module docs)
            g = missing_entries_counted(g, mask)
        det_state, score, alarm = det.step(det_state, g)
        return det_state, score, alarm, float(det.threshold)

    def _step(self, carry, y, u, mask):
        pred = self.filter.predict(carry.inner, u)
        updated, out = self.filter.update(carry.inner, pred, y, mask)
        if out.innovation_cov is None:
            raise ValueError(
                f"filter: {type(self.filter).__name__} reported no innovation covariance S_k, "
                "which the detector's statistic g_k = r_kᵀ S_k⁻¹ r_k needs"
            )
        # the filter's own, checked output (its mask: a jittered S's jitter is the received
        # entries' own, not scaled by the lost ones' unit placeholders)
        g = _nis(out.innovation, out.innovation_cov, mask)
        det_state, score, alarm, threshold = self._detect(carry.detector, g, mask, y.shape[-1])
        if self.gate:
            cov_shape = broadcast_shapes(updated.cov.shape, pred.cov.shape)
            mean = torch.where(alarm.unsqueeze(-1), pred.mean, updated.mean)
            cov = torch.where(
                alarm[..., None, None], pred.cov.expand(cov_shape), updated.cov.expand(cov_shape)
            )
            inner = GaussianState(mean, cov, updated.k, carry.model)
        else:
            inner = updated
        # what the filter reports of the carry kept (a held-input filter: x's part, the held
        # input's in extras, both of the gated carry: a review found the held input of the
        # dropped update reported at alarmed steps)
        mean, cov, extras = self.filter.reported(carry.model, inner.mean, inner.cov)
        out = out._replace(
            mean=mean, cov=cov, score=score, alarm=alarm, threshold=threshold,
            extras={**extras, "nis": g},
        )  # fmt: skip
        return GatedState(inner, det_state, carry.model), out


def _checked_detector(detector):
    if not isinstance(detector, (ChiSquareDetector, CusumDetector)):
        raise ValueError(
            f"detector must be a ChiSquareDetector or a CusumDetector; got {type(detector).__name__}"
        )
    if isinstance(detector, CusumDetector) and detector.threshold is None:
        raise ValueError(
            "detector: the CusumDetector has no threshold; pass threshold= or call calibrate() first"
        )
    return detector


def _checked_filter(filter):
    filter = ExtendedKalmanFilter() if filter is None else filter
    if not isinstance(filter, GaussianFilter):
        raise TypeError(
            "filter must be a Gaussian filter object (difffilter.KalmanFilter(), "
            f"ExtendedKalmanFilter(), UnscentedKalmanFilter()); got {type(filter).__name__}"
        )
    if not filter.reports_innovation_cov:  # (it failed inside torch at the first step)
        raise TypeError(
            f"filter: a {type(filter).__name__} reports no innovation covariance S_k, which "
            "the detector's statistic g_k = r_kᵀ S_k⁻¹ r_k needs: give a KalmanFilter, "
            "ExtendedKalmanFilter or UnscentedKalmanFilter"
        )
    return filter


def gated_gaussian_filter(
    model,
    ys: Tensor,
    us: Tensor | None = None,
    *,
    mask: Tensor | None = None,
    detector: ChiSquareDetector | CusumDetector,
    filter: GaussianFilter | None = None,
    gate: bool = True,
    nonfinite: NonFinite | str = NonFinite.RAISE,
) -> EstimatorOutput:
    """:class:`GatedFilter` on ``ys [..., T, dy]`` in the open loop.

    Args:
        model: the filter's model (linear for :class:`~difffilter.KalmanFilter`).
        us: inputs ``[..., T, du]`` or ``None``; mask: received entries ``[..., T, dy]``.
        detector: a :class:`ChiSquareDetector` or a calibrated :class:`CusumDetector`.
        filter: the Gaussian filter object (default :class:`~difffilter.ExtendedKalmanFilter`).
        gate: drop alarmed measurements (default) or only report the alarms.
        nonfinite: ``"skip"`` treats non-finite entries of ``ys`` as not received
            (:func:`difffilter.loop.open_loop`); ``"raise"`` (default) raises.

    Returns an :class:`~difffilter.EstimatorOutput` (``attack`` is ``None``; detection
    scores = the detector statistic, under a mask the χ² window's full-window equivalent;
    threshold ``[..., T]`` for a windowed χ², else a number) with ``extras``: ``nis``
    ``g_k`` ``[..., T]`` (and the filter's stacked statistics).
    """
    gated = GatedFilter(detector, filter, gate=gate)
    return open_loop(gated, model, ys, us, mask=mask, nonfinite=nonfinite)


def gated_extended_kalman_filter(
    model,
    ys: Tensor,
    us: Tensor | None = None,
    *,
    mask: Tensor | None = None,
    detector: ChiSquareDetector | CusumDetector,
    gate: bool = True,
    nonfinite: NonFinite | str = NonFinite.RAISE,
) -> EstimatorOutput:
    """:func:`gated_gaussian_filter` with the EKF."""
    return gated_gaussian_filter(model, ys, us, mask=mask, detector=detector, gate=gate,
                                 nonfinite=nonfinite)  # fmt: skip


def cusum_detector_for(
    model,
    *,
    false_alarm_rate: float,
    filter: GaussianFilter | None = None,
    bias: float | None = None,
    ys: Tensor | None = None,
    us: Tensor | None = None,
    mask: Tensor | None = None,
    runs: int = 100,
    steps: int = 100,
    generator: torch.Generator | None = None,
) -> CusumDetector:
    """A :class:`CusumDetector` calibrated for ``model`` and a Gaussian ``filter``.

    ``b = bias`` or ``dy + 2`` [DEF: the mean ``dy`` of an attack-free NIS plus a margin
    that makes the statistic drift down]; ``τ`` is set by
    :meth:`CusumDetector.calibrate` so that the alarm rate on attack-free statistics is
    ``false_alarm_rate``. The statistics are the NIS of the ungated filter (default the
    EKF) on ``ys`` (and ``us``, ``mask``) when given — attack-free measurements of the
    plant — else on ``runs × steps`` runs simulated from the model with ``generator``.
    One threshold for one model: a model of several parameter sets (a sweep) is refused
    (calibrate each set on its own; a pooled threshold would meet the rate on none).
    """
    check_one_model(model, "cusum_detector_for", "calibrate a detector per parameter set")
    filter = ExtendedKalmanFilter() if filter is None else filter
    if ys is None:
        # (a bad runs reached torch as "max(): Expected reduction dim" or a negative dimension)
        runs = check_positive_int(runs, "runs")
        _, ys, _ = model.simulate(steps, (runs,), us, generator=generator)
    elif isinstance(ys, Tensor) and ys.dim() >= 2 and ys[..., 0].numel() == 0:
        # (named as g_attack_free, a statistic the caller never saw: a batch-dims trial)
        raise ValueError(f"ys has no runs or no steps to calibrate on: {tuple(ys.shape)}")
    free = open_loop(filter, model, ys, us, mask=mask)
    g = normalized_innovation_squared(free.extras["innovations"], free.extras["innovation_covs"])
    if mask is not None:  # as in the gated filter: missing entries count their mean
        g = missing_entries_counted(g, mask)
    detector = CusumDetector(ys.shape[-1] + 2.0 if bias is None else bias)
    detector.calibrate(g, false_alarm_rate)
    return detector
