"""The particle filter's FFBSm smoother against FFBSm written out in numpy (a double loop over
particles, per run and step) on a nonlinear model with inputs, and against its Monte Carlo
limit, the Rauch–Tung–Striebel smoother of a linear Gaussian model."""

from __future__ import annotations

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

    module = importlib.import_module("difffilter.particle_smoother")

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
    with pytest.raises(ValueError, match=r"us must be the filter's inputs \[..., T = 4, du\]"):
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
