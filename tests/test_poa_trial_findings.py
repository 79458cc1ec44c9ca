"""The modified PF's detector against eqs (35), (46), (53) and Remark 6 (a red-team trial).

* ``RunningAttackRate.zeta`` computed ``ζ = α(N − 1)/N`` with ``α = p̂_l N/(N − 1)`` in
  floating point and landed an ulp below ``p̂_l``: ``β = p̂_l`` alarmed.
* A carry given as ``initial_state`` kept the weighting state of the run it came from: the
  gain of eq. (35) of another model, and no rate or bias-estimator state (an AttributeError).
* A ``RunningAttackRate`` of another particle count, ``detection_threshold(p_l, N, alpha=)``
  with ``α`` below eq. (53)'s bound, and a ``gamma_min`` of numpy's were not checked.
"""

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from difffilter import fdi
from difffilter.fdi.poa import AttackRateState, attack_threshold
from difffilter.models.four_tank import FourTankModel

F64 = torch.float64


def test_the_running_rate_threshold_is_the_estimated_rate_exactly():
    N = 200
    rate = fdi.RunningAttackRate(N)
    state = AttackRateState(torch.tensor(10.0, dtype=F64), 20)  # p̂_l = 0.5
    assert float(rate.zeta(state)) == 0.5  # was 0.49999999999999994
    model = FourTankModel(dtype=F64)
    y = model.initial.mean.clone()
    x = y.expand(N, 4).clone()
    x[:100] -= 1.0  # β = 100/200 of equal weights over η
    weighting = fdi.ModifiedPFWeighting(fdi.PoADetector(0.233, 0.5), torch.zeros(1, 4, dtype=F64),
                                        attack_rate=rate)  # fmt: skip
    start = weighting.init(model, (), F64, None)._replace(rate=state)
    predictive = SimpleNamespace(
        log_weights=torch.full((N,), -math.log(N), dtype=F64), mean=x.mean(0)
    )
    _, _, record = weighting.weigh(start, model, y, x, 1, None, predictive)
    assert float(record["beta"]) == pytest.approx(0.5, abs=1e-15)
    assert not bool(record["alarm"])


def _carry_of_model_a(n=50, steps=3):
    a = FourTankModel(dtype=F64)
    pf = fdi.ModifiedParticleFilter(
        n, fdi.PoADetector(0.233, 0.5), torch.zeros(1, 10, 4, dtype=F64)
    )
    carry = pf.init(a, (1,), torch.Generator().manual_seed(0))
    for _ in range(steps):
        carry, _ = pf.step(carry, a.initial.mean.expand(1, 4) + 0.2)
    return carry


def _resumed_on_b(state, **options):
    b = FourTankModel(R=(0.05, 0.05, 0.05, 0.05), Q=1e-2, dtype=F64)
    ys = (b.initial.mean + 0.2).expand(1, 3, 4).clone()
    args = dict(num_particles=50, detector=fdi.PoADetector(0.233, 0.5),
                gamma_hat=torch.zeros(1, 3, 4, dtype=F64), initial_state=state,
                generator=torch.Generator().manual_seed(1),
                resample_generator=torch.Generator().manual_seed(2)) | options  # fmt: skip
    return fdi.modified_particle_filter(b, ys, **args)


def test_a_carry_resumed_on_another_model_is_tested_with_that_models_gain():
    carry = _carry_of_model_a()
    torch.testing.assert_close(_resumed_on_b(carry).detection.scores,
                               _resumed_on_b(carry._replace(aux=None)).detection.scores)  # fmt: skip


@pytest.mark.parametrize("option", [{"attack_rate": fdi.RunningAttackRate(50)},
                                    {"gamma_hat": fdi.BiasAttackEstimator(4, 0.9)}])  # fmt: skip
def test_a_carry_without_the_state_the_filter_keeps_is_refused(option):
    with pytest.raises(ValueError, match="initial_state: the carry comes from a run without"):
        _resumed_on_b(_carry_of_model_a(), **option)


def test_a_running_rate_of_another_particle_count_is_refused():
    with pytest.raises(ValueError, match="RunningAttackRate of 2 particles.*num_particles = 50"):
        fdi.ModifiedParticleFilter(50, fdi.PoADetector(0.233, 0.5), torch.zeros(1, 10, 4, dtype=F64),
                                   attack_rate=fdi.RunningAttackRate(2))  # fmt: skip


def test_an_alpha_below_eq_53_for_the_given_p_l_is_refused():
    with pytest.raises(ValueError, match="below eq. \\(53\\)"):
        fdi.detection_threshold(0.5, 100, alpha=0.2)
    with pytest.raises(ValueError, match="p_l must lie in"):
        fdi.detection_threshold(1.7, 100, alpha=0.9)
    assert fdi.detection_threshold(0.5, 100, alpha=0.6) == pytest.approx(0.6 * 99 / 100)
    assert fdi.detection_threshold(None, 100, alpha=0.2) == pytest.approx(0.2 * 99 / 100)


@pytest.mark.parametrize("gamma_min", [np.float32(0.28), torch.tensor(0.28), 0.28])
def test_gamma_min_may_be_any_real_number(gamma_min):
    model = FourTankModel(dtype=F64)
    G = torch.eye(4, dtype=F64)
    Q, R = model.process_cov(0), model.measurement_cov(1)
    K = Q @ torch.linalg.inv(R + Q)
    assert float(attack_threshold(G, K, gamma_min)) == pytest.approx(0.28 * 5 / 6, rel=1e-6)
