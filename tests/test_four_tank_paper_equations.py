"""Hand checks of the four-tank modified-PF paper's equations against numpy.

Sadeghzadeh-Nokhodberiz, Meskin, Hasanzadeh, IEEE Access 2022 ("Modified particle
filters for detection of FDI attacks ..."); the plant is Johansson's quadruple tank
(SCENARIOS.md section 1, the paper itself gives no tank equations). Each test evaluates
the paper's equation with numpy on a tiny hand-made case and compares the library.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import torch

from difffilter import fdi
from difffilter.models.attacks import SensorBias
from difffilter.models.four_tank import R_NOMINAL, FourTankModel, FourTankParameters

# Johansson 2000, P- (SCENARIOS.md section 1)
A = np.array([28.0, 32.0, 28.0, 32.0])
a = np.array([0.071, 0.057, 0.071, 0.057])
g, k1, k2, g1, g2, v1, v2 = 981.0, 3.33, 3.35, 0.70, 0.60, 3.0, 3.0


def _johansson_rhs(h: np.ndarray) -> np.ndarray:
    """Johansson's four equations with the levels clamped at 0 under the square roots."""
    s = np.sqrt(2 * g * np.maximum(h, 0.0))
    return np.array(
        [
            -a[0] / A[0] * s[0] + a[2] / A[0] * s[2] + g1 * k1 / A[0] * v1,
            -a[1] / A[1] * s[1] + a[3] / A[1] * s[3] + g2 * k2 / A[1] * v2,
            -a[2] / A[2] * s[2] + (1 - g2) * k2 / A[2] * v2,
            -a[3] / A[3] * s[3] + (1 - g1) * k1 / A[3] * v1,
        ]
    )


def test_tank_dynamics_and_euler_step_match_johansson():
    """Eq. (1) with f = Johansson's quadruple tank, Euler-discretised (SCENARIOS.md section 1):
    x_{k+1} = x_k + dt f_c(max(x_k, 0), v); negative levels clamp at 0 inside the roots only."""
    dt = 0.7
    model = FourTankModel(dt=dt, dtype=torch.float64)
    xs = np.array([[10.0, 9.0, 2.0, 3.0], [-0.5, 4.0, -1.0, 2.0], [0.0, 0.0, 0.0, 0.0]])
    want = np.stack([x + dt * _johansson_rhs(x) for x in xs])
    x_t = torch.tensor(xs, dtype=torch.float64)
    np.testing.assert_allclose(model.transition(x_t, None, 1).numpy(), want, rtol=0, atol=1e-12)
    rhs = np.stack([_johansson_rhs(x) for x in xs])
    np.testing.assert_allclose(model.continuous_rhs(x_t).numpy(), rhs, rtol=0, atol=1e-12)
    M, c = model.sqrt_affine_form()
    fused = xs + c.numpy() + np.sqrt(np.maximum(xs, 0.0)) @ M.numpy()
    np.testing.assert_allclose(fused, want, rtol=0, atol=1e-12)
    # the fixed point: f_c(x*) = 0 (12.263, 12.783, 1.634, 1.409)
    xstar = np.array(FourTankParameters().fixed_point())
    np.testing.assert_allclose(_johansson_rhs(xstar), 0.0, atol=1e-12)
    np.testing.assert_allclose(xstar, [12.263, 12.783, 1.634, 1.409], atol=1e-3)
    # the Jacobian: central differences of the Euler map at a positive point
    x0 = xs[0]
    eps = 1e-6
    fd = np.stack(
        [
            (
                (x0 + eps * e + dt * _johansson_rhs(x0 + eps * e))
                - (x0 - eps * e + dt * _johansson_rhs(x0 - eps * e))
            )
            / (2 * eps)
            for e in np.eye(4)
        ],
        axis=1,
    )
    jac = model.transition_jacobian(torch.tensor(x0, dtype=torch.float64), None, 1).numpy()
    np.testing.assert_allclose(jac, fd, atol=1e-8)


def test_attack_recursion_eq4_and_indexing():
    """Eq. (4): gamma_{k+1} = tau gamma_k + (1 - tau) gamma_bar, gamma_0 = 0; values[t] = gamma_{t+1}."""
    att = SensorBias((0.5, 0.5, 0.5, 0.5), tau=0.9, p_l=0.5)
    got = att.values(5).numpy()
    gam, want = np.zeros(4), []
    for _ in range(5):
        gam = 0.9 * gam + 0.1 * 0.5 * np.ones(4)
        want.append(gam)
    np.testing.assert_allclose(got, np.array(want), atol=1e-15)
    # ||gamma_k|| = 1 - 0.9^k (SCENARIOS: 0.10, 0.19, 0.27, 0.34): k <= 3 is below ||gamma||_min
    np.testing.assert_allclose(np.linalg.norm(got, axis=1), 1 - 0.9 ** np.arange(1, 6), atol=1e-14)


def test_thresholds_eta_eq45_and_zeta_eq46_53():
    """Eqs (35), (45), (46), (53): K = Q G^T (R + G Q G^T)^-1, eta = |sigma_bar - 1| ||gamma||_min
    with sigma_bar the singular value of G K nearest 1 (paper: eta = 0.233 for 0.28);
    zeta = alpha (N-1)/N with alpha = p_l N/(N-1) -> zeta = p_l; alarm iff beta > zeta."""
    G, Q, R = np.eye(4), 1e-4 * np.eye(4), np.diag(R_NOMINAL)
    K = Q @ G.T @ np.linalg.inv(R + G @ Q @ G.T)
    K_lib = fdi.modified_pf_gain(torch.tensor(G), torch.tensor(Q), torch.tensor(R)).numpy()
    np.testing.assert_allclose(K_lib, K, atol=1e-15)
    sv = np.linalg.svd(G @ K, compute_uv=False)
    varsigma = abs(sv[np.argmin(abs(sv - 1))] - 1)
    eta = varsigma * 0.28
    assert abs(eta - 0.233) < 5e-4  # the paper's number
    eta_lib = float(fdi.attack_threshold(torch.tensor(G), torch.tensor(K), 0.28))
    assert abs(eta_lib - eta) < 1e-14
    det = fdi.poa_detector_for(
        FourTankModel(dtype=torch.float64), gamma_min=0.28, p_l=0.5, num_particles=100
    )
    assert abs(float(det.eta) - eta) < 1e-12
    assert det.zeta == 0.5 * (100 / 99) * (99 / 100) == 0.5
    assert fdi.detection_threshold(None, 10, alpha=0.6) == 0.6 * 9 / 10
    # strict: beta == zeta is no alarm (eq. 14: "beta_k exceeds zeta")
    z = torch.tensor([[1.0, 0, 0, 0], [0.0, 0, 0, 0]], dtype=torch.float64)
    beta, alarm = fdi.PoADetector(0.5, 0.5)(z)
    assert float(beta) == 0.5 and not bool(alarm)


def _case():
    """Five predictive particles, received y, and the nominal four-tank G, Q, R."""
    x = np.array(
        [
            [12.0, 12.5, 1.6, 1.4],
            [12.3, 12.8, 1.7, 1.3],
            [11.6, 12.9, 1.5, 1.5],
            [12.9, 12.2, 1.9, 1.2],
            [12.2, 12.7, 1.6, 1.45],
        ]
    )
    y = np.array([12.45, 13.05, 1.95, 1.75])  # ~ G x + a bias of 0.3
    G, Q, R = np.eye(4), 1e-4 * np.eye(4), np.diag(R_NOMINAL)
    K = Q @ G.T @ np.linalg.inv(R + G @ Q @ G.T)
    return x, y, G, Q, R, K


def test_modified_pf_correction_eq36_and_poa_eq58_use_corrected_residual():
    """Eq. (36): x~+ = x + K (y~ - G x); eq. (58): beta~ = (1/N) #{i: ||y~ - G x~+_i|| > eta}
    (weights 1/N, the corrected residual, not y~ - G x_i); alarm iff beta~ > zeta (2-3)."""
    x, y, G, _, _, K = _case()
    x_plus = x + (y - x @ G.T) @ K.T
    z_plus = y - x_plus @ G.T
    z_raw = y - x @ G.T
    eta = 0.57  # corrected norms 0.77 0.50 0.89 0.99 0.55; raw 0.87 0.59 1.00 1.11 0.63
    beta_paper = np.mean(np.linalg.norm(z_plus, axis=1) > eta)
    beta_raw = np.mean(np.linalg.norm(z_raw, axis=1) > eta)
    assert beta_paper != beta_raw  # the case tells the two residuals apart

    xt, yt, Gt, Kt = (torch.tensor(v) for v in (x, y, G, K))
    np.testing.assert_allclose(
        fdi.kalman_corrected_particles(xt, yt, Gt, Kt).numpy(), x_plus, atol=1e-13
    )
    np.testing.assert_allclose(fdi.corrected_residuals(xt, yt, Gt, Kt).numpy(), z_plus, atol=1e-13)

    # the filter's own step 2 (ModifiedPFWeighting.weigh), uniform predictive weights
    model = FourTankModel(dtype=torch.float64)
    gamma_hat = torch.zeros(3, 4, dtype=torch.float64)
    weighting = fdi.ModifiedPFWeighting(fdi.PoADetector(eta, 0.5), gamma_hat)
    state = weighting.init(model, (), torch.float64, None)
    pred = SimpleNamespace(
        log_weights=torch.full((5,), -np.log(5.0), dtype=torch.float64), mean=xt.mean(0)
    )
    _, _, rec = weighting.weigh(state, model, yt, xt, 1, None, pred)
    assert float(rec["beta"]) == beta_paper
    assert bool(rec["alarm"]) == (beta_paper > 0.5)


def test_compensated_weights_eq59_and_estimate_eq60():
    """Eq. (59): w_k^i ∝ p(y~_k - l^_k gamma^_k | x_k^i) w_{k-1}^i on the *uncorrected* x_k^i, with
    gamma^ of the same step k; eq. (60): x^_k = sum_i w_k^i x_k^i."""
    x, y, G, _, R, K = _case()
    eta, zeta = 0.2, 0.5  # every corrected residual exceeds 0.2 here: l^_k = 1
    model = FourTankModel(dtype=torch.float64)
    rows = np.array(
        [[9.0, 9.0, 9.0, 9.0], [0.3, 0.3, 0.3, 0.3], [7.0, 7.0, 7.0, 7.0]]
    )  # gamma^_1..3
    weighting = fdi.ModifiedPFWeighting(fdi.PoADetector(eta, zeta), torch.tensor(rows))
    state = weighting.init(model, (), torch.float64, None)
    xt, yt = torch.tensor(x), torch.tensor(y)
    prior = np.array([0.1, 0.3, 0.2, 0.25, 0.15])
    pred = SimpleNamespace(log_weights=torch.tensor(np.log(prior)), mean=xt.mean(0))
    k = 2
    _, log_p, rec = weighting.weigh(state, model, yt, xt, k, None, pred)
    # eq. (58) with the predictive weights w_{k-1} (eq. 29)
    z_plus = y - (x + (y - x @ G.T) @ K.T) @ G.T
    assert bool(rec["alarm"]) and float(rec["beta"]) == np.sum(
        prior[np.linalg.norm(z_plus, axis=1) > eta]
    )
    np.testing.assert_allclose(rec["gamma_hat"].numpy(), rows[k - 1])
    r = y - rows[k - 1] - x @ G.T
    ll = -0.5 * np.einsum("nd,de,ne->n", r, np.linalg.inv(R), r)
    w = np.exp(ll - ll.max()) * prior
    w /= w.sum()
    lib = log_p.numpy() + np.log(prior)
    lib = np.exp(lib - lib.max())
    lib /= lib.sum()
    np.testing.assert_allclose(lib, w, atol=1e-12)
    x_hat = w @ x  # eq. (60)
    np.testing.assert_allclose(torch.tensor(lib) @ xt, x_hat, atol=1e-12)


def test_normal_pf_poa_eq14_eq17():
    """Eqs (14)/(17): beta~_k = sum_{||y~ - G x_i|| > eta} p(y~|x_i) / sum_j p(y~|x_j) (uncorrected
    residual, likelihood-normalised weights); the literal float64 variant agrees."""
    x, y, G, _, R, _ = _case()
    r = y - x @ G.T
    ll = -0.5 * np.einsum("nd,de,ne->n", r, np.linalg.inv(R), r)
    w = np.exp(ll - ll.max())
    w /= w.sum()
    eta = 0.75
    exceed = np.linalg.norm(r, axis=1) > eta
    assert 0 < exceed.sum() < len(exceed)
    want = float(np.sum(w[exceed]))
    got = fdi.probability_of_attack(torch.tensor(r), eta, torch.tensor(ll))
    assert abs(float(got) - want) < 1e-12
    lit = fdi.literal_probability_of_attack(torch.tensor(r), torch.tensor(R), eta)
    assert abs(float(lit) - want) < 1e-12


def test_normal_pf_weights_eq7_and_poa_eq17_end_to_end():
    """Eqs (7), (14)-(17) inside the normal PF: the returned weights are
    p(y~_k|x_k^i) w_{k-1}^i / sum_j (...), w_{k-1} = 1/N after resampling (so eq. 7 = eq. 17),
    and the reported beta_k is the numpy sum of those weights over ||y~_k - G x_k^i|| > eta."""
    model = FourTankModel(dtype=torch.float64)
    gen = torch.Generator().manual_seed(0)
    T, n, eta = 3, 16, 0.15
    ys = model.initial.mean + torch.tensor([0.05, -0.04, 0.12, 0.1], dtype=torch.float64)
    ys = ys.expand(1, T, 4).clone()
    out = fdi.particle_filter_poa(
        model, ys, num_particles=n, detector=fdi.PoADetector(eta, 0.5), generator=gen,
        resample_generator=torch.Generator().manual_seed(1), return_particles=True,
    )  # fmt: skip
    R = np.diag(R_NOMINAL)
    for k in range(T):
        x = out.extras["particles"][0, k].numpy()
        prior = np.exp(out.extras["prior_log_weights"][0, k].numpy())
        np.testing.assert_allclose(prior, 1.0 / n, rtol=1e-12)
        r = ys[0, k].numpy() - x
        ll = -0.5 * np.einsum("nd,de,ne->n", r, np.linalg.inv(R), r)
        w = np.exp(ll - ll.max()) * prior
        w /= w.sum()
        np.testing.assert_allclose(np.exp(out.extras["log_weights"][0, k].numpy()), w, atol=1e-12)
        want = np.sum(w[np.linalg.norm(r, axis=1) > eta])
        assert abs(float(out.detection.scores[0, k]) - want) < 1e-12
    assert 0.0 < float(out.detection.scores[0, -1]) < 1.0  # a step with a partial sum


def test_modified_pf_estimate_eq59_eq60_is_bootstrap_pf_on_compensated_measurement():
    """Eqs (54)-(60): after detection the estimate uses the *uncorrected* x_k^i weighted with
    p(y~_k - l^_k gamma^_k | x_k^i): with eta = 0 (every step alarms, beta~ = 1 > zeta) it equals
    the normal PF on y~ - gamma^; with eta huge (no alarm) the normal PF on y~ itself."""
    model = FourTankModel(dtype=torch.float64)
    T, n = 4, 16
    gamma_hat = SensorBias((0.5,) * 4).values(T).unsqueeze(0)
    ys = model.initial.mean + gamma_hat + 0.01

    def gens():
        return torch.Generator().manual_seed(5), torch.Generator().manual_seed(6)

    def modified(eta):
        g, r = gens()
        return fdi.modified_particle_filter(
            model, ys, num_particles=n, detector=fdi.PoADetector(eta, 0.5), gamma_hat=gamma_hat,
            generator=g, resample_generator=r,
        )  # fmt: skip

    def normal(y):
        g, r = gens()
        return fdi.particle_filter_poa(
            model, y, num_particles=n, detector=fdi.PoADetector(1.0, 0.5), generator=g,
            resample_generator=r,
        )  # fmt: skip

    on, off = modified(0.0), modified(1e6)
    assert bool(on.detection.alarms.all()) and not bool(off.detection.alarms.any())
    np.testing.assert_allclose(on.means.numpy(), normal(ys - gamma_hat).means.numpy(), atol=1e-12)
    np.testing.assert_allclose(off.means.numpy(), normal(ys).means.numpy(), atol=1e-12)
