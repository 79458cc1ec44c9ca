"""Findings of a red-team trial of the four-tank family's report sections (each failed
before its fix)."""

from __future__ import annotations

import pytest

from difffilter.eval.families import four_tank as family
from difffilter.models.four_tank import R_HIGH, R_NOMINAL, FourTankScenario


def test_the_papers_column_is_chosen_by_the_noise_and_the_papers_threshold():
    """R × 5 with a Theorem-1 η of its own had been put in the nominal column (beside the
    paper's 0.0028 and no false alarms), given Table 4, and an "R × 5" section that ran
    R × 25; nominal R with the η of R × 5 sat beside the paper's tr R = 0.015 column."""
    assert family._paper_setting(R_NOMINAL, R_NOMINAL) == "nominal"
    assert family._paper_setting(list(R_HIGH), list(R_NOMINAL)) == "high"  # (as JSON reads)
    assert family._paper_setting(R_HIGH, R_HIGH) is None
    assert family._paper_setting(R_NOMINAL, R_HIGH) is None
    assert family._paper_setting(tuple(2 * r for r in R_NOMINAL), R_NOMINAL) is None


@pytest.mark.parametrize("scales", [(), (0.5, -1.0), (float("nan"),), "0.5"])
def test_a_detection_sweep_without_valid_scales_is_refused_when_built(scales):
    """An empty sweep had run the whole study and then stopped its report in torch.cat."""
    with pytest.raises(ValueError, match="sweep_scales must be a non-empty tuple"):
        FourTankScenario(name="x", description="", sweep_scales=scales)
