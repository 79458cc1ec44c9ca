"""Gaussian filters against closed forms and independent references (float64)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import constant_velocity
from reference import dense_joint_gaussian, numpy_kalman_filter

import difffilter as df
from difffilter.noise import Gaussian

METHODS = ["sequential", "parallel"]


def _np(model):
    return [
        t.detach().numpy()
        for t in (
            model.F,
            model.H,
            model.process_noise.cov,
            model.measurement_noise.cov,
            model.initial.mean,
            model.initial.cov,
        )
    ]


@pytest.mark.parametrize("method", METHODS)
def test_kf_equals_dense_joint_gaussian(method, generator):
    model = constant_velocity()
    _, ys, _ = model.simulate(8, (), generator=generator)
    res = df.kalman_filter(model, ys, method=method)
    F, H, Q, R, m0, P0 = _np(model)
    y = ys.numpy()
    # filtered mean at t = posterior of x_t given y_{1:t}: condition the joint on a prefix
    for t in range(1, 9):
        _, last, ll = dense_joint_gaussian(F, H, Q, R, m0, P0, y[:t])
        np.testing.assert_allclose(res.means[t - 1].numpy(), last, atol=1e-10, rtol=0)
        np.testing.assert_allclose(
            res.log_likelihood_increments[:t].sum().item(), ll, atol=1e-10, rtol=0
        )


@pytest.mark.parametrize("method", METHODS)
def test_kf_masked_equals_dense_joint_gaussian(method, generator):
    model = constant_velocity()
    _, ys, _ = model.simulate(10, (), generator=generator)
    mask = torch.rand(10, 2, generator=generator) > 0.4
    mask[3] = False  # a fully lost packet
    ys = torch.where(mask, ys, torch.nan)  # lost entries may be NaN
    res = df.kalman_filter(model, ys, mask=mask, method=method)
    F, H, Q, R, m0, P0 = _np(model)
    y = np.nan_to_num(ys.numpy())
    _, last, ll = dense_joint_gaussian(F, H, Q, R, m0, P0, y, mask.numpy())
    np.testing.assert_allclose(res.means[-1].numpy(), last, atol=1e-10, rtol=0)
    np.testing.assert_allclose(res.log_likelihood.item(), ll, atol=1e-10, rtol=0)


@pytest.mark.parametrize("method", METHODS)
def test_kf_equals_numpy_reference_with_inputs_and_mask(method, generator):
    model = constant_velocity(with_input=True)
    us = torch.randn(3, 25, 1, dtype=torch.float64, generator=generator)
    _, ys, _ = model.simulate(25, (3,), us=us, generator=generator)
    mask = torch.rand(3, 25, 2, generator=generator) > 0.3
    res = df.kalman_filter(model, ys, us, mask=mask, method=method)
    F, H, Q, R, m0, P0 = _np(model)
    for b in range(3):
        means, covs, ll = numpy_kalman_filter(
            F,
            H,
            Q,
            R,
            m0,
            P0,
            ys[b].numpy(),
            B=model.B.numpy(),
            us=us[b].numpy(),
            mask=mask[b].numpy(),
        )
        np.testing.assert_allclose(res.means[b].numpy(), means, atol=1e-10, rtol=0)
        np.testing.assert_allclose(res.covs[b].numpy(), covs, atol=1e-10, rtol=0)
        np.testing.assert_allclose(res.log_likelihood[b].item(), ll, atol=1e-10, rtol=0)


def test_kf_matches_filterpy(generator):
    filterpy = pytest.importorskip("filterpy.kalman")
    model = constant_velocity()
    _, ys, _ = model.simulate(30, (), generator=generator)
    res = df.kalman_filter(model, ys)
    F, H, Q, R, m0, P0 = _np(model)
    kf = filterpy.KalmanFilter(dim_x=4, dim_z=2)
    kf.x, kf.P, kf.F, kf.H, kf.Q, kf.R = m0.copy(), P0.copy(), F, H, Q, R
    for t, y in enumerate(ys.numpy()):
        kf.predict()
        kf.update(y)
        np.testing.assert_allclose(res.means[t].numpy(), kf.x, atol=1e-9)
        np.testing.assert_allclose(res.covs[t].numpy(), kf.P, atol=1e-9)


class RotatingModel(df.LinearGaussianModel):
    """A time-varying model: F rotates with k, R grows with k."""

    time_varying = True

    def transition_matrix(self, k):
        c, s = np.cos(0.1 * k), np.sin(0.1 * k)
        rot = torch.tensor([[c, -s], [s, c]], dtype=self.F.dtype)
        return 0.95 * torch.block_diag(rot, rot)

    def measurement_cov(self, k):
        return self.measurement_noise.cov * (1.0 + 0.1 * k)


def test_parallel_equals_sequential_batched_time_varying(generator):
    base = constant_velocity()
    model = RotatingModel(
        base.F,
        base.H,
        base.process_noise.cov,
        base.measurement_noise.cov,
        base.initial.mean,
        base.initial.cov,
    )
    _, ys, _ = model.simulate(33, (2, 3), generator=generator)
    a = df.kalman_filter(model, ys, method="sequential")
    b = df.kalman_filter(model, ys, method="parallel")
    for name in [
        "means",
        "covs",
        "pred_means",
        "pred_covs",
        "innovations",
        "innovation_covs",
        "log_likelihood",
    ]:
        torch.testing.assert_close(getattr(b, name), getattr(a, name), atol=1e-9, rtol=1e-9)


@pytest.mark.parametrize("filt", ["ekf", "ukf"])
def test_ekf_ukf_equal_kf_on_linear_model(filt, generator):
    model = constant_velocity(with_input=True)
    us = torch.randn(4, 20, 1, dtype=torch.float64, generator=generator)
    _, ys, _ = model.simulate(20, (4,), us=us, generator=generator)
    mask = torch.rand(4, 20, 2, generator=generator) > 0.25
    kf = df.kalman_filter(model, ys, us, mask=mask)
    run = df.extended_kalman_filter if filt == "ekf" else df.unscented_kalman_filter
    other = run(model, ys, us, mask=mask)
    for name in ["means", "covs", "innovations", "innovation_covs", "log_likelihood"]:
        torch.testing.assert_close(getattr(other, name), getattr(kf, name), atol=1e-10, rtol=1e-10)


def test_an_untraceable_function_is_named_at_one_run_too():
    """A transition that reads ``.item()`` has no torch.func Jacobian: one run online (an
    unbatched step, the Jacobian of one row) raises the error that names it, as a batch
    does. ``torch.func.jacfwd`` alone, without the ``vmap`` over that row, returns a wrong
    Jacobian silently here (``0.6 I`` for ``v · Σv`` at ``(0.3, 0.2, 0.1)``: the ``.item()``
    taken for a constant; tried as a speed-up on 2026-12-04, not kept)."""
    eye = torch.eye(3, dtype=torch.float64)
    model = df.NonlinearGaussianModel(lambda x: x * x.sum().item(), lambda x: x, 0.01 * eye,
                                      0.1 * eye, torch.tensor([0.3, 0.2, 0.1],
                                      dtype=torch.float64), eye)  # fmt: skip
    ekf = df.ExtendedKalmanFilter()
    for batch in [(), (2,)]:
        carry = ekf.init(model, batch)
        y = torch.zeros(*batch, 3, dtype=torch.float64)
        with pytest.raises(RuntimeError, match="differentiating .* with torch.func"):
            ekf.step(carry, y)


def test_nonlinear_model_autodiff_jacobians_match_closed_form(generator):
    def f(x, u):
        return torch.stack(
            [x[..., 0] + 0.1 * torch.sin(x[..., 1]), 0.9 * x[..., 1] + u[..., 0]], -1
        )

    def h(x):
        return (x[..., :1] ** 2) / 10.0

    def jf(x, u):
        z = torch.zeros_like(x[..., 0])
        row0 = torch.stack([torch.ones_like(z), 0.1 * torch.cos(x[..., 1])], -1)
        row1 = torch.stack([z, 0.9 + z], -1)
        return torch.stack([row0, row1], -2)

    kw = dict(
        Q=0.01 * torch.eye(2, dtype=torch.float64),
        R=0.1 * torch.eye(1, dtype=torch.float64),
        m0=torch.ones(2, dtype=torch.float64),
        P0=torch.eye(2, dtype=torch.float64),
        dim_u=1,
    )
    auto = df.NonlinearGaussianModel(f, h, **kw)
    closed = df.NonlinearGaussianModel(f, h, transition_jacobian=jf, **kw)
    x = torch.randn(5, 2, dtype=torch.float64, generator=generator)
    u = torch.randn(5, 1, dtype=torch.float64, generator=generator)
    torch.testing.assert_close(auto.transition_jacobian(x, u, 0), jf(x, u))
    torch.testing.assert_close(auto.observation_jacobian(x, 1)[..., 0, 0], x[..., 0] / 5.0)
    us = torch.randn(3, 15, 1, dtype=torch.float64, generator=generator)
    _, ys, _ = auto.simulate(15, (3,), us=us, generator=generator)
    torch.testing.assert_close(
        df.extended_kalman_filter(auto, ys, us).means,
        df.extended_kalman_filter(closed, ys, us).means,
    )


def test_fully_masked_step_equals_prediction(cv_model, generator):
    _, ys, _ = cv_model.simulate(6, (2,), generator=generator)
    mask = torch.ones(2, 6, 2, dtype=torch.bool)
    mask[:, 3] = False
    for run in (df.kalman_filter, df.extended_kalman_filter, df.unscented_kalman_filter):
        res = run(cv_model, ys, mask=mask)
        torch.testing.assert_close(res.means[:, 3], res.pred_means[:, 3], atol=1e-12, rtol=0)
        torch.testing.assert_close(res.covs[:, 3], res.pred_covs[:, 3], atol=1e-12, rtol=0)
        assert torch.all(res.log_likelihood_increments[:, 3] == 0)
        # and the prediction is F m_{t-1}, F P F' + Q exactly
        F, Q = cv_model.F, cv_model.process_noise.cov
        torch.testing.assert_close(res.pred_means[:, 3], res.means[:, 2] @ F.T, atol=1e-12, rtol=0)
        torch.testing.assert_close(
            res.pred_covs[:, 3], F @ res.covs[:, 2] @ F.T + Q, atol=1e-12, rtol=0
        )


def test_online_step_api_matches_whole_run(cv_model, generator):
    _, ys, _ = cv_model.simulate(12, (3,), generator=generator)
    whole = df.kalman_filter(cv_model, ys)
    state = df.gaussian_init(cv_model, (3,))
    for t in range(12):
        state, out = df.kalman_step(cv_model, state, ys[:, t])
        torch.testing.assert_close(out.mean, whole.means[:, t])
        torch.testing.assert_close(out.log_likelihood, whole.log_likelihood_increments[:, t])
    assert state.k == 12


def test_unbatched_model_shares_covariance_across_runs(cv_model, generator):
    # covariances of an LTI model without mask do not depend on the data
    _, ys, _ = cv_model.simulate(5, (7,), generator=generator)
    res = df.kalman_filter(cv_model, ys)
    assert res.covs.shape == (7, 5, 4, 4)
    torch.testing.assert_close(res.covs[0], res.covs[6])


def test_gradcheck_kf_log_likelihood_wrt_F_Q_R(generator):
    base = constant_velocity()
    _, ys, _ = base.simulate(6, (2,), generator=generator)
    H, m0, P0 = base.H, base.initial.mean, base.initial.cov

    def loglik(F, Lq, Lr):
        Q = Lq @ Lq.T + 1e-3 * torch.eye(4, dtype=torch.float64)
        R = Lr @ Lr.T + 1e-2 * torch.eye(2, dtype=torch.float64)
        return df.kalman_filter(df.LinearGaussianModel(F, H, Q, R, m0, P0), ys).log_likelihood

    F = base.F.clone().requires_grad_()
    Lq = torch.linalg.cholesky(
        base.process_noise.cov + 1e-2 * torch.eye(4, dtype=torch.float64)
    ).requires_grad_()
    Lr = torch.linalg.cholesky(base.measurement_noise.cov).requires_grad_()
    assert torch.autograd.gradcheck(loglik, (F, Lq, Lr), eps=1e-6, atol=1e-6)

    def loglik_par(F, Lq, Lr):
        Q = Lq @ Lq.T + 1e-3 * torch.eye(4, dtype=torch.float64)
        R = Lr @ Lr.T + 1e-2 * torch.eye(2, dtype=torch.float64)
        return df.kalman_filter(
            df.LinearGaussianModel(F, H, Q, R, m0, P0), ys, method="parallel"
        ).log_likelihood

    assert torch.autograd.gradcheck(loglik_par, (F, Lq, Lr), eps=1e-6, atol=1e-6)


def test_gradcheck_kf_log_likelihood_wrt_covariances_directly(generator):
    base = constant_velocity()
    _, ys, _ = base.simulate(5, (), generator=generator)

    def loglik(Q, R):
        Q, R = 0.5 * (Q + Q.T), 0.5 * (R + R.T)
        return df.kalman_filter(
            df.LinearGaussianModel(base.F, base.H, Q, R, base.initial.mean, base.initial.cov), ys
        ).log_likelihood

    Q = base.process_noise.cov.clone().requires_grad_()
    R = base.measurement_noise.cov.clone().requires_grad_()
    assert torch.autograd.gradcheck(loglik, (Q, R), eps=1e-7, atol=1e-5)


def test_auto_method_rejects_unknown(cv_model):
    with pytest.raises(ValueError, match="method"):
        df.kalman_filter(cv_model, torch.zeros(3, 2, dtype=torch.float64), method="magic")


# ------------------------------------------------- shared-covariance fast path (issue 12)


def _general(model, ys, us=None, mask=None):
    """The step-by-step filter without the shared fast paths (a carry without gains)."""
    from difffilter.kalman import KalmanFilter, gaussian_init
    from difffilter.loop import open_loop

    batch = ys.shape[:-2] if us is None else torch.broadcast_shapes(ys.shape[:-2], us.shape[:-2])
    carry = gaussian_init(model, batch)
    out = open_loop(KalmanFilter(), model, ys, us, mask=mask, carry=carry)
    return df.FilterResult.from_output(out)


FIELDS = (
    "means",
    "covs",
    "pred_means",
    "pred_covs",
    "innovations",
    "innovation_covs",
    "log_likelihood_increments",
    "log_likelihood",
)


@pytest.mark.parametrize("run_chunk", [4096, 2])  # 2: several run chunks, a ragged last one
@pytest.mark.parametrize("with_input", [False, True])
@pytest.mark.parametrize("batch, T", [((), 1), ((3,), 7), ((2, 3), 13), ((5,), 16), ((4,), 61)])
def test_shared_covariance_path_equals_the_general_path(
    with_input, batch, T, run_chunk, generator, monkeypatch
):
    from difffilter import _shared_cov
    from difffilter._shared_cov import shared_covariance_applies

    monkeypatch.setattr(_shared_cov, "RUN_CHUNK", run_chunk)
    model = constant_velocity(with_input=with_input)
    us = torch.randn(*batch, T, 1, dtype=torch.float64, generator=generator) if with_input else None
    _, ys, _ = model.simulate(T, batch, us=us, generator=generator)
    assert shared_covariance_applies(model, None)
    fast, ref = df.kalman_filter(model, ys, us), _general(model, ys, us)
    for name in FIELDS:
        a, b = getattr(fast, name), getattr(ref, name)
        assert a.shape == b.shape, name
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10, msg=name)
    if batch:  # covariances are views of one [T, dx, dx] tensor, not B copies
        assert fast.covs.stride(0) == 0 and fast.innovation_covs.stride(0) == 0


def test_shared_covariance_path_is_chosen_only_when_it_applies(cv_model, generator):
    from difffilter._shared_cov import shared_covariance_applies

    _, ys, _ = cv_model.simulate(5, (3,), generator=generator)
    mask = torch.ones(3, 5, 2, dtype=torch.bool)
    assert not shared_covariance_applies(cv_model, mask)
    batched = df.LinearGaussianModel(
        cv_model.F.expand(3, 4, 4),
        cv_model.H,
        cv_model.process_noise.cov,
        cv_model.measurement_noise.cov,
        cv_model.initial.mean,
        cv_model.initial.cov,
    )
    assert not shared_covariance_applies(batched, None)
    torch.testing.assert_close(
        df.kalman_filter(batched, ys).means, df.kalman_filter(cv_model, ys).means
    )


@pytest.mark.parametrize("with_input", [False, True])
def test_shared_covariance_path_gradients_equal_the_general_path(with_input, generator):
    base = constant_velocity(with_input=with_input)
    us = torch.randn(3, 11, 1, dtype=torch.float64, generator=generator) if with_input else None
    _, ys, _ = base.simulate(11, (3,), us=us, generator=generator)

    def grads(run):
        F = base.F.clone().requires_grad_()
        R = base.measurement_noise.cov.clone().requires_grad_()
        model = df.LinearGaussianModel(
            F,
            base.H,
            base.process_noise.cov,
            R,
            base.initial.mean,
            base.initial.cov,
            B=base.B if with_input else None,
        )
        res = run(model, ys, us)
        (res.log_likelihood.sum() + res.means.square().sum()).backward()
        return F.grad, R.grad

    for a, b in zip(grads(df.kalman_filter), grads(_general)):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-10)


def test_gain_schedule_reproduces_the_kalman_filter_with_inputs():
    """The shared-gain online step equals difffilter.kalman_filter on every run (1e-10),
    converges, and refuses a batched model."""
    gen = torch.Generator().manual_seed(4)
    F = torch.tensor([[1.0, 0.1], [0.0, 0.9]], dtype=torch.float64)
    H = torch.tensor([[1.0, 0.5]], dtype=torch.float64)
    model = df.LinearGaussianModel(
        F, H, 0.01 * torch.eye(2, dtype=torch.float64), torch.tensor([[0.04]], dtype=torch.float64),
        torch.zeros(2, dtype=torch.float64), torch.eye(2, dtype=torch.float64),
        B=torch.tensor([[0.0], [0.1]], dtype=torch.float64),
    )  # fmt: skip
    B, T = 4, 120
    ys = torch.randn(B, T, 1, generator=gen, dtype=torch.float64)
    us = torch.randn(B, T, 1, generator=gen, dtype=torch.float64)
    ref = df.kalman_filter(model, ys, us)
    schedule, mean = df.GainSchedule(model), model.initial.mean.expand(B, 2)
    for t in range(T):
        mean, innovation, S = schedule.update(schedule.predict(mean, us[:, t]), ys[:, t], t + 1)
        torch.testing.assert_close(mean, ref.means[:, t], rtol=0, atol=1e-10)
        torch.testing.assert_close(innovation, ref.innovations[:, t], rtol=0, atol=1e-10)
        torch.testing.assert_close(S, ref.innovation_covs[0, t], rtol=0, atol=1e-12)
    assert schedule.converged and len(schedule._moments) < T  # reused once converged
    batched = df.LinearGaussianModel(
        F.expand(2, 2, 2), H, torch.eye(2, dtype=torch.float64), torch.eye(1, dtype=torch.float64),
        torch.zeros(2, dtype=torch.float64), torch.eye(2, dtype=torch.float64),
    )  # fmt: skip
    with pytest.raises(ValueError, match="no batch dimension"):
        df.GainSchedule(batched)
    with pytest.raises(ValueError, match="k must be"):
        schedule.gain(0)


def _random_linear_model(dx=5, dy=3, du=2, seed=7):
    """A stable linear-Gaussian model with full matrices (every product of the recursion
    rounds), float64."""
    gen = torch.Generator().manual_seed(seed)

    def spd(d):
        a = torch.randn(d, d, generator=gen, dtype=torch.float64)
        return a @ a.T / d + 0.1 * torch.eye(d, dtype=torch.float64)

    a = torch.randn(dx, dx, generator=gen, dtype=torch.float64)
    F = 0.95 * a / torch.linalg.matrix_norm(a, 2)
    H = torch.randn(dy, dx, generator=gen, dtype=torch.float64)
    B = torch.randn(dx, du, generator=gen, dtype=torch.float64)
    m0 = torch.randn(dx, generator=gen, dtype=torch.float64)
    return df.LinearGaussianModel(F, H, 0.1 * spd(dx), spd(dy), m0, spd(dx), B=B)


def test_the_gain_schedule_is_the_gaussian_core_recursion():
    """The written-out covariance recursion (fused products, K from the whitening) of the
    gain schedule and of the shared-covariance path gives the Gaussian core's moments
    (difffilter.gaussian's blocks, as kalman_step runs them) up to round-off, every step
    until the schedule's gain converged."""
    from difffilter._shared_cov import _covariances
    from difffilter.gaussian import joseph_covariance, kalman_gain, predict_covariance
    from difffilter.linalg import LOG_2PI, symmetrize

    model = _random_linear_model()
    schedule = df.GainSchedule(model)
    schedule.moments(200)
    n = len(schedule._moments)
    assert schedule.converged and n < 200
    F, H = model.transition_matrix(0), model.observation_matrix(1)
    Q, R, P = model.process_cov(0), model.measurement_cov(1), model.initial.cov
    shared = _covariances(F, H, Q, R, P, 300)
    eye = torch.eye(3, dtype=torch.float64)
    for k in range(1, 301):
        pred = predict_covariance(P, F, Q)
        cross = pred @ H.T
        S = symmetrize(H @ cross + R)
        K, chol = kalman_gain(cross, S)
        P = joseph_covariance(pred, K, H, R)
        whiten = torch.linalg.solve_triangular(chol, eye, upper=False)
        half_logdet = torch.log(torch.diagonal(chol)).sum()
        want = (pred, P, S, K, whiten)
        for got, ref in zip((shared[0], shared[1], shared[2], shared[3], shared[4]), want):
            torch.testing.assert_close(got[k - 1], ref, rtol=0, atol=1e-12)
        torch.testing.assert_close(shared[5][k - 1], half_logdet, rtol=0, atol=1e-12)
        if k <= n:
            m = schedule.moments(k)
            for got, ref in zip((m.pred_cov, m.cov, m.innovation_cov, m.gain, m.whiten), want):
                torch.testing.assert_close(got, ref, rtol=0, atol=1e-12)
            log_norm = half_logdet + 0.5 * 3 * LOG_2PI
            torch.testing.assert_close(m.log_norm, log_norm, rtol=0, atol=1e-12)
    assert schedule.moments(n + 50) is schedule.moments(n)  # the last moments, once converged


def _gain_schedule_case(case: str):
    """A linear model for the chunked-recursion test (every one's gain converges)."""
    f64 = torch.float64
    if case == "random":
        return _random_linear_model()
    if case == "float32":
        return _random_linear_model().to(torch.float32)
    if case == "constant_velocity":  # the benchmark's kind: F unstable, half the state seen
        return constant_velocity(q=0.003, r=4.0)
    if case == "unobservable_unstable":  # x₁ grows by 2 % a step and is never measured
        F = torch.tensor([[1.02, 0.0], [0.0, 0.9]], dtype=f64)
        H = torch.tensor([[0.0, 1.0]], dtype=f64)
        model = df.LinearGaussianModel(
            F, H, 0.01 * torch.eye(2, dtype=f64), torch.tensor([[0.04]], dtype=f64),
            torch.zeros(2, dtype=f64), torch.eye(2, dtype=f64),
        )  # fmt: skip
        return model  # the gain converges (K₁ = 0) but P₁₁ grows without bound: no step
        # may repeat the last covariance (the schedule once stopped at the gain's convergence)
    # H Q Hᵀ + R singular (a duck-typed model with noise-free measurements of a state whose
    # noise they do not see): no scan element, the step-by-step recursion
    F = torch.tensor([[1.0, 0.1], [0.0, 1.0]], dtype=f64)
    model = df.LinearGaussianModel(
        F, torch.tensor([[1.0, 0.0]], dtype=f64), torch.eye(2, dtype=f64),
        torch.eye(1, dtype=f64), torch.zeros(2, dtype=f64), torch.eye(2, dtype=f64),
    )  # fmt: skip
    Q = torch.diag(torch.tensor([0.0, 0.01], dtype=f64))
    model.process_cov = lambda k: Q
    model.measurement_cov = lambda k: torch.zeros(1, 1, dtype=f64)
    return model


@pytest.mark.parametrize(
    "case", ["random", "float32", "constant_velocity", "unobservable_unstable", "singular_element"]
)
def test_the_chunked_recursion_is_the_step_by_step_one(case):
    """GainSchedule computes the covariance recursion a chunk at a time (riccati_chunk: the
    scan element's j-step maps over blocks of 16 steps, the blocks' remaining steps
    batched; step by step where H Q Hᵀ + R is singular); every moment equals riccati_step
    run one step at a time (relative to each moment's size: 1e-12 in float64, 1e-5 in
    float32), over 300 steps or until the gain and the covariance converged, at the same
    step as the one-step convergence test within one step (max |K_k − K_{k−1}| ≤ tol_ρ max
    |K_{k−1}|, each |ΔP_ij| ≤ tol_ρ √(P_ii P_jj), tol_ρ = 1e-12 min(1, (1 − ρ²)/ρ²) with ρ
    the spectral radius of (I − K_k H) F); a covariance that keeps growing never converges."""
    from difffilter.gain_schedule import riccati_step

    model = _gain_schedule_case(case)
    schedule = df.GainSchedule(model)
    F, H = schedule.F, schedule.H
    dx, dy = H.shape[1], H.shape[0]
    eye_x, eye_y = torch.eye(dx, dtype=F.dtype), torch.eye(dy, dtype=F.dtype)
    cov, reference, converged_at = model.initial.cov, [], None
    for k in range(1, 301):
        step = riccati_step(cov, F, F.mT, H, H.mT, schedule.Q, schedule.R, eye_x, eye_y)
        cov = step[1]
        if reference and converged_at is None:
            P_prev, K_prev = reference[-1][1], reference[-1][2]
            closed = (eye_x - step[2] @ H) @ F
            rho2 = float(torch.linalg.eigvals(closed.double()).abs().max()) ** 2
            tol = 1e-12 * min(1.0, (1 - rho2) / rho2) if rho2 < 1 else -1.0
            var = P_prev.diagonal().clamp_min(0)
            if (
                (step[2] - K_prev).abs().max() <= tol * K_prev.abs().max()
                and bool(((step[1] - P_prev).abs() <= tol * (var[:, None] * var[None, :]).sqrt()).all())
            ):  # fmt: skip
                converged_at = k
        reference.append(step)
    schedule.moments(300)
    n = len(schedule._moments)
    if case == "unobservable_unstable":
        assert not schedule.converged and converged_at is None and n == 300
        converged_at = 300
    elif case == "float32":
        # (whether float32's one-step recursion ever meets the test above is the CPU's
        # round-off: it repeated exactly on one machine, kept changing its last bit on an
        # AVX-512 one; the schedule's stop is checked against the recursion below)
        assert schedule.converged
    else:
        assert schedule.converged and converged_at is not None
    if case != "float32":
        assert abs(n - converged_at) <= 1, (n, converged_at)
    assert (schedule._chunks._maps == ()) == (case == "singular_element")
    # float32 (the schedule stops at a change of 16 ε, the one-step recursion at an exact
    # repeat, some steps later): every step, the schedule's last moments after it stopped
    last, rtol = (300, 2e-5) if case == "float32" else (min(n, converged_at), 1e-12)
    for k in range(1, last + 1):
        m = schedule.moments(k)
        got = (m.pred_cov, m.cov, m.gain, m.innovation_cov, m.chol, m.whiten)
        for a, b in zip(got, reference[k - 1]):
            assert (a - b).abs().max() <= rtol * b.abs().max(), (k, a, b)


@pytest.mark.parametrize("batch", [(), (4,), (2, 3)])
@pytest.mark.parametrize("with_input", [False, True])
def test_the_fused_gain_step_is_predict_update_and_evidence(batch, with_input):
    """GainSchedule.filter_step (one run: matrix-vector products; rows: GEMMs) equals
    predict, update and log N(ν; 0, S) (1e-12)."""
    model = _random_linear_model()
    schedule = df.GainSchedule(model)
    gen = torch.Generator().manual_seed(1)
    mean = torch.randn(*batch, 5, generator=gen, dtype=torch.float64)
    y = torch.randn(*batch, 3, generator=gen, dtype=torch.float64)
    u = torch.randn(*batch, 2, generator=gen, dtype=torch.float64) if with_input else None
    for k in (1, 2, 7):
        new, pred, nu, log_lik, m = schedule.filter_step(mean, y, u, k)
        want_pred = schedule.predict(mean, u)
        want_new, want_nu, S = schedule.update(want_pred, y, k)
        want_ll = torch.distributions.MultivariateNormal(torch.zeros(3, dtype=S.dtype), S)
        for got, want in ((pred, want_pred), (new, want_new), (nu, want_nu),
                          (log_lik, want_ll.log_prob(want_nu))):  # fmt: skip
            assert got.shape == want.shape
            torch.testing.assert_close(got, want, rtol=0, atol=1e-12)
        assert m is schedule.moments(k)


def test_the_shared_recursion_stops_where_the_gain_converges_with_the_same_numbers(monkeypatch):
    """Without gradients the shared-covariance path computes the recursion in chunks until
    the gain changes by round-off alone (the constant-velocity model of the benchmark: 136
    of 300 steps, no step-by-step call) and repeats the last moments: every one within
    1e-12 of its size (2e-14 measured) of the gradient path, which computes all 300 steps
    one at a time."""
    from difffilter import _shared_cov, gain_schedule

    f64 = torch.float64
    block = torch.tensor([[1 / 3, 1 / 2], [1 / 2, 1.0]], dtype=f64)
    F = torch.block_diag(*[torch.tensor([[1.0, 1.0], [0.0, 1.0]], dtype=f64)] * 2)
    H = torch.tensor([[1.0, 0, 0, 0], [0, 0, 1, 0]], dtype=f64)
    Q, R = 0.055**2 * torch.block_diag(block, block), 4.0 * torch.eye(2, dtype=f64)
    P0 = torch.diag(torch.tensor([1.0, 1e-4, 1.0, 1e-4], dtype=f64))
    calls, riccati_step = [], gain_schedule.riccati_step

    def counted(cov, *args):
        if cov.dim() == 2:  # one unbatched step (a chunk passes a batch of covariances)
            calls.append(1)
        return riccati_step(cov, *args)

    monkeypatch.setattr(gain_schedule, "riccati_step", counted)
    with torch.no_grad():
        cut = _shared_cov._covariances(F, H, Q, R, P0, 300)
    assert not calls  # the chunks, not the step-by-step recursion
    every = _shared_cov._covariances(F, H, Q.clone().requires_grad_(True), R, P0, 300)
    assert len(calls) == 300  # every step with gradients
    for a, b in zip(cut, every):
        assert a.shape == b.shape
        assert (a - b.detach()).abs().max() <= 1e-12 * b.detach().abs().max()
    assert torch.equal(cut[3][-1], cut[3][150])  # the converged gain, repeated


def test_the_online_step_is_differentiable_in_the_models_matrices(generator):
    """``KalmanFilter().step`` on a model whose matrices require gradients: gradcheck of
    the summed evidence in F, Q and R (the shared gain schedule, computed outside autograd,
    is not used for such a model: it used to drop these gradients silently)."""
    base = constant_velocity()
    _, ys, _ = base.simulate(5, (), generator=generator)
    H, m0, P0 = base.H, base.initial.mean, base.initial.cov
    eye = torch.eye(4, dtype=torch.float64)

    def model_of(F, Lq, Lr):
        Q = Lq @ Lq.T + 1e-3 * eye
        return df.LinearGaussianModel(F, H, Q, Lr @ Lr.T + 1e-2 * eye[:2, :2], m0, P0)

    def online(F, Lq, Lr):
        kf = df.KalmanFilter()
        carry, total = kf.init(model_of(F, Lq, Lr)), 0.0
        for y in ys:
            carry, out = kf.step(carry, y)
            total = total + out.log_likelihood
        return total

    F = base.F.clone().requires_grad_()
    Lq = torch.linalg.cholesky(base.process_noise.cov + 1e-2 * eye).requires_grad_()
    Lr = torch.linalg.cholesky(base.measurement_noise.cov).requires_grad_()
    assert torch.autograd.gradcheck(online, (F, Lq, Lr), eps=1e-6, atol=1e-6)
    whole = df.kalman_filter(model_of(F, Lq, Lr), ys).log_likelihood
    got = torch.autograd.grad(online(F, Lq, Lr), (F, Lq, Lr))
    expected = torch.autograd.grad(whole, (F, Lq, Lr))
    for g, e in zip(got, expected):
        assert g.abs().sum() > 0
        torch.testing.assert_close(g, e, atol=1e-10, rtol=1e-10)
    with torch.no_grad():  # without gradients the schedule serves the model again
        assert (
            df.KalmanFilter().init(model_of(F.detach(), Lq.detach(), Lr.detach())).gains is not None
        )


@pytest.mark.parametrize("masked", [False, True])
def test_innovation_is_the_updates_own_without_its_posterior(masked):
    """KalmanFilter.innovation on per-run covariances (no shared gains) returns the very
    ν, S and log N(ν; 0, S) of the update (the same numbers, bit for bit), without its
    gain and posterior, and S equals H P⁻ Hᵀ + R (the masked entries' unit variance)."""
    model = _random_linear_model()
    gen = torch.Generator().manual_seed(3)
    kf = df.KalmanFilter()
    a = torch.randn(4, 5, 5, generator=gen, dtype=torch.float64)
    carry = kf.init(model, (4,))._replace(
        cov=a @ a.mT + torch.eye(5, dtype=torch.float64), gains=None
    )
    y = torch.randn(4, 3, generator=gen, dtype=torch.float64)
    u = torch.randn(4, 2, generator=gen, dtype=torch.float64)
    mask = torch.tensor([[True, False, True], [True] * 3, [False, True, True], [False] * 3])
    mask = mask if masked else None
    pred = kf.predict(carry, u)
    nu, S, ell = kf.innovation(carry, pred, y, mask)
    _, out = kf.update(carry, pred, y, mask)
    for got, want in ((nu, out.innovation), (S, out.innovation_cov), (ell, out.log_likelihood)):
        assert torch.equal(got, want)
    H, R = model.observation_matrix(1), model.measurement_cov(1)
    want_S = H @ pred.cov @ H.T + R
    want_nu = y - pred.mean @ H.T
    if masked:  # unreceived entries: zero residual, unit variance, uncorrelated
        keep = mask.double()
        want_S = keep[:, :, None] * want_S * keep[:, None, :] + torch.diag_embed(1.0 - keep)
        want_nu = want_nu * keep
    torch.testing.assert_close(S, want_S, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(nu, want_nu, rtol=1e-12, atol=1e-12)
    assert kf.innovation(carry, pred, y, mask, evidence=False)[2] is None


def _range_bearing_model():
    """A nonlinear model whose EKF Jacobian depends on the prediction (range and a
    smooth bearing-like entry), float64."""

    def f(x, u):
        return torch.stack([x[..., 0] + 0.1 * x[..., 1], 0.9 * x[..., 1] + u[..., 0]], -1)

    def h(x):
        return torch.stack([x.square().sum(-1).sqrt(), torch.tanh(x[..., 1] / (1 + x[..., 0]))], -1)

    eye = torch.eye(2, dtype=torch.float64)
    return df.NonlinearGaussianModel(f, h, Q=0.01 * eye, R=0.1 * eye, m0=torch.full((2,), 2.0,
                                     dtype=torch.float64), P0=eye, dim_u=1)  # fmt: skip


@pytest.mark.parametrize("masked", [False, True])
@pytest.mark.parametrize("filt", ["kf", "ekf"])
def test_moments_shared_and_no_evidence_change_no_bit_of_the_update(filt, masked):
    """The part of an update that does not read ``y`` (``moments``), computed once for a
    prediction, serves the innovation of one measurement and the update with another:
    the same numbers, bit for bit, as each computing its own (what the learned estimator
    does every step: the innovation of ``y``, the update with ``y − â``). ``evidence=False``
    leaves the density ``None`` and every other output unchanged, and the innovation is
    the update's own ``ν``, ``S`` and ``log N(ν; 0, S)`` (the EKF's too)."""
    gen = torch.Generator().manual_seed(5)
    if filt == "kf":
        model, est, dx, dy = _random_linear_model(), df.KalmanFilter(), 5, 3
    else:
        model, est, dx, dy = _range_bearing_model(), df.ExtendedKalmanFilter(), 2, 2
    a = torch.randn(4, dx, dx, generator=gen, dtype=torch.float64)
    carry = est.init(model, (4,))._replace(
        mean=torch.randn(4, dx, generator=gen, dtype=torch.float64) + 2.0,
        cov=a @ a.mT + torch.eye(dx, dtype=torch.float64), gains=None,
    )  # fmt: skip
    y = torch.randn(4, dy, generator=gen, dtype=torch.float64)
    shifted = y - torch.randn(4, dy, generator=gen, dtype=torch.float64)  # a compensated y
    u = torch.randn(4, model.dim_u, generator=gen, dtype=torch.float64)
    mask = torch.rand(4, dy, generator=gen) > 0.4 if masked else None
    if masked:
        mask[0] = True  # one run receives everything, one nothing
        mask[1] = False
    pred = est.predict(carry, u)
    moments = est.moments(carry, pred, mask)
    assert moments is not None
    nu, S, ell = est.innovation(carry, pred, y, mask, moments=moments)
    _, own = est.update(carry, pred, y, mask)
    for got, want in ((nu, own.innovation), (S, own.innovation_cov), (ell, own.log_likelihood)):
        assert torch.equal(got, want)
    for evidence in (True, False):
        shared = est.update(carry, pred, shifted, mask, evidence=evidence, moments=moments)
        alone = est.update(carry, pred, shifted, mask)
        for name in ("mean", "cov"):
            assert torch.equal(getattr(shared[0], name), getattr(alone[0], name)), name
        for name in ("mean", "cov", "pred_mean", "pred_cov", "innovation", "innovation_cov"):
            assert torch.equal(getattr(shared[1], name), getattr(alone[1], name)), name
        assert (shared[1].log_likelihood is None) is not evidence
        if evidence:
            assert torch.equal(shared[1].log_likelihood, alone[1].log_likelihood)
    assert est.innovation(carry, pred, y, mask, evidence=False, moments=moments)[2] is None


def test_the_shared_schedule_has_no_moments_to_share_and_skips_its_evidence_too():
    """With the shared gain schedule (unbatched model, no mask) the KF's ``moments`` is
    ``None`` (the schedule holds them); ``evidence=False`` still changes no bit."""
    model = _random_linear_model()
    kf = df.KalmanFilter()
    carry = kf.init(model, (3,))
    assert carry.gains is not None
    y = torch.randn(3, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    pred = kf.predict(carry, None)
    assert kf.moments(carry, pred, None) is None
    (with_state, with_out), (without_state, without_out) = (
        kf.update(carry, pred, y, None, evidence=e) for e in (True, False)
    )
    assert without_out.log_likelihood is None and with_out.log_likelihood is not None
    assert torch.equal(with_state.mean, without_state.mean)
    assert without_state.gains is carry.gains


@pytest.mark.parametrize("batched", ["Q", "R", "B"])
def test_a_model_with_a_per_run_noise_or_input_map_takes_the_general_update(batched, cv_model,
                                                                             generator):  # fmt: skip
    """Per-run Q, R or B (F, H shared) once took the shared gain schedule: a batched B gave
    outputs of the wrong shape and values, a batched Q or R an error."""
    from difffilter.gain_schedule import shared_gains_apply

    m = cv_model
    B0 = torch.eye(4, 2, dtype=m.F.dtype)
    Q, R, B = m.process_noise.cov, m.measurement_noise.cov, B0
    if batched == "Q":
        Q = torch.stack([Q, 2.0 * Q, 3.0 * Q])
    elif batched == "R":
        R = torch.stack([R, 2.0 * R, 3.0 * R])
    else:
        B = torch.stack([B0, 2.0 * B0, 3.0 * B0])
    model = df.LinearGaussianModel(m.F, m.H, Q, R, m.initial.mean, m.initial.cov, B=B)
    assert not shared_gains_apply(model)
    _, ys, _ = cv_model.simulate(6, (3,), generator=generator)
    us = torch.randn(3, 6, 2, generator=generator, dtype=ys.dtype)
    got = df.kalman_filter(model, ys, us)
    general = df.kalman_filter(model, ys, us, mask=torch.ones(3, 6, 2, dtype=torch.bool))
    assert got.means.shape == (3, 6, 4)
    torch.testing.assert_close(got.means, general.means)
    kf = df.KalmanFilter()
    carry = kf.init(model, (3,))
    carry, out = kf.step(carry, ys[:, 0], us[:, 0])
    torch.testing.assert_close(out.mean, general.means[:, 0])


def test_a_carry_whose_gains_no_longer_hold_is_refused_when_validated(cv_model, generator):
    """The shared step reads the schedule, not the carry: a carry with another model, or whose
    covariance was written in place, must not run on it silently."""
    _, ys, _ = cv_model.simulate(4, (), generator=generator)
    kf = df.KalmanFilter()
    carry, _ = kf.step(kf.init(cv_model), ys[0])
    other = constant_velocity()
    with pytest.raises(ValueError, match="gain schedule of another model"):
        kf.step(carry._replace(model=other), ys[1])
    assert kf.step(carry._replace(model=other, gains=None), ys[1])[1].mean.shape == (4,)
    with torch.no_grad():
        carry.cov.mul_(100.0)
    with pytest.raises(ValueError, match="carry.cov was written in place"):
        kf.step(carry, ys[1])


def test_the_shared_covariance_path_follows_a_variance_the_gain_does_not_see():
    """A state no measurement reaches (F_bb = 0.999, zero row of K): the gain settles in
    about a hundred steps, its variance only after thousands. The default (shared-
    covariance) path and the online step equal the general recursion at every step (they
    froze P_bb at 2.1 where it reaches 4.46 by step 1,000)."""
    f64 = torch.float64
    model = df.LinearGaussianModel(
        torch.diag(torch.tensor([1.0, 0.999], dtype=f64)), torch.tensor([[1.0, 0.0]], dtype=f64),
        0.01 * torch.eye(2, dtype=f64), torch.eye(1, dtype=f64), torch.zeros(2, dtype=f64),
        torch.eye(2, dtype=f64),
    )  # fmt: skip
    ys = torch.randn(2, 1000, 1, generator=torch.Generator().manual_seed(3), dtype=f64)
    general = df.kalman_filter(model, ys, mask=torch.ones_like(ys, dtype=torch.bool))
    shared = df.kalman_filter(model, ys)
    torch.testing.assert_close(shared.covs, general.covs, rtol=1e-10, atol=0)
    torch.testing.assert_close(shared.means, general.means, rtol=1e-10, atol=1e-12)
    assert float(general.covs[0, -1, 1, 1]) > 4.4
    kf = df.KalmanFilter()
    carry = kf.init(model, ())
    for t in range(1000):
        carry, out = kf.step(carry, ys[0, t])
    torch.testing.assert_close(out.cov, general.covs[0, -1], rtol=1e-10, atol=0)


def _two_state(dtype=torch.float64):
    F = torch.tensor([[1.0, 0.1], [0.0, 1.0]], dtype=dtype)
    H = torch.tensor([[1.0, 0.0]], dtype=dtype)
    return df.LinearGaussianModel(F, H, 0.01 * torch.eye(2, dtype=dtype), torch.eye(1, dtype=dtype),
                                  torch.zeros(2, dtype=dtype), torch.eye(2, dtype=dtype))  # fmt: skip


def _scheduled_and_plain(model, steps: int, seed: int):
    """``(ys, kf, fast, slow)``: ``steps`` simulated measurements of ``model`` and a Kalman
    filter's carry with its gain schedule (``fast``) and the same carry without it
    (``slow``, the general update), to step side by side."""
    _, ys, _ = model.simulate(steps, (), generator=torch.Generator().manual_seed(seed))
    kf = df.KalmanFilter()
    fast = kf.init(model, ())
    return ys, kf, fast, fast._replace(gains=None)


def test_the_online_step_reads_a_model_written_in_place_as_the_general_step_does():
    """R (then F) edited in place between steps: the step drops the gain schedule, whose
    moments were computed ahead from the old model, and goes on with the general update
    (its chunk had mixed the old prediction covariance with the new R)."""
    model = _two_state()
    ys, kf, fast, slow = _scheduled_and_plain(model, 20, 0)
    assert fast.gains is not None and fast.gains.current()
    for t in range(20):
        if t in (5, 12):
            with torch.no_grad():
                (model.measurement_noise.cov if t == 5 else model.F).mul_(1.5 if t == 12 else 100.0)
        fast, of = kf.step(fast, ys[t])
        slow, os_ = kf.step(slow, ys[t])
        torch.testing.assert_close(of.mean, os_.mean, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(of.innovation_cov, os_.innovation_cov, rtol=1e-12, atol=0)
    assert fast.gains is None


@pytest.mark.parametrize("change", ["F", "noise", "to"])
def test_the_online_step_reads_a_model_whose_tensors_were_assigned_anew(change):
    """From a deployment trial: after ``model.F = new_F`` or ``model.measurement_noise =
    Gaussian(…)`` (a tensor or noise replaced, not written in place) the Kalman filter's
    step went on with the old matrices (equal to a filter never told, 2.7e-13), while the
    EKF on the same model followed. The step now follows as the general update does; and a
    change elsewhere (another model built) keeps the schedule."""
    from difffilter.noise import Gaussian

    model = _two_state()
    ys, kf, fast, slow = _scheduled_and_plain(model, 20, 0)
    for t in range(20):
        if t == 4:
            _two_state()  # another model built: nothing of this one changed
        if t == 8:
            if change == "F":
                model.F = 1.5 * model.F
            elif change == "noise":
                model.measurement_noise = Gaussian(torch.zeros(1, dtype=torch.float64),
                                                   100 * model.measurement_noise.cov)  # fmt: skip
            else:  # the same values in another tensor: the schedule still holds
                model.to(torch.float64)
                model.F = model.F.clone()
        fast, of = kf.step(fast, ys[t])
        slow, os_ = kf.step(slow, ys[t])
        torch.testing.assert_close(of.mean, os_.mean, rtol=1e-12, atol=1e-12)
        if t < 8:
            assert fast.gains is not None
    assert (fast.gains is None) == (change != "to")


def test_a_schedule_that_never_converges_keeps_a_bounded_window(monkeypatch):
    """An unobserved random walk's variance grows forever: the gain schedule never converges,
    and it kept every step's moments (4.8 kB a step, 1 GB in 200,000 online steps). It keeps
    the last KEEP to KEEP + TRIM; the steps equal the general update's, also from a carry older
    than the window (which goes on without the schedule), and a dropped step is named."""
    monkeypatch.setattr(df.GainSchedule, "KEEP", 8)
    monkeypatch.setattr(df.GainSchedule, "TRIM", 8)
    eye = torch.eye(2, dtype=torch.float64)
    H = torch.tensor([[1.0, 0.0]], dtype=torch.float64)
    R = torch.ones(1, 1, dtype=torch.float64)
    model = df.LinearGaussianModel(eye, H, 1e-2 * eye, R, torch.zeros(2, dtype=torch.float64), eye)
    _, ys, _ = model.simulate(100, (), generator=torch.Generator().manual_seed(0))
    kf = df.KalmanFilter()
    fast = kf.init(model, ())
    slow, kept = fast._replace(gains=None), {}
    for t in range(100):
        fast, of = kf.step(fast, ys[t])
        slow, os_ = kf.step(slow, ys[t])
        torch.testing.assert_close(of.mean, os_.mean, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(of.cov, os_.cov, rtol=1e-12, atol=0)
        kept[t + 1] = (fast, slow)
    schedule = fast.gains
    assert schedule is not None and not schedule.converged
    assert 8 <= len(schedule._moments) <= 16 and schedule.held(100) and not schedule.held(3)
    with pytest.raises(ValueError, match="moments of measurement 3 were dropped"):
        schedule.moments(3)
    old_fast, old_slow = kept[3]  # its next step's moments were dropped
    stepped, out = kf.step(old_fast, ys[3])
    torch.testing.assert_close(out.mean, kf.step(old_slow, ys[3])[1].mean, rtol=1e-12, atol=0)
    assert stepped.gains is None


def test_a_prior_given_by_its_factor_keeps_the_shared_gains():
    """``Gaussian(m0, scale_tril=L)`` makes a new ``cov`` at every read: ``init`` refused
    its own carry (identity check against a fresh tensor)."""
    model = _two_state()
    model.initial = Gaussian(
        torch.zeros(2, dtype=torch.float64), scale_tril=2 * torch.eye(2, dtype=torch.float64)
    )
    _, ys, _ = model.simulate(6, (3,), generator=torch.Generator().manual_seed(1))
    kf = df.KalmanFilter()
    carry = kf.init(model, (3,))
    assert carry.gains is not None
    for t in range(6):
        carry, out = kf.step(carry, ys[:, t])
    torch.testing.assert_close(
        out.mean, df.kalman_filter(model, ys).means[:, -1], rtol=1e-12, atol=1e-12
    )


def test_a_carry_stepped_under_inference_mode_goes_on_with_gradients():
    model = _two_state()
    _, ys, _ = model.simulate(6, (), generator=torch.Generator().manual_seed(2))
    kf = df.KalmanFilter()
    for batch in ((), (2,)):
        carry = kf.init(model, batch)
        with torch.inference_mode():
            for t in range(3):
                carry, _ = kf.step(carry, ys[t].expand(batch + (1,)))
        y = ys[3].expand(batch + (1,)).clone().requires_grad_(True)
        carry, out = kf.step(carry, y)
        out.log_likelihood.sum().backward()  # inference tensors could not be saved for it
        m = carry.gains.moments(4)
        expected = -(
            torch.linalg.solve(m.innovation_cov, out.innovation.detach().unsqueeze(-1))
        ).squeeze(-1)
        torch.testing.assert_close(y.grad, expected, rtol=1e-12, atol=1e-12)


def test_open_loop_refuses_a_carry_of_another_model():
    from difffilter.loop import open_loop

    kf, a, b = df.KalmanFilter(), _two_state(), _two_state()
    with pytest.raises(ValueError, match="carry holds another model"):
        open_loop(kf, b, torch.zeros(1, 3, 1, dtype=torch.float64), carry=kf.init(a, (1,)))


class _Bent(df.StateSpaceModel):
    """A nonlinear 2-state model (the UKF's sigma points see its curvature)."""

    dim_x, dim_y = 2, 2

    def __init__(self):
        super().__init__()
        f64 = torch.float64
        self.process_noise = Gaussian(
            torch.zeros(2, dtype=f64), torch.diag(torch.tensor([0.05, 0.02], dtype=f64))
        )
        self.measurement_noise = Gaussian(
            torch.zeros(2, dtype=f64), torch.diag(torch.tensor([0.1, 0.2], dtype=f64))
        )
        self.initial = Gaussian(
            torch.tensor([0.7, -0.4], dtype=f64), torch.tensor([[0.5, 0.1], [0.1, 0.3]], dtype=f64)
        )

    def transition(self, x, u, k):
        return torch.stack(
            [torch.sin(x[..., 0]) + 0.5 * x[..., 1] ** 2, x[..., 0] * x[..., 1] + x[..., 1]], -1
        )

    def observe(self, x, k):
        return torch.stack([x[..., 0] ** 2, torch.exp(0.3 * x[..., 1])], -1)


@pytest.mark.parametrize("alpha, beta, kappa", [(1.0, 2.0, 0.0), (0.5, 2.0, 1.0)])
def test_ukf_step_on_a_nonlinear_model_equals_filterpys(alpha, beta, kappa):
    """One UKF step against filterpy's (Merwe's scaled sigma points, redrawn from (m⁻, P⁻)):
    the weights (λ = α²(n + κ) − n, w₀ᶜ = w₀ + 1 − α² + β) and the posterior P = P⁻ − K S Kᵀ.
    Linear models (every other UKF test) see neither: the centre weight and λ cancel there,
    and the Joseph form with R alone left P smaller by K Ω Kᵀ (Var 0.062 against 0.113)."""
    filterpy = pytest.importorskip("filterpy.kalman")
    model = _Bent()
    m0, P0 = model.initial.mean.numpy(), model.initial.cov.numpy()
    Q, R = model.process_cov(0).numpy(), model.measurement_cov(1).numpy()
    y = np.array([0.9, 1.1])
    state = df.GaussianState(model.initial.mean, model.initial.cov, 0, model)
    sp = df.SigmaPoints(alpha=alpha, beta=beta, kappa=kappa)
    _, out = df.UnscentedKalmanFilter(sp).step(state, torch.tensor(y))
    points = filterpy.MerweScaledSigmaPoints(2, alpha=alpha, beta=beta, kappa=kappa)

    def f(x, dt):
        return model.transition(torch.tensor(x), None, 0).numpy()

    def h(x):
        return model.observe(torch.tensor(x), 1).numpy()

    ref = filterpy.UnscentedKalmanFilter(dim_x=2, dim_z=2, dt=1.0, hx=h, fx=f, points=points)
    ref.x, ref.P, ref.Q, ref.R = m0.copy(), P0.copy(), Q, R
    ref.predict()
    pred_mean, pred_cov = ref.x.copy(), ref.P.copy()
    ref.sigmas_f = points.sigma_points(ref.x, ref.P)  # redrawn from (m⁻, P⁻), as ours
    ref.update(y)
    for ours, theirs in ((out.pred_mean, pred_mean), (out.pred_cov, pred_cov),
                         (out.innovation_cov, ref.S), (out.mean, ref.x), (out.cov, ref.P)):  # fmt: skip
        np.testing.assert_allclose(ours.numpy(), theirs, rtol=1e-10, atol=1e-12)


def test_kf_reads_a_time_varying_observation_matrix_at_the_measurements_step():
    """H_k varying with k (every other time-varying test model varies F and R): the residual
    reads H at k, as a plain numpy Kalman filter does, with and without a mask."""
    F, Q, R = np.array([[1.0, 0.1], [0.0, 0.95]]), np.diag([0.01, 0.02]), np.diag([0.05, 0.08])

    def H_of(k):
        return np.array([[1.0, 0.3 * k], [np.cos(k), 1.0]])

    class TV(df.LinearGaussianModel):
        time_varying = True

        def observation_matrix(self, k):
            return torch.tensor(H_of(k), dtype=self.F.dtype)

    model = TV(*(torch.tensor(a) for a in (F, H_of(0), Q, R, np.zeros(2), np.eye(2))))
    ys = torch.randn(6, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    for mask in (None, torch.ones(6, 2, dtype=torch.bool)):
        res = df.kalman_filter(model, ys, mask=mask)
        m, P, ll = np.zeros(2), np.eye(2), 0.0
        for k in range(1, 7):
            m, P = F @ m, F @ P @ F.T + Q
            H = H_of(k)
            S = H @ P @ H.T + R
            K = P @ H.T @ np.linalg.inv(S)
            r = ys[k - 1].numpy() - H @ m
            ll += -0.5 * (r @ np.linalg.solve(S, r) + np.log(np.linalg.det(2 * np.pi * S)))
            m, P = m + K @ r, P - K @ S @ K.T
            np.testing.assert_allclose(res.means[k - 1].numpy(), m, rtol=1e-9, atol=1e-12)
            np.testing.assert_allclose(res.covs[k - 1].numpy(), P, rtol=1e-9, atol=1e-12)
        assert abs(float(res.log_likelihood) - ll) < 1e-9


def test_the_shared_gain_update_gives_the_gaussian_evidence():
    """predict + update on the shared gains (the halves the attack-aware wrappers call):
    log N(y; H m⁻, S) as scipy computes it, and innovation()'s the same."""
    from scipy.stats import multivariate_normal

    F, H = np.array([[1.0, 0.1], [0.0, 0.95]]), np.array([[1.0, 0.0], [0.5, 1.0]])
    Q, R, m0 = np.diag([0.01, 0.02]), np.diag([0.05, 0.08]), np.array([0.2, -0.1])
    model = df.LinearGaussianModel(*(torch.tensor(a) for a in (F, H, Q, R, m0, np.eye(2))))
    kf = df.KalmanFilter()
    carry = kf.init(model, (3,))
    assert carry.gains is not None
    ys = torch.randn(3, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    pred = kf.predict(carry, None)
    _, out = kf.update(carry, pred, ys, None)
    pm, pP = F @ m0, F @ np.eye(2) @ F.T + Q
    ref = np.array([multivariate_normal(H @ pm, H @ pP @ H.T + R).logpdf(y) for y in ys.numpy()])
    np.testing.assert_allclose(out.log_likelihood.numpy(), ref, rtol=0, atol=1e-10)
    np.testing.assert_allclose(
        kf.innovation(carry, pred, ys, None)[2].numpy(), ref, rtol=0, atol=1e-10
    )


def test_a_time_varying_model_without_the_flag_is_named():
    """A user trial overrode transition_matrix(k) and forgot ``time_varying = True``: the
    filters read the first step's F at every step (0.88 nats off at T = 60), silently."""
    base = constant_velocity()

    class Rotating(df.LinearGaussianModel):
        def transition_matrix(self, k):
            return self.F * (1.0 + 0.01 * k)

    class Constant(df.LinearGaussianModel):  # overridden, but the same at every k
        def transition_matrix(self, k):
            return self.F

    args = (base.F, base.H, base.process_noise.cov, base.measurement_noise.cov,
            base.initial.mean, base.initial.cov)  # fmt: skip
    ys = torch.zeros(2, 5, base.dim_y, dtype=base.F.dtype)
    with pytest.raises(ValueError, match=r"Rotating.transition_matrix\(k\) differs .* set "
                                         r"time_varying = True"):  # fmt: skip
        df.kalman_filter(Rotating(*args), ys)
    torch.testing.assert_close(df.kalman_filter(Constant(*args), ys).means,
                               df.kalman_filter(base, ys).means)  # fmt: skip
    Rotating.time_varying = True
    df.kalman_filter(Rotating(*args), ys)  # declared: filtered with F_k

    class Halved(df.LinearGaussianModel):  # a closed-loop trial's: F halves from step 5 on
        def transition_matrix(self, k):
            return self.F * (0.5 if k >= 5 else 1.0)

    with pytest.raises(ValueError, match=r"Halved.transition_matrix\(k\) differs between k = 1 "
                                         r"and k = 10"):  # fmt: skip
        df.kalman_filter(Halved(*args), ys)
    with pytest.raises(ValueError, match=r"Halved.transition_matrix\(k\) differs"):
        df.KalmanFilter().init(Halved(*args), (2,))

    class FirstStep(df.LinearGaussianModel):  # the transition into step 1 reads k = 0
        def transition_matrix(self, k):
            return self.F * (2.0 if k == 0 else 1.0)

    with pytest.raises(ValueError, match=r"FirstStep.transition_matrix\(k\) differs between k = 1 "
                                         r"and k = 0"):  # fmt: skip
        df.kalman_filter(FirstStep(*args), ys)

    class Blind(df.LinearGaussianModel):  # no measurement at k = 0, which nothing reads
        def observation_matrix(self, k):
            return self.H * (0.0 if k == 0 else 1.0)

    torch.testing.assert_close(df.kalman_filter(Blind(*args), ys).means,
                               df.kalman_filter(base, ys).means)  # fmt: skip

    class Tabulated(df.LinearGaussianModel):  # defined on steps 0 … 5 only (T = 5), all equal
        def transition_matrix(self, k):
            if k > 5:
                raise IndexError(f"no step {k}")
            return self.F

    torch.testing.assert_close(df.kalman_filter(Tabulated(*args), ys).means,
                               df.kalman_filter(base, ys).means)  # fmt: skip


def test_an_innovation_covariance_that_fails_names_the_models_covariances():
    """A user trial's optimiser walked Q indefinite: the error named S alone and said to
    check "the covariance you passed", which was Q."""
    model = constant_velocity()
    with torch.no_grad():
        model.process_noise._cov.copy_(-10.0 * torch.eye(model.dim_x, dtype=model.F.dtype))
    ys = torch.zeros(1, 3, model.dim_y, dtype=model.F.dtype)
    with pytest.raises(ValueError, match=r"innovation covariance S = H P⁻ Hᵀ \+ R \(made from "
                                         r"the model's Q, R and P0"):  # fmt: skip
        df.kalman_filter(model, ys)


@pytest.mark.parametrize("units", [1.0, 0.01])
def test_the_shared_path_is_the_general_one_for_a_slow_small_state_in_any_units(units):
    """A numerics trial: a slow state of small variance beside large ones (position ~1e4,
    a drift ~1e-3) counted as settled while it moved, since the covariance's change was
    compared with its largest entry: 3e-4 off in float64, 58 % with that state in units
    100× smaller, 70 % in float32. Every entry against its own scale and the recursion's
    contraction: the shared path equals the general one in any units."""
    D = torch.diag(torch.tensor([1.0, 1.0, units], dtype=torch.float64))
    Di = torch.linalg.inv(D)
    F = torch.tensor([[1, 1.0, 0], [0, 0.99, 0], [0, 0, 0.999]], dtype=torch.float64)
    H = torch.tensor([[1.0, 0, 1e-4], [0, 1e-3, 0]], dtype=torch.float64)
    Q = torch.diag(torch.tensor([1e2, 1e-2, 1e-8], dtype=torch.float64))
    R = torch.diag(torch.tensor([1e4, 1e-6], dtype=torch.float64))
    P0 = torch.diag(torch.tensor([1e8, 1.0, 1e-6], dtype=torch.float64))
    model = df.LinearGaussianModel(
        D @ F @ Di, H @ Di, D @ Q @ D, R, torch.zeros(3, dtype=torch.float64), D @ P0 @ D
    )
    ys = model.simulate(1500, batch_shape=(1,), generator=torch.Generator().manual_seed(3))[1]
    for dtype, rtol in ((torch.float64, 1e-10), (torch.float32, 2e-3)):
        m, y = model.to(dtype), ys.to(dtype)
        shared = df.kalman_filter(m, y).covs[0].double()
        general = df.kalman_filter(m, y, mask=torch.ones_like(y, dtype=torch.bool)).covs[0].double()
        var = general.diagonal(dim1=-2, dim2=-1)
        scale = (var.unsqueeze(-1) * var.unsqueeze(-2)).sqrt()  # each entry's own scale
        assert float(((shared - general).abs() / scale).max()) < rtol, dtype
        model = model.to(torch.float64)


def _non_normal_model() -> df.LinearGaussianModel:
    """A stable 3-state model (spectral radius 0.61) with a strongly non-normal ``F``
    (‖F‖ = 339) and ``R`` = 1.3e-7, from an audit of the parallel filter: its scan's means
    were 4e4 posterior sd from the sequential filter's, which agreed with a 40-digit one."""
    t = lambda rows: torch.tensor(rows, dtype=torch.float64)  # noqa: E731
    F = t([[115.49660641552107, -80.10676229981439, -273.3237482262779],
           [-33.12536371826567, -7.438854638538687, 63.45428466895664],
           [107.38576885223549, 224.43412233216588, -107.32408656858522]])  # fmt: skip
    H = t([[4.0900970415879145, -7.541696923107736, -0.3975266165806837]])
    Q = t([[0.2956041304240801, 0.2610824527856727, -0.3724803929329614],
           [0.2610824527856727, 0.23062622808073402, -0.3290858511138251],
           [-0.3724803929329614, -0.3290858511138251, 0.46967628513469556]])  # fmt: skip
    P0 = t([[57.45204790188038, -42.385727435002764, -66.08762471078795],
            [-42.385727435002764, 42.974490014795975, 43.46831162651479],
            [-66.08762471078795, 43.46831162651479, 78.45168392565675]])  # fmt: skip
    m0 = t([-1.1722986527217387, 0.9823427190095897, 0.561812289936042])
    return df.LinearGaussianModel(F, H, Q, t([[1.3411677652561856e-07]]), m0, P0)


def test_parallel_refuses_a_model_where_its_scan_loses_the_filter(generator):
    model = _non_normal_model()
    _, ys, _ = model.simulate(120, (2,), generator=generator)
    seq = df.kalman_filter(model, ys)
    F, H, Q, R, m0, P0 = _np(model)
    ref = numpy_kalman_filter(F, H, Q, R, m0, P0, ys[0].numpy())
    sd = seq.covs[0].diagonal(dim1=-2, dim2=-1).sqrt().numpy()
    assert (np.abs(seq.means[0].numpy() - ref[0]) / sd).max() < 1e-3  # sequential holds
    with pytest.raises(
        ValueError,
        match=r"method='parallel' lost accuracy.*method='sequential'.*float64, or a smaller P0",
    ):
        df.kalman_filter(model, ys, method="parallel")


def test_parallel_says_to_use_sequential_where_its_covariances_fail():
    """A model whose scan's covariances give an innovation covariance that is not positive
    definite, while the sequential filter runs (random ill-conditioned models: 12 in 287)."""
    t = lambda rows: torch.tensor(rows, dtype=torch.float64)  # noqa: E731
    F = t([[-1570.9234888554274, 6300.012750628963, 5045.759257703835],
           [7.706796308948433, 3781.8749425795595, -2435.661669257922],
           [-86.88285447916427, 4285.812235381665, -2210.627441647205]])  # fmt: skip
    H = t([[-0.07849189524008714, 0.3347831636543589, 0.00727629036537213]])
    Q = t([[9.955809853550992, 3.806700621427957, 7.511767426002586],
           [3.806700621427957, 1.6679968509991137, 2.9427748809701786],
           [7.511767426002586, 2.9427748809701786, 5.691155176338932]])  # fmt: skip
    P0 = t([[48093.44818640651, -140597.47289932062, 40195.95506979226],
            [-140597.47289932062, 411025.8789867269, -117509.75747816157],
            [40195.95506979226, -117509.75747816157, 33595.321391865145]])  # fmt: skip
    m0 = t([-0.2697543945973462, 1.1407801616733964, 0.4520117311517948])
    model = df.LinearGaussianModel(F, H, Q, t([[0.00064515072880271]]), m0, P0)
    _, ys, _ = model.simulate(120, (2,), generator=torch.Generator().manual_seed(0))
    assert torch.isfinite(df.kalman_filter(model, ys).log_likelihood).all()
    with pytest.raises(ValueError, match=r"innovation covariance.*try method='sequential'"):
        df.kalman_filter(model, ys, method="parallel")


def test_parallel_names_a_singular_combination(monkeypatch, generator):
    model = constant_velocity()
    _, ys, _ = model.simulate(6, (), generator=generator)

    def singular(*args, **kwargs):
        raise torch.linalg.LinAlgError("linalg.inv: The diagonal element 2 is zero")

    monkeypatch.setattr(torch.linalg, "inv", singular)
    with pytest.raises(
        ValueError, match=r"method='parallel' failed.*method='sequential'.*float64, or a smaller P0"
    ):
        df.kalman_filter(model, ys, method="parallel")


def test_parallel_consistency_check_holds_on_float32(generator):
    """The check's float32 tolerance leaves round-off through: float32 against float64."""
    model = constant_velocity()
    _, ys, _ = model.simulate(400, (3,), generator=generator)
    exact = df.kalman_filter(model, ys)
    fields = (model.F, model.H, model.process_noise.cov, model.measurement_noise.cov,
              model.initial.mean, model.initial.cov)  # fmt: skip
    single = df.LinearGaussianModel(*(f.float() for f in fields))
    res = df.kalman_filter(single, ys.float(), method="parallel")
    sd = exact.covs.diagonal(dim1=-2, dim2=-1).sqrt()
    assert ((res.means.double() - exact.means).abs() / sd).max() < 1e-2


def _non_normal_model_4x4() -> df.LinearGaussianModel:
    """A stable 4-state model with a strongly non-normal ``F`` (entries to 4.5e3) and an
    almost singular ``R``, from a random search: the whole-sequence shared-covariance
    path's means were 1e4 posterior sd from a 40-digit filter, the step-by-step filter's
    0.015."""
    t = lambda rows: torch.tensor(rows, dtype=torch.float64)  # noqa: E731
    F = t([[-4538.406098138516, -4312.320937945678, -4367.839150868573, 2133.5955347464155],
           [3941.645376645797, 3835.9459955916486, 3764.9698664634557, -1709.2901596255651],
           [3004.5433160295293, 3040.762813487212, 3033.73171573708, -1743.400438077506],
           [3167.547734470196, 4051.577884399208, 3520.680086005546, -2332.408210353128]])  # fmt: skip
    H = t([[-0.07842859429166536, 0.10243836276504573, 0.07124987591497303, 0.08393611625505146],
           [44.07631558812914, -18.541539189502156, -47.432351715544584, 6.912564283383646],
           [0.08390436304257987, -0.0468171598112165, -0.0973328377329518, 0.017910457339651693],
           [0.318803145829228, 0.9670465627986514, -0.1004295896385563, -0.5973454262805306]])  # fmt: skip
    Q = t([[1.3517434168823101, -0.1461675131769296, 0.16978126769520166, -2.6683818195738116],
           [-0.1461675131769296, 0.6790147961007019, 2.0035617870998648, 1.3572093103020075],
           [0.16978126769520166, 2.0035617870998648, 6.1861640469940875, 2.9230855858356843],
           [-2.6683818195738116, 1.3572093103020075, 2.9230855858356843, 6.989584103293906]])  # fmt: skip
    R = t([[0.32034980933656765, 0.40507201702037876, -0.36058450648894813, 0.2518932787817101],
           [0.40507201702037876, 0.5133725818689534, -0.45775569932991167, 0.31932722799087565],
           [-0.36058450648894813, -0.45775569932991167, 0.4087100731690809, -0.284812197420443],
           [0.2518932787817101, 0.31932722799087565, -0.284812197420443, 0.19864503804297742]])  # fmt: skip
    m0 = t([0.7438303988167724, -1.3259014368899744, 0.03843237972438399, -0.6422458371843208])  # fmt: skip
    P0 = t([[641.3546029272898, -415.3561835214181, -965.1503236588337, -1028.8268167687556],
           [-415.3561835214181, 269.47611510730053, 625.9071258491401, 666.9569423664533],
           [-965.1503236588337, 625.9071258491401, 1454.0473739795634, 1549.4382618513528],
           [-1028.8268167687556, 666.9569423664533, 1549.4382618513528, 1651.3107829612968]])  # fmt: skip
    return df.LinearGaussianModel(F, H, Q, R, m0, P0)


def test_the_default_filter_steps_where_the_shared_blocks_lose_the_means(generator):
    """The shared-covariance path sums coefficients formed ahead (``F − K H F``…), whose
    cancellation a strongly non-normal F makes large: where its means are not one Kalman
    update of their predecessors it gives way to the step-by-step filter."""
    from difffilter._shared_cov import shared_covariance_kalman_filter

    model = _non_normal_model_4x4()
    _, ys, _ = model.simulate(120, (3,), generator=generator)
    assert shared_covariance_kalman_filter(model, ys) is None  # refused: too far off
    default = df.kalman_filter(model, ys)
    general = df.kalman_filter(model, ys, mask=torch.ones(ys.shape, dtype=torch.bool))
    sd = general.covs.diagonal(dim1=-2, dim2=-1).sqrt()
    assert ((default.means - general.means).abs() / sd).max() < 1.0
    cv = constant_velocity()  # a well-conditioned model keeps the fast path
    _, ys_cv, _ = cv.simulate(50, (40,), generator=generator)
    assert shared_covariance_kalman_filter(cv, ys_cv) is not None


# ------------------------------------- one schedule for every run (a shared mask's path)


def _shared_schedule_case(batch, T, generator, *, with_input=False, lost_as_nan=False):
    model = constant_velocity(with_input=with_input)
    us = torch.randn(*batch, T, 1, dtype=torch.float64, generator=generator) if with_input else None
    _, ys, _ = model.simulate(T, batch, us=us, generator=generator)
    schedule = torch.rand(T, 2, generator=generator) > 0.35
    schedule[min(2, T - 1)] = False  # a packet lost whole
    mask = schedule.expand(*batch, T, 2)
    if lost_as_nan:
        ys = torch.where(mask, ys, torch.nan)
    return model, ys, us, mask


@pytest.mark.parametrize("materialised", [False, True])  # an expanded view, or B equal copies
@pytest.mark.parametrize("with_input", [False, True])
@pytest.mark.parametrize("batch, T", [((), 9), ((3,), 7), ((2, 3), 13)])
def test_a_schedule_every_run_shares_gives_the_per_run_filters_numbers(
    batch, T, with_input, materialised, generator
):
    """A mask equal in every run (round-robin scheduling, one lossy link for all runs):
    the covariance recursion reads the mask and never the data, so it is one recursion
    for all runs; the filter's every output equals the per-run filter's (a carry without
    the fast paths, stepped with the ``[B, dy]`` mask), and the covariances are shared
    views of one ``[T, dx, dx]`` tensor, as the unmasked shared path returns them."""
    model, ys, us, mask = _shared_schedule_case(batch, T, generator, with_input=with_input,
                                                lost_as_nan=True)  # fmt: skip
    if materialised:
        mask = mask.clone()
    fast, ref = df.kalman_filter(model, ys, us, mask=mask), _general(model, ys, us, mask=mask)
    for name in FIELDS:
        a, b = getattr(fast, name), getattr(ref, name)
        assert a.shape == b.shape, name
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12, msg=name)
    if batch:
        assert fast.covs.stride(0) == 0 and fast.innovation_covs.stride(0) == 0
        assert ref.covs.stride(0) != 0  # (the reference computed one recursion per run)


def test_a_mask_that_differs_in_one_run_keeps_one_recursion_per_run(generator):
    model, ys, _, mask = _shared_schedule_case((4,), 10, generator)
    mask = mask.clone()
    mask[2, 5, 0] = not mask[2, 5, 0]
    fast, ref = df.kalman_filter(model, ys, mask=mask), _general(model, ys, mask=mask)
    assert fast.covs.stride(0) != 0
    torch.testing.assert_close(fast.covs[2], ref.covs[2], rtol=1e-12, atol=1e-12)
    assert not torch.allclose(fast.covs[2, 5], fast.covs[0, 5])  # its own covariance
    torch.testing.assert_close(fast.log_likelihood, ref.log_likelihood, rtol=1e-12, atol=1e-12)


def test_a_shared_schedules_gradients_are_the_per_run_filters(generator):
    base, ys, _, mask = _shared_schedule_case((3,), 11, generator)

    def grads(run):
        F = base.F.clone().requires_grad_()
        R = base.measurement_noise.cov.clone().requires_grad_()
        y = ys.clone().requires_grad_()
        model = df.LinearGaussianModel(F, base.H, base.process_noise.cov, R, base.initial.mean,
                                       base.initial.cov)  # fmt: skip
        res = run(model, y, mask=mask)
        (res.log_likelihood.sum() + res.means.square().sum()).backward()
        return F.grad, R.grad, y.grad

    for a, b in zip(grads(df.kalman_filter), grads(_general)):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


def test_a_shared_schedule_on_a_time_varying_model_gives_the_per_run_filters_numbers(generator):
    base, _, _, mask = _shared_schedule_case((2, 3), 17, generator)
    model = RotatingModel(base.F, base.H, base.process_noise.cov, base.measurement_noise.cov,
                     base.initial.mean, base.initial.cov)  # fmt: skip
    _, ys, _ = model.simulate(17, (2, 3), generator=generator)
    fast, ref = df.kalman_filter(model, ys, mask=mask), _general(model, ys, mask=mask)
    for name in FIELDS:
        torch.testing.assert_close(getattr(fast, name), getattr(ref, name), rtol=1e-12,
                                   atol=1e-12, msg=name)  # fmt: skip
    assert fast.covs.stride(0) == 0


def test_the_ukf_posterior_stays_positive_semidefinite_beside_a_tiny_r():
    """From a numerics trial: a diffuse, badly scaled prior and a precise measurement of a
    combination of the states (R = 1e-10); the UKF's Joseph-form noise R + Ω with Ω a
    difference (Pyy − H̃ Pxy) came out negative in round-off and its posterior indefinite
    (normalised eigenvalue −7.4e-9 for +5e-11), where the EKF's was exact. Ω is now the
    weighted sum of the points' linearisation residuals: the posterior equals the exact one
    (rational arithmetic) as the EKF's does."""
    from fractions import Fraction

    P0, Q = np.diag([1e-8, 1e8]), np.diag([1e-20, 1e-8])
    H, R = np.array([[1e4, 1.0]]), np.array([[1e-10]])

    def lin(M):
        M = torch.tensor(M)
        return lambda x: x @ M.mT

    model = df.NonlinearGaussianModel(lin(np.eye(2)), lin(H), torch.tensor(Q), torch.tensor(R),
                                      torch.zeros(2, dtype=torch.float64), torch.tensor(P0))  # fmt: skip
    ys = torch.tensor([[[3.0]]], dtype=torch.float64)
    # the exact posterior: P⁻ = P0 + Q, P = P⁻ − P⁻Hᵀ (H P⁻ Hᵀ + R)⁻¹ H P⁻, in rationals
    fr = np.vectorize(Fraction)
    Pm, Hf = fr(P0) + fr(Q), fr(H)
    S = (Hf @ Pm @ Hf.T)[0, 0] + Fraction(R[0, 0])
    C = Pm @ Hf.T
    exact = (Pm - (C @ C.T) / S).astype(float)
    sd = np.sqrt(np.diag(exact))
    want = np.linalg.eigvalsh(exact / np.outer(sd, sd))
    for run in (df.unscented_kalman_filter, df.extended_kalman_filter):
        P = run(model, ys).covs[0, 0].numpy()
        np.testing.assert_allclose(P, exact, rtol=1e-6)
        got = np.linalg.eigvalsh(P / np.outer(sd, sd))
        np.testing.assert_allclose(got, want, rtol=1e-4)  # the smallest 5e-11, not negative
    ukf = df.unscented_kalman_filter(model, ys.expand(1, 3, 1))
    ekf = df.extended_kalman_filter(model, ys.expand(1, 3, 1))
    # (0 to 1.5e-8 apart with MKL's kernels of one CPU or another: P0 spans 16 decades)
    torch.testing.assert_close(ukf.log_likelihood, ekf.log_likelihood, rtol=1e-8, atol=1e-8)


def test_a_schedule_kept_after_an_assignment_watches_the_new_tensors_and_gradients():
    """From a review: after ``model.F = model.F.clone()`` (equal values: the schedule kept)
    an in-place write into the new F went unseen (the schedule watched the old tensor; the
    mean 7.69 off the general update), and F replaced by a Parameter of the same values kept
    the schedule, computed outside autograd (no gradient in F)."""
    model = _two_state()
    ys, kf, fast, slow = _scheduled_and_plain(model, 12, 1)
    for t in range(12):
        if t == 3:
            model.F = model.F.clone()
        if t == 6:
            with torch.no_grad():
                model.F.mul_(1.5)
        fast, of = kf.step(fast, ys[t])
        slow, os_ = kf.step(slow, ys[t])
        torch.testing.assert_close(of.mean, os_.mean, rtol=1e-12, atol=1e-12)
        assert (fast.gains is not None) == (t < 6)
    trained = _two_state()
    carry = kf.init(trained, ())
    trained.F = torch.nn.Parameter(trained.F.clone())
    for t in range(4):
        carry, out = kf.step(carry, ys[t])
    (grad,) = torch.autograd.grad(out.mean.sum(), trained.F)
    assert carry.gains is None and bool(grad.abs().sum() > 0)


def test_a_schedule_sees_a_write_before_an_assignment_and_into_the_tensor_it_computes_with():
    """From a second review: an in-place write into F followed by any assignment (another
    model built and assigned to) had the re-read compare F with itself and forget the write
    (the mean 6.27 off after six steps); after ``model.F = model.F.clone()`` the schedule
    watched the clone alone, while it multiplies by the old F, which another model sharing
    it could change (2.86 off)."""
    from difffilter.noise import Gaussian

    for case in ("write then assign", "old F shared"):
        model = _two_state()
        other = df.LinearGaussianModel(model.F, model.H, model.process_noise.cov,
                                       model.measurement_noise.cov, model.initial.mean,
                                       model.initial.cov)  # fmt: skip
        ys, kf, fast, slow = _scheduled_and_plain(model, 10, 2)
        for t in range(10):
            if t == 3:
                if case == "write then assign":
                    with torch.no_grad():
                        model.F.mul_(1.2)
                    spare = _two_state()
                    spare.measurement_noise = Gaussian(torch.zeros(1, dtype=torch.float64),
                                                       spare.measurement_noise.cov)  # fmt: skip
                else:
                    model.F = model.F.clone()  # equal values: the schedule is kept
            if t == 5 and case == "old F shared":
                with torch.no_grad():
                    other.F.mul_(1.2)  # the old F alone: the schedule multiplies by it
            fast, of = kf.step(fast, ys[t])
            slow, os_ = kf.step(slow, ys[t])
            torch.testing.assert_close(of.mean, os_.mean, rtol=1e-12, atol=1e-12, msg=case)
        assert fast.gains is None, case


def test_the_schedule_watches_a_bounded_set_and_sees_a_deleted_then_restored_matrix():
    """From a third review: every re-read added the model's tensors to those the schedule
    watches (4,000 after 4,000 steps of a covariance rebuilt at each read while another model
    was assigned to: 2.8 ms a step); and ``del model.F; model.F = F2`` (the second a first
    assignment, not counted) left the filter on the old F, 1.29 off."""
    model = _two_state()
    _, ys, _ = model.simulate(30, (), generator=torch.Generator().manual_seed(3))
    kf = df.KalmanFilter()
    fast = kf.init(model, ())
    for t in range(30):
        model.F = model.F.clone()  # equal values: kept, and re-read, at every step
        fast, _ = kf.step(fast, ys[t])
    assert fast.gains is not None and len(fast.gains._sources) <= 2 * len(fast.gains._own_sources)
    moved = _two_state()
    fast = kf.init(moved, ())
    slow = fast._replace(gains=None)
    for t in range(10):
        if t == 4:
            new_F = 1.3 * moved.F
            del moved.F
            moved.F = new_F
        fast, of = kf.step(fast, ys[t])
        slow, os_ = kf.step(slow, ys[t])
        torch.testing.assert_close(of.mean, os_.mean, rtol=1e-12, atol=1e-12)
    assert fast.gains is None
