"""Findings of a trial of gradients through the attack-aware estimators."""

from __future__ import annotations

import pytest
import torch

import difffilter as df
from difffilter import fdi
from difffilter.fdi.adaptive_kf import adaptive_kalman_filter, wald_statistic
from difffilter.fdi.detectors import ChiSquareDetector, chi_square_equivalent
from difffilter.fdi.gated import gated_gaussian_filter

D = torch.float64


def _model(B=None) -> df.LinearGaussianModel:
    return df.LinearGaussianModel(
        torch.tensor([[0.9, 0.1], [0.0, 0.95]], dtype=D),
        torch.tensor([[1.0, 0.0], [0.3, 1.0]], dtype=D), 0.05 * torch.eye(2, dtype=D),
        0.1 * torch.eye(2, dtype=D), torch.zeros(2, dtype=D), torch.eye(2, dtype=D), B=B,
    )  # fmt: skip


@pytest.mark.parametrize("transform", ["grad", "jacrev", "jacfwd"])
def test_torch_func_runs_through_a_gated_filter_under_a_mask(transform):
    """With an entry lost, the χ² score maps through ``chi_square_equivalent``, which read
    its argument by numpy: every ``torch.func`` transform failed ("Cannot access data
    pointer of Tensor that doesn't have storage"); reverse mode worked. Now equal to it."""
    model = _model()
    _, ys, _ = model.simulate(6, (2,), generator=torch.Generator().manual_seed(0))
    mask = torch.ones_like(ys, dtype=torch.bool)
    mask[0, 2, 1] = False

    def loss(y):
        out = gated_gaussian_filter(model, y, mask=mask, detector=ChiSquareDetector(2, 0.05, 3),
                                    filter=df.KalmanFilter())  # fmt: skip
        return out.means.sum() + out.detection.scores.sum()

    y = ys.clone().requires_grad_()
    (expected,) = torch.autograd.grad(loss(y), y)
    got = getattr(torch.func, transform)(loss)(ys)
    torch.testing.assert_close(got, expected, rtol=0, atol=1e-10)
    g = torch.tensor([3.0], dtype=D)
    slope = torch.func.grad(lambda g: chi_square_equivalent(g, 1, 2).sum())(g)
    g.requires_grad_()
    (reverse,) = torch.autograd.grad(chi_square_equivalent(g, 1, 2).sum(), g)
    torch.testing.assert_close(slope, reverse, rtol=0, atol=0)


def test_a_wald_score_of_a_zero_attack_covariance_is_a_number():
    """``attack_cov0 = 0`` (the adaptive KF is then the EKF) gave NaN scores, which never
    alarm, and NaN gradients: the regulariser was a subnormal 1e-312 that the solve divided
    into 0·∞. Now 0 for a zero estimate, a large number or +inf for one held certain."""
    model = _model(torch.tensor([[0.0], [0.1]], dtype=D))
    _, ys, _ = model.simulate(5, (2,), generator=torch.Generator().manual_seed(0))
    y = ys.clone().requires_grad_()
    out = adaptive_kalman_filter(model, y, forgetting=0.8, attack_cov0=0.0)
    (grad,) = torch.autograd.grad(out.means.sum() + out.detection.scores.sum(), y)
    assert torch.equal(out.detection.scores, torch.zeros_like(out.detection.scores))
    assert bool(torch.isfinite(grad).all())
    mdpf = fdi.adaptive_particle_filter(model, ys, torch.zeros(2, 5, 1, dtype=D),
                                        num_particles=20, attack_cov0=0.0,
                                        generator=torch.Generator().manual_seed(0))  # fmt: skip
    assert bool(torch.isfinite(mdpf.detection.scores).all())
    for dtype in (torch.float64, torch.float32):
        zero = torch.zeros(2, 2, dtype=dtype)
        assert wald_statistic(torch.zeros(2, dtype=dtype), zero) == 0
        assert wald_statistic(torch.tensor([1.0, 2.0], dtype=dtype), zero) > 1e30
        one = wald_statistic(torch.tensor([1.0, 0.0], dtype=dtype), torch.eye(2, dtype=dtype))
        assert float(one) == pytest.approx(1.0, rel=1e-6)  # (S + 1e-12 tr S · I)
