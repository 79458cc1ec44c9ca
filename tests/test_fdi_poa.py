"""PoA detector (eqs 10–17, 58), thresholds (Theorem 1, eqs 46/53), Remark 6, literal density."""

from __future__ import annotations

import math

import pytest
import torch

from difffilter import fdi
from difffilter.noise import Gaussian

R_PAPER = torch.diag(torch.tensor([1e-3, 1e-3, 0.5e-3, 0.5e-3], dtype=torch.float64))


def test_gain_eq35_identity_measurement_is_q_over_q_plus_r():
    K = fdi.modified_pf_gain(
        torch.eye(4, dtype=torch.float64), 1e-4 * torch.eye(4, dtype=torch.float64), R_PAPER
    )
    assert torch.allclose(
        K, torch.diag(torch.tensor([1 / 11, 1 / 11, 1 / 6, 1 / 6], dtype=torch.float64))
    )


def test_gain_eq35_general_measurement_matrix():
    G = torch.tensor([[1.0, 2.0, 0.0], [0.0, 1.0, -1.0]], dtype=torch.float64)
    Q = torch.tensor([[2.0, 0.3, 0.0], [0.3, 1.0, 0.1], [0.0, 0.1, 0.5]], dtype=torch.float64)
    R = torch.tensor([[0.4, 0.1], [0.1, 0.3]], dtype=torch.float64)
    expected = Q @ G.T @ torch.linalg.inv(R + G @ Q @ G.T)
    assert torch.allclose(fdi.modified_pf_gain(G, Q, R), expected)
    with pytest.raises(ValueError, match="Q must have shape"):
        fdi.modified_pf_gain(G, torch.eye(2), R)
    with pytest.raises(ValueError, match="R must have shape"):
        fdi.modified_pf_gain(G, Q, torch.eye(3))


def test_theorem1_threshold_paper_case():
    G = torch.eye(4, dtype=torch.float64)
    K = fdi.modified_pf_gain(G, 1e-4 * torch.eye(4, dtype=torch.float64), R_PAPER)
    # singular values of G K: 1/11 and 1/6; nearest to 1 is 1/6, so ς = 5/6 and η = 0.28·5/6
    assert math.isclose(float(fdi.attack_threshold_factor(G, K)), 5 / 6, rel_tol=1e-12)
    assert math.isclose(float(fdi.attack_threshold(G, K, 0.28)), 0.2333333333333, rel_tol=1e-9)
    # R × 5: ς = 1 − 1e-4/2.6e-3, the threshold the high-noise report recomputes
    K5 = fdi.modified_pf_gain(G, 1e-4 * torch.eye(4, dtype=torch.float64), 5 * R_PAPER)
    assert math.isclose(
        float(fdi.attack_threshold(G, K5, 0.28)), 0.28 * (1 - 1e-4 / 2.6e-3), rel_tol=1e-9
    )


def test_theorem1_picks_the_singular_value_nearest_to_one():
    G = torch.eye(2, dtype=torch.float64)
    K = torch.tensor(
        [[0.0, 2.0], [0.5, 0.0]], dtype=torch.float64
    )  # singular values 2 and 0.5 (both 0.5 or 1 from 1)
    assert math.isclose(float(fdi.attack_threshold_factor(G, K)), 0.5, rel_tol=1e-12)
    K = torch.tensor([[1.3, 0.0], [0.0, 0.2]], dtype=torch.float64)  # 1.3 is nearer to 1 than 0.2
    assert math.isclose(float(fdi.attack_threshold_factor(G, K)), 0.3, rel_tol=1e-12)
    with pytest.raises(ValueError, match="gamma_min"):
        fdi.attack_threshold(G, K, -1.0)
    with pytest.raises(ValueError, match="K must have shape"):
        fdi.attack_threshold_factor(G, torch.ones(3, 2, dtype=torch.float64))


def test_detection_threshold_eqs_46_and_53():
    assert math.isclose(fdi.detection_threshold(0.5, 100), 0.5)  # α = p_l N/(N−1) → ζ = p_l
    assert math.isclose(fdi.detection_threshold(None, 100, alpha=0.8), 0.8 * 99 / 100)
    with pytest.raises(ValueError, match="eq. \\(53\\)"):
        fdi.detection_threshold(0.6, 2)  # α = 1.2 ≥ 1
    with pytest.raises(ValueError, match="alpha"):
        fdi.detection_threshold(0.5, 100, alpha=1.0)
    with pytest.raises(ValueError, match="num_particles"):
        fdi.detection_threshold(0.5, 1)
    with pytest.raises(ValueError, match="p_l"):
        fdi.detection_threshold(None, 100)


def test_poa_on_a_hand_built_particle_set():
    # ‖z‖ = 0.1, 0.3, 0.25, 0.2828…; with η = 0.26 particles 1 and 3 exceed
    z = torch.tensor([[0.1, 0.0], [0.3, 0.0], [0.0, 0.25], [0.2, 0.2]], dtype=torch.float64)
    w = torch.tensor([0.1, 0.2, 0.3, 0.4], dtype=torch.float64)
    assert math.isclose(float(fdi.probability_of_attack(z, 0.26, torch.log(w))), 0.6, rel_tol=1e-12)
    assert math.isclose(float(fdi.probability_of_attack(z, 0.26)), 0.5)  # weights 1/N (eq. 58)
    # unnormalised log-weights give the same β (softmax inside)
    assert math.isclose(
        float(fdi.probability_of_attack(z, 0.26, torch.log(w) + 7.0)), 0.6, rel_tol=1e-12
    )
    beta, alarm = fdi.PoADetector(0.26, 0.55)(z, torch.log(w))
    assert bool(alarm) and math.isclose(float(beta), 0.6, rel_tol=1e-12)
    beta, alarm = fdi.PoADetector(0.26, 0.5)(z)
    assert not bool(alarm)  # β = ζ exactly is not an alarm
    # batched: [2, 3, N, dy]
    zb = z.expand(2, 3, 4, 2)
    assert fdi.probability_of_attack(zb, 0.26, torch.log(w).expand(2, 3, 4)).shape == (2, 3)


def test_poa_equal_weights_are_counted_exactly():
    # 50 of 100 particles exceed: with equal weights β must be exactly 0.5 (a float sum of
    # fifty 0.01 is not), so that β > ζ = 0.5 is false
    z = torch.zeros(100, 4, dtype=torch.float64)
    z[::2, 0] = 1.0
    lw = torch.full((100,), -math.log(100), dtype=torch.float64)
    assert float(fdi.probability_of_attack(z, 0.5, lw)) == 0.5
    with pytest.raises(ValueError, match="log_weights"):
        fdi.probability_of_attack(z, 0.5, lw[:10])
    with pytest.raises(ValueError, match="eta"):
        fdi.probability_of_attack(z, -0.1)
    with pytest.raises(ValueError, match="zeta"):
        fdi.PoADetector(0.2, 1.0)


def test_poa_never_exceeds_one_when_every_particle_exceeds():
    """A user trial: the softmax's weights summed to 1 + 4.4e-16 where every particle
    exceeded η, and a threshold calibrated at β = 1 read those steps as alarms."""
    g = torch.Generator().manual_seed(0)
    lw = torch.randn(1000, 200, generator=g, dtype=torch.float64)
    assert bool((torch.softmax(lw, -1).sum(-1) > 1).any())  # the round-off is there
    z = torch.ones(1000, 200, 2, dtype=torch.float64)
    beta = fdi.probability_of_attack(z, 0.5, lw)
    assert bool((beta == 1.0).all())
    assert bool((fdi.probability_of_attack(-z, 0.5, lw) == 1.0).all())
    assert bool((fdi.probability_of_attack(0 * z, 0.5, lw) == 0.0).all())


def test_literal_density_matches_log_density_until_it_underflows():
    R = R_PAPER
    noise = Gaussian(torch.zeros(4, dtype=torch.float64), R)
    r = torch.tensor(
        [[0.01, -0.02, 0.0, 0.01], [0.3, 0.3, 0.3, 0.3], [1.0, 1.0, 1.0, 1.0]], dtype=torch.float64
    )
    lit = fdi.literal_gaussian_density(r, R)
    assert torch.allclose(lit[:2], torch.exp(noise.log_prob(r[:2])), rtol=1e-10)
    # rᵀR⁻¹r = 6000 for the last residual: exp(−3000 − …) is below the smallest subnormal
    assert lit[2] == 0 and noise.log_prob(r[2:]).isfinite().all()


def test_literal_poa_is_nan_and_silent_when_every_density_underflows():
    R = R_PAPER
    big = torch.full((5, 4), 1.0, dtype=torch.float64) + 0.01 * torch.arange(
        5.0, dtype=torch.float64
    ).unsqueeze(-1)
    beta = fdi.literal_probability_of_attack(big, R, 0.233)
    assert math.isnan(float(beta))
    assert not bool(beta > 0.5)  # the detector raises no alarm: Fig. 9's "missed large attack"
    # the log-space PoA of the same set detects it
    assert float(fdi.probability_of_attack(big, 0.233, torch.zeros(5, dtype=torch.float64))) == 1.0
    # where nothing underflows both agree
    small = 0.05 * torch.randn(
        6, 4, generator=torch.Generator().manual_seed(0), dtype=torch.float64
    )
    logw = Gaussian(torch.zeros(4, dtype=torch.float64), R).log_prob(small)
    assert math.isclose(
        float(fdi.literal_probability_of_attack(small, R, 0.05)),
        float(fdi.probability_of_attack(small, 0.05, logw)),
        rel_tol=1e-10,
    )


def test_running_attack_rate_remark6():
    rate = fdi.RunningAttackRate(100, alpha0=0.6, warmup=3, alpha_min=0.05, alpha_max=0.95)
    s = rate.init((2,))
    assert torch.allclose(rate.zeta(s), torch.full((2,), 0.6 * 0.99, dtype=torch.float64))
    for alarms in ([True, False], [True, False], [False, False], [True, False]):
        s = rate.update(s, torch.tensor(alarms))
    # after warm-up: p̂ = 3/4 and 0/4 → α = p̂ N/(N−1) clipped to [0.05, 0.95] → ζ = α (N−1)/N
    assert torch.allclose(rate.estimate(s), torch.tensor([0.75, 0.0], dtype=torch.float64))
    assert torch.allclose(rate.zeta(s), torch.tensor([0.75, 0.05 * 0.99], dtype=torch.float64))
    with pytest.raises(ValueError, match="alpha0"):
        fdi.RunningAttackRate(100, alpha0=1.0)
    with pytest.raises(ValueError, match="warmup"):
        fdi.RunningAttackRate(100, warmup=0)


def test_a_residual_on_the_threshold_is_no_exceedance():
    """Eq. (14) counts ‖z‖ > η strictly: z = (3, 4) at η = 5 is a tie, not an attack."""
    z = torch.tensor([[[3.0, 4.0], [0.0, 0.0]]], dtype=torch.float64)
    assert float(fdi.probability_of_attack(z, 5.0)) == 0.0
    assert float(fdi.probability_of_attack(z, 4.999)) == 0.5
