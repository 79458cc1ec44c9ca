"""Mutation-review findings for difffilter.param_ekf, difffilter.fdi.adaptive_kf and
difffilter.fdi.attack_estimation: each test pins a behaviour a realistic bug changed while
the older tests still passed, against an independent truth (a literal numpy evaluation of
the module docstring's equations, a closed form, or the documented contract)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.stats import chi2
from torch import nn

import difffilter as df
from difffilter.fdi import BiasAttackEstimator
from difffilter.fdi.adaptive_kf import (
    AdaptiveKalmanFilter,
    adaptive_kalman_filter,
    adaptive_kalman_init,
    adaptive_kalman_step,
)
from difffilter.param_ekf import (
    EKFOptimizer,
    EKFRule,
    GradientRule,
    KroneckerJacobian,
    ParamEKF,
    WeightTemplate,
    dense_reference,
    ekf_along_sequence,
)

F64 = torch.float64


class TanhLayer(nn.Module):
    """``W tanh(V (δ / s))`` (the factored form), or ``W relu(V (δ / s))`` with ``relu``."""

    def __init__(self, m=2, h=3, n=4, relu=False, seed=0):
        super().__init__()
        g = torch.Generator().manual_seed(seed)
        self.W = nn.Parameter(0.5 * torch.randn(m, h, generator=g, dtype=F64))
        self.V = nn.Parameter(0.5 * torch.randn(h, n, generator=g, dtype=F64))
        self.register_buffer("in_scale", torch.linspace(0.5, 2.0, n, dtype=F64))
        self.relu = relu

    def forward(self, x):
        a = (x / self.in_scale) @ self.V.T
        return (torch.relu(a) if self.relu else torch.tanh(a)) @ self.W.T


def _np_jacobian(W, V, x, act="tanh"):
    """Eq. (13) in numpy: ``∂f/∂ζ`` of ``f = W σ(V x)``, ``ζ = [vec W, vec V]`` row-major."""
    a = V @ x
    s, ds = (np.tanh(a), 1 - np.tanh(a) ** 2) if act == "tanh" else (np.maximum(a, 0), a > 0)
    m, h = W.shape
    dW = np.zeros((m, m * h))
    for i in range(m):
        dW[i, i * h : (i + 1) * h] = s
    dV = ((W * ds)[:, :, None] * x[None, None, :]).reshape(m, -1)
    return W @ s, np.concatenate([dW, dV], axis=1)


# ----------------------------------------------------------------------------- param_ekf


def test_nested_dense_reference_restores_the_outer_mode():
    """``dense_reference`` restores the mode it found: after an inner block ends, the outer
    block still starts dense ``ρ [N, P, P]`` (the contract of a context manager), and after
    both the deferred form is back."""
    rule, theta = EKFRule(), torch.zeros(1, 3, dtype=F64)
    with dense_reference():
        with dense_reference():
            pass
        assert isinstance(rule.init(theta).rho, torch.Tensor)
    assert not isinstance(rule.init(theta).rho, torch.Tensor)


def test_a_w_v_module_that_is_not_tanh_is_not_factored():
    """A module named and shaped like the area network (``W``, ``V``, ``in_scale``) but with
    ``relu`` is not ``W tanh(V x)``: the template must not take the Kronecker factors, and its
    Jacobian is eq. (13) with ``relu`` (numpy, by hand)."""
    tmpl = WeightTemplate(TanhLayer(relu=True))
    assert not tmpl.factored
    assert WeightTemplate(TanhLayer()).factored
    g = torch.Generator().manual_seed(1)
    theta = torch.randn(2, tmpl.num_params, generator=g, dtype=F64)
    x = torch.randn(2, 4, generator=g, dtype=F64)
    out, H = tmpl.jacobian(theta, x)
    scale = tmpl.buffers["in_scale"].numpy()
    for n in range(2):
        th = theta[n].numpy()
        W, V = th[:6].reshape(2, 3), th[6:].reshape(3, 4)
        f, J = _np_jacobian(W, V, x[n].numpy() / scale, act="relu")
        np.testing.assert_allclose(out[n].numpy(), f, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(H[n].numpy(), J, rtol=1e-12, atol=1e-14)


def test_factored_false_gives_the_dense_jacobian_of_eq_13():
    """``jacobian(..., factored=False)`` (and ``ParamEKF.jacobian``) of a factored module is
    ``H [N, m, P]`` in θ's row-major order: eq. (13) in numpy."""
    module = TanhLayer()
    tmpl = WeightTemplate(module)
    g = torch.Generator().manual_seed(2)
    theta = torch.randn(3, tmpl.num_params, generator=g, dtype=F64)
    x = torch.randn(3, 4, generator=g, dtype=F64)
    _, H = tmpl.jacobian(theta, x, factored=False)
    assert isinstance(H, torch.Tensor)
    ekf = ParamEKF(module, (3,), params=tmpl.unflatten(theta))
    _, H_ekf = ekf.jacobian(x)
    assert isinstance(H_ekf, torch.Tensor)
    scale = module.in_scale.numpy()
    for n in range(3):
        th = theta[n].numpy()
        _, J = _np_jacobian(th[:6].reshape(2, 3), th[6:].reshape(3, 4), x[n].numpy() / scale)
        np.testing.assert_allclose(H[n].numpy(), J, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(H_ekf[n].numpy(), J, rtol=1e-12, atol=1e-14)


def test_the_jacobians_order_may_not_change_after_the_first_step():
    """A learner whose covariance was built in the Kronecker order refuses a dense ``H``
    (θ's order) at a later step: ρ_k ≠ c·I reads differently in the two orders."""
    tmpl = WeightTemplate(TanhLayer())
    g = torch.Generator().manual_seed(3)
    theta = 0.3 * torch.randn(1, tmpl.num_params, generator=g, dtype=F64)
    x = torch.randn(1, 4, generator=g, dtype=F64)
    rule = EKFRule()
    state = rule.init(theta)
    pred, H = tmpl.jacobian(state.theta, x)
    assert isinstance(H, KroneckerJacobian)
    state = rule.step(state, H, 0.1 - pred)
    pred, H = tmpl.jacobian(state.theta, x, factored=False)
    with pytest.raises(ValueError, match="order"):
        rule.step(state, H, 0.1 - pred)


def test_gradient_rule_on_kronecker_factors_is_h_transpose_e_and_counts_steps():
    """GradientRule with a Kronecker Jacobian: ``θ + lr·Hᵀe`` with H of eq. (13) in θ's order
    (numpy), and the step count ``k`` advances by one per step."""
    tmpl = WeightTemplate(TanhLayer())
    g = torch.Generator().manual_seed(4)
    theta = torch.randn(2, tmpl.num_params, generator=g, dtype=F64)
    x = torch.randn(2, 4, generator=g, dtype=F64)
    e = torch.randn(2, 2, generator=g, dtype=F64)
    _, H = tmpl.jacobian(theta, x)
    assert isinstance(H, KroneckerJacobian)
    rule = GradientRule(lr=0.3)
    state = rule.step(rule.init(theta), H, e)
    scale = tmpl.buffers["in_scale"].numpy()
    for n in range(2):
        th = theta[n].numpy()
        _, J = _np_jacobian(th[:6].reshape(2, 3), th[6:].reshape(3, 4), x[n].numpy() / scale)
        np.testing.assert_allclose(
            state.theta[n].numpy(), th + 0.3 * J.T @ e[n].numpy(), rtol=1e-12, atol=1e-14
        )
    assert state.k == 1
    assert rule.step(state, H, e).k == 2


def test_gain_norm_is_the_mean_diagonal_and_empty_batches_are_refused():
    """``gain_norm`` is ``tr ρ / P`` per filter: ``init_cov`` at the start (ρ = cI), and
    ``Υ(0) = init_noise`` (EKFRule's doc); a batch shape with a zero size is refused
    (non-empty positive sizes)."""
    lin = nn.Linear(3, 2).double()  # P = 8
    ekf = ParamEKF(lin, (2, 3), init_cov=4.0, init_noise=0.25)
    torch.testing.assert_close(ekf.gain_norm(), torch.full((2, 3), 4.0, dtype=F64))
    torch.testing.assert_close(ekf.upsilon, torch.full((6,), 0.25, dtype=F64))
    with pytest.raises(ValueError, match="batch_shape"):
        ParamEKF(lin, (0,))


class _Scalar(nn.Module):
    """``a·x₀``: one input to a scalar, not to a vector ``[m]``."""

    def __init__(self):
        super().__init__()
        self.a = nn.Parameter(torch.tensor(0.5, dtype=F64))

    def forward(self, x):
        return self.a * x[0]


def test_a_module_with_a_scalar_output_is_refused():
    """The module must map one input to a vector ``[m]`` (module doc): a scalar output is
    refused with that message rather than read as ``m`` = the batch size."""
    ekf = ParamEKF(_Scalar(), (2,))
    with pytest.raises(ValueError, match="vector"):
        ekf.step(torch.ones(2, 1, dtype=F64), torch.ones(2, 1, dtype=F64))


def _np_pooled_ekf(zeta, rho, ups, k, H, e, lr, ups_given=False):
    """Eqs (11), (12), (14), (14b) with S samples stacked (EKFOptimizer's doc), numpy
    (``ups_given``: ``Υ_k`` already updated, eq. 14b skipped)."""
    if not ups_given:
        ups = ups + (np.mean(np.sum(e * e, -1)) - ups) / k
    Hs, es = H.reshape(-1, H.shape[-1]), e.reshape(-1)
    lam = rho @ Hs.T @ np.linalg.inv(Hs @ rho @ Hs.T + ups * np.eye(len(es)))
    return zeta + lr * lam @ es, rho - lam @ Hs @ rho, ups


def test_ekf_along_sequence_masks_the_jacobian_of_unreceived_entries():
    """``ekf_along_sequence`` on ``out = [x·ζ, (c⊙x)·ζ]`` (m = 2) with a reception pattern:
    each step is eqs (11)–(14) with the S samples stacked on the received entries only
    (``J ⊙ r``, ``e ⊙ r``), numpy; so an unreceived entry neither moves ζ nor shrinks ρ."""
    g = torch.Generator().manual_seed(5)
    S, T, P = 3, 6, 4
    c = torch.tensor([1.0, -2.0, 0.5, 3.0], dtype=F64)
    zeta = torch.zeros(P, dtype=F64, requires_grad=True)
    opt = EKFOptimizer([zeta], lr=0.8, init_cov=5.0, init_noise=0.2)
    inputs = torch.randn(S, T, P, generator=g, dtype=F64)
    targets = torch.randn(S, T, 2, generator=g, dtype=F64)
    received = torch.rand(S, T, 2, generator=g) > 0.4
    received[:, 2] = False

    def predict(x):
        J = torch.stack([x, c * x], dim=1)  # [S, 2, P]
        return J @ zeta.detach(), J

    ekf_along_sequence(opt.step, predict, inputs, targets, received)
    z, rho, ups, seen = np.zeros(P), 5.0 * np.eye(P), 0.2, 0
    X, Y, r = inputs.numpy(), targets.numpy(), received.numpy().astype(float)
    for t in range(T):
        J = np.stack([X[:, t], c.numpy() * X[:, t]], axis=1)
        H = J * r[:, t, :, None]
        e = (Y[:, t] - J @ z) * r[:, t]
        # Υ: the running mean over the steps that received anything of the samples' energy
        # at their received entries' rate (m / m_s), over the samples that received any
        count = r[:, t].sum(-1)
        if count.any():
            seen += 1
            energy = (e * e).sum(-1)[count > 0] * 2 / count[count > 0]
            ups = ups + (energy.mean() - ups) / seen
        z, rho, _ = _np_pooled_ekf(z, rho, ups, 1, H, e, 0.8, ups_given=True)
    assert seen == T - 1  # step 3 received nothing
    np.testing.assert_allclose(zeta.detach().numpy(), z, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(opt.state[zeta]["rho"].numpy(), rho, rtol=1e-9, atol=1e-12)
    assert float(opt.state[zeta]["upsilon"]) == pytest.approx(ups, rel=1e-12)


def test_ekf_optimizer_calls_the_closure_and_checks_the_residual_shape():
    """``step`` calls the closure once first (Lightning's hooks); a residual that is not
    ``[S, m]`` of the Jacobian ``[S, m, P]`` is refused with the documented message."""
    zeta = torch.zeros(2, dtype=F64, requires_grad=True)
    opt = EKFOptimizer([zeta])
    calls = []
    jac = torch.ones(3, 1, 2, dtype=F64)
    opt.step(jac, torch.ones(3, 1, dtype=F64), closure=lambda: calls.append(1))
    assert calls == [1]
    with pytest.raises(ValueError, match="jacobian must be"):
        opt.step(jac, torch.ones(1, 3, dtype=F64))


# ---------------------------------------------------------------------------- adaptive_kf


class _TimeVarying(df.LinearGaussianModel):
    """A linear model whose ``F_k``, ``B_k``, ``H_k``, ``Q_k``, ``R_k`` all change with ``k``
    (so a step that reads the wrong time index is visible)."""

    time_varying = True

    def __init__(self):
        super().__init__(
            torch.eye(2, dtype=F64), torch.ones(3, 2, dtype=F64),
            0.1 * torch.eye(2, dtype=F64), 0.2 * torch.eye(3, dtype=F64),
            torch.tensor([0.5, -0.2], dtype=F64), torch.diag(torch.tensor([0.4, 0.9], dtype=F64)),
            B=torch.tensor([[1.0, 0.0], [0.5, 1.0]], dtype=F64),
        )  # fmt: skip

    @staticmethod
    def mats(k):
        """``(F, B, H, Q, R)`` at step ``k`` as numpy arrays (the model's definition)."""
        c, s = np.cos(0.3 * k), np.sin(0.3 * k)
        F = np.array([[0.9 * c, 0.2], [-0.1 * s, 0.8 + 0.05 * k]])
        B = np.array([[1.0 + 0.1 * k, 0.0], [0.3, 0.7 - 0.05 * k]])
        H = np.array([[1.0, 0.2 * k], [0.5 - 0.1 * k, 1.0], [0.3, -0.4]])
        Q = np.diag([0.05 + 0.01 * k, 0.02 + 0.02 * k])
        R = np.diag([0.1 + 0.02 * k, 0.3, 0.2 + 0.01 * k])
        return F, B, H, Q, R

    def transition_matrix(self, k):
        return torch.tensor(self.mats(k)[0])

    def control_matrix(self, k):
        return torch.tensor(self.mats(k)[1])

    def observation_matrix(self, k):
        return torch.tensor(self.mats(k)[2])

    def process_cov(self, k):
        return torch.tensor(self.mats(k)[3])

    def measurement_cov(self, k):
        return torch.tensor(self.mats(k)[4])


def _np_zhang(model_mats, x, P, th, S, Ups, y, u, k, lam, obs):
    """One step ``k → k+1`` of Zhang's eq. (5) (module docstring), literally, on the
    received entries ``obs`` of ``y`` (the others' rows of ``C``, ``y``, ``R`` dropped)."""
    F, B, _, Q, _ = model_mats(k)
    _, _, H, _, R = model_mats(k + 1)
    C, Rm = H[obs], R[np.ix_(obs, obs)]
    x_pred = F @ x + B @ (u + th)
    Pp = F @ P @ F.T + Q
    ytil = y[obs] - C @ x_pred
    Sig = C @ Pp @ C.T + Rm
    K = Pp @ C.T @ np.linalg.inv(Sig)
    P_new = (np.eye(len(x)) - K @ C) @ Pp
    drive = F @ Ups + B
    Ups_new = (np.eye(len(x)) - K @ C) @ drive  # (5e)
    Om = C @ drive  # (5f)
    Lam = np.linalg.inv(lam * Sig + Om @ S @ Om.T)  # (5g)
    Gam = S @ Om.T @ Lam  # (5h)
    S_new = S / lam - S @ Om.T @ Lam @ Om @ S / lam  # (5i)
    th_new = th + Gam @ ytil
    x_new = x_pred + K @ ytil + Ups_new @ (th_new - th)
    return x_new, P_new, th_new, S_new, Ups_new


def test_zhang_filter_is_eq_5_on_a_time_varying_model_with_missing_entries():
    """The adaptive KF over a sequence (λ = 0.6, θ̂_0 ≠ 0, S_0 = 2 I, some entries not
    received) against eq. (5) in numpy: step ``k → k+1`` reads ``F_k, B_k, Q_k`` and ``H_{k+1},
    R_{k+1}``; means, covariances, attack estimates and S_k, and the Wald score θ̂ᵀS⁻¹θ̂ with
    the χ²_du threshold (scipy)."""
    model = _TimeVarying()
    g = torch.Generator().manual_seed(7)
    T = 8
    ys = torch.randn(T, 3, generator=g, dtype=F64)
    us = torch.randn(T, 2, generator=g, dtype=F64)
    mask = torch.rand(T, 3, generator=g) > 0.3
    mask[3] = torch.tensor([True, False, False])
    attack0 = torch.tensor([0.3, -0.1], dtype=F64)
    out = adaptive_kalman_filter(model, ys, us, mask=mask, forgetting=0.6, attack_cov0=2.0,
                                 attack0=attack0, false_alarm_rate=0.05)  # fmt: skip
    x, P = np.array([0.5, -0.2]), np.diag([0.4, 0.9])
    th, S, Ups = attack0.numpy(), 2.0 * np.eye(2), np.zeros((2, 2))
    thr = chi2.ppf(0.95, 2)
    for k in range(T):
        obs = mask[k].numpy()
        x, P, th, S, Ups = _np_zhang(_TimeVarying.mats, x, P, th, S, Ups, ys[k].numpy(),
                                     us[k].numpy(), k, 0.6, obs)  # fmt: skip
        np.testing.assert_allclose(out.means[k].numpy(), x, rtol=1e-9, atol=1e-11)
        np.testing.assert_allclose(out.covs[k].numpy(), P, rtol=1e-9, atol=1e-11)
        np.testing.assert_allclose(out.attack[k].numpy(), th, rtol=1e-9, atol=1e-11)
        np.testing.assert_allclose(out.extras["attack_covs"][k].numpy(), S, rtol=1e-9, atol=1e-11)
        score = th @ np.linalg.solve(S, th)
        assert float(out.detection.scores[k]) == pytest.approx(score, rel=1e-6)
        assert bool(out.detection.alarms[k]) == (score > thr)
    assert np.allclose(np.asarray(out.detection.threshold, dtype=float), thr)


def test_adaptive_kalman_step_uses_the_forgetting_it_is_given():
    """``adaptive_kalman_step(..., forgetting=λ)``: one step equals eq. (5) with that λ
    (numpy), not the class default."""
    model = _TimeVarying()
    state = adaptive_kalman_init(model, (), attack_cov0=1.5)
    y = torch.tensor([0.4, -0.3, 1.1], dtype=F64)
    u = torch.tensor([0.2, 0.5], dtype=F64)
    new, step_out = adaptive_kalman_step(model, state, y, u, forgetting=0.35)
    x, P, th, S, _ = _np_zhang(_TimeVarying.mats, np.array([0.5, -0.2]), np.diag([0.4, 0.9]),
                               np.zeros(2), 1.5 * np.eye(2), np.zeros((2, 2)), y.numpy(),
                               u.numpy(), 0, 0.35, np.ones(3, dtype=bool))  # fmt: skip
    np.testing.assert_allclose(new.attack.numpy(), th, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(new.attack_cov.numpy(), S, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(step_out.mean.numpy(), x, rtol=1e-9, atol=1e-12)
    assert new.k == 1


def test_the_adaptive_filter_refuses_a_model_without_inputs():
    """The attack has the input's dimension: a model with ``dim_u = 0`` is refused."""
    model = df.LinearGaussianModel(torch.eye(2, dtype=F64), torch.eye(2, dtype=F64),
                                   torch.eye(2, dtype=F64), torch.eye(2, dtype=F64),
                                   torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64))  # fmt: skip
    with pytest.raises(ValueError, match="dim_u"):
        AdaptiveKalmanFilter().init(model, ())


# ----------------------------------------------------------------------- attack_estimation


def test_bias_attack_estimator_with_distinct_process_variances_and_tau_bounds():
    """With ``process_var = (q_γ, q_γ̄)`` distinct and ``v ≠ 1``, the estimator is the Kalman
    filter on ``[γ; γ̄]`` of eq. (4) with ``Q = diag(q_γ I, q_γ̄ I)``, ``P_0 = diag(0, v I)``
    (numpy), per-entry flags included; τ = 1 lies outside ``(0, 1)``."""
    d, tau, v, qg, qb = 2, 0.7, 2.5, 1e-2, 1e-4
    I, Z = np.eye(d), np.zeros((d, d))
    F = np.block([[tau * I, (1 - tau) * I], [Z, I]])
    Hf = np.hstack([I, Z])
    Q = np.diag([qg] * d + [qb] * d)
    m, P = np.zeros(2 * d), np.diag([1e-12] * d + [v] * d)
    rng = np.random.default_rng(3)
    T = 6
    res = rng.normal(size=(T, d)) + np.array([0.5, -0.3])
    Sk = np.diag([0.2, 0.3])
    flags = np.array([[1, 1], [1, 0], [0, 0], [0, 1], [1, 1], [1, 1]], dtype=bool)
    est = BiasAttackEstimator(d, tau, gamma_bar_var=v, process_var=(qg, qb))
    st = est.init(())
    for k in range(T):
        m, P = F @ m, F @ P @ F.T + Q
        o = flags[k]
        if o.any():
            H = Hf[o]
            S = H @ P @ H.T + Sk[np.ix_(o, o)]
            K = P @ H.T @ np.linalg.inv(S)
            m = m + K @ (res[k][o] - H @ m)
            P = P - K @ S @ K.T
        st, gam, gcov = est.step(st, torch.tensor(res[k]), torch.tensor(Sk), torch.tensor(o))
        np.testing.assert_allclose(gam.numpy(), m[:d], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(gcov.numpy(), P[:d, :d], rtol=1e-9, atol=1e-12)
        assert st.k == k + 1
    with pytest.raises(ValueError, match="tau"):
        BiasAttackEstimator(d, 1.0)


@pytest.mark.parametrize("bad", [float("inf"), float("nan"), -1.0, 0.0])
@pytest.mark.parametrize("field", ["lr", "init_cov", "init_noise"])
def test_the_learning_rules_refuse_a_rate_or_covariance_that_is_not_finite_and_positive(field, bad):
    """From a fuzzing trial of the constructors: ``EKFRule`` (and with it ``ParamEKF`` and
    ``EKFOptimizer``) and ``GradientRule`` took an infinite ``lr`` or covariance, every weight
    NaN after the first update; each is refused now, naming it."""
    message = rf"{field} must be a finite number > 0"
    with pytest.raises(ValueError, match=message):
        EKFRule(**{field: bad})
    with pytest.raises(ValueError, match=message):
        EKFOptimizer([nn.Parameter(torch.zeros(2))], **{field: bad})
    if field == "lr":
        with pytest.raises(ValueError, match=message):
            GradientRule(lr=bad)


@pytest.mark.parametrize("bad", [float("inf"), float("nan"), -1e-3])
def test_the_ekf_rule_refuses_a_process_noise_that_is_not_finite_and_nonnegative(bad):
    with pytest.raises(ValueError, match=r"process_noise must be a finite number >= 0"):
        EKFRule(process_noise=bad)
    assert EKFRule(process_noise=0.0).process_noise == 0.0
