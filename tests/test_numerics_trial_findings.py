"""Findings of a numerics trial of the Gaussian filters, each checked against an
independent truth (a float64 Kalman filter, the steps' own finiteness)."""

from __future__ import annotations

import warnings

import pytest
import torch

import difffilter as df


def _unstable_unobserved(dtype=torch.float32) -> df.LinearGaussianModel:
    """A stable measured state beside an unstable one (1.05) no measurement reaches: its
    variance grows as 1.05^(2k) and overflows float32 near step 900."""
    kw = {"dtype": dtype}
    return df.LinearGaussianModel(
        torch.tensor([[0.5, 0.0], [0.0, 1.05]], **kw), torch.tensor([[1.0, 0.0]], **kw),
        0.1 * torch.eye(2, **kw), torch.eye(1, **kw), torch.zeros(2, **kw), torch.eye(2, **kw),
    )  # fmt: skip


def test_an_overflowing_covariance_is_named_by_the_gain_schedule_paths():
    """The whole-sequence filter and the online step (both on the gain schedule) had
    returned NaN means, covariances and log-likelihoods with numpy's RuntimeWarnings alone,
    where the general update raises: now a NumericalBreakdown at the step that overflowed,
    every earlier step handed out finite, and no numpy warning."""
    model = _unstable_unobserved()
    ys = torch.randn(1, 1000, 1, generator=torch.Generator().manual_seed(0))
    kf = df.KalmanFilter()
    with warnings.catch_warnings(record=True) as caught, torch.no_grad():
        warnings.simplefilter("always")
        carry, done = kf.init(model, ()), 0
        with pytest.raises(df.NumericalBreakdown, match=r"not finite at step (\d+).*float32"):
            for k in range(ys.shape[1]):
                carry, out = kf.step(carry, ys[0, k])
                assert bool(torch.isfinite(out.cov).all() & torch.isfinite(out.mean).all())
                done = k + 1
        with pytest.raises(df.NumericalBreakdown, match=f"not finite at step {done + 1}"):
            df.kalman_filter(model, ys)
        # the steps before it: finite, and the general update's (a mask of all True)
        prefix = df.kalman_filter(model, ys[:, :done])
        general = df.kalman_filter(
            model, ys[:, :done], mask=torch.ones(1, done, 1, dtype=torch.bool)
        )
    assert 800 < done < 1000
    assert bool(torch.isfinite(prefix.covs).all()) and prefix.covs[0, -1, 1, 1] > 1e37
    torch.testing.assert_close(prefix.means, general.means, rtol=1e-4, atol=1e-5)
    assert not [w for w in caught if issubclass(w.category, RuntimeWarning)]


def _linear(dtype) -> df.LinearGaussianModel:
    kw = {"dtype": dtype}
    return df.LinearGaussianModel(
        torch.tensor([[1.0, 0.1], [0.0, 0.95]], **kw), torch.tensor([[1.0, 0.0]], **kw),
        0.01 * torch.eye(2, **kw), 0.1 * torch.eye(1, **kw), torch.tensor([10.0, 1.0], **kw),
        torch.eye(2, **kw),
    )  # fmt: skip


def _ukf_error(alpha: float, dtype) -> tuple[float, list]:
    """The UKF's largest mean error in posterior standard deviations against the float64
    Kalman filter on a linear model (where they are equal), and the warnings raised."""
    ys = 10 + torch.randn(1, 50, 1, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    ref = df.kalman_filter(_linear(torch.float64), ys)
    points = df.SigmaPoints(alpha)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = df.unscented_kalman_filter(_linear(dtype), ys.to(dtype), sigma_points=points)
        df.unscented_kalman_filter(_linear(dtype), ys.to(dtype), sigma_points=points)
    std = ref.covs.diagonal(dim1=-2, dim2=-1).sqrt()
    err = float(((out.means.double() - ref.means).abs() / std).max())
    return err, [w for w in caught if issubclass(w.category, UserWarning)]


def test_sigma_points_whose_weights_swamp_float32_say_so_once():
    """A small alpha in float32 puts the UKF of a linear model posterior standard
    deviations away from its Kalman filter (10 at alpha = 1e-3): a warning, once per
    object; none where the round-off stays small (alpha 0.1 in float32, 1e-3 in float64)."""
    err, caught = _ukf_error(1e-3, torch.float32)
    assert err > 1.0 and len(caught) == 1
    assert "alpha=0.001" in str(caught[0].message) and "float64" in str(caught[0].message)
    for alpha, dtype in ((0.1, torch.float32), (1.0, torch.float32), (1e-3, torch.float64)):
        err, caught = _ukf_error(alpha, dtype)
        assert err < 1e-2 and not caught, (alpha, dtype, err)
