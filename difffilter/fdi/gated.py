"""Residual detectors run online on an EKF, gating its measurement update.

At each step the EKF predicts, the detector sees the normalised innovation squared
``g_k = r_kᵀ S_k⁻¹ r_k`` (``r_k = ỹ_k − h(x̂_{k|k−1})``, ``S_k = H P_{k|k−1} Hᵀ + R``) and::

    alarm  → x̂_k = x̂_{k|k−1}, P_k = P_{k|k−1}      (the measurement is dropped)
    else   → the usual EKF update

so an alarmed packet never biases the state estimate; a missed one does. Detectors:
:class:`~difffilter.fdi.detectors.ChiSquareDetector` (``g_k`` or its window sum against a
``χ²`` quantile) and :class:`~difffilter.fdi.detectors.CusumDetector` (``S_k = max(0,
S_{k−1} + g_k − b)`` against ``τ``, reset after an alarm), both through their online
``init``/``step`` methods.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from .._checks import check_filter_inputs
from ..extended import extended_kalman_step
from ..kalman import gaussian_init
from ..results import GaussianState
from .detectors import ChiSquareDetector, CusumDetector, normalized_innovation_squared

__all__ = ["GatedFilterResult", "gated_extended_kalman_filter"]


@dataclass
class GatedFilterResult:
    """Output of :func:`gated_extended_kalman_filter` (time index ``t`` ↔ ``k = t + 1``).

    Attributes: ``means [..., T, dx]``, ``covs [..., T, dx, dx]``, ``nis`` (``g_k``)
    ``[..., T]``, ``scores`` (the detector statistic) ``[..., T]``, ``alarms [..., T]``.
    """

    means: Tensor
    covs: Tensor
    nis: Tensor
    scores: Tensor
    alarms: Tensor


def gated_extended_kalman_filter(
    model, ys: Tensor, us: Tensor | None = None, *, detector: ChiSquareDetector | CusumDetector
) -> GatedFilterResult:
    """EKF on ``ys [..., T, dy]`` whose update is skipped where ``detector`` raises an alarm."""
    check_filter_inputs(model, ys, us)  # the plain filters' checks (shape, dtype, finite)
    if not isinstance(detector, (ChiSquareDetector, CusumDetector)):
        raise ValueError(
            f"detector must be a ChiSquareDetector or a CusumDetector; got {type(detector).__name__}"
        )
    if ys.dim() < 2 or ys.shape[-1] != model.dim_y:
        raise ValueError(f"ys must have shape [..., T, {model.dim_y}]; got {tuple(ys.shape)}")
    batch = ys.shape[:-2]
    state = gaussian_init(model, batch)
    det_state = detector.init(batch, dtype=ys.dtype, device=ys.device)
    means, covs, nis, scores, alarms = [], [], [], [], []
    for t in range(ys.shape[-2]):
        u = None if us is None else us[..., t, :]
        updated, out = extended_kalman_step(model, state, ys[..., t, :], u)
        g = normalized_innovation_squared(out.innovation, out.innovation_cov)
        det_state, score, alarm = detector.step(det_state, g)
        cov_shape = torch.broadcast_shapes(updated.cov.shape, out.pred_cov.shape)
        mean = torch.where(alarm.unsqueeze(-1), out.pred_mean, updated.mean)
        cov = torch.where(
            alarm[..., None, None], out.pred_cov.expand(cov_shape), updated.cov.expand(cov_shape)
        )
        state = GaussianState(mean, cov, updated.k)
        for lst, v in zip((means, covs, nis, scores, alarms), (mean, cov, g, score, alarm)):
            lst.append(v)
    d = len(batch)
    return GatedFilterResult(
        torch.stack(means, d),
        torch.stack(covs, d),
        torch.stack(nis, d),
        torch.stack(scores, d),
        torch.stack(alarms, d),
    )
