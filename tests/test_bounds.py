"""The posterior Cramér–Rao bound against the Kalman covariance and closed forms (float64)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from conftest import constant_velocity
from scipy.integrate import trapezoid

import difffilter as df
from difffilter.bounds import gaussian_information, noise_information
from difffilter.noise import Gaussian, GaussianMixture


def _run(model, T, generator, mask=None):
    xs, ys, x0 = model.simulate(T, (1,), generator=generator)
    pcrb = df.posterior_crb(model, xs, x0, mask=mask)
    kf = df.kalman_filter(model, ys, mask=None if mask is None else mask.unsqueeze(0))
    return pcrb, kf


def test_pcrb_equals_kalman_covariance_on_linear_gaussian(generator):
    model = constant_velocity()
    pcrb, kf = _run(model, 12, generator)
    torch.testing.assert_close(pcrb.bound, kf.covs[0], atol=1e-10, rtol=1e-9)


def test_pcrb_with_mask_equals_kalman_covariance(generator):
    model = constant_velocity()
    T = 15
    mask = torch.rand(T, 2, generator=generator) > 0.4
    mask[3] = False  # a step with nothing received: no information, pure prediction
    pcrb, kf = _run(model, T, generator, mask)
    torch.testing.assert_close(pcrb.bound, kf.covs[0], atol=1e-10, rtol=1e-9)
    # an all-false step: J_k = (Q + F J⁻¹ Fᵀ)⁻¹ (prediction only)
    F, Q = model.F, model.process_noise.cov
    pred = F @ pcrb.bound[2] @ F.T + Q
    torch.testing.assert_close(pcrb.bound[3], pred, atol=1e-10, rtol=1e-9)


@pytest.mark.parametrize("masks", [1, 2, 3, 4, 5])
def test_a_batch_of_masks_gives_each_masks_own_bound_whatever_its_length(generator, masks):
    """A batch of ``B`` mask patterns gives, for each, the bound of that mask alone (the
    Kalman covariance): ``B = dx`` (4 here) had given wrong bounds, not even semi-definite,
    as ``torch.linalg.solve`` read the unbatched ``D12 [dx, dx]`` beside ``J [dx, dx, dx]``
    as dx vectors (a trial: the tracking report's oracle bounds at ``--runs 4``)."""
    model = constant_velocity()
    T = 8
    xs, ys, x0 = model.simulate(T, (1,), generator=generator)
    mask = torch.rand(masks, T, 2, generator=generator) > 0.4
    bound = df.posterior_crb(model, xs, x0, mask=mask).bound
    assert bound.shape == (masks, T, 4, 4)
    for b in range(masks):
        kf = df.kalman_filter(model, ys, mask=mask[b].unsqueeze(0))
        torch.testing.assert_close(bound[b], kf.covs[0], atol=1e-10, rtol=1e-9)


def test_pcrb_scalar_closed_form():
    # x_{k+1} = a x_k + w, y = x + v: J_1 = 1/(q + a² p0) + 1/r, J_2 = 1/(q + a²/J_1) + 1/r
    a, q, r, p0 = 0.9, 0.3, 2.0, 1.5
    t = lambda v: torch.tensor([[v]], dtype=torch.float64)  # noqa: E731
    model = df.LinearGaussianModel(
        t(a), t(1.0), t(q), t(r), torch.zeros(1, dtype=torch.float64), t(p0)
    )
    xs = torch.zeros(1, 2, 1, dtype=torch.float64)
    res = df.posterior_crb(model, xs, torch.zeros(1, 1, dtype=torch.float64))
    j1 = 1 / (q + a * a * p0) + 1 / r
    j2 = 1 / (q + a * a / j1) + 1 / r
    np.testing.assert_allclose(res.information[:, 0, 0].numpy(), [j1, j2], rtol=1e-12)
    np.testing.assert_allclose(res.rmse([0]).numpy(), [j1**-0.5, j2**-0.5], rtol=1e-12)
    # a component given as an int is the same per-step floor (once summed over the steps)
    np.testing.assert_allclose(res.rmse(0).numpy(), [j1**-0.5, j2**-0.5], rtol=1e-12)


def test_gaussian_information_mask_is_inverse_of_received_block():
    R = torch.tensor([[2.0, 0.5, 0.1], [0.5, 1.0, 0.2], [0.1, 0.2, 3.0]], dtype=torch.float64)
    mask = torch.tensor([True, False, True])
    J = gaussian_information(R, mask)
    sub = torch.linalg.inv(R[[0, 2]][:, [0, 2]])
    torch.testing.assert_close(J[[0, 2]][:, [0, 2]], sub)
    assert float(J[1].abs().sum() + J[:, 1].abs().sum()) == 0.0


def _mixture_fisher_quadrature(weights, sigmas):
    """Scalar zero-mean mixture: ∫ p'(v)²/p(v) dv on a fine grid (independent truth)."""
    v = np.linspace(-60, 60, 400_001)
    comps = [
        w * np.exp(-0.5 * (v / s) ** 2) / (s * math.sqrt(2 * math.pi))
        for w, s in zip(weights, sigmas)
    ]
    p = sum(comps)
    dp = sum(-c * v / s**2 for c, s in zip(comps, sigmas))
    return trapezoid(dp**2 / p, v)  # scipy's: numpy has it only from 2.0 (we accept 1.24)


def test_mixture_information_matches_quadrature():
    weights, sigmas = (0.8, 0.2), (2.0, 5.0)  # the glint range noise of the RRP paper
    mix = GaussianMixture(
        torch.tensor(weights, dtype=torch.float64),
        torch.zeros(2, 1, dtype=torch.float64),
        torch.tensor([[[sigmas[0] ** 2]], [[sigmas[1] ** 2]]], dtype=torch.float64),
    )
    gen = torch.Generator().manual_seed(0)
    J = noise_information(mix, num_samples=400_000, generator=gen)
    truth = _mixture_fisher_quadrature(weights, sigmas)
    assert abs(float(J[0, 0]) - truth) / truth < 0.01
    # less informative than its narrow component alone, more than the moment-matched Gaussian
    assert 1 / float(mix.cov[0, 0]) < float(J[0, 0]) < 1 / sigmas[0] ** 2


def test_mixture_information_honours_mask_and_gaussian_is_exact():
    cov = torch.tensor([[[1.0, 0.0], [0.0, 4.0]], [[9.0, 0.0], [0.0, 16.0]]], dtype=torch.float64)
    mix = GaussianMixture(
        torch.tensor([0.7, 0.3], dtype=torch.float64), torch.zeros(2, 2, dtype=torch.float64), cov
    )
    mask = torch.tensor([[True, False], [True, True], [False, False]])
    J = noise_information(mix, mask, num_samples=50_000, generator=torch.Generator().manual_seed(1))
    assert J.shape == (3, 2, 2)
    assert float(J[0, 1].abs().sum() + J[0, :, 1].abs().sum()) == 0.0
    assert float(J[2].abs().sum()) == 0.0
    g = Gaussian(torch.zeros(2, dtype=torch.float64), cov[0])
    torch.testing.assert_close(noise_information(g, mask[1]), torch.linalg.inv(cov[0]))


def test_pcrb_bad_input_raises():
    model = constant_velocity()
    xs = torch.zeros(1, 5, 4, dtype=torch.float64)
    x0 = torch.zeros(1, 4, dtype=torch.float64)
    with pytest.raises(ValueError, match="xs must be"):
        df.posterior_crb(model, torch.zeros(5, 4, dtype=torch.float64), x0)
    with pytest.raises(ValueError, match="x0 must have shape"):
        df.posterior_crb(model, xs, torch.zeros(4, dtype=torch.float64))
    with pytest.raises(ValueError, match="mask must be a bool"):
        df.posterior_crb(model, xs, x0, mask=torch.ones(5, 2))
    with pytest.raises(ValueError, match="one row per step"):
        df.posterior_crb(model, xs, x0, mask=torch.ones(4, 2, dtype=torch.bool))
    with pytest.raises(ValueError, match="finite"):
        df.posterior_crb(model, xs * math.nan, x0)
    # (a docs trial: float32 paths on a float64 model met torch's "expected scalar type
    # Double but found Float"; a float mask was told only its shape)
    with pytest.raises(
        ValueError,
        match=r"xs must have the model's dtype torch.float64; got "
        r"torch.float32 \(convert with xs.to",
    ):
        df.posterior_crb(model, xs.float(), x0)
    with pytest.raises(ValueError, match="x0 must have the model's dtype torch.float64"):
        df.posterior_crb(model, xs, x0.float())
    with pytest.raises(ValueError, match="xs must have a floating dtype"):
        df.posterior_crb(model, xs.long(), x0)
    with pytest.raises(
        ValueError,
        match=r"mask must be a bool tensor \[\.\.\., 2\] \(True = "
        r"received\); got torch.float64 \(5, 2\)",
    ):
        df.posterior_crb(model, xs, x0, mask=torch.ones(5, 2, dtype=torch.float64))
    with pytest.raises(ValueError, match="model must be"):
        df.posterior_crb("cv", xs, x0)
    with pytest.raises(ValueError, match="noise must be"):
        noise_information(torch.eye(2))


class _GrowingNoise(df.LinearGaussianModel):
    """Q_k = (1 + k) Q, R_k = (1 + k/2) R: time-varying noise as ``StateSpaceModel`` says."""

    time_varying = True

    def process_cov(self, k):
        return self.process_noise.cov * (1 + k)

    def measurement_cov(self, k):
        return self.measurement_noise.cov * (1 + 0.5 * k)


def test_pcrb_reads_a_time_varying_models_noise_at_every_step(generator):
    """J_k⁻¹ = the Kalman filter's P_{k|k} with Q_k and R_k read per step (it used Q_0, R)."""
    eye = torch.eye(2, dtype=torch.float64)
    model = _GrowingNoise(
        0.9 * eye, eye, 0.1 * eye, 0.2 * eye, torch.zeros(2, dtype=torch.float64), eye
    )
    T = 6
    mask = torch.rand(T, 2, generator=generator) > 0.3
    for m in (None, mask):
        pcrb, kf = _run(model, T, generator, m)
        torch.testing.assert_close(pcrb.bound, kf.covs[0], atol=1e-12, rtol=1e-10)


def test_pcrb_refuses_a_model_with_a_batch_of_its_own():
    """A batched Q or R lined up with the paths M (wrong bounds, or a shape error)."""
    eye = torch.eye(2, dtype=torch.float64)
    model = df.LinearGaussianModel(0.9 * eye, eye, 0.1 * eye.expand(2, 2, 2), 0.2 * eye,
                                   torch.zeros(2, dtype=torch.float64), eye)  # fmt: skip
    xs, x0 = torch.zeros(2, 3, 2, dtype=torch.float64), torch.zeros(2, 2, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"without batch dimensions of its own.*process_cov"):
        df.posterior_crb(model, xs, x0)
