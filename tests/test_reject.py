"""Rejection of the compensated measurement: where the compensated innovation
``ν_k − â_k`` fails its χ² test at rate ``ρ``, the compensated filter keeps its prediction
(NeuralCompensation(reject=ρ))."""

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
from difffilter.fdi.detectors import chi_square_quantile, normalized_innovation_squared
from difffilter.models.learned_estimator import NeuralCompensation
from difffilter.models.neural_estimator import EstimatorCard


def test_each_step_keeps_the_prediction_where_the_compensated_innovation_fails_by_hand():
    """Step by step against the Kalman filter written out here: the compensated update of
    the previous posterior with ``y_k − â_k``; its innovation's NIS against
    ``F⁻¹_{χ²_2}(1 − ρ)``; the update where it passes, the prediction where it fails."""
    model = _linear()
    _, ys = _data(model, runs=4, steps=14)
    rho = 0.05
    out = neural_gaussian_filter(model, ys, network=_net(), filter=df.KalmanFilter(), reject=rho)
    limit = chi_square_quantile(2, 1 - rho)
    prior, kept_steps = df.kalman.gaussian_init(model, (4,)), []
    for k in range(ys.shape[1]):
        pred_mean, pred_cov = df.kalman_predict(model, prior, None)
        compensated, step = df.kalman_step(model, prior, ys[:, k] - out.attack[:, k])
        kept = normalized_innovation_squared(step.innovation, step.innovation_cov) <= limit
        kept_steps.append(kept)
        mean = torch.where(kept[:, None], compensated.mean, pred_mean)
        cov = torch.where(kept[:, None, None], compensated.cov, pred_cov)
        torch.testing.assert_close(out.means[:, k], mean, rtol=0, atol=1e-10)
        torch.testing.assert_close(out.covs[:, k], cov, rtol=0, atol=1e-10)
        prior = compensated._replace(mean=mean, cov=cov)
    kept = torch.stack(kept_steps, 1)
    assert kept.any() and (~kept).any()  # both branches are exercised (the bias from step 5)


def test_a_test_that_never_fails_is_the_compensation_alone_and_one_always_failing_predicts():
    model = _linear()
    _, ys, _ = model.simulate(12, (3,), generator=torch.Generator().manual_seed(0))  # no attack
    full = neural_gaussian_filter(model, ys, network=_net(), filter=df.KalmanFilter())
    never = neural_gaussian_filter(model, ys, network=_net(), filter=df.KalmanFilter(),
                                   reject=1e-12)  # fmt: skip
    assert full.attack.abs().max() > 1e-2  # the network's estimate moves the filter
    torch.testing.assert_close(never.means, full.means, rtol=0, atol=1e-12)
    torch.testing.assert_close(never.attack, full.attack, rtol=0, atol=1e-12)
    always = neural_gaussian_filter(model, ys, network=_net(), filter=df.KalmanFilter(),
                                    reject=1 - 1e-12)  # fmt: skip
    # no update ever: the prior mean (zero) and the covariance recursion P ← F P Fᵀ + Q
    assert always.means.abs().max() == 0
    cov, Q = model.initial.cov, model.process_noise.cov
    for k in range(ys.shape[1]):
        cov = model.F @ cov @ model.F.T + Q
        torch.testing.assert_close(always.covs[:, k], cov.expand(3, 2, 2), rtol=0, atol=1e-12)


def test_the_particle_filter_keeps_its_predictive_weights_where_the_compensated_innovation_fails():
    """Without resampling the weights are the updates: every step whose compensated
    innovation (the filter's predictive ``ν_k`` minus ``â_k``, against its ``S_k``) fails
    the test at ``ρ`` leaves them as they were (its evidence ``log Σ w⁻ = 0``), every other
    step weighs them; where every step fails, the measurements do not matter."""
    model = _linear()
    _, ys = _data(model, runs=3, steps=14)
    g = lambda: torch.Generator().manual_seed(4)  # noqa: E731
    opts = dict(num_particles=64, ess_threshold=0.0, network=_net())
    rho = 0.05
    out = neural_particle_filter(model, ys, generator=g(), reject=rho, **opts)
    x = out.extras
    nis = normalized_innovation_squared(x["innovations"] - out.attack, x["innovation_covs"])
    kept = nis <= chi_square_quantile(2, 1 - rho)
    assert kept.any() and (~kept).any()  # both branches (the bias from step 5)
    increments = x["log_likelihood_increments"]
    assert increments[~kept].abs().max() < 1e-12 and increments[kept].abs().min() > 1e-3
    # a test that always fails: what is measured does not matter at all (no update)
    always = neural_particle_filter(model, ys, generator=g(), reject=1 - 1e-12, **opts)
    moved = neural_particle_filter(model, ys + 10.0, generator=g(), reject=1 - 1e-12, **opts)
    torch.testing.assert_close(moved.means, always.means, rtol=0, atol=0)
    assert not torch.allclose(always.means, out.means, atol=1e-3)


def test_reject_needs_a_rate_a_sensor_attack_and_every_entry():
    with pytest.raises(ValueError, match="reject must be a false-alarm rate in"):
        NeuralCompensation(_net(), df.KalmanFilter(), reject=0.0)
    with pytest.raises(ValueError, match="channel must be 'sensor'"):
        NeuralCompensation(_net(), df.KalmanFilter(), reject=0.01, channel="actuator")
    model = _linear()
    _, ys = _data(model, runs=2, steps=3)
    mask = torch.ones_like(ys, dtype=torch.bool)
    mask[0, 1, 0] = False  # an entry lost (all True is no mask)
    for inner in (df.KalmanFilter(), df.ParticleFilter(16)):
        est = NeuralCompensation(_net(), inner, reject=0.01)
        with pytest.raises(ValueError, match="reject tests every channel"):
            df.loop.open_loop(est, model, ys, mask=mask)


def test_the_card_carries_the_rejection_rate():
    card = EstimatorCard(filter="kf", restart=0.01, reject=0.01)
    assert EstimatorCard.from_dict(card.to_dict()).reject == 0.01
    assert EstimatorCard.from_dict({"filter": "kf"}).reject is None  # older cards
