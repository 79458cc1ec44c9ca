"""Findings of a trial of time indices across the estimators, each checked against the
steps' own convention or the Kalman filter."""

from __future__ import annotations

import torch

import difffilter as df
from difffilter.fdi.modified_pf import modified_particle_filter
from difffilter.fdi.poa import PoADetector
from difffilter.noise import Gaussian

D = torch.float64
F = torch.tensor([[0.9, 0.2], [0.0, 0.8]], dtype=D)


def _model(B=None) -> df.LinearGaussianModel:
    eye = torch.eye(2, dtype=D)
    return df.LinearGaussianModel(F, eye, 0.01 * eye, 0.1 * eye, torch.zeros(2, dtype=D),
                                  0.5 * eye, B=B)  # fmt: skip


def test_a_modified_pf_continued_from_a_state_reads_gamma_hat_aligned_with_ys():
    """From a carry at k0 > 0 the steps had read γ̂ at the absolute step k − 1 of a table
    the wrapper requires aligned with ``ys``: k0 rows late, then "gamma_hat has 5 rows and
    step 6 needs row k"; neither layout ran. Now the aligned table compensates ``ys[t]``
    with ``γ̂[t]``."""
    model = _model(torch.tensor([[1.0], [0.5]], dtype=D))
    T, k0 = 8, 3
    gen = torch.Generator().manual_seed(0)
    us = torch.randn(1, T, 1, generator=gen, dtype=D)
    _, ys, _ = model.simulate(T, (1,), us=us, generator=gen)
    gamma = 0.5 * torch.arange(1, T + 1, dtype=D)[:, None].expand(T, 2)
    pf = df.ParticleFilter(200)
    carry = pf.init(model, (1,), torch.Generator().manual_seed(1))
    for t in range(k0):
        carry, _ = pf.step(carry, ys[:, t], us[:, t])
    out = modified_particle_filter(
        model, (ys + gamma)[:, k0:], us[:, k0:], num_particles=200,
        detector=PoADetector(0.0, 0.5), gamma_hat=gamma[None, k0:], initial_state=carry,
        generator=torch.Generator().manual_seed(2),
    )  # fmt: skip
    assert torch.equal(out.extras["gamma_hat"][0], gamma[k0:])


def test_the_fused_modified_pf_from_a_weighted_state_is_the_steps_filter():
    """The fused path took the state's particles and dropped its weights (and its k): a
    weighted set filtered as if equally weighted, 0.27 off the steps' means. It now leaves
    such a state to the steps: the same numbers."""
    model = _model()
    T, N = 4, 2000
    _, ys, _ = model.simulate(T, (1,), generator=torch.Generator().manual_seed(0))
    particles = model.sample_initial((1, N), torch.Generator().manual_seed(5))
    state = df.ParticleState(particles, torch.log_softmax(3.0 * particles[..., 0], -1), 0)
    means = [
        modified_particle_filter(
            model, ys, num_particles=N, detector=PoADetector(1e6, 0.5),
            gamma_hat=torch.zeros(1, T, 2, dtype=D), initial_state=state,
            generator=torch.Generator().manual_seed(3),
            resample_generator=torch.Generator().manual_seed(4), fused=fused,
        ).means
        for fused in (False, True)
    ]  # fmt: skip
    assert torch.equal(means[0], means[1])


class _GrowingQ(df.StateSpaceModel):
    """A linear model whose class overrides ``process_cov(k)`` (``time_varying`` False)."""

    dim_x, dim_y, dim_u = 2, 2, 0

    def __init__(self):
        super().__init__()
        eye = torch.eye(2, dtype=D)
        self.initial = Gaussian(torch.zeros(2, dtype=D), 0.5 * eye)
        self.process_noise = Gaussian(torch.zeros(2, dtype=D), 0.01 * eye)
        self.measurement_noise = Gaussian(torch.zeros(2, dtype=D), 0.1 * eye)

    def transition(self, x, u, k):
        return x @ F.T

    def observe(self, x, k):
        return x

    def process_cov(self, k):
        return (0.01 + 0.5 * k) * torch.eye(2, dtype=D)


def test_the_pcrb_reads_an_overridden_process_cov_at_every_step():
    """The bound had read ``process_cov(0)`` at every step where simulate and the filters
    read ``process_cov(k)``: 4.5 times below the EKF's covariance on a linear model, where
    the two are equal."""
    model = _GrowingQ()
    xs, ys, x0 = model.simulate(6, generator=torch.Generator().manual_seed(0))
    ekf = df.extended_kalman_filter(model, ys)
    bound = df.posterior_crb(model, xs[None], x0[None]).bound
    torch.testing.assert_close(bound, ekf.covs, rtol=0, atol=1e-10)
