"""The modified Riccati equations of difffilter.lossy_control against their independent
truths: the DAREs at rate 1, the scalar critical rate 1 − 1/a², the Kalman filter's mean
prediction covariance under Bernoulli losses between Sinopoli's bounds, and the TCP-like
controller's expected cost tr(S W) in Monte Carlo."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.linalg as sla
import torch

import difffilter as df
from difffilter.control import dlqr, kalman_steady_state
from difffilter.lossy_control import critical_arrival_rate, intermittent_kalman_bounds, lossy_dlqr

F = torch.tensor([[1.1, 0.2], [0.0, 0.95]], dtype=torch.float64)
H = torch.tensor([[1.0, 0.0]], dtype=torch.float64)
B = torch.tensor([[0.0], [1.0]], dtype=torch.float64)
Q = torch.diag(torch.tensor([0.1, 0.05], dtype=torch.float64))
R = torch.tensor([[0.2]], dtype=torch.float64)


def test_every_packet_arriving_is_the_dare():
    K, S = lossy_dlqr(F, B, Q, R, arrival_rate=1.0)
    K0, S0 = dlqr(F, B, Q, R)
    torch.testing.assert_close(K, K0, rtol=1e-8, atol=1e-10)
    torch.testing.assert_close(S, S0, rtol=1e-8, atol=1e-10)
    lower, upper = intermittent_kalman_bounds(F, H, Q, R, 1.0)
    pred = kalman_steady_state(F, H, Q, R)[1]
    torch.testing.assert_close(upper, pred, rtol=1e-8, atol=1e-10)
    torch.testing.assert_close(lower, pred, rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize("a", [1.2, 2.0])
def test_the_scalar_critical_rate_is_one_minus_one_over_a_squared(a):
    Fs = torch.tensor([[a]], dtype=torch.float64)
    one = torch.ones(1, 1, dtype=torch.float64)
    rate = critical_arrival_rate(Fs, one, one, one)
    assert rate.lower == pytest.approx(1 - 1 / a**2)
    assert rate.lower <= rate.upper <= rate.lower + 2e-3  # (the MARE converges slowly near it)
    with pytest.raises(ValueError, match="critical rate"):
        intermittent_kalman_bounds(Fs, one, one, one, 0.9 * (1 - 1 / a**2))


def test_the_filters_mean_covariance_lies_between_sinopolis_bounds():
    """4,000 runs with measurements lost at 35 %: the mean of the Kalman filter's prediction
    covariance after 150 steps lies between the lower and the upper bound (traces, and the
    matrices in the positive semidefinite order)."""
    lam, runs, T = 0.65, 4000, 150
    model = df.LinearGaussianModel(F, H, Q, R, torch.zeros(2, dtype=torch.float64),
                                   torch.eye(2, dtype=torch.float64))  # fmt: skip
    gen = torch.Generator().manual_seed(0)
    ys = torch.zeros(runs, T, 1, dtype=torch.float64)  # (P⁻ never reads the data)
    mask = torch.rand(runs, T, 1, generator=gen) < lam
    out = open_pred_covs(model, ys, mask)
    mean = out[:, -1].mean(0)
    lower, upper = intermittent_kalman_bounds(F, H, Q, R, lam)
    assert float(torch.linalg.eigvalsh(mean - lower).min()) > 0
    assert float(torch.linalg.eigvalsh(upper - mean).min()) > 0
    assert float(lower.trace()) < float(mean.trace()) < float(upper.trace())


def open_pred_covs(model, ys, mask):
    from difffilter.loop import open_loop

    return open_loop(df.KalmanFilter(), model, ys, mask=mask).extras["pred_covs"]


def test_the_tcp_like_controller_costs_tr_s_w_and_beats_the_lossless_gain():
    """x_{k+1} = F x + ν B u + w with u = −K x (the state known), inputs lost at 30 %: over
    4,000 runs the mean cost per step of the last 100 of 300 steps is tr(S W) within Monte
    Carlo error, and the lossless LQR gain costs more."""
    rate, runs, T = 0.7, 4000, 300
    K, S = lossy_dlqr(F, B, Q, R, arrival_rate=rate)
    K0, _ = dlqr(F, B, Q, R)
    W = 0.01 * torch.eye(2, dtype=torch.float64)
    costs = {}
    for name, gain in (("lossy", K), ("lossless", K0)):
        gen = torch.Generator().manual_seed(1)
        x = torch.zeros(runs, 2, dtype=torch.float64)
        total = torch.zeros(runs, dtype=torch.float64)
        for t in range(T):
            u = -x @ gain.T
            nu = (torch.rand(runs, 1, generator=gen) < rate).to(torch.float64)
            if t >= T - 100:
                total += (x @ Q * x).sum(-1) + ((nu * u) @ R * (nu * u)).sum(-1)
            w = torch.randn(runs, 2, generator=gen, dtype=torch.float64) @ W.sqrt()
            x = x @ F.T + (nu * u) @ B.T + w
        costs[name] = total / 100
    expected = float((S @ W).trace())
    mean, se = float(costs["lossy"].mean()), float(costs["lossy"].std()) / runs**0.5
    assert abs(mean - expected) < 4 * se + 0.01 * expected
    assert float(costs["lossless"].mean()) > mean


def test_bad_rates_and_undetectable_pairs_are_named():
    for bad in (0.0, 1.2, True, "0.5"):
        with pytest.raises(ValueError, match="arrival_rate must be a probability"):
            lossy_dlqr(F, B, Q, R, arrival_rate=bad)
    with pytest.raises(ValueError, match="lossy_dlqr.*at or below the critical rate"):
        lossy_dlqr(torch.tensor([[3.0]], dtype=torch.float64), torch.ones(1, 1, dtype=torch.float64),
                   arrival_rate=0.5)  # fmt: skip
    blind = torch.tensor([[0.0, 1.0]], dtype=torch.float64)  # sees the stable state alone
    with pytest.raises(ValueError, match="not detectable"):
        critical_arrival_rate(F, blind)
    # at every rate, 1 included (it had said "at or below the critical rate" there)
    for rate in (1.0, 0.9):
        with pytest.raises(ValueError, match="not detectable"):
            intermittent_kalman_bounds(F, blind, Q, R, rate)
        with pytest.raises(ValueError, match="not stabilizable"):  # 1.2 not reached by u
            lossy_dlqr(torch.diag(torch.tensor([1.2, 0.5], dtype=torch.float64)), blind.mT,
                       arrival_rate=rate)  # fmt: skip


def test_an_uncontrollable_mode_on_the_unit_circle_is_named_as_such_at_rate_one():
    """A trial on the LFC plant (its conserved tie-line sum a mode at 1 no input reaches):
    at rate 1 the error had blamed a critical rate and "an undetectable mode"."""
    F1 = torch.diag(torch.tensor([1.0, 0.5], dtype=torch.float64))
    B1 = torch.tensor([[0.0], [1.0]], dtype=torch.float64)
    with pytest.raises(ValueError, match="rate 1.0 had not settled") as err:
        lossy_dlqr(F1, B1, arrival_rate=1.0)
    assert "uncontrollable mode on (or very near) the unit circle" in str(err.value)
    assert "critical rate (" not in str(err.value) and "undetectable" not in str(err.value)


def test_the_bounds_solve_their_equations_and_the_scalar_mare_its_closed_form():
    """Below rate 1: S̄ − (1 − λ) F S̄ Fᵀ − Q = 0 and V̄ − g_λ(V̄) = 0 (residuals); in the
    scalar case V̄ is the positive root of (1 − a² + λa²) v² + ((1 − a²) r − q) v − q r = 0."""
    lam = 0.7
    lower, upper = intermittent_kalman_bounds(F, H, Q, R, lam)
    torch.testing.assert_close(lower - (1 - lam) * F @ lower @ F.T, Q, rtol=0, atol=1e-12)
    gain = F @ upper @ H.T @ torch.linalg.inv(H @ upper @ H.T + R) @ H @ upper @ F.T
    torch.testing.assert_close(F @ upper @ F.T + Q - lam * gain, upper, rtol=0, atol=1e-9)
    assert float(torch.linalg.eigvalsh(upper - lower).min()) > 0
    a, q, r = 1.5, 0.3, 0.7
    one = torch.ones(1, 1, dtype=torch.float64)
    for lam in (0.6, 0.8, 0.95):
        _, v = intermittent_kalman_bounds(a * one, one, q * one, r * one, lam)
        c2, c1, c0 = 1 - a * a + lam * a * a, (1 - a * a) * r - q, -q * r
        root = (-c1 + (c1 * c1 - 4 * c2 * c0) ** 0.5) / (2 * c2)
        assert float(v) == pytest.approx(root, rel=1e-9)


def test_sinopolis_example_has_a_critical_interval():
    """Sinopoli et al. 2004's example, A = [[1.25, 0], [1, 1.1]], C = [1, 1], Q = 20 I,
    R = 2.5: λ_min = 1 − 1/1.25² = 0.36 and the MARE's threshold λ̄ about 0.47 (a review's
    2-million-step iteration put it between 0.471 and 0.475); a stable F has 0 for both."""
    A = torch.tensor([[1.25, 0.0], [1.0, 1.1]], dtype=torch.float64)
    C = torch.tensor([[1.0, 1.0]], dtype=torch.float64)
    rate = critical_arrival_rate(A, C, 20 * torch.eye(2, dtype=torch.float64),
                                 2.5 * torch.ones(1, 1, dtype=torch.float64))  # fmt: skip
    assert rate.lower == pytest.approx(0.36)
    assert 0.47 <= rate.upper <= 0.476
    assert critical_arrival_rate(0.5 * A, C) == (0.0, 0.0)
    eye = torch.eye(2, dtype=torch.float64)  # marginal and detectable: 0 too (not 0.002)
    assert critical_arrival_rate(eye, eye) == (0.0, 0.0)


def _t(*rows):
    return torch.tensor(rows, dtype=torch.float64)


def test_a_singular_q_reaches_the_stabilising_solution():
    """An API trial: from Q the iteration stayed at the fixed point 0 of the modes Q does not
    excite: an LQR gain that left the unstable mode 1.2 alone (ρ 1.2 in closed loop), an
    upper bound of 0 where the filter settles at a² − 1. Started positive definite now."""
    F, B = _t([1.2, 0.0], [0.0, 0.5]), _t([1.0], [1.0])
    Q = torch.diag(_t(0.0, 1.0))
    K, _ = lossy_dlqr(F, B, Q, arrival_rate=1.0)
    ref, _ = dlqr(F, B, Q)
    torch.testing.assert_close(K, ref, rtol=0, atol=1e-9)
    assert float(torch.linalg.eigvals(F - B @ K).abs().max()) < 0.9
    a, one, zero = _t([1.05]), _t([1.0]), _t([0.0])
    for lam in (1.0, 0.9):  # Q = 0: V = R (a² − 1) / (1 − a² (1 − λ)), the MARE's positive root
        _, upper = intermittent_kalman_bounds(a, one, zero, one, lam)
        assert float(upper) == pytest.approx(0.1025 / (1 - 1.1025 * (1 - lam)), rel=1e-9)


def test_the_solutions_do_not_depend_on_the_units():
    """An API trial: the divergence test compared the iterate with tr Q alone, so Q = 1e-12
    and R = 1e6 (a fixed point of 4.4e5) was called divergent even at rate 1, and F = 1e8
    undetectable (its MARE also lost its answer to cancellation: the Joseph form now)."""
    a, one = _t([1.2]), _t([1.0])
    Q, R = 1e-12 * one, 1e6 * one
    exact = 1e6 * 0.44  # V² + V (R (1 − a²) − Q) − Q R = 0, to 1e-12 relative
    for lam in (1.0, 0.8):
        _, upper = intermittent_kalman_bounds(a, one, Q, R, lam)
        closed = 1e6 * 0.44 / (1 - 1.44 * (1 - lam))
        assert float(upper) == pytest.approx(exact if lam == 1.0 else closed, rel=1e-9)
    K, _ = lossy_dlqr(a, one, Q, R, arrival_rate=1.0)
    assert float(K) == pytest.approx(1.2 * exact / (exact + 1e6), rel=1e-9)
    rate = critical_arrival_rate(a, one, Q, R)
    assert rate.lower == pytest.approx(1 - 1 / 1.44) and rate.upper - rate.lower < 2e-3
    assert critical_arrival_rate(_t([1e8]), one).lower == pytest.approx(1.0)


def test_an_invertible_h_gives_the_critical_rate_exactly():
    """Where ``H`` is square and invertible the critical rate is ``1 − 1/ρ(F)²`` exactly
    (Sinopoli et al. 2004): a review's scalar ``a = 1.01`` bisected for seconds to 1.9e-3
    above it (the MARE settles slowly there); a 2×2 plant with a non-diagonal invertible
    ``H`` and eigenvalues 1.5 and 0.5 gives 1 − 1/1.5² at both ends. The bounds then exist
    right above it: the scalar MARE's fixed point at λ = λ_c + 1e-3 by hand, from
    v = a²v + 1 − λa²v²/(v + 1) ⇔ c v² − a² v − 1 = 0 with c = 1 − a²(1 − λ)."""
    a = 1.01
    rate = critical_arrival_rate(_t([a]), _t([1.0]))
    assert rate.lower == rate.upper == pytest.approx(1 - 1 / a**2, rel=1e-12)
    F = torch.tensor([[1.5, 0.3], [0.0, 0.5]], dtype=torch.float64)
    H = torch.tensor([[1.0, 2.0], [0.5, -1.0]], dtype=torch.float64)
    rate = critical_arrival_rate(F, H)
    assert rate.lower == rate.upper == pytest.approx(1 - 1 / 1.5**2, rel=1e-12)
    lam = 1 - 1 / a**2 + 1e-3
    c = 1 - a**2 * (1 - lam)
    v = (a**2 + math.sqrt(a**4 + 4 * c)) / (2 * c)
    _, upper = intermittent_kalman_bounds(_t([a]), _t([1.0]), _t([1.0]), _t([1.0]), lam)
    assert float(upper) == pytest.approx(v, rel=1e-6)


@pytest.mark.parametrize("tol", [0.0, -1.0, float("nan"), 2.0, "0.01", True])
def test_a_bad_tolerance_is_named(tol):
    with pytest.raises(ValueError, match="tol must be a number in"):  # (0 had looped forever)
        critical_arrival_rate(_t([1.2]), _t([1.0]), tol=tol)


def test_bad_values_are_named():
    F, H, eye = _t([0.9, 0.1], [0.0, 1.1]), _t([1.0, 0.0]), torch.eye(2, dtype=torch.float64)
    one = _t([1.0])
    cases = [
        (lambda: intermittent_kalman_bounds(F * float("nan"), H, eye, one, 0.9), "F contains NaN"),
        (lambda: intermittent_kalman_bounds(F, H, eye, -one, 0.9), "R must be positive definite"),
        (lambda: intermittent_kalman_bounds(F, H, torch.diag(_t(1.0, -1.0)), one, 0.9),
         "Q must be positive semidefinite"),
        (lambda: intermittent_kalman_bounds(F, H, _t([1.0, 0.5], [0.0, 1.0]), one, 0.9),
         "Q must be symmetric"),
        (lambda: critical_arrival_rate(F, H, eye, one * float("nan")), "R contains NaN"),
        (lambda: intermittent_kalman_bounds(_t([1.1, 0.0], [0.0, 0.5]), _t([0.0, 1.0]), eye, one,
                                            0.9), "not detectable"),
        (lambda: lossy_dlqr(_t([1.1, 0.0], [0.0, 0.5]), _t([0.0], [1.0]), arrival_rate=0.9),
         "not stabilizable"),
        (lambda: lossy_dlqr(torch.zeros(0, 0, dtype=torch.float64),
                            torch.zeros(0, 1, dtype=torch.float64), arrival_rate=0.9), "n = 0"),
    ]  # fmt: skip
    for call, why in cases:
        with pytest.raises(ValueError, match=why):
            call()
    lower, _ = intermittent_kalman_bounds(F, H, eye, one, torch.tensor(0.9, dtype=torch.float64))
    assert lower.shape == (2, 2)


def test_a_marginal_mode_q_does_not_excite_settles_at_zero():
    """A review of the positive definite start: a constant bias state (eigenvalue 1, no
    noise) shrank like 1/k from it and never settled ("not detectable" at rate 0.8); from Q
    its covariance is 0 at once, scipy's DARE's limit. The start is Q, and Q + c I only where
    that fixed point leaves an unstable mode unestimated."""
    F, H = torch.diag(_t(0.9, 1.0)), _t([1.0, 1.0])
    Q, R = torch.diag(_t(1.0, 0.0)), _t([1.0])
    _, upper = intermittent_kalman_bounds(F, H, Q, R, 1.0)
    ref = sla.solve_discrete_are(F.numpy().T, H.numpy().T, Q.numpy(), R.numpy())
    np.testing.assert_allclose(upper.numpy(), ref, rtol=0, atol=1e-9)
    lower, upper = intermittent_kalman_bounds(F, H, Q, R, 0.8)
    assert float(upper[1, 1]) == 0.0 and float(upper[0, 0]) > float(lower[0, 0]) > 0
    assert critical_arrival_rate(F, H, Q, R) == (0.0, 0.0)
    K, _ = lossy_dlqr(F.T, H.T, Q, R, arrival_rate=1.0)
    assert K.shape == (1, 2)


def test_a_bias_mode_beside_an_unexcited_unstable_one():
    """A review: with Q = 0 on F = diag(1, 2) the restart from Q + c I brought back the bias
    mode's 1/k decay (never settled); the restart adds the unstable mode alone now."""
    F, H, Q, R = (
        torch.diag(_t(1.0, 2.0)),
        torch.eye(2, dtype=torch.float64),
        torch.zeros(2, 2, dtype=torch.float64),
        torch.eye(2, dtype=torch.float64),
    )
    for lam, unstable in ((1.0, 3.0), (0.9, 5.0)):  # 3 / (1 − 4 (1 − λ))
        _, upper = intermittent_kalman_bounds(F, H, Q, R, lam)
        torch.testing.assert_close(upper, torch.diag(_t(0.0, unstable)), rtol=0, atol=1e-9)
    K, S = lossy_dlqr(F, H, Q, R, arrival_rate=1.0)
    ref_K, ref_S = dlqr(F, H, Q, R)
    torch.testing.assert_close(S, ref_S, rtol=0, atol=1e-9)
    assert critical_arrival_rate(F, H, Q, R).lower == pytest.approx(0.75)


def test_a_jordan_block_q_does_not_excite_reaches_the_stabilising_solution():
    """A review: the restart's projector came from eigenvectors, which on a Jordan block are
    parallel (rank 1 for a 2 × 2 block), and the fixed point reached left the loop at 1.2.
    From the ordered Schur form's invariant subspace now: scipy's DARE, filter and control."""
    F, Q = _t([1.2, 1.0], [0.0, 1.2]), torch.zeros(2, 2, dtype=torch.float64)
    for H in (_t([1.0, 0.0]), torch.eye(2, dtype=torch.float64)):
        R = torch.eye(H.shape[0], dtype=torch.float64)
        _, upper = intermittent_kalman_bounds(F, H, Q, R, 1.0)
        ref = sla.solve_discrete_are(F.numpy().T, H.numpy().T, Q.numpy(), R.numpy())
        np.testing.assert_allclose(upper.numpy(), ref, rtol=1e-9, atol=1e-9)
    B = _t([0.0], [1.0])
    K, S = lossy_dlqr(F, B, Q, _t([1.0]), arrival_rate=1.0)
    ref = sla.solve_discrete_are(F.numpy(), B.numpy(), Q.numpy(), np.eye(1))
    np.testing.assert_allclose(S.numpy(), ref, rtol=1e-9, atol=1e-9)
    assert float(torch.linalg.eigvals(F - B @ K).abs().max()) < 1.0
