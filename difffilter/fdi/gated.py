"""Residual detectors run online on a Gaussian filter, gating its measurement update.

At each step the filter (KF, EKF or UKF: any online step of the library) predicts, the
detector sees the normalised innovation squared ``g_k = r_kᵀ S_k⁻¹ r_k``
(``r_k = ỹ_k − ŷ_{k|k−1}``, ``S_k`` its covariance) and::

    alarm  → x̂_k = x̂_{k|k−1}, P_k = P_{k|k−1}      (the measurement is dropped)
    else   → the usual update

so an alarmed packet never biases the state estimate; a missed one does (``gate=False``
keeps every update and only reports the alarms). Detectors:
:class:`~difffilter.fdi.detectors.ChiSquareDetector` (``g_k`` or its window sum against a
``χ²`` quantile) and :class:`~difffilter.fdi.detectors.CusumDetector` (``S_k = max(0,
S_{k−1} + g_k − b)`` against ``τ``, reset after an alarm), both through their online
``init``/``step`` methods.

With a measurement ``mask`` only the received entries count: ``g_k`` then has
``m_k = #received`` degrees of freedom. The χ² detector (window 1) compares it with the
quantile for ``m_k``; for CUSUM, whose drift ``b`` is set for ``m`` degrees of freedom,
``g_k + (m − m_k)`` keeps the attack-free mean at ``m`` (each missing entry counts its
expectation, 1).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from .._checks import check_filter_inputs
from .._steps import StepRecorder
from ..estimator import Detection, EstimatorOutput
from ..extended import extended_kalman_step
from ..kalman import gaussian_init, run_gaussian_filter
from ..results import GaussianState
from .detectors import (
    ChiSquareDetector,
    CusumDetector,
    chi_square_quantile,
    normalized_innovation_squared,
)

__all__ = ["gated_gaussian_filter", "gated_extended_kalman_filter", "cusum_detector_for"]


def gated_gaussian_filter(
    model,
    ys: Tensor,
    us: Tensor | None = None,
    *,
    mask: Tensor | None = None,
    detector: ChiSquareDetector | CusumDetector,
    step: Callable = extended_kalman_step,
    gate: bool = True,
) -> EstimatorOutput:
    """Gaussian filter on ``ys [..., T, dy]`` whose update is skipped where ``detector`` alarms.

    Args:
        model: the filter's model (linear for ``difffilter.kalman_step``).
        us: inputs ``[..., T, du]`` or ``None``; mask: received entries ``[..., T, dy]``.
        detector: a :class:`ChiSquareDetector` or a calibrated :class:`CusumDetector`.
        step: the online step, ``difffilter.kalman_step``, ``extended_kalman_step``
            (default) or ``unscented_kalman_step``.
        gate: drop alarmed measurements (default) or only report the alarms.

    Returns an :class:`~difffilter.EstimatorOutput` (``attack`` is ``None``; detection
    scores = the detector statistic, threshold ``[..., T]`` for a windowed or masked
    χ², else a number) with ``extras``: ``nis`` ``g_k`` ``[..., T]``.
    """
    if not isinstance(detector, (ChiSquareDetector, CusumDetector)):
        raise ValueError(
            f"detector must be a ChiSquareDetector or a CusumDetector; got {type(detector).__name__}"
        )
    if not callable(step):
        raise TypeError(f"step must be an online filter step function; got {type(step).__name__}")
    if isinstance(detector, CusumDetector) and detector.threshold is None:
        raise ValueError(
            "detector: the CusumDetector has no threshold; pass threshold= or call calibrate() first"
        )
    masked_chi2 = mask is not None and isinstance(detector, ChiSquareDetector)
    if masked_chi2 and detector.window != 1:
        raise ValueError("a measurement mask needs a ChiSquareDetector with window=1")
    ys, us, mask = check_filter_inputs(model, ys, us, mask)
    batch, dy = ys.shape[:-2], ys.shape[-1]
    if masked_chi2:  # quantile for each possible number of received entries (0: never alarm)
        fa = 1.0 - detector.false_alarm_rate
        q = [float("inf")] + [chi_square_quantile(m, fa) for m in range(1, dy + 1)]
        quantiles = torch.tensor(q, dtype=ys.dtype, device=ys.device)
    elif isinstance(detector, ChiSquareDetector):  # computed once, not at every step
        step_thresholds = detector.thresholds(ys.shape[-2], ys.dtype).tolist()
    else:
        step_thresholds = [float(detector.threshold)] * ys.shape[-2]
    state = gaussian_init(model, batch)
    det_state = detector.init(batch, dtype=ys.dtype, device=ys.device)
    rec = StepRecorder()
    for t in range(ys.shape[-2]):
        u = None if us is None else us[..., t, :]
        m = None if mask is None else mask[..., t, :]
        updated, out = step(model, state, ys[..., t, :], u, m)
        g = normalized_innovation_squared(out.innovation, out.innovation_cov)
        if masked_chi2:
            threshold = quantiles[m.sum(-1)]
            score, alarm = g, g > threshold
        else:
            if m is not None:  # CUSUM: missing entries count their mean (see module docs)
                g = g + (dy - m.sum(-1)).to(g.dtype)
            det_state, score, alarm = detector.step(det_state, g)
            threshold = step_thresholds[t]
        if gate:
            cov_shape = torch.broadcast_shapes(updated.cov.shape, out.pred_cov.shape)
            mean = torch.where(alarm.unsqueeze(-1), out.pred_mean, updated.mean)
            cov = torch.where(
                alarm[..., None, None],
                out.pred_cov.expand(cov_shape),
                updated.cov.expand(cov_shape),
            )
            state = GaussianState(mean, cov, updated.k)
        else:
            state = updated
        rec.add(mean=state.mean, cov=state.cov, nis=g, score=score, alarm=alarm)
        rec.add(threshold=torch.as_tensor(threshold, dtype=ys.dtype).expand(alarm.shape))
    r = rec.stack(len(batch))
    thr = r["threshold"]
    fixed = bool((thr == thr.reshape(-1)[:1]).all()) if thr.numel() else True
    return EstimatorOutput(
        means=r["mean"],
        covs=r["cov"],
        detection=Detection(r["score"], r["alarm"], float(thr.reshape(-1)[0]) if fixed else thr),
        extras={"nis": r["nis"]},
    )


def gated_extended_kalman_filter(
    model,
    ys: Tensor,
    us: Tensor | None = None,
    *,
    mask: Tensor | None = None,
    detector: ChiSquareDetector | CusumDetector,
    gate: bool = True,
) -> EstimatorOutput:
    """:func:`gated_gaussian_filter` with the EKF step (``extended_kalman_step``)."""
    return gated_gaussian_filter(
        model, ys, us, mask=mask, detector=detector, step=extended_kalman_step, gate=gate
    )


def cusum_detector_for(
    model,
    *,
    false_alarm_rate: float,
    step: Callable = extended_kalman_step,
    bias: float | None = None,
    ys: Tensor | None = None,
    us: Tensor | None = None,
    mask: Tensor | None = None,
    runs: int = 100,
    steps: int = 100,
    generator: torch.Generator | None = None,
) -> CusumDetector:
    """A :class:`CusumDetector` calibrated for ``model`` and a filter ``step``.

    ``b = bias`` or ``dy + 2`` [DEF: the mean ``dy`` of an attack-free NIS plus a margin
    that makes the statistic drift down]; ``τ`` is set by
    :meth:`CusumDetector.calibrate` so that the alarm rate on attack-free statistics is
    ``false_alarm_rate``. The statistics are the NIS of the ungated filter on ``ys`` (and
    ``us``, ``mask``) when given — attack-free measurements of the plant — else on
    ``runs × steps`` runs simulated from the model with ``generator``.
    """
    if ys is None:
        _, ys, _ = model.simulate(steps, (runs,), us, generator=generator)
    free = run_gaussian_filter(step, model, ys, us, mask)
    g = normalized_innovation_squared(free.innovations, free.innovation_covs)
    if mask is not None:  # as in gated_gaussian_filter: missing entries count their mean
        g = g + (ys.shape[-1] - mask.sum(-1)).to(g.dtype)
    detector = CusumDetector(ys.shape[-1] + 2.0 if bias is None else bias)
    detector.calibrate(g, false_alarm_rate)
    return detector
