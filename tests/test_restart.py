"""Restart from a χ²-gated copy that never reads the estimate: on every step where the
copy's test is quiet the compensated filter takes the copy's posterior
(NeuralCompensation(restart=α))."""

from __future__ import annotations

import pytest
import torch
from test_learned_estimator import _data, _linear, _net, neural_gaussian_filter

import difffilter as df
from difffilter.fdi.detectors import chi_square_quantile, normalized_innovation_squared
from difffilter.models.learned_estimator import NeuralCompensation
from difffilter.models.neural_estimator import EstimatorCard


def test_a_test_that_is_always_quiet_gives_the_filter_alone_and_one_never_quiet_no_restart():
    model = _linear()
    _, ys, _ = model.simulate(12, (3,), generator=torch.Generator().manual_seed(0))  # no attack
    full = neural_gaussian_filter(model, ys, network=_net(), filter=df.KalmanFilter())
    assert full.attack.abs().max() > 1e-2  # the network's estimate moves the filter
    alone = df.kalman_filter(model, ys)
    nis = normalized_innovation_squared(alone.innovations, alone.innovation_covs)
    assert nis.max() < chi_square_quantile(2, 1 - 1e-12)  # every step of the copy is quiet
    quiet = neural_gaussian_filter(model, ys, network=_net(), filter=df.KalmanFilter(),
                                   restart=1e-12)  # fmt: skip
    torch.testing.assert_close(quiet.means, alone.means, rtol=0, atol=1e-12)
    torch.testing.assert_close(quiet.covs, alone.covs, rtol=0, atol=1e-12)
    assert nis.min() > chi_square_quantile(2, 1e-12)  # and none is quiet at α = 1 − 1e-12
    loud = neural_gaussian_filter(model, ys, network=_net(), filter=df.KalmanFilter(),
                                  restart=1 - 1e-12)  # fmt: skip
    # (the same updates; the shared gain schedule's moments are computed for two carries)
    torch.testing.assert_close(loud.means, full.means, rtol=0, atol=1e-14)
    torch.testing.assert_close(loud.attack, full.attack, rtol=0, atol=1e-14)


def gated_copy_by_hand(model, ys, alpha: float) -> list[tuple]:
    """``[(nis [B], quiet [B], copy), …]`` per step: a Kalman filter gated by its own χ²
    test at ``alpha`` written out (its NIS against ``F⁻¹(1 − α)``; where quiet it updates
    with ``y_k``, where loud it keeps its prediction), ``copy`` its posterior."""
    limit = chi_square_quantile(ys.shape[-1], 1 - alpha)
    copy, steps = df.kalman.gaussian_init(model, (ys.shape[0],)), []
    for k in range(ys.shape[1]):
        pred_mean, pred_cov = df.kalman_predict(model, copy, None)
        updated, step_out = df.kalman_step(model, copy, ys[:, k])
        nis = normalized_innovation_squared(step_out.innovation, step_out.innovation_cov)
        quiet = nis <= limit
        copy = updated._replace(mean=torch.where(quiet[:, None], updated.mean, pred_mean),
                                cov=torch.where(quiet[:, None, None], updated.cov, pred_cov))  # fmt: skip
        steps.append((nis, quiet, copy))
    return steps


def test_each_step_restarts_from_the_gated_copy_where_its_test_is_quiet_by_hand():
    """Step by step against a χ²-gated Kalman filter written out here: its NIS against
    ``F⁻¹(1 − α)``; where quiet it updates with ``y_k`` and the posterior is its own,
    where loud it keeps its prediction and the posterior is the compensated update of the
    previous posterior with ``y_k − â_k``."""
    model = _linear()
    _, ys = _data(model, runs=4, steps=14)
    alpha = 0.05
    out = neural_gaussian_filter(model, ys, network=_net(), filter=df.KalmanFilter(),
                                 restart=alpha)  # fmt: skip
    prior = df.kalman.gaussian_init(model, (4,))
    quiet_steps = []
    for k, (_, quiet, copy) in enumerate(gated_copy_by_hand(model, ys, alpha)):
        quiet_steps.append(quiet)
        compensated, _ = df.kalman_step(model, prior, ys[:, k] - out.attack[:, k])
        want = torch.where(quiet[:, None], copy.mean, compensated.mean)
        torch.testing.assert_close(out.means[:, k], want, rtol=0, atol=1e-10)
        prior = compensated._replace(mean=out.means[:, k], cov=torch.where(
            quiet[:, None, None], copy.cov, compensated.cov))  # fmt: skip
    quiet = torch.stack(quiet_steps, 1)
    assert quiet.any() and (~quiet).any()  # both branches are exercised (the bias from step 5)


@pytest.mark.parametrize("option", [{"restart": 0.05}, {"reject": 0.05}])
def test_gradients_flow_through_the_branch_taken(option):
    """The restart's hard choice, and the rejection's (tests/test_reject.py)."""
    model = _linear()
    _, ys = _data(model, runs=2, steps=10)
    net = _net()
    out = neural_gaussian_filter(model, ys, network=net, filter=df.KalmanFilter(), **option)
    out.means.square().sum().backward()
    for weights in (net.W, net.V):  # the estimate's weights (the head does not move the means)
        assert torch.isfinite(weights.grad).all() and weights.grad.abs().sum() > 0


def test_restart_needs_a_rate_a_gaussian_filter_a_sensor_attack_and_every_entry():
    with pytest.raises(ValueError, match="restart must be a false-alarm rate in"):
        NeuralCompensation(_net(), df.KalmanFilter(), restart=1.5)
    with pytest.raises(ValueError, match="restart must be a false-alarm rate in"):
        NeuralCompensation(_net(), df.KalmanFilter(), restart=True)
    with pytest.raises(ValueError, match="inner must be a Gaussian filter"):
        NeuralCompensation(_net(), df.ParticleFilter(10), restart=0.01)
    model = _linear()
    _, ys = _data(model, runs=2, steps=3)
    est = NeuralCompensation(_net(), df.KalmanFilter(), restart=0.01)
    mask = torch.ones_like(ys, dtype=torch.bool)
    mask[0, 1, 0] = False  # an entry lost (all True is no mask)
    with pytest.raises(ValueError, match="restart tests every channel"):
        df.loop.open_loop(est, model, ys, mask=mask)


def test_the_card_carries_the_restart_rate():
    card = EstimatorCard(filter="kf", restart=0.01)
    assert EstimatorCard.from_dict(card.to_dict()).restart == 0.01
    assert EstimatorCard.from_dict({"filter": "kf"}).restart is None  # older cards


@pytest.mark.parametrize("gating", [False, True])
def test_without_evidence_every_output_but_the_density_is_the_same_bit_for_bit(gating):
    """``evidence=False`` (what the training task builds) skips the density of the
    compensated update and of the copy's: every mean, covariance, attack estimate and score
    is the same, bit for bit, and the log-likelihood is absent instead of computed."""
    model = _linear()
    _, ys = _data(model, runs=4, steps=14)
    outs = [
        neural_gaussian_filter(
            model,
            ys,
            network=_net(),
            filter=df.KalmanFilter(),
            restart=0.05,
            gating=gating,
            evidence=evidence,
        )  # fmt: skip
        for evidence in (True, False)
    ]
    with_density, without = outs
    for name in ("means", "covs", "attack"):
        assert torch.equal(getattr(with_density, name), getattr(without, name)), name
    assert torch.equal(with_density.detection.scores, without.detection.scores)
    assert torch.isfinite(with_density.extras["log_likelihood"]).all()
    assert "log_likelihood" not in without.extras
