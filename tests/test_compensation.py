"""Compensation weighed by detection: the filter subtracts each area's estimate times its
probability of attack (NeuralCompensation(compensation="detected")) instead of the estimate."""

from __future__ import annotations

import pytest
import torch
from test_gating import _with_head_bias
from test_learned_estimator import (
    _data,
    _linear,
    _net,
    neural_gaussian_filter,
    neural_particle_filter,
)

import difffilter as df
from difffilter.models.learned_estimator import NeuralCompensation
from difffilter.models.neural_estimator import EstimatorCard, NeuralFDIEstimator
from difffilter.particle import particle_filter


def test_certain_attack_is_full_compensation_and_none_is_the_filter_alone():
    model = _linear()
    _, ys = _data(model)
    always, never = _with_head_bias(60.0), _with_head_bias(-60.0)
    full = neural_gaussian_filter(model, ys, network=always, filter=df.KalmanFilter())
    detected = neural_gaussian_filter(model, ys, network=always, filter=df.KalmanFilter(),
                                      compensation="detected")  # fmt: skip
    assert full.attack.abs().max() > 1e-2  # the estimate is not zero: the weight is what acts
    torch.testing.assert_close(detected.means, full.means, rtol=0, atol=1e-12)
    alone = neural_gaussian_filter(model, ys, network=never, filter=df.KalmanFilter(),
                                   compensation="detected")  # fmt: skip
    torch.testing.assert_close(alone.means, df.kalman_filter(model, ys).means, rtol=0, atol=1e-12)
    assert alone.attack.abs().max() > 1e-2  # â is reported, though none of it was subtracted
    g = lambda: torch.Generator().manual_seed(5)  # noqa: E731
    pf = neural_particle_filter(model, ys, network=never, num_particles=40, generator=g(),
                                compensation="detected")  # fmt: skip
    plain = particle_filter(model, ys, num_particles=40, generator=g())
    torch.testing.assert_close(pf.means, plain.means, rtol=0, atol=1e-12)
    pf_full = neural_particle_filter(model, ys, network=always, num_particles=40, generator=g())
    pf_det = neural_particle_filter(model, ys, network=always, num_particles=40, generator=g(),
                                    compensation="detected")  # fmt: skip
    torch.testing.assert_close(pf_det.means, pf_full.means, rtol=0, atol=1e-12)


def test_each_area_weighs_its_own_estimate_by_hand():
    """Two areas of one channel each, logits (−60, 0): the first step updates with
    y − (0, â₂ / 2), checked against the Kalman step on that measurement."""
    model = _linear()
    _, ys = _data(model, runs=2, steps=1)
    net = NeuralFDIEstimator(num_areas=2, area_dim=1, a=1, b=2, hidden=4, init="symmetric",
                             init_scale=0.5, resid_scale=3.0, seed=2, dtype=torch.float64)  # fmt: skip
    _with_head_bias([-60.0, 0.0], net)
    out = neural_gaussian_filter(model, ys, network=net, filter=df.KalmanFilter(),
                                 compensation="detected")  # fmt: skip
    a_hat = out.attack[:, 0]
    assert a_hat[:, 1].abs().min() > 1e-4
    prior = df.kalman.gaussian_init(model, (2,))  # kalman_step predicts, then updates
    applied = torch.stack([torch.zeros_like(a_hat[:, 0]), 0.5 * a_hat[:, 1]], -1)
    upd, _ = df.kalman_step(model, prior, ys[:, 0] - applied)
    torch.testing.assert_close(out.means[:, 0], upd.mean, rtol=0, atol=1e-12)


def test_detected_compensation_needs_a_head_and_an_additive_attack():
    headless = NeuralFDIEstimator(num_areas=1, area_dim=2, detection_head=False)
    with pytest.raises(ValueError, match="compensation='detected'.*detection head"):
        NeuralCompensation(headless, df.KalmanFilter(), compensation="detected")
    with pytest.raises(ValueError, match="not a Compensation"):
        NeuralCompensation(_net(), df.KalmanFilter(), compensation="sometimes")


def test_the_card_carries_the_compensation():
    card = EstimatorCard(filter="kf", compensation="detected")
    assert EstimatorCard.from_dict(card.to_dict()).compensation == "detected"
    assert EstimatorCard.from_dict({"filter": "kf"}).compensation == "full"  # older cards


def test_the_predicted_residual_is_standardised_and_masked_after_the_estimate_is_taken_off():
    """``ν_k − â_{k−1}``, then ``/ √diag S``, then 0 where unreceived (the docstring's
    order): once ``â`` (measurement units) came off the standardised, masked ν, so an
    unreceived entry read ``−â``."""
    net = NeuralFDIEstimator(num_areas=1, area_dim=2, a=1, b=1, hidden=4, init="symmetric",
                             init_scale=0.5, seed=1, dtype=torch.float64)  # fmt: skip
    nu = torch.tensor([[1.0, 2.0]], dtype=torch.float64)
    S = torch.diag(torch.tensor([4.0, 16.0], dtype=torch.float64))[None]
    mask = torch.tensor([[True, False]])
    for standardize, expected in ((False, [0.7, 0.0]), (True, [0.35, 0.0])):
        core = NeuralCompensation(net, df.KalmanFilter(), residual="predicted",
                                  standardize=standardize).core  # fmt: skip
        state = core.init(torch.Size([1]), torch.float64, "cpu", None)
        state = state._replace(attack_hist=torch.tensor([[[[0.3, -0.2]]]], dtype=torch.float64))
        *_, delta = core.step(state, nu, S, mask)
        torch.testing.assert_close(delta[0, 0, 2:], torch.tensor(expected, dtype=torch.float64))


def test_an_actuator_estimate_is_not_subtracted_from_the_measurements_innovation():
    net = NeuralFDIEstimator(num_areas=1, area_dim=1, resid_dim=2, a=1, b=1, hidden=4,
                             dtype=torch.float64)  # fmt: skip
    for residual in ("predicted", "lagged"):
        with pytest.raises(
            ValueError, match=f"residual='{residual}' subtracts the attack estimate"
        ):
            NeuralCompensation(net, df.KalmanFilter(), channel="actuator", residual=residual)
    NeuralCompensation(net, df.KalmanFilter(), channel="actuator")  # the innovation: fine
    from difffilter.fdi.neural import OnlineLearning
    from difffilter.param_ekf import EKFRule

    with pytest.raises(ValueError, match="online learning fits the estimate to the innovation"):
        NeuralCompensation(net, df.KalmanFilter(), channel="actuator",
                           learning=OnlineLearning(EKFRule()))  # fmt: skip


@pytest.mark.parametrize("kind", ["kf", "ekf", "learning"])
def test_a_carry_of_no_runs_on_a_model_of_three_parameter_sets_steps_three_runs(kind):
    """A trial: every estimator steps a carry of ``init(model, ())`` on a model of 3
    parameter sets as 3 runs (the contract), but NeuralCompensation failed in a raw cat
    error (its histories had the carry's batch, not the runs'). The same numbers as a
    carry of ``init(model, (3,))``."""
    from difffilter.fdi.neural import OnlineLearning
    from difffilter.param_ekf import EKFRule

    d = torch.float64
    Q3 = 0.02 * torch.eye(2, dtype=d) * torch.tensor([0.5, 1.0, 2.0], dtype=d)[:, None, None]
    model = df.LinearGaussianModel(torch.tensor([[1.0, 0.1], [-0.05, 0.95]], dtype=d),
                                   torch.eye(2, dtype=d), Q3, 0.04 * torch.eye(2, dtype=d),
                                   torch.zeros(2, dtype=d), torch.eye(2, dtype=d))  # fmt: skip
    ys = torch.randn(3, 4, 2, generator=torch.Generator().manual_seed(0), dtype=d)
    net = NeuralFDIEstimator(num_areas=1, area_dim=2, resid_dim=2, a=1, b=2, hidden=4, seed=1,
                             detection_head=False)  # fmt: skip
    inner = df.ExtendedKalmanFilter() if kind == "ekf" else df.KalmanFilter()
    kw = dict(residual="lagged", learning=OnlineLearning(EKFRule())) if kind == "learning" else {}
    est = NeuralCompensation(net, inner, **kw)
    outs = []
    for batch in ((), (3,)):
        carry = est.init(model, batch, torch.Generator().manual_seed(2))
        means = []
        for k in range(4):
            carry, out = est.step(carry, ys[:, k])
            means.append(out.mean)
        outs.append(torch.stack(means))
    assert outs[0].shape == (4, 3, 2)
    torch.testing.assert_close(outs[0], outs[1], rtol=0, atol=1e-12)


def test_a_batch_of_no_runs_gives_empty_outputs_with_online_learning_and_the_adaptive_pf():
    """A trial: ``open_loop`` on ``ys [0, T, dy]`` gives empty outputs for every estimator but
    these two, which failed in raw reshape errors (a ``-1`` inferred from no elements)."""
    from difffilter import fdi
    from difffilter.fdi.neural import OnlineLearning
    from difffilter.loop import open_loop
    from difffilter.param_ekf import EKFRule

    d = torch.float64
    model = df.LinearGaussianModel(torch.tensor([[1.0, 0.1], [-0.05, 0.95]], dtype=d),
                                   torch.eye(2, dtype=d), 0.02 * torch.eye(2, dtype=d),
                                   0.04 * torch.eye(2, dtype=d), torch.zeros(2, dtype=d),
                                   torch.eye(2, dtype=d), B=torch.tensor([[0.0], [0.1]], dtype=d))  # fmt: skip
    ys, us = torch.zeros(0, 5, 2, dtype=d), torch.zeros(0, 5, 1, dtype=d)
    net = NeuralFDIEstimator(num_areas=1, area_dim=2, resid_dim=2, a=1, b=2, hidden=4, seed=1,
                             detection_head=False)  # fmt: skip
    for est in (fdi.AdaptiveParticleFilter(16),
                NeuralCompensation(net, df.KalmanFilter(), residual="lagged",
                                   learning=OnlineLearning(EKFRule()))):  # fmt: skip
        out = open_loop(est, model, ys, us, generator=torch.Generator().manual_seed(0))
        assert out.means.shape == (0, 5, 2)


@pytest.mark.parametrize("option", [{"restart": 0.05}, {"reject": 0.05}])
def test_restart_and_reject_take_an_all_true_mask_as_no_mask(option):
    """A trial: both refused a mask of every entry received, which every other estimator
    reads as ``mask=None``; a mask with an entry lost is still refused."""
    d = torch.float64
    model = df.LinearGaussianModel(torch.tensor([[1.0, 0.1], [-0.05, 0.95]], dtype=d),
                                   torch.eye(2, dtype=d), 0.02 * torch.eye(2, dtype=d),
                                   0.04 * torch.eye(2, dtype=d), torch.zeros(2, dtype=d),
                                   torch.eye(2, dtype=d))  # fmt: skip
    net = NeuralFDIEstimator(num_areas=1, area_dim=2, resid_dim=2, a=1, b=2, hidden=4, seed=1)
    est = NeuralCompensation(net, df.KalmanFilter(), **option)
    y = torch.randn(3, 2, generator=torch.Generator().manual_seed(0), dtype=d)
    with torch.no_grad():
        _, plain = est.step(est.init(model, (3,)), y)
        _, masked = est.step(est.init(model, (3,)), y, None, torch.ones(3, 2, dtype=torch.bool))
        # (the Kalman filter's masked update with every entry received: the same numbers up
        # to the order of its operations, bit for bit on one CPU, 1 ulp apart on another)
        torch.testing.assert_close(plain.mean, masked.mean, rtol=1e-14, atol=1e-15)
        lost = torch.ones(3, 2, dtype=torch.bool)
        lost[0, 1] = False
        with pytest.raises(ValueError, match="needs every entry received"):
            est.step(est.init(model, (3,)), y, None, lost)
