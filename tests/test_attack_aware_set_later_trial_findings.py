"""The analytic attack-aware pieces' settings assigned after construction, and the PoA's
threshold per run (a red-team trial, 2026-12-07; each test of a refusal or of a setting
read failed before its fix). Assigned, a setting is checked as the constructor checks it,
and a valid one gives what the object built with it gives, bit for bit (the two tests of
that alone held before)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from difffilter import ExtendedKalmanFilter, KalmanFilter
from difffilter.fdi.attack_estimation import BiasAttackEstimator
from difffilter.fdi.detectors import ChiSquareDetector, CusumDetector
from difffilter.fdi.gated import GatedFilter
from difffilter.fdi.poa import PoADetector, RunningAttackRate, probability_of_attack
from difffilter.loop import open_loop
from difffilter.observers import FixedGainFilter
from difffilter.ssm import LinearGaussianModel

F64 = torch.float64
EYE = torch.eye(2, dtype=F64)
MODEL = LinearGaussianModel(torch.tensor([[1.0, 0.1], [0.0, 0.9]], dtype=F64), EYE,
                            0.01 * EYE, 0.1 * EYE, torch.zeros(2, dtype=F64), EYE)  # fmt: skip
_, YS, _ = MODEL.simulate(12, (3,), generator=torch.Generator().manual_seed(0))
YS[:, 6:] += 2.0  # an attack the gate drops


@pytest.mark.parametrize(("name", "bad"), [("alpha0", math.nan), ("alpha0", 1.5),
                                           ("alpha0", "0.5"), ("warmup", 0), ("n", 1),
                                           ("alpha_max", 2.0), ("alpha_min", -1.0),
                                           ("alpha_min", 0.99)])  # fmt: skip
def test_a_running_attack_rates_settings_set_later(name, bad):
    """alpha0 = NaN or warmup = 0 gave ζ = NaN (β = 1 never alarmed), alpha0 = 1.5 a ζ of
    1.485; alpha_min above alpha_max, a clip upside down."""
    rate = RunningAttackRate(100)
    with pytest.raises(ValueError, match=name if name != "n" else "num_particles"):
        setattr(rate, name, bad)


def test_a_running_attack_rate_set_later_is_the_one_built_so():
    later = RunningAttackRate(100)
    later.alpha0, later.warmup, later.alpha_max = 0.3, 3, 0.6
    built = RunningAttackRate(100, alpha0=0.3, warmup=3, alpha_max=0.6)
    alarms = torch.tensor([[True, True, False, True, True, True, True, False]])
    for rate in (later, built):
        state, zetas = rate.init((1,)), []
        for k in range(alarms.shape[-1]):
            zetas.append(rate.zeta(state))
            state = rate.update(state, alarms[:, k])
        rate.zetas = torch.stack(zetas)
    assert torch.equal(later.zetas, built.zetas)
    assert float(later.zetas[0]) == 0.3 * 99 / 100 and float(later.zetas[-1]) == 0.6 * 99 / 100


def _gamma_hats(est, residuals):
    state, out = est.init(()), []
    for r in residuals:
        state, gamma_hat, _ = est.step(state, r, torch.eye(2, dtype=F64), torch.tensor(True))
        out.append(gamma_hat)
    return torch.stack(out)


def test_a_bias_estimators_tau_set_later_is_read():
    """τ is built into eq. (4)'s transition matrix: assigned later it was stored and never
    read (γ̂₃ of τ = 0.9, 1.1736, where τ = 0.1 gives 1.0314)."""
    residuals = 1.0 + torch.randn(4, 2, generator=torch.Generator().manual_seed(2), dtype=F64)
    est = BiasAttackEstimator(2, 0.9)
    est.tau = 0.1
    assert torch.equal(
        _gamma_hats(est, residuals), _gamma_hats(BiasAttackEstimator(2, 0.1), residuals)
    )
    assert not torch.equal(_gamma_hats(est, residuals),
                           _gamma_hats(BiasAttackEstimator(2, 0.9), residuals))  # fmt: skip
    for bad in (5.0, math.nan, True):
        with pytest.raises(ValueError, match="tau must lie in"):
            est.tau = bad
    with pytest.raises(AttributeError, match="dim is the size"):
        est.dim = 3
    with pytest.raises(AttributeError, match="model follows tau"):
        est.model = BiasAttackEstimator(2, 0.5).model


def test_a_fixed_gain_set_later_is_checked():
    """A NaN gain assigned later made every estimate NaN (the constructor refuses it); a
    numpy one failed on "'numpy.ndarray' object has no attribute 'to'"."""
    obs = FixedGainFilter(0.5 * EYE)
    with pytest.raises(ValueError, match="gain contains NaN"):
        obs.gain = torch.full((2, 2), math.nan, dtype=F64)
    with pytest.raises(ValueError, match=r"gain must be a tensor \[dx, dy\]"):
        obs.gain = np.eye(2)
    obs.gain = 0.3 * EYE
    assert torch.equal(open_loop(obs, MODEL, YS).means,
                       open_loop(FixedGainFilter(0.3 * EYE), MODEL, YS).means)  # fmt: skip


def test_a_gated_filters_detector_and_filter_set_later():
    """A PoADetector assigned later failed on "'PoADetector' object has no attribute
    'init'", a filter of None on "'NoneType' object has no attribute '_init'" (None builds
    a gated EKF in the constructor)."""
    gated = GatedFilter(ChiSquareDetector(2, 0.01), KalmanFilter())
    with pytest.raises(ValueError, match="detector must be a ChiSquareDetector or a CusumDetector"):
        gated.detector = PoADetector(0.5, 0.1)
    with pytest.raises(ValueError, match="CusumDetector has no threshold"):
        gated.detector = CusumDetector(bias=2.0)
    with pytest.raises(TypeError, match="filter must be a Gaussian filter"):
        gated.filter = "kf"
    with pytest.raises(TypeError, match="reports no innovation covariance"):
        gated.filter = FixedGainFilter(0.5 * EYE)
    with pytest.raises(ValueError, match="gate must be True or False"):
        gated.gate = "no"
    gated.filter = None
    assert isinstance(gated.filter, ExtendedKalmanFilter)
    built = GatedFilter(ChiSquareDetector(2, 0.01), None)
    a, b = open_loop(gated, MODEL, YS), open_loop(built, MODEL, YS)
    assert torch.equal(a.means, b.means) and torch.equal(a.detection.alarms, b.detection.alarms)
    assert bool(a.detection.alarms[:, 6:].any())


def test_a_gated_filters_detector_replaced_between_steps_is_the_new_ones():
    gated = GatedFilter(ChiSquareDetector(2, 0.01), KalmanFilter())
    carry = gated.init(MODEL, (3,))
    carry, _ = gated.step(carry, YS[:, 0])
    gated.detector = ChiSquareDetector(2, 0.01, window=3)
    with pytest.raises(ValueError, match="init"):  # a window-1 state for a window-3 test
        gated.step(carry, YS[:, 1])


def test_the_poas_threshold_per_run_must_fit_the_runs():
    """η ``[B, 1]`` for residuals ``[B, N, dy]`` gave β ``[B, B]``: every run against every
    run's threshold, silently."""
    z = torch.randn(3, 50, 2, generator=torch.Generator().manual_seed(0), dtype=F64)
    eta = torch.tensor([0.5, 1.0, 1.5], dtype=F64)
    beta = probability_of_attack(z, eta)
    by_hand = torch.stack([(z[b].norm(dim=-1) > eta[b]).to(F64).mean() for b in range(3)])
    assert torch.equal(beta, by_hand)
    for bad in (eta[:, None], eta[:2], torch.ones(2, 3, dtype=F64)):
        with pytest.raises(ValueError, match="eta has shape"):
            probability_of_attack(z, bad)
        with pytest.raises(ValueError, match="eta has shape"):
            PoADetector(bad, 0.5)(z)
    assert probability_of_attack(z, torch.tensor(1.0, dtype=F64)).shape == (3,)
    assert probability_of_attack(z[None], eta).shape == (1, 3)  # (broadcast, as numbers do)
