"""Findings of a trial of the mixture-likelihood and fused modified particle filters and
the tracking model's glint density (each failed before its fix)."""

from __future__ import annotations

import pytest
import torch

import difffilter as df
from difffilter import fdi
from difffilter.estimator import Generators
from difffilter.fdi.fused import FusedModifiedPF
from difffilter.fdi.mixture import (
    BiasDeception,
    DeceptionMixtureLikelihood,
    MixtureParticleFilter,
    ReplacementDeception,
)
from difffilter.models.four_tank import FourTankModel
from difffilter.models.tracking import TrackingModel
from difffilter.noise import Gaussian, UniformBox
from difffilter.resampling import Multinomial

D = torch.float64


def _linear(dtype=D):
    eye = torch.eye(2, dtype=dtype)
    return df.LinearGaussianModel(torch.tensor([[1.0, 0.1], [0.0, 0.9]], dtype=dtype), eye,
                                  0.05 * eye, 0.1 * eye, torch.zeros(2, dtype=dtype), eye)  # fmt: skip


def _ys(model, T=12):
    _, ys, _ = model.simulate(T, (3,), generator=torch.Generator().manual_seed(0))
    return ys


def _mixture(p=0.2):
    box = UniformBox(-5 * torch.ones(2, dtype=D), 5 * torch.ones(2, dtype=D))
    return DeceptionMixtureLikelihood(p, ReplacementDeception(box))


def _means(pf, model, ys, online=False):
    if not online:
        return df.open_loop(pf, model, ys, generator=torch.Generator().manual_seed(1)).means
    carry = pf.init(model, (3,), torch.Generator().manual_seed(1))
    means = []
    for y in ys.unbind(1):
        carry, out = pf.step(carry, y)
        means.append(out.mean)
    return torch.stack(means, 1)


@pytest.mark.parametrize(
    ("name", "value"),
    [("resampler", Multinomial()), ("ess_threshold", 0.0), ("likelihood", None), ("mixture", None)],
)
def test_a_mixture_filters_setting_assigned_later_is_the_one_run(name, value):
    """The whole-sequence fast path built its filter from the constructor's settings (a
    resampler or ESS threshold assigned later ran in the steps alone, means 0.88-2.04 off),
    and the mixture was kept twice (``likelihood``, ``mixture``): one assigned later left the
    other weighing or scoring with the old ``p``."""
    model = _linear()
    ys = _ys(model)
    value = _mixture(0.6) if value is None else value
    later = MixtureParticleFilter(64, _mixture())
    setattr(later, name, value)
    built = MixtureParticleFilter(64, value if name in ("likelihood", "mixture") else _mixture(),
                                  **({name: value} if name in ("resampler", "ess_threshold") else {}))  # fmt: skip
    for online in (False, True):
        torch.testing.assert_close(
            _means(later, model, ys, online), _means(built, model, ys, online), rtol=0, atol=0
        )
    assert later.mixture is later.likelihood


def test_a_mixture_filter_keeps_its_own_hook_and_runs_hooks_assigned_later():
    """``pf.hooks = (h,)`` had dropped the filter's own hook (its score: a bare KeyError 'p'
    at the next step), and a hook assigned later left no record in the whole-sequence run."""
    model = _linear()
    pf = MixtureParticleFilter(32, _mixture())
    pf.hooks = (
        lambda model, y, mask, carry, out: {"mine": carry.log_weights.exp().max(-1).values},
    )
    out = df.open_loop(pf, model, _ys(model), generator=torch.Generator().manual_seed(1))
    assert "mine" in out.extras and out.detection is not None


def test_a_bias_deception_of_another_number_of_runs_is_refused_by_name():
    model = _linear()
    lik = BiasDeception(torch.zeros(3, 2, dtype=D))
    with pytest.raises(
        ValueError, match=r"rho \(3, 2\) must broadcast to the measurements \(2, 2\)"
    ):
        lik(model, torch.zeros(2, 2, dtype=D), torch.zeros(2, 5, 2, dtype=D), 1, None)


def _fused(model, **kw):
    return FusedModifiedPF(
        model, num_particles=kw.pop("n", 64), eta=kw.pop("eta", 0.233), zeta=kw.pop("zeta", 0.5)
    )


def test_a_fused_filters_model_changed_later_is_the_one_run():
    """The measurement's constants were made at construction: a model changed since ran
    with the old R (means 0.85 off a filter built on the changed model)."""
    model, fresh = FourTankModel(dtype=D), FourTankModel(dtype=D)
    pf = _fused(model)
    with torch.no_grad():
        model.measurement_noise._cov.mul_(4.0)
        fresh.measurement_noise._cov.mul_(4.0)
    ys = torch.full((2, 10, 4), 12.0, dtype=D)
    gamma = torch.zeros_like(ys)
    runs = [
        p.run(ys, gamma, generator=torch.Generator().manual_seed(0)).means
        for p in (pf, _fused(fresh))
    ]
    torch.testing.assert_close(runs[0], runs[1], rtol=0, atol=0)


def test_a_fused_filter_refuses_what_its_weights_are_not_written_for():
    """A measurement noise of non-zero mean had been weighed as zero-mean (0.124 off the
    composed filter); eta, zeta and n assigned later ran unchecked (zeta = 1.5 never
    alarmed, eta = -1 acted as +1, n = 1 ran one particle)."""
    model = FourTankModel(dtype=D)
    model.measurement_noise = Gaussian(0.05 * torch.ones(4, dtype=D), model.measurement_noise.cov)
    with pytest.raises(ValueError, match="zero-mean Gaussian measurement noise"):
        _fused(model)
    pf = _fused(FourTankModel(dtype=D))
    cases = (("zeta", 1.5, r"zeta must be a number in \[0, 1\)"),
             ("eta", -1.0, "eta must be a finite number >= 0"),
             ("n", 1, "num_particles must be an integer >= 2"))  # fmt: skip
    for name, value, match in cases:
        with pytest.raises(ValueError, match=match):
            setattr(pf, name, value)


def test_the_fused_filter_in_float32_keeps_its_weights_where_the_attack_estimate_is_large():
    """Below float64 eq. (59)'s expanded quadratic cancelled for a large γ̂: the step-1 mean
    2.5e-3 off at γ̂ = 20 and 1.3e-2 at 50 (eqs 59-60 on the same particles in float64),
    where the composed filter is 2.4e-6 off."""
    model = FourTankModel(dtype=torch.float32)
    var = torch.diagonal(model.measurement_cov(1)).double()
    noise = 0.03 * torch.randn(4, 3, 4, generator=torch.Generator().manual_seed(1), dtype=D)
    gam = 50.0
    ys = model.initial.mean + noise.float() + gam
    gamma = torch.full((4, 3, 4), gam)
    detector = fdi.PoADetector(0.2, 0.5)

    def generators():
        return Generators(*(torch.Generator().manual_seed(i) for i in range(3)))

    fused = df.open_loop(fdi.ModifiedParticleFilter(100, detector, gamma, fused=True), model, ys,
                         generator=generators())  # fmt: skip
    pf = fdi.ModifiedParticleFilter(100, detector, gamma)
    carry, _ = pf.step(pf.init(model, (4,), generators()), ys[:, 0])  # the same step-1 draws
    x = carry.particles.double()
    r = ys[:, 0].double().unsqueeze(-2) - gam - x
    w = torch.softmax(-0.5 * (r * r / var).sum(-1), -1)
    truth = (w.unsqueeze(-1) * x).sum(-2)
    assert float((fused.means[:, 0].double() - truth).abs().max()) < 5e-5


def test_a_glint_residual_whose_square_overflows_leaves_the_other_sensors_finite():
    """The masked table's zeros times ∞ made every sensor's term NaN: [-inf, nan, nan, nan]
    where the per-sensor closed form gives [-inf, 1.22, 0.87, 1.16]."""
    glint = TrackingModel().measurement_noise
    v = torch.tensor([1e200, 0.001, 1.0, 0.001, 2.0, 0.0, 0.5, -0.01], dtype=D)
    got = glint.block_log_prob(v)
    want = torch.stack([glint.sensor_log_prob(v[2 * s], v[2 * s + 1]) for s in range(4)])
    torch.testing.assert_close(got[1:], want[1:], rtol=1e-12, atol=0)
    assert float(got[0]) < -1e300 and not bool(torch.isnan(got).any())
