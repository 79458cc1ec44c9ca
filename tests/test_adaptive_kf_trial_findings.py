"""The adaptive Kalman filter's Wald score and its carry (a red-team trial, 2026-12-07; each
test failed before its fix)."""

from __future__ import annotations

import math

import pytest
import torch

import difffilter as df
from difffilter.fdi.adaptive_kf import AdaptiveKalmanFilter, adaptive_kalman_filter, wald_statistic

F64 = torch.float64


def test_the_wald_score_of_a_direction_never_seen_beside_one_estimated():
    """With forgetting, an attack direction the sensors never see has its variance grow as
    ``S/λᵏ`` (eq. 5i subtracts nothing for it): a regulariser of ``1e-12·tr S`` on every
    entry then swamped the well-estimated direction's variance, and the score fell from 31.6
    to 3.8 (T = 60) and 3.5e-6 (T = 100), where ``θ̂ᵀS⁻¹θ̂`` is 28.7 and 35.5: alarms missed."""
    theta = torch.tensor([0.3, 0.0], dtype=F64)
    S = torch.diag(torch.tensor([0.003, 1e16], dtype=F64))
    assert wald_statistic(theta, S).item() == pytest.approx(30.0, rel=1e-9)
    model = df.LinearGaussianModel(0.9 * torch.eye(2, dtype=F64), torch.tensor([[1.0, 0.0]], dtype=F64),
                                   0.01 * torch.eye(2, dtype=F64), torch.tensor([[0.01]], dtype=F64),
                                   torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64),
                                   B=torch.eye(2, dtype=F64))  # fmt: skip
    ys = 0.1 * torch.randn(100, 1, generator=torch.Generator().manual_seed(0), dtype=F64)
    ys[50:] += 3.0  # an attack on input 1 (identifiable), none on input 2 (never seen)
    out = adaptive_kalman_filter(model, ys, None, forgetting=0.7)
    a, S = out.attack[-1], out.extras["attack_covs"][-1]
    assert float(S[1, 1] / S[0, 0]) > 1e18  # the unseen direction's variance has grown
    truth = float(a @ torch.linalg.solve(S, a))
    assert out.detection.scores[-1].item() == pytest.approx(truth, rel=1e-9)
    assert bool(out.detection.alarms[-1])
    # S_0 = 0 still gives a score: 0 for θ̂ = 0, +inf or huge for an estimate held certain
    zero = torch.zeros(2, 2, dtype=F64)
    assert wald_statistic(torch.zeros(2, dtype=F64), zero).item() == 0.0
    assert wald_statistic(theta, zero).item() > 1e200 or math.isinf(
        wald_statistic(theta, zero).item()
    )


@pytest.mark.parametrize(("bad", "match"), [
    ("nan", "carry.sensitivity contains NaN"),
    ((3, 2), r"carry.sensitivity must be Υ \[..., 2, 2\]"),
    ((4, 2, 2), r"carry.sensitivity must be Υ \[..., 2, 2\]"),
])  # fmt: skip
def test_a_carrys_sensitivity_is_checked_as_its_other_tensors_are(bad, match):
    """A NaN Υ had been blamed on Q, R and P₀; one of [3, 2] for dx = 2 met torch's shape
    error; one of 4 runs on a carry of one made 4 runs, silently."""
    eye = torch.eye(2, dtype=F64)
    model = df.LinearGaussianModel(0.9 * eye, eye, 0.01 * eye, 0.1 * eye, torch.zeros(2, dtype=F64),
                                   eye, B=eye)  # fmt: skip
    akf = AdaptiveKalmanFilter(0.9)
    carry = akf.init(model, ())
    if bad == "nan":
        sensitivity = torch.full_like(carry.sensitivity, math.nan)
    else:
        sensitivity = torch.zeros(bad, dtype=F64)
    with pytest.raises(ValueError, match=match):
        akf.step(carry._replace(sensitivity=sensitivity), torch.zeros(2, dtype=F64))
