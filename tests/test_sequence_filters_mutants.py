"""Mutation-review tests of parallel_kalman's consistency check, the fixed-gain observer,
the expected-input (UDP-like) Kalman filter and the input-loss channel, each against an
independent truth written out here: a numpy filter of the docstring's equations, the
deliberately spoiled scan that the check must refuse (at the step where it was spoiled),
or the channel's equations applied by hand."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import difffilter as df
import difffilter.parallel_kalman as pk
from difffilter.input_loss import InputLoss
from difffilter.observers import FixedGainFilter

F64 = torch.float64


def _t(a):
    return torch.tensor(a, dtype=F64)


def _small_model(B=None):
    F = _t([[1.0, 0.1], [-0.2, 0.9]])
    H = _t([[1.0, 0.5]])
    Q = _t([[0.05, 0.01], [0.01, 0.03]])
    return df.LinearGaussianModel(F, H, Q, _t([[0.2]]), _t([0.3, -0.2]), _t([[1.0, 0.2], [0.2, 0.5]]),
                                  B=B)  # fmt: skip


# -- parallel_kalman: the one-step consistency check ---------------------------------------
def _spoiled_scan(monkeypatch, spoil):
    """Make the parallel filter's associative scan return its exact result with ``spoil``
    applied to ``(means, covs)`` (a scan that lost the filter at a known step)."""
    real, depth = pk.associative_scan, [0]

    def scan(combine, elems, dims):  # (the scan recurses through this name: spoil the outer)
        depth[0] += 1
        try:
            out = real(combine, elems, dims)
        finally:
            depth[0] -= 1
        if depth[0] == 0:
            out[1], out[2] = spoil(out[1].clone(), out[2].clone())
        return out

    monkeypatch.setattr(pk, "associative_scan", scan)


def _two_runs(seed=0, T=7):
    """The small model, two runs of ``T`` steps and a mask that differs between the runs
    (so the scan's covariances are per run)."""
    model = _small_model()
    _, ys, _ = model.simulate(T, (2,), generator=torch.Generator().manual_seed(seed))
    mask = torch.ones(2, T, 1, dtype=torch.bool)
    mask[0, 1] = False
    return model, ys, mask


def test_parallel_check_refuses_a_small_mean_error_in_the_second_run_at_its_step(monkeypatch):
    """A scan whose mean of run 1 (of 2) at step 3 is off by 1e-3 posterior sd must be
    refused, the message naming step 3 (1-based, ``x_3``): the docstring's float64
    tolerance is 1e-4 sd, taken as the worst over runs. The spoil is written against the
    sequential filter's sd; unspoiled, the same call passes."""
    model, ys, mask = _two_runs()
    seq = df.kalman_filter(model, ys, mask=mask)
    sd = seq.covs[1, 2].diagonal().sqrt()
    df.kalman_filter(model, ys, mask=mask, method="parallel")  # the exact scan passes

    def spoil(means, covs):
        means[1, 2] += 1e-3 * sd
        return means, covs

    _spoiled_scan(monkeypatch, spoil)
    with pytest.raises(ValueError, match=r"lost accuracy.*first at step 3\b"):
        df.kalman_filter(model, ys, mask=mask, method="parallel")


def test_parallel_check_refuses_a_small_covariance_error_in_the_second_run(monkeypatch):
    """A scan whose covariance of run 1 (of 2, per-run covariances under a mask) at step 4
    is 1e-3 of its scale too large must be refused at step 4 (tolerance 1e-4 of
    ``√(P_ii P_jj)``, worst over runs)."""
    model, ys, mask = _two_runs(1)

    def spoil(means, covs):
        assert covs.shape[0] == 2, "the masked scan keeps a covariance per run"
        covs[1, 3] *= 1.0 + 1e-3
        return means, covs

    _spoiled_scan(monkeypatch, spoil)
    with pytest.raises(ValueError, match=r"lost accuracy.*first at step 4\b"):
        df.kalman_filter(model, ys, mask=mask, method="parallel")


def test_parallel_check_ignores_a_nan_entry_but_not_a_gap_elsewhere(monkeypatch):
    """``scaled_gap`` takes a NaN as 0 (docstring): a NaN in run 0's mean must not hide a
    1e-3 sd error in run 1 at a later step (NaN propagating through the maxima would)."""
    model, ys, mask = _two_runs(2)
    seq = df.kalman_filter(model, ys, mask=mask)
    sd = seq.covs[1, 4].diagonal().sqrt()

    def spoil(means, covs):
        means[0, 1, 0] = float("nan")
        means[1, 4] += 1e-3 * sd
        return means, covs

    _spoiled_scan(monkeypatch, spoil)
    with pytest.raises(ValueError, match=r"lost accuracy.*first at step 5\b"):
        df.kalman_filter(model, ys, mask=mask, method="parallel")


# -- observers: the fixed-gain observer on a time-varying model -----------------------------
def _fk(k):
    c, s = np.cos(0.4 * k), np.sin(0.4 * k)
    return 0.9 * np.array([[c, -s], [s, c]])


def _hk(k):
    return np.array([[1.0, 0.3 * k]])


def _bk(k):
    return np.array([[1.0 + k], [0.5 - k]])


class _TimeVarying(df.LinearGaussianModel):
    """F, B read at k − 1 and H at k (the transition into x_k), each different at every k."""

    time_varying = True

    def transition_matrix(self, k):
        return _t(_fk(k))

    def observation_matrix(self, k):
        return _t(_hk(k))

    def control_matrix(self, k):
        return _t(_bk(k))


def _tv_model():
    return _TimeVarying(_t(_fk(0)), _t(_hk(0)), 0.1 * torch.eye(2, dtype=F64), _t([[0.2]]),
                        _t([0.5, -1.0]), torch.eye(2, dtype=F64), B=_t(_bk(0)))  # fmt: skip


def test_fixed_gain_observer_reads_a_time_varying_model_at_the_right_steps():
    """Three steps of ``m⁻_k = F_{k−1} m + B_{k−1} u``, ``m_k = m⁻_k + L (y_k − H_k m⁻_k)``
    in numpy (the module docstring), on a model whose F, B and H differ at every step."""
    model = _tv_model()
    L = _t([[0.4], [0.1]])
    obs = FixedGainFilter(L)
    carry = obs.init(model, (1,))
    rng = np.random.default_rng(0)
    m = np.array([0.5, -1.0])
    for k in range(1, 4):
        y, u = rng.normal(size=1), rng.normal(size=1)
        carry, out = obs.step(carry, _t(y)[None], _t(u)[None])
        mp = _fk(k - 1) @ m + _bk(k - 1) @ u
        r = y - _hk(k) @ mp
        m = mp + L.numpy() @ r
        np.testing.assert_allclose(out.pred_mean[0].numpy(), mp, rtol=0, atol=1e-13)
        np.testing.assert_allclose(out.innovation[0].numpy(), r, rtol=0, atol=1e-13)
        np.testing.assert_allclose(out.mean[0].numpy(), m, rtol=0, atol=1e-13)


# -- expected_input -------------------------------------------------------------------------
class _Undeclared(_TimeVarying):
    """The time-varying model with ``time_varying`` left false (a user's slip)."""

    time_varying = False


@pytest.mark.parametrize("on_loss", ["zero", "hold"])
def test_expected_input_filter_refuses_an_undeclared_time_varying_model(on_loss):
    """``F_k`` differs between k = 1 and k = 2 while ``time_varying`` is false: like the
    Kalman filter (kalman._check_declared_time_varying's docstring), the expected-input
    filter must refuse the model at init and say to set ``time_varying``; the declared
    model is accepted."""
    est = df.ExpectedInputKalmanFilter(0.7, on_loss=on_loss)
    est.init(_tv_model(), (1,))
    with pytest.raises(ValueError, match="time_varying"):
        est.init(_Undeclared(*(getattr(_tv_model(), n) for n in ("F", "H")),
                             0.1 * torch.eye(2, dtype=F64), _t([[0.2]]), _t([0.5, -1.0]),
                             torch.eye(2, dtype=F64), B=_t(_bk(0))), (1,))  # fmt: skip


# -- input_loss -----------------------------------------------------------------------------
@pytest.mark.parametrize("shape", [(6,), (2, 6, 2, 1)])
def test_input_loss_refuses_a_mask_that_is_not_runs_by_steps(shape):
    """The mask is ``[B, T]`` or ``[B, T, du]`` (docstring): a 1-D or 4-D one is refused at
    construction with a ValueError naming the shapes, not left to fail later."""
    with pytest.raises(ValueError, match=r"\[B, T\].*\[B, T, du\]"):
        InputLoss(torch.ones(shape, dtype=torch.bool))


def _numpy_expected_input(ys, us, rate, on_loss):
    """The UDP-like filter of expected_input's module docstring, one packet, in numpy, on
    the time-varying model (F, B read at k − 1, H at k): ``"zero"`` on ``x``, ``"hold"`` on
    ``s = [x; z]`` with ``Ā = [[F, B(1 − ν̄)], [0, 1 − ν̄]]``, ``G = [B; I]``,
    ``V = ν̄(1 − ν̄)(d dᵀ + P_zz)``. Returns x's filtered means and covariances."""
    Q, R = 0.1 * np.eye(2), np.array([[0.2]])
    m, P = np.array([0.5, -1.0]), np.eye(2)
    if on_loss == "hold":
        m, P = np.append(m, 0.0), np.pad(P, ((0, 1), (0, 1)))
    means, covs = [], []
    for k, (y, u) in enumerate(zip(ys, us), start=1):
        F, B, H = _fk(k - 1), _bk(k - 1), _hk(k)
        if on_loss == "zero":
            Bu = B @ u
            m, P = F @ m + rate * Bu, F @ P @ F.T + Q + rate * (1 - rate) * np.outer(Bu, Bu)
        else:
            d = u - m[2:]
            V = rate * (1 - rate) * (np.outer(d, d) + P[2:, 2:])
            z = m[2:] + rate * d
            A = np.block([[F, B * (1 - rate)], [np.zeros((1, 2)), (1 - rate) * np.eye(1)]])
            G = np.vstack([B, np.eye(1)])
            m = np.concatenate([F @ m[:2] + B @ z, z])
            P = A @ P @ A.T + np.pad(Q, ((0, 1), (0, 1))) + G @ V @ G.T
            H = np.hstack([H, np.zeros((1, 1))])
        S = H @ P @ H.T + R
        K = P @ H.T @ np.linalg.inv(S)
        IKH = np.eye(len(m)) - K @ H
        m, P = m + K @ (y - H @ m), IKH @ P @ IKH.T + K @ R @ K.T
        means.append(m[:2])
        covs.append(P[:2, :2])
    return np.array(means), np.array(covs)


@pytest.mark.parametrize("on_loss", ["zero", "hold"])
def test_expected_input_filter_reads_a_time_varying_model_at_the_right_steps(on_loss):
    """Five steps on a model whose F, B and H differ at every step, against the numpy filter
    of the module docstring (F, B of the transition into x_k read at k − 1, H at k)."""
    from difffilter.loop import open_loop

    gen = torch.Generator().manual_seed(3)
    ys = torch.randn(1, 5, 1, generator=gen, dtype=F64)
    us = torch.randn(1, 5, 1, generator=gen, dtype=F64)
    est = df.ExpectedInputKalmanFilter(0.6, on_loss=on_loss)
    out = open_loop(est, _tv_model(), ys, us)
    means, covs = _numpy_expected_input(ys[0].numpy(), us[0].numpy(), 0.6, on_loss)
    np.testing.assert_allclose(out.means[0].numpy(), means, rtol=0, atol=1e-11)
    np.testing.assert_allclose(out.covs[0].numpy(), covs, rtol=0, atol=1e-11)


# -- parallel_kalman: every matrix of a time-varying model at its step ----------------------
def _qk(k):
    return (0.05 + 0.02 * k) * np.array([[1.0, 0.3], [0.3, 0.5]])


def _rk(k):
    return np.array([[0.2 + 0.1 * k]])


class _TimeVaryingNoise(_TimeVarying):
    """The time-varying model with ``Q`` (read at k − 1) and ``R`` (at k) varying too."""

    def process_cov(self, k):
        return _t(_qk(k))

    def measurement_cov(self, k):
        return _t(_rk(k))


@pytest.mark.parametrize("method", ["sequential", "parallel"])
def test_kalman_filter_reads_f_b_q_at_k_minus_1_and_h_r_at_k(method):
    """Seven steps (odd, so the scan's odd/even recursion is uneven) with inputs on a model
    whose F, B, Q, H and R all differ at every step, against a numpy Kalman filter that
    predicts with ``F_{k−1}, B_{k−1}, Q_{k−1}`` and updates with ``H_k, R_k``: means,
    covariances and the log-likelihood."""
    model = _TimeVaryingNoise(_t(_fk(0)), _t(_hk(0)), _t(_qk(0)), _t(_rk(0)), _t([0.5, -1.0]),
                              torch.eye(2, dtype=F64), B=_t(_bk(0)))  # fmt: skip
    gen = torch.Generator().manual_seed(4)
    ys = torch.randn(1, 7, 1, generator=gen, dtype=F64)
    us = torch.randn(1, 7, 1, generator=gen, dtype=F64)
    res = df.kalman_filter(model, ys, us, method=method)
    m, P, ll = np.array([0.5, -1.0]), np.eye(2), 0.0
    for k in range(1, 8):
        y, u = ys[0, k - 1].numpy(), us[0, k - 1].numpy()
        m = _fk(k - 1) @ m + _bk(k - 1) @ u
        P = _fk(k - 1) @ P @ _fk(k - 1).T + _qk(k - 1)
        H, R = _hk(k), _rk(k)
        S = H @ P @ H.T + R
        r = y - H @ m
        ll += -0.5 * (r @ np.linalg.solve(S, r) + np.log(np.linalg.det(2 * np.pi * S)))
        K = P @ H.T @ np.linalg.inv(S)
        m, P = m + K @ r, (np.eye(2) - K @ H) @ P @ (np.eye(2) - K @ H).T + K @ R @ K.T
        np.testing.assert_allclose(res.means[0, k - 1].numpy(), m, rtol=0, atol=1e-10)
        np.testing.assert_allclose(res.covs[..., k - 1, :, :].reshape(2, 2).numpy(), P, rtol=0,
                                   atol=1e-10)  # fmt: skip
    np.testing.assert_allclose(float(res.log_likelihood[0]), ll, rtol=0, atol=1e-10)


@pytest.mark.parametrize("runs", [1, 3])
def test_input_loss_check_refuses_a_mask_of_another_number_of_runs(runs):
    """``check`` must refuse a mask whose runs are not the loop's (docstring: ``[runs, T >=
    end]``): a one-run mask would otherwise broadcast one run's arrivals over every run."""
    loss = InputLoss(torch.ones(runs, 10, dtype=torch.bool), "zero")
    loss.check(runs, 1, 10)  # the matching loop passes
    with pytest.raises(ValueError, match=r"mask must be \[2, T >= 10\]"):
        loss.check(2, 1, 10)


def test_input_loss_schedule_refuses_a_non_boolean_acknowledged():
    """``acknowledged`` is True or False (as for InputLoss): a string such as ``"no"``,
    truthy, must be refused rather than taken as acknowledged."""
    from difffilter.input_loss import InputLossSchedule

    class _Schedule:
        def mask(self, batch_shape, num_steps, dim, generator=None, device=None):
            return torch.ones(*batch_shape, num_steps, dim, dtype=torch.bool)

    assert InputLossSchedule(_Schedule(), acknowledged=False).draw(2, 5, 1).acknowledged is False
    with pytest.raises(ValueError, match="acknowledged must be True or False"):
        InputLossSchedule(_Schedule(), acknowledged="no")


# -- construction-time validation --------------------------------------------------------------
@pytest.mark.parametrize("shape", [(4,), (1, 4, 2)])
def test_fixed_gain_observer_refuses_a_gain_that_is_not_a_matrix(shape):
    """``gain: L [dx, dy]`` (docstring): a vector or a batch of matrices is refused at
    construction, naming ``[dx, dy]``."""
    with pytest.raises(ValueError, match=r"gain must be a tensor \[dx, dy\]"):
        FixedGainFilter(torch.zeros(shape, dtype=F64))


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_fixed_gain_observer_refuses_a_gain_that_is_not_finite(bad):
    """A NaN or infinite entry of ``L`` is refused at construction, naming ``gain`` (one
    had run, and every estimate was NaN from the first step on)."""
    gain = 0.5 * torch.eye(4, 2, dtype=F64)
    gain[1, 0] = bad
    with pytest.raises(ValueError, match="gain contains NaN or Inf"):
        FixedGainFilter(gain)


def test_expected_input_rate_as_a_0d_tensor_is_the_number():
    """A 0-d tensor rate is a number in (0, 1] (docstring): accepted as that number, for one
    packet as well as per actuator."""
    for independent in (False, True):
        est = df.ExpectedInputKalmanFilter(torch.tensor(0.6), independent=independent)
        assert est.arrival_rate.dim() == 0 and float(est.arrival_rate) == pytest.approx(0.6)


def test_expected_input_per_actuator_rates_are_a_copy_without_gradient():
    """ "The rate is a number, not a parameter: no gradient reaches it" (docstring): a rate
    tensor that requires grad is stored detached, and a later in-place change of the
    caller's tensor does not move the filter's rate."""
    given = torch.tensor([0.3, 0.9], dtype=F64, requires_grad=True)
    est = df.ExpectedInputKalmanFilter(given, independent=True)
    assert not est.arrival_rate.requires_grad
    with torch.no_grad():
        given[0] = 0.5
    assert est.arrival_rate.tolist() == [0.3, 0.9]
