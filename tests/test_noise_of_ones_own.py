"""Noise models of one's own and the checks around them (a non-Gaussian-noise trial): a
noise without a covariance stopped even the bootstrap particle filter in its checks, a
missing member raised an empty ``NotImplementedError``, a mixture could not draw 0
samples, a symmetric box's round-off mean was refused, and a noise of another dtype failed
deep in the Kalman update."""

from __future__ import annotations

import math

import pytest
import torch

import difffilter as df
from difffilter.noise import GaussianMixture, NoiseModel, UniformBox

F64 = torch.float64


class Cauchy(NoiseModel):
    """A standard Cauchy noise per entry: no mean, no covariance (``cov`` left out)."""

    def __init__(self, dim: int, scale: float):
        super().__init__()
        self.dim, self.scale = dim, scale

    def sample(self, sample_shape=(), generator=None):
        u = torch.rand(*sample_shape, self.dim, dtype=F64, generator=generator)
        return self.scale * torch.tan(math.pi * (u - 0.5))

    def log_prob(self, value, mask=None):
        logp = -torch.log(math.pi * self.scale * (1 + (value / self.scale) ** 2))
        return (logp if mask is None else torch.where(mask, logp, 0.0)).sum(-1)

    @property
    def mean(self):
        return torch.zeros(self.dim, dtype=F64)


def _model():
    eye = torch.eye(1, dtype=F64)
    return df.LinearGaussianModel(0.9 * eye, eye, 0.1 * eye, eye, torch.zeros(1, dtype=F64), eye)


def test_a_noise_without_a_covariance_runs_in_the_particle_filter_and_is_named_elsewhere():
    model = _model()
    model.measurement_noise = Cauchy(1, 0.3)
    ys = torch.tensor([[[0.1], [0.5], [-0.2], [3.0]]], dtype=F64)
    out = df.particle_filter(model, ys, num_particles=4000, innovations=False,
                             generator=torch.Generator().manual_seed(0))  # fmt: skip
    # the truth: the exact likelihood by quadrature (a grid filter over x)
    grid = torch.linspace(-6, 6, 4001, dtype=F64)
    dx = float(grid[1] - grid[0])
    prior = torch.exp(-0.5 * grid**2) / math.sqrt(2 * math.pi)
    trans = torch.exp(-0.5 * (grid[:, None] - 0.9 * grid[None, :]) ** 2 / 0.1) / math.sqrt(
        0.2 * math.pi
    )
    log_lik, p = 0.0, prior
    for y in ys[0, :, 0]:
        p = trans @ p * dx
        like = torch.exp(model.measurement_noise.log_prob((y - grid)[:, None]))
        z = float((like * p).sum() * dx)
        log_lik, p = log_lik + math.log(z), like * p / z
    assert float(out.log_likelihood.sum()) == pytest.approx(log_lik, abs=0.08)
    with pytest.raises(NotImplementedError, match=r"Cauchy.cov is not implemented: a NoiseModel "
                                                  r"subclass provides"):  # fmt: skip
        df.kalman_filter(model, ys)
    with pytest.raises(NotImplementedError, match=r"Cauchy.cov is not implemented.*pass "
                                                  r"innovations=False"):  # fmt: skip
        df.particle_filter(model, ys, num_particles=10, generator=torch.Generator().manual_seed(0))


def test_a_missing_member_is_named():
    class Half(NoiseModel):
        dim = 1

        def sample(self, sample_shape=(), generator=None):
            return torch.zeros(*sample_shape, 1, dtype=F64)

    model = _model()
    model.measurement_noise = Half()
    with pytest.raises(NotImplementedError, match=r"Half.log_prob\(value, mask=None\) is not "
                                                  r"implemented"):  # fmt: skip
        df.particle_filter(model, torch.zeros(1, 3, 1, dtype=F64), num_particles=10,
                           innovations=False, generator=torch.Generator().manual_seed(0))  # fmt: skip


def test_a_mixture_draws_no_sample_as_the_other_noises_do():
    mix = GaussianMixture(torch.tensor([0.3, 0.7]), torch.zeros(2, 2), torch.eye(2).expand(2, 2, 2))
    assert mix.sample((0,)).shape == (0, 2) and mix.sample((3, 0)).shape == (3, 0, 2)
    assert UniformBox(-torch.ones(2), torch.ones(2)).sample((0,)).shape == (0, 2)


def test_zero_mean_up_to_round_off_and_the_noises_dtype():
    model = _model()
    box = UniformBox(torch.tensor([-0.1 - 0.2], dtype=F64), torch.tensor([0.3], dtype=F64))
    assert float(box.mean) != 0.0 and abs(float(box.mean)) < 1e-16  # −2.8e-17: round-off
    model.measurement_noise = box
    ys = torch.tensor([[[0.4], [-0.3], [1.1]]], dtype=F64)  # (zeros gave means 0 whatever R)
    reference = df.kalman_filter(_model_with_r(box.cov), ys)
    assert not torch.allclose(
        reference.means, df.kalman_filter(_model_with_r(10 * box.cov), ys).means
    )
    torch.testing.assert_close(df.kalman_filter(model, ys).means, reference.means)
    model.measurement_noise = UniformBox(
        torch.tensor([-0.3], dtype=F64), torch.tensor([0.31], dtype=F64)
    )
    with pytest.raises(ValueError, match="take every noise as zero-mean"):
        df.kalman_filter(model, ys)
    model.measurement_noise = UniformBox(torch.tensor([-0.3]), torch.tensor([0.3]))  # float32
    with pytest.raises(ValueError, match=r"model.measurement_noise.low is torch.float32 and the "
                                         r"model is torch.float64"):  # fmt: skip
        df.kalman_filter(model, ys)


def _model_with_r(R):
    eye = torch.eye(1, dtype=F64)
    return df.LinearGaussianModel(0.9 * eye, eye, 0.1 * eye, R, torch.zeros(1, dtype=F64), eye)


class _LaplacePerRun(NoiseModel):
    """Zero-mean Laplace noise of scale ``b [*batch, d]``: one scale per run."""

    def __init__(self, b):
        super().__init__()
        self.dim, self.b = b.shape[-1], b

    def sample(self, sample_shape=(), generator=None):
        shape = torch.Size(sample_shape) + self.b.shape
        u = torch.rand(shape, dtype=F64, generator=generator) - 0.5
        return -self.b * torch.sign(u) * torch.log1p(-2 * u.abs())

    @property
    def mean(self):
        return torch.zeros_like(self.b)

    @property
    def cov(self):
        return torch.diag_embed(2 * self.b**2)


def test_a_batched_noise_of_ones_own_is_drawn_one_per_run_in_simulate():
    """A noise of one's own with a scale per run (mean [3, 1]) as the measurement noise: 3
    runs (batch_shape (N, 1) → (N, 3)), each with its own variance 2 b² (a Laplace's); it had
    failed in a reshape (a noise trial)."""
    b = torch.tensor([[0.5], [1.0], [2.0]], dtype=F64)
    model = _model()
    model.measurement_noise = _LaplacePerRun(b)
    assert model.measurement_noise.has_batch() and not Cauchy(1, 0.3).has_batch()
    xs, ys, x0 = model.simulate(4, (5000, 1), generator=torch.Generator().manual_seed(0))
    assert xs.shape == ys.shape == (5000, 3, 4, 1) and x0.shape == (5000, 3, 1)
    v = (ys - xs).transpose(0, 1).reshape(3, -1)
    torch.testing.assert_close(v.var(-1), 2 * b[:, 0] ** 2, rtol=0.05, atol=0)
