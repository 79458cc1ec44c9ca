"""Time-varying Gaussian noise written as the docs say (override ``process_cov(k)`` and
``measurement_cov(k)``, set ``time_varying``): simulation, the particle filters and the
Gaussian filters see one model. Before, ``simulate`` and the bootstrap PF kept the
constructor's ``Q`` and ``R`` while the Kalman filter read the overrides (a PF
log-likelihood of −44 to −51 against the KF's −77 on the model below)."""

from __future__ import annotations

import math

import pytest
import torch

import difffilter as df
from difffilter.noise import Gaussian

F64 = torch.float64


class _Growing(df.LinearGaussianModel):
    """``Q_k = (1 + k/10) Q``, ``R_k = 25 (1 + k/20) R``: the overrides alone."""

    time_varying = True

    def process_cov(self, k):
        return self.process_noise.cov * (1 + 0.1 * k)

    def measurement_cov(self, k):
        return self.measurement_noise.cov * 25.0 * (1 + 0.05 * k)


def _model(cls=_Growing):
    eye = torch.eye(2, dtype=F64)
    F = torch.tensor([[0.9, 0.1], [0.0, 0.8]], dtype=F64)
    H = torch.tensor([[1.0, 0.0]], dtype=F64)
    return cls(F, H, 0.1 * eye, torch.eye(1, dtype=F64), torch.zeros(2, dtype=F64), eye)


def test_the_noise_at_a_step_is_the_overridden_covariance():
    model = _model()
    for k in (0, 3, 17):
        assert isinstance(model.process_noise_at(k), Gaussian)
        torch.testing.assert_close(model.process_noise_at(k).cov, model.process_cov(k))
        torch.testing.assert_close(model.measurement_noise_at(k).cov, model.measurement_cov(k))
    plain = _model(df.LinearGaussianModel)  # no override: the modules themselves
    assert plain.process_noise_at(5) is plain.process_noise
    assert plain.measurement_noise_at(5) is plain.measurement_noise


def test_the_default_hooks_draw_and_weigh_with_the_overridden_covariance():
    model, k = _model(), 7
    x = torch.tensor([[0.3, -1.0], [2.0, 0.5]], dtype=F64)
    y = torch.tensor([[1.5], [-4.0]], dtype=F64)
    r_k = model.measurement_cov(k)
    expected = -0.5 * ((y - x[:, :1]) ** 2 / r_k[0, 0] + math.log(2 * math.pi) + r_k[0, 0].log())
    torch.testing.assert_close(model.measurement_log_prob(y, x, k), expected[:, 0])
    draw = model.sample_measurement(x, k, torch.Generator().manual_seed(3))
    eps = torch.randn(2, 1, generator=torch.Generator().manual_seed(3), dtype=F64)
    torch.testing.assert_close(draw, x[:, :1] + r_k[0, 0].sqrt() * eps)
    step = model.sample_transition(x, None, k, torch.Generator().manual_seed(4))
    eps = torch.randn(2, 2, generator=torch.Generator().manual_seed(4), dtype=F64)
    chol = torch.linalg.cholesky(model.process_cov(k))
    torch.testing.assert_close(step, x @ model.F.mT + eps @ chol.mT)


def test_simulate_draws_the_overridden_noise():
    model = _model()
    xs, ys, _ = model.simulate(40, (4000,), generator=torch.Generator().manual_seed(0))
    v = ys[..., 0] - xs[..., 0]  # v_k, k = 1 … 40: variance 25 (1 + k/20)
    expected = 25.0 * (1 + 0.05 * torch.arange(1, 41, dtype=F64))
    ratio = v.var(0) / expected
    # 4,000 draws a step: the sample variance's sd is sqrt(2/3999) = 2.2 %
    assert (ratio - 1).abs().max() < 0.1, ratio
    assert abs(float(ratio.mean()) - 1) < 0.02


@pytest.mark.parametrize("batch, proposal", [((4,), None), ((), None),
                                             ((4,), df.KalmanProposal())])  # fmt: skip
def test_the_particle_filter_converges_to_the_kalman_filter(batch, proposal):
    model = _model()
    _, ys, _ = model.simulate(30, batch, generator=torch.Generator().manual_seed(1))
    kf = df.kalman_filter(model, ys).log_likelihood
    kwargs = {} if proposal is None else {"proposal": proposal}
    pf = df.particle_filter(model, ys, num_particles=20000, **kwargs,
                            generator=torch.Generator().manual_seed(2)).log_likelihood  # fmt: skip
    # 20,000 particles, 30 steps: a Monte Carlo error of a few hundredths (the constructor's
    # R, the bug, was 25 to 32 nats off)
    torch.testing.assert_close(pf, kf, atol=0.3, rtol=0)


def test_the_online_one_run_particle_step_follows_the_overrides():
    """The lean one-run step (host arrays) reads the noise modules directly: it must step
    aside for a model whose covariances vary."""
    model = _model()
    _, ys, _ = model.simulate(30, (), generator=torch.Generator().manual_seed(5))
    pf = df.ParticleFilter(20000)
    carry = pf.init(model, (), generator=torch.Generator().manual_seed(6))
    total = torch.zeros((), dtype=F64)
    for y in ys:
        carry, out = pf.step(carry, y)
        total = total + out.log_likelihood
    kf = df.kalman_filter(model, ys).log_likelihood
    assert abs(float(total - kf)) < 0.3, (float(total), float(kf))


def test_a_covariance_that_cannot_be_drawn_from_is_named_with_its_method_and_step():
    class Singular(_Growing):
        def process_cov(self, k):  # noise on the second state only: PSD, singular
            return torch.diag(torch.tensor([0.0, 0.1 * (1 + k)], dtype=F64))

    model = _model(Singular)
    ys = torch.zeros(2, 5, 1, dtype=F64)
    df.kalman_filter(model, ys)  # the Kalman filter runs on it
    with pytest.raises(ValueError, match=r"Singular.process_cov\(0\) \(what simulate"):
        model.simulate(5, (2,))


def test_a_particle_filter_refuses_a_covariance_override_of_one_set_per_run():
    """A per-run Q from process_cov(k) was applied along the particles where N = B."""

    class PerRun(_Growing):
        def process_cov(self, k):
            return self.process_noise.cov * torch.tensor([1.0, 2.0, 3.0], dtype=F64).view(3, 1, 1)

    ys = torch.zeros(3, 5, 1, dtype=F64)
    with pytest.raises(ValueError, match=r"takes one model for all runs.*\(3,\)"):
        df.particle_filter(_model(PerRun), ys, num_particles=3)
