"""Findings of a red-team trial of the smoothers (each failed before its fix)."""

from __future__ import annotations

import pytest
import torch

import difffilter as df

F64 = torch.float64
F = torch.tensor([[0.9, 0.2], [-0.1, 0.85]], dtype=F64)
H = torch.tensor([[1.0, 0.0]], dtype=F64)
Q = torch.diag(torch.tensor([0.05, 0.08], dtype=F64))
R = torch.tensor([[0.3]], dtype=F64)
M0, P0 = torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64)


class _Undeclared(df.LinearGaussianModel):
    """F_k = F·(1 + 0.1 k), time_varying left False."""

    def transition_matrix(self, k):
        return self.F * (1.0 + 0.1 * k)


def test_the_extended_smoother_refuses_an_undeclared_time_varying_transition():
    """The EKF reads F_k at every step and filtered it right; the smoother read F_0 at every
    step (means 0.8 off the dense posterior). Refused, as the Kalman filter refuses it."""
    model = _Undeclared(F, H, Q, R, M0, P0)
    _, ys, _ = model.simulate(8, (1,), generator=torch.Generator().manual_seed(22))
    with pytest.raises(ValueError, match="time_varying is False"):
        df.extended_kalman_smoother(model, ys)

    class Declared(_Undeclared):
        time_varying = True

    declared = Declared(F, H, Q, R, M0, P0)
    eks = df.extended_kalman_smoother(declared, ys)
    torch.testing.assert_close(eks.means, df.kalman_smoother(declared, ys).means)


def test_the_unscented_and_extended_smoothers_take_a_kalman_filters_shared_covariances():
    """A Kalman filter's covariances shared by every run (stride 0) passed the check of step
    1 and failed in torch.stack: the last step's shared, the earlier per run."""
    linear = df.LinearGaussianModel(F, H, Q, R, M0, P0)
    wrapped = df.NonlinearGaussianModel(lambda x: x @ F.mT, lambda x: x @ H.mT, Q, R, M0, P0)
    ys = torch.randn(3, 5, 1, dtype=F64, generator=torch.Generator().manual_seed(12))
    kf = df.kalman_filter(linear, ys)
    assert kf.covs.stride(0) == 0  # the shared path
    rts = df.rts_smoother(linear, kf)
    for smoothed in (df.unscented_rts_smoother(linear, kf), df.unscented_rts_smoother(wrapped, kf),
                     df.rts_smoother(wrapped, kf)):  # fmt: skip
        for name in ("means", "covs", "cross_covs", "gains", "initial_mean", "initial_cov"):
            torch.testing.assert_close(getattr(smoothed, name), getattr(rts, name))


def test_smoothers_name_a_model_batch_that_does_not_fit_the_runs():
    """A model of 4 parameter sets against 3 runs: torch's "size of tensor a (4)" from the
    Kalman smoother; the particle smoother lined the runs' sets up with its particles (0.75
    off where N = runs), where the particle filter refuses such a model."""
    batched = df.LinearGaussianModel(F.expand(4, 2, 2), H, Q, R, M0, P0)
    one = df.LinearGaussianModel(F, H, Q, R, M0, P0)
    ys = torch.randn(3, 5, 1, dtype=F64, generator=torch.Generator().manual_seed(1))
    with pytest.raises(ValueError, match=r"batch shape \(4,\) of the model's parameters"):
        df.rts_smoother(batched, df.kalman_filter(one, ys))
    pf = df.particle_filter(one, ys, num_particles=3, return_particles=True,
                            generator=torch.Generator().manual_seed(2))  # fmt: skip
    three = df.LinearGaussianModel(F.expand(3, 2, 2), H, Q, R, M0, P0)
    with pytest.raises(ValueError, match="the particle smoother takes one model for all runs"):
        df.particle_smoother(three, pf)
