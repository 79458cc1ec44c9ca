"""The RTS smoother against the dense joint Gaussian: x_{1:T} and y_{1:T} of a linear model
are jointly Gaussian, so E[x_k | y_{1:T}], Cov(x_k | y_{1:T}) and Cov(x_k, x_{k+1} | y_{1:T})
are a conditional of one big Gaussian; with inputs, a time-varying F, lost entries and a
batch of runs; and its gradient by gradcheck."""

from __future__ import annotations

import dataclasses

import pytest
import torch

import difffilter as df
from difffilter.smoother import kalman_smoother, rts_smoother

F64 = torch.float64
F = torch.tensor([[1.0, 0.2], [-0.1, 0.9]], dtype=F64)
H = torch.tensor([[1.0, 0.0]], dtype=F64)
B = torch.tensor([[0.0], [0.5]], dtype=F64)
Q = torch.tensor([[0.05, 0.01], [0.01, 0.08]], dtype=F64)
R = torch.tensor([[0.3]], dtype=F64)
M0 = torch.tensor([0.5, -1.0], dtype=F64)
P0 = torch.tensor([[1.0, 0.2], [0.2, 0.5]], dtype=F64)


class Turning(df.LinearGaussianModel):
    time_varying = True

    def transition_matrix(self, k):
        return self.F * (1.0 + 0.05 * k)


def _dense_posterior(model, ys, us, received):
    """The conditional of x_{1:T} given the received y's, from the joint Gaussian of
    z = (x_0, w_1 … w_T, v_1 … v_T): every x_k and y_k is linear in z (plus the inputs)."""
    T, dx, dy = ys.shape[0], 2, 1
    nz = dx + T * dx + T * dy
    cov_z = torch.block_diag(P0, *([Q] * T), *([R] * T))
    mean_z = torch.cat([M0, torch.zeros(nz - dx, dtype=F64)])
    coef = torch.zeros(dx, nz, dtype=F64)
    coef[:, :dx] = torch.eye(dx, dtype=F64)
    shift = torch.zeros(dx, dtype=F64)
    xs_c, xs_s, ys_c, ys_s = [], [], [], []
    for k in range(1, T + 1):
        A = model.transition_matrix(k - 1)
        coef = A @ coef
        coef[:, dx + (k - 1) * dx : dx + k * dx] += torch.eye(dx, dtype=F64)
        shift = A @ shift + (B @ us[k - 1] if us is not None else 0)
        yc = H @ coef
        yc[:, dx + T * dx + (k - 1) * dy : dx + T * dx + k * dy] += torch.eye(dy, dtype=F64)
        xs_c.append(coef.clone())
        xs_s.append(shift.clone())
        ys_c.append(yc)
        ys_s.append(H @ shift)
    x0 = torch.zeros(dx, nz, dtype=F64)
    x0[:, :dx] = torch.eye(dx, dtype=F64)
    X, Y = torch.cat([x0] + xs_c), torch.cat(ys_c)  # x_0 first
    mx, my = (
        X @ mean_z + torch.cat([torch.zeros(dx, dtype=F64)] + xs_s),
        Y @ mean_z + torch.cat(ys_s),
    )
    keep = received.reshape(-1)
    Y, my, y = Y[keep], my[keep], ys.reshape(-1)[keep]
    sxy, syy = X @ cov_z @ Y.T, Y @ cov_z @ Y.T
    gain = sxy @ torch.linalg.inv(syy)
    mean = mx + gain @ (y - my)
    cov = X @ cov_z @ X.T - gain @ sxy.T
    return mean.reshape(T + 1, dx), cov  # steps 0 … T


@pytest.mark.parametrize("varying", [False, True])
def test_the_smoother_is_the_dense_gaussian_conditional(varying):
    cls = Turning if varying else df.LinearGaussianModel
    model = cls(F, H, Q, R, M0, P0, B=B)
    T, runs = 7, 3
    gen = torch.Generator().manual_seed(0)
    us = torch.randn(runs, T, 1, dtype=F64, generator=gen)
    _, ys, _ = model.simulate(T, (runs,), us, generator=gen)
    mask = torch.ones_like(ys, dtype=torch.bool)
    mask[1, 2] = mask[2, 4:6] = False  # lost entries in two runs
    out = kalman_smoother(model, ys, us, mask=mask)
    for r in range(runs):
        mean, cov = _dense_posterior(model, ys[r], us[r], mask[r])
        torch.testing.assert_close(out.means[r], mean[1:], rtol=1e-10, atol=1e-10)
        torch.testing.assert_close(out.initial_mean[r], mean[0], rtol=1e-10, atol=1e-10)
        torch.testing.assert_close(out.initial_cov[r], cov[:2, :2], rtol=1e-9, atol=1e-11)
        torch.testing.assert_close(out.initial_cross[r], cov[:2, 2:4], rtol=1e-9, atol=1e-11)
        for k in range(T):  # step k + 1: rows 2 (k + 1) on
            j = 2 * (k + 1)
            torch.testing.assert_close(out.covs[r, k], cov[j : j + 2, j : j + 2], rtol=1e-9,
                                       atol=1e-11)  # fmt: skip
            if k < T - 1:
                cross = cov[j : j + 2, j + 2 : j + 4]
                torch.testing.assert_close(out.cross_covs[r, k], cross, rtol=1e-9, atol=1e-11)
    whole = kalman_smoother(model, ys, us)  # every entry received: the shared-covariance path
    for r in range(runs):
        mean, _ = _dense_posterior(model, ys[r], us[r], torch.ones_like(mask[r]))
        torch.testing.assert_close(whole.means[r], mean[1:], rtol=1e-10, atol=1e-10)
    unpredicted = dataclasses.replace(out.filtered, pred_covs=None)  # P⁻ from the model
    again = rts_smoother(model, unpredicted)
    torch.testing.assert_close(again.covs, out.covs, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(again.means, out.means, rtol=1e-10, atol=1e-12)
    # the last step is the filter's, and smoothing never widens the filter's uncertainty
    torch.testing.assert_close(out.means[:, -1], out.filtered.means[:, -1], rtol=0, atol=0)
    shrink = out.filtered.covs.expand_as(out.covs) - out.covs
    assert bool((torch.linalg.eigvalsh(shrink) > -1e-12).all())


def test_the_smoother_is_differentiable_and_refuses_what_it_cannot_smooth():
    model = df.LinearGaussianModel(F, H, Q, R, M0, P0)
    ys = torch.randn(1, 4, 1, dtype=F64, generator=torch.Generator().manual_seed(1))
    ys.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda y: kalman_smoother(model, y).means.sum(-1), (ys,))
    with pytest.raises(TypeError, match="filtered must be the FilterResult"):
        rts_smoother(model, ys)
    with pytest.raises(TypeError, match="the RTS smoother needs a state-space model"):
        rts_smoother(object(), df.kalman_filter(model, ys.detach()))


def test_one_step_shared_covariances_and_gradients_in_the_models_parameters():
    """From the review: T = 1 on a time-varying model failed (no transition to stack); the
    covariance recursion ran once per run where the filter's covariances are shared (2,000
    runs × 300 steps: 2 s and 73 MiB for each of covs, gains, cross_covs); the gradient in
    the model's matrices was untested."""
    varying = Turning(F, H, Q, R, M0, P0, B=B)
    ys = torch.randn(3, 1, 1, dtype=F64, generator=torch.Generator().manual_seed(2))
    one = kalman_smoother(varying, ys, torch.zeros(3, 1, 1, dtype=F64))
    torch.testing.assert_close(one.means, one.filtered.means, rtol=0, atol=0)
    assert one.gains.shape == (3, 0, 2, 2)
    model = df.LinearGaussianModel(F, H, Q, R, M0, P0)
    ys = torch.randn(50, 20, 1, dtype=F64, generator=torch.Generator().manual_seed(3))
    shared = kalman_smoother(model, ys)
    per_run = kalman_smoother(model, ys, mask=torch.ones_like(ys, dtype=torch.bool))
    assert shared.gains.shape == per_run.gains.shape == (50, 19, 2, 2)
    assert shared.gains.stride(0) == 0 and shared.cross_covs.stride(0) == 0  # computed once
    torch.testing.assert_close(shared.means, per_run.means, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(shared.covs, per_run.covs, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(shared.cross_covs.expand_as(per_run.cross_covs), per_run.cross_covs,
                               rtol=1e-12, atol=1e-12)  # fmt: skip

    def smoothed(f, q):  # (q symmetrised: gradcheck perturbs one entry at a time)
        model = df.LinearGaussianModel(f, H, 0.5 * (q + q.mT), R, M0, P0)
        return kalman_smoother(model, ys[:2, :4]).means

    f = F.clone().requires_grad_(True)
    q = Q.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(smoothed, (f, q))


def test_the_smoother_is_public():
    import difffilter.smoother as smoother

    assert {"kalman_smoother", "rts_smoother", "SmootherResult"} <= set(df.__all__)
    assert df.kalman_smoother is smoother.kalman_smoother
    assert df.SmootherResult is smoother.SmootherResult


def test_a_result_of_another_model_is_refused():
    """From an identification trial: a Kalman filter result of another model (or a stale one
    in an EM loop) smoothed silently wrong (means 0.48 off); a particle filter's too."""
    model = df.LinearGaussianModel(F, H, Q, R, M0, P0)
    ys = torch.randn(2, 6, 1, dtype=F64, generator=torch.Generator().manual_seed(4))
    other = df.LinearGaussianModel(0.9 * F, H, Q, R, M0, P0)
    with pytest.raises(ValueError, match="filtered is not this model's Kalman filter result"):
        rts_smoother(model, df.kalman_filter(other, ys))
    moved = df.LinearGaussianModel(F, H, Q, R, M0 + 2.0, P0)  # another prior mean
    with pytest.raises(ValueError, match="filtered is not this model's Kalman filter result"):
        rts_smoother(model, df.kalman_filter(moved, ys))
    # one run's model other (per run, in very different units): judged per run
    scales = torch.tensor([1.0, 1e4], dtype=F64)[:, None, None]
    sweep = df.LinearGaussianModel(F.expand(2, 2, 2), H, Q * scales, R, M0, P0 * scales)
    stale = df.LinearGaussianModel(torch.stack([F, 0.5 * F]), H, Q * scales, R, M0, P0 * scales)
    with pytest.raises(ValueError, match="filtered is not this model's Kalman filter result"):
        rts_smoother(sweep, df.kalman_filter(stale, ys))
    pf = df.particle_filter(model, ys, num_particles=50, generator=torch.Generator().manual_seed(0))
    with pytest.raises(TypeError, match="filtered must be the FilterResult"):
        rts_smoother(model, pf)


def test_the_smoother_takes_its_own_filters_result_in_float32_and_diffuse_priors():
    """From the review: a fixed 1e-6 check on every step refused the filter's own result
    where its shared-covariance path differs from the plain recursion by round-off (float32
    at T = 30; a diffuse prior with a tiny Q at T = 3 in float64)."""
    model = df.LinearGaussianModel(F, H, Q, R, M0, P0).to(torch.float32)
    ys = torch.randn(4, 60, 1, generator=torch.Generator().manual_seed(5))
    for T in range(2, 61, 7):  # its own result accepted, and the same as the per-run path's
        shared = kalman_smoother(model, ys[:, :T])
        every = torch.ones_like(ys[:, :T], dtype=torch.bool)
        per_run = kalman_smoother(model, ys[:, :T], mask=every)
        torch.testing.assert_close(shared.means, per_run.means, rtol=1e-4, atol=1e-5)
    dt = 0.1
    Fca = torch.tensor([[1, dt, dt * dt / 2], [0, 1, dt], [0, 0, 1]], dtype=F64)
    diffuse = df.LinearGaussianModel(Fca, torch.tensor([[1.0, 0, 0]], dtype=F64),
                                     1e-10 * torch.eye(3, dtype=F64), 1e-2 * torch.eye(1, dtype=F64),
                                     torch.zeros(3, dtype=F64), 1e6 * torch.eye(3, dtype=F64))  # fmt: skip
    for T in (2, 3, 4, 10):
        ys = torch.randn(2, T, 1, dtype=F64, generator=torch.Generator().manual_seed(T))
        out = kalman_smoother(diffuse, ys)
        assert bool(out.means.isfinite().all()) and bool(out.initial_cov.isfinite().all())


DT, GRAVITY = 0.1, 9.81


def _swing(x, u=None):  # a pendulum: angle, rate (and a torque input)
    rate = x[..., 1] - DT * GRAVITY * torch.sin(x[..., 0])
    if u is not None:
        rate = rate + DT * u[..., 0]
    return torch.stack([x[..., 0] + DT * x[..., 1], rate], -1)


def _sine(x):
    return torch.sin(x[..., :1])


def test_the_extended_smoother_is_a_numpy_extended_rts_smoother():
    """The EKF forward and the RTS backward with Jacobians at the filtered means, written
    out in numpy, against difffilter.extended_kalman_smoother on a pendulum with inputs;
    and on a linear model it is the Kalman smoother."""
    import numpy as np

    Qp = np.diag([1e-4, 4e-3])
    Rp = np.array([[0.05]])
    m0, P0p = np.array([0.8, 0.0]), np.diag([0.1, 0.2])
    model = df.NonlinearGaussianModel(_swing, _sine, torch.as_tensor(Qp), torch.as_tensor(Rp),
                                      torch.as_tensor(m0), torch.as_tensor(P0p), dim_u=1)  # fmt: skip
    T = 25
    gen = torch.Generator().manual_seed(7)
    us = 0.3 * torch.randn(2, T, 1, dtype=F64, generator=gen)
    _, ys, _ = model.simulate(T, (2,), us, generator=gen)
    out = df.extended_kalman_smoother(model, ys, us)

    def f(x, u):
        return np.array([x[0] + DT * x[1], x[1] - DT * GRAVITY * np.sin(x[0]) + DT * u[0]])

    def jac(x):
        return np.array([[1.0, DT], [-DT * GRAVITY * np.cos(x[0]), 1.0]])

    for r in range(2):
        y, u = ys[r].numpy(), us[r].numpy()
        ms, Ps, pm, pP, Fs = [m0], [P0p], [], [], []
        m, P = m0, P0p
        for k in range(T):
            J = jac(m)
            mp, Pp = f(m, u[k]), J @ P @ J.T + Qp
            Hk = np.array([[np.cos(mp[0]), 0.0]])
            S = Hk @ Pp @ Hk.T + Rp
            K = Pp @ Hk.T @ np.linalg.inv(S)
            m = mp + K @ (y[k] - np.sin(mp[:1]))
            P = (np.eye(2) - K @ Hk) @ Pp @ (np.eye(2) - K @ Hk).T + K @ Rp @ K.T
            ms.append(m), Ps.append(P), pm.append(mp), pP.append(Pp), Fs.append(J)
        sm, sP, cross = [None] * (T + 1), [None] * (T + 1), [None] * T
        sm[T], sP[T] = ms[T], Ps[T]
        for k in range(T - 1, -1, -1):
            G = Ps[k] @ Fs[k].T @ np.linalg.inv(pP[k])
            sm[k] = ms[k] + G @ (sm[k + 1] - pm[k])
            sP[k] = Ps[k] + G @ (sP[k + 1] - pP[k]) @ G.T
            cross[k] = G @ sP[k + 1]
        torch.testing.assert_close(
            out.means[r], torch.as_tensor(np.stack(sm[1:])), rtol=1e-9, atol=1e-10
        )
        torch.testing.assert_close(
            out.covs[r], torch.as_tensor(np.stack(sP[1:])), rtol=1e-9, atol=1e-11
        )
        torch.testing.assert_close(out.cross_covs[r], torch.as_tensor(np.stack(cross[1:])),
                                   rtol=1e-9, atol=1e-11)  # fmt: skip
        torch.testing.assert_close(
            out.initial_mean[r], torch.as_tensor(sm[0]), rtol=1e-9, atol=1e-10
        )
        torch.testing.assert_close(out.initial_cross[r], torch.as_tensor(cross[0]), rtol=1e-9,
                                   atol=1e-11)  # fmt: skip
    linear = df.LinearGaussianModel(F, H, Q, R, M0, P0)
    wrapped = df.NonlinearGaussianModel(lambda x: x @ F.mT, lambda x: x @ H.mT, Q, R, M0, P0)
    ys = torch.randn(3, 8, 1, dtype=F64, generator=torch.Generator().manual_seed(8))
    a, b = kalman_smoother(linear, ys), df.extended_kalman_smoother(wrapped, ys)
    torch.testing.assert_close(b.means, a.means, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(b.covs, a.covs, rtol=1e-10, atol=1e-12)
    with pytest.raises(ValueError, match=r"us must have T = 25 steps, one per measurement"):
        rts_smoother(model, out.filtered, us[:, :3])


def test_a_nonlinear_models_own_result_is_taken_and_another_prior_mean_refused():
    """From the final review: the check read the first predicted mean as F_0 m0, which for a
    nonlinear model is its linearisation, not f(m0): an EKF result of the model itself was
    refused. The model's own transition is the prediction (with the inputs, where given)."""
    Qp, Rp = torch.diag(torch.tensor([1e-4, 4e-3], dtype=F64)), torch.tensor([[0.05]], dtype=F64)
    m0, P0p = torch.tensor([0.8, 0.0], dtype=F64), torch.diag(torch.tensor([0.1, 0.2], dtype=F64))
    free = df.NonlinearGaussianModel(_swing, _sine, Qp, Rp, m0, P0p)
    ys = torch.randn(2, 6, 1, dtype=F64, generator=torch.Generator().manual_seed(9)) * 0.3
    out = df.extended_kalman_smoother(free, ys)
    torch.testing.assert_close(out.means[:, -1], out.filtered.means[:, -1], rtol=0, atol=0)
    driven = df.NonlinearGaussianModel(_swing, _sine, Qp, Rp, m0, P0p, dim_u=1)
    moved = df.NonlinearGaussianModel(_swing, _sine, Qp, Rp, m0 + 0.5, P0p, dim_u=1)
    us = torch.ones(2, 6, 1, dtype=F64)
    with pytest.raises(ValueError, match="filtered is not this model's Kalman filter result"):
        rts_smoother(driven, df.extended_kalman_filter(moved, ys, us), us)


def _numpy_unscented_rts(m0, P0, means, covs, pred_means, pred_covs, f, us, Qp, alpha, beta,
                         kappa):  # fmt: skip
    """Särkkä's unscented RTS smoother (2008, eqs. for D_{k+1}, G_k) written out in numpy from
    a filter's ``m_k, P_k`` (k = 1 … T) and ``m⁻_{k+1}, P⁻_{k+1}`` (k = 0 … T − 1):
    ``(smoothed means [T + 1], covs [T + 1], gains [T])`` with the prior first."""
    import numpy as np

    n = m0.shape[0]
    lam = alpha**2 * (n + kappa) - n
    wm = np.full(2 * n + 1, 0.5 / (n + lam))
    wm[0] = lam / (n + lam)
    wc = wm.copy()
    wc[0] += 1.0 - alpha**2 + beta
    ms, Ps = [m0, *means], [P0, *covs]
    T = len(means)
    sm, sP, G = [None] * (T + 1), [None] * (T + 1), [None] * T
    sm[T], sP[T] = ms[T], Ps[T]
    for k in range(T - 1, -1, -1):
        L = np.linalg.cholesky(Ps[k]) * np.sqrt(n + lam)
        X = np.vstack([ms[k], ms[k] + L.T, ms[k] - L.T])  # rows: the 2n + 1 points
        FX = np.stack([f(x, us[k]) for x in X])
        mp = wm @ FX
        D = sum(wc[i] * np.outer(X[i] - ms[k], FX[i] - mp) for i in range(2 * n + 1))
        Pp = sum(wc[i] * np.outer(FX[i] - mp, FX[i] - mp) for i in range(2 * n + 1)) + Qp
        np.testing.assert_allclose(mp, pred_means[k], rtol=1e-10, atol=1e-12)  # the UKF's own
        np.testing.assert_allclose(Pp, pred_covs[k], rtol=1e-10, atol=1e-12)
        G[k] = D @ np.linalg.inv(Pp)
        sm[k] = ms[k] + G[k] @ (sm[k + 1] - mp)
        sP[k] = Ps[k] + G[k] @ (sP[k + 1] - Pp) @ G[k].T
    return sm, sP, G


@pytest.mark.parametrize("points", [(1.0, 2.0, 0.0), (0.5, 2.0, 1.0)])
def test_the_unscented_smoother_is_a_numpy_unscented_rts_smoother(points):
    """Särkkä's unscented RTS smoother written out in numpy (sigma points, weights, D_{k+1}
    and G_k of its own) on the UKF's filtered moments, against
    difffilter.unscented_kalman_smoother on a pendulum with inputs, for the default sigma
    points and another (α, β, κ)."""
    import numpy as np

    Qp, Rp = np.diag([1e-4, 4e-3]), np.array([[0.05]])
    m0, P0p = np.array([0.8, 0.0]), np.diag([0.1, 0.2])
    model = df.NonlinearGaussianModel(_swing, _sine, torch.as_tensor(Qp), torch.as_tensor(Rp),
                                      torch.as_tensor(m0), torch.as_tensor(P0p), dim_u=1)  # fmt: skip
    T = 20
    gen = torch.Generator().manual_seed(11)
    us = 0.3 * torch.randn(2, T, 1, dtype=F64, generator=gen)
    _, ys, _ = model.simulate(T, (2,), us, generator=gen)
    sp = df.SigmaPoints(*points)
    out = df.unscented_kalman_smoother(model, ys, us, sigma_points=sp)

    def f(x, u):
        return np.array([x[0] + DT * x[1], x[1] - DT * GRAVITY * np.sin(x[0]) + DT * u[0]])

    filt = out.filtered
    for r in range(2):
        sm, sP, G = _numpy_unscented_rts(
            m0, P0p, filt.means[r].numpy(), filt.covs[r].numpy(), filt.pred_means[r].numpy(),
            filt.pred_covs[r].numpy(), f, us[r].numpy(), Qp, *points,
        )  # fmt: skip
        torch.testing.assert_close(out.means[r], torch.as_tensor(np.stack(sm[1:])), rtol=1e-9,
                                   atol=1e-11)  # fmt: skip
        torch.testing.assert_close(out.covs[r], torch.as_tensor(np.stack(sP[1:])), rtol=1e-9,
                                   atol=1e-12)  # fmt: skip
        torch.testing.assert_close(out.gains[r], torch.as_tensor(np.stack(G[1:])), rtol=1e-9,
                                   atol=1e-11)  # fmt: skip
        cross = [G[k] @ sP[k + 1] for k in range(T)]
        torch.testing.assert_close(out.cross_covs[r], torch.as_tensor(np.stack(cross[1:])),
                                   rtol=1e-9, atol=1e-12)  # fmt: skip
        torch.testing.assert_close(out.initial_mean[r], torch.as_tensor(sm[0]), rtol=1e-9,
                                   atol=1e-11)  # fmt: skip
        torch.testing.assert_close(out.initial_cov[r], torch.as_tensor(sP[0]), rtol=1e-9,
                                   atol=1e-12)  # fmt: skip
    # the smoother moved the estimates: not the filter's (but the last step's, its own)
    assert (out.means[:, :-1] - filt.means[:, :-1]).abs().max() > 1e-3
    torch.testing.assert_close(out.means[:, -1], filt.means[:, -1], rtol=0, atol=0)


def test_the_unscented_smoother_is_the_rts_smoother_on_a_linear_model():
    """The sigma points carry a linear map exactly: D_k = P_k F_kᵀ, the Kalman smoother's
    (with inputs, lost entries and a time-varying F, three runs)."""
    model = Turning(F, H, Q, R, M0, P0, B=B)
    gen = torch.Generator().manual_seed(12)
    us = torch.randn(3, 9, 1, dtype=F64, generator=gen)
    _, ys, _ = model.simulate(9, (3,), us, generator=gen)
    mask = torch.rand(3, 9, 1, generator=gen) > 0.3
    a = kalman_smoother(model, ys, us, mask=mask)
    b = df.unscented_kalman_smoother(model, ys, us, mask=mask)
    for name in ("means", "covs", "cross_covs", "gains", "initial_mean", "initial_cov",
                 "initial_cross"):  # fmt: skip
        torch.testing.assert_close(getattr(b, name), getattr(a, name), rtol=1e-9, atol=1e-12,
                                   msg=name)  # fmt: skip


def test_the_unscented_smoother_is_differentiable_public_and_refuses_another_filter():
    Qp, Rp = torch.diag(torch.tensor([1e-4, 4e-3], dtype=F64)), torch.tensor([[0.05]], dtype=F64)
    m0, P0p = torch.tensor([0.8, 0.0], dtype=F64), torch.diag(torch.tensor([0.1, 0.2], dtype=F64))
    model = df.NonlinearGaussianModel(_swing, _sine, Qp, Rp, m0, P0p)
    ys = 0.3 * torch.randn(2, 5, 1, dtype=F64, generator=torch.Generator().manual_seed(13))
    assert torch.autograd.gradcheck(
        lambda y: df.unscented_kalman_smoother(model, y).means.sum(-1), (ys.requires_grad_(),)
    )
    ys = ys.detach()
    assert {"unscented_kalman_smoother", "unscented_rts_smoother"} <= set(df.__all__)
    other_points = df.unscented_kalman_filter(model, ys, sigma_points=df.SigmaPoints(0.5))
    with pytest.raises(ValueError, match="not this model's unscented Kalman filter result"):
        df.unscented_rts_smoother(model, other_points)
    moved = df.NonlinearGaussianModel(_swing, _sine, Qp, Rp, m0 + 0.3, P0p)
    with pytest.raises(ValueError, match="not this model's unscented Kalman filter result"):
        df.unscented_rts_smoother(model, df.unscented_kalman_filter(moved, ys))
    with pytest.raises(TypeError, match="sigma_points must be a SigmaPoints"):
        df.unscented_kalman_smoother(model, ys, sigma_points=(1.0, 2.0, 0.0))
    # its own result at a small α too (its weights ~1e6: the check's prediction is summed as
    # the filter's, not in another order, which differed by 1.35e-12 and refused it)
    df.unscented_kalman_smoother(model, ys, sigma_points=df.SigmaPoints(1e-3))
    # its own result, in float32 too
    own = df.unscented_rts_smoother(model, df.unscented_kalman_filter(model, ys))
    torch.testing.assert_close(own.means[:, -1], own.filtered.means[:, -1], rtol=0, atol=0)
    single = df.NonlinearGaussianModel(_swing, _sine, *(t.float() for t in (Qp, Rp, m0, P0p)))
    df.unscented_kalman_smoother(single, ys.float())
