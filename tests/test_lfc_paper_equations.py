"""Hand checks of the LFC implementation against the equations of Sargolzaei et al.,
IEEE TII 2020 (docs/papers.md §3): each test evaluates a paper equation in plain numpy on
a tiny hand-made case and compares the library's function with it."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.linalg as sla
import torch

from difffilter.attack import Channel
from difffilter.control import uncontrollable_direction
from difffilter.estimator import Generators
from difffilter.fdi.neural import OnlineLearning, Residual, _Core
from difffilter.models.lfc import (
    LFCParameters,
    LFCPlant,
    SecureController,
    continuous_model,
    lqr_gain,
    scenario_attack,
)
from difffilter.models.lfc_estimators import LFCContext, lfc_estimator, paper_network
from difffilter.models.neural_estimator import AreaNetwork, NeuralFDIEstimator
from difffilter.param_ekf import EKFRule, WeightTemplate


def _paper_H(W, V, x):
    """Eq. (13): ∂M̂/∂ζ, ζ = [vec W, vec V] row-major, as an [m, P] array."""
    h = np.tanh(V @ x)
    m, hid = W.shape
    dW = np.zeros((m, m * hid))
    for i in range(m):
        dW[i, i * hid : (i + 1) * hid] = h
    dV = ((W * (1 - h * h))[:, :, None] * x[None, None, :]).reshape(m, -1)
    return W @ h, np.concatenate([dW, dV], axis=1)


def _paper_ekf_step(zeta, rho, ups, k, W_shape, V_shape, x, target, eta, q):
    """Eqs (11), (12), (14), (14b) for one area, literally (H_paper = ∂M̂/∂ζ as P×m)."""
    nW = int(np.prod(W_shape))
    W, V = zeta[:nW].reshape(W_shape), zeta[nW:].reshape(V_shape)
    pred, Hm = _paper_H(W, V, x)
    e = target - pred  # e_k = z_k − ẑ_k, ẑ = Cx̂ + M̂
    ups = ups + (e @ e - ups) / k  # (14b)
    Hp = Hm.T  # the paper's H [P, m]
    lam = rho @ Hp @ np.linalg.inv(Hp.T @ rho @ Hp + ups * np.eye(len(e)))  # (12)
    zeta = zeta + eta * lam @ e  # (11)
    rho = rho - lam @ Hp.T @ rho + q * np.eye(len(zeta))  # (14) (+ the declared Q_ρ)
    return zeta, rho, ups, pred, e


@pytest.mark.parametrize("q", [0.0, 1e-3])
def test_ekf_rule_matches_eqs_11_12_14(q):
    """Eqs (11), (12), (13), (14) and (14b): the library's EKF over the weights (deferred
    covariance, Kronecker Jacobian, folds every 2 steps) against a dense numpy evaluation;
    q = 0 is the paper's eq. (14) alone, q > 0 the declared Q_ρ deviation."""
    rng = np.random.default_rng(0)
    m, hid, n = 2, 3, 4
    net = AreaNetwork(n, hid, m, dtype=torch.float64)
    template = WeightTemplate(net)
    assert template.factored
    W0, V0 = 0.3 * rng.random((m, hid)), 0.3 * rng.random((hid, n))
    zeta = np.concatenate([W0.ravel(), V0.ravel()])
    rule = EKFRule(lr=0.7, init_cov=10.0, init_noise=5.0, process_noise=q, fold_every=2)
    state = rule.init(torch.tensor(zeta)[None])
    rho, ups = 10.0 * np.eye(zeta.size), 5.0
    for k in range(1, 13):
        x = rng.normal(size=n)
        target = rng.normal(size=m) * 0.5
        pred, H = template.jacobian(state.theta, torch.tensor(x)[None])
        state = rule.step(state, H, torch.tensor(target)[None] - pred)
        zeta, rho, ups, pred_np, _ = _paper_ekf_step(
            zeta, rho, ups, k, (m, hid), (hid, n), x, target, 0.7, q
        )
        np.testing.assert_allclose(pred[0].numpy(), pred_np, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(state.theta[0].numpy(), zeta, rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(float(state.upsilon[0]), ups, rtol=1e-12)
        np.testing.assert_allclose(EKFRule.covariance(state)[0].numpy(), rho, atol=1e-8)


def test_network_input_and_online_update_eqs_8_9_11():
    """Eqs (8), (9) with δ's definition (lags 1…a of M̂, 1…b of e), (11) with e = z − ẑ:
    the LFC network inside the observer wrapper (_Core, residual LAGGED, raw residuals,
    EKF online, posterior estimate) against a per-area numpy recursion fed the same
    innovations ν_k = z_k − Cx̂_{k|k−1}."""
    J, d, a, b, hid = 2, 2, 2, 2, 3
    net = NeuralFDIEstimator(num_areas=J, area_dim=d, a=a, b=b, hidden=hid, init_scale=0.3,
                             detection_head=False, seed=3)  # fmt: skip
    rule = EKFRule(lr=1.0, init_cov=10.0, init_noise=1e-3, process_noise=1e-3)
    core = _Core(net, Channel.SENSOR, Residual.LAGGED, False, (), None,
                 OnlineLearning(rule, posterior=True), False)  # fmt: skip
    state = core.init(torch.Size([1]), torch.float64, "cpu", torch.Generator())
    cov = torch.eye(J * d, dtype=torch.float64)[None]

    W0, V0 = net.W.detach().numpy(), net.V.detach().numpy()
    P = d * hid + hid * d * (a + b)
    areas = [
        {"zeta": np.concatenate([W0[i].ravel(), V0[i].ravel()]), "rho": 10 * np.eye(P),
         "ups": 1e-3, "M": [np.zeros(d)] * a, "e": [np.zeros(d)] * b}
        for i in range(J)
    ]  # fmt: skip
    rng = np.random.default_rng(1)
    for k in range(1, 8):
        nu = rng.normal(size=J * d) * 0.3
        state, attack, _, _, delta = core.step(state, torch.tensor(nu)[None], cov, None)
        for i, ar in enumerate(areas):
            x = np.concatenate([*ar["M"][:a], *ar["e"][:b]])  # δ: M̂_{k−1..k−a}, e_{k−1..k−b}
            np.testing.assert_allclose(delta[0, i].numpy(), x, atol=1e-12)
            target = nu[i * d : (i + 1) * d]
            ar["zeta"], ar["rho"], ar["ups"], prior, e = _paper_ekf_step(
                ar["zeta"], ar["rho"], ar["ups"], k, (d, hid), (hid, d * (a + b)), x, target,
                1.0, 1e-3,
            )  # fmt: skip
            nW = d * hid
            Wk, Vk = ar["zeta"][:nW].reshape(d, hid), ar["zeta"][nW:].reshape(hid, -1)
            post = Wk @ np.tanh(Vk @ x)  # Algorithm 1: estimate from (8) after (11)
            np.testing.assert_allclose(attack[0, i * d : (i + 1) * d].numpy(), post,
                                       rtol=1e-8, atol=1e-10)  # fmt: skip
            ar["M"] = [post, *ar["M"][:-1]]
            ar["e"] = [e, *ar["e"][:-1]]


def _paper_area_A(p, i):
    J, mu, Ttu, Tg, w, beta = (p.inertia[i], p.damping[i], p.turbine_time[i],
                               p.governor_time[i], p.droop[i], p.freq_bias[i])  # fmt: skip
    return np.array([
        [-mu / J, 1 / J, 0, -1 / J, 0],
        [0, -1 / Ttu, 1 / Ttu, 0, 0],
        [-1 / (w * Tg), 0, -1 / Tg, 0, 0],
        [2 * math.pi * p.tie_stiffness, 0, 0, 0, 0],
        [beta, 0, 0, 1, 0],
    ])  # fmt: skip


def test_plant_and_zoh_eqs_35_to_42():
    """Eqs (35)–(41) (A_i, B_i, F_i, A_ij) and eq. (42)'s A_d = e^{AΔt},
    B_d = ∫₀^Δt e^{Aα} dα B, built in numpy from hand-changed parameters, against the
    library (Simpson quadrature for the integral)."""
    p = LFCParameters(inertia=(8.0, 11.0), damping=(0.9, 1.4), turbine_time=(0.35, 0.45),
                      governor_time=(0.12, 0.2), droop=(0.04, 0.06), freq_bias=(20.0, 22.0),
                      tie_stiffness=0.25)  # fmt: skip
    A = np.zeros((10, 10))
    B = np.zeros((10, 2))
    F = np.zeros((10, 2))
    for i in range(2):
        A[5 * i : 5 * i + 5, 5 * i : 5 * i + 5] = _paper_area_A(p, i)
        A[5 * i + 3, 5 * (1 - i)] = -2 * math.pi * p.tie_stiffness  # A_ij (41)
        B[5 * i + 2, i] = 1 / p.governor_time[i]  # (36)
        F[5 * i, i] = -1 / p.inertia[i]  # (37)
    At, Bt, Ft = continuous_model(p)
    np.testing.assert_allclose(At.numpy(), A, atol=1e-14)
    np.testing.assert_allclose(Bt.numpy(), B, atol=1e-14)
    np.testing.assert_allclose(Ft.numpy(), F, atol=1e-14)

    dt = 0.01
    plant = LFCPlant(dt=dt, params=p)
    s = np.linspace(0.0, dt, 201)
    wts = np.ones_like(s)
    wts[1:-1:2], wts[2:-1:2] = 4.0, 2.0
    integral = sum(wk * sla.expm(A * sk) for wk, sk in zip(wts, s)) * (s[1] - s[0]) / 3
    np.testing.assert_allclose(plant.Ad.numpy(), sla.expm(A * dt), atol=1e-13)
    np.testing.assert_allclose(plant.Bd.numpy(), integral @ B, atol=1e-12)
    np.testing.assert_allclose(plant.Fd.numpy(), integral @ F, atol=1e-12)


def test_lqr_gain_solves_care_eq_16_on_controllable_subspace():
    """Eqs (15)–(16): K₁ = R⁻¹BᵀP, P the CARE solution, Q = I, R = I ([DEF]). The LFC pair
    has an uncontrollable zero mode (tie-line sum), so the CARE is solved on w⊥: K₁ must
    equal, on w⊥, the gain of scipy's CARE on an orthonormal basis of w⊥, and A − BK₁
    must be stable there."""
    plant = LFCPlant(dt=0.01)
    A, B = plant.A.numpy(), plant.B.numpy()
    K1 = lqr_gain(plant).numpy()
    w = uncontrollable_direction(plant.A, plant.B).numpy()
    np.testing.assert_allclose(w @ A, 0.0, atol=1e-12)
    np.testing.assert_allclose(w @ B, 0.0, atol=1e-12)
    Vb = sla.null_space(w[None])  # orthonormal basis of w⊥ [10, 9]
    Ar, Br, Qr = Vb.T @ A @ Vb, Vb.T @ B, Vb.T @ Vb
    Pr = sla.solve_continuous_are(Ar, Br, Qr, np.eye(2))
    np.testing.assert_allclose(Pr @ Ar + Ar.T @ Pr + Qr - Pr @ Br @ Br.T @ Pr, 0.0, atol=1e-8)
    np.testing.assert_allclose(K1 @ Vb, Br.T @ Pr, rtol=1e-7, atol=1e-9)
    assert np.linalg.eigvals(Ar - Br @ K1 @ Vb).real.max() < 0


def test_attack_signals_eqs_44_to_47():
    """Eqs (44)–(47) at hand-picked sample times, closed intervals inclusive."""
    t = torch.tensor([0.05, 0.1, 2.99, 3.0, 5.0, 5.01, 6.99, 7.0, 8.0, 8.01], dtype=torch.float64)
    tn = t.numpy()
    step = scenario_attack("step", t)[:, 2].numpy()
    np.testing.assert_allclose(step, [0, 0, 0, 0.4, 0.4, 0, 0, 0.9, 0.9, 0])
    sine = scenario_attack("sine", t)[:, 2].numpy()
    np.testing.assert_allclose(sine, np.where(tn >= 3, 1.5 * np.sin(10 * tn), 0.0), atol=1e-15)
    sim = scenario_attack("simultaneous", t).numpy()
    first, second = (tn >= 0.1) & (tn <= 5), (tn >= 7) & (tn <= 8)
    np.testing.assert_allclose(sim[:, 2], 0.6 * first + 1.2 * second)
    np.testing.assert_allclose(sim[:, 7], 0.9 * np.sin(10 * tn) * first + 0.1 * second, atol=1e-15)
    assert np.count_nonzero(np.delete(sim, [2, 7], axis=1)) == 0


def test_compensated_kalman_step_and_secure_controller_eqs_5_to_7_and_17():
    """Eqs (5)–(7) sampled (the discrete KF on (A_d, B_d, I, Ξ, Θ), Σ(0) = 1e-2·I [DEF]) with
    Ẑ = CX̂ + M̂: the update reads Z_k − M̂_k; eq. (8)–(9) for M̂ (fixed weights, e = ν − M̂
    lagged); eq. (17) with K₂ = 0: U_k = −K₁(Z_k − M̂_k). Three steps against numpy."""
    ctx = LFCContext(dt=0.01)
    net = paper_network(init_scale=0.05)
    est = lfc_estimator(ctx, network=net)
    model = ctx.plant.model(knows_load=False)
    carry = est._init(model, torch.Size([1]), Generators.of(torch.Generator()))
    Ad, Bd = ctx.plant.Ad.numpy(), ctx.plant.Bd.numpy()
    Xi, Th, K1 = ctx.plant.Q.numpy(), ctx.plant.R.numpy(), ctx.K1.numpy()
    load = torch.tensor([[0.01, 0.0]], dtype=torch.float64)
    ctrl = SecureController(ctx.K1, load)
    W, V = net.W.detach().numpy(), net.V.detach().numpy()
    x, P = np.zeros(10), 1e-2 * np.eye(10)
    hist_M, hist_e = np.zeros((2, 3, 5)), np.zeros((2, 3, 5))
    rng = np.random.default_rng(2)
    u = ctrl.init((1,), torch.float64, "cpu")
    for k in range(1, 4):
        z = rng.normal(size=10) * 0.2
        carry, out = est._step(carry, torch.tensor(z)[None], u, None)
        xm = Ad @ x + Bd @ u[0, :2].detach().numpy()  # the load is unknown to the observer
        Pm = Ad @ P @ Ad.T + Xi
        nu = z - xm
        M = np.concatenate([
            W[i] @ np.tanh(V[i] @ np.concatenate([hist_M[i].ravel(), hist_e[i].ravel()]))
            for i in range(2)
        ])  # fmt: skip
        S = Pm + Th
        G = Pm @ np.linalg.inv(S)
        x = xm + G @ (z - M - xm)
        P = (np.eye(10) - G) @ Pm
        for i in range(2):
            sl = slice(5 * i, 5 * i + 5)
            hist_M[i] = np.vstack([M[sl], hist_M[i][:-1]])
            hist_e[i] = np.vstack([nu[sl] - M[sl], hist_e[i][:-1]])
        np.testing.assert_allclose(out.attack[0].detach().numpy(), M, rtol=1e-9, atol=1e-13)
        np.testing.assert_allclose(out.mean[0].detach().numpy(), x, rtol=1e-8, atol=1e-12)
        u = ctrl(k, torch.tensor(z)[None], out)
        np.testing.assert_allclose(u[0, :2].detach().numpy(), -K1 @ (z - M), rtol=1e-10, atol=1e-13)
        np.testing.assert_allclose(u[0, 2:].detach().numpy(), load[0].numpy())
