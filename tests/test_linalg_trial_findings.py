"""Findings of a trial of difffilter.linalg and the result containers."""

from __future__ import annotations

import pytest
import torch

import difffilter as df
from difffilter.estimator import output_of
from difffilter.linalg import safe_cholesky

D = torch.float64


def test_a_jittered_factors_gradient_is_the_jittered_matrixs():
    """A member that needed jitter had its failed first factor merged by ``torch.where``,
    whose backward sent 0·∞ = NaN into the matrix's gradient; now the gradient of
    ``cholesky(M + εI)`` for the ε the ladder chose, and the other members' their own."""
    singular = torch.tensor([[1.0, 1.0], [1.0, 1.0]], dtype=D)
    regular = torch.tensor([[2.0, 0.5], [0.5, 1.0]], dtype=D)
    batch = torch.stack([singular, regular]).requires_grad_()
    factor = safe_cholesky(batch, name="M")
    (grad,) = torch.autograd.grad(factor.sum(), batch)
    assert bool(torch.isfinite(grad).all())
    for i, eps in ((0, 1e-14 * 1.0), (1, 0.0)):  # (the singular one's ε: the first rung)
        member = (batch[i].detach() + eps * torch.eye(2, dtype=D)).requires_grad_()
        (expected,) = torch.autograd.grad(torch.linalg.cholesky(member).sum(), member)
        torch.testing.assert_close(grad[i], expected, rtol=1e-6, atol=0)
    torch.testing.assert_close(factor[1], torch.linalg.cholesky(regular), rtol=0, atol=0)


def test_an_infinite_variance_is_a_breakdown_as_nan_is():
    """``cholesky_ex`` factorises diag(∞, 1, 2) without an error (√∞ on the diagonal): a
    covariance overflowed on its diagonal alone had passed, where NaN is refused."""
    with pytest.raises(
        df.NumericalBreakdown, match="P must be symmetric positive definite and finite"
    ):
        safe_cholesky(torch.diag(torch.tensor([float("inf"), 1.0, 2.0], dtype=D)), name="P")


def test_output_of_keeps_the_count_of_skipped_measurements():
    """``output_of`` (the EstimatorOutput ``open_loop`` would give) dropped
    ``nonfinite_skipped`` of a ``nonfinite="skip"`` run."""
    eye = torch.eye(2, dtype=D)
    model = df.LinearGaussianModel(eye, eye, 0.1 * eye, eye, torch.zeros(2, dtype=D), eye)
    _, ys, _ = model.simulate(4, (3,), generator=torch.Generator().manual_seed(0))
    ys[0, 1, 0] = float("nan")
    ys[2, 3, 1] = float("inf")
    result = df.kalman_filter(model, ys, nonfinite="skip")
    assert torch.equal(output_of(result).extras["nonfinite_skipped"], result.nonfinite_skipped)
    assert result.nonfinite_skipped.tolist() == [1, 0, 1]
