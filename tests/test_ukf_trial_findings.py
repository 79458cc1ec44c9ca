"""Findings of a red-team trial of the extended and unscented Kalman filters (2026-12-06),
against the Kalman filter on linear models."""

from __future__ import annotations

import pytest
import torch

import difffilter as df
from difffilter.linalg import NumericalBreakdown

D = torch.float64


class _ResetState(df.LinearGaussianModel):
    """The second state reset every step and known: a singular predicted covariance."""

    time_varying = True

    def process_cov(self, k):
        return torch.diag(torch.tensor([0.1, 0.0], dtype=D))


def test_the_ukf_runs_through_a_singular_predicted_covariance():
    model = _ResetState(torch.tensor([[1.0, 0.1], [0.0, 0.0]], dtype=D), torch.tensor([[1.0, 1.0]], dtype=D),
                        0.1 * torch.eye(2, dtype=D), 0.2 * torch.eye(1, dtype=D),
                        torch.zeros(2, dtype=D), torch.eye(2, dtype=D))  # fmt: skip
    ys = torch.randn(3, 5, 1, dtype=D, generator=torch.Generator().manual_seed(0))
    kf, ukf = df.kalman_filter(model, ys), df.unscented_kalman_filter(model, ys)  # ukf had raised
    assert torch.allclose(ukf.log_likelihood, kf.log_likelihood, rtol=0, atol=1e-10)
    assert torch.allclose(ukf.means, kf.means, rtol=0, atol=1e-10)


@pytest.mark.parametrize("runs", [5, 3])
def test_the_ukf_refuses_per_run_matrices_of_a_time_varying_model(runs):
    # they had met the sigma points: 3-5 off the KF where runs = 2n + 1, a raw error else
    Fb = torch.eye(2, dtype=D) + 0.3 * torch.randn(
        runs, 2, 2, dtype=D, generator=torch.Generator().manual_seed(0)
    )

    class PerRun(df.LinearGaussianModel):
        time_varying = True

        def transition_matrix(self, k):
            return Fb

    model = PerRun(torch.eye(2, dtype=D), torch.tensor([[1.0, 0.0]], dtype=D), 0.1 * torch.eye(2, dtype=D),
                   0.2 * torch.eye(1, dtype=D), torch.zeros(2, dtype=D), torch.eye(2, dtype=D))  # fmt: skip
    with pytest.raises(ValueError, match=rf"F, B or H have batch shape \({runs},\)"):
        df.unscented_kalman_filter(model, torch.zeros(runs, 4, 1, dtype=D))


W = torch.tensor([[0.9, 0.1, 0.5], [0.0, 0.8, 1.0]], dtype=D)


def _joined(x, u):
    return torch.cat([x, u], -1) @ W.T


def _apart(x, u):
    return x @ W[:, :2].T + u @ W[:, 2:].T


def _model(f):
    return df.NonlinearGaussianModel(f, lambda x: x[..., :1] ** 2, 0.1 * torch.eye(2, dtype=D),
                                     0.2 * torch.eye(1, dtype=D), torch.ones(2, dtype=D),
                                     torch.eye(2, dtype=D), dim_u=1)  # fmt: skip


def test_a_transition_that_joins_state_and_input_runs_in_the_ukf_and_the_particle_filter():
    # u [..., 1, du] beside the points had failed in torch.cat
    g = torch.Generator().manual_seed(1)
    ys, us = torch.randn(3, 4, 1, dtype=D, generator=g), torch.randn(3, 4, 1, dtype=D, generator=g)
    a, b = (df.unscented_kalman_filter(_model(f), ys, us) for f in (_joined, _apart))
    assert torch.allclose(a.means, b.means, rtol=0, atol=1e-12)
    p, q = (df.particle_filter(_model(f), ys, us, num_particles=64, generator=torch.Generator().manual_seed(2))
            for f in (_joined, _apart))  # fmt: skip
    assert torch.allclose(p.means, q.means, rtol=0, atol=1e-12)
    with torch.no_grad():  # the one-run host step too
        pf = df.ParticleFilter(32)
        carry = pf.init(_model(_joined), (), torch.Generator().manual_seed(3))
        pf.step(carry, ys[0, 0], us[0, 0])


def test_a_nonlinear_model_is_built_inside_a_torch_func_transform():
    # its width probe had called requires_grad_, which the transforms refuse
    ys = torch.randn(2, 5, 1, dtype=D, generator=torch.Generator().manual_seed(4))

    def loss(theta):
        model = df.NonlinearGaussianModel(lambda x: theta * x, lambda x: x[..., :1],
                                          0.1 * torch.eye(1, dtype=D), 0.2 * torch.eye(1, dtype=D),
                                          torch.zeros(1, dtype=D), torch.eye(1, dtype=D))  # fmt: skip
        return df.extended_kalman_filter(model, ys).log_likelihood.sum()

    theta = torch.tensor(0.9, dtype=D, requires_grad=True)
    (reverse,) = torch.autograd.grad(loss(theta), theta)
    assert torch.allclose(torch.func.grad(loss)(theta.detach()), reverse, rtol=1e-12)


def test_a_transition_that_gives_nan_is_named_with_its_step():
    model = df.NonlinearGaussianModel(lambda x: 2 * torch.sqrt(x) - 3.0, lambda x: x,
                                      0.01 * torch.eye(1, dtype=D), 0.01 * torch.eye(1, dtype=D),
                                      torch.ones(1, dtype=D), 0.01 * torch.eye(1, dtype=D))  # fmt: skip
    with pytest.raises(
        NumericalBreakdown, match=r"the UKF's (prediction|estimate) at step \d+ is NaN or inf"
    ):
        df.unscented_kalman_filter(model, torch.zeros(1, 10, 1, dtype=D))


def _gains_model(a, jacobians=False):
    """``f(x) = a sin x + x / 2`` with one gain row per run (``a [B, 2]``)."""
    eye = torch.eye(2, dtype=D)
    jf = (lambda x: torch.diag_embed(a * torch.cos(x) + 0.5)) if jacobians else None
    jh = (lambda x: torch.diag_embed(x / 2 + 1)) if jacobians else None
    return df.NonlinearGaussianModel(lambda x: a * torch.sin(x) + 0.5 * x,
                                     lambda x: x**2 / 4 + x, 0.1 * eye, 0.2 * eye,
                                     torch.zeros(a.shape[0], 2, dtype=D), eye,
                                     transition_jacobian=jf, observation_jacobian=jh)  # fmt: skip


def test_a_function_holding_values_per_run_is_refused_on_stacks_of_states():
    """A second trial: with gains per run ``a [B, 2]`` and ``B = 2n + 1 = 5`` the UKF moved
    sigma point ``i`` of every run with run ``i``'s gain (means up to 1.36 from each run
    filtered alone); at other ``B`` torch's raw shape errors. Truth: each run filtered alone."""
    g = torch.Generator().manual_seed(2)
    a, ys = torch.randn(5, 2, generator=g, dtype=D), torch.randn(5, 6, 2, generator=g, dtype=D)
    with pytest.raises(
        ValueError, match=r"transition holds values of its own per run.*\[5, 5, 2\]"
    ):
        df.unscented_kalman_filter(_gains_model(a), ys)
    with pytest.raises(ValueError, match="holds values of its own per run.*closed-form"):
        df.extended_kalman_filter(_gains_model(a[:3]), ys[:3])  # its Jacobian, one state
    batched = df.extended_kalman_filter(_gains_model(a, jacobians=True), ys)  # on x [B, 2]
    for b in range(5):
        alone = df.extended_kalman_filter(_gains_model(a[b : b + 1], jacobians=True), ys[b : b + 1])
        torch.testing.assert_close(batched.means[b], alone.means[0], rtol=1e-13, atol=1e-14)
