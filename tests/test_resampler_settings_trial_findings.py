"""Resamplers', the Kalman proposal's and the particle filter's likelihood's settings
assigned after construction, and resampling in half precision (a red-team trial of the
particle filters' statistics, 2026-12-07; each test of a refusal failed before its fix). A
setting assigned is checked as the constructor checks it, and a valid one gives what the
object built with it gives, bit for bit."""

from __future__ import annotations

import math

import pytest
import torch

import difffilter as df
from difffilter.particle import KalmanProposal, ModelLikelihood, particle_filter
from difffilter.resampling import Multinomial, Residual, Soft, StopGradient, Stratified, Systematic

F64 = torch.float64
MODEL = df.LinearGaussianModel(*(torch.tensor([[v]], dtype=F64) for v in (0.9, 1.0, 0.5, 0.3)),
                               torch.zeros(1, dtype=F64), torch.eye(1, dtype=F64))  # fmt: skip
YS = torch.randn(4, 6, 1, generator=torch.Generator().manual_seed(0), dtype=F64)


def _run(**kw):
    return particle_filter(MODEL, YS, num_particles=8, ess_threshold=1.0,
                           generator=torch.Generator().manual_seed(1), **kw)  # fmt: skip


class _FirstOnly(Multinomial):
    def _draw(self, log_w, generator):  # every ancestor particle 0: a `_draw` of its own
        return torch.zeros(log_w.shape, dtype=torch.int64, device=log_w.device)


@pytest.mark.parametrize("bad", [0.0, 1.5, -0.2, math.inf, True])
def test_soft_resamplings_alpha_set_later(bad):
    """α outside (0, 1] stopped the filter on a bare "math domain error"; ``True`` was
    taken as 1."""
    soft = Soft(0.5)
    with pytest.raises(ValueError, match="alpha must be"):
        soft.alpha = bad


def test_soft_resamplings_base_set_later():
    """A Soft base (refused by the constructor) drew from its own mixture while the weights
    divided by this one's: Σ w/q f 245 standard errors off Σ w f."""
    soft = Soft(0.5)
    for bad in (Soft(0.5), StopGradient(), "multinomial"):
        with pytest.raises(ValueError, match="base must"):
            soft.base = bad
    soft.alpha, soft.base = 0.3, Stratified()
    assert torch.equal(_run(resampler=soft).means, _run(resampler=Soft(0.3, Stratified())).means)
    soft.base = None  # (the constructor's default)
    assert isinstance(soft.base, Multinomial)


def test_residual_and_stop_gradients_base_set_later():
    """A Residual base with a ``_draw`` of its own (refused by the constructor: the R < N
    residual draws ignore it) was ignored silently; Soft() or None failed on "no attribute
    '_draw_from'"."""
    residual = Residual()
    for bad in (_FirstOnly(), Soft(), "x"):
        with pytest.raises(ValueError, match="base must"):
            residual.base = bad
    residual.base = None
    assert isinstance(residual.base, Multinomial)
    residual.base = Systematic()
    assert torch.equal(_run(resampler=residual).means,
                       _run(resampler=Residual(Systematic())).means)  # fmt: skip
    stop = StopGradient()
    with pytest.raises(ValueError, match="base must"):
        stop.base = Soft()
    stop.base = None
    assert isinstance(stop.base, Systematic)


@pytest.mark.parametrize("bad", [1.0, -0.1, math.nan, "0.2"])
def test_the_kalman_proposals_defensive_weight_set_later(bad):
    """ρ = 1 (refused by the constructor) stopped the first step on "math domain error"."""
    proposal = KalmanProposal()
    with pytest.raises(ValueError, match=r"defensive \(rho\) must be a number in \[0, 1\)"):
        proposal.rho = bad


def test_the_kalman_proposals_defensive_weight_set_later_is_the_one_built_so():
    proposal = KalmanProposal()
    proposal.rho = 0.25
    assert torch.equal(_run(proposal=proposal).means, _run(proposal=KalmanProposal(0.25)).means)


def test_a_particle_filters_likelihood_set_later():
    """None failed at the step ("'NoneType' object is not callable": the constructor reads
    it as the default), the class for an instance on "takes no arguments"."""
    pf = df.ParticleFilter(8)
    with pytest.raises(TypeError, match="instance, not the class"):
        pf.likelihood = ModelLikelihood
    with pytest.raises((TypeError, ValueError), match="likelihood"):
        pf.likelihood = "gaussian"
    pf.likelihood = None
    assert isinstance(pf.likelihood, ModelLikelihood)
    carry = pf.init(MODEL, (4,), torch.Generator().manual_seed(1))
    pf.step(carry, YS[:, 0])


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
@pytest.mark.parametrize("scheme", [Multinomial, Systematic, Stratified, Residual, Soft])
def test_resampling_in_half_precision_is_refused(scheme, dtype):
    """The draws ran in the log-weights' dtype: offspring counts 33–243 standard errors off
    ``N w`` in bfloat16 (Residual gave particle 0 ⌊1.25 N w⌋ copies and the small ones
    none), 5–11 in float16."""
    log_w = torch.log(torch.tensor([0.6, 0.3] + [0.005] * 20)).to(dtype)
    with pytest.raises(ValueError, match="half precision biases the offspring counts"):
        scheme().ancestors(log_w, torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match="half precision biases the offspring counts"):
        scheme()(torch.zeros(22, 1, dtype=dtype), log_w, torch.Generator().manual_seed(0))
