"""Findings of a red-team trial of the particle filter's proposals and plug-in checks
(2026-12-06), against the Kalman filter and by name."""

from __future__ import annotations

import pytest
import torch

import difffilter as df
from difffilter.noise import Gaussian

D = torch.float64
ONE = torch.eye(1, dtype=D)


class _Drift(df.StateSpaceModel):
    """``x' = 0.9 x + w``, ``w ~ N(0.5, 0.1)``; ``y = x + v``, ``v ~ N(0, 0.1)``."""

    dim_x, dim_y = 1, 1

    def __init__(self):
        super().__init__()
        self.initial = Gaussian(torch.zeros(1, dtype=D), ONE)
        self.process_noise = Gaussian(torch.tensor([0.5], dtype=D), 0.1 * ONE)
        self.measurement_noise = Gaussian(torch.zeros(1, dtype=D), 0.1 * ONE)

    def transition(self, x, u, k):
        return 0.9 * x

    def observe(self, x, k):
        return x


def test_the_kalman_proposal_takes_the_process_noise_mean():
    # truth: the Kalman filter of the zero-mean model with the mean as a known input; the
    # proposal had left the mean out (32 nats off, final means 0.31 low)
    model, T = _Drift(), 20
    _, ys, _ = model.simulate(T, (3,), generator=torch.Generator().manual_seed(1))
    equivalent = df.LinearGaussianModel(0.9 * ONE, ONE, 0.1 * ONE, 0.1 * ONE,
                                        torch.zeros(1, dtype=D), ONE, B=ONE)  # fmt: skip
    kf = df.kalman_filter(equivalent, ys, torch.full((3, T, 1), 0.5, dtype=D))
    pf = df.particle_filter(model, ys, num_particles=4000, proposal=df.KalmanProposal(),
                            generator=torch.Generator().manual_seed(0))  # fmt: skip
    # on a linear-Gaussian model the proposal is optimal: few particles reach the KF's
    assert torch.allclose(pf.log_likelihood, kf.log_likelihood, atol=0.1)
    assert torch.allclose(pf.means[:, -1], kf.means[:, -1], atol=0.02)


def test_the_kalman_proposal_refuses_a_model_that_draws_its_own_transitions():
    # the robot draws f + B(θ) n: the weights had targeted N(f, Q)'s posterior, 4 nats off
    from difffilter.models.needs import TRANSITION_IS_PROCESS_NOISE
    from difffilter.models.robot import RobotModel

    model, T = RobotModel(), 3
    us = torch.tensor([1.0, 0.05], dtype=D).expand(1, T, 2)
    _, ys, _ = model.simulate(T, (1,), us=us, generator=torch.Generator().manual_seed(1))
    with pytest.raises(ValueError, match="RobotModel draws its transitions its own way"):
        df.particle_filter(model, ys, us, num_particles=16, proposal=df.KalmanProposal(),
                           generator=torch.Generator().manual_seed(0))  # fmt: skip
    assert "weighs its particles by N(f, Q)" in TRANSITION_IS_PROCESS_NOISE.unmet(None, model)
    assert TRANSITION_IS_PROCESS_NOISE.unmet(None, _Drift()) is None


@pytest.mark.parametrize("cov_dims", [-1, 0, True, 2.5, "2"])
def test_cov_dims_is_checked_when_the_filter_is_made(cov_dims):
    # -1 had given the first dx − 1 states' covariance, unsaid; 0 an empty one
    with pytest.raises(ValueError, match=r"cov_dims must be None or an integer in \[1, dx\]"):
        df.ParticleFilter(8, cov_dims=cov_dims)


def test_cov_dims_beyond_the_state_is_refused_at_init():
    with pytest.raises(ValueError, match=r"cov_dims must be None or an integer in \[1, 1\]; got 3"):
        df.ParticleFilter(8, cov_dims=3).init(_Drift())


def _two_args(carry, out):
    return {}


@pytest.mark.parametrize(
    ("hooks", "message"),
    [
        (_two_args, "hooks must be a sequence of callables"),
        ([None], r"hooks\[0\] must be callable"),
        ([_two_args], r"hooks\[0\] is called as hook\(model, y, mask, carry, out\)"),
    ],
)
def test_hooks_are_checked_when_the_filter_is_made(hooks, message):
    with pytest.raises(TypeError, match=message):
        df.ParticleFilter(8, hooks=hooks)


class _NoPredictive:
    uses_predictive = True

    def __call__(self, model, y, particles, k, mask):
        return model.measurement_log_prob(y.unsqueeze(-2), particles, k, None)


def test_a_likelihood_that_uses_the_predictive_moments_takes_them():
    with pytest.raises(TypeError, match=r"uses_predictive = True\) is called as .*predictive="):
        df.ParticleFilter(8, likelihood=_NoPredictive())
