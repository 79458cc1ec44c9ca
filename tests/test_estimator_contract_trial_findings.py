"""Findings of trials of the estimator protocol and the LFC online learners: a user's step
that wrote its carry in place ran through the drivers silently (every stacked mean read the
last step's), and an ``OnlineLearning``'s ``rule`` and ``init_scale`` were taken unchecked."""

from __future__ import annotations

from typing import Any, NamedTuple

import pytest
import torch

import difffilter as df
from difffilter.estimator import Estimator
from difffilter.loop import DrawnNoise, closed_loop, open_loop
from difffilter.results import StepOutput

DT = torch.float64


class _Carry(NamedTuple):
    mean: torch.Tensor
    k: int = 0
    model: Any = None


class _Average(Estimator):
    """``x̂_k = (x̂_{k−1} + y_k) / 2``: out of place, or (``in_place``) written into the
    carry's tensor and that tensor handed out, against ``Estimator.step``'s contract."""

    carry_type = _Carry

    def __init__(self, in_place: bool = False, constant_cov: torch.Tensor | None = None):
        self.in_place, self.constant_cov = in_place, constant_cov

    def _init(self, model, batch_shape, generators):
        return _Carry(model.initial.mean.expand(*batch_shape, model.dim_x).clone(), 0, model)

    def _step(self, carry, y, u, mask):
        if self.in_place:
            carry.mean.mul_(0.5).add_(0.5 * y)
            new = carry.mean
        else:
            new = 0.5 * carry.mean + 0.5 * y
        return _Carry(new, carry.k + 1, carry.model), StepOutput(new, cov=self.constant_cov)


def _model():
    eye = torch.eye(2, dtype=DT)
    F = torch.tensor([[1.0, 0.1], [0.0, 1.0]], dtype=DT)
    return df.LinearGaussianModel(F, eye, 0.01 * eye, 0.05 * eye, torch.zeros(2, dtype=DT), eye)


def _by_hand(ys):
    mean, means = torch.zeros_like(ys[:, 0]), []
    for t in range(ys.shape[1]):
        mean = 0.5 * mean + 0.5 * ys[:, t]
        means.append(mean)
    return torch.stack(means, 1)


def test_a_step_writing_its_handed_out_mean_in_place_is_named_by_the_open_loop():
    model = _model()
    _, ys, _ = model.simulate(12, (3,), generator=torch.Generator().manual_seed(1))
    # a constant covariance handed out at every step is one tensor, never written: fine
    cov = 0.1 * torch.eye(2, dtype=DT)
    good = open_loop(_Average(constant_cov=cov), model, ys)
    torch.testing.assert_close(good.means, _by_hand(ys), rtol=0, atol=0)
    torch.testing.assert_close(good.covs, cov.expand(3, 12, 2, 2))
    with pytest.raises(RuntimeError, match="the mean it handed out at step 1 was written in place"):
        open_loop(_Average(in_place=True), model, ys)
    with torch.inference_mode():  # inference tensors keep no counter: not checked, still runs
        open_loop(_Average(), model, ys.clone())


def test_a_step_writing_its_handed_out_mean_in_place_is_named_by_the_closed_loop():
    model = _model()
    noise = DrawnNoise(torch.Generator().manual_seed(0))
    x0 = torch.zeros(2, 2, dtype=DT)
    good = closed_loop(model, 6, noise=noise, x0=x0, estimator=_Average())
    torch.testing.assert_close(
        good.output.means, _by_hand(good.trajectories.y_recv), rtol=0, atol=0
    )
    noise = DrawnNoise(torch.Generator().manual_seed(0))
    with pytest.raises(RuntimeError, match="_Average: the mean it handed out at step 1"):
        closed_loop(model, 6, noise=noise, x0=x0, estimator=_Average(in_place=True))


def test_an_online_learnings_rule_and_init_scale_are_checked_when_built():
    from difffilter.fdi.neural import NeuralCompensation, OnlineLearning
    from difffilter.models.neural_estimator import NeuralFDIEstimator
    from difffilter.param_ekf import EKFRule, GradientRule

    net = NeuralFDIEstimator(num_areas=1, area_dim=2, resid_dim=2, a=1, b=1, hidden=4,
                             dtype=DT)  # fmt: skip

    def build(learning):
        return NeuralCompensation(net, df.KalmanFilter(), learning=learning)

    for scale in (-0.01, 0.0, float("nan"), float("inf"), True, "0.01"):
        with pytest.raises(ValueError, match="learning.init_scale must be a finite number > 0"):
            build(OnlineLearning(EKFRule(), init_scale=scale))
    with pytest.raises(TypeError, match="learning.rule must be an EKFRule or a GradientRule"):
        build(OnlineLearning("ekf"))
    with pytest.raises(TypeError, match="learning.posterior must be True or False"):
        build(OnlineLearning(EKFRule(), posterior="yes"))
    for learning in (OnlineLearning(EKFRule(), init_scale=0.01),
                     OnlineLearning(GradientRule(), posterior=False, init_scale=2),
                     OnlineLearning(EKFRule())):  # fmt: skip
        build(learning)
