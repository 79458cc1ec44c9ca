"""Findings of a numerics trial of the Gaussian filters (2026-12-04).

* A time-varying model's ``process_cov(k)`` / ``measurement_cov(k)`` override went into
  every Gaussian filter unchecked: a negative-definite ``R_3`` gave the EKF, the adaptive
  KF and the time-varying KF a posterior covariance with negative eigenvalues and no error
  (``simulate`` refused the same model); an indefinite or non-symmetric one ran silently.
* ``BiasAttackEstimator.step`` took a NaN residual on a flagged step, and ``γ̂`` stayed NaN
  at every later step; a flag of 0.3 was read as attacked.
"""

from __future__ import annotations

import pytest
import torch

import difffilter as df
from difffilter._checks import step_covariance
from difffilter.fdi.adaptive_kf import adaptive_kalman_filter
from difffilter.fdi.attack_estimation import BiasAttackEstimator
from difffilter.fdi.detectors import ChiSquareDetector
from difffilter.fdi.gated import GatedFilter

F64 = torch.float64
F = torch.tensor([[1.0, 0.1], [0.0, 1.0]], dtype=F64)
H = torch.eye(2, dtype=F64)
B = torch.tensor([[0.0], [0.1]], dtype=F64)
Q, R = 0.01 * torch.eye(2, dtype=F64), 0.1 * torch.eye(2, dtype=F64)
BAD_STEP = 3

BAD = {
    "negative": lambda c: -1e-3 * c,
    "indefinite": lambda c: c * torch.tensor([1.0, -1.0], dtype=F64),
    "asymmetric": lambda c: c + torch.tensor([[0.0, 0.05], [-0.05, 0.0]], dtype=F64),
    "nan": lambda c: c * float("nan"),
}
WHY = {
    "negative": "positive semi-definite",
    "indefinite": "positive semi-definite",
    "asymmetric": "must be symmetric",
    "nan": "NaN or Inf",
}


def _models(which: str, how: str):
    """A linear and a nonlinear model, time-varying, whose ``which`` covariance is bad at
    step ``BAD_STEP`` alone."""

    def override(self, k, base):
        return BAD[how](base) if k == BAD_STEP else base

    attrs = {
        "time_varying": True,
        which: lambda self, k: override(
            self, k, (self.process_noise if which == "process_cov" else self.measurement_noise).cov
        ),
    }
    Linear = type("TVLinear", (df.LinearGaussianModel,), attrs)
    Nonlinear = type("TVNonlinear", (df.NonlinearGaussianModel,), attrs)
    linear = Linear(F, H, Q, R, torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64), B=B)
    nonlinear = Nonlinear(lambda x, u: x @ F.mT + u @ B.mT, lambda x: x @ H.mT, Q, R,
                          torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64), dim_u=1)  # fmt: skip
    return linear, nonlinear


YS = torch.randn(8, 2, generator=torch.Generator().manual_seed(0), dtype=F64)
US = torch.zeros(8, 1, dtype=F64)


def _runs(linear, nonlinear):
    """Every Gaussian filter that reads the model's covariances at each step."""

    def online(est, model):
        def go():
            carry = est.init(model)
            with torch.no_grad():  # (the one-run host-array step where it applies)
                for y, u in zip(YS, US):
                    carry, _ = est.step(carry, y, u)

        return go

    return {
        "kalman_filter": lambda: df.kalman_filter(linear, YS, US),
        "kalman_filter parallel": lambda: df.kalman_filter(linear, YS, US, method="parallel"),
        "KalmanFilter.step": online(df.KalmanFilter(), linear),
        "extended_kalman_filter": lambda: df.extended_kalman_filter(nonlinear, YS, US),
        "unscented_kalman_filter": lambda: df.unscented_kalman_filter(nonlinear, YS, US),
        "adaptive_kalman_filter": lambda: adaptive_kalman_filter(nonlinear, YS, US),
        "expected input KF": online(df.ExpectedInputKalmanFilter(0.9), linear),
        "gated EKF": online(GatedFilter(ChiSquareDetector(2, 0.01)), nonlinear),
    }


@pytest.mark.parametrize("how", sorted(BAD))
@pytest.mark.parametrize("which", ["process_cov", "measurement_cov"])
def test_a_bad_time_varying_covariance_is_named_by_every_gaussian_filter(which, how):
    linear, nonlinear = _models(which, how)
    # (the process noise of step k enters the prediction of k + 1: read at k = BAD_STEP)
    for name, run in _runs(linear, nonlinear).items():
        with pytest.raises(ValueError, match=rf"{which}\({BAD_STEP}\).*{WHY[how]}") as info:
            run()
        assert "TV" in str(info.value), name


def test_the_smoothers_name_it_too():
    linear, nonlinear = _models("process_cov", "negative")
    good_linear, good_nonlinear = _models("process_cov", "negative")
    for model in (good_linear, good_nonlinear):
        type(model).process_cov = lambda self, k: self.process_noise.cov
    filtered = df.kalman_filter(good_linear, YS, US)
    with pytest.raises(ValueError, match=r"process_cov\(3\).*positive semi-definite"):
        df.rts_smoother(linear, filtered, US)
    filtered = df.unscented_kalman_filter(good_nonlinear, YS, US)
    with pytest.raises(ValueError, match=r"process_cov\(3\).*positive semi-definite"):
        df.unscented_rts_smoother(nonlinear, filtered, US)


def test_a_singular_time_varying_covariance_still_runs():
    """``R_3 = 0`` (a perfect measurement at one step) and ``Q_k = 0``: semi-definite, as the
    Gaussian filters take them (only drawing from them needs them definite), the same
    numbers as the time-invariant filter at every other step."""

    class Exact(df.LinearGaussianModel):
        time_varying = True

        def measurement_cov(self, k):
            return (
                torch.zeros_like(self.measurement_noise.cov)
                if k == 3
                else self.measurement_noise.cov
            )

        def process_cov(self, k):
            return torch.zeros_like(self.process_noise.cov) if k == 5 else self.process_noise.cov

    model = Exact(F, H, Q, R, torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64), B=B)
    result = df.kalman_filter(model, YS, US)
    # a perfect measurement of the whole state: the posterior is the measurement
    torch.testing.assert_close(result.means[2], YS[2])
    assert float(result.covs[2].abs().max()) < 1e-12
    assert bool(torch.isfinite(result.log_likelihood))


def test_a_model_that_overrides_nothing_is_not_checked():
    model = df.LinearGaussianModel(F, H, Q, R, torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64))
    # the noise module's own covariance, as read before: no copy, no check
    assert step_covariance(model, "process_cov", 4) is model.process_cov(4)
    assert step_covariance(model, "measurement_cov", 4) is model.measurement_cov(4)


def test_bias_estimator_refuses_a_nan_residual_on_a_flagged_step():
    est = BiasAttackEstimator(2, 0.9)
    S = 0.1 * torch.eye(2, dtype=F64).expand(1, 2, 2)
    state = est.init((1,))
    with pytest.raises(ValueError, match="residual contains NaN"):
        est.step(state, torch.tensor([[float("nan"), 0.0]], dtype=F64), S, torch.tensor([True]))
    # a NaN on an entry not flagged is never read: the same as a zero there
    flag = torch.tensor([[False, True]])
    _, with_nan, _ = est.step(state, torch.tensor([[float("nan"), 0.5]], dtype=F64), S, flag)
    _, with_zero, _ = est.step(state, torch.tensor([[0.0, 0.5]], dtype=F64), S, flag)
    assert bool(torch.isfinite(with_nan).all())
    torch.testing.assert_close(with_nan, with_zero)


def test_bias_estimator_refuses_a_flag_that_is_not_0_or_1_and_a_bad_residual_cov():
    est = BiasAttackEstimator(2, 0.9)
    state, r = est.init((1,)), torch.tensor([[1.0, 0.5]], dtype=F64)
    S = 0.1 * torch.eye(2, dtype=F64).expand(1, 2, 2)
    with pytest.raises(ValueError, match="flag must be bool or 0/1"):
        est.step(state, r, S, torch.tensor([0.3], dtype=F64))
    # 0/1 numbers are flags
    _, as_float, _ = est.step(state, r, S, torch.tensor([1.0], dtype=F64))
    _, as_bool, _ = est.step(state, r, S, torch.tensor([True]))
    torch.testing.assert_close(as_float, as_bool)
    skew = torch.tensor([[[0.1, 0.09], [-0.09, 0.1]]], dtype=F64)
    with pytest.raises(ValueError, match="residual_cov must be symmetric"):
        est.step(state, r, skew, torch.tensor([True]))
    with pytest.raises(ValueError, match="residual_cov must be a covariance"):
        est.step(state, r, -S, torch.tensor([True]))
    with pytest.raises(TypeError, match="flag must be a torch.Tensor"):
        est.step(state, r, S, True)


def test_the_modified_pf_feeds_its_estimator_as_the_public_step_would():
    """The modified PF calls the estimator's update on its own (checked) innovations: the
    same numbers as the public step on the same inputs."""
    est = BiasAttackEstimator(2, 0.9)
    state = est.init((3,))
    g = torch.Generator().manual_seed(1)
    for _ in range(4):
        r = torch.randn(3, 2, generator=g, dtype=F64)
        S = 0.1 * torch.eye(2, dtype=F64).expand(3, 2, 2)
        flag = torch.rand(3, 2, generator=g) < 0.6
        public = est.step(state, r, S, flag)
        internal = est._update(state, r, S, est._flagged(flag, r))
        for a, b in zip(public[1:], internal[1:]):
            torch.testing.assert_close(a, b)
        state = public[0]


def test_the_zero_mean_check_reads_a_gaussian_loc_written_in_place():
    """``init``'s zero-mean check takes a Gaussian's cached ``loc == 0`` (no read of the
    mean): a loc written in place after a first ``init`` is still refused."""
    model = df.LinearGaussianModel(F, H, Q, R, torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64))
    kf = df.KalmanFilter()
    kf.init(model)
    with torch.no_grad():
        model.measurement_noise.loc[0] = 0.5
    with pytest.raises(ValueError, match=r"measurement_noise has mean \[0.5, 0.0\]"):
        kf.init(model)
    with torch.no_grad():
        model.measurement_noise.loc[0] = 0.0
    kf.init(model)
