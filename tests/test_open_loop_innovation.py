"""The ``open_loop_innovation`` feature: the measurement against the noise-free open-loop
trajectory of the prior mean, ``(ỹ_k − h(x̄°_k)) / √diag R``, each area its own channels."""

from __future__ import annotations

import pytest
import torch
from test_learned_estimator import _captured_inputs

import difffilter as df
from difffilter.fdi.neural import feature_dim
from difffilter.loop import open_loop
from difffilter.models.four_tank import FourTankModel
from difffilter.models.learned_estimator import NeuralCompensation
from difffilter.models.neural_estimator import NeuralFDIEstimator

FEATURE = ("open_loop_innovation",)


def _model_with_input():
    """A stable linear model with an input and a prior mean away from 0 (so that the
    open-loop trajectory moves)."""
    d = torch.float64
    F = torch.tensor([[0.9, 0.1], [0.0, 0.8]], dtype=d)
    B = torch.tensor([[0.0], [0.5]], dtype=d)
    R = torch.diag(torch.tensor([1e-2, 4e-2], dtype=d))
    return df.LinearGaussianModel(F, torch.eye(2, dtype=d), 1e-3 * torch.eye(2, dtype=d), R,
                                  torch.tensor([1.0, -2.0], dtype=d), torch.eye(2, dtype=d), B=B)  # fmt: skip


def _two_areas(seed: int = 4) -> NeuralFDIEstimator:
    return NeuralFDIEstimator(num_areas=2, area_dim=1, a=2, b=2, hidden=4, init="symmetric",
                              init_scale=0.8, resid_scale=0.3, extra_inputs=1, seed=seed)  # fmt: skip


@pytest.mark.parametrize("masked", [False, True])
def test_each_area_reads_the_measurement_against_the_open_loop_trajectory(masked):
    """δ's last entry of area i at step k is (ỹ_{k,i} − (F x̄°_{k−1} + B u_{k−1})_i) / √R_ii
    with x̄°_0 = m0, computed here by hand (0 where unreceived), and the carry ends on
    x̄°_T whatever the network and the measurements."""
    model = _model_with_input()
    runs, steps = 3, 12
    gen = torch.Generator().manual_seed(2)
    us = torch.randn(runs, steps, 1, generator=gen, dtype=torch.float64)
    _, ys, _ = model.simulate(steps, (runs,), us=us, generator=gen)
    ys = ys.clone()
    ys[:, 4:9, 1] += 0.7
    mask = None
    if masked:
        mask = torch.ones(ys.shape, dtype=torch.bool)
        mask[0, 6, 1] = mask[2, 10, 0] = False
        ys[~mask] = float("nan")  # what an unreceived entry may hold
    net = _two_areas()
    seen = _captured_inputs(net)
    est = NeuralCompensation(net, df.KalmanFilter(), features=FEATURE, residual="innovation")
    carry = est.init(model, (runs,))
    open_loop(est, model, ys, us, mask=mask, carry=carry)
    x = model.initial.mean.expand(runs, 2)
    want = []
    for k in range(steps):
        x = x @ model.F.T + us[:, k] @ model.B.T
        want.append((ys[:, k] - x) / torch.tensor([0.1, 0.2], dtype=torch.float64))
    want = torch.stack(want, 1)
    if masked:
        want = torch.where(mask, want, 0.0)
    got = torch.stack([d[..., -1] for d in seen], dim=1)  # [B, T, J]
    torch.testing.assert_close(got, want, rtol=0, atol=1e-12)


def test_the_particle_filter_reads_the_open_loop_trajectory_of_a_nonlinear_model():
    """Around the particle filter, on the four-tank plant (nonlinear, started away from its
    fixed point): the feature is (ỹ_k − h(f(…f(m0)…))) / √diag R, the noise-free transition
    applied k times; the particles' draws do not touch it."""
    model = FourTankModel(dtype=torch.float64, x0=[12.0, 13.0, 4.0, 5.0])
    runs, steps = 2, 6
    _, ys, _ = model.simulate(steps, (runs,), generator=torch.Generator().manual_seed(5))
    net = NeuralFDIEstimator(num_areas=1, area_dim=4, a=1, b=1, hidden=3, init="symmetric",
                             init_scale=0.5, extra_inputs=feature_dim(FEATURE, 4), seed=1,
                             dtype=torch.float64)  # fmt: skip
    seen = _captured_inputs(net)
    est = NeuralCompensation(net, df.ParticleFilter(16), features=FEATURE)
    open_loop(est, model, ys, generator=torch.Generator().manual_seed(0))
    std = model.measurement_noise.cov.diagonal().sqrt()
    x = model.initial.mean.expand(runs, 4)
    for k in range(steps):
        x = model.transition(x, None, k)
        want = (ys[:, k] - model.observe(x, k + 1)) / std
        torch.testing.assert_close(seen[k][:, 0, -4:], want, rtol=0, atol=1e-12)


def test_the_feature_is_per_area_and_a_network_must_have_its_width():
    """Two areas may read it (each its own channels); a network without the extra inputs
    is named."""
    assert feature_dim(FEATURE, 3) == 3
    NeuralCompensation(_two_areas(), df.KalmanFilter(), features=FEATURE)
    narrow = NeuralFDIEstimator(num_areas=2, area_dim=1, a=2, b=2, hidden=4, extra_inputs=0)
    with pytest.raises(ValueError, match="extra_inputs is 0 but features"):
        NeuralCompensation(narrow, df.KalmanFilter(), features=FEATURE)


def test_particles_attached_after_the_first_step_are_named():
    """The trajectory starts at E[x_0]: particles of a later step cannot join it."""
    model = FourTankModel(dtype=torch.float64)
    net = NeuralFDIEstimator(num_areas=1, area_dim=4, a=1, b=1, hidden=3,
                             extra_inputs=feature_dim(FEATURE, 4), seed=1)  # fmt: skip
    est = NeuralCompensation(net, df.ParticleFilter(8), features=FEATURE)
    carry = est.init(model, (2,), torch.Generator().manual_seed(0))
    assert est.attach(carry, model, df.Generators()).aux.open_loop is not None
    with pytest.raises(ValueError, match="attach particles of step k = 0 \\(got k = 3\\)"):
        est.attach(carry._replace(k=3), model, df.Generators())
