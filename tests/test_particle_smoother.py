"""The particle filter's FFBSm smoother against FFBSm written out in numpy (a double loop over
particles, per run and step) on a nonlinear model with inputs, and against its Monte Carlo
limit, the Rauch–Tung–Striebel smoother of a linear Gaussian model."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from scipy.stats import multivariate_normal
from test_smoother import DT, GRAVITY, _swing

import difffilter as df

F64 = torch.float64


def _pendulum():
    Q = torch.diag(torch.tensor([1e-3, 4e-3], dtype=F64))
    return df.NonlinearGaussianModel(
        _swing, lambda x: torch.sin(x[..., :1]), Q, torch.tensor([[0.05]], dtype=F64),
        torch.tensor([0.8, 0.0], dtype=F64), torch.diag(torch.tensor([0.1, 0.2], dtype=F64)),
        dim_u=1,
    )  # fmt: skip


def test_the_smoother_is_ffbsm_written_out():
    """w_{k|T}^i = w_k^i Σ_j w_{k+1|T}^j f(x_{k+1}^j | x_k^i) / Σ_l w_k^l f(x_{k+1}^j | x_k^l),
    by a double loop in numpy with scipy's Gaussian density, on the filter's particles."""
    model = _pendulum()
    gen = torch.Generator().manual_seed(3)
    us = 0.3 * torch.randn(2, 6, 1, dtype=F64, generator=gen)
    _, ys, _ = model.simulate(6, (2,), us, generator=gen)
    pf = df.particle_filter(model, ys, us, num_particles=7, return_particles=True,
                            generator=torch.Generator().manual_seed(4))  # fmt: skip
    out = df.particle_smoother(model, pf, us)
    Q = model.process_noise.cov.numpy()

    def f(x, u):
        return np.array([x[0] + DT * x[1], x[1] - DT * GRAVITY * np.sin(x[0]) + DT * u[0]])

    for r in range(2):
        X, W = pf.particles[r].numpy(), pf.log_weights[r].exp().numpy()
        smooth = [None] * 6
        smooth[5] = W[5]
        for k in range(4, -1, -1):
            dens = np.array([[multivariate_normal.pdf(X[k + 1, j], f(X[k, i], us[r, k + 1].numpy()), Q)
                              for j in range(7)] for i in range(7)])  # fmt: skip
            norm = W[k] @ dens  # [j]: Σ_l w_k^l f(x_{k+1}^j | x_k^l)
            smooth[k] = W[k] * (dens @ (smooth[k + 1] / norm))
        want = np.stack(smooth)
        np.testing.assert_allclose(out.log_weights[r].exp().numpy(), want, rtol=1e-10, atol=1e-14)
        means = np.einsum("tn,tnd->td", want, X)
        np.testing.assert_allclose(out.means[r].numpy(), means, rtol=1e-10, atol=1e-12)
        dev = X - means[:, None]
        covs = np.einsum("tn,tni,tnj->tij", want, dev, dev)
        np.testing.assert_allclose(out.covs[r].numpy(), covs, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(out.log_weights[:, -1], pf.log_weights[:, -1], rtol=0, atol=0)


def test_the_smoother_converges_to_the_rts_smoother_on_a_linear_model(monkeypatch):
    """A linear Gaussian model: the FFBSm means approach the RTS smoother's as N grows
    (the Monte Carlo limit), further from the filtered ones than their own error; the run
    chunks (a small chunk: several of them) change nothing."""
    import importlib

    module = importlib.import_module("difffilter.particle_smoothing")

    F = torch.tensor([[0.9, 0.2], [-0.1, 0.85]], dtype=F64)
    model = df.LinearGaussianModel(F, torch.tensor([[1.0, 0.0]], dtype=F64),
                                   torch.diag(torch.tensor([0.05, 0.08], dtype=F64)),
                                   torch.tensor([[0.3]], dtype=F64), torch.zeros(2, dtype=F64),
                                   torch.eye(2, dtype=F64))  # fmt: skip
    _, ys, _ = model.simulate(20, (4,), generator=torch.Generator().manual_seed(5))
    rts = df.kalman_smoother(model, ys)
    sd = rts.covs.diagonal(dim1=-2, dim2=-1).sqrt()
    gaps = {}
    for n in (100, 800):
        pf = df.particle_filter(model, ys, num_particles=n, return_particles=True,
                                generator=torch.Generator().manual_seed(6))  # fmt: skip
        out = df.particle_smoother(model, pf)
        gaps[n] = float(((out.means - rts.means) / sd).abs().mean())
        if n == 800:
            filtered_gap = float(((pf.means - rts.means) / sd).abs().mean())
            covs = out.covs.diagonal(dim1=-2, dim2=-1) / rts.covs.diagonal(dim1=-2, dim2=-1)
            monkeypatch.setattr(module, "CHUNK_ELEMENTS", n * n * 2 * 3)  # 3 runs a chunk
            chunked = df.particle_smoother(model, pf)
            torch.testing.assert_close(chunked.log_weights, out.log_weights, rtol=1e-12, atol=1e-12)
    assert gaps[800] < 0.08 and gaps[800] < gaps[100] / 2  # (about 1/√N)
    assert filtered_gap > 4 * gaps[800]  # the smoother moved the estimates towards the RTS's
    assert float((covs.mean() - 1).abs()) < 0.1


def test_the_smoother_says_what_it_needs():
    model = _pendulum()
    gen = torch.Generator().manual_seed(7)
    us = torch.zeros(1, 4, 1, dtype=F64)
    _, ys, _ = model.simulate(4, (1,), us, generator=gen)
    plain = df.particle_filter(model, ys, us, num_particles=5, generator=gen)
    with pytest.raises(ValueError, match="run the particle filter with return_particles=True"):
        df.particle_smoother(model, plain, us)
    with pytest.raises(TypeError, match="filtered must be the ParticleFilterResult"):
        df.particle_smoother(model, df.extended_kalman_filter(model, ys, us), us)
    kept = df.particle_filter(model, ys, us, num_particles=5, generator=gen, return_particles=True)
    with pytest.raises(ValueError, match=r"us must have T = 4 steps, one per measurement"):
        df.particle_smoother(model, kept, us[:, :2])

    class Multiplicative(df.NonlinearGaussianModel):
        def sample_transition(self, x, u, k, generator=None):
            return self.transition(x, u, k) * 1.01

    odd = Multiplicative(_swing, lambda x: torch.sin(x[..., :1]), model.process_noise.cov,
                         model.measurement_noise.cov, model.initial.mean, model.initial.cov,
                         dim_u=1)  # fmt: skip
    with pytest.raises(TypeError, match="draws its transition its own way"):
        df.particle_smoother(odd, kept, us)
    assert {"particle_smoother", "ParticleSmootherResult"} <= set(df.__all__)


def test_zero_weights_of_a_bounded_noise_weigh_nothing_with_finite_gradients():
    """From a review: with a bounded process noise (UniformBox) and no resampling most
    filtering weights are 0 (log −inf) and particles of step k + 1 that no weighted particle
    reaches have a zero denominator: 36 of 40 smoothed means were NaN, and any −inf weight
    made the gradients NaN. Against FFBSm in numpy, a term 0/0 taken as 0; an empty batch;
    a filter started at k = 3 (``start``)."""
    import dataclasses

    from difffilter.noise import UniformBox

    F = torch.tensor([[1.0, 0.1], [0.0, 1.0]], dtype=F64)
    model = df.LinearGaussianModel(F, torch.tensor([[1.0, 0.0]], dtype=F64),
                                   0.01 * torch.eye(2, dtype=F64), 0.04 * torch.eye(1, dtype=F64),
                                   torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64))  # fmt: skip
    half = 0.1
    model.process_noise = UniformBox(
        torch.full((2,), -half, dtype=F64), torch.full((2,), half, dtype=F64)
    )
    model.measurement_noise = UniformBox(
        torch.full((1,), -0.3, dtype=F64), torch.full((1,), 0.3, dtype=F64)
    )
    _, ys, _ = model.simulate(6, (2,), generator=torch.Generator().manual_seed(0))
    pf = df.particle_filter(model, ys, num_particles=30, return_particles=True, ess_threshold=0.0,
                            generator=torch.Generator().manual_seed(1))  # fmt: skip
    assert bool(torch.isinf(pf.log_weights).any())
    parts = pf.particles.clone().requires_grad_(True)
    log_w = pf.log_weights.clone().requires_grad_(True)
    out = df.particle_smoother(model, dataclasses.replace(pf, particles=parts, log_weights=log_w))
    assert not bool(out.means.isnan().any())
    out.means.sum().backward()
    assert not bool(parts.grad.isnan().any() or log_w.grad.isnan().any())
    Fn = F.numpy()
    for r in range(2):
        X, W = pf.particles[r].numpy(), pf.log_weights[r].exp().numpy()
        smooth = [None] * 6
        smooth[5] = W[5]
        for k in range(4, -1, -1):
            ahead = X[k] @ Fn.T  # [i, dx]
            inside = (np.abs(X[k + 1][None, :, :] - ahead[:, None, :]) <= half).all(-1)
            dens = inside / (2 * half) ** 2  # [i, j]
            norm = W[k] @ dens
            ratio = np.divide(smooth[k + 1], norm, out=np.zeros_like(norm), where=norm > 0)
            smooth[k] = W[k] * (dens @ ratio)
            smooth[k] = smooth[k] / smooth[k].sum()
        np.testing.assert_allclose(out.log_weights[r].exp().detach().numpy(), np.stack(smooth),
                                   rtol=1e-9, atol=1e-12)  # fmt: skip
    empty = df.particle_filter(model, ys[:0], num_particles=5, return_particles=True,
                               generator=torch.Generator().manual_seed(2))  # fmt: skip
    assert df.particle_smoother(model, empty).means.shape == (0, 6, 2)
    with pytest.raises(ValueError, match="start must be an integer >= 0"):
        df.particle_smoother(model, pf, start=-1)


def test_each_backward_step_reads_the_noise_at_its_own_k():
    """x_{k+1} = f(x_k, u_k, k) + w_k: the step from the stored index t (x_{t+1}) reads k = t + 1,
    and t + 1 + start for a filter started at step ``start`` (a review: a time-varying model
    was read at the wrong k)."""
    model = _pendulum()
    us = torch.zeros(1, 5, 1, dtype=F64)
    _, ys, _ = model.simulate(5, (1,), us, generator=torch.Generator().manual_seed(9))
    pf = df.particle_filter(model, ys, us, num_particles=6, return_particles=True,
                            generator=torch.Generator().manual_seed(10))  # fmt: skip
    read = []
    original = model.process_noise_at

    def recording(k):
        read.append(k)
        return original(k)

    model.process_noise_at = recording
    df.particle_smoother(model, pf, us)
    df.particle_smoother(model, dataclasses.replace(pf, start=None), us, start=3)
    assert read == [4, 3, 2, 1, 7, 6, 5, 4]


def test_the_smoother_starts_where_the_filter_started():
    """A filter run from a carry of step k = 3 records it (``start``), and the smoother reads
    the model at k = 4, … by default: left at 0 it had read a time-varying noise at the wrong
    steps (2.7 sd off, a trial). A ``start`` that contradicts the record is refused."""
    model = _pendulum()
    us = torch.zeros(2, 5, 1, dtype=F64)
    _, ys, _ = model.simulate(5, (2,), us, generator=torch.Generator().manual_seed(9))
    gens = df.Generators.of(torch.Generator().manual_seed(10))
    carry = df.ParticleFilter(6).init(model, (2,), gens)._replace(k=3)
    pf = df.particle_filter(model, ys, us, num_particles=6, return_particles=True,
                            initial_state=carry, generator=gens)  # fmt: skip
    assert pf.start == 3
    assert df.particle_filter(model, ys, us, num_particles=6).start == 0
    read = []
    original = model.process_noise_at
    model.process_noise_at = lambda k: read.append(k) or original(k)
    recorded = df.particle_smoother(model, pf, us)
    assert read == [7, 6, 5, 4]
    told = df.particle_smoother(model, dataclasses.replace(pf, start=None), us, start=3)
    torch.testing.assert_close(recorded.log_weights, told.log_weights, rtol=0, atol=0)
    with pytest.raises(ValueError, match=r"start=0 but the particle filter started from k = 3"):
        df.particle_smoother(model, pf, us, start=0)
    assert df.particle_smoother(model, pf, us, start=3).means.shape == (2, 5, 2)
