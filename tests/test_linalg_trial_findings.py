"""Findings of a trial of difffilter.linalg and the result containers."""

from __future__ import annotations

import pytest
import torch

import difffilter as df
from difffilter.estimator import output_of
from difffilter.linalg import safe_cholesky
from difffilter.noise import Gaussian, GaussianMixture

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


def _scipy_logpdf(r, cov):
    from scipy.stats import multivariate_normal

    return float(multivariate_normal(mean=[0.0] * len(r), cov=cov).logpdf(r))


def test_a_masked_density_ignores_what_a_lost_entry_holds():
    """A second trial: ``residual · mask`` made a NaN or ∞ where nothing was received (as
    lost values are stored) a NaN density and gradient. Truth: scipy on the received entries."""
    cov = torch.tensor([[2.0, 0.3, 0.1], [0.3, 1.0, 0.2], [0.1, 0.2, 1.5]], dtype=D)
    mask = torch.tensor([True, False, True])
    want = _scipy_logpdf([0.4, -0.7], cov[[0, 2]][:, [0, 2]].numpy())
    for lost in (float("nan"), float("inf")):
        y = torch.tensor([0.4, lost, -0.7], dtype=D, requires_grad=True)
        for noise in (
            Gaussian(0, cov),
            GaussianMixture([1.0], torch.zeros(1, 3, dtype=D), cov[None]),
        ):
            got = noise.log_prob(y, mask)
            assert float(got.detach()) == pytest.approx(want, rel=1e-13)
            (grad,) = torch.autograd.grad(got, y)
            assert grad.isfinite().all() and float(grad[1]) == 0.0


def test_a_densitys_mask_and_value_are_checked():
    """A second trial: an all-True ``[N, 1]`` mask counted one received entry of three (the
    density (d − 1)/2 · log 2π off), an integer mask holding 2 weighed its entry twice, and a
    ``[N, 1]`` value broadcast to (v, v, v) against a non-zero mean."""
    g = Gaussian(torch.tensor([0.1, 0.2, 0.3], dtype=D), torch.eye(3, dtype=D))
    y = torch.zeros(4, 3, dtype=D)
    with pytest.raises(ValueError, match=r"mask must be bool \[\.\.\., 3\].*\(4, 1\)"):
        g.log_prob(y, torch.ones(4, 1, dtype=torch.bool))
    with pytest.raises(ValueError, match=r"mask must be bool.*torch.int64"):
        g.log_prob(y, torch.tensor([1, 2, 0]).expand(4, 3))
    with pytest.raises(ValueError, match=r"value must be \[\.\.\., 3\]; got \(4, 1\)"):
        g.log_prob(torch.zeros(4, 1, dtype=D))
    assert g.log_prob(y, torch.ones(4, 3, dtype=torch.bool)).shape == (4,)


def test_a_correlation_written_in_one_triangle_is_refused():
    """A second trial: variances 1e6, 1e-2, 1e-2 and a correlation of 0.9 written below the
    diagonal only passed (9e-9 of the largest entry), and sampling (the lower triangle: 0.9)
    and the filters (symmetrised: 0.45) then used two noise models."""
    cov = torch.diag(torch.tensor([1e6, 1e-2, 1e-2], dtype=D))
    cov[2, 1] = 0.009
    with pytest.raises(ValueError, match=r"entries \(1, 2\) and \(2, 1\) differ by 0\.9 of"):
        Gaussian(0, cov)
    cov[1, 2] = 0.009 * (1 + 1e-9)  # round-off: taken
    Gaussian(0, cov)
    psd = torch.diag(torch.tensor([1.0, 0.0], dtype=D))  # a zero variance has no scale: taken
    Gaussian(0, psd + 1e-12 * torch.eye(2, dtype=D))
