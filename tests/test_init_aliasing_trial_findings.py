"""A carry from ``init`` holds its own tensors (an aliasing trial): written in place (a write
the step follows), it had written the model's prior through an expanded view, moving every
run's start, every later ``init`` and ``model.simulate``; the adaptive KF's ``attack0``
option likewise."""

import pytest
import torch

import difffilter as df
from difffilter.fdi import AdaptiveKalmanFilter

F64 = torch.float64


def _model():
    F = torch.tensor([[0.9, 0.1], [0.0, 0.8]], dtype=F64)
    H = torch.eye(2, dtype=F64)
    return df.LinearGaussianModel(
        F, H, 0.1 * torch.eye(2, dtype=F64), 0.2 * torch.eye(2, dtype=F64),
        torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64), B=torch.eye(2, dtype=F64),
    )  # fmt: skip


@pytest.mark.parametrize("make", [lambda: df.KalmanFilter(), lambda: df.ExtendedKalmanFilter(),
                                  lambda: df.UnscentedKalmanFilter()])  # fmt: skip
def test_writing_one_runs_start_moves_neither_the_other_runs_nor_the_model(make):
    model, estimator = _model(), make()
    carry = estimator.init(model, (3,))
    carry.mean[0] = torch.tensor([5.0, 1.0], dtype=F64)
    _, out = estimator.step(carry, torch.zeros(3, 2, dtype=F64))
    torch.testing.assert_close(out.mean[1:], torch.zeros(2, 2, dtype=F64), rtol=0, atol=1e-12)
    assert out.mean[0].abs().sum() > 0.5  # the written start is followed
    assert model.initial.mean.abs().sum() == 0
    assert estimator.init(model, (2,)).mean.abs().sum() == 0


def test_writing_the_covariance_of_a_filter_without_a_schedule_leaves_the_prior():
    model = _model()
    carry = df.ExtendedKalmanFilter().init(model, (2,))
    carry.cov.mul_(4.0)
    torch.testing.assert_close(model.initial.cov, torch.eye(2, dtype=F64), rtol=0, atol=0)


def test_the_adaptive_filters_attack0_and_prior_are_not_written_through_its_carry():
    model = _model()
    estimator = AdaptiveKalmanFilter(attack0=torch.zeros(2, dtype=F64))
    carry = estimator.init(model, (3,))
    carry.attack[0] = torch.tensor([2.0, 2.0], dtype=F64)
    carry.mean[0] = torch.tensor([1.0, 1.0], dtype=F64)
    carry.cov[0].mul_(3.0)
    carry.attack_cov[0].mul_(3.0)
    assert estimator.attack0.abs().sum() == 0
    assert model.initial.mean.abs().sum() == 0
    torch.testing.assert_close(model.initial.cov, torch.eye(2, dtype=F64), rtol=0, atol=0)
    fresh = estimator.init(model, (3,))
    torch.testing.assert_close(carry.attack[1:], fresh.attack[1:], rtol=0, atol=0)
    torch.testing.assert_close(carry.attack_cov[1:], fresh.attack_cov[1:], rtol=0, atol=0)
    torch.testing.assert_close(carry.cov[1:], fresh.cov[1:], rtol=0, atol=0)


def test_the_bias_estimators_start_is_its_own():
    from difffilter.fdi import BiasAttackEstimator

    est = BiasAttackEstimator(2, 0.5)
    state = est.init((2,))
    state.mean[0] = torch.tensor([1.0, 1.0, 2.0, 2.0], dtype=state.mean.dtype)
    state.cov[0, 0] = 5.0
    assert state.mean[1].abs().sum() == 0
    assert est.init((2,)).mean.abs().sum() == 0
    assert float(est.model.initial.cov[0, 0]) == pytest.approx(1e-12)
