"""Hand checks of the RRP tracking code against the paper's equations (Song, Wang, Wang & Shan,
"Particle filtering ... under Round-Robin protocol subject to randomly occurring deception
attacks"): each library call on a tiny hand-made case against numpy written from the paper."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from difffilter.fdi import (
    DeceptionMixtureLikelihood,
    ReplacementDeception,
    mixture_likelihood_particle_filter,
)
from difffilter.models.tracking import PerSensorDeception, TrackingModel, TrackingScenario
from difffilter.noise import UniformBox
from difffilter.particle import ParticleState

LOW, HIGH = (-10.0, -math.pi / 2), (80.0, math.pi / 2)
S1, S2, KAPPA = (4.0, (math.pi / 180) ** 2), (25.0, (math.pi / 90) ** 2), 0.2


def _log_normal(v, var):
    return -0.5 * v * v / var - 0.5 * np.log(2 * np.pi * var)


def _log_glint(r, b):
    """Eq. (19): log[(1 − κ) N(ν; 0, Σ1) + κ N(ν; 0, Σ2)], diagonal Σ (log space: no underflow)."""
    c1 = np.log(1 - KAPPA) + _log_normal(r, S1[0]) + _log_normal(b, S1[1])
    c2 = np.log(KAPPA) + _log_normal(r, S2[0]) + _log_normal(b, S2[1])
    return np.logaddexp(c1, c2)


def _paper_log_likelihood(y, x, sensor, eta):
    """Eq. (14): log[(1 − η̄) p_ν(ỹ − h^γ(x)) + η̄ p_ξ(ỹ)], h of eq. (18), p_ξ uniform on the box."""
    sz, sp = sensor
    rng = np.hypot(x[:, 0] - sz, x[:, 2] - sp)
    brg = np.arctan2(x[:, 2] - sp, x[:, 0] - sz)
    r = y[0] - rng
    b = np.angle(np.exp(1j * (y[1] - brg)))  # wrapped residual
    inside = LOW[0] <= y[0] <= HIGH[0] and LOW[1] <= y[1] <= HIGH[1]
    with np.errstate(divide="ignore"):
        log_att = (
            np.log(eta) - np.log((HIGH[0] - LOW[0]) * (HIGH[1] - LOW[1])) if inside else -np.inf
        )
        return np.logaddexp(np.log1p(-eta) + _log_glint(r, b), log_att)


def _mixture(eta):
    box = UniformBox(
        torch.tensor(LOW * 4, dtype=torch.float64), torch.tensor(HIGH * 4, dtype=torch.float64)
    )
    return DeceptionMixtureLikelihood(eta, ReplacementDeception(box))


def test_round_robin_schedule_eq3():
    """Eq. (3): γ_k = mod(k + γ_ini − 2, N) + 1 for k = 1 … K (the first measurement is k = 1)."""
    K = 9
    for g_ini in (1, 2, 3, 4):
        mask = TrackingScenario(name="t", gamma_ini=g_ini).schedule().mask((), K, 8)
        sent = mask.reshape(K, 4, 2)
        assert bool((sent.all(-1) | ~sent.any(-1)).all())  # whole sensors only
        assert bool((sent.any(-1).sum(-1) == 1).all())  # one sensor per step
        got = sent.any(-1).long().argmax(-1).numpy() + 1
        k = np.arange(1, K + 1)
        np.testing.assert_array_equal(got, np.mod(k + g_ini - 2, 4) + 1)


def test_mixture_likelihood_eq14_15():
    """Eqs (14)–(15) with (18)–(19): the library's per-particle log-likelihood of one scheduled
    packet equals log[(1 − η̄) p_ν(ỹ − h^{γ_k}(x)) + η̄ p_ξ(ỹ)], inside and outside the ξ box,
    with a bearing residual across ±π."""
    model = TrackingModel()
    x = np.array(
        [
            [20.0, 0.3, 20.0, 0.3],
            [12.0, 0.0, 18.0, 0.0],
            [55.0, 0.1, 9.0, -0.2],
            [70.0, 0.0, 62.0, 0.0],
        ]
    )
    xt = torch.tensor(x)
    cases = [  # (sensor index, packet (range, bearing), η̄)
        (0, (14.0, 0.80), 0.2),  # clean-looking packet, inside the box
        (2, (5.5, 3.10), 0.2),  # bearing outside the box: p_ξ = 0; residuals wrap near ±π
        (3, (-3.0, -1.0), 0.6),  # a replaced packet (negative range): likelihood ≈ η̄ p_ξ
        (1, (60.0, 1.2), 0.0),  # η̄ = 0: the plain glint likelihood (Remark 1)
    ]
    for s, packet, eta in cases:
        y = torch.zeros(8, dtype=torch.float64)
        y[2 * s : 2 * s + 2] = torch.tensor(packet, dtype=torch.float64)
        mask = torch.zeros(8, dtype=torch.bool)
        mask[2 * s : 2 * s + 2] = True
        got = _mixture(eta)(model, y, xt, 1, mask).numpy()
        want = _paper_log_likelihood(np.array(packet), x, model.sensor_pos[s].tolist(), eta)
        np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-10)


def test_pf_da_product_likelihood_eq14_all_sensors():
    """PF-DA (Sec. 4): Π_i of eq. (14)'s per-sensor mixture over all four sensors' packets."""
    model = TrackingModel()
    x = np.array([[20.0, 0.3, 20.0, 0.3], [33.0, 0.0, 41.0, 0.0]])
    packets = np.array([[14.0, 0.75], [41.0, -1.4], [40.0, 2.5], [55.0, -2.3]])
    lik = PerSensorDeception(0.2, LOW, HIGH, 4)
    got = lik(model, torch.tensor(packets.ravel()), torch.tensor(x), 1, None).numpy()
    want = sum(
        (_paper_log_likelihood(packets[i], x, model.sensor_pos[i].tolist(), 0.2)) for i in range(4)
    )
    np.testing.assert_allclose(got, want, rtol=1e-10)


@pytest.mark.parametrize("batched", [True, False])
def test_weight_recursion_and_estimate_alg1(batched):
    """Alg. 1 Steps 2–5 with eq. (15): W_k ∝ W_{k−1} [(1 − η̄) p_ν(ỹ_k^{γ_k} − h^{γ_k}(x_k)) +
    η̄ p_ξ(ỹ_k^{γ_k})], x̂_k = Σ W_k^m x_k^m, on the Round-Robin mask (eq. 3) over three steps.
    Near-zero process noise makes x_k^m = F^k x_0^m; no resampling keeps the product visible."""
    model = TrackingModel(sigma_omega=1e-9)
    F = model.F.numpy()
    x0 = np.array([[20.0, 0.3, 20.0, 0.3], [21.0, 0.2, 19.5, 0.4], [19.0, 0.5, 20.5, 0.1]])
    lw0 = np.log(np.array([0.5, 0.3, 0.2]))
    K, eta = 3, 0.2
    lead = (1,) if batched else ()  # one run unbatched: the library's single-run step
    mask = TrackingScenario(name="t", gamma_ini=2).schedule().mask(lead, K, 8)
    ys = torch.zeros(lead + (K, 8), dtype=torch.float64)
    packets = {1: (51.0, -1.35), 2: (9.0, 0.9), 3: (70.0, 1.5)}  # γ_1..3 = 2, 3, 4 (γ_ini = 2)
    for k, p in packets.items():
        s = (k + 2 - 2) % 4
        ys[..., k - 1, 2 * s : 2 * s + 2] = torch.tensor(p, dtype=torch.float64)
    state = ParticleState(
        torch.tensor(x0).expand(lead + x0.shape),
        torch.tensor(lw0).expand(lead + lw0.shape),
        0,
        model=model,
    )
    out = mixture_likelihood_particle_filter(
        model, ys, mask=mask, num_particles=3, likelihood=_mixture(eta), ess_threshold=0.0,
        initial_state=state, generator=torch.Generator().manual_seed(0),
    )  # fmt: skip
    logw, x = lw0.copy(), x0.copy()
    for k in range(1, K + 1):
        x = x @ F.T
        s = (k + 2 - 2) % 4
        logw = logw + (
            _paper_log_likelihood(np.array(packets[k]), x, model.sensor_pos[s].tolist(), eta)
        )
        w = np.exp(logw - logw.max())
        w /= w.sum()
        np.testing.assert_allclose(
            out.means[..., k - 1, :].reshape(4).numpy(), w @ x, rtol=1e-7, atol=1e-7
        )


def test_rmse_p_v_metric():
    """Sec. 4's RMSE_{p,k}, RMSE_{v,k}: sqrt of the mean over L runs of the squared position
    (velocity) error norm at each k; the eval family's helper on a 3-run, 2-step case."""
    from difffilter.eval.families.tracking import _rmse_pv

    rng = np.random.default_rng(0)
    x, xh = rng.normal(size=(3, 2, 4)), rng.normal(size=(3, 2, 4))
    p, v = _rmse_pv(torch.tensor(xh), torch.tensor(x))
    e = (x - xh) ** 2
    np.testing.assert_allclose(p.numpy(), np.sqrt((e[..., 0] + e[..., 2]).mean(0)))
    np.testing.assert_allclose(v.numpy(), np.sqrt((e[..., 1] + e[..., 3]).mean(0)))


def test_target_model_eq16_17():
    """Eqs (16)–(17): x_{k+1} = F x_k + ω_k, ω_k ~ N(0, σ_ω² blkdiag([[T³/3, T²/2], [T²/2, T]] ×2));
    the matrices and the sampled transition's moments (T = 2 so T³/3 ≠ T²/2 ≠ T)."""
    T, sw = 2.0, 0.055
    model = TrackingModel(sigma_omega=sw, dt=T)
    F = np.array([[1, T, 0, 0], [0, 1, 0, 0], [0, 0, 1, T], [0, 0, 0, 1]])
    b = sw**2 * np.array([[T**3 / 3, T**2 / 2], [T**2 / 2, T]])
    Q = np.block([[b, np.zeros((2, 2))], [np.zeros((2, 2)), b]])
    np.testing.assert_allclose(model.F.numpy(), F)
    np.testing.assert_allclose(model.process_noise.cov.numpy(), Q, rtol=1e-12, atol=1e-15)
    x = torch.tensor([20.0, 0.3, 20.0, 0.3], dtype=torch.float64).expand(200_000, 4)
    nxt = model.sample_transition(x, None, 0, torch.Generator().manual_seed(1)).numpy()
    np.testing.assert_allclose(
        nxt.mean(0), F @ x[0].numpy(), atol=4 * np.sqrt(np.diag(Q).max() / 2e5)
    )
    np.testing.assert_allclose(np.cov(nxt.T), Q, rtol=0.02, atol=2e-2 * Q.max())


def test_glint_noise_sampling_eq19():
    """Eq. (19): each sensor's (range, bearing) noise is ONE 2-D mixture, so both entries share
    the component: E[ν_r² ν_b²] = (1 − κ) Σ1_r Σ1_b + κ Σ2_r Σ2_b (≠ E[ν_r²] E[ν_b²])."""
    noise = TrackingModel().measurement_noise
    v = noise.sample((400_000,), torch.Generator().manual_seed(2)).numpy().reshape(-1, 4, 2)
    want_r2 = (1 - KAPPA) * S1[0] + KAPPA * S2[0]
    want_b2 = (1 - KAPPA) * S1[1] + KAPPA * S2[1]
    want_rb = (1 - KAPPA) * S1[0] * S1[1] + KAPPA * S2[0] * S2[1]
    np.testing.assert_allclose((v[..., 0] ** 2).mean(), want_r2, rtol=0.01)
    np.testing.assert_allclose((v[..., 1] ** 2).mean(), want_b2, rtol=0.01)
    np.testing.assert_allclose((v[..., 0] ** 2 * v[..., 1] ** 2).mean(), want_rb, rtol=0.03)


def test_deception_attack_eq4_to_7():
    """Eqs (4)–(7): ỹ^{γ_k} = y^{γ_k} + η_k(−y^{γ_k} + ξ_k) (= ξ_k when η_k = 1), P{η_k = 1} = η̄,
    ξ_k uniform on [−10, 80] × [−π/2, π/2]; ȳ_k zero outside the scheduled sensor (zero input)."""
    sc = TrackingScenario(name="t", eta_bar=0.3, steps=40)
    gens = {
        k: torch.Generator().manual_seed(i) for i, k in enumerate(("plant", "attack", "schedule"))
    }
    tr = sc.simulate(200, gens)
    sched = tr.mask.reshape(200, 40, 4, 2).any(-1)
    flag = (tr.info["sensor_flags"] & sched).any(-1)
    np.testing.assert_array_equal(flag.numpy(), tr.flags.numpy())
    assert abs(float(flag.double().mean()) - 0.3) < 0.02  # η̄ = 0.3, 8000 packets
    xi = tr.info["attack_values"]
    want = torch.where(flag[..., None], xi, tr.y_true)  # eq. (4)–(5)
    got_sched = tr.y_recv[tr.mask].reshape(200, 40, 2)
    np.testing.assert_array_equal(got_sched.numpy(), want[tr.mask].reshape(200, 40, 2).numpy())
    assert bool((tr.y_recv[~tr.mask] == 0).all())  # eq. (7), zero input
    lo, hi = torch.tensor(LOW * 4, dtype=xi.dtype), torch.tensor(HIGH * 4, dtype=xi.dtype)
    assert bool(((xi >= lo) & (xi <= hi)).all())
