"""The particle filter's one-run step (difffilter._pf_single_run) against the general step.

For one run on the default strategies, ``ParticleFilter.step`` takes the written-out step;
it must give the general step's numbers (the same draws in the same order), values and
gradients, in float64 where round-off cannot move a resampling decision.
"""

from __future__ import annotations

import math

import pytest
import torch

import difffilter as df
from difffilter import particle
from difffilter._pf_single_run import applies
from difffilter.estimator import Generators
from difffilter.models.four_tank import FourTankModel
from difffilter.resampling import Multinomial

STEPS = 40


def _linear_model(dtype=torch.float64, control=False, full_noise=False):
    """A 3-state, 2-output linear model; a 1-input control matrix and a full (not
    diagonal) measurement covariance on request."""
    F = torch.tensor([[0.9, 0.1, 0.0], [0.0, 0.8, 0.2], [0.1, 0.0, 0.7]], dtype=dtype)
    H = torch.tensor([[1.0, 0.0, 0.5], [0.0, 1.0, 0.0]], dtype=dtype)
    R = (
        torch.tensor([[0.3, 0.1], [0.1, 0.2]], dtype=dtype)
        if full_noise
        else 0.2 * torch.eye(2, dtype=dtype)
    )
    B = torch.tensor([[1.0], [0.0], [0.5]], dtype=dtype) if control else None
    return df.LinearGaussianModel(F, H, 0.05 * torch.eye(3, dtype=dtype), R,
                                  torch.zeros(3, dtype=dtype), torch.eye(3, dtype=dtype), B=B)  # fmt: skip


def _data(model, steps=STEPS, seed=0, du=0):
    gen = torch.Generator().manual_seed(seed)
    us = torch.randn(steps, du, generator=gen, dtype=torch.float64) if du else None
    with torch.no_grad():
        _, ys, _ = model.simulate(steps, (1,), generator=gen, us=None if us is None else us[None])
    return ys[0], us


def _run(pf, model, ys, us, general: bool):
    """Step ``pf`` through ``ys`` from one seeded carry: through ``pf.step`` (the one-run
    step where it applies) or the general step. Returns the carries and outputs."""
    gens = Generators.of(torch.Generator().manual_seed(7))
    carry = pf.init(model, (), gens)
    carries, outs = [], []
    for k, y in enumerate(ys):
        u = None if us is None else us[k]
        if general:
            carry, out = particle._particle_step(pf, carry, y, u, None)
        else:
            carry, out = pf.step(carry, y, u)
        carries.append(carry)
        outs.append(out)
    return carries, outs


def _assert_same(a, b, tol=1e-10):
    (ca, oa), (cb, ob) = a, b
    for x, y in zip(ca, cb):
        torch.testing.assert_close(x.particles, y.particles, atol=tol, rtol=tol)
        torch.testing.assert_close(x.log_weights, y.log_weights, atol=tol, rtol=tol)
        torch.testing.assert_close(x.ess, y.ess, atol=tol, rtol=tol)
    for x, y in zip(oa, ob):
        for name in ("mean", "cov", "pred_mean", "log_likelihood", "innovation", "innovation_cov"):
            u, v = getattr(x, name), getattr(y, name)
            assert (u is None) == (v is None), name
            if u is not None:
                torch.testing.assert_close(u, v, atol=tol, rtol=tol, msg=name)
        for name in ("ess", "resampled", "degenerate"):
            torch.testing.assert_close(x.extras[name], y.extras[name], atol=tol, rtol=tol)
        assert set(x.extras) == set(y.extras)


@pytest.mark.parametrize("innovations", [True, False])
@pytest.mark.parametrize("case", ["four_tank", "linear_control", "full_noise"])
def test_the_one_run_step_equals_the_general_step(case, innovations):
    du = 1 if case == "linear_control" else 0
    if case == "four_tank":
        model = FourTankModel(dtype=torch.float64)
    else:
        model = _linear_model(control=du > 0, full_noise=case == "full_noise")
    ys, us = _data(model, du=du)
    pf = df.ParticleFilter(200, innovations=innovations)
    assert applies(pf, pf.init(model, ()), None)
    fused, general = _run(pf, model, ys, us, False), _run(pf, model, ys, us, True)
    assert any(bool(o.extras["resampled"]) for o in fused[1])  # both branches ran
    assert not all(bool(o.extras["resampled"]) for o in fused[1])
    _assert_same(fused, general)


def test_gradients_equal_the_general_steps():
    """d/dy of the summed evidence and means through both steps (the same detached
    maximum, the same non-differentiable ancestors)."""
    model = _linear_model()
    ys, _ = _data(model, steps=12)
    pf = df.ParticleFilter(64)

    def grad(general):
        y = ys.clone().requires_grad_(True)
        _, outs = _run(pf, model, y, None, general)
        loss = sum(o.log_likelihood + o.mean.square().sum() + o.cov.sum() for o in outs)
        (g,) = torch.autograd.grad(loss, y)
        return g

    g_fused, g_general = grad(False), grad(True)
    assert g_fused.abs().sum() > 0
    torch.testing.assert_close(g_fused, g_general, atol=1e-10, rtol=1e-10)


def test_a_degenerate_step_resets_as_the_general_step():
    """A measurement every particle finds impossible: evidence −inf, weights reset to the
    predictive ones, the step flagged; then filtering goes on, in both steps alike."""
    model = _linear_model()
    ys, _ = _data(model, steps=6)
    ys = ys.clone()
    ys[3] = 1e200
    pf = df.ParticleFilter(50)
    fused, general = _run(pf, model, ys, None, False), _run(pf, model, ys, None, True)
    out = fused[1][3]
    assert bool(out.extras["degenerate"]) and out.log_likelihood.item() == -math.inf
    assert torch.isfinite(fused[1][5].log_likelihood)
    _assert_same(fused, general)


def test_where_the_one_run_step_does_not_apply():
    model = _linear_model()
    carry = df.ParticleFilter(10).init(model, ())
    batched = df.ParticleFilter(10).init(model, (3,))
    assert applies(df.ParticleFilter(10), carry, None)
    assert not applies(df.ParticleFilter(10), batched, None)  # a batch of runs
    assert not applies(df.ParticleFilter(10), carry, torch.tensor([True, False]))  # a mask
    assert not applies(df.ParticleFilter(10, resampler=Multinomial()), carry, None)
    assert not applies(df.ParticleFilter(10, proposal=df.KalmanProposal()), carry, None)
    assert not applies(df.ParticleFilter(10, record_prior=True), carry, None)
    assert not applies(df.ParticleFilter(10, hooks=[lambda *a: {}]), carry, None)
    assert not applies(df.ParticleFilter(10, cov_dims=1), carry, None)
