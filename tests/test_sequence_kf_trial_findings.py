"""Whole-sequence Kalman filters against an exact answer (a red-team trial).

* The covariance recursion's chunks start their steps from the j-step maps, whose
  ``(I + P J)⁻¹`` is ill-conditioned on a strongly non-normal ``F`` with small ``Q`` and
  ``R``: ``S`` 6.5 % off, ``P`` 3.8 %, the log-likelihood 0.034 nats (the shared-covariance
  path and the online step alike), while the means, the only thing checked, held.
* The shared-covariance path checked the 32 runs of the largest raw data, inputs and
  measurements in one ranking, so runs of large inputs through a small ``B`` crowded out a
  run whose measurements broke the blocks (0.47 posterior sd, 8.7 nats off, unchecked).
* ``method="parallel"`` took the first step's ``B`` (or ``None``) for every step of a
  time-varying model, and blamed a non-normal ``F`` for a singular ``H Q Hᵀ + R``.

The truth is the step-by-step filter (the model given a batch dimension of one, which no
fast path takes; it agrees with a 50-digit filter to 7e-10 here) and the dense joint
Gaussian.
"""

import math

import pytest
import torch

import difffilter as df
from difffilter.kalman import KalmanFilter, kalman_filter
from difffilter.ssm import LinearGaussianModel

d = torch.float64


def _non_normal():
    F = torch.tensor([[0.628209869395114, -6845.67443550063, 5329.475273575839],
                      [0.0, -0.07821364542317932, 4313.860950071209],
                      [0.0, 0.0, 0.41486194811652555]], dtype=d)  # fmt: skip
    H = torch.tensor([[0.8406347707177637, 0.7969257562821679, -0.6990027762399978]], dtype=d)
    Q = 1.596445463354458e-08 * torch.eye(3, dtype=d)
    R = 5.742082695285073e-10 * torch.eye(1, dtype=d)
    return F, H, Q, R, torch.zeros(3, dtype=d), torch.eye(3, dtype=d)


def _scaled(a, b, cov):
    sd = cov.diagonal(dim1=-2, dim2=-1).sqrt()
    return float(((a - b).abs() / (sd.unsqueeze(-1) * sd.unsqueeze(-2))).max())


def test_the_covariance_chain_holds_on_a_strongly_non_normal_model():
    F, H, Q, R, m0, P0 = _non_normal()
    ys = torch.randn(10, 1, generator=torch.Generator().manual_seed(0), dtype=d)
    shared = kalman_filter(LinearGaussianModel(F, H, Q, R, m0, P0), ys)
    truth = kalman_filter(LinearGaussianModel(F[None], H, Q, R, m0, P0), ys[None])
    assert _scaled(shared.covs, truth.covs[0], truth.covs[0]) < 1e-6  # was 3.8e-2
    torch.testing.assert_close(shared.innovation_covs, truth.innovation_covs[0], rtol=1e-6, atol=0)
    assert float(shared.log_likelihood) == pytest.approx(float(truth.log_likelihood[0]), abs=1e-6)
    kf, total = KalmanFilter(), 0.0
    carry = kf.init(LinearGaussianModel(F, H, Q, R, m0, P0))
    for y in ys:
        carry, out = kf.step(carry, y)
        total += float(out.log_likelihood)
    assert total == pytest.approx(float(truth.log_likelihood[0]), abs=1e-6)  # was 0.034 off


def test_a_run_is_checked_whatever_the_units_of_the_other_runs_inputs():
    F = torch.tensor([[-0.3104096762817524, 1064.3689266873796, -1187.5080217089028],
                      [0.0, 0.6412375109135576, 3788.2909933219953],
                      [0.0, 0.0, -0.23762145418601355]], dtype=d)  # fmt: skip
    H = torch.tensor([[0.5180804412387305, -0.018268252835709008, -0.15062110843603707],
                      [-1.6508242364837613, 0.013712986418582322, 0.07774928935523732]], dtype=d)  # fmt: skip
    Q, R = 0.2502107086642089 * torch.eye(3, dtype=d), 1.34870851202289e-06 * torch.eye(2, dtype=d)
    B = 1e-12 * torch.ones(3, 1, dtype=d)  # inputs in units where B is small
    model = LinearGaussianModel(F, H, Q, R, torch.zeros(3, dtype=d), torch.eye(3, dtype=d), B)
    T, g = 40, torch.Generator().manual_seed(0)
    x, ys = torch.randn(3, generator=g, dtype=d), []
    for _ in range(T):
        x = F @ x + Q.sqrt() @ torch.randn(3, generator=g, dtype=d)
        ys.append(H @ x + R.sqrt() @ torch.randn(2, generator=g, dtype=d))
    Y, U = torch.zeros(33, T, 2, dtype=d), torch.zeros(33, T, 1, dtype=d)
    Y[0] = 10 * torch.stack(ys)
    U[1:] = 2 * float(Y[0].abs().max())
    batch = kalman_filter(model, Y, U)
    truth = kalman_filter(
        model, Y[:1], U[:1]
    )  # run 0 alone: checked (7e-6 sd, 4e-4 nats off 50 digits)
    sd = truth.covs[0].diagonal(dim1=-2, dim2=-1).sqrt()
    assert float(((batch.means[0] - truth.means[0]).abs() / sd).max()) < 1e-3  # was 0.47
    assert float(batch.log_likelihood[0]) == pytest.approx(float(truth.log_likelihood[0]), abs=1e-3)


def _dense_truth(F, H, Q, R, m0, P0, ys, us, B_of_k):
    """Log-likelihood and final filtered mean from the dense joint Gaussian."""
    T, dx, dy = ys.shape[0], F.shape[0], H.shape[0]
    n = dx * (T + 1)
    mu, G = torch.zeros(n, dtype=d), torch.zeros(n, n, dtype=d)
    mu[:dx], G[:dx, :dx] = m0, torch.eye(dx, dtype=d)
    for k in range(T):
        p, c = slice(k * dx, (k + 1) * dx), slice((k + 1) * dx, (k + 2) * dx)
        Bk = B_of_k(k)
        mu[c] = F @ mu[p] + (0 if Bk is None else Bk @ us[k])
        G[c] = F @ G[p]
        G[c, c] += torch.eye(dx, dtype=d)
    Sx = G @ torch.block_diag(P0, *[Q] * T) @ G.T
    Hb = torch.zeros(T * dy, n, dtype=d)
    for t in range(T):
        Hb[t * dy : (t + 1) * dy, (t + 1) * dx : (t + 2) * dx] = H
    Syy = Hb @ Sx @ Hb.T + torch.block_diag(*[R] * T)
    r = ys.reshape(-1) - Hb @ mu
    ll = (
        -0.5 * r @ torch.linalg.solve(Syy, r)
        - 0.5 * torch.logdet(Syy)
        - 0.5 * T * dy * math.log(2 * math.pi)
    )
    last = slice(T * dx, (T + 1) * dx)
    return float(ll), mu[last] + (Sx @ Hb.T)[last] @ torch.linalg.solve(Syy, r)


@pytest.mark.parametrize("acting", [lambda k: k >= 1, lambda k: k < 2])
def test_parallel_filter_with_a_control_matrix_absent_at_some_steps(acting):
    F = torch.tensor([[0.9, 0.2], [-0.1, 0.8]], dtype=d)
    H = torch.tensor([[1.0, 0.0], [0.3, 1.0]], dtype=d)
    Q, R = 0.1 * torch.eye(2, dtype=d), 0.2 * torch.eye(2, dtype=d)
    m0, P0, B = (
        torch.zeros(2, dtype=d),
        torch.eye(2, dtype=d),
        torch.tensor([[1.0], [0.5]], dtype=d),
    )
    g = torch.Generator().manual_seed(0)
    ys, us = torch.randn(5, 2, generator=g, dtype=d), 3.0 * torch.randn(5, 1, generator=g, dtype=d)

    class Switched(LinearGaussianModel):
        time_varying = True

        def control_matrix(self, k):
            return self.B if acting(k) else None

    ll, mean = _dense_truth(F, H, Q, R, m0, P0, ys, us, lambda k: B if acting(k) else None)
    for method in ("parallel", "sequential"):
        out = kalman_filter(Switched(F, H, Q, R, m0, P0, B), ys, us, method=method)
        assert float(out.log_likelihood) == pytest.approx(ll, abs=1e-9)  # was 6 nats off
        torch.testing.assert_close(out.means[-1], mean, rtol=1e-9, atol=1e-9)


def test_parallel_filter_names_a_singular_h_q_ht_plus_r():
    F = torch.tensor([[1.0, 1.0], [0.0, 1.0]], dtype=d)
    H = torch.tensor([[1.0, 0.0]], dtype=d)

    class NoiseFreeSensor(LinearGaussianModel):  # noise on the velocity alone, R = 0
        def process_cov(self, k):
            return torch.tensor([[0.0, 0.0], [0.0, 0.5]], dtype=d)

        def measurement_cov(self, k):
            return torch.zeros(1, 1, dtype=d)

    eye = torch.eye(2, dtype=d)
    model = NoiseFreeSensor(F, H, eye, torch.eye(1, dtype=d), torch.zeros(2, dtype=d), eye)
    ys = torch.randn(6, 1, generator=torch.Generator().manual_seed(0), dtype=d)
    assert torch.isfinite(kalman_filter(model, ys).log_likelihood)
    with pytest.raises(ValueError, match=r"H Q Hᵀ \+ R positive definite.*singular"):
        kalman_filter(model, ys, method="parallel")


def test_the_parallel_filter_holds_a_differentiated_result_to_a_tighter_bound():
    """Values within 1e-4 sd did not make the gradient right: on this ill-conditioned model
    (‖F‖ = 110, r = 3.9e-7) the parallel log-likelihood carried 1e-3 nats of round-off and
    its gradient in log q was 1.997 where the exact one is 1.028 (a 50-digit filter; the
    sequential filter's 1.0284). Differentiated, the float64 bound is 1e-8: refused."""
    D = torch.float64
    F = torch.tensor([[18.01906100720241, 33.365755201756045, 11.928180225295739],
                      [-21.746570767297204, 13.883683755659515, 4.175067041469902],
                      [30.720347111621848, -94.02350832862112, -31.4164321623323]], dtype=D)  # fmt: skip
    H = torch.tensor([[2.2355743340126697, 0.5577573678077569, -0.09378922288520852]], dtype=D)

    def model(log_q, log_r):
        eye = torch.eye(3, dtype=D)
        return df.LinearGaussianModel(F, H, log_q.exp() * eye, log_r.exp() * torch.eye(1, dtype=D),
                                      torch.zeros(3, dtype=D), eye)  # fmt: skip

    log_q, log_r = (
        torch.tensor(-4.618268826506003, dtype=D),
        torch.tensor(-14.748931978401725, dtype=D),
    )
    _, ys, _ = model(log_q, log_r).simulate(100, (2,), generator=torch.Generator().manual_seed(0))
    plain = df.kalman_filter(model(log_q, log_r), ys, method="parallel")  # values: accepted
    exact = df.kalman_filter(model(log_q, log_r), ys)
    assert float((plain.log_likelihood - exact.log_likelihood).abs().max()) < 1e-1
    log_q.requires_grad_()
    with pytest.raises(
        ValueError, match="beyond 1e-08 \\(the bound where the result is differentiated"
    ):
        df.kalman_filter(model(log_q, log_r), ys, method="parallel")
    with torch.no_grad():  # (no gradient asked: the values' bound)
        df.kalman_filter(model(log_q, log_r), ys, method="parallel")
    eye2 = torch.eye(2, dtype=D)

    def well():
        return df.LinearGaussianModel(0.9 * eye2, eye2, 0.1 * eye2, log_q.exp() * eye2,
                                      torch.zeros(2, dtype=D), eye2)  # fmt: skip

    _, ys2, _ = well().simulate(200, (3,), generator=torch.Generator().manual_seed(1))
    grads = [torch.autograd.grad(df.kalman_filter(well(), ys2.detach(), method=m).log_likelihood.sum(), log_q)[0]
             for m in ("parallel", "sequential")]  # fmt: skip
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-10, atol=0)


@pytest.mark.parametrize("none_at_0", [True, False])
def test_an_input_matrix_none_at_some_steps_is_an_undeclared_time_varying_model(none_at_0):
    """``control_matrix(k)`` None at some steps and B at others, ``time_varying`` left
    False: the check stopped at a None, and B_0 was read at every step (every input dropped,
    117 nats off, or the sequential filter failed in ``torch.pad``)."""
    D = torch.float64
    B = torch.tensor([[0.0], [1.0]], dtype=D)

    class Switching(df.LinearGaussianModel):
        def control_matrix(self, k):
            return None if (k == 0) == none_at_0 else self.B

    model = Switching(torch.eye(2, dtype=D), torch.eye(2, dtype=D)[:1], 0.01 * torch.eye(2, dtype=D),
                      0.1 * torch.eye(1, dtype=D), torch.zeros(2, dtype=D), torch.eye(2, dtype=D), B=B)  # fmt: skip
    for method in ("parallel", "sequential"):
        with pytest.raises(
            ValueError, match="control_matrix\\(k\\) differs between k = 1 and k = 0"
        ):
            df.kalman_filter(
                model, torch.zeros(1, 20, 1, dtype=D), torch.ones(1, 20, 1, dtype=D), method=method
            )
