"""Findings of a trial of the filters at the edges of valid input (each failed before its
fix)."""

from __future__ import annotations

import pytest
import torch

import difffilter as df
from difffilter.extended import SigmaPoints, unscented_kalman_filter


@pytest.mark.parametrize(("dtype", "scale"), [(torch.float32, 1e19), (torch.float64, 8.9e153)])
def test_an_innovation_covariance_that_overflows_is_a_breakdown_on_the_shared_path(dtype, scale):
    """In units scaled so that every variance fits but ``S₃₃`` overflows, the default path
    (and the online step) took the infinite S: means 0.047 s off and a log-likelihood of
    -inf, where the masked path, the parallel one, the EKF and the UKF raise."""

    def t(values):
        return torch.tensor(values, dtype=dtype)

    model = df.LinearGaussianModel(
        t([[1.0, 0.1], [0.0, 0.95]]), t([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]]),
        t([[0.01, 0.0], [0.0, 0.02]]) * scale**2, torch.diag(t([0.1, 0.2, 0.3])) * scale**2,
        t([0.5, -0.2]) * scale, torch.eye(2, dtype=dtype) * scale**2,
    )  # fmt: skip
    ys = (
        torch.randn(8, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64).to(dtype)
        * scale
    )
    with pytest.raises(
        df.NumericalBreakdown,
        match="innovation covariance S = H P⁻ Hᵀ \\+ R made from it\\) is not finite at step 1",
    ):
        df.kalman_filter(model, ys)
    kf = df.KalmanFilter()
    with pytest.raises(df.NumericalBreakdown, match="is not finite at step 1"):
        kf.step(kf.init(model), ys[0])


def test_a_sigma_point_alpha_that_overflows_is_named():
    """alpha = 1e160 failed on a bare OverflowError from alpha**2."""
    eye = torch.eye(2, dtype=torch.float64)
    model = df.LinearGaussianModel(eye, eye, eye, eye, torch.zeros(2, dtype=torch.float64), eye)
    with pytest.raises(
        ValueError,
        match="sigma-point scaling alpha² \\(n \\+ kappa\\) overflows for alpha = 1e\\+160",
    ):
        unscented_kalman_filter(
            model, torch.zeros(3, 2, dtype=torch.float64), sigma_points=SigmaPoints(alpha=1e160)
        )


def test_a_linear_models_constructor_arguments_are_not_attributes():
    """``model.P0 = …`` had set an attribute beside the prior, never read."""
    eye = torch.eye(2, dtype=torch.float64)
    model = df.LinearGaussianModel(eye, eye, eye, eye, torch.zeros(2, dtype=torch.float64), eye)
    for name, where in (
        ("P0", "model.initial"),
        ("Q", "model.process_noise"),
        ("R", "model.measurement_noise"),
    ):
        with pytest.raises(AttributeError, match=f"{name} is kept in {where}"):
            setattr(model, name, torch.zeros(2, 2, dtype=torch.float64))
