"""The Kalman filter's general one-run step on host arrays (difffilter._kf_host_step) against
its torch update.

A masked step of one run, and every step of a carry without a gain schedule, takes the
host-array update where autograd records nothing; it must give the torch update's numbers
(the same equations) to round-off, fall back to torch wherever that update does more
(jitter, a breakdown, a gradient), and leave every other filter alone.
"""

from __future__ import annotations

import math

import pytest
import torch

import difffilter as df
from difffilter import _kf_host_step, kalman

STEPS = 60


def _model(dtype=torch.float64, control=True):
    """A 4-state, 3-output linear model with a full measurement covariance and (on request)
    a 2-input control matrix."""
    g = torch.Generator().manual_seed(3)
    F = torch.eye(4, dtype=dtype) + 0.1 * torch.randn(4, 4, generator=g, dtype=dtype)
    H = torch.randn(3, 4, generator=g, dtype=dtype)
    a = torch.randn(3, 3, generator=g, dtype=dtype)
    R = 0.1 * a @ a.T + 0.05 * torch.eye(3, dtype=dtype)
    B = torch.randn(4, 2, generator=g, dtype=dtype) if control else None
    Q = 0.02 * torch.eye(4, dtype=dtype)
    return df.LinearGaussianModel(F, H, Q, R, torch.zeros(4, dtype=dtype),
                                  torch.eye(4, dtype=dtype), B=B)  # fmt: skip


def _inputs(dtype, control=True, seed=0):
    g = torch.Generator().manual_seed(seed)
    ys = torch.randn(STEPS, 3, generator=g, dtype=dtype)
    us = torch.randn(STEPS, 2, generator=g, dtype=dtype) if control else None
    masks = torch.rand(STEPS, 3, generator=g) > 0.3
    masks[5] = False  # a step without any measurement
    masks[6] = True  # a step with every one (after a masked step: the general update too)
    return ys, us, masks


def _run(model, ys, us, masks, host: bool):
    """The carries' means and every step's outputs of ``KalmanFilter().step``; with
    ``host``, under ``torch.no_grad()`` (the host-array step), else with a gradient
    recorded (the torch update: ``y`` requires one)."""
    kf, outs = df.KalmanFilter(), []
    with torch.set_grad_enabled(not host):
        carry = kf.init(model, ())
        for k in range(STEPS):
            y = ys[k] if host else ys[k].clone().requires_grad_()
            u = None if us is None else us[k]
            carry, out = kf.step(carry, y, u, masks[k])
            outs.append(out)
    return carry, outs


def _assert_same(a, b, rtol, atol):
    (ca, oa), (cb, ob) = a, b
    assert ca.k == cb.k == STEPS and ca.gains is None and cb.gains is None
    for x, y in zip(oa, ob):
        for name in ("mean", "cov", "pred_mean", "pred_cov", "innovation", "innovation_cov",
                     "log_likelihood"):  # fmt: skip
            got, want = getattr(x, name), getattr(y, name)
            assert got.dtype == want.dtype and got.shape == want.shape, name
            torch.testing.assert_close(got, want.detach(), rtol=rtol, atol=atol, msg=name)


@pytest.mark.parametrize("control", [True, False])
def test_the_host_step_equals_the_torch_update(control, monkeypatch):
    """float64: every output of 60 masked steps (a step without measurements, one with all
    of them) to round-off; the host step is taken at every step under ``no_grad`` and at
    none with a gradient recorded."""
    taken = []
    host_step = _kf_host_step.host_step

    def counting(*args):
        result = host_step(*args)
        taken.append(result is not None)
        return result

    monkeypatch.setattr(_kf_host_step, "host_step", counting)
    model = _model(control=control)
    ys, us, masks = _inputs(torch.float64, control)
    host = _run(model, ys, us, masks, host=True)
    assert taken == [True] * STEPS
    taken.clear()
    torch_update = _run(model, ys, us, masks, host=False)
    assert taken == [False] * STEPS
    _assert_same(host, torch_update, rtol=1e-10, atol=1e-12)
    # the masked entries: a zero innovation, a unit and uncorrelated innovation variance
    out = host[1][5]
    assert torch.equal(out.innovation, torch.zeros(3, dtype=torch.float64))
    assert torch.equal(out.innovation_cov, torch.eye(3, dtype=torch.float64))
    assert float(out.log_likelihood) == 0.0  # no entry received: log N of nothing


def test_the_host_step_in_float32():
    """float32: the same outputs to float32's round-off over 60 steps."""
    model = _model(torch.float32)
    ys, us, masks = _inputs(torch.float32)
    host = _run(model, ys, us, masks, host=True)
    assert host[1][-1].mean.dtype == torch.float32
    _assert_same(host, _run(model, ys, us, masks, host=False), rtol=2e-4, atol=2e-5)


def test_the_evidence_is_the_density_of_the_received_entries():
    """log N(r'; 0, S) of a step with entries 0 and 2 received equals the density of those
    entries alone under the predicted moments, computed here directly."""
    model = _model(control=False)
    y = torch.tensor([0.3, float("nan"), -0.7], dtype=torch.float64)
    mask = torch.tensor([True, False, True])
    kf = df.KalmanFilter()
    with torch.no_grad():
        carry = kf.init(model, ())
        _, out = kf.step(carry, y, None, mask)
    P = model.F @ model.initial.cov @ model.F.T + model.process_noise.cov
    H, R = model.H[[0, 2]], model.measurement_noise.cov[[0, 2]][:, [0, 2]]
    S = H @ P @ H.T + R
    want = torch.distributions.MultivariateNormal(torch.zeros(2, dtype=S.dtype), S).log_prob(
        y[[0, 2]]
    )
    assert float(out.log_likelihood) == pytest.approx(float(want), rel=1e-12)
    gain = P @ H.T @ torch.linalg.inv(S)
    torch.testing.assert_close(out.mean, gain @ y[[0, 2]], rtol=1e-12, atol=1e-14)


def test_a_matrix_that_is_not_positive_definite_is_left_to_the_torch_update():
    """``S`` not positive definite (a carry whose covariance is negative): the host step
    declines, and the torch update raises its NumericalBreakdown, naming the innovation
    covariance."""
    model = _model(control=False)
    kf = df.KalmanFilter()
    y, mask = torch.ones(3, dtype=torch.float64), torch.tensor([True, True, False])
    with torch.no_grad():
        carry = kf.init(model, ())
        carry = carry._replace(cov=-100.0 * torch.eye(4, dtype=torch.float64), gains=None)
        assert _kf_host_step.host_step(carry, y, None, mask) is None
        with pytest.raises(df.NumericalBreakdown, match="innovation"):
            kf.update(carry, kf.predict(carry, None), y, mask)


def test_the_host_step_is_declined_where_the_torch_update_differs():
    """A batch of runs, a learnable matrix with grad enabled, a transform and the
    expected-input filter (its own prediction) never take the host step."""
    model = _model(control=False)
    y, mask = torch.zeros(3, dtype=torch.float64), torch.tensor([True, False, True])
    kf = df.KalmanFilter()
    batched = kf.init(model, (2,))
    assert _kf_host_step.host_step(batched, y.expand(2, 3), None, mask.expand(2, 3)) is None
    one = kf.init(model, ())
    assert _kf_host_step.host_step(one, y, None, mask) is not None
    model.F.requires_grad_()
    assert _kf_host_step.host_step(kf.init(model, ()), y, None, mask) is None
    with torch.no_grad():  # nothing is recorded: the host step again
        assert _kf_host_step.host_step(kf.init(model, ()), y, None, mask) is not None
    model.F.requires_grad_(False)
    seen = []
    torch.func.vmap(lambda t: seen.append(_kf_host_step.host_step(one, t, None, mask)) or t)(
        y.expand(2, 3)
    )
    assert seen == [None]
    assert kalman._own_update(df.KalmanFilter)
    assert not kalman._own_update(df.ExpectedInputKalmanFilter)


def test_a_gradient_flows_through_a_masked_step():
    """With a gradient recorded the torch update steps: ``∂ log p / ∂ y`` of one masked step
    is ``−S⁻¹ r`` on the received entries and 0 on the lost one."""
    model = _model(control=False)
    kf = df.KalmanFilter()
    y = torch.tensor([0.3, 0.5, -0.7], dtype=torch.float64, requires_grad=True)
    mask = torch.tensor([True, False, True])
    _, out = kf.step(kf.init(model, ()), y, None, mask)
    (grad,) = torch.autograd.grad(out.log_likelihood, y)
    S = out.innovation_cov[[0, 2]][:, [0, 2]]
    want = -torch.linalg.solve(S, out.innovation[[0, 2]])
    torch.testing.assert_close(grad[[0, 2]], want.detach(), rtol=1e-10, atol=1e-12)
    assert float(grad[1]) == 0.0 and math.isfinite(out.log_likelihood.item())


def test_a_review_s_three_cases_take_the_torch_update():
    """A review of the host step: a carry of one mean and a batch of covariances (the torch
    update broadcasts it; numpy's ``.T`` reversed all three axes: wrong numbers where n =
    dx = dy), a nearly singular ``S`` (numpy factored what torch jitters: 2.6 nats apart),
    and an update given to the object itself (bypassed) are all the torch update's."""
    dtype = torch.float64
    model = df.LinearGaussianModel(torch.eye(2, dtype=dtype), torch.eye(2, dtype=dtype),
                                   0.1 * torch.eye(2, dtype=dtype), 0.2 * torch.eye(2, dtype=dtype),
                                   torch.zeros(2, dtype=dtype), torch.eye(2, dtype=dtype))  # fmt: skip
    kf, mask = df.KalmanFilter(), torch.tensor([True, True])
    y = torch.tensor([0.5, -0.5], dtype=dtype)
    covs = torch.stack(
        [torch.eye(2, dtype=dtype), torch.tensor([[2.0, 0.3], [0.3, 1.0]], dtype=dtype)]
    )
    stacked = df.GaussianState(torch.zeros(2, dtype=dtype), covs, 0, model)
    with torch.no_grad():
        assert _kf_host_step.host_step(stacked, y, None, mask) is None
        _, out = kf.step(stacked, y, None, mask)
        want = kf.update(stacked, kf.predict(stacked, None), y, mask)[1]
    assert out.log_likelihood.shape == (2,)
    torch.testing.assert_close(out.log_likelihood, want.log_likelihood, rtol=0, atol=0)

    # S = H P⁻ Hᵀ singular (R = 0 from a time-varying override, a third output the sum of
    # the first two): numpy factors some of these (2 of the first 3 here), torch jitters
    class NoiselessOutputs(df.LinearGaussianModel):
        time_varying = True

        def measurement_cov(self, k):
            return torch.zeros(3, 3, dtype=dtype)

    g = torch.Generator().manual_seed(5)
    for _ in range(10):
        F = torch.eye(4, dtype=dtype) + 0.1 * torch.randn(4, 4, generator=g, dtype=dtype)
        H = torch.randn(3, 4, generator=g, dtype=dtype)
        H[2] = H[0] + H[1]
        singular = NoiselessOutputs(F, H, 0.02 * torch.eye(4, dtype=dtype), torch.eye(3, dtype=dtype),
                                    torch.zeros(4, dtype=dtype), torch.eye(4, dtype=dtype))  # fmt: skip
        carry = kf.init(singular, ())
        assert _kf_host_step.host_step(carry, torch.zeros(3, dtype=dtype), None,
                                       torch.tensor([True, True, True])) is None  # fmt: skip
    # an update of the object's own: called at every step
    calls = []
    plain = df.KalmanFilter()

    def update(*args, **kwargs):
        calls.append(1)
        return df.KalmanFilter.update(plain, *args, **kwargs)

    plain.update = update
    assert not kalman._own_update(plain) and kalman._own_update(df.KalmanFilter())
    with torch.no_grad():
        carry = plain.init(model, ())
        for _ in range(3):
            carry, _ = plain.step(carry, y, None, mask)
    assert len(calls) == 3


def test_an_overflowing_step_raises_the_breakdown_without_numpy_s_warnings():
    """A carry whose covariance overflows in the prediction (1.7e308 in float64): the host
    step declines without numpy's "overflow encountered" RuntimeWarning (a review: it
    escaped before the torch update's NumericalBreakdown, which names the trouble)."""
    import warnings

    model = _model(control=False)
    kf = df.KalmanFilter()
    y, mask = torch.ones(3, dtype=torch.float64), torch.tensor([True, True, False])
    with torch.no_grad():
        carry = kf.init(model, ())
        carry = carry._replace(cov=1.7e308 * torch.eye(4, dtype=torch.float64), gains=None)
        with warnings.catch_warnings():
            warnings.simplefilter("error", RuntimeWarning)
            assert _kf_host_step.host_step(carry, y, None, mask) is None
            with pytest.raises(df.NumericalBreakdown):
                kf.step(carry, y, None, mask)
