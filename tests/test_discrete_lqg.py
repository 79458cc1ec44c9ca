"""The discrete-time LQG pieces a closed-loop design trial had to write itself: ``dlqr``
against the Riccati difference equation iterated to its limit, ``kalman_steady_state``
against the Kalman filter's converged gain, and ``StateFeedback`` in the closed loop
against a numpy loop on the same noise (one gain, and one gain per run of a sweep)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import difffilter as df
from difffilter.control import dare_residual, dlqr, kalman_steady_state
from difffilter.loop import ReplayedNoise, StateFeedback, closed_loop

F64 = torch.float64
F = torch.tensor([[1.02, 0.1], [0.0, 0.95]], dtype=F64)  # open-loop unstable
B = torch.tensor([[0.0], [0.1]], dtype=F64)
H = torch.tensor([[1.0, 0.0]], dtype=F64)
Q = torch.tensor([[1e-3, 2e-4], [2e-4, 5e-4]], dtype=F64)
R = torch.tensor([[1e-2]], dtype=F64)


def test_dlqr_is_the_limit_of_the_riccati_difference_equation():
    Qc, Rc = torch.diag(torch.tensor([1.0, 0.5], dtype=F64)), torch.tensor([[0.1]], dtype=F64)
    P = Qc.clone()
    for _ in range(5000):  # the cost-to-go of the finite-horizon problem, backwards
        gain = torch.linalg.solve(Rc + B.T @ P @ B, B.T @ P @ F)
        P = Qc + F.T @ P @ (F - B @ gain)
    K, P_star = dlqr(F, B, Qc, Rc)
    torch.testing.assert_close(P_star, P, rtol=1e-9, atol=0)
    torch.testing.assert_close(K, torch.linalg.solve(Rc + B.T @ P @ B, B.T @ P @ F), rtol=1e-9,
                               atol=0)  # fmt: skip
    assert float(dare_residual(F, B, Qc, Rc, P_star).abs().max()) < 1e-10
    assert float(torch.linalg.eigvals(F - B @ K).abs().max()) < 1.0
    with pytest.raises(ValueError, match=r"F must have shape \[2, 2\] to match B \[2, 1\]"):
        dlqr(F[:1], B)
    # a square F and B of other rows: either may be wrong, and both are named (a
    # lossy-control trial: the message had blamed F alone, asking for [1, 1])
    with pytest.raises(
        ValueError, match=r"F \(2, 2\) and B \(1, 1\) do not match: B must have 2 rows"
    ):
        dlqr(F, B[:1])
    with pytest.raises(ValueError, match=r"R must have shape \[1, 1\]"):
        dlqr(F, B, Qc, torch.eye(2, dtype=F64))


def test_kalman_steady_state_is_where_the_kalman_filter_converges():
    model = df.LinearGaussianModel(F, H, Q, R, torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64))
    ys = torch.zeros(1, 400, 1, dtype=F64)
    result = df.kalman_filter(model, ys)
    gain, pred, cov = kalman_steady_state(F, H, Q, R)
    torch.testing.assert_close(cov, result.covs[0, -1], rtol=1e-9, atol=0)
    torch.testing.assert_close(pred, result.pred_covs[0, -1], rtol=1e-9, atol=0)
    S = H @ pred @ H.T + R
    torch.testing.assert_close(gain, pred @ H.T @ torch.linalg.inv(S), rtol=1e-12, atol=0)


def _numpy_lqg(x0, w, v, K, m0, P0):
    """Plant, Kalman filter and u_k = −K_b m_k, run by run in numpy (the truth)."""
    Fn, Bn, Hn, Qn, Rn = (t.numpy() for t in (F, B, H, Q, R))
    runs, T = w.shape[:2]
    xs, means, us = np.zeros((runs, T, 2)), np.zeros((runs, T, 2)), np.zeros((runs, T, 1))
    for b in range(runs):
        Kb = K[b] if K.ndim == 3 else K
        x, m, P, u = x0[b].copy(), m0.copy(), P0.copy(), np.zeros(1)
        for k in range(T):
            us[b, k] = u
            x = Fn @ x + Bn @ u + w[b, k]
            y = Hn @ x + v[b, k]
            m, P = Fn @ m + Bn @ u, Fn @ P @ Fn.T + Qn
            S = Hn @ P @ Hn.T + Rn
            G = P @ Hn.T @ np.linalg.inv(S)
            m, P = m + G @ (y - Hn @ m), (np.eye(2) - G @ Hn) @ P
            u = -Kb @ m
            xs[b, k], means[b, k] = x, m
    return xs, means, us


@pytest.mark.parametrize("per_run", [False, True])
def test_state_feedback_in_the_closed_loop_is_the_numpy_lqg_loop(per_run):
    rng = np.random.default_rng(4)
    runs, T = 3, 40
    w = rng.multivariate_normal(np.zeros(2), Q.numpy(), size=(runs, T))
    v = rng.multivariate_normal(np.zeros(1), R.numpy(), size=(runs, T))
    x0 = rng.standard_normal((runs, 2))
    K, _ = dlqr(F, B, torch.eye(2, dtype=F64), torch.tensor([[0.1]], dtype=F64))
    gains = K * torch.tensor([0.5, 1.0, 1.5], dtype=F64)[:, None, None] if per_run else K
    m0, P0 = np.zeros(2), np.eye(2)
    plant = df.LinearGaussianModel(F, H, Q, R, torch.as_tensor(m0), torch.as_tensor(P0), B=B)
    loop = closed_loop(plant, T, noise=ReplayedNoise(torch.as_tensor(w), torch.as_tensor(v)),
                       x0=torch.as_tensor(x0), estimator=df.KalmanFilter(),
                       controller=StateFeedback(gains))  # fmt: skip
    xs, means, us = _numpy_lqg(x0, w, v, gains.numpy(), m0, P0)
    torch.testing.assert_close(loop.trajectories.x, torch.as_tensor(xs), rtol=0, atol=1e-12)
    torch.testing.assert_close(loop.output.means, torch.as_tensor(means), rtol=0, atol=1e-12)
    torch.testing.assert_close(loop.trajectories.us, torch.as_tensor(us), rtol=0, atol=1e-12)


def test_state_feedback_names_what_it_needs():
    K = torch.ones(1, 2, dtype=F64)
    plant = df.LinearGaussianModel(F, H, Q, R, torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64),
                                   B=B)  # fmt: skip
    x0 = torch.zeros(2, 2, dtype=F64)
    noise = ReplayedNoise(torch.zeros(2, 3, 2, dtype=F64), torch.zeros(2, 3, 1, dtype=F64))
    with pytest.raises(ValueError, match="StateFeedback reads the estimator's mean"):
        closed_loop(plant, 3, noise=noise, x0=x0, controller=StateFeedback(K))
    with pytest.raises(ValueError, match=r"gain must be a floating tensor K \[du, dx\]"):
        StateFeedback(torch.ones(2, dtype=F64))
    with pytest.raises(ValueError, match=r"reference must be x_ref \[2\]"):
        StateFeedback(K, torch.zeros(3, dtype=F64))
    ref = torch.tensor([0.5, 0.0], dtype=F64)  # a set point: u = −K (m − x_ref)
    out = type("Out", (), {"mean": torch.tensor([[1.0, 2.0]], dtype=F64)})()
    torch.testing.assert_close(StateFeedback(K, ref)(1, None, out),
                               torch.tensor([[-2.5]], dtype=F64))  # fmt: skip


def test_the_designs_give_no_gradient_rather_than_a_wrong_one_and_name_their_inputs():
    """From the review: a gradient through the products alone held P fixed (dK/dF 1.32 for
    23.9; dgain/dH +0.118 for −0.093): the results are detached."""
    Fg, Hg = F.clone().requires_grad_(True), H.clone().requires_grad_(True)
    K, P = dlqr(Fg, B)
    gain, pred, cov = kalman_steady_state(Fg, Hg, Q, R)
    assert not any(t.requires_grad for t in (K, P, gain, pred, cov))
    with pytest.raises(ValueError, match="Q and R .* are needed"):
        kalman_steady_state(F, H, None, R)
    with pytest.raises(
        ValueError, match="R is torch.float32 on cpu and the plant's matrices torch.float64"
    ):
        kalman_steady_state(F, H, Q, R.float())


def _refused_at_the_start(runs: int, controller, match: str) -> None:
    """A two-step closed loop of ``runs`` runs on the plant with ``controller`` raises."""
    plant = df.LinearGaussianModel(F, H, Q, R, torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64),
                                   B=B)  # fmt: skip
    noise = ReplayedNoise(torch.zeros(runs, 2, 2, dtype=F64), torch.zeros(runs, 2, 1, dtype=F64))
    with pytest.raises(ValueError, match=match):
        closed_loop(plant, 2, noise=noise, x0=torch.zeros(runs, 2, dtype=F64),
                    estimator=df.KalmanFilter(), controller=controller)  # fmt: skip


def test_a_per_run_gain_of_other_runs_is_named_at_the_start():
    _refused_at_the_start(3, StateFeedback(torch.ones(2, 1, 2, dtype=F64)),
                          r"StateFeedback's gain \(2, 1, 2\) holds \(2,\) runs, and the loop \(3,\)")  # fmt: skip


def test_the_continuous_lqr_is_detached_too_and_the_feedback_names_its_dtype():
    from difffilter.control import lqr

    A = torch.tensor([[0.0, 1.0], [-1.0, -0.5]], dtype=F64, requires_grad=True)
    K, P = lqr(A, B.clone().requires_grad_(True))
    assert not K.requires_grad and not P.requires_grad  # (K held a half gradient: P fixed)
    _refused_at_the_start(2, StateFeedback(torch.ones(1, 2)),
                          r"StateFeedback's gain is torch.float32 on cpu and the loop torch.float64")  # fmt: skip


def test_state_feedback_is_differentiable_in_its_gain():
    plant = df.LinearGaussianModel(F, H, Q, R, torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64),
                                   B=B)  # fmt: skip
    gen = torch.Generator().manual_seed(6)
    noise = ReplayedNoise(0.03 * torch.randn(2, 6, 2, dtype=F64, generator=gen),
                          0.1 * torch.randn(2, 6, 1, dtype=F64, generator=gen))  # fmt: skip
    x0 = torch.tensor([[1.0, 0.0], [0.0, -1.0]], dtype=F64)

    def cost(K):
        loop = closed_loop(plant, 6, noise=noise, x0=x0, estimator=df.KalmanFilter(),
                           controller=StateFeedback(K))  # fmt: skip
        return loop.trajectories.x.square().sum()

    K = torch.tensor([[0.5, 1.0]], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(cost, (K,))
