"""Findings of a trial of the EKF and UKF (each failed before its fix)."""

from __future__ import annotations

import pytest
import torch

import difffilter as df
from difffilter import NonlinearGaussianModel
from difffilter.extended import (
    SigmaPoints,
    UnscentedKalmanFilter,
    extended_kalman_filter,
    unscented_kalman_filter,
)

D = torch.float64


def test_an_unreceived_entry_whose_jacobian_or_h_is_nan_is_left_out():
    """``masked_measurement`` multiplied by the mask, and NaN × 0 is NaN: the EKF at a silent
    range beacon it sits on (∂|x − b|/∂x = 0/0), and the UKF of an unreceived √x₀ gauge at
    x₀ < 0, stopped, where the received entries' own model runs."""
    beacons = torch.tensor([[0.0, 0.0], [10.0, 0.0]], dtype=D)
    Q, P0, m0 = 0.01 * torch.eye(2, dtype=D), 0.01 * torch.eye(2, dtype=D), torch.zeros(2, dtype=D)

    def ranges(b):
        return lambda x: (x[..., None, :] - b).square().sum(-1).sqrt()

    both = NonlinearGaussianModel(
        lambda x: x, ranges(beacons), Q, 0.1 * torch.eye(2, dtype=D), m0, P0
    )
    only = NonlinearGaussianModel(
        lambda x: x, ranges(beacons[1:]), Q, 0.1 * torch.eye(1, dtype=D), m0, P0
    )
    ys, mask = torch.tensor([[0.0, 10.1]] * 3, dtype=D), torch.tensor([[False, True]] * 3)
    got, want = extended_kalman_filter(both, ys, mask=mask), extended_kalman_filter(only, ys[:, 1:])
    torch.testing.assert_close(got.means, want.means, rtol=0, atol=1e-12)
    torch.testing.assert_close(got.log_likelihood, want.log_likelihood, rtol=0, atol=1e-12)

    m0b, P0b = torch.tensor([-3.0, 1.0], dtype=D), 0.01 * torch.eye(2, dtype=D)
    gauge = NonlinearGaussianModel(lambda x: 0.9 * x, lambda x: torch.stack([x[..., 0] + x[..., 1], x[..., 0].sqrt()], -1),
                                   0.1 * torch.eye(2, dtype=D), 0.1 * torch.eye(2, dtype=D), m0b, P0b)  # fmt: skip
    first = NonlinearGaussianModel(lambda x: 0.9 * x, lambda x: (x[..., 0] + x[..., 1])[..., None],
                                   0.1 * torch.eye(2, dtype=D), 0.1 * torch.eye(1, dtype=D), m0b, P0b)  # fmt: skip
    ys, mask = torch.tensor([[0.5, 0.0]] * 3, dtype=D), torch.tensor([[True, False]] * 3)
    got, want = (
        unscented_kalman_filter(gauge, ys, mask=mask),
        unscented_kalman_filter(first, ys[:, :1]),
    )
    torch.testing.assert_close(got.means, want.means, rtol=0, atol=1e-12)


def test_sigma_point_settings_assigned_later_are_checked():
    """alpha, beta and kappa were checked by the constructor alone: NaN assigned later was
    blamed on the transition f, alpha = -0.5 ran; ``ukf.sigma_points`` = a tuple failed on
    "'tuple' object has no attribute 'weights'"."""
    points = SigmaPoints()
    for name, value in (
        ("alpha", -0.5),
        ("alpha", float("nan")),
        ("beta", float("inf")),
        ("kappa", float("nan")),
    ):
        with pytest.raises(ValueError, match=f"{name} must be a finite number"):
            setattr(points, name, value)
    ukf = UnscentedKalmanFilter()
    with pytest.raises(TypeError, match="sigma_points must be a SigmaPoints object"):
        ukf.sigma_points = (1.0, 2.0, 0.0)
    ukf.sigma_points = None  # as the constructor reads it: the defaults
    assert isinstance(ukf.sigma_points, SigmaPoints) and ukf.sigma_points.alpha == 1.0


def test_the_ukf_takes_a_model_of_one_parameter_set_in_a_batch_of_one():
    """F of shape [1, n, n] is one model (the KF and EKF take it): the UKF had refused it as
    one set per run."""
    eye = torch.eye(3, dtype=D)
    model = df.LinearGaussianModel(
        (0.9 * eye)[None], eye, 0.1 * eye, 0.2 * eye, torch.zeros(3, dtype=D), eye
    )
    _, ys, _ = model.simulate(8, (2,), generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(unscented_kalman_filter(model, ys).means, df.kalman_filter(model, ys).means,
                               rtol=0, atol=1e-12)  # fmt: skip
