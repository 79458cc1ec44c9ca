"""Findings of a red-team trial of the demo's reports against their JSON (each failed
before its fix): the leaderboard's best and its false-alarm cells."""

from __future__ import annotations

import numpy as np
import pytest

from difffilter.eval import leaderboard as board


def test_an_off_band_detection_rate_does_not_set_the_best():
    """0.9925 at 98.7 % false alarms (hatched) had been the best, and an in-band 0.975
    painted 0.82."""
    grid = np.array([[0.9925, 0.987], [0.975, 0.012]])
    cols = ["tpr_at_far", "fpr_at_far"]
    off_band = np.array([[True, False], [False, False]])
    good = board.cell_goodness(grid, ["s"] * 2, cols, targets=np.full(2, 0.01),
                               off_band=off_band)  # fmt: skip
    assert good[1, 0] == pytest.approx(1.0) and good[0, 0] == pytest.approx(1.0)  # (clipped)


@pytest.mark.parametrize("rate", [0.0200004, 0.0049996])
def test_a_false_alarm_rate_beside_its_band_edge_prints_apart_from_it(rate):
    """0.0200004 had printed "0.02" in a row hatched as outside [0.005, 0.02]."""
    row = {"far_target": 0.01}
    assert board._value_text(row, "fpr_at_far", rate) == f"{rate:g}"
    assert board._value_text(row, "fpr_at_far", 0.02) == "0.02"
    assert board._value_text(row, "tpr_at_far", 0.0200004) == "0.02"  # (no band there)
