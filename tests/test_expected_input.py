"""The UDP-like Kalman filter (difffilter.expected_input): Schenato et al.'s predictor
written out in numpy, the Kalman filter at ν̄ = 1, and its consistency over the arrivals
(its P is the mean squared error of the loop under unacknowledged, zeroed inputs, where a
Kalman filter given the sent inputs is overconfident)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import difffilter as df
from difffilter.loop import InputLoss, KnownInputs, ReplayedNoise, closed_loop, open_loop


def _plant():
    F = torch.tensor([[0.98, 0.1], [0.0, 0.9]], dtype=torch.float64)
    Bu = torch.tensor([[0.0, 0.05], [0.3, 0.1]], dtype=torch.float64)
    eye = torch.eye(2, dtype=torch.float64)
    return df.LinearGaussianModel(F, torch.tensor([[1.0, 0.0]], dtype=torch.float64),
                                  1e-3 * eye, 1e-2 * torch.eye(1, dtype=torch.float64),
                                  torch.zeros(2, dtype=torch.float64), 0.1 * eye, B=Bu)  # fmt: skip


def _numpy(model, ys, us, rate, independent):
    F, H, B = (t.numpy() for t in (model.F, model.H, model.B))
    Q, R = model.process_cov(0).numpy(), model.measurement_cov(0).numpy()
    m, P, means, covs = model.initial.mean.numpy(), model.initial.cov.numpy(), [], []
    rate = np.asarray(rate, dtype=float)
    for y, u in zip(ys, us):
        if independent:
            m, P = (
                F @ m + B @ (rate * u),
                F @ P @ F.T + Q + B @ np.diag(rate * (1 - rate) * u * u) @ B.T,
            )
        else:
            Bu = B @ u
            m, P = F @ m + rate * Bu, F @ P @ F.T + Q + rate * (1 - rate) * np.outer(Bu, Bu)
        S = H @ P @ H.T + R
        K = P @ H.T @ np.linalg.inv(S)
        m = m + K @ (y - H @ m)
        I_KH = np.eye(2) - K @ H
        P = I_KH @ P @ I_KH.T + K @ R @ K.T
        means.append(m)
        covs.append(P)
    return np.array(means), np.array(covs)


@pytest.mark.parametrize("independent, rate", [(False, 0.6), (True, 0.6), (True, (0.3, 0.9))])
def test_the_predictor_is_schenatos_written_out(independent, rate):
    model = _plant()
    gen = torch.Generator().manual_seed(0)
    _, ys, _ = model.simulate(30, (1,), generator=gen)
    us = torch.randn(1, 30, 2, generator=gen, dtype=torch.float64)
    out = open_loop(df.ExpectedInputKalmanFilter(rate, independent=independent), model, ys, us)
    means, covs = _numpy(model, ys[0].numpy(), us[0].numpy(), rate, independent)
    np.testing.assert_allclose(out.means[0].numpy(), means, rtol=0, atol=1e-12)
    np.testing.assert_allclose(out.covs[0].numpy(), covs, rtol=0, atol=1e-12)


def test_every_packet_arriving_is_the_kalman_filter():
    model = _plant()
    gen = torch.Generator().manual_seed(1)
    _, ys, _ = model.simulate(20, (3,), generator=gen)
    us = torch.randn(3, 20, 2, generator=gen, dtype=torch.float64)
    mask = torch.rand(3, 20, 1, generator=gen) > 0.3
    got = open_loop(df.ExpectedInputKalmanFilter(1.0), model, ys, us, mask=mask)
    ref = df.kalman_filter(model, ys, us, mask=mask)
    torch.testing.assert_close(got.means, ref.means, rtol=0, atol=1e-12)
    torch.testing.assert_close(got.extras["log_likelihood"], ref.log_likelihood, rtol=0, atol=1e-10)


def test_its_covariance_is_the_loops_error_under_lost_inputs():
    """4,000 runs of the loop with zeroed, unacknowledged inputs (rate 0.5, large inputs):
    the filter's mean NEES is dx = 2 within Monte Carlo error and its MSE below that of a
    Kalman filter given the sent inputs, whose NEES is far above 2."""
    model, runs, T = _plant(), 4000, 40
    gen = torch.Generator().manual_seed(2)
    noise = ReplayedNoise(torch.randn(runs, T, 2, generator=gen, dtype=torch.float64) * 1e-3**0.5,
                          torch.randn(runs, T, 1, generator=gen, dtype=torch.float64) * 0.1)  # fmt: skip
    us = 2.0 * torch.randn(runs, T, 2, generator=gen, dtype=torch.float64)
    arrived = torch.rand(runs, T, generator=gen) < 0.5
    x0 = model.initial.mean + torch.randn(runs, 2, generator=gen, dtype=torch.float64) * 0.1**0.5
    nees, mse = {}, {}
    for name, est in (("udp", df.ExpectedInputKalmanFilter(0.5)), ("kf", df.KalmanFilter())):
        loop = closed_loop(model, T, noise=noise, x0=x0, estimator=est, controller=KnownInputs(us),
                           input_loss=InputLoss(arrived, "zero", acknowledged=False))  # fmt: skip
        err = loop.trajectories.x - loop.output.means
        covs = loop.output.covs.expand(runs, T, 2, 2)
        nees[name] = (err.unsqueeze(-2) @ torch.linalg.solve(covs, err.unsqueeze(-1))).mean()
        mse[name] = err.square().sum(-1).mean()
    # NEES over 4,000 × 40 correlated steps: its standard error is well under 0.05
    assert abs(float(nees["udp"]) - 2.0) < 0.05  # (1.997 measured; its standard error 0.007)
    assert float(nees["kf"]) > 5.0 and float(mse["udp"]) < float(mse["kf"])


def test_bad_arrival_rates_are_named():
    for bad in (0.0, 1.5, True, "0.5", (0.5, 0.5)):
        with pytest.raises(ValueError, match="arrival_rate"):
            df.ExpectedInputKalmanFilter(bad)
    with pytest.raises(ValueError, match="independent"):
        df.ExpectedInputKalmanFilter(0.5, independent=1)
    with pytest.raises(ValueError, match="holds 3 rates, and the model has 2"):
        df.ExpectedInputKalmanFilter((0.5, 0.5, 0.5), independent=True).init(_plant())


def test_a_kalman_filters_carry_with_shared_gains_is_stepped_without_them():
    """A KF carry on a time-invariant model holds the shared gain schedule, whose covariances
    ignore the inputs: given to this filter it went on with the KF's covariances (a review:
    pred_cov 0.249 off). The filter drops the schedule and steps as from a plain carry."""
    model = _plant()
    gen = torch.Generator().manual_seed(3)
    _, ys, _ = model.simulate(5, (2,), generator=gen)
    us = torch.randn(2, 5, 2, generator=gen, dtype=torch.float64)
    est = df.ExpectedInputKalmanFilter(0.5)
    gained = df.KalmanFilter().init(model, (2,))
    assert gained.gains is not None
    ref = open_loop(est, model, ys, us)
    for t in range(5):
        gained, out = est.step(gained, ys[:, t], us[:, t])
        torch.testing.assert_close(out.pred_cov.expand(2, 2, 2), ref.extras["pred_covs"][:, t],
                                   rtol=0, atol=1e-12)  # fmt: skip
        torch.testing.assert_close(out.mean, ref.means[:, t], rtol=0, atol=1e-12)
