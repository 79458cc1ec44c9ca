"""Findings of trials of the closed loop's resume paths and of the attacks that conceal
their effect (each failed before its fix)."""

from __future__ import annotations

import pytest
import torch

import difffilter as df
from difffilter.attack import Attack, Channel
from difffilter.loop import ReplayedNoise, StateFeedback, closed_loop
from difffilter.threats import Bias

D = torch.float64
F = torch.tensor([[1.0, 0.1], [0.0, 0.95]], dtype=D)
EYE = torch.eye(2, dtype=D)
B_IN = torch.tensor([[0.0], [0.1]], dtype=D)
K = torch.tensor([[0.5, 0.8]], dtype=D)
RUNS, T = 3, 60


def _model(H=EYE, R=1e-2 * EYE):
    return df.LinearGaussianModel(F, H, 1e-3 * EYE, R, torch.zeros(2, dtype=D), EYE, B=B_IN)


def _noise(dy=2):
    g = torch.Generator().manual_seed(7)
    w, v = (
        0.03 * torch.randn(RUNS, T, 2, generator=g, dtype=D),
        0.1 * torch.randn(RUNS, T, 2, generator=g, dtype=D),
    )
    return ReplayedNoise(w, v[..., :dy]), torch.randn(RUNS, 2, generator=g, dtype=D)


def _loop(model, steps, estimator=None, **kw):
    noise, x0 = _noise(model.dim_y)
    start = {} if "state" in kw or "fork" in kw else {"x0": x0}
    return closed_loop(model, steps, noise=noise, estimator=estimator or df.KalmanFilter(),
                       controller=StateFeedback(K), **start, **kw)  # fmt: skip


def test_a_loop_resumed_on_another_plant_is_checked_as_a_fresh_start():
    """``state=`` skipped the checks of the plant against the estimator's model: a plant of
    one sensor fed the estimator of two a broadcast measurement (its means those of a KF on
    [y₁, y₁]), and one of three states failed in torch."""
    first = _loop(_model(), 10)
    one_sensor = _model(H=torch.tensor([[1.0, 0.0]], dtype=D), R=1e-2 * torch.eye(1, dtype=D))
    with pytest.raises(
        ValueError, match="model \\(the estimator's\\) measures 2 entries and the plant 1"
    ):
        _loop(one_sensor, 10, state=first.state)


def test_a_loop_resumed_with_another_kind_of_estimator_is_refused_by_name():
    """A Kalman filter's state resumed by a particle filter had failed on "'GaussianState'
    object has no attribute 'particles'"."""
    first = _loop(_model(), 10)
    with pytest.raises(
        TypeError, match="the loop kept ran another estimator \\(its carry is a GaussianState"
    ):
        _loop(_model(), 10, estimator=df.ParticleFilter(20), state=first.state)


@pytest.mark.parametrize("horizon", [10, 0])
def test_a_forks_horizon_is_checked(horizon):
    """``horizon`` one short of a fork's steps failed in torch's ``narrow``, and 0 was taken
    for the default (``horizon or …``), where a fresh start refuses both."""
    forks = {19: None}
    _loop(_model(), 30, forks=forks, horizon=T)
    with pytest.raises(
        ValueError, match="horizon \\(the whole loop's T\\) must be an integer >= 39"
    ):
        _loop(_model(), 20, fork=forks[19], horizon=horizon, attack=Bias(onset=25))


class _Concealing(Attack):
    channel, conceals, reads_state = Channel.ACTUATOR, True, False

    def __init__(self, correction):
        self.correction = correction

    def init(self, batch, steps, dim, generator=None, *, dtype, device=None):
        return None

    def step(self, state, k, *, y=None, x=None, u=None, view=None):
        return state, torch.full_like(u, 0.1), torch.ones(u.shape[:-1], dtype=torch.bool)

    def conceal(self, state, k, *, y, x):
        return state, self.correction(y)


@pytest.mark.parametrize(
    "correction",
    [
        lambda y: torch.full((y.shape[0], 1), 0.5, dtype=D),
        lambda y: torch.ones(y.shape, dtype=torch.int64),
        lambda y: torch.zeros(y.shape[0], 1, y.shape[1], dtype=D),
        lambda y: torch.zeros(3, dtype=D),
    ],
)
def test_a_concealing_attacks_correction_is_checked(correction):
    """The correction was added unchecked: ``[B, 1]`` spread over both sensors, an integer
    one taken, others failed in torch or were blamed on the controller."""
    with pytest.raises(
        ValueError, match="_Concealing's conceal returned .* at step 1; it returns the correction"
    ):
        _loop(_model(), 10, attack=_Concealing(correction))


def test_a_covert_attack_on_the_robot_keeps_its_bearings_wrapped():
    """Its correction was the difference of two wrapped predictions: bearings reached 2π
    outside (−π, π] (93 of 4,800 on the robot's own covert threat, 8 runs)."""
    from difffilter.models import registry
    from difffilter.models.streams import Streams
    from difffilter.threats import threat_from_dict

    scenario = registry.get("robot_actuator_attack")
    model = scenario.system()
    covert = threat_from_dict({"kind": "covert", "signal": {"kind": "bias", "value": [10.0, 0.175], "onset": 30}},
                              model=model)  # fmt: skip
    received = scenario.with_threat(covert).simulate(8, Streams(0).simulation()).y_recv
    assert float(received[..., 1::2].abs().max()) < torch.pi + 0.2
