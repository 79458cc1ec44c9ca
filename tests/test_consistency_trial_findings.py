"""The consistency tests (a red-team trial, 2026-12-07; each test failed before its fix)."""

from __future__ import annotations

import math

import pytest
import torch

import difffilter as df
from difffilter.consistency import ensemble_test, nees, whiteness
from difffilter.particle import weighted_moments

F64 = torch.float64


def test_the_nees_of_a_cloud_collapsed_to_round_off_is_huge_never_negative():
    """A cloud of two particles has a rank-one covariance whose other eigenvalue is a
    round-off of either sign: the solve came back negative (down to −4.6e22) in 632 of
    2,000 clouds. Truth: ``eᵀP⁻¹e ≥ 0``; a direction P does not hold gets +inf."""
    g = torch.Generator().manual_seed(0)
    parts = (
        torch.randn(2000, 2, 2, generator=g, dtype=F64) * torch.tensor([1.0, 3.0], dtype=F64) + 5
    )
    _, cov = weighted_moments(parts, torch.randn(2000, 2, generator=g, dtype=F64))
    e = torch.randn(2000, 2, generator=g, dtype=F64)
    value = nees(e, cov)
    assert bool((value >= 0).all())
    assert not bool(value.isnan().any())
    # a positive definite P keeps its NEES, the solve's
    A = torch.randn(2000, 2, 2, generator=g, dtype=F64)
    spd = A @ A.mT + 0.1 * torch.eye(2, dtype=F64)
    want = (e.unsqueeze(-2) @ torch.linalg.solve(spd, e.unsqueeze(-1))).flatten()
    assert torch.equal(nees(e, spd), want)


def test_the_nees_of_a_particle_filter_that_collapses_is_never_nan():
    """A particle filter on a nearly noise-free sensor (R = 1e-6, N = 10): covariances down
    to 1e-323, whose solve overflowed to NaN (48 of 15,000) or came back negative (1,465);
    the mean over runs and steps, the robot reports' ``nees``, read NaN."""
    F = torch.tensor([[1.0, 0.1], [0.0, 1.0]], dtype=F64)
    model = df.LinearGaussianModel(F, torch.tensor([[1.0, 0.0]], dtype=F64),
                                   1e-2 * torch.eye(2, dtype=F64), torch.tensor([[1e-6]], dtype=F64),
                                   torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64))  # fmt: skip
    xs, ys, _ = model.simulate(30, (500,), generator=torch.Generator().manual_seed(0))
    out = df.particle_filter(
        model, ys, num_particles=10, generator=torch.Generator().manual_seed(1)
    )
    value = nees(xs - out.means, out.covs)
    assert not bool(value.isnan().any()) and bool((value >= 0).all())
    assert float(value.mean()) == math.inf


def test_an_indefinite_covariance_is_refused_by_the_nees():
    """``diag(1, −1)`` with ``e = (0, 1)`` gave −1."""
    with pytest.raises(ValueError, match="positive semi-definite"):
        nees(torch.tensor([0.0, 1.0], dtype=F64), torch.diag(torch.tensor([1.0, -1.0], dtype=F64)))


def _ar1(runs=50, steps=40, phi=0.9):
    g = torch.Generator().manual_seed(3)
    z = torch.randn(runs, steps, 1, generator=g, dtype=F64)
    for k in range(1, steps):
        z[:, k] = phi * z[:, k - 1] + math.sqrt(1 - phi**2) * z[:, k]
    return z, torch.eye(1, dtype=F64)


def test_whiteness_refuses_a_diverged_runs_innovations():
    """Innovations correlated at 0.9 (rejected at every step) with one run NaN from step 3:
    ρ̄ NaN at 37 of 39 steps, which ``|ρ̄| > bound`` reads as white (5 % rejected)."""
    z, S = _ar1()
    rho, bound = whiteness(z, S)
    assert bool((rho.abs() > bound).all())
    z[0, 3:] = math.nan
    with pytest.raises(ValueError, match="innovations contains NaN or Inf"):
        whiteness(z, S)


def test_whiteness_of_huge_innovations_is_their_cosine():
    """Innovations of 1e160 overflowed the sums of squares (inf/inf = NaN); the cosine does
    not depend on their scale."""
    z, S = _ar1()
    rho, _ = whiteness(z, S)
    huge, _ = whiteness(z * 1e160, S)
    torch.testing.assert_close(huge, rho, rtol=1e-12, atol=0)


def test_an_infinite_dof_is_refused_by_the_ensemble_test():
    """A tensor dof holding inf passed both checks, and its step's bounds came back NaN."""
    stat = torch.ones(4, 3, dtype=F64)
    dof = torch.full((4, 3), 2.0, dtype=F64)
    dof[1, 2] = math.inf
    with pytest.raises(ValueError, match="finite and >= 0"):
        ensemble_test(stat, dof)


def test_a_negative_statistic_is_refused_by_the_ensemble_test():
    """NEES and NIS are squared norms: a negative value (a covariance that is no covariance)
    had been averaged with the others, and a run of -3 beside runs of 5 read as consistent
    (noted in an earlier session)."""
    stat = torch.full((4, 3), 2.0, dtype=torch.float64)
    assert ensemble_test(stat, 2).outside == 0.0
    stat[0, 1] = -3.0
    with pytest.raises(ValueError, match=r"statistic must be >= 0 .* got -3"):
        ensemble_test(stat, 2)
