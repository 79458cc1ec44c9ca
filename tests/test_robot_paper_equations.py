"""Audit: the robot scenario's library code against Tan, Weng, Chen & Yu (supplementary).

Each test evaluates one equation of the paper in plain numpy on a tiny hand-made case
and compares it with the library's function.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from difffilter.fdi.adaptive_kf import adaptive_update
from difffilter.fdi.fusion import covariance_intersection
from difffilter.fdi.mdpf import AdaptiveKalmanProposal, Form, ParticleLayout, Reading
from difffilter.models.robot import DEG, RobotModel

LAM = 0.7
SENSORS = ((-120.0, 0.0), (-60.0, -60.0), (60.0, -60.0))  # group {1, 2, 3} of (B7)
Q = np.diag([1.0, 1.0, DEG**2])
R = np.diag([1.0, DEG**2] * 3)


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def _f(x, u):  # (B2)
    sx, sy, th = x
    return np.array([sx + u[0] * math.cos(th), sy + u[0] * math.sin(th), th + u[1]])


def _B(th):  # (B4), T0 = 1
    return np.array([[math.cos(th), 0.0], [math.sin(th), 0.0], [0.0, 1.0]])


def _h(x):  # (B6), stacked over the three sensors (atan2, as SCENARIOS.md says)
    out = []
    for px, py in SENSORS:
        dx, dy = px - x[0], py - x[1]
        out += [math.hypot(dx, dy), _wrap(x[2] - math.atan2(dy, dx))]
    return np.array(out)


def _jac(fun, x, eps=1e-6):
    cols = []
    for i in range(len(x)):
        d = np.zeros(len(x))
        d[i] = eps
        diff = fun(x + d) - fun(x - d)
        cols.append(diff / (2 * eps))
    return np.stack(cols, -1)


def _paper_step(x_hat, a_hat, ups, S, u, y):
    """(A1)–(A5), (A2) and the density of (A8) for one particle, literally."""
    u_eff = u + a_hat
    x_p = _f(x_hat, u) + _B(x_hat[2]) @ a_hat  # (A3)
    F = _jac(lambda z: _f(z, u_eff), x_hat)  # (A1) at x̂(k−1) (extended form)
    H = _jac(_h, x_p)  # (A1) at x_p
    eps = y - _h(x_p)
    eps[1::2] = _wrap(eps[1::2])
    P_p = Q  # (A4)
    Sig = H @ P_p @ H.T + R
    K = P_p @ H.T @ np.linalg.inv(Sig)
    P = P_p - K @ Sig @ K.T
    B = _B(x_hat[2])
    ImKH = np.eye(3) - K @ H
    ups_new = ImKH @ F @ ups + ImKH @ B  # (A5)
    Om = H @ F @ ups + H @ B
    Lam = np.linalg.inv(LAM * Sig + Om @ S @ Om.T)
    Gam = S @ Om.T @ Lam
    S_new = S / LAM - Gam @ Om @ S / LAM
    a_bar = a_hat + Gam @ eps  # (A2)
    x_bar = x_p + (K + ups_new @ Gam) @ eps
    m = len(y)
    loglik = -0.5 * (eps @ np.linalg.solve(Sig, eps) + np.linalg.slogdet(Sig)[1])
    loglik -= 0.5 * m * math.log(2 * math.pi)  # (A8): log N(y; h(x_p), Σ)
    return x_bar, a_bar, ups_new, S_new, P, loglik


def _case(seed):
    rng = np.random.default_rng(seed)
    x_hat = np.array([10.0, -5.0, 0.4]) + rng.normal(size=3) * [3, 3, 0.2]
    a_hat = np.array([2.0, 0.05]) + rng.normal(size=2) * [1, 0.02]
    ups = rng.normal(size=(3, 2))
    A = rng.normal(size=(2, 2))
    S = A @ A.T + np.eye(2)
    u = np.array([5.0, 5 * DEG])
    y = _h(_f(x_hat, u + np.array([20.0, 20 * DEG]))) + rng.normal(size=6) * np.array([1, DEG] * 3)
    return x_hat, a_hat, ups, S, u, y


def _t(a):
    return torch.as_tensor(a, dtype=torch.float64)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_theorem1_covariance_form_matches_a2_a5(seed):
    """Theorem 1, eqs (A2)–(A5) and (A8): one step of ``adaptive_update`` with ``P_p = Q``
    equals the paper's formulas evaluated literally (Λ, Γ, S of (A5) without the Joseph
    form, P = P_p − KΣKᵀ of (A4), Υ(k) in x̄ = x_p + (K + ΥΓ)ε of (A2))."""
    x_hat, a_hat, ups, S, u, y = _case(seed)
    model = RobotModel(sensors=SENSORS)
    upd = adaptive_update(
        model, _t(x_hat), _t(a_hat), _t(S), _t(ups), _t(y), _t(u), 0,
        forgetting=LAM, pred_cov=_t(Q),
    )  # fmt: skip
    x_bar, a_bar, ups_new, S_new, P, loglik = _paper_step(x_hat, a_hat, ups, S, u, y)
    np.testing.assert_allclose(upd.mean.numpy(), x_bar, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(upd.attack.numpy(), a_bar, rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(upd.sensitivity.numpy(), ups_new, rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(upd.attack_cov.numpy(), S_new, rtol=1e-6, atol=1e-10)
    np.testing.assert_allclose(upd.cov.numpy(), P, rtol=1e-6, atol=1e-10)
    assert float(upd.log_likelihood) == pytest.approx(loglik, rel=1e-7)


@pytest.mark.parametrize("form", [Form.INFORMATION, Form.COVARIANCE])
def test_proposal_copy_reading_matches_a2_a5_a8(form):
    """Theorem 1, eqs (A2)–(A5), and the particle weight (A8): the MDPF proposal (both
    forms, ``COPY`` reading so no draw) on three particles equals the paper's per-particle
    formulas, and its log-correction is log N(y; h(x_p), Σ) of (A8)."""
    cases = [_case(s) for s in (3, 4, 5)]
    y, u = cases[0][5], cases[0][4]
    model = RobotModel(sensors=SENSORS)
    lay = ParticleLayout(3, 2)
    packed = lay.pack(
        _t(np.stack([c[0] for c in cases])), _t(np.stack([c[1] for c in cases])),
        _t(np.stack([c[2] for c in cases])), _t(np.stack([c[3] for c in cases])),
        torch.zeros(3, 3, 3, dtype=torch.float64),
    )  # fmt: skip
    prop = AdaptiveKalmanProposal(model, LAM, Reading.COPY, form)
    new, loglik = prop(model, packed, _t(u), _t(y), 0, None, None)
    x, a, ups, S, P = lay.unpack(new)
    for j, c in enumerate(cases):
        ref = _paper_step(c[0], c[1], c[2], c[3], u, y)
        for got, want in zip((x[j], a[j], ups[j], S[j], P[j]), ref[:5]):
            np.testing.assert_allclose(got.numpy(), want, rtol=1e-6, atol=1e-8)
        assert float(loglik[j]) == pytest.approx(ref[5], rel=1e-7)
    # (A8): normalised weights
    w = torch.softmax(loglik, -1).numpy()
    lw = np.array([_paper_step(c[0], c[1], c[2], c[3], u, y)[5] for c in cases])
    np.testing.assert_allclose(w, np.exp(lw - lw.max()) / np.exp(lw - lw.max()).sum(), atol=1e-8)


def test_model_b2_b4_b6():
    """Eqs (B2)–(B4) and (B6): ``f(x, u) + B(k) a = f(x, u + a)`` with B(k) at θ(k−1),
    the input Jacobian is B(k), and h_i and its Jacobian equal the paper's range–bearing
    map (atan2, wrapped) and its finite differences."""
    model = RobotModel(sensors=SENSORS)
    x = np.array([10.0, -5.0, 3.0])
    u, a = np.array([5.0, 5 * DEG]), np.array([20.0, 20 * DEG])
    got = model.transition(_t(x), _t(u + a), 0).numpy()
    np.testing.assert_allclose(got, _f(x, u) + _B(x[2]) @ a, rtol=1e-12)
    np.testing.assert_allclose(model.input_jacobian(_t(x), _t(u), 0).numpy(), _B(x[2]))
    F = model.transition_jacobian(_t(x), _t(u + a), 0).numpy()
    np.testing.assert_allclose(F, _jac(lambda z: _f(z, u + a), x), atol=1e-6)
    np.testing.assert_allclose(model.observe(_t(x), 0).numpy(), _h(x), rtol=1e-12)
    H = model.observation_jacobian(_t(x), 0).numpy()
    np.testing.assert_allclose(H, _jac(_h, x), atol=1e-7)


def _ci_covs(P1, P2, w):
    w = w[:, None, None]
    return np.linalg.inv(w * np.linalg.inv(P1) + (1 - w) * np.linalg.inv(P2))


def test_covariance_intersection_trace_criterion():
    """Fusion rule (the letter's main-text rule, absent; SCENARIOS.md [DEF] CI with ω
    minimising tr P_f): ω is the trace minimiser (not the determinant one, which differs
    on this case), and x̂_f, P_f follow P_f⁻¹ = ωP₁⁻¹ + (1−ω)P₂⁻¹,
    x̂_f = P_f(ωP₁⁻¹x̂₁ + (1−ω)P₂⁻¹x̂₂)."""
    P1 = np.array([[4.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 1e-3]])
    P2 = np.array([[1.0, -0.5, 0.0], [-0.5, 3.0, 0.1], [0.0, 0.1, 5e-3]])
    x1, x2 = np.array([1.0, 2.0, 0.1]), np.array([1.5, 1.0, 0.2])
    grid = np.linspace(0, 1, 200001)
    Pf_grid = _ci_covs(P1, P2, grid)
    w_tr = grid[np.argmin(np.trace(Pf_grid, axis1=-2, axis2=-1))]
    w_det = grid[np.argmin(np.linalg.det(Pf_grid))]
    assert abs(w_tr - w_det) > 0.05  # the case tells the two criteria apart
    mean, cov, omega = covariance_intersection(_t(np.stack([x1, x2])), _t(np.stack([P1, P2])))
    assert float(omega) == pytest.approx(w_tr, abs=1e-4)
    I1, I2 = np.linalg.inv(P1), np.linalg.inv(P2)
    w = float(omega)
    Pf = np.linalg.inv(w * I1 + (1 - w) * I2)
    np.testing.assert_allclose(cov.numpy(), Pf, rtol=1e-9)
    np.testing.assert_allclose(mean.numpy(), Pf @ (w * I1 @ x1 + (1 - w) * I2 @ x2), rtol=1e-9)
