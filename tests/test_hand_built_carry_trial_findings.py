"""Findings of a red-team trial of hand-built carries of the attack-aware estimators and the
particle filter: fields the full carry checks had not reached. Each test failed on the code
before its fix."""

from __future__ import annotations

import pytest
import torch

import difffilter as df
from difffilter.fdi import ChiSquareDetector, CusumDetector, GatedFilter
from difffilter.fdi.adaptive_kf import AdaptiveKalmanFilter

D = torch.float64
EYE = torch.eye(2, dtype=D)


def _model(B=None) -> df.LinearGaussianModel:
    return df.LinearGaussianModel(
        0.9 * EYE, EYE, 0.1 * EYE, 0.2 * EYE, torch.zeros(2, dtype=D), EYE, B=B
    )


@pytest.mark.parametrize(
    "detector", [CusumDetector(4.0, threshold=5.0), ChiSquareDetector(2, 0.01, window=3)]
)
def test_a_gated_filters_detector_state_is_checked(detector):
    # a NaN S (or window value) had scored NaN and never alarmed: a measurement 5 off was used
    gated = GatedFilter(detector, df.KalmanFilter())
    carry = gated.init(_model(), (2,))
    state = carry.detector
    bad = (
        state * float("nan")
        if isinstance(state, torch.Tensor)
        else (state[0] * float("nan"),) + state[1:]
    )
    with pytest.raises(ValueError, match="carry.detector.* must be >= 0 and not NaN"):
        gated.step(carry._replace(detector=bad), torch.zeros(2, 2, dtype=D))
    gated.step(carry, torch.zeros(2, 2, dtype=D))  # (the init carry steps)


def test_a_wrapped_carrys_step_index_is_checked():
    # carry.inner.k = -3 had read a time-varying model there
    gated = GatedFilter(ChiSquareDetector(2, 0.01), df.KalmanFilter())
    carry = gated.init(_model(), ())
    with pytest.raises(ValueError, match=r"carry.inner.k must be an integer step index >= 0"):
        gated.step(carry._replace(inner=carry.inner._replace(k=-3)), torch.zeros(2, dtype=D))


def test_a_learned_estimators_histories_are_checked():
    # a NaN in attack_hist had run to NaN means; another layout failed in torch's cat
    from difffilter.fdi.neural import NeuralCompensation
    from difffilter.models.neural_estimator import NeuralFDIEstimator

    torch.manual_seed(0)
    est = NeuralCompensation(NeuralFDIEstimator(num_areas=1, area_dim=2, init_scale=0.5).double(),
                             df.KalmanFilter())  # fmt: skip
    carry = est.init(_model(), (3,))
    hist = carry.net.attack_hist.clone()
    hist[0, 0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="NeuralState.attack_hist contains NaN"):
        est.step(
            carry._replace(net=carry.net._replace(attack_hist=hist)), torch.zeros(3, 2, dtype=D)
        )
    more = carry.net.resid_hist.unsqueeze(0)
    with pytest.raises(
        ValueError, match="NeuralState.resid_hist must be a torch.float64 tensor of shape"
    ):
        est.step(
            carry._replace(net=carry.net._replace(resid_hist=more)), torch.zeros(3, 2, dtype=D)
        )


@pytest.mark.parametrize("field", ["cov", "attack", "attack_cov"])
def test_an_adaptive_kf_carry_of_other_runs_is_named(field):
    akf = AdaptiveKalmanFilter()
    carry = akf.init(_model(B=EYE), (3,))
    with pytest.raises(ValueError, match=f"carry.{field} .* must hold the runs of carry.mean"):
        akf.step(carry._replace(**{field: getattr(carry, field)[:2]}), torch.zeros(3, 2, dtype=D))


@pytest.mark.parametrize("field,value", [("log_weights", lambda c: c.log_weights.numpy()),
                                         ("weights", lambda c: c.log_weights.exp().numpy()),
                                         ("ess", lambda c: torch.full(c.log_weights.shape[:-1], 10.0))])  # fmt: skip
def test_a_particle_carrys_weights_and_caches_are_named(field, value):
    pf = df.ParticleFilter(10)
    carry = pf.init(_model(), (2,), torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match=f"carry.{field} must be a torch.float64 tensor"):
        pf.step(carry._replace(**{field: value(carry)}), torch.zeros(2, 2, dtype=D))


@pytest.mark.parametrize(
    "filt", [df.UnscentedKalmanFilter(), df.ExtendedKalmanFilter(), df.KalmanFilter()]
)
def test_an_integer_carry_mean_is_named(filt):
    # an int64 mean of init's values had made the UKF's sigma-point weights int64 (rounded to
    # 0: mean [0.1, -0.07] for [0.27, -0.18]); the others failed in torch's words
    carry = filt.init(_model(), ())
    with pytest.raises(ValueError, match="carry.mean must be a floating tensor"):
        filt.step(carry._replace(mean=carry.mean.long()), torch.tensor([1.0, -1.0], dtype=D))
    with pytest.raises(ValueError, match=r"carry.cov must be a covariance \[\.\.\., d, d\]"):
        filt.step(carry._replace(cov=carry.cov[0]), torch.tensor([1.0, -1.0], dtype=D))


def test_a_stateful_particle_filters_carry_without_its_state_is_named():
    # (a modified PF's carry with aux None had failed on None's attributes)
    from difffilter.fdi import ModifiedParticleFilter, PoADetector

    pf = ModifiedParticleFilter(20, PoADetector(0.5, 0.5), torch.zeros(4, 2, dtype=D))
    carry = pf.init(_model(), (2,), torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match="carry.aux is None"):
        pf.step(carry._replace(aux=None), torch.zeros(2, 2, dtype=D))


def test_an_adaptive_pf_carry_of_a_singular_attack_covariance_is_refused_by_its_step():
    # attach refused it; the step took it and ran to NaN means in the information form
    from difffilter.fdi.mdpf import AdaptiveParticleFilter, adaptive_particle_init

    model = _model(B=EYE)
    apf = AdaptiveParticleFilter(16, form="information")
    carry = apf.init(model, (1,), torch.Generator().manual_seed(0))
    state = adaptive_particle_init(
        model, 16, (1,), torch.Generator().manual_seed(0), attack_cov0=0.0
    )
    with pytest.raises(ValueError, match="singular"):
        apf.step(carry._replace(particles=state.particles), torch.zeros(1, 2, dtype=D))
