"""A detectors trial's finding: under a mask, ``ChiSquareDetector`` set its alarms from the
window's statistic against its own degrees of freedom and reported the score through
scipy's map to the full window (``chi_square_equivalent``), which lands within a few ulp of
the threshold for a statistic a few ulp from its own: alarms with a score below the
threshold and scores above it without an alarm (18 of 401 values within 200 ulp), where
one threshold on the scores is to give exactly the alarms."""

from __future__ import annotations

import math

import pytest
import torch

from difffilter.fdi.detectors import ChiSquareDetector, chi_square_upper_quantile

F64 = torch.float64


def _near_own_threshold(dof: int = 1, count: int = 200) -> torch.Tensor:
    q = chi_square_upper_quantile(dof, 0.05)
    values, up, down = [q], q, q
    for _ in range(count):
        up, down = math.nextafter(up, math.inf), math.nextafter(down, 0.0)
        values += [up, down]
    return torch.tensor(values, dtype=F64)


def _one_of_three(g: torch.Tensor):
    innovations = torch.zeros(len(g), 1, 3, dtype=F64)
    innovations[:, 0, 0] = g.sqrt()
    covs = torch.eye(3, dtype=F64).expand(len(g), 1, 3, 3)
    mask = torch.zeros(len(g), 1, 3, dtype=torch.bool)
    mask[..., 0] = True
    return innovations, covs, mask


def test_a_masked_windows_score_is_above_the_threshold_exactly_where_it_alarms():
    det = ChiSquareDetector(3, 0.05, 1)
    g = _near_own_threshold()
    score, alarm = det.detect(*_one_of_three(g))
    assert torch.equal(alarm, score > det.threshold)
    assert bool(alarm.any()) and bool((~alarm).any())  # the values straddle the threshold
    # away from the threshold the scores are the map's own
    far = torch.tensor([1.0, 2.0, 6.0, 9.0], dtype=F64)
    s_far, _ = det.detect(*_one_of_three(far))
    torch.testing.assert_close(s_far[:, 0], torch.tensor(
        [chi_square_upper_quantile(3, float(torch.special.gammaincc(torch.tensor(0.5, dtype=F64),
                                                                     v / 2)))
         for v in far], dtype=F64), rtol=1e-9, atol=0)  # fmt: skip


@pytest.mark.parametrize("window", [1, 2])
def test_the_online_steps_score_agrees_with_its_alarm_under_a_mask(window):
    det = ChiSquareDetector(3, 0.05, window)
    g = _near_own_threshold()  # the window holds one received entry (this step's)
    state = det.init((len(g),))
    mask = torch.zeros(len(g), 3, dtype=torch.bool)
    mask[:, 0] = True
    for _ in range(window - 1):  # earlier steps of the window: nothing received
        state, _, _ = det.step(state, torch.zeros(len(g), dtype=F64), torch.zeros_like(mask))
    state, score, alarm = det.step(state, g, mask)
    assert torch.equal(alarm, score > det.threshold)
    assert bool(alarm.any()) and bool((~alarm).any())
