"""Findings of a red-team trial of the recorded-log workflow (docs/recorded-logs.md): the χ²
detector of a threshold of one's own, and the advice a NaN in a log gets. Each test failed
on the code before its fix."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import difffilter as df
from difffilter.fdi import ChiSquareDetector, gated_gaussian_filter
from difffilter.fdi.adaptive_kf import adaptive_kalman_filter
from difffilter.metrics import threshold_for

F64 = dict(dtype=torch.float64)


@pytest.mark.parametrize("dim,window", [(1, 1), (2, 1), (3, 1), (5, 3)])
def test_at_threshold_gates_at_or_just_above_the_threshold_given(dim, window):
    # the rate read back had given a quantile up to 2 ulp below τ one time in three
    # (thresholds of the rates a detector runs at: at rates near 1 a float64 rate resolves
    # the quantile to 1e-11 only)
    rng = np.random.default_rng(dim * 10 + window)
    dof = dim * window
    for tau in rng.uniform(dof, 4 * dof + 20, 300):
        det = ChiSquareDetector.at_threshold(dim, float(tau), window)
        assert det.threshold >= tau
        assert det.threshold <= math.nextafter(math.nextafter(tau, math.inf), math.inf) or (
            det.threshold - tau <= 1e-14 * tau
        )


def _page_model() -> df.LinearGaussianModel:
    F = torch.tensor([[0.95, 0.1], [0.0, 0.9]], **F64)
    H = torch.tensor([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]], **F64)
    B = torch.tensor([[0.0], [0.1]], **F64)
    return df.LinearGaussianModel(F, H, 1e-3 * torch.eye(2, **F64), 1e-2 * torch.eye(3, **F64),
                                  torch.zeros(2, **F64), torch.eye(2, **F64), B=B)  # fmt: skip


@pytest.mark.parametrize("seed", [1, 12, 19])
def test_the_pages_calibration_allows_no_more_alarms_than_it_promises(seed):
    # seeds 1, 12 and 19 (7 of 0–39) had given ⌊αn⌋ + 1 alarms on the stretch τ was
    # calibrated on (τ is one of the scores, and the detector gated 2 ulp below it)
    model, T = _page_model(), 350
    us = torch.ones(T, 1, **F64)
    _, y, _ = model.simulate(T, (), us, generator=torch.Generator().manual_seed(seed))
    y[200:204, 2] = float("nan")
    kw = dict(filter=df.KalmanFilter(), gate=False, nonfinite="skip")
    free = gated_gaussian_filter(model, y, us, detector=ChiSquareDetector(3), **kw)
    tau = threshold_for(free.detection.scores, 0.01)
    same = gated_gaussian_filter(
        model, y, us, detector=ChiSquareDetector.at_threshold(3, tau), **kw
    )
    assert int(same.detection.alarms.sum()) == int((free.detection.scores > tau).sum()) <= 3


def test_a_nan_in_a_log_is_met_with_advice_the_function_takes():
    # "Pass nonfinite='skip'" had been said to functions without that argument (TypeError)
    model = _page_model()
    _, ys, _ = model.simulate(
        20, (2,), torch.ones(20, 1, **F64), generator=torch.Generator().manual_seed(0)
    )
    ys[0, 5, 1] = float("nan")
    us = torch.ones(2, 20, 1, **F64)
    with pytest.raises(ValueError, match=r"Pass mask=torch.isfinite\(ys\)") as caught:
        adaptive_kalman_filter(model, ys, us)
    assert "first at index (0, 5, 1)" in str(caught.value)
    out = adaptive_kalman_filter(model, ys, us, mask=torch.isfinite(ys))
    assert torch.isfinite(out.means).all()
