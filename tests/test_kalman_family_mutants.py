"""Mutation-review tests of the Kalman-family core (kalman, extended, smoother,
parallel_kalman), each against an independent truth written out here: a plain numpy
Kalman filter over the received entries alone, the dense joint Gaussian of all states and
measurements, a numpy unscented transform, or a cross-algorithm identity."""

from __future__ import annotations

import dataclasses

import numpy as np
import torch
from reference import scaled_sigma_points, scaled_sigma_weights

import difffilter as df

F0 = np.array([[1.0, 0.1], [-0.2, 0.9]])
Q0 = np.array([[0.05, 0.01], [0.01, 0.03]])
R0 = np.array([[0.2, 0.05], [0.05, 0.3]])
M0 = np.array([0.3, -0.2])
P0 = np.array([[1.0, 0.2], [0.2, 0.5]])


def _h_of(k):
    """A time-varying observation matrix (differs at every k)."""
    return np.array([[1.0, 0.3 * k], [np.cos(k), 1.0]])


def _f_of(k):
    c, s = np.cos(0.3 * k), np.sin(0.3 * k)
    return 0.95 * np.array([[c, -s], [s, c]])


class _TimeVarying(df.LinearGaussianModel):
    """F and H both vary with k (F read at k − 1, H at k)."""

    time_varying = True

    def transition_matrix(self, k):
        return torch.tensor(_f_of(k), dtype=self.F.dtype)

    def observation_matrix(self, k):
        return torch.tensor(_h_of(k), dtype=self.F.dtype)


def _tv_model():
    return _TimeVarying(*(torch.tensor(a) for a in (_f_of(0), _h_of(0), Q0, R0, M0, P0)))


def _np_kf(F_of, H_of, Q, R, m0, P0_, ys, mask=None, offsets=None):
    """A plain numpy Kalman filter that updates with the received entries alone (the
    marginal model of the measurement). Returns means, covs, pred means, pred covs and the
    log-likelihood."""
    m, P, ll = m0.copy(), P0_.copy(), 0.0
    out = ([], [], [], [])
    for t, y in enumerate(ys):
        k = t + 1
        F = F_of(k - 1)
        m = F @ m + (0.0 if offsets is None else offsets[t])
        P = F @ P @ F.T + Q
        out[2].append(m.copy())
        out[3].append(P.copy())
        obs = np.ones(len(y), bool) if mask is None else mask[t]
        if obs.any():
            H, Rs = H_of(k)[obs], R[np.ix_(obs, obs)]
            r = y[obs] - H @ m
            S = H @ P @ H.T + Rs
            K = P @ H.T @ np.linalg.inv(S)
            ll += -0.5 * (r @ np.linalg.solve(S, r) + np.log(np.linalg.det(2 * np.pi * S)))
            m, P = m + K @ r, P - K @ S @ K.T
        out[0].append(m.copy())
        out[1].append(P.copy())
    return (*(np.array(o) for o in out), ll)


def _ys(shape, seed):
    return torch.randn(*shape, dtype=torch.float64, generator=torch.Generator().manual_seed(seed))


def _masks(T, seed):
    """Two runs with different lost entries (some steps lose everything)."""
    g = np.random.default_rng(seed)
    mask = g.random((2, T, 2)) > 0.35
    mask[0, 2] = False
    mask[1, 3] = [True, False]
    return mask


def _assert_filter(res, run, ref, atol=1e-9):
    means, covs, pmeans, pcovs, ll = ref
    np.testing.assert_allclose(res.means[run].numpy(), means, atol=atol)
    np.testing.assert_allclose(res.covs[run].numpy(), covs, atol=atol)
    np.testing.assert_allclose(res.pred_means[run].numpy(), pmeans, atol=atol)
    np.testing.assert_allclose(res.pred_covs[run].numpy(), pcovs, atol=atol)
    np.testing.assert_allclose(float(res.log_likelihood[run]), ll, atol=atol)


def test_batched_masked_kf_reads_time_varying_h_at_the_measurement_step():
    """Two runs, each with its own lost entries, on a model whose F and H both vary with k
    (batched, so the torch update, not the one-run host step, takes every step): each run
    equals a numpy filter on its received entries alone (H read at k, F at k − 1)."""
    T = 7
    model, ys, mask = _tv_model(), _ys((2, T, 2), 0), _masks(T, 0)
    for method in ("sequential", "parallel"):
        res = df.kalman_filter(model, ys, mask=torch.tensor(mask), method=method)
        for run in range(2):
            ref = _np_kf(_f_of, _h_of, Q0, R0, M0, P0, ys[run].numpy(), mask[run])
            _assert_filter(res, run, ref)


def test_kalman_step_objects_match_numpy_on_batched_masked_steps():
    """The estimator object's predict/moments/update/innovation halves, stepped by hand over
    a batch of two runs with different masks on a time-invariant model (the carry has a
    gain schedule; masked steps leave it): every step's posterior, prediction, innovation
    and evidence equal the numpy filter's on the received entries."""
    T = 6
    model = df.LinearGaussianModel(*(torch.tensor(a) for a in (F0, _h_of(1), Q0, R0, M0, P0)))
    ys, mask = _ys((2, T, 2), 1), _masks(T, 1)
    mask[:, :2] = True  # unmasked first steps: the shared-gain update (then dropped)
    mask[:, 4] = True
    kf = df.KalmanFilter()
    carry = kf.init(model, (2,))
    refs = [_np_kf(lambda k: F0, lambda k: _h_of(1), Q0, R0, M0, P0, ys[r].numpy(), mask[r])
            for r in range(2)]  # fmt: skip
    prev_ll = np.zeros(2)
    for t in range(T):
        m = None if mask[:, t].all() else torch.tensor(mask[:, t])
        pred = kf.predict(carry, None)
        nu, S, ell = kf.innovation(carry, pred, ys[:, t], m)
        carry, out = kf.update(carry, pred, ys[:, t], m)
        for r in range(2):
            np.testing.assert_allclose(pred.mean[r].numpy(), refs[r][2][t], atol=1e-10)
            np.testing.assert_allclose(pred.cov.expand(2, 2, 2)[r].numpy(), refs[r][3][t],
                                       atol=1e-10)  # fmt: skip
            np.testing.assert_allclose(out.mean[r].numpy(), refs[r][0][t], atol=1e-10)
            np.testing.assert_allclose(out.cov.expand(2, 2, 2)[r].numpy(), refs[r][1][t],
                                       atol=1e-10)  # fmt: skip
        ll_t = np.array([_np_kf(lambda k: F0, lambda k: _h_of(1), Q0, R0, M0, P0,
                                ys[r, : t + 1].numpy(), mask[r, : t + 1])[-1]
                         for r in range(2)])  # fmt: skip
        np.testing.assert_allclose(out.log_likelihood.numpy(), ll_t - prev_ll, atol=1e-10)
        np.testing.assert_allclose(ell.numpy(), ll_t - prev_ll, atol=1e-10)
        np.testing.assert_allclose(nu.numpy(), out.innovation.numpy(), atol=1e-12)
        prev_ll = ll_t


def test_parallel_filter_with_inputs_and_odd_length_equals_numpy():
    """The associative-scan filter with inputs (offsets B u), an odd and an even number of
    steps (both branches of the scan) and per-run masks: each run equals the numpy filter."""
    B = np.array([[0.5], [1.0]])
    for T in (9, 10):
        model = _TimeVarying(*(torch.tensor(a) for a in (_f_of(0), _h_of(0), Q0, R0, M0, P0, B)))
        ys, us, mask = _ys((2, T, 2), T), _ys((2, T, 1), 100 + T), _masks(T, T)
        res = df.kalman_filter(model, ys, us, mask=torch.tensor(mask), method="parallel")
        for run in range(2):
            off = us[run].numpy() @ B.T
            ref = _np_kf(_f_of, _h_of, Q0, R0, M0, P0, ys[run].numpy(), mask[run], off)
            _assert_filter(res, run, ref)


def _dense_posterior(F_of, H_of, Q, R, m0, P0_, ys, mask):
    """The posterior of ``[x_0, …, x_T]`` given the received entries of ``y_1 … y_T``, by
    conditioning the dense joint Gaussian (no recursion): mean ``[T+1, dx]`` and
    covariance ``[T+1, dx, T+1, dx]``."""
    T, dx = len(ys), len(m0)
    nz = dx * (T + 1)
    L = np.zeros((T + 1, dx, nz))  # x_k = L_k z, z = [x_0, w_0, …, w_{T−1}]
    L[0, :, :dx] = np.eye(dx)
    for k in range(1, T + 1):
        L[k] = F_of(k - 1) @ L[k - 1]
        L[k, :, dx * k : dx * (k + 1)] += np.eye(dx)
    cov_z = np.zeros((nz, nz))
    cov_z[:dx, :dx] = P0_
    mu_z = np.zeros(nz)
    mu_z[:dx] = m0
    for k in range(T):
        cov_z[dx * (k + 1) : dx * (k + 2), dx * (k + 1) : dx * (k + 2)] = Q
    Lx = L.reshape(-1, nz)
    mu_x, S_x = Lx @ mu_z, Lx @ cov_z @ Lx.T
    rows, y_obs, r_idx = [], [], []
    for t in range(T):
        for i in np.flatnonzero(mask[t]):
            row = H_of(t + 1)[i] @ L[t + 1]
            rows.append(row)
            y_obs.append(ys[t, i])
            r_idx.append((t, i))
    Hy = np.array(rows)
    Ry = np.array([[R[i, j] if s == u else 0.0 for (u, j) in r_idx] for (s, i) in r_idx])
    S_xy = Lx @ cov_z @ Hy.T
    S_yy = Hy @ cov_z @ Hy.T + Ry
    gain = S_xy @ np.linalg.inv(S_yy)
    mean = mu_x + gain @ (np.array(y_obs) - Hy @ mu_z)
    cov = S_x - gain @ S_xy.T
    return mean.reshape(T + 1, dx), cov.reshape(T + 1, dx, T + 1, dx)


def test_rts_smoother_equals_the_dense_gaussian_posterior_time_varying_masked():
    """kalman_smoother on a model whose F and H vary with k, two runs with their own lost
    entries: smoothed means and covariances of x_1 … x_T, the lag-one cross-covariances
    Cov(x_k, x_{k+1} | y), the smoothed prior x_0, its covariance and Cov(x_0, x_1 | y) all
    equal the dense joint Gaussian's conditional."""
    T = 6
    model, ys, mask = _tv_model(), _ys((2, T, 2), 3), _masks(T, 3)
    sm = df.kalman_smoother(model, ys, mask=torch.tensor(mask))
    for run in range(2):
        mean, cov = _dense_posterior(_f_of, _h_of, Q0, R0, M0, P0, ys[run].numpy(), mask[run])
        np.testing.assert_allclose(sm.means[run].numpy(), mean[1:], atol=1e-9)
        np.testing.assert_allclose(sm.initial_mean[run].numpy(), mean[0], atol=1e-9)
        for k in range(T + 1):
            got = sm.initial_cov[run] if k == 0 else sm.covs[run, k - 1]
            np.testing.assert_allclose(got.numpy(), cov[k, :, k, :], atol=1e-9)
        for k in range(T):
            got = sm.initial_cross[run] if k == 0 else sm.cross_covs[run, k - 1]
            np.testing.assert_allclose(got.numpy(), cov[k, :, k + 1, :], atol=1e-9)


def test_rts_smoother_without_predicted_covariances_recomputes_them_with_q():
    """A FilterResult without pred_covs (a result built by hand, e.g. from a log): the
    smoother forms P⁻_{k+1} = F P_k Fᵀ + Q itself and still equals the dense Gaussian."""
    T = 5
    model, ys = _tv_model(), _ys((T, 2), 4)
    filt = df.kalman_filter(model, ys)
    sm = df.rts_smoother(model, dataclasses.replace(filt, pred_covs=None))
    mean, cov = _dense_posterior(_f_of, _h_of, Q0, R0, M0, P0, ys.numpy(), np.ones((T, 2), bool))
    np.testing.assert_allclose(sm.means.numpy(), mean[1:], atol=1e-9)
    for k in range(1, T + 1):
        np.testing.assert_allclose(sm.covs[k - 1].numpy(), cov[k, :, k, :], atol=1e-9)


def _f_np(x, k):
    return np.array([x[0] + 0.2 * np.sin(x[1]) * (1 + 0.3 * k), 0.9 * x[1] + 0.1 * x[0] ** 2])


def _h_np(x):
    return np.array([0.5 * x[0] ** 2 + x[1], np.sin(x[0]) - 0.4 * x[1] ** 3])


def _nonlinear_model():
    """f depends on k (so the step index the filters read is visible); h is nonlinear."""

    def f(x, u, k):
        return torch.stack(
            [x[..., 0] + 0.2 * torch.sin(x[..., 1]) * (1 + 0.3 * k),
             0.9 * x[..., 1] + 0.1 * x[..., 0] ** 2], -1)  # fmt: skip

    def h(x):
        return torch.stack([0.5 * x[..., 0] ** 2 + x[..., 1],
                            torch.sin(x[..., 0]) - 0.4 * x[..., 1] ** 3], -1)  # fmt: skip

    return df.NonlinearGaussianModel(f, h, *(torch.tensor(a) for a in (Q0, R0, M0, P0)))


def _jac(fn, x, eps=1e-6):
    return np.stack([(fn(x + eps * e) - fn(x - eps * e)) / (2 * eps) for e in np.eye(len(x))], 1)


def _np_ukf(ys, mask, alpha=1.0, beta=2.0, kappa=0.0):
    """A numpy UKF (van der Merwe's scaled points, additive noise, points redrawn from the
    prediction), updating with the received entries alone: P = P⁻ − K S Kᵀ."""
    n = 2
    lam, wm, wc = scaled_sigma_weights(n, alpha, beta, kappa)

    def points(m, P):
        return scaled_sigma_points(m, P, lam)

    m, P, ll, out = M0.copy(), P0.copy(), 0.0, []
    for t, y in enumerate(ys):
        X = points(m, P)
        FX = np.array([_f_np(x, t) for x in X])
        m = wm @ FX
        P = sum(w * np.outer(d, d) for w, d in zip(wc, FX - m)) + Q0
        pm, pP = m.copy(), P.copy()
        X = points(m, P)
        Y = np.array([_h_np(x) for x in X])
        obs = mask[t]
        yh = wm @ Y
        dY, dX = (Y - yh)[:, obs], X - m
        S = sum(w * np.outer(d, d) for w, d in zip(wc, dY)) + R0[np.ix_(obs, obs)]
        C = sum(w * np.outer(a, b) for w, a, b in zip(wc, dX, dY))
        K = C @ np.linalg.inv(S)
        r = (y - yh)[obs]
        ll += -0.5 * (r @ np.linalg.solve(S, r) + np.log(np.linalg.det(2 * np.pi * S)))
        m, P = m + K @ r, P - K @ S @ K.T
        out.append((pm, pP, m, P))
    return out, ll


def _np_ekf(ys, mask):
    """A numpy EKF (central-difference Jacobians; F at the previous estimate, H at the
    prediction) on the received entries."""
    m, P, ll, out = M0.copy(), P0.copy(), 0.0, []
    for t, y in enumerate(ys):
        F = _jac(lambda x, t=t: _f_np(x, t), m)
        m, P = _f_np(m, t), F @ P @ F.T + Q0
        pm, pP = m.copy(), P.copy()
        obs = mask[t]
        H = _jac(_h_np, m)[obs]
        S = H @ P @ H.T + R0[np.ix_(obs, obs)]
        K = P @ H.T @ np.linalg.inv(S)
        r = (y - _h_np(m))[obs]
        ll += -0.5 * (r @ np.linalg.solve(S, r) + np.log(np.linalg.det(2 * np.pi * S)))
        m, P = m + K @ r, P - K @ S @ K.T
        out.append((pm, pP, m, P))
    return out, ll


def _assert_steps(res, run, ref, atol):
    steps, ll = ref
    for t, (pm, pP, m, P) in enumerate(steps):
        np.testing.assert_allclose(res.pred_means[run, t].numpy(), pm, atol=atol)
        np.testing.assert_allclose(res.pred_covs[run, t].numpy(), pP, atol=atol)
        np.testing.assert_allclose(res.means[run, t].numpy(), m, atol=atol)
        np.testing.assert_allclose(res.covs[run, t].numpy(), P, atol=atol)
    np.testing.assert_allclose(float(res.log_likelihood[run]), ll, atol=atol)


def test_ukf_on_a_nonlinear_time_varying_model_with_masks_equals_numpy():
    """The UKF on a nonlinear model whose f reads k, two runs with their own lost entries,
    default and non-default sigma points: predictions, posteriors and evidence equal a numpy
    UKF that updates with the received entries alone."""
    T = 5
    model, ys, mask = _nonlinear_model(), 0.5 * _ys((2, T, 2), 5), _masks(T, 5)
    for a, b, kap in ((1.0, 2.0, 0.0), (0.8, 2.0, 1.0)):
        sp = df.SigmaPoints(a, b, kap)
        res = df.unscented_kalman_filter(model, ys, mask=torch.tensor(mask), sigma_points=sp)
        for run in range(2):
            _assert_steps(res, run, _np_ukf(ys[run].numpy(), mask[run], a, b, kap), 1e-9)


def test_ekf_on_a_nonlinear_time_varying_model_with_masks_equals_numpy():
    """The EKF on the same model: F = ∂f/∂x at the previous posterior with f at step k − 1,
    H = ∂h/∂x at the prediction, equal to a numpy EKF with finite-difference Jacobians."""
    T = 5
    model, ys, mask = _nonlinear_model(), 0.5 * _ys((2, T, 2), 6), _masks(T, 6)
    res = df.extended_kalman_filter(model, ys, mask=torch.tensor(mask))
    for run in range(2):
        _assert_steps(res, run, _np_ekf(ys[run].numpy(), mask[run]), 1e-7)


def _np_rts(steps, cross_of):
    """Backward RTS pass over numpy filter steps ``(pm, pP, m, P)``, with ``cross_of(k, m_k,
    P_k) = Cov(x_k, x_{k+1} | y_{1:k})``; returns smoothed means/covs for k = 0 … T."""
    ms = [M0] + [s[2] for s in steps]
    Ps = [P0] + [s[3] for s in steps]
    sm, sP = [ms[-1]], [Ps[-1]]
    for k in range(len(steps) - 1, -1, -1):
        pm, pP = steps[k][0], steps[k][1]
        G = cross_of(k, ms[k], Ps[k]) @ np.linalg.inv(pP)
        sm.insert(0, ms[k] + G @ (sm[0] - pm))
        sP.insert(0, Ps[k] + G @ (sP[0] - pP) @ G.T)
    return np.array(sm), np.array(sP)


def _assert_smoothed(sm, run, ref, atol):
    means, covs = ref
    np.testing.assert_allclose(sm.initial_mean[run].numpy(), means[0], atol=atol)
    np.testing.assert_allclose(sm.initial_cov[run].numpy(), covs[0], atol=atol)
    np.testing.assert_allclose(sm.means[run].numpy(), means[1:], atol=atol)
    np.testing.assert_allclose(sm.covs[run].numpy(), covs[1:], atol=atol)


def test_extended_smoother_linearises_at_the_filtered_means_equal_to_numpy():
    """extended_kalman_smoother: F_k = ∂f/∂x (f at step k) at the filtered mean m_k (the
    prior mean at k = 0), G_k = P_k F_kᵀ (P⁻_{k+1})⁻¹, equal to a numpy pass on the numpy
    EKF's steps."""
    T = 5
    model, ys, mask = _nonlinear_model(), 0.5 * _ys((2, T, 2), 7), _masks(T, 7)
    sm = df.extended_kalman_smoother(model, ys, mask=torch.tensor(mask))
    for run in range(2):
        steps, _ = _np_ekf(ys[run].numpy(), mask[run])

        def cross(k, m, P):
            return P @ _jac(lambda x: _f_np(x, k), m).T

        _assert_smoothed(sm, run, _np_rts(steps, cross), 1e-7)


def test_unscented_smoother_equals_numpy_sigma_point_cross_covariance():
    """unscented_kalman_smoother (Särkkä 2008): G_k = D_k (P⁻_{k+1})⁻¹ with D_k =
    Σ wᶜ (X − m_k)(f(X) − m⁻)ᵀ over the points of N(m_k, P_k), for non-default sigma points
    (w₀ᶜ ≠ w₀ᵐ, w₀ᵐ ≠ 0), equal to a numpy pass on the numpy UKF's steps."""
    T = 5
    a, b, kap = 0.8, 2.0, 1.0
    model, ys, mask = _nonlinear_model(), 0.5 * _ys((2, T, 2), 8), _masks(T, 8)
    sp = df.SigmaPoints(a, b, kap)
    sm = df.unscented_kalman_smoother(model, ys, mask=torch.tensor(mask), sigma_points=sp)
    n = 2
    lam, wm, wc = scaled_sigma_weights(n, a, b, kap)
    for run in range(2):
        steps, _ = _np_ukf(ys[run].numpy(), mask[run], a, b, kap)

        def cross(k, m, P):
            L = np.linalg.cholesky(P) * np.sqrt(n + lam)
            X = np.array([m] + [m + L[:, i] for i in range(n)] + [m - L[:, i] for i in range(n)])
            FX = np.array([_f_np(x, k) for x in X])
            pm = wm @ FX
            return sum(w * np.outer(x - m, fx - pm) for w, x, fx in zip(wc, X, FX))

        _assert_smoothed(sm, run, _np_rts(steps, cross), 1e-9)


def test_parallel_log_likelihood_gradient_equals_the_sequential_filters_and_gradcheck():
    """∂ log p(y_{1:T}) / ∂(F, R) of the parallel filter (masked, two runs) equals the
    sequential filter's, and the parallel filter passes gradcheck in float64."""
    T = 5
    ys, mask = _ys((2, T, 2), 9), torch.tensor(_masks(T, 9))

    def loglik(F, R, method):
        model = df.LinearGaussianModel(F, torch.tensor(_h_of(1)), torch.tensor(Q0), R,
                                       torch.tensor(M0), torch.tensor(P0))  # fmt: skip
        return df.kalman_filter(model, ys, mask=mask, method=method).log_likelihood.sum()

    F = torch.tensor(F0, requires_grad=True)
    R = torch.tensor(R0, requires_grad=True)
    grads = [torch.autograd.grad(loglik(F, R, m), (F, R)) for m in ("sequential", "parallel")]
    for a, b in zip(*grads):
        np.testing.assert_allclose(a.numpy(), b.numpy(), atol=1e-9)
    assert torch.autograd.gradcheck(lambda F_: loglik(F_, R.detach(), "parallel"), (F,))


def test_smoothed_covariances_are_exactly_symmetric():
    """Every smoothed covariance (and the prior's) is symmetric to the bit, as the module
    promises (P_k + G (P^s − P⁻) Gᵀ is not, in floating point, without symmetrising), and
    positive definite."""
    T = 8
    model, ys, mask = _tv_model(), _ys((2, T, 2), 10), _masks(T, 10)
    for sm in (df.kalman_smoother(model, ys, mask=torch.tensor(mask)),
               df.unscented_kalman_smoother(_nonlinear_model(), 0.5 * ys)):  # fmt: skip
        for P in (sm.covs, sm.initial_cov):
            assert torch.equal(P, P.mT)
            assert bool((torch.linalg.eigvalsh(P) > 0).all())
