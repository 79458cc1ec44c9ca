"""A bounds trial's findings: the posterior CRB inverted the model's ``Q``, ``R`` and ``P₀``
as they came (a covariance written in place after the model was built: a negated ``Q``
gave a "bound" of negative variances, a negated ``R`` a negative-definite information, NaN
an all-NaN bound, where the Kalman filter refuses the model); ``nees`` checked only the
covariances whose solve came back negative (``diag(1, −1)`` gave 0.99 for ``e = (1, 0.1)``);
``nees`` and ``whiteness`` took an asymmetric covariance (read as one triangle), which the
NIS refuses."""

from __future__ import annotations

import pytest
import torch

import difffilter as df
from difffilter.bounds import gaussian_information
from difffilter.consistency import nees, whiteness

F64 = torch.float64


def _model():
    F = torch.tensor([[1.0, 0.1], [0.0, 1.0]], dtype=F64)
    H = torch.tensor([[1.0, 0.0], [0.5, 1.0]], dtype=F64)
    R = torch.tensor([[0.5, 0.2], [0.2, 0.4]], dtype=F64)
    eye = torch.eye(2, dtype=F64)
    model = df.LinearGaussianModel(F, H, 0.1 * eye, R, torch.zeros(2, dtype=F64), eye)
    xs, _, x0 = model.simulate(5, (2,), generator=torch.Generator().manual_seed(0))
    return model, xs, x0


@pytest.mark.parametrize(
    ("where", "write", "message"),
    [("process", lambda c: c.mul_(-1.0), r"process_cov\(0\) must be positive definite"),
     ("process", lambda c: c.fill_(float("nan")), r"process_cov\(0\) contains NaN"),
     ("measurement", lambda c: c.mul_(-1.0), r"measurement noise covariance R .* must be "
                                             r"positive definite"),
     ("measurement", lambda c: c[0, 0].fill_(float("nan")), "R .* contains NaN"),
     ("initial", lambda c: c.mul_(-1.0), r"initial.cov must be positive definite"),
     ("initial", lambda c: c.fill_(float("inf")), r"initial.cov contains NaN or Inf")],
)  # fmt: skip
def test_the_pcrb_refuses_a_covariance_written_in_place_out_of_definiteness(where, write, message):
    model, xs, x0 = _model()
    cov = {"process": model.process_noise.cov, "measurement": model.measurement_noise.cov,
           "initial": model.initial.cov}[where]  # fmt: skip
    with torch.no_grad():
        write(cov)
    with pytest.raises(ValueError, match=message):
        df.posterior_crb(model, xs, x0)


def test_the_pcrb_of_a_covariance_written_in_place_and_still_definite_is_the_kfs():
    model, xs, x0 = _model()
    with torch.no_grad():
        model.process_noise.cov.mul_(3.0)  # written in place, still a covariance: followed
    bound = df.posterior_crb(model, xs, x0).bound
    ys = torch.zeros(1, 5, 2, dtype=F64)  # the KF's covariances do not depend on the data
    torch.testing.assert_close(bound, df.kalman_filter(model, ys).covs[0], rtol=1e-10,
                               atol=1e-12)  # fmt: skip


def test_gaussian_information_refuses_an_indefinite_r():
    R = torch.tensor([[0.5, 0.2], [0.2, 0.4]], dtype=F64)
    with pytest.raises(ValueError, match="must be positive definite"):
        gaussian_information(-R)
    torch.testing.assert_close(gaussian_information(R), torch.linalg.inv(R), rtol=1e-12, atol=0)


@pytest.mark.parametrize("error", [(1.0, 0.1), (0.1, 1.0)])
def test_nees_refuses_an_indefinite_covariance_whatever_the_error(error):
    cov = torch.diag(torch.tensor([1.0, -1.0], dtype=F64))
    with pytest.raises(ValueError, match="covs must be a covariance, positive semi-definite"):
        nees(torch.tensor(error, dtype=F64), cov)


def test_nees_and_whiteness_refuse_an_asymmetric_covariance():
    nu = torch.randn(20, 10, 2, dtype=F64, generator=torch.Generator().manual_seed(0))
    S = torch.tensor([[1.0, 0.9], [0.0, 1.0]], dtype=F64)
    with pytest.raises(ValueError, match="covs must be symmetric"):
        nees(nu[0, 0], S)
    with pytest.raises(ValueError, match="innovation_covs must be symmetric"):
        whiteness(nu, S, 1)


def test_nees_still_takes_a_collapsed_and_a_round_off_indefinite_cloud():
    # a particle cloud collapsed to one direction: rank one, its other eigenvalue round-off
    d = torch.tensor([[1.0, 2.0]], dtype=F64) * torch.linspace(-1, 1, 7, dtype=F64)[:, None]
    d = d + 1e-17 * torch.randn(7, 2, dtype=F64, generator=torch.Generator().manual_seed(1))
    cov = d.T @ d / 7
    value = nees(torch.tensor([1.0, 2.0], dtype=F64) * 0.3, cov)
    assert float(value) >= 0  # a number or +inf, neither an error nor NaN
    spd = torch.tensor([[2.0, 0.3], [0.3, 1.0]], dtype=F64)
    e = torch.tensor([0.4, -0.7], dtype=F64)
    torch.testing.assert_close(nees(e, spd), e @ torch.linalg.solve(spd, e), rtol=1e-14, atol=0)
