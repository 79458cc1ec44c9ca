"""Mutation-review tests for the tracking and robot papers' attack-aware filters and fusion.

Each test checks :mod:`difffilter.fdi` (``poa``, ``modified_pf``, ``fused``, ``mixture``,
``fusion``, ``mdpf``) against an independent truth: a literal float64 numpy evaluation of
the docstring's equation on a small case, a closed form, or a cross-algorithm identity.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import difffilter as df
from difffilter import fdi
from difffilter.fdi.fused import FusedModifiedPF
from difffilter.fdi.fusion import fuse
from difffilter.noise import Gaussian

F64 = torch.float64


def scalar_model(q: float = 1.0, r: float = 1.0) -> df.LinearGaussianModel:
    """``x_k = x_{k−1} + w``, ``y = x + v``, ``w ~ N(0, q)``, ``v ~ N(0, r)``, ``x_0 ~ N(0, 1)``."""
    one = torch.ones(1, 1, dtype=F64)
    return df.LinearGaussianModel(one, one, q * one, r * one, torch.zeros(1, dtype=F64), one)


# ------------------------------------------------------------------------------- poa.py


def test_weighted_poa_never_exceeds_one_when_all_but_a_negligible_particle_exceed():
    """β = Σ_{‖z^i‖>η} w^i is a sum over a subset of normalised weights, so β ≤ 1 (eq. 14).

    Eight heavy particles exceed η, a ninth of weight e^{−800} relative does not; the float
    sum of the eight softmax weights rounds to 1 + 2.2e-16 here, and β must still be ≤ 1.
    """
    lw = torch.tensor(
        [-0.5545191073679396, 0.19199507185683629, 0.5427713494727768, -2.2187793699300005,
         0.2589845413662202, -1.029702181843019, -0.5007584123764369, 0.27336773842007633,
         -800.0],
        dtype=F64,
    )  # fmt: skip
    z = torch.zeros(9, 1, dtype=F64)
    z[:8] = 2.0  # ‖z‖ = 2 > η = 1 for the first eight
    beta = fdi.probability_of_attack(z, 1.0, lw)
    w = np.exp(lw.numpy() - lw.numpy().max())
    assert float(beta) <= 1.0
    assert math.isclose(float(beta), float(w[:8].sum() / w.sum()), rel_tol=1e-15)


def test_running_attack_rate_switches_to_the_estimate_right_after_warmup():
    """Remark 6: ζ = α₀(N−1)/N for the first ``warmup`` steps only; the zeta for step
    warmup + 1 is p̂ = #alarms/#steps mapped through eqs 53/46 (here p̂ = 1/2 → ζ = 1/2)."""
    n = 10
    rate = fdi.RunningAttackRate(n, alpha0=0.3, warmup=2)
    s = rate.init(())
    assert math.isclose(float(rate.zeta(s)), 0.3 * (n - 1) / n)
    s = rate.update(s, torch.tensor(True))
    assert math.isclose(float(rate.zeta(s)), 0.3 * (n - 1) / n)  # still in the warm-up
    s = rate.update(s, torch.tensor(False))
    assert math.isclose(float(rate.zeta(s)), 0.5, rel_tol=1e-12)  # α = ½·N/(N−1): ζ = ½


def test_running_attack_rate_clips_alpha_at_alpha_max():
    """α = p̂ N/(N−1) is clipped to ``alpha_max``: after only alarms (p̂ = 1) ζ = 0.9·(N−1)/N."""
    n = 20
    rate = fdi.RunningAttackRate(n, alpha0=0.5, warmup=1, alpha_min=0.1, alpha_max=0.9)
    s = rate.update(rate.init((2,)), torch.tensor([True, True]))
    s = rate.update(s, torch.tensor([True, True]))
    expected = torch.full((2,), 0.9 * (n - 1) / n, dtype=F64)
    assert torch.allclose(rate.zeta(s), expected, rtol=1e-14, atol=0)


def test_literal_poa_weighs_by_the_prior_weights():
    """Eq. 7 in linear space: w^i ∝ N(z^i; 0, R) w_{k−1}^i; β = Σ_{‖z^i‖>η} w^i (numpy)."""
    z = np.array([[0.1, 0.0], [1.5, 0.0], [0.0, 2.0]])
    R = np.diag([1.0, 2.0])
    prior = np.array([0.7, 0.2, 0.1])
    dens = np.exp(-0.5 * np.einsum("ni,ij,nj->n", z, np.linalg.inv(R), z))
    dens /= 2 * math.pi * math.sqrt(np.linalg.det(R))
    w = dens * prior / (dens * prior).sum()
    expected = w[np.linalg.norm(z, axis=1) > 1.0].sum()
    got = fdi.literal_probability_of_attack(
        torch.tensor(z), torch.tensor(R), 1.0, torch.tensor(prior)
    )
    assert math.isclose(float(got), expected, rel_tol=1e-12)


def test_poa_detector_for_uses_the_given_measurement_covariance():
    """Theorem 1 on a scalar model: G = 1, K = q/(q + r), ς = |GK − 1| = r/(q + r) and
    η = ς γ_min, with r the ``R`` passed (not the model's); ζ = p_l (eq. 53)."""
    q, r, r_given = 0.5, 1.0, 4.0
    det = fdi.poa_detector_for(
        scalar_model(q, r), gamma_min=2.0, p_l=0.25, num_particles=50, R=[[r_given]]
    )
    assert math.isclose(float(det.eta), 2.0 * r_given / (q + r_given), rel_tol=1e-12)
    assert det.zeta == 0.25
    own = fdi.poa_detector_for(scalar_model(q, r), gamma_min=2.0, p_l=0.25, num_particles=50)
    assert math.isclose(float(own.eta), 2.0 * r / (q + r), rel_tol=1e-12)


def test_detection_threshold_rejects_alpha_exactly_one():
    """Eq. (53) needs p_l N/(N−1) < 1 strictly: p_l = ½, N = 2 gives α = 1, no solution."""
    with pytest.raises(ValueError, match="eq. \\(53\\)"):
        fdi.detection_threshold(0.5, 2)


# ------------------------------------------------------------------------ modified_pf.py


def test_literal_likelihood_keeps_minus_inf_where_only_some_densities_underflow():
    """LiteralGaussianLikelihood: log of the literal density per particle; only a row where
    *every* density underflowed is replaced by zeros. One near particle keeps
    log N(y − x; 0, r) (numpy), the far one (density 0 in float64) is −inf."""
    model = scalar_model(1.0, 2.0)
    particles = torch.tensor([[0.5], [1e3]], dtype=F64)
    y = torch.tensor([0.0], dtype=F64)
    out = fdi.LiteralGaussianLikelihood()(model, y, particles, 1, None)
    assert math.isclose(float(out[0]), -0.5 * 0.25 / 2.0 - 0.5 * math.log(2 * math.pi * 2.0),
                        rel_tol=1e-12)  # fmt: skip
    assert float(out[1]) == -math.inf
    both_far = fdi.LiteralGaussianLikelihood()(model, y, particles + 1e3, 1, None)
    assert torch.equal(both_far, torch.zeros(2, dtype=F64))


def _frozen_start(x0, w0):
    """A particle set ``[1, N, 1]`` with the given (non-uniform) weights at k = 0."""
    from difffilter.particle import ParticleState

    x = torch.tensor(x0, dtype=F64).reshape(1, -1, 1)
    lw = torch.log(torch.tensor(w0, dtype=F64)).reshape(1, -1)
    return ParticleState(x, lw, 0)


def test_modified_pf_poa_uses_the_predictive_weights_without_resampling():
    """Step 2-2: β̃ = Σ_{‖(I − GK)(ỹ − G x^i)‖ > η} w_{k−1}^i with the weights w_{k−1} (eq.
    58 only reduces to 1/N after resampling). With q = 1e-14 the particles do not move and
    K ≈ 0: particles (0, 5) of weights (0.8, 0.2), ỹ = 0, η = 1 give β̃ = 0.2 (not ½)."""
    model = scalar_model(1e-14, 1.0)
    out = fdi.modified_particle_filter(
        model, torch.zeros(1, 1, 1, dtype=F64), num_particles=2,
        detector=fdi.PoADetector(1.0, 0.5), gamma_hat=torch.zeros(1, 1, dtype=F64),
        ess_threshold=0.0, initial_state=_frozen_start([0.0, 5.0], [0.8, 0.2]),
        generator=torch.Generator().manual_seed(0),
    )  # fmt: skip
    assert math.isclose(float(out.detection.scores[0, 0]), 0.2, rel_tol=1e-9)


def plane_model(q: float = 1e-14, r: float = 1.0) -> df.LinearGaussianModel:
    """A 2-d random walk measured directly: ``F = H = I``, ``Q = q I``, ``R = r I``."""
    eye = torch.eye(2, dtype=F64)
    return df.LinearGaussianModel(eye, eye, q * eye, r * eye, torch.zeros(2, dtype=F64), eye)


def _plane_start(points):
    from difffilter.particle import ParticleState

    x = torch.tensor(points, dtype=F64).unsqueeze(0)
    return ParticleState(x, torch.full(x.shape[:-1], -math.log(x.shape[1]), dtype=F64), 0)


def test_modified_pf_alarm_is_strict_at_beta_equal_zeta():
    """Step 2-3: l̂ = [β̃ > ζ] (eq. 46), strictly. Particles (0, 0), (5, 0) of equal weight,
    ỹ = 0, η = 1 (K ≈ 0 as q = 1e-14): one of two exceeds, β̃ = ½ = ζ, so no alarm and no
    compensation (attack = l̂ γ̂ = 0)."""
    out = fdi.modified_particle_filter(
        plane_model(), torch.zeros(1, 1, 2, dtype=F64), num_particles=2,
        detector=fdi.PoADetector(1.0, 0.5), gamma_hat=torch.ones(1, 2, dtype=F64),
        initial_state=_plane_start([[0.0, 0.0], [5.0, 0.0]]),
        generator=torch.Generator().manual_seed(0),
        resample_generator=torch.Generator().manual_seed(1),
    )  # fmt: skip
    assert float(out.detection.scores[0, 0]) == 0.5
    assert not bool(out.detection.alarms[0, 0])
    assert torch.equal(out.attack, torch.zeros(1, 1, 2, dtype=F64))


def test_modified_pf_poa_ignores_unreceived_entries():
    """ModifiedPFWeighting: unreceived entries (``mask``) enter neither the correction nor
    the norm. Particles (0, 0), (0, 5), (5, 0), (0, 0.5), ỹ = (0, 100) with the second entry
    not received, η = 1: only (5, 0) exceeds on the received entry, β̃ = ¼."""
    out = fdi.modified_particle_filter(
        plane_model(), torch.tensor([[[0.0, 100.0]]], dtype=F64),
        mask=torch.tensor([[[True, False]]]), num_particles=4,
        detector=fdi.PoADetector(1.0, 0.7), gamma_hat=torch.zeros(1, 2, dtype=F64),
        initial_state=_plane_start([[0.0, 0.0], [0.0, 5.0], [5.0, 0.0], [0.0, 0.5]]),
        generator=torch.Generator().manual_seed(0),
        resample_generator=torch.Generator().manual_seed(1),
    )  # fmt: skip
    assert float(out.detection.scores[0, 0]) == 0.25


def test_poa_pf_poa_ignores_unreceived_entries():
    """PoAParticleFilter: β = Σ_{‖y − h(x^i)‖ > η} w^i over the received entries only, with
    the posterior weights w^i ∝ N(ỹ₁ − x^i₁; 0, 1) (numpy). Particles (0, 0), (0, 5),
    (1.5, 0), ỹ = (0, 100) with the second entry unreceived, η = 1: only (1.5, 0) exceeds."""
    pts = np.array([[0.0, 0.0], [0.0, 5.0], [1.5, 0.0]])
    out = fdi.particle_filter_poa(
        plane_model(), torch.tensor([[[0.0, 100.0]]], dtype=F64),
        mask=torch.tensor([[[True, False]]]), num_particles=3,
        detector=fdi.PoADetector(1.0, 0.5), initial_state=_plane_start(pts.tolist()),
        generator=torch.Generator().manual_seed(0),
        resample_generator=torch.Generator().manual_seed(1),
    )  # fmt: skip
    w = np.exp(-0.5 * pts[:, 0] ** 2)
    w /= w.sum()
    assert math.isclose(float(out.detection.scores[0, 0]), w[2], rel_tol=1e-6)


def test_modified_pf_feeds_the_attack_estimator_only_alarmed_received_entries():
    """Step 3-0 with a BiasAttackEstimator: only flagged steps update γ̂ (unflagged steps
    only predict from γ_0 = 0, so γ̂ stays exactly 0). With η = 10 no particle exceeds,
    β̃ = 0, no alarm: γ̂ must be 0 although the received innovation is 3."""
    out = fdi.modified_particle_filter(
        plane_model(), torch.tensor([[[3.0, 100.0]]], dtype=F64),
        mask=torch.tensor([[[True, False]]]), num_particles=2,
        detector=fdi.PoADetector(10.0, 0.5), gamma_hat=fdi.BiasAttackEstimator(2, 0.9),
        initial_state=_plane_start([[0.0, 0.0], [0.5, 0.0]]),
        generator=torch.Generator().manual_seed(0),
        resample_generator=torch.Generator().manual_seed(1),
    )  # fmt: skip
    assert not bool(out.detection.alarms[0, 0])
    assert torch.equal(out.extras["gamma_hat"], torch.zeros(1, 1, 2, dtype=F64))


def test_poa_pf_alarm_is_strict_at_beta_equal_zeta():
    """Normal PF + PoA: l̂ = [β > ζ] strictly. R = diag(1, 4), particles (1, 0) and (0, 2)
    at ỹ = 0 have the same likelihood (rᵀR⁻¹r = 1; q = 1e-200 leaves them in place) so equal
    posterior weights, and only
    the second has ‖r‖ = 2 > η = 1.5: β = ½ = ζ, no alarm."""
    eye = torch.eye(2, dtype=F64)
    model = df.LinearGaussianModel(
        eye, eye, 1e-200 * eye, torch.diag(torch.tensor([1.0, 4.0], dtype=F64)),
        torch.zeros(2, dtype=F64), eye,
    )  # fmt: skip
    out = fdi.particle_filter_poa(
        model, torch.zeros(1, 1, 2, dtype=F64), num_particles=2,
        detector=fdi.PoADetector(1.5, 0.5), initial_state=_plane_start([[1.0, 0.0], [0.0, 2.0]]),
        generator=torch.Generator().manual_seed(0),
        resample_generator=torch.Generator().manual_seed(1),
    )  # fmt: skip
    assert float(out.detection.scores[0, 0]) == 0.5
    assert not bool(out.detection.alarms[0, 0])


def test_literal_poa_pf_weighs_by_the_prior_weights_without_resampling():
    """literal=True: β from eq. 7 in linear space, w^i ∝ N(ỹ − x^i; 0, r) w_{k−1}^i (numpy);
    with ess_threshold = 0 the prior weights (0.8, 0.2) are not reset to 1/N."""
    pts, w0 = np.array([0.0, 1.5]), np.array([0.8, 0.2])
    out = fdi.particle_filter_poa(
        scalar_model(1e-14, 1.0), torch.zeros(1, 1, 1, dtype=F64), num_particles=2,
        detector=fdi.PoADetector(1.0, 0.5), literal=True, ess_threshold=0.0,
        initial_state=_frozen_start(pts.tolist(), w0.tolist()),
        generator=torch.Generator().manual_seed(0),
    )  # fmt: skip
    w = np.exp(-0.5 * pts**2) * w0
    assert math.isclose(float(out.detection.scores[0, 0]), w[1] / w.sum(), rel_tol=1e-6)


def test_modified_pf_nonlinear_path_equals_the_linear_path_for_a_linear_h():
    """Cross-algorithm identity: a NonlinearGaussianModel with h(x) = x (G its Jacobian,
    I) must give the linear path's β̃ from (I − GK)(ỹ − h(x^i)) (eqs 36, 58) and the same
    estimates, with the same random numbers. q = r = 1 makes K = ½, so (I − GK) matters."""
    lin = scalar_model(1.0, 1.0)
    one = torch.ones(1, 1, dtype=F64)
    nonlin = df.NonlinearGaussianModel(
        lambda x: x, lambda x: 1.0 * x, one, one, torch.zeros(1, dtype=F64), one
    )
    ys = torch.tensor([[[0.3], [2.5], [-1.0], [4.0], [0.0], [1.2]]], dtype=F64)

    def run(model):
        return fdi.modified_particle_filter(
            model, ys, num_particles=16, detector=fdi.PoADetector(0.8, 0.5),
            gamma_hat=torch.zeros(6, 1, dtype=F64),
            generator=torch.Generator().manual_seed(3),
            resample_generator=torch.Generator().manual_seed(4),
        )  # fmt: skip

    a, b = run(lin), run(nonlin)
    assert torch.allclose(a.detection.scores, b.detection.scores, atol=1e-12)
    assert torch.allclose(a.means, b.means, atol=1e-10)
    assert float(a.detection.scores.std()) > 0  # the case is not degenerate


# ------------------------------------------------------------------------------ fused.py


def _fused_models():
    one = torch.ones(1, 1, dtype=F64)
    scaled = df.LinearGaussianModel(one, 2.0 * one, 0.3 * one, 0.5 * one,
                                    torch.zeros(1, dtype=F64), one)  # fmt: skip
    G = torch.tensor([[1.0, 0.5], [0.0, 1.0]], dtype=F64)
    Q = torch.tensor([[0.3, 0.1], [0.1, 0.2]], dtype=F64)
    R = torch.tensor([[0.5, 0.2], [0.2, 0.4]], dtype=F64)
    eye = torch.eye(2, dtype=F64)
    full = df.LinearGaussianModel(0.9 * eye, G, Q, R, torch.zeros(2, dtype=F64), eye)
    shifted = df.LinearGaussianModel(0.9 * eye, eye, 0.3 * eye, 0.5 * eye,
                                     torch.zeros(2, dtype=F64), eye)  # fmt: skip
    shifted.process_noise = Gaussian(torch.tensor([0.3, -0.2], dtype=F64), 0.3 * eye)
    return {"scaled": scaled, "full": full, "shifted": shifted}


@pytest.mark.parametrize("name", ["scaled", "full", "shifted"])
def test_fused_modified_pf_equals_the_composed_filter_for_general_g_and_r(name):
    """FusedModifiedPF's docstring identity: the same numbers as ``modified_particle_filter``
    with the same generators, here for a square G ≠ I (the fused path must form ỹ − G x),
    for a non-diagonal R, Q and I − GK (the whitened and matrix-detection branches) and
    for a process noise of non-zero mean (the pre-drawn noise horizon keeps its loc)."""
    model = _fused_models()[name]
    B, T, N, dy = 2, 8, 16, model.dim_y
    g = torch.Generator().manual_seed(5)
    ys = torch.randn(B, T, dy, generator=g, dtype=F64)
    ys[:, 3:6] += 3.0  # an attack, so that some steps alarm and compensate
    gamma_hat = torch.full((B, T, dy), 2.5, dtype=F64)
    eta, zeta = 1.0, 0.4
    fused = FusedModifiedPF(model, num_particles=N, eta=eta, zeta=zeta).run(
        ys, gamma_hat, generator=torch.Generator().manual_seed(1),
        resample_generator=torch.Generator().manual_seed(2),
    )  # fmt: skip
    composed = fdi.modified_particle_filter(
        model, ys, num_particles=N, detector=fdi.PoADetector(eta, zeta), gamma_hat=gamma_hat,
        generator=torch.Generator().manual_seed(1),
        resample_generator=torch.Generator().manual_seed(2),
    )  # fmt: skip
    alarms = composed.detection.alarms
    assert bool(alarms.any()) and not bool(alarms.all())
    assert torch.equal(fused.detection.alarms, alarms)
    assert torch.allclose(fused.detection.scores, composed.detection.scores, atol=1e-12)
    assert torch.allclose(fused.means, composed.means, atol=1e-9)


def test_fused_modified_pf_alarm_is_strict_at_beta_equal_zeta():
    """Fused path, step 2-3: l̂ = [β̃ > ζ] strictly (eq. 46). Particles (0, 0), (5, 0) and
    ỹ = 0 with η = 1 (K ≈ 0 as q = 1e-14): β̃ = 1/2 = ζ, no alarm; ζ = 0.49 alarms."""
    x0 = torch.tensor([[[0.0, 0.0], [5.0, 0.0]]], dtype=F64)
    ys, gamma_hat = torch.zeros(1, 1, 2, dtype=F64), torch.ones(1, 1, 2, dtype=F64)
    for zeta, alarm in ((0.5, False), (0.49, True)):
        out = FusedModifiedPF(plane_model(), num_particles=2, eta=1.0, zeta=zeta).run(
            ys, gamma_hat, generator=torch.Generator().manual_seed(0), initial_particles=x0
        )
        assert float(out.detection.scores[0, 0]) == 0.5
        assert bool(out.detection.alarms[0, 0]) is alarm


# ----------------------------------------------------------------------------- fusion.py


def _spd(rng, d, scale=1.0):
    a = rng.standard_normal((d, d))
    return scale * (a @ a.T + 0.5 * np.eye(d))


def _np_ci(m, P, iters=200):
    """Covariance intersection in numpy: ω minimising the convex J(ω) = tr P_f(ω) on [0, 1],
    found by bisection on the sign of J′(ω) = −tr(P_f (P₁⁻¹ − P₂⁻¹) P_f) (the bound where J′
    does not change sign), then P_f = (ω P₁⁻¹ + (1−ω) P₂⁻¹)⁻¹, x̂_f = P_f(ω P₁⁻¹x̂₁ +
    (1−ω) P₂⁻¹x̂₂)."""
    I1, I2 = np.linalg.inv(P[0]), np.linalg.inv(P[1])

    def slope(w):
        Pf = np.linalg.inv(w * I1 + (1 - w) * I2)
        return -np.trace(Pf @ (I1 - I2) @ Pf)

    if slope(0.0) >= 0:
        w = 0.0
    elif slope(1.0) <= 0:
        w = 1.0
    else:
        lo, hi = 0.0, 1.0
        for _ in range(iters):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if slope(mid) < 0 else (lo, mid)
        w = 0.5 * (lo + hi)
    Pf = np.linalg.inv(w * I1 + (1 - w) * I2)
    return Pf @ (w * I1 @ m[0] + (1 - w) * I2 @ m[1]), Pf, w


def _crossing_pair(rng, d):
    """Two SPD covariances, each the better one in some directions (ω strictly inside)."""
    P1 = np.diag([1.0] + [0.1 + 0.1 * i for i in range(d - 1)]) + 0.02 * _spd(rng, d)
    P2 = np.diag([0.05] + [1.0 + 0.2 * i for i in range(d - 1)]) + 0.02 * _spd(rng, d)
    return np.stack([P1, P2])


@pytest.mark.parametrize("d", [2, 4])
def test_covariance_intersection_matches_numpy(d):
    """CI (Julier & Uhlmann) against a numpy ternary search of the convex tr P_f(ω), for the
    by-hand (d ≤ 3) and the torch.linalg (d = 4) routes; the locals are chosen so that the
    minimiser is inside (0, 1)."""
    rng = np.random.default_rng(7)
    m = rng.standard_normal((2, d))
    P = _crossing_pair(rng, d)
    mean_np, cov_np, w_np = _np_ci(m, P)
    assert 0.02 < w_np < 0.98
    mean, cov, omega = fdi.covariance_intersection(torch.tensor(m), torch.tensor(P))
    assert abs(float(omega) - w_np) < 1e-5
    assert np.allclose(cov.numpy(), cov_np, rtol=1e-5, atol=1e-8)
    assert np.allclose(mean.numpy(), mean_np, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("d", [2, 4])
def test_information_fusion_and_fuse_rules_match_numpy(d):
    """Naive fusion P_f = (P₁⁻¹ + P₂⁻¹)⁻¹, x̂_f = P_f(P₁⁻¹x̂₁ + P₂⁻¹x̂₂) (numpy), by both
    routes; ``fuse`` dispatches "naive" to it and "ci" to covariance intersection."""
    rng = np.random.default_rng(11)
    m = rng.standard_normal((2, d))
    P = np.stack([_spd(rng, d), _spd(rng, d, 3.0)])
    I1, I2 = np.linalg.inv(P[0]), np.linalg.inv(P[1])
    cov_np = np.linalg.inv(I1 + I2)
    mean_np = cov_np @ (I1 @ m[0] + I2 @ m[1])
    mt, Pt = torch.tensor(m), torch.tensor(P)
    for mean, cov in (fdi.information_fusion(mt, Pt), fuse(mt, Pt, "naive")):
        assert np.allclose(cov.numpy(), cov_np, rtol=1e-10, atol=1e-12)
        assert np.allclose(mean.numpy(), mean_np, rtol=1e-10, atol=1e-12)
    mean_ci, cov_ci = fuse(mt, Pt, "ci")
    assert not np.allclose(cov_ci.numpy(), cov_np, rtol=1e-3)
    mean_np_ci, cov_np_ci, _ = _np_ci(m, P)
    assert np.allclose(cov_ci.numpy(), cov_np_ci, rtol=1e-5, atol=1e-8)


def test_covariance_intersection_omega_gradient_matches_finite_differences():
    """dω/dθ of the CI minimiser (implicit function theorem, module docstring) against a
    central finite difference of the numpy ternary-search minimiser, for P₁ = P₁⁰ + θ E."""
    rng = np.random.default_rng(3)
    d = 2
    m = rng.standard_normal((2, d))
    P = np.stack([np.diag([1.0, 0.1]), np.diag([0.2, 1.0])])
    E = np.array([[0.3, 0.1], [0.1, 0.2]])
    theta = torch.tensor(0.0, dtype=F64, requires_grad=True)
    Pt = torch.tensor(P) + torch.stack([theta * torch.tensor(E), torch.zeros(d, d, dtype=F64)])
    _, _, omega = fdi.covariance_intersection(torch.tensor(m), Pt)
    (grad,) = torch.autograd.grad(omega, theta)
    h = 1e-5
    plus = _np_ci(m, np.stack([P[0] + h * E, P[1]]))[2]
    minus = _np_ci(m, np.stack([P[0] - h * E, P[1]]))[2]
    fd = (plus - minus) / (2 * h)
    assert 0.05 < float(omega.detach()) < 0.95 and abs(fd) > 1e-2
    assert math.isclose(float(grad), fd, rel_tol=1e-6)


# ---------------------------------------------------------------------------- mixture.py


def _np_normal(r, var):
    return np.exp(-0.5 * r**2 / var) / math.sqrt(2 * math.pi * var)


def test_attack_probability_of_a_bias_deception_matches_numpy():
    """P(l_k = 1 | ỹ) = Σ w^i p p_v(ỹ − ρ − x^i) / Σ w^i [(1−p) p_v(ỹ − x^i) + p p_v(ỹ − ρ −
    x^i)] (numpy, scalar model, r = 0.5), with non-uniform predictive weights."""
    p, rho, r = 0.3, 2.0, 0.5
    x = np.array([0.0, 1.0, 2.5])
    w = np.array([0.5, 0.3, 0.2])
    y = 1.8
    lik = fdi.DeceptionMixtureLikelihood(p, fdi.BiasDeception([rho]))
    got = lik.attack_probability(
        scalar_model(1.0, r), torch.tensor([y], dtype=F64), torch.tensor(x).unsqueeze(-1),
        torch.log(torch.tensor(w)), 1,
    )  # fmt: skip
    att = p * _np_normal(y - rho - x, r)
    expected = (w * att).sum() / (w * ((1 - p) * _np_normal(y - x, r) + att)).sum()
    assert math.isclose(float(got), expected, rel_tol=1e-12)


def test_replacement_density_is_recomputed_after_an_in_place_change_of_y():
    """ReplacementDeception.log_density caches the last packet, keyed on the tensor *and*
    its version: y changed in place must give the new log p_ξ(ỹ), here of ξ ~ N(0, I₂):
    −½‖y‖² − log 2π (numpy)."""
    dens = fdi.ReplacementDeception(Gaussian(torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64)))
    y = torch.tensor([0.5, -1.0], dtype=F64)
    first = float(dens.log_density(y))
    assert math.isclose(first, -0.5 * 1.25 - math.log(2 * math.pi), rel_tol=1e-12)
    y.mul_(3.0)
    assert math.isclose(float(dens.log_density(y)), -0.5 * 11.25 - math.log(2 * math.pi),
                        rel_tol=1e-12)  # fmt: skip


# ------------------------------------------------------------------------------- mdpf.py


def test_information_form_applies_only_to_a_diagonal_measurement_covariance():
    """The information form reads R's diagonal only, so it applies to a time-invariant,
    *diagonal* R: R = [[1, 0.3], [0.3, 1]] must select the covariance form."""
    from difffilter.fdi.mdpf import information_form_applies

    eye = torch.eye(2, dtype=F64)
    R = torch.tensor([[1.0, 0.3], [0.3, 1.0]], dtype=F64)
    full = df.LinearGaussianModel(eye, eye, eye, R, torch.zeros(2, dtype=F64), eye)
    assert not information_form_applies(full)
    assert information_form_applies(plane_model(1.0, 2.0))


def _input_model():
    """dx = du = 2, dy = 3: ``x_k = x_{k−1} + u + w``, ``y = H x + v`` (diagonal R)."""
    eye = torch.eye(2, dtype=F64)
    H = torch.tensor([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]], dtype=F64)
    R = 0.5 * torch.eye(3, dtype=F64)
    return df.LinearGaussianModel(eye, H, 0.1 * eye, R, torch.zeros(2, dtype=F64), eye, B=eye)


def test_adaptive_pf_init_and_wald_threshold_follow_the_attack_dimension():
    """adaptive_particle_init: Sʲ = attack_cov0 · I (docstring); the Wald test on (â, Ŝ) has
    du degrees of freedom, and χ²₂'s upper α-quantile is −2 ln α (closed form; dy = 3 here)."""
    from difffilter.fdi.mdpf import ParticleLayout, adaptive_particle_init

    model = _input_model()
    st = adaptive_particle_init(model, 4, (1,), torch.Generator().manual_seed(0), attack_cov0=3.0)
    S = ParticleLayout(2, 2).unpack(st.particles)[3]
    assert torch.equal(S, torch.full((1, 4, 2, 2), 0.0, dtype=F64) + 3.0 * torch.eye(2, dtype=F64))
    out = fdi.adaptive_particle_filter(
        model, torch.zeros(1, 2, 3, dtype=F64), torch.zeros(1, 2, 2, dtype=F64),
        num_particles=4, false_alarm_rate=0.01, generator=torch.Generator().manual_seed(1),
    )  # fmt: skip
    assert math.isclose(float(out.detection.threshold), -2 * math.log(0.01), rel_tol=1e-6)


def test_mixture_pf_alarm_is_strict_at_a_certain_attack_and_threshold_one():
    """With p = 1 every packet is a deception: P(l_k = 1 | ỹ) = 1 exactly (closed form, the
    clean term has weight 0), and the alarm P > threshold is strict, so threshold = 1 never
    alarms while threshold = 0.99 always does."""
    lik = fdi.DeceptionMixtureLikelihood(1.0, fdi.BiasDeception([0.5]))
    ys = torch.tensor([[[0.3], [1.0], [-0.4]]], dtype=F64)
    for threshold, alarm in ((1.0, False), (0.99, True)):
        out = fdi.mixture_likelihood_particle_filter(
            scalar_model(), ys, num_particles=8, likelihood=lik, threshold=threshold,
            generator=torch.Generator().manual_seed(0),
        )  # fmt: skip
        assert torch.equal(out.detection.scores, torch.ones(1, 3, dtype=F64))
        assert torch.equal(out.detection.alarms, torch.full((1, 3), alarm))
