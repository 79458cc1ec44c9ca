"""Gating and compensation in one estimator: the network may drop a measurement (with its
probability of attack) as well as subtract its estimate (NeuralCompensation(gating=True))."""

from __future__ import annotations

import pytest
import torch
from test_learned_estimator import (
    _data,
    _linear,
    _net,
    neural_gaussian_filter,
    neural_particle_filter,
)

import difffilter as df
from difffilter.fdi.neural import gate_of
from difffilter.models.learned_estimator import NeuralCompensation


def _with_head_bias(bias, net=None):
    """``net`` (default ``_net()``) whose head answers ``logit = c = bias`` (one per area, or
    one for all) at every step: ``g = sigmoid(c)``."""
    net = _net() if net is None else net
    with torch.no_grad():
        net.P.zero_()
        net.c.copy_(torch.as_tensor(bias, dtype=net.c.dtype).expand_as(net.c))
    return net


@pytest.mark.parametrize("inner", [df.KalmanFilter, df.ExtendedKalmanFilter])
def test_gate_zero_is_compensation_and_gate_one_skips_the_update(inner):
    model = _linear()
    _, ys = _data(model)
    never = _with_head_bias(-60.0)
    plain = neural_gaussian_filter(model, ys, network=never, filter=inner())
    gated = neural_gaussian_filter(model, ys, network=never, filter=inner(), gating=True)
    torch.testing.assert_close(gated.means, plain.means, rtol=0, atol=1e-12)
    torch.testing.assert_close(gated.covs, plain.covs.expand_as(gated.covs), rtol=0, atol=1e-12)
    # g = 1: every update skipped, the filter only predicts: m_k = F^k m_0, P_k = F P F' + Q
    always = _with_head_bias(60.0)
    dropped = neural_gaussian_filter(model, ys, network=always, filter=inner(), gating=True)
    F, Q = model.transition_matrix(0), model.process_cov(0)
    mean, cov = model.initial.mean.expand(3, 2), model.initial.cov
    for t in range(ys.shape[1]):
        mean, cov = mean @ F.mT, F @ cov @ F.mT + Q
        torch.testing.assert_close(dropped.means[:, t], mean, rtol=0, atol=1e-12)
        torch.testing.assert_close(dropped.covs[:, t], cov.expand(3, 2, 2), rtol=0, atol=1e-12)


def test_a_half_gate_gives_the_moments_of_the_two_component_mixture_by_hand():
    model = _linear()
    _, ys = _data(model, runs=2, steps=1)
    half = _with_head_bias(0.0)  # g = 1/2
    out = neural_gaussian_filter(model, ys, network=half, filter=df.KalmanFilter(), gating=True)
    a_hat = out.attack[:, 0]
    pred = df.kalman.gaussian_init(model, (2,))
    pm, pc = pred.mean @ model.transition_matrix(0).mT, None
    pc = model.transition_matrix(0) @ pred.cov @ model.transition_matrix(0).mT + model.process_cov(
        0
    )
    upd, _ = df.kalman_step(model, pred, ys[:, 0] - a_hat)
    jump = upd.mean - pm
    want_mean = pm + 0.5 * jump
    want_cov = 0.5 * upd.cov + 0.5 * pc + 0.25 * jump.unsqueeze(-1) * jump.unsqueeze(-2)
    torch.testing.assert_close(out.means[:, 0], want_mean, rtol=0, atol=1e-12)
    torch.testing.assert_close(out.covs[:, 0], want_cov, rtol=0, atol=1e-12)


def test_the_particle_filters_gate_tempers_its_update():
    model = _linear()
    _, ys = _data(model)
    g = lambda: torch.Generator().manual_seed(4)  # noqa: E731
    opts = dict(num_particles=64, ess_threshold=0.0)  # no resampling: the weights are the update
    never, always = _with_head_bias(-60.0), _with_head_bias(60.0)
    plain = neural_particle_filter(model, ys, network=never, generator=g(), **opts)
    gated = neural_particle_filter(model, ys, network=never, generator=g(), gating=True, **opts)
    torch.testing.assert_close(gated.means, plain.means, rtol=0, atol=1e-10)
    # g = 1: the likelihood is switched off, so what is measured does not matter at all
    dropped = neural_particle_filter(model, ys, network=always, generator=g(), gating=True, **opts)
    moved = neural_particle_filter(model, ys + 10.0, network=always, generator=g(), gating=True,
                                   **opts)  # fmt: skip
    torch.testing.assert_close(moved.means, dropped.means, rtol=0, atol=0)
    assert not torch.allclose(dropped.means, plain.means, atol=1e-3)


def test_gradients_reach_the_head_through_the_gate_gradcheck():
    model = _linear()
    _, ys = _data(model, runs=2, steps=4)
    net = _net()
    del net.c  # the head's bias becomes the input gradcheck perturbs

    def means(c):
        net.c = c
        return df.open_loop(
            NeuralCompensation(net, df.KalmanFilter(), gating=True), model, ys
        ).means

    c = torch.tensor([0.3], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(means, (c,))
    means(c).sum().backward()
    assert c.grad.abs().item() > 0  # the gate moves the means
    assert gate_of(torch.tensor([[0.0, 2.0]])).item() == pytest.approx(
        torch.sigmoid(torch.tensor(2.0)).item()
    )


def test_gating_needs_a_head_and_a_sensor_attack():
    from difffilter.models.neural_estimator import NeuralFDIEstimator

    headless = NeuralFDIEstimator(area_dim=2, resid_dim=2, a=2, b=2, hidden=4, detection_head=False,
                                  dtype=torch.float64)  # fmt: skip
    with pytest.raises(ValueError, match="gating drops a measurement"):
        NeuralCompensation(headless, df.KalmanFilter(), gating=True)


def test_the_task_trains_a_gated_estimator_and_its_card_composes_one():
    from difffilter.models.learned_estimator import compose
    from difffilter.train.task import FilterEstimatorTask

    task = FilterEstimatorTask("four_tank_bias", num_particles=20, hidden=4, gating=True)
    assert task.estimator_object(training=True).gating
    card = task.card()
    assert card.gating and compose(task.estimator, card).gating
    assert not compose(task.estimator, card.__class__(**{**card.to_dict(), "gating": False})).gating
