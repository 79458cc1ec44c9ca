"""Contract tests: every filter, every batch shape, both float dtypes, gradients.

A base class defines the contract (gpytorch style); each filter is a subclass that says
how to run it. Batch shapes (), [3], [2, 3]; float32 and float64.
"""

from __future__ import annotations

import pytest
import torch
from conftest import constant_velocity

import difffilter as df
from difffilter import resampling
from difffilter.particle import KalmanProposal, particle_filter

BATCH_SHAPES = [(), (3,), (2, 3)]
DTYPES = [torch.float32, torch.float64]
T = 6


class FilterContract:
    """Subclasses implement ``run(model, ys, us, mask)``."""

    particle = False

    def run(self, model, ys, us=None, mask=None):
        raise NotImplementedError

    @pytest.mark.parametrize("batch", BATCH_SHAPES, ids=str)
    @pytest.mark.parametrize("dtype", DTYPES, ids=str)
    def test_shapes_dtype_and_finiteness(self, batch, dtype):
        model = constant_velocity(dtype=dtype, with_input=True)
        g = torch.Generator().manual_seed(0)
        us = torch.randn(*batch, T, 1, dtype=dtype, generator=g)
        _, ys, _ = model.simulate(T, batch, us=us, generator=g)
        res = self.run(model, ys, us)
        assert res.means.shape == (*batch, T, 4)
        assert res.covs.shape == (*batch, T, 4, 4)
        assert res.innovations.shape == (*batch, T, 2)
        assert res.innovation_covs.shape == (*batch, T, 2, 2)
        assert res.log_likelihood.shape == batch
        assert res.log_likelihood_increments.shape == (*batch, T)
        for t in (res.means, res.covs, res.innovations, res.innovation_covs, res.log_likelihood):
            assert t.dtype == dtype
            assert torch.isfinite(t).all()
        # covariances symmetric positive semidefinite
        torch.testing.assert_close(res.covs, res.covs.transpose(-1, -2))
        assert (torch.linalg.eigvalsh(res.covs.double()) > -1e-6).all()
        if self.particle:
            assert res.ess.shape == (*batch, T)

    @pytest.mark.parametrize("batch", BATCH_SHAPES, ids=str)
    def test_mask_shapes(self, batch):
        model = constant_velocity()
        g = torch.Generator().manual_seed(1)
        _, ys, _ = model.simulate(T, batch, generator=g)
        mask = torch.rand(*batch, T, 2, generator=g) > 0.3
        res = self.run(model, ys, mask=mask)
        assert res.means.shape == (*batch, T, 4)
        assert torch.isfinite(res.log_likelihood).all()

    def test_gradients_flow_to_model_parameters(self):
        base = constant_velocity()
        F = torch.nn.Parameter(base.F.clone())
        log_r = torch.nn.Parameter(torch.zeros(()))
        model = df.LinearGaussianModel(
            F,
            base.H,
            base.process_noise.cov,
            base.measurement_noise.cov * torch.exp(log_r),
            base.initial.mean,
            base.initial.cov,
        )
        _, ys, _ = base.simulate(T, (2,), generator=torch.Generator().manual_seed(2))
        res = self.run(model, ys)
        (res.log_likelihood.sum() + res.means.sum()).backward()
        assert F.grad is not None and torch.isfinite(F.grad).all() and F.grad.abs().sum() > 0
        assert log_r.grad is not None and torch.isfinite(log_r.grad)


class TestKalmanSequential(FilterContract):
    def run(self, model, ys, us=None, mask=None):
        return df.kalman_filter(model, ys, us, mask=mask, method="sequential")


class TestKalmanParallel(FilterContract):
    def run(self, model, ys, us=None, mask=None):
        return df.kalman_filter(model, ys, us, mask=mask, method="parallel")


class TestExtended(FilterContract):
    def run(self, model, ys, us=None, mask=None):
        return df.extended_kalman_filter(model, ys, us, mask=mask)


class TestUnscented(FilterContract):
    def run(self, model, ys, us=None, mask=None):
        return df.unscented_kalman_filter(model, ys, us, mask=mask)


class TestBootstrapParticle(FilterContract):
    particle = True

    def run(self, model, ys, us=None, mask=None):
        return particle_filter(
            model, ys, us, mask=mask, num_particles=64, generator=torch.Generator().manual_seed(0)
        )


class TestKalmanProposalParticle(FilterContract):
    particle = True

    def run(self, model, ys, us=None, mask=None):
        return particle_filter(
            model,
            ys,
            us,
            mask=mask,
            num_particles=64,
            proposal=KalmanProposal(),
            resampler=resampling.Soft(0.5),
            generator=torch.Generator().manual_seed(0),
        )


class TestOptimalTransportParticle(FilterContract):
    particle = True

    def run(self, model, ys, us=None, mask=None):
        return particle_filter(
            model,
            ys,
            us,
            mask=mask,
            num_particles=32,
            resampler=resampling.OptimalTransport(),
            ess_threshold=1.0,
            generator=torch.Generator().manual_seed(0),
        )
