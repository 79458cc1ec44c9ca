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
    with pytest.raises(ValueError, match="learning.posterior must be True or False"):
        build(OnlineLearning(EKFRule(), posterior="yes"))
    # the flags of the estimator itself (read with bool(): "false" had gated, "no" standardised)
    for flag, value in (("gating", "false"), ("standardize", "no"), ("evidence", None),
                        ("record_inputs", 2)):  # fmt: skip
        with pytest.raises(ValueError, match=f"{flag} must be True or False; got {value!r}"):
            NeuralCompensation(net, df.KalmanFilter(), **{flag: value})
    for learning in (OnlineLearning(EKFRule(), init_scale=0.01),
                     OnlineLearning(GradientRule(), posterior=False, init_scale=2),
                     OnlineLearning(EKFRule())):  # fmt: skip
        build(learning)


def test_a_field_given_at_some_steps_only_is_named_when_the_steps_are_stacked():
    """The first step's fields alone had decided what ``stack_steps`` stacked: a detector
    scoring from step 2 on came out of ``open_loop`` without its detection or attack
    estimate (scored as a plain filter); the other order failed in torch's words."""
    from difffilter.estimator import stack_steps

    m, s = torch.zeros(3, 2, dtype=DT), torch.zeros(3, dtype=DT)
    runs = torch.Size([3])
    plain, scored = StepOutput(m), StepOutput(m, score=s, alarm=s > 1, attack=m[:, :1])
    for first, later, field in ((plain, scored, "attack is None at step 1 and given at step 2"),
                                (scored, plain, "attack is given at step 1 and None at step 2"),
                                (StepOutput(m, cov=torch.eye(2, dtype=DT)), plain,
                                 "cov is given at step 1 and None at step 2")):  # fmt: skip
        with pytest.raises(ValueError, match=field):
            stack_steps([first, later], runs)
    with pytest.raises(ValueError, match="a score without an alarm or an alarm without a score"):
        stack_steps([StepOutput(m, alarm=s > 1)] * 2, runs)
    out = stack_steps([scored, scored, scored], runs)  # every step: stacked as before
    assert out.detection.scores.shape == (3, 3) and out.attack.shape == (3, 3, 1)
    assert stack_steps([plain, plain], runs).detection is None


def test_output_of_keeps_a_particle_filters_records_as_its_steps_give_them():
    from difffilter.estimator import output_of

    model = _model()
    _, ys, _ = model.simulate(8, (2,), generator=torch.Generator().manual_seed(3))
    whole = output_of(df.particle_filter(model, ys, num_particles=64,
                                         generator=torch.Generator().manual_seed(4)))  # fmt: skip
    stepped = open_loop(df.ParticleFilter(num_particles=64), model, ys,
                        generator=torch.Generator().manual_seed(4))  # fmt: skip
    for key in ("ess", "resampled", "degenerate"):
        assert whole.extras[key].shape == stepped.extras[key].shape == (2, 8)
        torch.testing.assert_close(whole.extras[key], stepped.extras[key])


def test_a_need_whose_check_returns_no_reason_string_is_named():
    from difffilter.models.needs import Need, first_unmet

    met, unmet = Need("met", lambda sc, m: None), Need("unmet", lambda sc, m: "no dim_y")
    assert first_unmet((met, unmet), None, None) == "no dim_y"
    assert first_unmet((met,), None, None) is None
    for got in (True, False, "", 0):
        with pytest.raises(
            TypeError, match=r"the need 'a predicate': its check\(scenario, model\)"
        ):
            first_unmet((Need("a predicate", lambda sc, m, got=got: got),), None, None)


def test_an_outputs_covariances_must_fit_its_means():
    from difffilter.estimator import EstimatorOutput

    means = torch.zeros(3, 5, 2, dtype=DT)
    for bad in ((3, 5, 2), (5, 5), (3, 5, 3, 3), (4, 3, 5, 2, 2)):
        with pytest.raises(ValueError, match=r"covs must have shape \[3, 5, 2, 2\]"):
            EstimatorOutput(means, torch.zeros(bad, dtype=DT))
    # per run and step, shared, or the leading block (a particle filter's cov_dims)
    for good in ((3, 5, 2, 2), (5, 2, 2), (2, 2), (1, 5, 2, 2), (3, 5, 1, 1)):
        EstimatorOutput(means, torch.zeros(good, dtype=DT))


class _AttackInPlace(_Average):
    """Hands out its running attack estimate and score, written in place at later steps."""

    def _init(self, model, batch_shape, generators):
        carry = super()._init(model, batch_shape, generators)
        return carry._replace(model=(model, torch.zeros(*batch_shape, 2, dtype=DT)))

    def _step(self, carry, y, u, mask):
        model, attack = carry.model
        new = 0.5 * carry.mean + 0.5 * y
        attack.mul_(0.5).add_(0.5 * (y - new))  # written in place, then handed out
        score = attack.square().sum(-1)
        return _Carry(new, carry.k + 1, (model, attack)), StepOutput(
            new, attack=attack, score=score, alarm=score > 1.0, threshold=1.0
        )


def test_an_attack_estimate_written_in_place_after_it_was_handed_out_is_named():
    model = _model()
    _, ys, _ = model.simulate(6, (2,), generator=torch.Generator().manual_seed(1))
    with pytest.raises(RuntimeError, match="the attack it handed out at step 1 was written"):
        open_loop(_AttackInPlace(), model, ys)


class _SubtractingController:
    """``u = −½ (x̂ − ref)``, with ``e = out.mean; e −= ref`` (in place) when ``in_place``."""

    def __init__(self, in_place):
        self.in_place = in_place

    def init(self, batch_shape, dtype, device):
        return torch.zeros(*batch_shape, 2, dtype=dtype)

    def __call__(self, k, y, out):
        ref = torch.tensor([1.0, 0.0], dtype=DT)
        if self.in_place:
            e = out.mean
            e -= ref
        else:
            e = out.mean - ref
        return -0.5 * e


def test_a_controller_writing_the_estimators_output_in_place_is_named_not_the_estimator():
    eye = torch.eye(2, dtype=DT)
    F = torch.tensor([[1.0, 0.1], [0.0, 1.0]], dtype=DT)
    model = df.LinearGaussianModel(F, eye, 0.01 * eye, 0.05 * eye, torch.zeros(2, dtype=DT), eye,
                                   B=0.1 * eye)  # fmt: skip
    run = dict(noise=DrawnNoise(torch.Generator().manual_seed(0)), x0=torch.zeros(3, 2, dtype=DT),
               estimator=df.KalmanFilter())  # fmt: skip
    closed_loop(model, 5, controller=_SubtractingController(False), **run)
    with pytest.raises(ValueError, match="controller _SubtractingController.__call__ wrote in "
                       "place into the estimator's output the loop handed it at step 1"):  # fmt: skip
        closed_loop(model, 5, controller=_SubtractingController(True), **run)


def test_an_online_learnings_init_scale_may_be_a_numpy_number():
    import numpy as np

    from difffilter.fdi.neural import NeuralCompensation, OnlineLearning
    from difffilter.models.neural_estimator import NeuralFDIEstimator
    from difffilter.param_ekf import EKFRule

    net = NeuralFDIEstimator(num_areas=1, area_dim=2, resid_dim=2, a=1, b=1, hidden=4, dtype=DT)
    for scale in (np.float32(0.01), np.int64(1), np.float64(0.5)):  # (refused for a while)
        NeuralCompensation(
            net, df.KalmanFilter(), learning=OnlineLearning(EKFRule(), init_scale=scale)
        )
    with pytest.raises(ValueError, match="init_scale must be a finite number > 0"):
        NeuralCompensation(
            net, df.KalmanFilter(), learning=OnlineLearning(EKFRule(), init_scale=torch.tensor(0.1))
        )


class _BackingOffController:
    """``u = −x̂ / (1 + tr(S + I))`` from the adaptive KF's ``extras["attack_covs"]`` (its
    next carry's own tensor), the sum in place (``S += I``) when ``in_place``."""

    def __init__(self, in_place):
        self.in_place = in_place

    def init(self, batch_shape, dtype, device):
        return torch.zeros(*batch_shape, 2, dtype=dtype, device=device)

    def __call__(self, k, y, out):
        S = out.extras["attack_covs"]
        if self.in_place:
            S += torch.eye(2, dtype=S.dtype)
        else:
            S = S + torch.eye(2, dtype=S.dtype)
        return -out.mean / (1.0 + torch.diagonal(S, dim1=-2, dim2=-1).sum(-1, keepdim=True))


def test_a_controller_writing_an_extra_of_the_output_in_place_is_named():
    """A review: the controller's check narrowed to the metrics' four fields had let
    ``S += I`` into the adaptive KF's carry move every later estimate (0.105)."""
    from difffilter.fdi import AdaptiveKalmanFilter
    from difffilter.loop import ReplayedNoise

    eye = torch.eye(2, dtype=DT)
    F = torch.tensor([[1.0, 0.1], [0.0, 0.95]], dtype=DT)
    model = df.LinearGaussianModel(F, eye, 1e-3 * eye, 1e-2 * eye, torch.zeros(2, dtype=DT), eye,
                                   B=eye)  # fmt: skip
    gen = torch.Generator().manual_seed(0)
    noise = ReplayedNoise(0.03 * torch.randn(2, 12, 2, generator=gen, dtype=DT),
                          0.1 * torch.randn(2, 12, 2, generator=gen, dtype=DT))  # fmt: skip
    run = dict(noise=noise, x0=torch.ones(2, 2, dtype=DT), estimator=AdaptiveKalmanFilter(0.7))
    closed_loop(model, 12, controller=_BackingOffController(False), **run)
    with pytest.raises(
        ValueError, match="controller _BackingOffController.__call__ wrote in place"
    ):
        closed_loop(model, 12, controller=_BackingOffController(True), **run)
