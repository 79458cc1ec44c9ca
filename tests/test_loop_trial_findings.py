"""Findings of a red-team trial of the time-loop drivers (``difffilter.loop``, 2026-12-06),
each against the loop run at once or a hand-written filter."""

from __future__ import annotations

import pytest
import torch

import difffilter as df
from difffilter.loop import KnownInputs, ReplayedNoise, StateFeedback, closed_loop, open_loop
from difffilter.models.attacks import Signal

D = torch.float64
I2 = torch.eye(2, dtype=D)
B_IN = torch.tensor([[0.0], [0.1]], dtype=D)


def _model(F=((1.0, 0.1), (0.0, 0.95)), r=1e-2):
    return df.LinearGaussianModel(torch.tensor(F, dtype=D), I2, 1e-3 * I2, r * I2,
                                  torch.zeros(2, dtype=D), I2, B=B_IN)  # fmt: skip


def _noise(runs, steps, seed=2):
    g = torch.Generator().manual_seed(seed)
    noise = ReplayedNoise(0.03 * torch.randn(runs, steps, 2, generator=g, dtype=D),
                          0.1 * torch.randn(runs, steps, 2, generator=g, dtype=D))  # fmt: skip
    return noise, torch.randn(runs, 2, generator=g, dtype=D), g


@pytest.mark.parametrize("chunk", [7, 5])
def test_a_fork_kept_by_a_resumed_loop_continues_under_attack_as_the_whole_loop(chunk):
    # the fork records its chunk's steps only: the attack's records had been built for all
    # k steps (a bare size error, or at chunk 7 attack rows misaligned with x by 7 steps)
    model, (runs, T) = _model(), (3, 20)
    noise, x0, _ = _noise(runs, T)
    signal = torch.zeros(T, 2, dtype=D)
    signal[12:, 0] = 0.5  # from step 13

    def loop(steps, **kw):
        return closed_loop(model, steps, noise=noise, x0=x0, estimator=df.KalmanFilter(),
                           controller=StateFeedback(torch.tensor([[0.5, 1.2]], dtype=D)),
                           horizon=T, **kw)  # fmt: skip

    whole = loop(T, attack=Signal(signal)).trajectories
    forks = {8: None}
    loop(10, state=loop(chunk).state, forks=forks)
    tr = loop(T - 8, attack=Signal(signal), fork=forks[8]).trajectories
    assert tr.x.shape[1] == tr.attack.shape[1] == tr.flags.shape[1] == T - chunk
    assert torch.equal(tr.x, whole.x[:, chunk:])
    assert torch.equal(tr.flags, whole.flags[:, chunk:])
    assert torch.equal(tr.attack, whole.attack[:, chunk:])


def _kf_loop_parts(runs=2, T=12):
    noise, x0, g = _noise(runs, T, seed=4)
    us = torch.randn(runs, T, 1, dtype=D, generator=g)
    return noise, x0, us


def test_a_loop_resumed_with_another_estimator_presence_is_named():
    model, (noise, x0, us) = _model(), _kf_loop_parts()
    bare = closed_loop(model, 5, noise=noise, x0=x0, horizon=12, controller=KnownInputs(us))
    with pytest.raises(ValueError, match="state: the loop kept had no estimator"):
        closed_loop(model, 7, noise=noise, estimator=df.KalmanFilter(),
                    controller=KnownInputs(us), state=bare.state)  # fmt: skip
    forks = {5: None}
    closed_loop(model, 12, noise=noise, x0=x0, estimator=df.KalmanFilter(),
                controller=KnownInputs(us), forks=forks)  # fmt: skip
    with pytest.raises(ValueError, match="fork: the loop kept had an estimator"):
        closed_loop(model, 7, noise=noise, controller=KnownInputs(us), fork=forks[5])


def test_a_loop_resumed_with_another_model_is_refused():
    # the resumed steps had filtered with the carry's model, the one given ignored (1.54
    # off a Kalman filter on the model given)
    plant, other = _model(), _model(((0.5, 0.0), (0.0, 0.5)), r=1.0)
    noise, x0, us = _kf_loop_parts()
    kw = dict(noise=noise, estimator=df.KalmanFilter(), controller=KnownInputs(us))
    first = closed_loop(plant, 5, x0=x0, horizon=12, **kw)
    with pytest.raises(ValueError, match="model: the state's estimator carry filters with its own"):
        closed_loop(plant, 7, model=other, state=first.state.copy(), **kw)
    same = closed_loop(plant, 7, model=plant, state=first.state.copy(), **kw)
    unsaid = closed_loop(plant, 7, state=first.state.copy(), **kw)
    assert torch.equal(same.output.means, unsaid.output.means)


@pytest.mark.parametrize("how", ["copy", "detach"])
def test_a_copied_kalman_carry_steps_on_elsewhere(how):
    # the copy cloned the gain schedule's shared covariance, and the Kalman filter refused
    # the carry as "changed"
    model, (noise, x0, us) = _model(), _kf_loop_parts()
    kw = dict(noise=noise, estimator=df.KalmanFilter(), controller=KnownInputs(us))
    first = closed_loop(model, 5, x0=x0, horizon=12, **kw)
    whole = closed_loop(model, 12, x0=x0, **kw)
    carry = getattr(first.state, how)().carry
    tr = whole.trajectories
    out = open_loop(df.KalmanFilter(), model, tr.y_recv[:, 5:], tr.us[:, 5:], carry=carry)
    assert torch.allclose(out.means, whole.output.means[:, 5:], rtol=0, atol=1e-14)
    df.KalmanFilter().step(carry, tr.y_recv[:, 5], tr.us[:, 5])


def test_collected_records_lead_with_the_runs_or_are_refused():
    # a shared covariance [dx, dx] had been stacked as [dx, T, dx]
    model = df.LinearGaussianModel(torch.tensor([[1.0, 0.1], [0.0, 0.95]], dtype=D), I2,
                                   1e-3 * I2, 1e-2 * I2, torch.zeros(2, dtype=D), I2)  # fmt: skip
    ys = torch.randn(3, 6, 2, dtype=D, generator=torch.Generator().manual_seed(3))
    with pytest.raises(ValueError, match=r"collect: its record 'P' at step 1 has shape \(2, 2\)"):
        open_loop(df.KalmanFilter(), model, ys, collect=lambda c, o: {"P": c.cov})
    out = open_loop(df.KalmanFilter(), model, ys,
                    collect=lambda c, o: {"P": c.cov.expand(3, 2, 2), "one": c.mean[:1]})  # fmt: skip
    assert torch.equal(out.extras["P"], out.covs)
    assert out.extras["one"].shape == (3, 6, 2)  # a leading 1 expanded to the runs


def test_a_loop_resumed_past_its_known_inputs_is_refused():
    # KnownInputs left a copy of u_{T−1} as u_T, and a resumed loop drove step T + 1 with it
    model, (noise, x0, us) = _model(), _kf_loop_parts(T=16)
    kw = dict(noise=noise, estimator=df.KalmanFilter())
    first = closed_loop(model, 10, x0=x0, horizon=16, controller=KnownInputs(us[:, :10]), **kw)
    with pytest.raises(ValueError, match="its last input u_10 is not finite"):
        closed_loop(model, 6, state=first.state, controller=KnownInputs(us), **kw)
    # the whole table given to the first chunk: the chunks are the loop run at once
    first = closed_loop(model, 10, x0=x0, horizon=16, controller=KnownInputs(us), **kw)
    rest = closed_loop(model, 6, state=first.state, controller=KnownInputs(us), **kw)
    whole = closed_loop(model, 16, x0=x0, controller=KnownInputs(us), **kw)
    assert torch.equal(rest.trajectories.x, whole.trajectories.x[:, 10:])
