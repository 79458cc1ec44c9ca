"""Findings of a trial of the differentiable workflows (docs/gradients.md, plugins.md):

* ``torch.func.grad``, ``jvp``, ``jacrev`` (and ``jacfwd`` with ``randomness="same"``) raised
  "Cannot access data pointer of Tensor that doesn't have storage" on the particle filter
  (the noise's factor cached by ``data_ptr()``) and on an online step (the carry's value
  check read ``.numpy()`` of a functorch wrapper); the docs promise them for every filter.
  Truth: reverse mode on the same function;
* a stateful likelihood with its ``weigh`` misspelt was told "must be a callable object".
"""

from __future__ import annotations

import pytest
import torch

import difffilter as df
from difffilter.noise import UniformBox

D = torch.float64
F = torch.tensor([[0.9, 0.1], [0.0, 0.95]], dtype=D)
H = torch.tensor([[1.0, 0.0]], dtype=D)
Q = torch.diag(torch.tensor([1e-2, 2e-2], dtype=D))
R = torch.tensor([[0.1]], dtype=D)
YS = torch.randn(3, 8, 1, dtype=D, generator=torch.Generator().manual_seed(0))
X = torch.tensor(0.1, dtype=D)


def _model(log_q, noise=None):
    model = df.LinearGaussianModel(F, H, Q * log_q.exp(), R, torch.zeros(2, dtype=D),
                                   0.5 * torch.eye(2, dtype=D))  # fmt: skip
    if noise is not None:
        model.measurement_noise = noise
    return model


def _whole_pf(log_q):
    pf = df.particle_filter(_model(log_q), YS, num_particles=40,
                            generator=torch.Generator().manual_seed(0))  # fmt: skip
    return pf.log_likelihood.sum()


def _online(estimator, runs):
    def loglik(log_q):
        gen = torch.Generator().manual_seed(0)
        args = (gen,) if isinstance(estimator, df.ParticleFilter) else ()
        carry = estimator.init(_model(log_q), runs, *args)
        total = 0.0
        for t in range(YS.shape[-2]):
            y = YS[:, t] if runs else YS[0, t]
            carry, out = estimator.step(carry, y)
            total = total + out.log_likelihood.sum()
        return total

    return loglik


def _reverse(fn):
    x = X.clone().requires_grad_()
    return torch.autograd.grad(fn(x), x)[0]


def _transforms(fn):
    one = torch.ones((), dtype=D)
    return {"grad": torch.func.grad(fn)(X), "jacrev": torch.func.jacrev(fn)(X),
            "jvp": torch.func.jvp(fn, (X,), (one,))[1],
            "jacfwd": torch.func.jacfwd(fn, randomness="same")(X)}  # fmt: skip


@pytest.mark.parametrize(
    "name",
    [
        "particle_filter",
        "online_kf_batch",
        "online_kf_one_run",
        "online_pf_batch",
        "online_pf_one_run",
    ],  # fmt: skip
)
def test_torch_func_transforms_run_through_the_filter_and_equal_reverse_mode(name):
    fn = {
        "particle_filter": _whole_pf,
        "online_kf_batch": _online(df.KalmanFilter(), (3,)),
        "online_kf_one_run": _online(df.KalmanFilter(), ()),
        "online_pf_batch": _online(df.ParticleFilter(40), (3,)),
        "online_pf_one_run": _online(df.ParticleFilter(40), ()),
    }[name]
    want = _reverse(fn)
    for transform, got in _transforms(fn).items():
        torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-12, msg=transform)


@pytest.mark.parametrize("estimator", ["kf", "pf"])
def test_forward_mode_under_no_grad_keeps_the_tangent_of_one_run(estimator):
    """The one-run particle step took its numpy path under ``no_grad`` with a dual model
    (dual tensors report ``requires_grad=False``): its output had no tangent at all."""
    fn = _online(df.KalmanFilter() if estimator == "kf" else df.ParticleFilter(40), ())
    want = torch.func.jvp(fn, (X,), (torch.ones((), dtype=D),))[1]
    with torch.autograd.forward_ad.dual_level(), torch.no_grad():
        out = fn(torch.autograd.forward_ad.make_dual(X, torch.ones((), dtype=D)))
        tangent = torch.autograd.forward_ad.unpack_dual(out).tangent
    assert tangent is not None
    torch.testing.assert_close(tangent, want, rtol=1e-10, atol=1e-12)


def test_the_particle_filters_hessian_through_torch_func_is_reverse_over_reverse():
    x = X.clone().requires_grad_()
    (g,) = torch.autograd.grad(_whole_pf(x), x, create_graph=True)
    (want,) = torch.autograd.grad(g, x)
    got = torch.func.jacfwd(torch.func.jacrev(_whole_pf), randomness="same")(X)
    torch.testing.assert_close(got, want, rtol=1e-9, atol=1e-12)


def test_a_uniform_noise_under_torch_func_grad():
    """The box's log-lengths were cached by ``data_ptr()`` too."""

    def loglik(log_q):
        half = 8.0 * log_q.exp()  # (wide: every particle inside at every step)
        box = UniformBox(-half * torch.ones(1, dtype=D), half * torch.ones(1, dtype=D))
        ys = 0.3 * YS.tanh()
        pf = df.particle_filter(_model(log_q, box), ys, num_particles=40,
                                generator=torch.Generator().manual_seed(0))  # fmt: skip
        return pf.log_likelihood.sum()

    torch.testing.assert_close(torch.func.grad(loglik)(X), _reverse(loglik), rtol=1e-10, atol=0)


def test_a_stateful_likelihood_with_a_misspelt_weigh_is_named():
    class Counting:
        def init(self, model, batch_shape, dtype, device):
            return torch.zeros(batch_shape, dtype=dtype, device=device)

        def weight(self, state, model, y, particles, k, mask, predictive):  # (weigh)
            return state + 1, torch.zeros(particles.shape[:-1], dtype=D), {}

    with pytest.raises(TypeError, match="has an init, so it is a stateful likelihood, and it "
                                        "has no weigh method"):  # fmt: skip
        df.particle_filter(_model(X), YS, num_particles=20, likelihood=Counting())
