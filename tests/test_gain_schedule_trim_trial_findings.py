"""A carry kept from the step a gain schedule's trimming dropped last (a red-team trial of
the one-run fast paths, 2026-12-07; the test failed before its fix)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import difffilter as df

F64 = torch.float64
F, H, Q, R = np.eye(2), np.array([[1.0, 0.0]]), np.diag([1e-2, 1e-2]), np.array([[0.5]])


def _kf_step(m, P, y):
    """The textbook step in numpy float64: the truth."""
    mp, Pp = F @ m, F @ P @ F.T + Q
    K = Pp @ H.T @ np.linalg.inv(H @ Pp @ H.T + R)
    return mp + K @ (y - H @ mp), (np.eye(2) - K @ H) @ Pp


@pytest.mark.parametrize("change", ["replaced", "written in place"])
def test_a_carry_from_the_trim_boundary_steps_from_its_own_covariance(change):
    """An unobserved random walk: the gain never settles, and the schedule drops its oldest
    steps (KEEP/TRIM). A carry kept from step k = the last dropped, its covariance reset
    (``carry._replace(cov=3 I)``) or written in place, was stepped with the schedule's
    moments: the mean 0.36 off (0.08 in place). One step earlier it went on from its own
    covariance, one later it is refused."""
    t = lambda a: torch.as_tensor(np.asarray(a), dtype=F64)  # noqa: E731
    model = df.LinearGaussianModel(t(F), t(H), t(Q), t(R), t([0.0, 0.0]), t(np.eye(2)))
    ys = np.random.default_rng(0).normal(size=(df.GainSchedule.KEEP + 2 * df.GainSchedule.TRIM, 1))
    kf, kept = df.KalmanFilter(), {}
    with torch.no_grad():
        carry = kf.init(model, ())
        for y in ys:
            carry, _ = kf.step(carry, t(y))
            kept[carry.k] = carry
        boundary = carry.gains._dropped
        assert boundary > 0 and not carry.gains.held(boundary) and carry.gains.held(boundary + 1)
        old = kept[boundary]
        if change == "replaced":
            P = 3.0 * np.eye(2)
            old = old._replace(cov=t(P))
        else:
            P = 3.0 * old.cov.numpy()
            old.cov.mul_(3.0)
        m_true, P_true = _kf_step(old.mean.numpy().copy(), P, np.array([0.7]))
        _, out = kf.step(old, t([0.7]))
    np.testing.assert_allclose(out.mean.numpy(), m_true, rtol=0, atol=1e-12)
    np.testing.assert_allclose(out.cov.numpy(), P_true, rtol=0, atol=1e-12)
