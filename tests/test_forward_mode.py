"""Forward-mode differentiation (``torch.func.jvp``, ``torch.autograd.forward_ad``) through
the whole-sequence Kalman filter's default path. Its shared-covariance branch is chosen
for tensors that require no gradient, which dual tensors report; it wrote them into
preallocated outputs and forward mode raised ("mm_out ... is an out= function")."""

from __future__ import annotations

import pytest
import torch
import torch.autograd.forward_ad as fwAD

import difffilter as df

F64 = torch.float64


def _log_likelihood(theta, ys, method="sequential", mask=None):
    """Total log-likelihood of a 2-state model whose ``F[0, 1]``, ``q`` and ``r`` are
    ``theta``: a time-invariant model of shared matrices, the default path's case."""
    F = torch.eye(2, dtype=F64) + theta[0] * torch.tensor([[0.0, 1.0], [0.0, 0.0]], dtype=F64)
    Q = theta[1] * torch.eye(2, dtype=F64)
    R = theta[2] * torch.eye(1, dtype=F64)
    H = torch.tensor([[1.0, 0.0]], dtype=F64)
    model = df.LinearGaussianModel(F, H, Q, R, torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64))
    return df.kalman_filter(model, ys, method=method, mask=mask).log_likelihood.sum()


@pytest.fixture
def data():
    g = torch.Generator().manual_seed(0)
    return torch.randn(6, 40, 1, generator=g, dtype=F64).cumsum(-2) * 0.3


THETA = torch.tensor([0.1, 0.05, 0.2], dtype=F64)
DIRECTION = torch.tensor([1.0, -0.5, 2.0], dtype=F64)


@pytest.mark.parametrize("batch", ["runs", "one run"])
def test_jvp_equals_the_reverse_mode_directional_derivative(data, batch):
    ys = data if batch == "runs" else data[0]
    theta = THETA.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(_log_likelihood(theta, ys), theta)
    value, tangent = torch.func.jvp(lambda t: _log_likelihood(t, ys), (THETA,), (DIRECTION,))
    torch.testing.assert_close(value, _log_likelihood(THETA, ys))
    torch.testing.assert_close(tangent, grad @ DIRECTION, rtol=1e-10, atol=1e-10)


def test_forward_ad_duals_equal_reverse_mode(data):
    theta = THETA.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(_log_likelihood(theta, data), theta)
    with fwAD.dual_level():
        out = _log_likelihood(fwAD.make_dual(THETA, DIRECTION), data)
        tangent = fwAD.unpack_dual(out).tangent
    torch.testing.assert_close(tangent, grad @ DIRECTION, rtol=1e-10, atol=1e-10)


def test_jacfwd_of_the_measurements_equals_jacrev(data):
    ys = data[:2, :10]
    f = lambda y: _log_likelihood(THETA, y)  # noqa: E731
    torch.testing.assert_close(torch.func.jacfwd(f)(ys), torch.func.jacrev(f)(ys),
                               rtol=1e-10, atol=1e-10)  # fmt: skip


def test_an_untraced_call_keeps_the_shared_path():
    """The step-through fallback is for traced calls only: a plain call still takes the
    shared-covariance path (it is what makes 100,000 runs fast)."""
    from difffilter.linalg import under_transform

    assert not under_transform(THETA, None)
    with fwAD.dual_level():
        assert not under_transform(THETA)
        assert under_transform(fwAD.make_dual(THETA, DIRECTION))


def test_second_derivatives_through_torch_func_equal_reverse_over_reverse(data):
    """A review: under jacrev(jacfwd), jacfwd(jacfwd) and grad(jvp) the step-through path
    still took the gain schedule, computed without a graph, and the outer level lost the
    gains' derivative (errors up to 978, silently)."""
    from torch.func import grad, jacfwd, jacrev, jvp

    ys = data[:2, :15]

    def ll(t):
        return _log_likelihood(t, ys)

    hessian = torch.autograd.functional.hessian(ll, THETA)
    for name, got in (("jacrev(jacfwd)", jacrev(jacfwd(ll))(THETA)),
                      ("jacfwd(jacfwd)", jacfwd(jacfwd(ll))(THETA)),
                      ("jacfwd(jacrev)", jacfwd(jacrev(ll))(THETA))):  # fmt: skip
        torch.testing.assert_close(got, hessian, rtol=1e-9, atol=1e-9, msg=name)
    hvp = grad(lambda t: jvp(ll, (t,), (DIRECTION,))[1])(THETA)
    torch.testing.assert_close(hvp, hessian @ DIRECTION, rtol=1e-9, atol=1e-9)


def test_forward_mode_under_no_grad_and_beside_tensors_that_require_grad(data):
    """A second review: with the shared path kept wherever any input required a gradient,
    a dual or jvp under no_grad, a jvp over parameters of data that requires a gradient,
    and a grad over a jvp raised (mm out=). Each is checked against the same call with an
    all-true mask, which steps through."""
    from torch.func import grad, jvp

    ys, mask = data[:2, :12], torch.ones(2, 12, 1, dtype=torch.bool)
    dys = torch.randn(ys.shape, generator=torch.Generator().manual_seed(5), dtype=F64)
    theta = THETA.clone().requires_grad_(True)

    def trained(**kw):  # a model built with grad on, its F, Q, R requiring a gradient
        return lambda y: _log_likelihood(theta, y, **kw)

    def under_no_grad(**kw):
        with torch.no_grad(), fwAD.dual_level():
            dual = trained(**kw)(fwAD.make_dual(ys, dys))
            return fwAD.unpack_dual(dual).tangent

    def jvp_no_grad(**kw):
        with torch.no_grad():
            return jvp(trained(**kw), (ys,), (dys,))[1]

    y_rg = ys.clone().requires_grad_(True)
    cases = {
        "dual under no_grad": under_no_grad,
        "jvp under no_grad": jvp_no_grad,
        "jvp beside data requiring grad": lambda **kw: jvp(
            lambda t: _log_likelihood(t, y_rg, **kw), (THETA,), (DIRECTION,))[1],
        "grad of jvp": lambda **kw: (grad(lambda y: jvp(
            lambda t: _log_likelihood(t, y, **kw), (THETA,), (DIRECTION,))[1])(ys) * dys).sum(),
    }  # fmt: skip
    for name, f in cases.items():
        torch.testing.assert_close(f(), f(mask=mask), rtol=1e-10, atol=1e-10, msg=name)


def test_nested_reverse_transforms_keep_the_shared_path_and_are_right(data):
    from torch.func import jacrev

    from difffilter import kalman

    ys = data[:2, :15]

    def ll(t):
        return _log_likelihood(t, ys)

    hessian = torch.autograd.functional.hessian(ll, THETA)
    torch.testing.assert_close(jacrev(jacrev(ll))(THETA), hessian, rtol=1e-9, atol=1e-9)
    seen = []
    original = kalman.shared_covariance_kalman_filter
    try:
        kalman.shared_covariance_kalman_filter = lambda *a: seen.append(1) or original(*a)
        torch.func.grad(ll)(THETA)
    finally:
        kalman.shared_covariance_kalman_filter = original
    assert seen  # first-order grad: the fast path (2x the time otherwise)


def test_vmap_over_the_parameters_is_refused_naming_the_batched_model(data):
    """vmap cannot read values, which the checks do: torch's "data-dependent control flow"
    error alone reached a system-identification trial; the refusal names the batched
    model that works, and jacfwd (vmap over tangents only) still runs."""
    ys = data
    with pytest.raises(ValueError, match="vmap over a model's parameters.*per-run matrices"):
        torch.func.vmap(lambda t: _log_likelihood(t, ys))(torch.stack([THETA, THETA * 1.1]))
    jac = torch.func.jacfwd(lambda t: _log_likelihood(t, ys))(THETA)
    assert jac.shape == THETA.shape and bool(torch.isfinite(jac).all())
