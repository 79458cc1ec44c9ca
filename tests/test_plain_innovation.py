"""The ``plain_innovation`` feature: the standardised innovation of an uncompensated copy
of the filter, each area reading its own channels."""

from __future__ import annotations

import pytest
import torch
from test_learned_estimator import _captured_inputs, _linear

import difffilter as df
from difffilter.loop import open_loop
from difffilter.models.learned_estimator import NeuralCompensation
from difffilter.models.neural_estimator import NeuralFDIEstimator

FEATURE = ("plain_innovation",)


def _data(model, runs=3, steps=15):
    _, ys, _ = model.simulate(steps, (runs,), generator=torch.Generator().manual_seed(2))
    ys = ys.clone()
    ys[:, 4:9, 1] += 0.7  # an attack on sensor 2 that ends at step 9
    return ys


def _two_areas(extra_inputs: int, seed: int = 4) -> NeuralFDIEstimator:
    """Two areas of one channel each (the model's two sensors)."""
    return NeuralFDIEstimator(num_areas=2, area_dim=1, a=2, b=2, hidden=4, init="symmetric",
                              init_scale=0.8, resid_scale=0.3, extra_inputs=extra_inputs,
                              seed=seed)  # fmt: skip


@pytest.mark.parametrize("masked", [False, True])
def test_each_area_reads_the_plain_kalman_filters_standardised_innovation(masked):
    """δ's last entry of area i at step k is ν°_{k,i} / √S°_{k,ii} of a Kalman filter run
    alone on the received measurements (0 where unreceived), while the compensated filter
    inside has other innovations."""
    model = _linear()
    ys = _data(model)
    mask = None
    if masked:
        mask = torch.ones(ys.shape, dtype=torch.bool)
        mask[0, 6, 1] = mask[2, 10, 0] = False
    net = _two_areas(extra_inputs=1)
    seen = _captured_inputs(net)
    est = NeuralCompensation(net, df.KalmanFilter(), features=FEATURE, residual="innovation")
    out = open_loop(est, model, ys, mask=mask)
    plain = df.kalman_filter(model, ys, mask=mask)
    std = torch.diagonal(plain.innovation_covs, dim1=-2, dim2=-1).sqrt()
    want = plain.innovations / std
    if masked:
        want = want * mask
    got = torch.stack([d[..., -1] for d in seen], dim=1)  # [B, T, J]
    torch.testing.assert_close(got, want, rtol=0, atol=1e-12)
    # the compensated filter is another filter: its state differs from the plain one's
    assert (out.means - plain.means).abs().max() > 1e-3


def test_zero_weights_on_the_feature_give_the_network_without_it():
    """The feature only adds inputs: with its V columns zero, every output equals the
    same network's without the feature (means, attack estimates, scores)."""
    model = _linear()
    ys = _data(model)
    without, with_ = _two_areas(extra_inputs=0), _two_areas(extra_inputs=1)
    with torch.no_grad():
        with_.W.copy_(without.W)
        with_.V.zero_()
        with_.V[..., :-1] = without.V
        for name in ("P", "c"):
            getattr(with_, name).copy_(getattr(without, name))
    a = open_loop(NeuralCompensation(without, df.KalmanFilter()), model, ys)
    b = open_loop(NeuralCompensation(with_, df.KalmanFilter(), features=FEATURE), model, ys)
    for name in ("means", "covs", "attack"):
        torch.testing.assert_close(getattr(b, name), getattr(a, name), rtol=0, atol=1e-12)
    torch.testing.assert_close(b.detection.scores, a.detection.scores, rtol=0, atol=1e-12)


def test_the_feature_is_differentiable_and_its_copy_never_reads_the_estimate():
    """A loss on the attack estimate has a gradient on the feature's weights; the plain
    copy's carry after the run equals the plain filter's whatever the network."""
    model = _linear()
    ys = _data(model)
    net = _two_areas(extra_inputs=1)
    est = NeuralCompensation(net, df.KalmanFilter(), features=FEATURE)
    carry = est.init(model, (ys.shape[0],))
    for k in range(ys.shape[1]):
        carry, out = est.step(carry, ys[:, k])
    out.attack.square().sum().backward()
    assert net.V.grad[..., -1].abs().max() > 0
    plain = df.kalman_filter(model, ys)
    torch.testing.assert_close(carry.plain.mean, plain.means[:, -1], rtol=0, atol=1e-12)


def test_the_feature_needs_a_gaussian_filter_and_whole_run_features_one_area():
    with pytest.raises(ValueError, match="uncompensated copy of a Gaussian filter"):
        NeuralCompensation(_two_areas(extra_inputs=1), df.ParticleFilter(8), features=FEATURE)
    with pytest.raises(ValueError, match=r"features \['mask'\] are read by a network of one"):
        NeuralCompensation(_two_areas(extra_inputs=2), df.KalmanFilter(), features=("mask",))
    with pytest.raises(ValueError, match="extra_inputs is 0"):
        NeuralCompensation(_two_areas(extra_inputs=0), df.KalmanFilter(), features=FEATURE)
