"""Findings of a red-team trial of the robot's estimators (2026-12-06)."""

from __future__ import annotations

import copy
import pickle

import pytest
import torch

from difffilter.estimator import Generators
from difffilter.fdi.mdpf import AdaptiveParticleFilter, adaptive_particle_filter
from difffilter.models.robot import DEG, RobotModel
from difffilter.models.robot_estimators import FusedLocals
from difffilter.noise import Gaussian

T = 6


def _data():
    us = torch.tensor([5.0, 5 * DEG], dtype=torch.float64).expand(2, T, 2).clone()
    _, ys, _ = RobotModel().simulate(T, (2,), us=us, generator=torch.Generator().manual_seed(1))
    return ys, us


def _gens():
    return Generators(*(torch.Generator().manual_seed(i) for i in range(3)))


def test_an_attack_prior_of_zero_runs_the_covariance_form():
    # the information form inverts S: with S₀ = 0 every particle was NaN at step 2
    ys, us = _data()
    out = adaptive_particle_filter(RobotModel(), ys, us, num_particles=16, attack_cov0=0.0,
                                   generator=torch.Generator().manual_seed(0))  # fmt: skip
    assert bool(torch.isfinite(out.means).all()) and bool((out.attack == 0).all())
    with pytest.raises(ValueError, match="attack_cov0 = 0 .* needs form='covariance'"):
        AdaptiveParticleFilter(16, attack_cov0=0.0, form="information")
    with pytest.raises(ValueError, match="local.attack_cov0 must be > 0"):
        FusedLocals(AdaptiveParticleFilter(16, attack_cov0=0.0))


def test_the_fusion_takes_two_groups():
    with pytest.raises(ValueError, match="groups must be two sensor groups"):
        FusedLocals(AdaptiveParticleFilter(16), groups=((0, 1), (2, 3), (4, 5)))


@pytest.mark.parametrize("change", ["R assigned", "R in place", "Q assigned"])
def test_a_model_changed_under_the_fused_carry_is_refused(change):
    # the locals step grouped copies made at init: the change had been ignored (the
    # estimate bit-identical), where the adaptive filters on the full model follow it
    ys, us = _data()
    model, est = RobotModel(), FusedLocals(AdaptiveParticleFilter(16))
    carry = est.init(model, (2,), _gens())
    carry, _ = est.step(carry, ys[:, 0], us[:, 0])
    if change == "R assigned":
        model.measurement_noise = Gaussian(torch.zeros(12, dtype=torch.float64),
                                           100 * model.measurement_noise.cov)  # fmt: skip
    elif change == "R in place":
        with torch.no_grad():
            model.measurement_noise.cov.mul_(100.0)
    else:
        model.process_noise = Gaussian(torch.zeros(3, dtype=torch.float64),
                                       100 * model.process_noise.cov)  # fmt: skip
    with pytest.raises(ValueError, match="FusedLocals: the model changed since init"):
        est.step(carry, ys[:, 1], us[:, 1])


@pytest.mark.parametrize("how", ["deepcopy", "pickle"])
def test_a_copied_fused_carry_steps_as_the_original(how):
    ys, us = _data()
    est = FusedLocals(AdaptiveParticleFilter(16))
    carry = est.init(RobotModel(), (2,), _gens())
    carry, _ = est.step(carry, ys[:, 0], us[:, 0])
    twin = copy.deepcopy(carry) if how == "deepcopy" else pickle.loads(pickle.dumps(carry))
    _, a = est.step(carry, ys[:, 1], us[:, 1])
    _, b = est.step(twin, ys[:, 1], us[:, 1])
    assert torch.equal(a.mean, b.mean)
