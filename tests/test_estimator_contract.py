"""The estimator contract, checked for every attack-aware filter and detector of difffilter.fdi.

Each estimator is ``(model, ys, us=None, *, mask=None, ...) -> EstimatorOutput``; the base
class runs it over batch shapes, dtypes, inputs, a Round-Robin mask and gradients.
"""

from __future__ import annotations

import pytest
import torch

import difffilter as df
from difffilter import fdi
from difffilter.estimator import EstimatorOutput

T, DX, DY = 12, 2, 2


def linear_model(dtype):
    return df.LinearGaussianModel(
        torch.tensor([[1.0, 0.1], [0.0, 0.95]], dtype=dtype),
        torch.eye(2, dtype=dtype),
        1e-2 * torch.eye(2, dtype=dtype),
        4e-2 * torch.eye(2, dtype=dtype),
        torch.zeros(2, dtype=dtype),
        torch.eye(2, dtype=dtype),
        B=torch.tensor([[0.0], [0.1]], dtype=dtype),
    )


def pf_kwargs(seed=0):
    return {"num_particles": 64, "generator": torch.Generator().manual_seed(seed)}


class EstimatorContract:
    """Subclasses define :meth:`run`; ``has_attack``: whether ``attack`` is estimated."""

    has_attack = False

    def run(self, model, ys, us=None, mask=None) -> EstimatorOutput:
        raise NotImplementedError

    def data(self, batch, dtype, seed=0):
        gen = torch.Generator().manual_seed(seed)
        ys = torch.randn(*batch, T, DY, generator=gen).to(dtype) * 0.3
        us = torch.randn(*batch, T, 1, generator=gen).to(dtype)
        return ys, us

    @pytest.mark.parametrize("batch", [(), (3,), (2, 3)])
    def test_batch_shapes(self, batch):
        ys, _ = self.data(batch, torch.float64)
        out = self.run(linear_model(torch.float64), ys)
        assert isinstance(out, EstimatorOutput)
        assert out.means.shape == (*batch, T, DX)
        assert out.detection.scores.shape == out.detection.alarms.shape == (*batch, T)
        assert out.detection.alarms.dtype == torch.bool
        if self.has_attack:
            assert out.attack.shape == (*batch, T, DY)
        if out.covs is not None:
            assert out.covs.shape == (*batch, T, DX, DX)

    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
    def test_dtype_follows_the_inputs(self, dtype):
        ys, _ = self.data((3,), dtype)
        out = self.run(linear_model(dtype), ys)
        assert out.means.dtype == dtype and bool(out.means.isfinite().all())

    def test_inputs_and_round_robin_mask(self):
        ys, us = self.data((3,), torch.float64)
        mask = torch.zeros(3, T, DY, dtype=torch.bool)
        mask[:, 0::2, 0] = True
        mask[:, 1::2, 1] = True
        model = linear_model(torch.float64)
        out = self.run(model, ys, us, mask)
        assert out.means.shape == (3, T, DX) and bool(out.means.isfinite().all())
        assert not torch.allclose(out.means, self.run(model, ys, None, mask).means)  # us is used
        garbage = torch.where(mask, ys, torch.full_like(ys, 1e6))  # unreceived entries unread
        torch.testing.assert_close(self.run(model, garbage, us, mask).means, out.means)

    def test_gradients_reach_the_measurements(self):
        ys, us = self.data((2,), torch.float64)
        ys.requires_grad_(True)
        out = self.run(linear_model(torch.float64), ys, us)
        (grad,) = torch.autograd.grad(out.means.square().sum(), ys)
        assert bool(grad.isfinite().all()) and float(grad.abs().sum()) > 0


class TestGatedKalmanChiSquare(EstimatorContract):
    def run(self, model, ys, us=None, mask=None):
        det = fdi.ChiSquareDetector(DY, 0.01)
        return fdi.gated_gaussian_filter(
            model, ys, us, mask=mask, detector=det, filter=df.KalmanFilter()
        )


class TestGatedEKFCusum(EstimatorContract):
    def run(self, model, ys, us=None, mask=None):
        return fdi.gated_extended_kalman_filter(
            model, ys, us, mask=mask, detector=fdi.CusumDetector(4.0, 8.0)
        )


class TestGatedUKF(EstimatorContract):
    def run(self, model, ys, us=None, mask=None):
        det = fdi.ChiSquareDetector(DY, 0.01)
        return fdi.gated_gaussian_filter(
            model, ys, us, mask=mask, detector=det, filter=df.UnscentedKalmanFilter()
        )


class TestPoAParticleFilter(EstimatorContract):
    def run(self, model, ys, us=None, mask=None):
        det = fdi.PoADetector(0.5, 0.5)
        return fdi.particle_filter_poa(model, ys, us, mask=mask, detector=det, **pf_kwargs())


class TestModifiedParticleFilter(EstimatorContract):
    has_attack = True

    def run(self, model, ys, us=None, mask=None):
        gamma = torch.full_like(ys, 0.2).detach()
        return fdi.modified_particle_filter(
            model,
            ys,
            us,
            mask=mask,
            detector=fdi.PoADetector(0.5, 0.5),
            gamma_hat=gamma,
            **pf_kwargs(),
        )


class TestModifiedParticleFilterWithEstimator(EstimatorContract):
    has_attack = True

    def run(self, model, ys, us=None, mask=None):
        est = fdi.BiasAttackEstimator(DY, 0.9, dtype=ys.dtype)
        return fdi.modified_particle_filter(
            model,
            ys,
            us,
            mask=mask,
            detector=fdi.PoADetector(0.5, 0.5),
            gamma_hat=est,
            **pf_kwargs(),
        )


class TestMixtureLikelihoodParticleFilter(EstimatorContract):
    def run(self, model, ys, us=None, mask=None):
        lik = fdi.DeceptionMixtureLikelihood(
            0.3, fdi.BiasDeception(torch.full((DY,), 0.5, dtype=ys.dtype))
        )
        return fdi.mixture_likelihood_particle_filter(
            model, ys, us, mask=mask, likelihood=lik, **pf_kwargs()
        )


class TestZhangAdaptiveKalmanFilter(EstimatorContract):
    """The attack has the input's dimension (actuator channel), not ``DY``: checked here."""

    def run(self, model, ys, us=None, mask=None):
        out = fdi.adaptive_kalman_filter(model, ys, us, mask=mask, forgetting=0.9)
        assert out.attack.shape == out.means.shape[:-1] + (model.dim_u,)
        return out


class TestAdaptiveParticleFilter(EstimatorContract):
    def run(self, model, ys, us=None, mask=None):
        out = fdi.adaptive_particle_filter(
            model, ys, us, mask=mask, num_particles=16, generator=torch.Generator().manual_seed(0)
        )
        assert out.attack.shape == out.means.shape[:-1] + (model.dim_u,)
        return out


def test_a_stacked_output_keeps_the_steps_innovations_in_extras():
    """A Kalman filter's stacked output holds each step's innovation ``ν_k = y_k − H F x̂_{k−1}``
    (``x̂_0`` the prior mean; no input) in ``extras["innovations"]``, checked by hand in
    float64; asking the output for a step's field names where it went (a trial met a bare
    AttributeError on ``out.innovation``)."""
    model = linear_model(torch.float64)
    ys = torch.randn(3, T, DY, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    from difffilter.loop import open_loop

    out = open_loop(df.KalmanFilter(), model, ys)
    F, H = model.F, model.H
    previous = torch.cat([model.initial.mean.expand(3, 1, DX), out.means[:, :-1]], dim=1)
    expected = ys - previous @ F.T @ H.T
    torch.testing.assert_close(out.extras["innovations"], expected, rtol=1e-12, atol=1e-12)
    assert out.extras["innovation_covs"].shape == (3, T, DY, DY)
    with pytest.raises(AttributeError, match=r"stacked in extras\['innovations'\]"):
        out.innovation  # noqa: B018
    with pytest.raises(AttributeError, match=r"stacked in \.means \[\.\.\., T, \.\.\.\]"):
        out.mean  # noqa: B018  (a docs trial: the step's name, on the stacked output)
    with pytest.raises(AttributeError, match=r"stacked in \.covs"):
        out.cov  # noqa: B018
    with pytest.raises(AttributeError, match="has no attribute 'nope'"):
        out.nope  # noqa: B018


def test_the_init_functions_take_a_batch_shape_as_the_estimators_init_does():
    """A docs trial: ``df.gaussian_init(model, 32)`` met "'int' object is not iterable"
    while ``KalmanFilter().init(model, 32)`` took the int; the function forms now read a
    batch shape as ``init`` does, with its error for a bad one."""
    model = linear_model(torch.float64)
    assert df.gaussian_init(model, 32).mean.shape == (32, model.dim_x)
    assert df.gaussian_init(model, (2, 3)).mean.shape == (2, 3, model.dim_x)
    gen = torch.Generator().manual_seed(0)
    assert df.particle_init(model, 10, 4, gen).particles.shape == (4, 10, model.dim_x)
    assert df.gaussian_init(model, 0).mean.shape == (0, model.dim_x)  # no runs: as before
    for bad in (-1, (2, -1), "32", 2.5):
        with pytest.raises(ValueError, match="batch_shape must be a tuple of integers >= 0"):
            df.gaussian_init(model, bad)
        with pytest.raises(ValueError, match="batch_shape must be a tuple of integers >= 0"):
            df.particle_init(model, 10, bad, gen)
