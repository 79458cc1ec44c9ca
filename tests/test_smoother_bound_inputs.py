"""The inputs ``us`` of the smoothers and the posterior CRB are checked as the filters check
them (a fuzzing trial: a wrong width, batch or dtype failed deep in torch, and ``us`` without
its T axis gave ``posterior_crb`` a silently wrong bound), and the particle smoother names a
model of another state width."""

from __future__ import annotations

import pytest
import torch

import difffilter as df

D = torch.float64
T = 4


def _linear(dx=2):
    eye = torch.eye(dx, dtype=D)
    return df.LinearGaussianModel(0.9 * eye, torch.ones(1, dx, dtype=D), eye, torch.eye(1, dtype=D),
                                  torch.zeros(dx, dtype=D), eye, B=torch.ones(dx, 1, dtype=D))  # fmt: skip


@pytest.fixture(scope="module")
def filtered():
    model = _linear()
    us = torch.randn(2, T, 1, dtype=D, generator=torch.Generator().manual_seed(0))
    _, ys, _ = model.simulate(T, (2,), us=us, generator=torch.Generator().manual_seed(0))
    kf = df.kalman_filter(model, ys, us)
    pf = df.particle_filter(model, ys, us, num_particles=50, return_particles=True,
                            generator=torch.Generator().manual_seed(0))  # fmt: skip
    return model, us, kf, pf


@pytest.mark.parametrize("smoother", ["rts", "particle"])
def test_a_smoothers_inputs_are_named_as_a_filters(filtered, smoother):
    model, us, kf, pf = filtered
    smooth = ((lambda u: df.rts_smoother(model, kf, u)) if smoother == "rts"
              else (lambda u: df.particle_smoother(model, pf, u)))  # fmt: skip
    smooth(us)  # the filter's own inputs
    with pytest.raises(ValueError, match=r"us must have shape \[\.\.\., T, 1\]; got \(2, 4, 3\)"):
        smooth(torch.zeros(2, T, 3, dtype=D))
    with pytest.raises(ValueError, match=r"us's batch shape \(5,\) does not broadcast with the"):
        smooth(torch.zeros(5, T, 1, dtype=D))
    with pytest.raises(ValueError, match="us must have the model's dtype torch.float64"):
        smooth(us.float())
    with pytest.raises(ValueError, match="us must have T = 4 steps"):
        smooth(us[:, :3])


def test_the_particle_smoother_names_a_model_of_another_state_width(filtered):
    _, _, _, pf = filtered
    with pytest.raises(
        ValueError, match="model's states have 3 entries and the filter's particles 2"
    ):
        df.particle_smoother(_linear(3), pf)


def test_the_posterior_crb_checks_its_inputs_and_its_masks_time_axis():
    dt = 0.3

    def f(x, u):  # the input scales the nonlinearity: the bound depends on u
        return torch.stack([x[..., 0] + dt * x[..., 1],
                            x[..., 1] - dt * (1 + u[..., 0]) * torch.sin(x[..., 0])], -1)  # fmt: skip

    model = df.NonlinearGaussianModel(f, lambda x: x[..., :1], 0.1 * torch.eye(2, dtype=D),
                                      torch.eye(1, dtype=D), torch.zeros(2, dtype=D),
                                      torch.eye(2, dtype=D), dim_u=1)  # fmt: skip
    M = 5
    us = torch.randn(M, 3, 1, dtype=D, generator=torch.Generator().manual_seed(0))
    xs, _, x0 = model.simulate(3, (M,), us=us, generator=torch.Generator().manual_seed(0))
    df.posterior_crb(model, xs, x0, us=us)
    df.posterior_crb(model, xs, x0, us=us[0])  # [T, du]: the same inputs on every path
    # [M, du], the T axis left out: it had read path t's input at step t, unsaid
    with pytest.raises(ValueError, match="us must have T = 3 steps"):
        df.posterior_crb(model, xs, x0, us=us[:, 0])
    with pytest.raises(ValueError, match=r"us's batch shape \(2,\) does not broadcast with xs's"):
        df.posterior_crb(model, xs, x0, us=us[:2])
    with pytest.raises(ValueError, match=r"us must have shape \[\.\.\., T, 1\]"):
        df.posterior_crb(model, xs, x0, us=torch.zeros(M, 3, 2, dtype=D))
    with pytest.raises(TypeError, match="us must be a torch.Tensor"):
        df.posterior_crb(model, xs, x0, us=[[0.0]])
    with pytest.raises(
        ValueError, match=r"mask must have shape \[\.\.\., 3, 1\] \(one row per step\)"
    ):
        df.posterior_crb(model, xs, x0, us=us, mask=torch.ones(1, dtype=torch.bool))
