"""One particle-filter step against a dense computation by hand (torch.distributions for
the Gaussian densities, explicit sums for the moments), on every path: the general batched
step, the one-run torch step, the host-array step; the Kalman proposal's predictive
weights and a batch in which one run resamples and one does not (a mutation review of the
particle-filter core: its unnormalised p/q weights, the cached weights used in place of the
predictive ones, a plain average for a run kept, and a log-sum-exp without its shift all
passed the suite, whose one-run paths were checked against the batched step alone)."""

from __future__ import annotations

import math

import pytest
import torch

import difffilter as df
from difffilter import _pf_host_step, particle
from difffilter.estimator import Generators

D = torch.float64


def _model():
    F = torch.tensor([[0.9, 0.1, 0.0], [0.0, 0.8, 0.2], [0.1, 0.0, 0.7]], dtype=D)
    H = torch.tensor([[1.0, 0.0, 0.5], [0.0, 1.0, 0.0]], dtype=D)
    R = torch.diag(torch.tensor([0.2, 0.3], dtype=D))
    return (
        df.LinearGaussianModel(
            F, H, 0.05 * torch.eye(3, dtype=D), R, torch.zeros(3, dtype=D), torch.eye(3, dtype=D)
        ),
        H,
        R,
    )


def _carry(pf, model, batch):
    gens = Generators.of(torch.Generator().manual_seed(7))
    c = pf.init(model, batch, gens)
    g = torch.Generator().manual_seed(3)
    lw = torch.log_softmax(2.0 * torch.randn(c.log_weights.shape, generator=g, dtype=D), -1)
    return c._replace(log_weights=lw, ess=None, weights=None)


@pytest.mark.parametrize("far", [False, True])
@pytest.mark.parametrize("path", ["general", "single", "host", "batched"])
@pytest.mark.parametrize("resample", [False, True])
def test_step_by_hand(path, resample, far):
    model, H, R = _model()
    n = 16
    pf = df.ParticleFilter(n, ess_threshold=1.0 if resample else 0.0)
    carry = _carry(pf, model, (2,) if path == "batched" else ())
    # far: a measurement 30 units off, log-densities near -5000 (exp underflows unshifted)
    y = torch.tensor([30.0, -30.0] if far else [0.7, -0.4], dtype=D)
    if path == "batched":
        y = y.expand(2, 2)
    with torch.set_grad_enabled(path != "host"):
        if path in ("general", "batched"):
            new, out = particle._particle_step(pf, carry, y, None, None)
        else:
            assert (_pf_host_step.density(carry, y, None) is not None) == (path == "host")
            new, out = pf.step(carry, y, None)
    x = new.particles  # proposed particles [.., N, 3]
    lw_prev = carry.log_weights
    if resample:
        lw_prev = torch.full_like(lw_prev, -math.log(n))
    assert bool(out.extras["resampled"].all()) == resample
    assert not bool(out.extras["degenerate"].any())
    obs = x @ H.T
    loglik = torch.distributions.MultivariateNormal(torch.zeros(2, dtype=D), R).log_prob(
        y.unsqueeze(-2) - obs
    )
    joint = lw_prev + loglik
    inc = torch.logsumexp(joint, -1)
    w = torch.softmax(joint, -1)
    wp = torch.softmax(lw_prev, -1)
    mean = (w.unsqueeze(-1) * x).sum(-2)
    dev = x - mean.unsqueeze(-2)
    cov = torch.einsum("...n,...ni,...nj->...ij", w, dev, dev)
    pred_mean = (wp.unsqueeze(-1) * x).sum(-2)
    yhat = (wp.unsqueeze(-1) * obs).sum(-2)
    od = obs - yhat.unsqueeze(-2)
    S = torch.einsum("...n,...ni,...nj->...ij", wp, od, od) + R
    kw = dict(rtol=1e-9, atol=1e-11)
    torch.testing.assert_close(out.log_likelihood, inc, **kw)
    torch.testing.assert_close(new.log_weights, joint - inc.unsqueeze(-1), **kw)
    torch.testing.assert_close(out.mean, mean, **kw)
    torch.testing.assert_close(out.cov, cov, **kw)
    torch.testing.assert_close(out.pred_mean, pred_mean, **kw)
    torch.testing.assert_close(out.innovation, y - yhat, **kw)
    torch.testing.assert_close(out.innovation_cov, S, **kw)
    torch.testing.assert_close(out.extras["ess"], 1.0 / (w * w).sum(-1), **kw)
    torch.testing.assert_close(new.ess, 1.0 / (w * w).sum(-1), **kw)


@pytest.mark.parametrize("path", ["general", "single", "host"])
def test_degenerate_step_keeps_predictive_weights(path):
    model, H, R = _model()
    n = 8
    pf = df.ParticleFilter(n, ess_threshold=0.0)
    carry = _carry(pf, model, ())
    y = torch.tensor([1e200, -1e200], dtype=D)  # every density underflows
    with torch.set_grad_enabled(path != "host"):
        if path == "general":
            new, out = particle._particle_step(pf, carry, y, None, None)
        else:
            new, out = pf.step(carry, y, None)
    assert bool(out.extras["degenerate"])
    torch.testing.assert_close(new.log_weights, carry.log_weights)
    torch.testing.assert_close(new.weights, carry.log_weights.exp())
    w = carry.log_weights.exp()
    torch.testing.assert_close(out.mean, (w.unsqueeze(-1) * new.particles).sum(0))


def test_kalman_proposal_predictive_moments_use_normalised_p_over_q_weights():
    """pred_mean = Σ softmax(log w + log p(x|f) − log q(x)) x, with p, q from the proposal's
    moments (dense Gaussian densities), and the innovation covariance under those weights."""
    model, H, R = _model()
    n = 12
    pf = df.ParticleFilter(n, proposal=df.KalmanProposal(), ess_threshold=0.0)
    carry = _carry(pf, model, ())
    carry = carry._replace(weights=carry.log_weights.exp())  # the cached exp, as a step leaves it
    y = torch.tensor([0.7, -0.4], dtype=D)
    new, out = particle._particle_step(pf, carry, y, None, None)
    x = new.particles
    f, Q, mu, sigma = particle.kalman_proposal_moments(model, carry.particles, None, y, 0, None)
    MVN = torch.distributions.MultivariateNormal
    log_p = MVN(f, Q).log_prob(x)
    log_q = MVN(mu, sigma).log_prob(x)
    wp = torch.softmax(carry.log_weights + log_p - log_q, -1)
    torch.testing.assert_close(out.pred_mean, (wp.unsqueeze(-1) * x).sum(0), rtol=1e-8, atol=1e-10)
    obs = x @ H.T
    yhat = (wp.unsqueeze(-1) * obs).sum(0)
    torch.testing.assert_close(out.innovation, y - yhat, rtol=1e-8, atol=1e-10)
    # the weights after the step: log w + log p(y|x) + log p − log q, normalised
    loglik = MVN(torch.zeros(2, dtype=D), R).log_prob(y - obs)
    joint = carry.log_weights + loglik + log_p - log_q
    torch.testing.assert_close(new.log_weights, torch.log_softmax(joint, -1), rtol=1e-8, atol=1e-10)
    torch.testing.assert_close(
        out.log_likelihood, torch.logsumexp(joint, -1), rtol=1e-8, atol=1e-10
    )


def test_partial_resampling_pred_mean_per_row():
    """Batch of two runs: run 0 has even weights (kept), run 1 a degenerate cloud (resampled).
    pred_mean of run 0 must weigh the proposed particles by its kept weights."""
    model, H, R = _model()
    n = 16
    pf = df.ParticleFilter(n, ess_threshold=0.5)
    c = pf.init(model, (2,), Generators.of(torch.Generator().manual_seed(7)))
    g = torch.Generator().manual_seed(4)
    lw0 = torch.log_softmax(0.5 * torch.randn(n, generator=g, dtype=D), -1)  # ESS ≈ 0.8 N
    lw1 = torch.log_softmax(torch.tensor([8.0] + [0.0] * (n - 1), dtype=D), -1)  # ESS ≈ 1
    c = c._replace(log_weights=torch.stack([lw0, lw1]), ess=None, weights=None)
    y = torch.tensor([[0.7, -0.4], [0.7, -0.4]], dtype=D)
    new, out = particle._particle_step(pf, c, y, None, None)
    assert out.extras["resampled"].tolist() == [False, True]
    x = new.particles
    torch.testing.assert_close(out.pred_mean[0], (lw0.exp().unsqueeze(-1) * x[0]).sum(0))
    torch.testing.assert_close(out.pred_mean[1], x[1].mean(0))
    loglik = torch.distributions.MultivariateNormal(torch.zeros(2, dtype=D), R).log_prob(
        y[0] - x @ H.T
    )
    torch.testing.assert_close(out.log_likelihood[0], torch.logsumexp(lw0 + loglik[0], -1))
    torch.testing.assert_close(out.log_likelihood[1], torch.logsumexp(loglik[1], -1) - math.log(n))
