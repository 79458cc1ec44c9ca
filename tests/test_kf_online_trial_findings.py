"""Findings of a red-team trial of the Kalman filter's online paths (each failed before its
fix)."""

from __future__ import annotations

import torch

import difffilter as df

D = torch.float64


def _model():
    F = torch.tensor([[0.9, 0.2], [-0.1, 0.8]], dtype=D)
    H = torch.tensor([[1.0, 0.0]], dtype=D)
    return df.LinearGaussianModel(F, H, 0.05 * torch.eye(2, dtype=D), 0.3 * torch.eye(1, dtype=D),
                                  torch.zeros(2, dtype=D), torch.eye(2, dtype=D))  # fmt: skip


def _ys(model, steps=20):
    return model.simulate(steps, (), generator=torch.Generator().manual_seed(3))[1]


def _online(model, ys, change=None, at=5):
    kf, carry = df.KalmanFilter(), None
    carry = kf.init(model)
    total = 0.0
    for k, y in enumerate(ys):
        if k == at and change is not None:
            change(model)
        carry, out = kf.step(carry, y)
        total = total + out.log_likelihood
    return carry, total


def test_a_new_tensor_given_through_data_drops_the_gain_schedule():
    """F.data = new (as vector_to_parameters assigns) kept the version counter, and the
    online step went on with the old gains (0.67 off the mean)."""
    model = _model()
    ys = _ys(model)
    new = torch.tensor([[0.5, 0.3], [0.1, 0.6]], dtype=D)

    def data_assign(m):
        m.F.data = new.clone()

    def vector(m):
        torch.nn.utils.vector_to_parameters(new.reshape(-1), [m.F])

    for change in (data_assign, vector):
        model = _model()
        carry, _ = _online(model, ys, change)
        ref = _model()
        ref_carry, _ = _online(ref, ys, lambda m: setattr(m, "F", new.clone()))
        torch.testing.assert_close(carry.mean, ref_carry.mean)
        torch.testing.assert_close(carry.cov, ref_carry.cov)


def test_a_matrix_made_to_require_a_gradient_is_differentiated_through_the_covariances():
    """requires_grad_() after init kept the schedule computed without autograd: dLL/dF
    missed every path through the gains (1.5 off the whole-sequence filter's)."""
    model = _model()
    ys = _ys(model, 15)
    _, total = _online(model, ys, lambda m: m.F.requires_grad_(True), at=0)
    (online,) = torch.autograd.grad(total, model.F)
    whole = _model()
    whole.F.requires_grad_(True)
    (want,) = torch.autograd.grad(df.kalman_filter(whole, ys).log_likelihood.sum(), whole.F)
    torch.testing.assert_close(online, want)
