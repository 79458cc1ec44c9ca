"""The modified PF of Table 2 and its parts, the normal PF with PoA, the γ̂ estimator, the
deception mixture likelihood, the gated EKF detectors and the fused benchmark path."""

from __future__ import annotations

import math

import pytest
import torch
from attacked import simulate_attacked

import difffilter as df
from difffilter import fdi
from difffilter.fdi.fused import FusedModifiedPF
from difffilter.loop import open_loop
from difffilter.models.attacks import BiasAttack
from difffilter.models.four_tank import FourTankModel
from difffilter.noise import Gaussian, UniformBox
from difffilter.particle import ModelLikelihood, particle_filter, particle_init

ETA, ZETA = 0.28 * 5 / 6, 0.5


def scalar_model(r: float = 1.0) -> df.LinearGaussianModel:
    one = torch.ones(1, 1, dtype=torch.float64)
    return df.LinearGaussianModel(one, one, one, r * one, torch.zeros(1, dtype=torch.float64), one)


def streams(model, B, N, seed=0):
    return {
        "num_particles": N,
        "initial_state": particle_init(model, N, (B,), torch.Generator().manual_seed(seed)),
        "generator": torch.Generator().manual_seed(seed + 1),
        "resample_generator": torch.Generator().manual_seed(seed + 2),
    }


@pytest.fixture(scope="module")
def plant():
    model = FourTankModel(dtype=torch.float64)
    tr = simulate_attacked(
        model,
        BiasAttack((0.5,) * 4),
        4,
        30,
        plant_generator=torch.Generator().manual_seed(10),
        attack_generator=torch.Generator().manual_seed(11),
    )
    return model, tr


# ------------------------------------------------------------------------------ pieces


def test_kalman_corrected_particles_eq36_and_residuals_eq58():
    G = torch.eye(2, dtype=torch.float64)
    K = torch.diag(torch.tensor([0.5, 0.25], dtype=torch.float64))
    x = torch.tensor([[[1.0, 2.0], [0.0, 0.0]]], dtype=torch.float64)  # [1, N=2, 2]
    y = torch.tensor([[3.0, 6.0]], dtype=torch.float64)
    xp = fdi.kalman_corrected_particles(x, y, G, K)
    assert torch.allclose(xp[0, 0], torch.tensor([2.0, 3.0], dtype=torch.float64))  # x + K(y − x)
    z = fdi.corrected_residuals(x, y, G, K)
    assert torch.allclose(z, y.unsqueeze(-2) - xp)
    assert torch.allclose(
        z[0, 0], torch.tensor([1.0, 3.0], dtype=torch.float64)
    )  # (I − GK)(y − Gx)


def test_eq59_weights_on_a_hand_case():
    model = scalar_model(1.0)
    x = torch.tensor([[[0.0], [1.0], [2.0]]], dtype=torch.float64)  # [B=1, N=3, 1]
    y = torch.tensor([[3.0]], dtype=torch.float64)
    lik = fdi.AttackCompensatedLikelihood(
        torch.tensor([True]), torch.tensor([[2.0]], dtype=torch.float64)
    )
    ll = lik(model, y, x, 1, None)
    # ỹ − l̂γ̂ = 1: residuals 1, 0, −1 → N(·; 0, 1) ∝ e^{−1/2}, 1, e^{−1/2}
    prior = torch.tensor([[0.2, 0.3, 0.5]], dtype=torch.float64)
    log_w, _ = fdi.reweight(torch.log(prior), ll)
    unnorm = prior * torch.tensor([math.exp(-0.5), 1.0, math.exp(-0.5)], dtype=torch.float64)
    assert torch.allclose(torch.exp(log_w), unnorm / unnorm.sum())
    # l̂ = 0: the measurement is used as received
    lik0 = fdi.AttackCompensatedLikelihood(
        torch.tensor([False]), torch.tensor([[2.0]], dtype=torch.float64)
    )
    assert torch.allclose(lik0(model, y, x, 1, None), ModelLikelihood()(model, y, x, 1, None))


def test_modified_pf_equals_attack_free_pf_when_every_attack_is_detected(plant):
    """With l̂ = l and γ̂ = γ, eq. (59) gives the attack-free weights: under common random
    numbers the modified PF reproduces the attack-free normal PF exactly (eqs 55–57)."""
    model, tr = plant
    big = torch.ones_like(tr.gammas)  # ‖γ‖ = 2 ≫ ‖γ‖_min at every attacked step
    y_recv = tr.y_true + tr.flags.unsqueeze(-1) * big
    det = fdi.PoADetector(ETA, ZETA)
    mod = fdi.modified_particle_filter(
        model, y_recv, detector=det, gamma_hat=big, **streams(model, 4, 50)
    )
    free = fdi.particle_filter_poa(model, tr.y_true, detector=det, **streams(model, 4, 50))
    assert torch.equal(mod.alarms, tr.flags)
    assert torch.allclose(mod.means, free.means, atol=1e-9)
    assert not bool(free.alarms.any())
    # the normal PF on the attacked data is biased
    att = fdi.particle_filter_poa(model, y_recv, detector=det, **streams(model, 4, 50))
    assert (att.means - free.means).abs().max() > 0.05


def test_modified_pf_online_steps_compose_to_the_filter(plant):
    model, tr = plant
    det = fdi.PoADetector(ETA, ZETA)
    res = fdi.modified_particle_filter(
        model, tr.y_recv, detector=det, gamma_hat=tr.gammas, **streams(model, 4, 40)
    )
    kw = streams(model, 4, 40)
    state = kw.pop("initial_state")
    kw.pop("num_particles")
    weighting = fdi.ModifiedPFWeighting(det, tr.gammas)
    K = fdi.modified_pf_gain(model.G, model.process_cov(0), model.measurement_cov(1))
    for t in range(5):
        state, out = df.particle_step(
            model, state, tr.y_recv[:, t], likelihood=weighting, ess_threshold=1.0, **kw
        )
        # eq. (58) by hand: the fraction of Kalman-corrected residuals above η (weights 1/N after resampling)
        z = tr.y_recv[:, t].unsqueeze(-2) - fdi.kalman_corrected_particles(
            state.particles, tr.y_recv[:, t], model.G, K
        )
        beta, alarm = out.extras["beta"], out.extras["alarm"]  # the weighting's record
        assert torch.allclose(beta, (z.norm(dim=-1) > ETA).double().mean(-1))
        assert torch.allclose(out.mean, res.means[:, t]) and torch.equal(alarm, res.alarms[:, t])
    assert res.scores.shape == res.alarms.shape == (4, 30) and res.extras["gamma_hat"].shape == (
        4,
        30,
        4,
    )


def test_modified_pf_rejects_bad_arguments(plant):
    model, tr = plant
    with pytest.raises(ValueError, match="gamma_hat"):
        fdi.modified_particle_filter(
            model,
            tr.y_recv,
            num_particles=10,
            detector=fdi.PoADetector(ETA, ZETA),
            gamma_hat=tr.gammas[:, :5],
        )
    with pytest.raises(ValueError, match="detector"):
        fdi.modified_particle_filter(
            model, tr.y_recv, num_particles=10, detector=0.5, gamma_hat=tr.gammas
        )
    with pytest.raises(ValueError, match="ys"):
        fdi.modified_particle_filter(
            model,
            tr.y_recv[..., :2],
            num_particles=10,
            detector=fdi.PoADetector(ETA, ZETA),
            gamma_hat=tr.gammas,
        )


def test_normal_pf_poa_uses_the_posterior_weights(plant):
    model, tr = plant
    det = fdi.PoADetector(ETA, ZETA)
    res = fdi.particle_filter_poa(
        model,
        tr.y_recv,
        detector=det,
        ess_threshold=0.0,
        return_particles=True,
        **streams(model, 4, 30),
    )
    particles, log_weights = res.extras["particles"], res.extras["log_weights"]
    z = tr.y_recv.unsqueeze(-2) - particles  # G = I
    beta = (torch.softmax(log_weights, -1) * (z.norm(dim=-1) > ETA)).sum(-1)
    assert torch.allclose(res.scores, beta)
    assert torch.equal(res.alarms, beta > ZETA)
    # without resampling the predictive weights are the previous posterior's
    assert torch.allclose(res.extras["prior_log_weights"][:, 1:], log_weights[:, :-1])


def test_literal_normal_pf_misses_what_the_log_space_pf_detects():
    model = FourTankModel(dtype=torch.float64)
    tr = simulate_attacked(
        model,
        BiasAttack((2.0,) * 4),
        3,
        25,
        plant_generator=torch.Generator().manual_seed(0),
        attack_generator=torch.Generator().manual_seed(1),
    )
    det = fdi.PoADetector(ETA, ZETA)
    log = fdi.particle_filter_poa(model, tr.y_recv, detector=det, **streams(model, 3, 50))
    lit = fdi.particle_filter_poa(
        model, tr.y_recv, detector=det, literal=True, **streams(model, 3, 50)
    )
    large = tr.flags & (tr.gammas.norm(dim=-1) > 2.0)  # rᵀR⁻¹r ≳ 6e3: every density underflows
    assert bool(large.any())
    assert bool(log.alarms[large].all())
    assert bool(lit.scores[large].isnan().all()) and not bool(lit.alarms[large].any())
    assert bool(lit.means.isfinite().all())  # the guard keeps the filter running
    with pytest.raises(ValueError, match="literal"):
        fdi.particle_filter_poa(
            model,
            tr.y_recv,
            detector=det,
            literal=True,
            likelihood=ModelLikelihood(),
            num_particles=10,
        )


# ------------------------------------------------------------------------- γ̂ estimator


def test_bias_attack_estimator_names_residuals_of_another_dtype():
    """A float32 estimator fed float64 residuals, and a float64 one fed float32: refused by
    name, with the constructor's dtype to use (torch's "expected scalar type Float but found
    Double" had named neither; the other way round γ̂ came back float64, silently)."""
    for own, other in ((torch.float32, torch.float64), (torch.float64, torch.float32)):
        est = fdi.BiasAttackEstimator(2, 0.9, dtype=own)
        state = est.init((1,))
        r, S = torch.zeros(1, 2, dtype=other), torch.eye(2, dtype=other)
        with pytest.raises(ValueError, match=rf"residual is {other} .* dtype={other}"):
            est.step(state, r, S, torch.ones(1, dtype=torch.bool))
        _, g_hat, _ = est.step(state, r.to(own), S.to(own), torch.ones(1, dtype=torch.bool))
        assert g_hat.dtype == own


def test_bias_attack_estimator_tracks_eq4_from_flagged_residuals():
    attack = BiasAttack((0.5, -0.3), tau=0.9)
    gammas = attack.values(40).unsqueeze(0)  # [1, T, 2]
    est = fdi.BiasAttackEstimator(2, 0.9)
    state = est.init((1,))
    cov = 1e-6 * torch.eye(2, dtype=torch.float64)
    flags = torch.zeros(40, dtype=torch.bool)
    flags[5::2] = True
    out = []
    for t in range(40):
        state, g_hat, g_cov = est.step(state, gammas[:, t], cov, flags[t : t + 1])
        out.append(g_hat)
    g_hat = torch.stack(out, 1)
    assert torch.allclose(
        g_hat[:, :5], torch.zeros(1, 5, 2, dtype=torch.float64)
    )  # nothing flagged yet: γ̂ = 0
    assert (
        g_hat[:, 10:] - gammas[:, 10:]
    ).abs().max() < 1e-2  # γ̄ identified, also on unflagged steps
    assert g_cov.shape == (1, 2, 2)
    with pytest.raises(ValueError, match="tau"):
        fdi.BiasAttackEstimator(2, 1.5)
    with pytest.raises(ValueError, match="residual"):
        est.step(state, torch.zeros(1, 3, dtype=torch.float64), cov, flags[:1])


def test_modified_pf_with_estimated_gamma_runs_and_reports_estimates(plant):
    model, tr = plant
    res = fdi.modified_particle_filter(
        model,
        tr.y_recv,
        detector=fdi.PoADetector(ETA, ZETA),
        gamma_hat=fdi.BiasAttackEstimator(4, 0.9),
        **streams(model, 4, 40),
    )
    late = tr.flags & res.alarms
    late[:, :15] = False
    assert (res.extras["gamma_hat"][late] - tr.gammas[late]).abs().mean() < 0.05


def test_remark6_running_rate_drives_zeta(plant):
    model, tr = plant
    res = fdi.modified_particle_filter(
        model,
        tr.y_recv,
        detector=fdi.PoADetector(ETA, ZETA),
        gamma_hat=tr.gammas,
        attack_rate=fdi.RunningAttackRate(40, warmup=5),
        **streams(model, 4, 40),
    )
    assert torch.allclose(
        res.detection.threshold[:, :5], torch.full((4, 5), 0.5 * 39 / 40, dtype=torch.float64)
    )
    p_hat = res.alarms[:, :-1].double().mean(-1)
    assert torch.allclose(res.extras["attack_rate"], res.alarms.double().mean(-1))
    assert torch.allclose(
        res.detection.threshold[:, -1], (p_hat * 40 / 39).clamp(0.05, 0.95) * 39 / 40
    )


# -------------------------------------------------------------------- mixture likelihood


def test_deception_mixture_likelihood_hand_case():
    model = scalar_model(1.0)
    x = torch.zeros(1, 1, 1, dtype=torch.float64)
    y = torch.tensor([[1.0]], dtype=torch.float64)
    n = lambda v: math.exp(-0.5 * v * v) / math.sqrt(2 * math.pi)  # noqa: E731
    lik = fdi.DeceptionMixtureLikelihood(
        0.2, fdi.BiasDeception(torch.tensor([1.0], dtype=torch.float64))
    )
    assert math.isclose(
        float(lik(model, y, x, 1, None)), math.log(0.8 * n(1.0) + 0.2 * n(0.0)), rel_tol=1e-12
    )
    box = UniformBox(
        torch.tensor([-5.0], dtype=torch.float64), torch.tensor([5.0], dtype=torch.float64)
    )
    rep = fdi.DeceptionMixtureLikelihood(0.2, fdi.ReplacementDeception(box))
    assert math.isclose(
        float(rep(model, y, x, 1, None)), math.log(0.8 * n(1.0) + 0.2 / 10.0), rel_tol=1e-12
    )
    # P(attacked | y) with one particle = p p_a / [(1 − p) p_v + p p_a]
    post = lik.attack_probability(model, y, x, torch.zeros(1, 1, dtype=torch.float64), 1)
    assert math.isclose(float(post), 0.2 * n(0.0) / (0.8 * n(1.0) + 0.2 * n(0.0)), rel_tol=1e-12)
    # p = 0 is the model's likelihood
    plain = fdi.DeceptionMixtureLikelihood(
        0.0, fdi.BiasDeception(torch.tensor([1.0], dtype=torch.float64))
    )
    assert torch.allclose(plain(model, y, x, 1, None), ModelLikelihood()(model, y, x, 1, None))
    with pytest.raises(ValueError, match="attack_probability"):
        fdi.DeceptionMixtureLikelihood(1.2, fdi.BiasDeception([1.0]))


def test_mixture_likelihood_plugs_into_the_particle_filter(plant):
    model, tr = plant
    lik = fdi.DeceptionMixtureLikelihood(
        0.5, fdi.BiasDeception(torch.full((4,), 0.5, dtype=torch.float64))
    )
    res = particle_filter(model, tr.y_recv, likelihood=lik, **streams(model, 4, 50))
    plain = particle_filter(model, tr.y_recv, **streams(model, 4, 50))
    late = slice(15, None)  # once γ_k ≈ γ̄ the mixture explains the attacked packets
    err_mix = (res.means[:, late] - tr.x[:, late]).square().mean()
    err_plain = (plain.means[:, late] - tr.x[:, late]).square().mean()
    assert err_mix < err_plain


# ----------------------------------------------------------------------- gated detectors


@pytest.mark.parametrize("window", [1, 3])
def test_chi_square_online_step_equals_offline_detect(window):
    det = fdi.ChiSquareDetector(2, 0.05, window=window)
    r = torch.randn(3, 12, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    S = torch.eye(2, dtype=torch.float64).expand(3, 12, 2, 2)
    scores, alarms = det.detect(r, S)
    g = fdi.normalized_innovation_squared(r, S)
    state = det.init((3,))
    for t in range(12):
        state, s, a = det.step(state, g[:, t])
        assert torch.allclose(s, scores[:, t]) and torch.equal(a, alarms[:, t])


def test_cusum_online_step_equals_offline_run():
    det = fdi.CusumDetector(3.0, threshold=4.0)
    g = 6 * torch.rand(3, 20, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    stats, alarms = det.run(g)
    state = det.init((3,))
    for t in range(20):
        state, s, a = det.step(state, g[:, t])
        assert torch.allclose(s, stats[:, t]) and torch.equal(a, alarms[:, t])


def test_gated_ekf_drops_alarmed_measurements(plant):
    model, tr = plant
    y = tr.y_true.clone()
    y[:, 10] += 5.0  # one huge injected packet
    det = fdi.ChiSquareDetector(4, 1e-9)  # (almost) no false alarms
    gated = fdi.gated_extended_kalman_filter(model, y, detector=det)
    plain = df.extended_kalman_filter(model, tr.y_true)
    assert bool(gated.alarms[:, 10].all()) and int(gated.alarms.sum()) == 4
    assert torch.allclose(gated.means[:, :10], plain.means[:, :10])
    # at the alarm the estimate is the prediction: the update is skipped
    pred = model.transition(gated.means[:, 9], None, 9)
    assert torch.allclose(gated.means[:, 10], pred)
    with pytest.raises(ValueError, match="detector"):
        fdi.gated_extended_kalman_filter(model, y, detector=fdi.PoADetector(0.2, 0.5))


# ------------------------------------------------------------------------- fused path


@pytest.mark.parametrize(
    "B, N", [(2, 50), (21, 100)]
)  # searchsorted and offspring-count resampling
def test_fused_modified_pf_equals_the_composed_filter(B, N):
    model = FourTankModel(dtype=torch.float64)
    tr = simulate_attacked(
        model,
        BiasAttack((0.5,) * 4),
        B,
        25,
        plant_generator=torch.Generator().manual_seed(3),
        attack_generator=torch.Generator().manual_seed(4),
    )
    det = fdi.PoADetector(ETA, ZETA)
    ref = fdi.modified_particle_filter(
        model, tr.y_recv, num_particles=N, detector=det, gamma_hat=tr.gammas,
        generator=torch.Generator().manual_seed(5), resample_generator=torch.Generator().manual_seed(6),
    )  # fmt: skip
    out = fdi.modified_particle_filter(
        model, tr.y_recv, num_particles=N, detector=det, gamma_hat=tr.gammas,
        generator=torch.Generator().manual_seed(5), resample_generator=torch.Generator().manual_seed(6),
        fused=True,
    )  # fmt: skip
    assert out.covs is None and torch.equal(out.attack, ref.attack)
    assert torch.equal(out.alarms, ref.alarms)
    assert torch.equal(out.scores, ref.scores)
    assert torch.allclose(out.means, ref.means, atol=1e-10)


def _fused_and_steps(model, ys, gamma_hat, detector, n):
    """The fused modified PF's whole-sequence path and its composed steps (a carry given),
    from identically seeded generators."""
    from difffilter.estimator import Generators
    from difffilter.loop import open_loop

    def gens():
        return Generators(*(torch.Generator().manual_seed(i) for i in range(3)))

    est = fdi.ModifiedParticleFilter(n, detector, gamma_hat, fused=True)
    fused = open_loop(est, model, ys, generator=gens())
    steps = open_loop(est, model, ys, carry=est.init(model, ys.shape[:-2], gens()))
    return fused, steps


def test_the_fused_modified_pf_alarms_as_its_steps_where_beta_meets_zeta():
    """β̃ = 100/200 against ζ = 0.499999999: the fused path compared the int64 count with ζN
    in float32 (99.9999998 read as 100: no alarm where the steps alarm), and the runs then
    parted (29 alarms, means 0.34 apart). And ζ of eq. (53) is p_l itself (0.5 at N = 200
    came out an ulp below: β = p_l alarmed)."""
    assert fdi.detection_threshold(0.5, 200) == 0.5 and fdi.detection_threshold(0.5, 500) == 0.5
    model = FourTankModel(dtype=torch.float64)
    g = torch.Generator().manual_seed(0)
    ys = model.initial.mean + 0.03 * torch.randn(8, 30, 4, dtype=torch.float64, generator=g)
    gamma_hat = torch.full((8, 30, 4), 0.3, dtype=torch.float64)
    fused, steps = _fused_and_steps(model, ys, gamma_hat, fdi.PoADetector(0.175, 0.499999999), 200)
    assert bool((steps.detection.scores == 0.5).any())  # the tie is met
    assert torch.equal(fused.detection.alarms, steps.detection.alarms)
    torch.testing.assert_close(fused.means, steps.means, rtol=0, atol=1e-10)


def test_the_fused_modified_pf_steps_where_its_assumptions_fail():
    """A measurement noise other than N(0, R) (an offset; the fused weights are written for
    eq. (59)'s), γ̂ of one row for every run, runs of two batch dimensions: the same numbers
    as the steps (the noise gave other weights, means 4.6 apart; the others raised)."""
    model = FourTankModel(dtype=torch.float64)
    g = torch.Generator().manual_seed(1)
    ys = model.initial.mean + 0.03 * torch.randn(3, 10, 4, dtype=torch.float64, generator=g)
    det = fdi.PoADetector(0.2, 0.5)
    gamma_rows = torch.full((10, 4), 0.3, dtype=torch.float64)
    fused, steps = _fused_and_steps(model, ys, gamma_rows, det, 50)
    torch.testing.assert_close(fused.means, steps.means, rtol=0, atol=1e-10)
    shifted = FourTankModel(dtype=torch.float64)
    cov = shifted.measurement_noise.cov
    shifted.measurement_noise = Gaussian(torch.full((4,), 0.05, dtype=torch.float64), cov)
    fused, steps = _fused_and_steps(shifted, ys, gamma_rows.expand(3, 10, 4), det, 50)
    assert fused.covs is not None  # stepped
    torch.testing.assert_close(fused.means, steps.means, rtol=0, atol=0)
    fused, steps = _fused_and_steps(model, ys.expand(2, 3, 10, 4), gamma_rows, det, 50)
    assert fused.means.shape == (2, 3, 10, 4)
    torch.testing.assert_close(fused.means, steps.means, rtol=0, atol=0)


def test_fused_rejects_bad_input():
    model = FourTankModel(dtype=torch.float64)
    with pytest.raises(ValueError, match="zeta"):
        FusedModifiedPF(model, num_particles=10, eta=0.2, zeta=1.0)
    pf = FusedModifiedPF(model, num_particles=10, eta=0.2, zeta=0.5)
    with pytest.raises(ValueError, match="gamma_hat"):
        pf.run(torch.zeros(1, 5, 4, dtype=torch.float64), torch.zeros(1, 4, 4, dtype=torch.float64))
    y = torch.zeros(1, 5, 4, dtype=torch.float64)
    with pytest.raises(ValueError, match="fused=True does not support mask"):
        fdi.modified_particle_filter(
            model, y, mask=torch.ones_like(y, dtype=torch.bool), num_particles=10,
            detector=fdi.PoADetector(0.2, 0.5), gamma_hat=y, fused=True,
        )  # fmt: skip


class _AngleModel(df.LinearGaussianModel):
    """The scalar random walk measured as an angle: residuals wrapped into (−π, π]."""

    def measurement_residual(self, y, y_hat):
        return (
            torch.remainder(super().measurement_residual(y, y_hat) + math.pi, 2 * math.pi) - math.pi
        )


def test_the_probability_of_attack_reads_the_models_wrapped_residuals():
    """An angle measured 2π away is the same angle: the PoA (eq. 17) and the literal
    likelihood see the residual the model defines (once the raw difference, ~2π: every
    particle 'exceeded η' without any attack)."""
    one = torch.ones(1, 1, dtype=torch.float64)
    model = _AngleModel(one, one, 1e-4 * one, 1e-2 * one, torch.zeros(1, dtype=torch.float64),
                        1e-4 * one)  # fmt: skip
    _, ys, _ = model.simulate(6, (3,), generator=torch.Generator().manual_seed(0))
    det = fdi.PoADetector(0.5, 0.5)
    for literal in (False, True):
        plain = fdi.particle_filter_poa(
            model, ys, detector=det, literal=literal, **streams(model, 3, 40)
        )
        turned = fdi.particle_filter_poa(model, ys + 2 * math.pi, detector=det, literal=literal,
                                         **streams(model, 3, 40))  # fmt: skip
        torch.testing.assert_close(turned.detection.scores, plain.detection.scores)
        assert not turned.alarms.any()


def test_corrected_residuals_are_the_measurement_minus_the_corrected_particles():
    """z̃ = ỹ − G x̃⁺ (eqs. 36 and 58) with a G K that is not symmetric (every other case's
    is, so a dropped transpose went unseen)."""
    from difffilter.fdi.modified_pf import corrected_residuals, kalman_corrected_particles

    g = torch.Generator().manual_seed(0)
    G = torch.randn(3, 2, generator=g, dtype=torch.float64)
    K = torch.randn(2, 3, generator=g, dtype=torch.float64)
    x = torch.randn(5, 2, generator=g, dtype=torch.float64)
    y = torch.randn(3, generator=g, dtype=torch.float64)
    direct = y - kalman_corrected_particles(x, y, G, K) @ G.T
    torch.testing.assert_close(corrected_residuals(x, y, G, K), direct, rtol=0, atol=1e-12)


def test_the_bias_estimator_of_a_modified_pf_hands_out_the_measurements_dtype():
    """A trial: a float32 model with the default (float64) BiasAttackEstimator recorded
    float64 attacks beside float32 means, and a float32 estimator on a float64 model failed
    in a raw matmul. The estimator runs in its own dtype; γ̂ comes in the model's."""
    from difffilter.loop import open_loop

    def model(dt):
        return df.LinearGaussianModel(torch.tensor([[1.0, 0.1], [-0.05, 0.95]], dtype=dt),
                                      torch.eye(2, dtype=dt), 0.02 * torch.eye(2, dtype=dt),
                                      0.04 * torch.eye(2, dtype=dt), torch.zeros(2, dtype=dt),
                                      torch.eye(2, dtype=dt))  # fmt: skip

    ys = torch.randn(2, 8, 2, generator=torch.Generator().manual_seed(0))
    for model_dtype, est_dtype in ((torch.float32, torch.float64), (torch.float64, torch.float32)):
        pf = fdi.ModifiedParticleFilter(32, fdi.PoADetector(0.5, 0.5),
                                        fdi.BiasAttackEstimator(2, 0.9, dtype=est_dtype))  # fmt: skip
        out = open_loop(pf, model(model_dtype), ys.to(model_dtype),
                        generator=torch.Generator().manual_seed(1))  # fmt: skip
        assert out.means.dtype == out.attack.dtype == model_dtype
        assert bool(out.attack.isfinite().all())


# ------------------------------------------ settings assigned after construction (a trial)


def _mixture_last(p, assign=None, owner=None):
    """The last step's (mean, score) of a ``MixtureParticleFilter`` at attack probability
    ``p`` whose carry, after one step, goes on with ``assign(likelihood)`` applied or under
    ``owner``."""
    model = scalar_model(0.1)
    ys = torch.randn(5, 1, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    bias = lambda: fdi.BiasDeception(torch.tensor([2.0], dtype=torch.float64))  # noqa: E731
    lik = fdi.DeceptionMixtureLikelihood(p, bias())
    pf = fdi.MixtureParticleFilter(100, lik)
    carry = pf.init(model, generator=torch.Generator().manual_seed(2))
    carry, _ = pf.step(carry, ys[0])
    if assign is not None:
        assign(lik)
    pf = owner(bias()) if owner is not None else pf
    for k in range(1, 5):
        carry, out = pf.step(carry, ys[k])
    return torch.cat([out.mean, out.score.reshape(1)])


def test_a_mixture_attack_probability_assigned_is_the_one_weighed_with():
    # log p and log(1 − p) were made once at __init__: likelihood.p = 0.5 had weighed with
    # p = 0.1 bit for bit (and 1.5 was taken). Truth: a filter built with the new p
    # stepping the very same carry (same particles and generator states).
    for new in (0.5, 0.0, 1.0):
        assigned = _mixture_last(0.1, lambda lik, new=new: setattr(lik, "p", new))
        built = _mixture_last(0.1, owner=lambda attack, new=new: fdi.MixtureParticleFilter(
            100, fdi.DeceptionMixtureLikelihood(new, attack)))  # fmt: skip
        assert torch.equal(assigned, built)
        assert (assigned - _mixture_last(0.1)).abs().max() > 1e-3
    lik = fdi.DeceptionMixtureLikelihood(0.1, fdi.BiasDeception([1.0]))
    for bad in (1.5, -0.1, float("nan")):
        with pytest.raises(ValueError, match=r"attack_probability must lie in \[0, 1\]"):
            lik.p = bad
    assert lik.p == 0.1


def _modified_pf_last(pf, T=8):
    model = df.LinearGaussianModel(
        torch.tensor([[1.0, 0.1], [-0.05, 0.95]], dtype=torch.float64),
        torch.eye(2, dtype=torch.float64), 0.02 * torch.eye(2, dtype=torch.float64),
        0.04 * torch.eye(2, dtype=torch.float64), torch.zeros(2, dtype=torch.float64),
        torch.eye(2, dtype=torch.float64),
    )  # fmt: skip
    ys = 0.2 * torch.randn(T, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    ys[4:, 0] += 1.5  # a bias of 1.5 on sensor 0 from step 4
    carry = pf.init(model, generator=torch.Generator().manual_seed(1))
    for k in range(T):
        carry, out = pf.step(carry, ys[k])
    run = open_loop(pf, model, ys, generator=torch.Generator().manual_seed(1))
    return torch.cat([out.mean, out.attack, run.means[-1], run.attack[-1]]), (model, ys)


def test_a_modified_pf_gamma_hat_or_detector_assigned_is_the_one_used():
    # pf.gamma_hat = table was kept beside the weighting's copy, which the steps read: the
    # new table was never used (attack 0 where it says 1.5). Truth: the filter built with it.
    old, new = torch.zeros(8, 2, dtype=torch.float64), torch.zeros(8, 2, dtype=torch.float64)
    new[:, 0] = 1.5
    pf = fdi.ModifiedParticleFilter(64, fdi.PoADetector(0.5, 0.5), old)
    pf.gamma_hat = new
    assigned, _ = _modified_pf_last(pf)
    built, _ = _modified_pf_last(fdi.ModifiedParticleFilter(64, fdi.PoADetector(0.5, 0.5), new))
    assert torch.equal(assigned, built) and assigned[2] == 1.5 and pf.likelihood.gamma_hat is new
    pf.detector = fdi.PoADetector(0.3, 0.2)
    assigned, (model, ys) = _modified_pf_last(pf)
    built, _ = _modified_pf_last(fdi.ModifiedParticleFilter(64, fdi.PoADetector(0.3, 0.2), new))
    assert torch.equal(assigned, built)
    # refused with __init__'s words; a γ̂ estimator assigned under a carry of a table: its
    # next step (lean or not) names the carry's missing state, not a raw AttributeError
    with pytest.raises(ValueError, match=r"gamma_hat must be a tensor \[..., T, dy\]"):
        pf.gamma_hat = torch.zeros(2)
    with pytest.raises(ValueError, match="detector must be a PoADetector"):
        pf.detector = "poa"
    with pytest.raises(ValueError, match=r"fused=True does not support gamma_hat \(an estimator"):
        fdi.ModifiedParticleFilter(8, pf.detector, new, fused=True).gamma_hat = (
            fdi.BiasAttackEstimator(2, 0.9))  # fmt: skip
    carry, _ = pf.step(pf.init(model, generator=torch.Generator().manual_seed(1)), ys[0])
    pf.gamma_hat = fdi.BiasAttackEstimator(2, 0.9)
    with pytest.raises(ValueError, match="carry.aux: the carry comes from a run without a Bias"):
        pf.step(carry, ys[1])
