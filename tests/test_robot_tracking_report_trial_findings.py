"""Findings of a red-team trial of the robot and tracking families' report sections (each
failed before its fix)."""

from __future__ import annotations

import math

import pytest
import torch

from difffilter.eval.families import robot, tracking
from difffilter.models.robot import RobotScenario


def test_a_diverged_step_is_no_step_below_the_bound():
    """A NaN RMSE step (a diverged estimate) compared False: 0.5 of the steps read as
    beating a lower bound where every finite step is 20× above it."""
    p = torch.tensor([2.0, 2.0, float("nan"), 2.0])
    bound = torch.full((4,), 0.1)
    assert math.isnan(tracking._share_at_or_above(p, p, bound, bound))
    assert tracking._share_at_or_above(p.nan_to_num(2.0), p.nan_to_num(2.0), bound, bound) == 1.0


def test_the_share_of_runs_lower_counts_the_runs_with_both_numbers():
    """A diverged run had counted as "not lower": 0.5 where the one run judged is lower."""
    a, b = torch.tensor([1.0, float("nan")]), torch.tensor([2.0, 2.0])
    assert robot._share_lower(a, b) == 1.0
    assert math.isnan(robot._share_lower(torch.tensor([float("nan")]), torch.tensor([1.0])))


@pytest.mark.parametrize("attack", [(20.0, 20.0, 99.0), (20.0,), (20.0, float("nan")), "20"])
def test_a_robot_attack_is_two_finite_numbers(attack):
    """(20, 20, 99) had been accepted and its third entry dropped."""
    with pytest.raises(ValueError, match="attack must be two finite numbers"):
        RobotScenario(name="x", attack=attack)
