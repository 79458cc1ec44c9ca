"""Mutation review of the Kalman filter's fast paths against independent truths.

The host-array one-run step (``difffilter._kf_host_step``), the gain schedule
(``difffilter.gain_schedule``), the whole-sequence shared covariance
(``difffilter._shared_cov``) and the carry registry (``difffilter._vouched``) must give
the numbers of a plain Kalman filter (here: one written in numpy, masked entries removed
from the measurement) to round-off, and the registry must never trust a carry that
changed since it was vouched for.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import difffilter as df
from difffilter import _kf_host_step

F64 = torch.float64


def _np_step(m, P, y, u, keep, F, B, H, Q, R):
    """One Kalman step in numpy, the unreceived rows removed from ``y``, ``H``, ``R``:
    ``(mean, cov, log N(received residual; 0, S))``."""
    pm = F @ m + (B @ u if u is not None else 0.0)
    pP = F @ P @ F.T + Q
    idx = np.flatnonzero(keep)
    if len(idx) == 0:
        return pm, pP, 0.0
    Hk, Rk, yk = H[idx], R[np.ix_(idx, idx)], y[idx]
    r = yk - Hk @ pm
    S = Hk @ pP @ Hk.T + Rk
    K = pP @ Hk.T @ np.linalg.inv(S)
    mean = pm + K @ r
    cov = (np.eye(len(m)) - K @ Hk) @ pP
    _, logdet = np.linalg.slogdet(S)
    ll = -0.5 * (r @ np.linalg.solve(S, r) + logdet + len(idx) * math.log(2 * math.pi))
    return mean, cov, ll


def _rand_model(seed=0, dx=3, dy=2, du=1):
    g = np.random.default_rng(seed)
    F = np.eye(dx) * 0.9 + 0.1 * g.standard_normal((dx, dx))
    H = g.standard_normal((dy, dx))
    a = g.standard_normal((dy, dy))
    R = 0.2 * a @ a.T + 0.1 * np.eye(dy)
    b = g.standard_normal((dx, dx))
    Q = 0.05 * b @ b.T + 0.01 * np.eye(dx)
    B = g.standard_normal((dx, du))
    return F, H, Q, R, B


def _lgm(F, H, Q, R, B, cls=df.LinearGaussianModel):
    t = lambda a: torch.as_tensor(a, dtype=F64)  # noqa: E731
    dx = F.shape[0]
    return cls(t(F), t(H), t(Q), t(R), torch.zeros(dx, dtype=F64), torch.eye(dx, dtype=F64),
               B=t(B))  # fmt: skip


class _Varying(df.LinearGaussianModel):
    """A time-varying model: every matrix read depends on ``k`` (F, Q at the transition
    out of ``k``; H, R at measurement ``k``)."""

    time_varying = True

    def transition_matrix(self, k):
        return self.F * (1.0 + 0.05 * math.sin(k))

    def process_cov(self, k):
        return self.process_noise.cov * (1.0 + 0.3 * k)

    def observation_matrix(self, k):
        return self.H * (1.0 + 0.2 * k)

    def measurement_cov(self, k):
        return self.measurement_noise.cov * (1.0 + 0.1 * k)


def _np_matrices(model, k):
    n = lambda t: t.detach().numpy()  # noqa: E731
    return (n(model.transition_matrix(k)), n(model.control_matrix(k)),
            n(model.observation_matrix(k + 1)), n(model.process_cov(k)),
            n(model.measurement_cov(k + 1)))  # fmt: skip


def test_host_step_of_a_time_varying_model_with_masks_equals_numpy(monkeypatch):
    """The host-array step (one run, no gradient, masks): mean, covariance and evidence
    of every step equal a numpy Kalman filter that drops the unreceived rows, on a
    time-varying model (F, Q read at ``k``, H, R at ``k + 1``) with ``dx != dy`` and an
    input; the host step is checked to have been taken."""
    taken = []
    real = _kf_host_step.host_step
    monkeypatch.setattr(_kf_host_step, "host_step", lambda *a: taken.append(1) or real(*a))
    F, H, Q, R, B = _rand_model(1, dx=3, dy=3)
    model = _lgm(F, H, Q, R, B, cls=_Varying)
    g = np.random.default_rng(5)
    T = 12
    ys, us = g.standard_normal((T, 3)), g.standard_normal((T, 1))
    masks = g.random((T, 3)) > 0.4
    masks[0] = True
    masks[3] = False
    masks[4] = [True, False, True]
    kf = df.KalmanFilter()
    carry = kf.init(model, ())
    m, P = np.zeros(3), np.eye(3)
    with torch.no_grad():
        for k in range(T):
            y = torch.as_tensor(np.where(masks[k], ys[k], 0.0))
            carry, out = kf.step(carry, y, torch.as_tensor(us[k]), torch.as_tensor(masks[k]))
            Fk, Bk, Hk, Qk, Rk = _np_matrices(model, k)
            m, P, ll = _np_step(m, P, ys[k], us[k], masks[k], Fk, Bk, Hk, Qk, Rk)
            np.testing.assert_allclose(out.mean.numpy(), m, rtol=1e-10, atol=1e-12)
            np.testing.assert_allclose(out.cov.numpy(), P, rtol=1e-10, atol=1e-12)
            np.testing.assert_allclose(float(out.log_likelihood), ll, rtol=1e-10, atol=1e-12)
    assert len(taken) == T


def _slow_model():
    """An LTI model (dx = dy = 2, H square, not the identity) whose second state is never
    measured alone and contracts slowly: its variance keeps moving after the gain of the
    first has settled (a schedule that stops on the gain alone, or too early, is off)."""
    F = np.array([[0.5, 0.0], [0.0, 0.995]])
    H = np.array([[1.0, 0.0], [2.0, 0.0]])
    Q = np.diag([0.3, 0.01])
    R = np.array([[0.5, 0.1], [0.1, 0.7]])
    B = np.array([[1.0], [0.5]])
    return F, H, Q, R, B


@pytest.mark.parametrize("which", ["random", "slow"])
def test_gain_schedule_steps_equal_numpy(which):
    """An unbatched LTI model's online step (the gain schedule, fused one-run step): every
    step's mean, covariance and evidence over 400 steps equal a numpy Kalman filter, on a
    random model with ``dx != dy`` and a slowly contracting one with a square,
    non-identity ``H``."""
    F, H, Q, R, B = _rand_model(2) if which == "random" else _slow_model()
    dx, dy = F.shape[0], H.shape[0]
    model = _lgm(F, H, Q, R, B)
    g = np.random.default_rng(7)
    T = 400
    ys, us = g.standard_normal((T, dy)), g.standard_normal((T, 1))
    kf = df.KalmanFilter()
    carry = kf.init(model, ())
    assert carry.gains is not None
    m, P = np.zeros(dx), np.eye(dx)
    keep = np.ones(dy, bool)
    for k in range(T):
        carry, out = kf.step(carry, torch.as_tensor(ys[k]), torch.as_tensor(us[k]))
        m, P, ll = _np_step(m, P, ys[k], us[k], keep, F, B, H, Q, R)
        np.testing.assert_allclose(out.mean.numpy(), m, rtol=1e-9, atol=1e-11)
        np.testing.assert_allclose(out.cov.numpy(), P, rtol=1e-9, atol=1e-11)
        np.testing.assert_allclose(float(out.log_likelihood), ll, rtol=1e-9, atol=1e-11)
    assert carry.gains is not None


@pytest.mark.parametrize("which", ["random", "slow"])
def test_shared_covariance_filter_equals_numpy(which):
    """The whole-sequence shared-covariance path (a batch of runs of an LTI model, no
    mask): means, covariances and log-likelihood increments of every run equal a numpy
    Kalman filter (T = 37: blocks of 8 and a short last one; ``dx != dy`` and an input)."""
    F, H, Q, R, B = _rand_model(3) if which == "random" else _slow_model()
    dx, dy = F.shape[0], H.shape[0]
    model = _lgm(F, H, Q, R, B)
    g = np.random.default_rng(8)
    T, n = 37, 3
    ys, us = g.standard_normal((n, T, dy)), g.standard_normal((n, T, 1))
    res = df.kalman_filter(model, torch.as_tensor(ys), torch.as_tensor(us))
    keep = np.ones(dy, bool)
    for i in range(n):
        m, P = np.zeros(dx), np.eye(dx)
        for t in range(T):
            m, P, ll = _np_step(m, P, ys[i, t], us[i, t], keep, F, B, H, Q, R)
            np.testing.assert_allclose(res.means[i, t].numpy(), m, rtol=1e-9, atol=1e-11)
            np.testing.assert_allclose(res.covs[i, t].numpy(), P, rtol=1e-9, atol=1e-11)
            np.testing.assert_allclose(
                float(res.log_likelihood_increments[i, t]), ll, rtol=1e-9, atol=1e-11
            )


def test_whole_sequence_filter_with_masks_equals_numpy():
    """``kalman_filter`` with runs whose masks differ (the shared covariance must not be
    used): every run's means and log-likelihood equal a numpy filter that drops the
    unreceived rows."""
    F, H, Q, R, B = _rand_model(4)
    model = _lgm(F, H, Q, R, B)
    g = np.random.default_rng(9)
    T, n = 10, 2
    ys, us = g.standard_normal((n, T, 2)), g.standard_normal((n, T, 1))
    masks = g.random((n, T, 2)) > 0.4
    res = df.kalman_filter(model, torch.as_tensor(np.where(masks, ys, 0.0)),
                           torch.as_tensor(us), mask=torch.as_tensor(masks))  # fmt: skip
    for i in range(n):
        m, P, total = np.zeros(3), np.eye(3), 0.0
        for t in range(T):
            m, P, ll = _np_step(m, P, ys[i, t], us[i, t], masks[i, t], F, B, H, Q, R)
            total += ll
            np.testing.assert_allclose(res.means[i, t].numpy(), m, rtol=1e-9, atol=1e-11)
        np.testing.assert_allclose(float(res.log_likelihood[i]), total, rtol=1e-9)


def _vouched_pair():
    eye = torch.eye(2, dtype=F64)
    model = df.LinearGaussianModel(0.9 * eye, eye + 0.1, 0.1 * eye, 0.2 * eye,
                                   torch.zeros(2, dtype=F64), eye)  # fmt: skip
    return model, df.KalmanFilter(), torch.ones(2, dtype=F64)


def test_a_normal_tensor_of_a_carry_vouched_in_inference_mode_written_in_place_is_checked():
    """Under ``torch.inference_mode()`` a one-run KF carry holds an inference mean and the
    gain schedule's covariance (a normal tensor, which keeps a version counter): a NaN
    written into that covariance in place must be validated again (the step raises,
    naming ``carry.cov``), not trusted by identity as an inference tensor would be."""
    model, kf, y = _vouched_pair()
    with torch.inference_mode():
        carry, _ = kf.step(kf.init(model, ()), y)
        assert carry.mean.is_inference() and not carry.cov.is_inference()
        carry.cov[0, 1] = float("nan")
        with pytest.raises(ValueError, match=r"carry\.cov"):
            kf.step(carry, y)


@pytest.mark.parametrize("field", ["mean", "cov"])
def test_a_one_run_host_path_carry_written_in_place_is_validated_again(field):
    """A one-run carry of a time-varying model (the host-array step: its tensors come from
    numpy) written in place with a NaN after the step vouched for it: the next step
    validates it and raises naming the field."""
    F, H, Q, R, B = _rand_model(1)
    model = _lgm(F, H, Q, R, B, cls=_Varying)
    kf, y, u = df.KalmanFilter(), torch.zeros(2, dtype=F64), torch.zeros(1, dtype=F64)
    with torch.no_grad():
        carry, _ = kf.step(kf.init(model, ()), y, u)
        carry, _ = kf.step(carry, y, u)
        getattr(carry, field)[0, ...].fill_(float("nan"))
        with pytest.raises(ValueError, match=rf"carry\.{field}"):
            kf.step(carry, y, u)


def _masked_loglik(model, ys, us, masks, y_tangent=None):
    kf, total = df.KalmanFilter(), 0.0
    carry = kf.init(model, ())
    for k in range(len(ys)):
        carry, out = kf.step(carry, ys[k], us[k], masks[k])
        total = total + out.log_likelihood
    return total


def _masked_data(T=6):
    g = torch.Generator().manual_seed(4)
    ys, us = torch.randn(T, 2, generator=g, dtype=F64), torch.randn(T, 1, generator=g, dtype=F64)
    masks = torch.tensor([[True, False], [True, True], [False, True]] * (T // 3))
    return ys, us, masks


def test_a_gradient_in_a_model_matrix_through_masked_one_run_steps(monkeypatch):
    """A model whose ``F`` requires a gradient, one run, masked steps: the gradient of the
    total log-likelihood in ``F`` equals the one with the host-array step switched off
    (the general torch update)."""
    F, H, Q, R, B = _rand_model(6)
    ys, us, masks = _masked_data()

    def grad_of_F():
        model = _lgm(F, H, Q, R, B)
        model.F.requires_grad_(True)
        (g,) = torch.autograd.grad(_masked_loglik(model, ys, us, masks), model.F)
        return g

    got = grad_of_F()
    monkeypatch.setattr(_kf_host_step, "host_step", lambda *a: None)
    torch.testing.assert_close(got, grad_of_F(), rtol=1e-10, atol=1e-12)


def test_a_forward_mode_tangent_in_y_through_masked_one_run_steps(monkeypatch):
    """A forward-mode dual ``y`` (``torch.autograd.forward_ad``: it reports no
    ``requires_grad``) through masked one-run steps: the log-likelihood's tangent equals
    the one with the host-array step switched off, and is not zero."""
    import torch.autograd.forward_ad as fwAD

    F, H, Q, R, B = _rand_model(6)
    ys, us, masks = _masked_data()
    direction = torch.ones_like(ys)

    def tangent():
        model = _lgm(F, H, Q, R, B)
        with fwAD.dual_level():
            dual = fwAD.make_dual(ys, direction)
            return fwAD.unpack_dual(_masked_loglik(model, dual, us, masks)).tangent

    got = tangent()
    monkeypatch.setattr(_kf_host_step, "host_step", lambda *a: None)
    want = tangent()
    assert want is not None and float(want.abs()) > 0
    assert got is not None
    torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-12)


def test_a_slowly_contracting_schedule_settles_on_the_fixed_point():
    """A state no measurement reaches, contracting by ρ = 0.99 a step (its variance's error
    by ρ² = 0.98): the schedule's covariance after 1,500 steps equals a numpy Kalman filter
    to 5e-12 relative (a convergence test not tightened by (1 − ρ²)/ρ² stops ~50× the
    step's change short of the fixed point)."""
    F = np.diag([0.5, 0.99])
    H = np.array([[1.0, 0.0]])
    Q, R, B = np.diag([0.3, 0.01]), np.array([[0.5]]), np.zeros((2, 1))
    model = _lgm(F, H, Q, R, B)
    kf, y, u = df.KalmanFilter(), torch.zeros(1, dtype=F64), torch.zeros(1, dtype=F64)
    carry = kf.init(model, ())
    P = np.eye(2)
    with torch.no_grad():
        for _k in range(1500):
            carry, out = kf.step(carry, y, u)
            pP = F @ P @ F.T + Q
            K = pP @ H.T @ np.linalg.inv(H @ pP @ H.T + R)
            P = (np.eye(2) - K @ H) @ pP
    assert carry.gains is not None and carry.gains.converged
    np.testing.assert_allclose(out.cov.numpy(), P, rtol=5e-12, atol=0)


def test_a_schedule_read_again_hands_out_each_step_s_own_moments():
    """One schedule, read again: stepping once more from each carry of an earlier run (the
    schedule's moments of those steps already handed out) gives the outputs of the first
    run exactly, and each equals a numpy Kalman filter's step k (not k − 1's gain)."""
    F, H, Q, R, B = _rand_model(11)
    model = _lgm(F, H, Q, R, B)
    g = np.random.default_rng(12)
    T = 20
    ys, us = g.standard_normal((T, 2)), g.standard_normal((T, 1))
    kf = df.KalmanFilter()
    carries, outs = [kf.init(model, ())], []
    for k in range(T):
        carry, out = kf.step(carries[-1], torch.as_tensor(ys[k]), torch.as_tensor(us[k]))
        carries.append(carry)
        outs.append(out)
    m, P = np.zeros(3), np.eye(3)
    for k in range(T):
        again = kf.step(carries[k], torch.as_tensor(ys[k]), torch.as_tensor(us[k]))[1]
        m, P, ll = _np_step(m, P, ys[k], us[k], np.ones(2, bool), F, B, H, Q, R)
        for name in ("mean", "cov", "innovation_cov", "log_likelihood"):
            torch.testing.assert_close(getattr(again, name), getattr(outs[k], name), rtol=0, atol=0)
        np.testing.assert_allclose(again.mean.numpy(), m, rtol=1e-9, atol=1e-11)
        np.testing.assert_allclose(float(again.log_likelihood), ll, rtol=1e-9, atol=1e-11)


def test_whole_sequence_filter_of_a_time_varying_model_equals_numpy():
    """``kalman_filter`` on a batch of runs of a time-varying model (the shared covariance
    must not be used): every run's means and log-likelihood equal a numpy filter reading
    the model at each ``k``."""
    F, H, Q, R, B = _rand_model(13)
    model = _lgm(F, H, Q, R, B, cls=_Varying)
    g = np.random.default_rng(14)
    T, n = 10, 2
    ys, us = g.standard_normal((n, T, 2)), g.standard_normal((n, T, 1))
    res = df.kalman_filter(model, torch.as_tensor(ys), torch.as_tensor(us))
    keep = np.ones(2, bool)
    for i in range(n):
        m, P, total = np.zeros(3), np.eye(3), 0.0
        for t in range(T):
            m, P, ll = _np_step(m, P, ys[i, t], us[i, t], keep, *_np_args(model, t))
            total += ll
            np.testing.assert_allclose(res.means[i, t].numpy(), m, rtol=1e-9, atol=1e-11)
        np.testing.assert_allclose(float(res.log_likelihood[i]), total, rtol=1e-9)


def _np_args(model, k):
    Fk, Bk, Hk, Qk, Rk = _np_matrices(model, k)
    return Fk, Bk, Hk, Qk, Rk
