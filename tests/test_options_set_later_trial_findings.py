"""Options assigned after construction, checked as the constructor checks them (a red-team
trial, 2026-12-07; each test failed before its fix). A valid value assigned later gives
what the object built with it gives, bit for bit."""

from __future__ import annotations

import math

import pytest
import torch

import difffilter as df
from difffilter.fdi.adaptive_kf import AdaptiveKalmanFilter
from difffilter.fdi.mixture import BiasDeception, DeceptionMixtureLikelihood, MixtureParticleFilter
from difffilter.resampling import OptimalTransport, Systematic

F64 = torch.float64
EYE = torch.eye(2, dtype=F64)
MODEL = df.LinearGaussianModel(torch.tensor([[0.9, 0.1], [0.0, 0.95]], dtype=F64), EYE, 0.1 * EYE,
                               0.2 * EYE, torch.zeros(2, dtype=F64), EYE,
                               B=torch.tensor([[1.0], [0.5]], dtype=F64))  # fmt: skip
YS = 3 * torch.randn(3, 8, 2, generator=torch.Generator().manual_seed(0), dtype=F64)


def _steps(estimator, runs=(3,), us=None):
    carry = estimator.init(MODEL, runs, torch.Generator().manual_seed(1))
    outs = []
    for k in range(YS.shape[-2]):
        carry, out = estimator.step(carry, YS[:, k], None if us is None else us[..., k, :])
        outs.append(out)
    return outs


@pytest.mark.parametrize("bad", [math.nan, 2.0, -1.0, "0.5"])
def test_a_particle_filters_ess_threshold_set_later(bad):
    """NaN or −1 turned resampling off for good (bit for bit the filter of 0), 2.0 resampled
    at every step."""
    pf = df.ParticleFilter(50)
    with pytest.raises((ValueError, TypeError), match="ess_threshold must"):
        pf.ess_threshold = bad
    pf.ess_threshold = 0.0
    got = _steps(pf)[-1].mean
    assert torch.equal(got, _steps(df.ParticleFilter(50, ess_threshold=0.0))[-1].mean)


def test_a_particle_filters_resampler_proposal_and_hooks_set_later():
    pf = df.ParticleFilter(50)
    with pytest.raises(TypeError, match="resampler"):
        pf.resampler = "systematic"
    with pytest.raises(TypeError, match="hooks must be a sequence"):
        pf.hooks = None
    pf.resampler = None  # the default, as the constructor reads None
    assert isinstance(pf.resampler, Systematic)
    assert torch.equal(_steps(pf)[-1].mean, _steps(df.ParticleFilter(50))[-1].mean)


@pytest.mark.parametrize("bad", [math.nan, -1.0, 2.0, True])
def test_a_mixture_filters_threshold_set_later(bad):
    """A NaN threshold assigned later never alarmed (0 of 24 where the attack probability
    reached 0.996), −1 alarmed at every step."""

    def mixture(**kw):
        likelihood = DeceptionMixtureLikelihood(0.1, BiasDeception(torch.ones(2, dtype=F64)))
        return MixtureParticleFilter(40, likelihood, **kw)

    pf = mixture()
    with pytest.raises(ValueError, match="threshold must lie in"):
        pf.threshold = bad
    pf.threshold = 0.3
    got = torch.stack([o.alarm for o in _steps(pf)])
    assert torch.equal(got, torch.stack([o.alarm for o in _steps(mixture(threshold=0.3))]))


@pytest.mark.parametrize("bad", [2.0, 0.0, -1.0, math.nan])
def test_an_adaptive_kalman_filters_forgetting_set_later(bad):
    """λ = 2 assigned later ran (a shrinking attack covariance: Wald scores of 968 and an
    alarm); 0 and NaN failed at the step blaming the model's Q, R and P0."""
    akf = AdaptiveKalmanFilter()
    with pytest.raises(ValueError, match="forgetting"):
        akf.forgetting = bad
    akf.forgetting = 0.5
    us = torch.zeros(3, 8, 1, dtype=F64)
    got = torch.stack([o.score for o in _steps(akf, us=us)])
    assert torch.equal(
        got, torch.stack([o.score for o in _steps(AdaptiveKalmanFilter(0.5), us=us)])
    )


def test_a_kalman_filters_method_set_later():
    """ "parallel" assigned later stayed a string the whole-sequence path never matched (it
    ran sequentially); "bogus" was taken."""
    kf = df.KalmanFilter()
    with pytest.raises(ValueError, match="method must be one of"):
        kf.method = "bogus"
    kf.method = "parallel"
    assert (
        kf.method is df.Method.PARALLEL if hasattr(df, "Method") else kf.method.value == "parallel"
    )
    ys = torch.randn(2, 64, 2, generator=torch.Generator().manual_seed(0), dtype=F64)
    assert torch.equal(df.open_loop(kf, MODEL, ys).means,
                       df.open_loop(df.KalmanFilter("parallel"), MODEL, ys).means)  # fmt: skip


@pytest.mark.parametrize(
    "name, bad",
    [("epsilon", -1.0), ("max_iterations", 0), ("tolerance", 5.0), ("tolerance", math.nan),
     ("method", "bogus"), ("scale", "x"), ("grad_iterations", -1), ("checkpoint", 1)],
)  # fmt: skip
def test_optimal_transports_settings_set_later(name, bad):
    """ε = −1 assigned later hung the ε-scaling loop; max_iterations = 0 returned a transport
    of no iteration (the mean 0.07 off); a tolerance of 5 stopped after one iteration."""
    ot = OptimalTransport()
    with pytest.raises(ValueError, match=name):
        setattr(ot, name, bad)
    ot.epsilon = 0.3
    particles = torch.randn(2, 30, 2, generator=torch.Generator().manual_seed(2), dtype=F64)
    log_w = torch.log_softmax(particles[..., 0], -1)
    torch.testing.assert_close(ot(particles, log_w).particles,
                               OptimalTransport(0.3)(particles, log_w).particles, rtol=0, atol=0)  # fmt: skip


@pytest.mark.parametrize("name, bad", [("lr", math.nan), ("lr", -1.0), ("init_cov", math.inf),
                                       ("init_noise", 0.0), ("process_noise", -1e-3),
                                       ("fold_every", 0)])  # fmt: skip
def test_the_weight_learners_settings_set_later(name, bad):
    from difffilter.models.neural_estimator import AreaNetwork
    from difffilter.param_ekf import EKFRule, GradientRule, WeightTemplate

    rule = EKFRule()
    with pytest.raises(ValueError, match=name):
        setattr(rule, name, bad)
    if name == "lr":
        with pytest.raises(ValueError, match="lr"):
            GradientRule().lr = bad
    template = WeightTemplate(AreaNetwork(3, 4, 2))
    g = torch.Generator().manual_seed(0)
    theta = 0.3 * torch.randn(2, template.num_params, generator=g, dtype=F64)
    x, target = torch.randn(2, 3, generator=g, dtype=F64), torch.randn(2, 2, generator=g, dtype=F64)
    rule.lr = 0.5
    prediction, H = template.jacobian(theta, x)
    got = rule.step(rule.init(theta.clone()), H, target - prediction).theta
    want = EKFRule(lr=0.5).step(EKFRule(lr=0.5).init(theta.clone()), H, target - prediction).theta
    assert torch.equal(got, want)


# --- the modified PF's fused path and the mixture likelihood's parts (2026-12-07, later) ---


def _four_tank_case():
    from difffilter.models.four_tank import FourTankModel

    model = FourTankModel(dtype=F64)
    g = torch.Generator().manual_seed(0)
    ys = model.initial.mean + 0.03 * torch.randn(4, 40, 4, dtype=F64, generator=g)
    ys[:, ::2] += 0.3
    return model, ys, torch.full((4, 40, 4), 0.3, dtype=F64)


def _generators():
    from difffilter.estimator import Generators

    return Generators(*(torch.Generator().manual_seed(i) for i in range(3)))


def test_fused_set_later_is_checked_against_the_running_attack_rate():
    """``fused = True`` assigned beside an ``attack_rate`` ran the fused path, which has no
    running rate: ζ fixed at 0.5 where the running one is 0.45 (0.045 off)."""
    from difffilter.loop import open_loop

    model, ys, gamma_hat = _four_tank_case()
    pf = df.fdi.ModifiedParticleFilter(100, df.fdi.PoADetector(0.175, 0.5), gamma_hat,
                                       attack_rate=df.fdi.RunningAttackRate(100))  # fmt: skip
    ref = open_loop(pf, model, ys, generator=_generators())
    with pytest.raises(ValueError, match="fused=True does not support attack_rate"):
        pf.fused = True
    assert pf.fused is False
    again = open_loop(pf, model, ys, generator=_generators())
    assert torch.equal(ref.detection.threshold, again.detection.threshold)
    with pytest.raises(ValueError, match="fused must be True or False"):
        pf.fused = "yes"


def test_a_resampler_set_later_on_a_fused_filter_is_checked_at_its_run():
    """A multinomial resampler assigned to a fused filter was ignored (systematic draws on
    the fused path: means 0.023 off the unfused multinomial filter's)."""
    from difffilter.loop import open_loop

    model, ys, gamma_hat = _four_tank_case()
    pf = df.fdi.ModifiedParticleFilter(100, df.fdi.PoADetector(0.175, 0.5), gamma_hat, fused=True)
    pf.resampler = df.resampling.Multinomial()
    with pytest.raises(ValueError, match=r"resampler \(not Systematic\)"):
        open_loop(pf, model, ys, generator=_generators())
    with pytest.raises(ValueError, match=r"resampler \(not Systematic\)"):
        df.fdi.modified_particle_filter(model, ys, num_particles=100, gamma_hat=gamma_hat,
                                        detector=df.fdi.PoADetector(0.175, 0.5), fused=True,
                                        resampler=df.resampling.Multinomial())  # fmt: skip


@pytest.mark.parametrize("when", ["before the first run", "between steps"])
def test_an_attack_rate_of_another_n_set_later_is_refused(when):
    """The constructor refuses a RunningAttackRate of another N (its warm-up ζ is eq. 46's
    for its own N); one assigned to the weighting later had been used."""
    model, ys, gamma_hat = _four_tank_case()
    pf = df.fdi.ModifiedParticleFilter(100, df.fdi.PoADetector(0.175, 0.5), gamma_hat,
                                       attack_rate=df.fdi.RunningAttackRate(100))  # fmt: skip
    if when == "between steps":
        carry = pf.init(model, (4,), _generators())
        carry, _ = pf.step(carry, ys[:, 0])
    pf.likelihood.attack_rate = df.fdi.RunningAttackRate(50)
    with pytest.raises(ValueError, match="RunningAttackRate of 50 particles"):
        if when == "between steps":
            pf.step(carry, ys[:, 1])
        else:
            pf.init(model, (4,), _generators())


def test_the_mixture_likelihoods_attack_and_bias_set_later_are_checked():
    """``BiasDeception.rho`` set to a 0-d tensor met a bare ``IndexError`` in the likelihood;
    an ``attack`` that is not callable, a ``TypeError`` at the first step."""
    bias = BiasDeception(torch.zeros(2, dtype=F64))
    with pytest.raises(ValueError, match="rho must be a finite vector"):
        bias.rho = torch.tensor(1.0, dtype=F64)
    with pytest.raises(ValueError, match="rho must be a finite vector"):
        bias.rho = torch.tensor([math.nan, 0.0], dtype=F64)
    lik = DeceptionMixtureLikelihood(0.2, bias)
    with pytest.raises(ValueError, match="attack must be a callable"):
        lik.attack = 3
    bias.rho = torch.tensor([0.5, 0.0], dtype=F64)
    made = DeceptionMixtureLikelihood(0.2, BiasDeception(torch.tensor([0.5, 0.0], dtype=F64)))
    parts = (MODEL, YS[:, 0], torch.zeros(3, 5, 2, dtype=F64), 1, None)
    assert torch.equal(lik(*parts), made(*parts))
