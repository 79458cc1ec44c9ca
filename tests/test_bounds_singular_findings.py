"""The PCRB of a model whose P_0 or R became singular after construction (written in place,
which the constructors cannot see): named, not torch's "linalg.inv: The diagonal element 1
is zero" (noticed in an earlier red-team trial, fixed 2026-12-07; each failed before)."""

from __future__ import annotations

import pytest
import torch

import difffilter as df
from difffilter.bounds import gaussian_information

F64 = torch.float64
EYE = torch.eye(2, dtype=F64)


def _model():
    return df.LinearGaussianModel(EYE, torch.tensor([[1.0, 0.0]], dtype=F64), 0.1 * EYE,
                                  torch.eye(1, dtype=F64), torch.zeros(2, dtype=F64), EYE)  # fmt: skip


def test_a_singular_prior_covariance_is_named_by_the_pcrb():
    model = _model()
    xs, _, _ = model.simulate(5, (16,), generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        model.initial.cov[1, 1] = 0.0
    with pytest.raises(ValueError, match=r"initial.cov is singular: the PCRB starts from"):
        df.posterior_crb(model, xs, torch.zeros(16, 2, dtype=F64))


@pytest.mark.parametrize("mask", [None, torch.tensor([True, True])])
def test_a_singular_measurement_covariance_is_named(mask):
    R = torch.tensor([[1.0, 1.0], [1.0, 1.0]], dtype=F64)
    with pytest.raises(ValueError, match="measurement noise covariance R .* is singular"):
        gaussian_information(R, mask)
    # a lost entry's part is not inverted: the received one's alone
    torch.testing.assert_close(gaussian_information(R, torch.tensor([True, False])),
                               torch.tensor([[1.0, 0.0], [0.0, 0.0]], dtype=F64))  # fmt: skip
