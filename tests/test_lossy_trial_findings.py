"""The modified Riccati iteration settles per entry, not against the largest entry.

Its stopping test had compared the change of every entry with the largest entry of the
iterate, so a state in units 10⁶ times smaller stopped unconverged (8× low) and an unstable
state in small units below the critical rate passed for settled: finite "bounds" (a lower
one with a negative variance), a unit-dependent LQR gain, and a critical rate's upper end
below the true one (a red-team trial). A change of the state's units (``x → D x``) must not
change any answer.
"""

import math

import numpy as np
import pytest
import scipy.linalg as sla
import torch

from difffilter.control import dlqr
from difffilter.lossy_control import critical_arrival_rate, intermittent_kalman_bounds, lossy_dlqr

d = torch.float64


def _scalar_mare(a, q, r, rate):
    """Positive root of V = a²V + q − rate a² V²/(V + r) (h = 1)."""
    A = (1 - a * a) + rate * a * a
    B = r * (1 - a * a) - q
    return (-B + math.sqrt(B * B + 4 * A * q * r)) / (2 * A)


def _two_modes(s):
    F = torch.diag(torch.tensor([0.5, 0.999], dtype=d))
    Q = torch.diag(torch.tensor([1.0, 1e-4 * s * s], dtype=d))
    R = torch.diag(torch.tensor([1.0, s * s], dtype=d))
    return F, torch.eye(2, dtype=d), Q, R


def test_a_slow_mode_in_small_units_reaches_its_fixed_point():
    s = 1e-6
    F, H, Q, R = _two_modes(s)
    _, upper = intermittent_kalman_bounds(F, H, Q, R, 1.0)
    dare = sla.solve_discrete_are(F.numpy().T, H.numpy().T, Q.numpy(), R.numpy())
    assert upper[1, 1].item() == pytest.approx(dare[1, 1], rel=1e-8)  # was 1.085e-15 vs 9.095e-15
    _, upper = intermittent_kalman_bounds(F, H, Q, R, 0.8)
    assert upper[1, 1].item() == pytest.approx(
        _scalar_mare(0.999, 1e-4, 1.0, 0.8) * s * s, rel=1e-8
    )
    assert upper[0, 0].item() == pytest.approx(_scalar_mare(0.5, 1.0, 1.0, 0.8), rel=1e-10)


def test_the_lossy_lqr_gain_of_a_slow_mode_in_small_units():
    F, B, Q, R = _two_modes(1e-6)
    K, S = lossy_dlqr(F, B, Q, R, arrival_rate=1.0)
    K0, S0 = dlqr(F, B, Q, R)
    torch.testing.assert_close(K, K0, rtol=1e-7, atol=0)  # K[1, 1] was 1.08e-3 vs 9.00e-3
    torch.testing.assert_close(S, S0, rtol=1e-7, atol=0)


@pytest.mark.parametrize("s", [1.0, 1e-9])
def test_below_the_critical_rate_no_bounds_in_any_units(s):
    F = torch.diag(torch.tensor([0.5, 1.2, 0.3], dtype=d))
    H = torch.tensor([[1.0, 0, 0], [0, 1.0 / s, 0]], dtype=d)
    Q = torch.diag(torch.tensor([1.0, s * s, 1.0], dtype=d))
    with pytest.raises(ValueError, match="at or below the critical rate"):
        intermittent_kalman_bounds(F, H, Q, torch.eye(2, dtype=d), 0.2)  # 1 − 1/1.44 = 0.306


@pytest.mark.parametrize("s", [1.0, 1e-9])
def test_the_lossy_lqr_closed_loop_does_not_depend_on_units(s):
    F = torch.diag(torch.tensor([0.5, 1.2, 0.3], dtype=d))
    B = torch.tensor([[1.0, 0], [0, 1.0 / s], [0, 0]], dtype=d)
    Q = torch.diag(torch.tensor([1.0, s * s, 1.0], dtype=d))
    R = torch.eye(2, dtype=d)
    a, rate = 1.2, 0.5
    S = _scalar_mare(a, 1.0, 1.0, rate)  # the control MARE of the mode has the same form
    K, _ = lossy_dlqr(F, B, Q, R, arrival_rate=rate)
    assert (F - B @ K)[1, 1].item() == pytest.approx(a - a * S / (S + 1.0), rel=1e-9)
    with pytest.raises(ValueError):
        lossy_dlqr(F, B, Q, R, arrival_rate=0.2)


@pytest.mark.parametrize("s", [1.0, 1e-9])
def test_the_critical_rate_does_not_depend_on_units(s):
    # A = diag(2, −2), C = [1 1] (two modes the measurement cannot tell apart in one step)
    F = torch.diag(torch.tensor([2.0, -2.0, 0.5], dtype=d))
    H = torch.tensor([[1 / s, 1 / s, 0], [0, 0, 1.0]], dtype=d)
    Q = torch.diag(torch.tensor([s * s, s * s, 1.0], dtype=d))
    R = torch.eye(2, dtype=d)
    rate = critical_arrival_rate(F, H, Q, R)
    assert rate.lower == pytest.approx(0.75)
    assert rate.upper >= 1 - 1 / 16  # was 0.751 at s = 1e-9 (0.9385 at s = 1)
    with pytest.raises(ValueError, match="at or below the critical rate"):
        intermittent_kalman_bounds(F, H, Q, R, 0.85)


def test_a_rate_no_fixed_point_can_have_is_refused_at_once():
    F = torch.tensor([[3.0]], dtype=d)  # (1 − 0.5)·9 ≥ 1: Sinopoli et al.'s lower bound on λ_c
    one = torch.eye(1, dtype=d)
    with pytest.raises(ValueError, match="at or below the critical rate"):
        intermittent_kalman_bounds(F, one, one, one, 0.5)
    assert np.isclose(critical_arrival_rate(F, one, one, one).lower, 1 - 1 / 9)
