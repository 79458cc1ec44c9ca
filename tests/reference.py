"""Independent numpy references used as test oracles (no difffilter code)."""

from __future__ import annotations

import numpy as np


def numpy_kalman_filter(F, H, Q, R, m0, P0, ys, B=None, us=None, mask=None):
    """Textbook Kalman filter, one run: explicit inverse and the short covariance form.

    ``ys [T, dy]``; returns means ``[T, dx]``, covs ``[T, dx, dx]``, log-likelihood.
    Masked entries are dropped by selecting the received rows of ``H`` and ``R``.
    """
    m, P = np.asarray(m0, float), np.asarray(P0, float)
    means, covs, ll = [], [], 0.0
    for t, y in enumerate(ys):
        m = F @ m + (B @ us[t] if B is not None else 0.0)
        P = F @ P @ F.T + Q
        keep = np.ones(len(y), bool) if mask is None else np.asarray(mask[t], bool)
        if keep.any():
            Hk, Rk, yk = H[keep], R[np.ix_(keep, keep)], y[keep]
            S = Hk @ P @ Hk.T + Rk
            Sinv = np.linalg.inv(S)
            K = P @ Hk.T @ Sinv
            r = yk - Hk @ m
            m = m + K @ r
            P = (np.eye(len(m)) - K @ Hk) @ P
            _, logdet = np.linalg.slogdet(S)
            ll += -0.5 * (r @ Sinv @ r + logdet + len(r) * np.log(2 * np.pi))
        means.append(m.copy())
        covs.append(P.copy())
    return np.array(means), np.array(covs), ll


def dense_joint_gaussian(F, H, Q, R, m0, P0, ys, mask=None):
    """Posterior of every state and the evidence from the joint Gaussian of (x_{1:T}, y_{1:T}).

    Builds the full ``[T dx + T dy]`` covariance by brute force and conditions on the
    received measurements. Returns (smoothed means ``[T, dx]``, filtered mean of the last
    state ``[dx]``, log-likelihood).
    """
    T, dy = ys.shape
    dx = F.shape[0]
    powers = [np.linalg.matrix_power(F, t) for t in range(T + 1)]
    mx = np.stack([powers[t] @ m0 for t in range(1, T + 1)])
    Cx = np.zeros((T * dx, T * dx))
    for t in range(1, T + 1):
        for s in range(1, T + 1):
            c = powers[t] @ P0 @ powers[s].T
            for j in range(1, min(t, s) + 1):
                c = c + powers[t - j] @ Q @ powers[s - j].T
            Cx[(t - 1) * dx : t * dx, (s - 1) * dx : s * dx] = c
    Hb = np.kron(np.eye(T), H)
    my = Hb @ mx.reshape(-1)
    Cy = Hb @ Cx @ Hb.T + np.kron(np.eye(T), R)
    keep = np.ones(T * dy, bool) if mask is None else np.asarray(mask, bool).reshape(-1)
    yv = ys.reshape(-1)[keep]
    Cyy = Cy[np.ix_(keep, keep)]
    resid = yv - my[keep]
    sol = np.linalg.solve(Cyy, resid)
    post = mx.reshape(-1) + (Cx @ Hb.T)[:, keep] @ sol
    _, logdet = np.linalg.slogdet(Cyy)
    ll = -0.5 * (resid @ sol + logdet + keep.sum() * np.log(2 * np.pi))
    return post.reshape(T, dx), post.reshape(T, dx)[-1], ll


def scaled_sigma_weights(n, alpha, beta, kappa):
    """``(λ, w_m, w_c)`` of van der Merwe's scaled sigma points in ``n`` dimensions:
    ``λ = α²(n + κ) − n``, ``w_m = (λ/(n+λ), 1/(2(n+λ)), …)``, ``w_c`` the same but
    ``w_c0 = w_m0 + 1 − α² + β``."""
    lam = alpha**2 * (n + kappa) - n
    wm = np.full(2 * n + 1, 0.5 / (n + lam))
    wm[0] = lam / (n + lam)
    wc = wm.copy()
    wc[0] += 1 - alpha**2 + beta
    return lam, wm, wc


def scaled_sigma_points(m, P, lam):
    """The ``2n + 1`` points ``m, m ± √(n+λ) L[:, i]`` (``L`` the Cholesky factor of ``P``)
    as rows ``[2n+1, n]``."""
    n = len(m)
    L = np.linalg.cholesky(P) * np.sqrt(n + lam)
    return np.array([m] + [m + L[:, i] for i in range(n)] + [m - L[:, i] for i in range(n)])
