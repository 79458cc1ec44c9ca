"""A gain-schedule trial's finding: where the stricter convergence test of a slow mode
(``ρ`` near 1) asks for a change below the dtype's resolution, a float32 step's change is a
few ulp or, rounded, exactly 0, and one such step had passed: a float32 schedule froze its
gain at step 1738 (float64: 4470) 2.3e-5 from the fixed point, 12× the tolerance. There the
test must hold for ``STEADY_WINDOW`` steps in a row; float64 schedules are unchanged."""

from __future__ import annotations

import torch

import difffilter as df
from difffilter._riccati_host import STEADY_WINDOW
from difffilter.gain_schedule import GainSchedule


def _slow_model(dtype):
    t = lambda v: torch.tensor([[v]], dtype=dtype)  # noqa: E731
    return df.LinearGaussianModel(t(0.9999), t(1.0), t(1e-5), t(1.0), torch.zeros(1, dtype=dtype),
                                  t(100.0))  # fmt: skip


def _riccati_gains(steps: int) -> list[float]:
    """The float64 scalar Riccati recursion's gains K_1 … K_steps (Joseph form)."""
    P, gains = 100.0, []
    for _ in range(steps):
        Pm = 0.9999 * P * 0.9999 + 1e-5
        K = Pm / (Pm + 1.0)
        P = (1 - K) * Pm * (1 - K) + K * K
        gains.append(K)
    return gains


def _run(schedule, steps):
    """Step the schedule to ``steps``; the last step of its own (where it converged), or
    None."""
    for k in range(1, steps + 1):
        schedule.moments(k)
    return schedule._dropped + len(schedule._moments) if schedule.converged else None


def test_a_float32_schedule_of_a_slow_mode_does_not_freeze_its_gain_early():
    schedule = GainSchedule(_slow_model(torch.float32))
    converged = _run(schedule, 3000)
    fixed = _riccati_gains(20000)[-1]
    if converged is not None:  # then its gain must be the fixed point to float32's tolerance
        gain = float(schedule.moments(converged).gain)
        assert abs(gain - fixed) / fixed <= 4 * 16 * torch.finfo(torch.float32).eps
    # the steps it hands out are the float32 recursion's: near the float64 one's
    gains = _riccati_gains(3000)
    for k in (2000, 2500, 2999):
        assert abs(float(schedule.moments(k).gain) - gains[k - 1]) <= 3e-5 * gains[k - 1]


def test_a_float64_schedule_converges_where_it_did():
    schedule = GainSchedule(_slow_model(torch.float64))
    assert _run(schedule, 6000) == 4470
    assert STEADY_WINDOW > 1
